"""The MCAP writer's chunk indexes kept in a temporary file instead of in memory.

mcap's ``Writer`` keeps one ``ChunkIndex`` object per chunk (with a dict of message-index
offsets, one entry per channel in the chunk) until ``finish()`` writes them into the
file's summary. The recorder closes a chunk when it passes ``CHUNK_SIZE`` (about 8 a
second at 320 Hz, measured) or at the latest every ``FLUSH_EVERY_S``, so that list grew
without bound: about 1.1 kB per chunk, 0.5 MB a minute, the whole of the recorder's
memory growth (docs/reliability.md, the soak). :func:`spool_chunk_indexes` replaces
that list with :class:`ChunkIndexSpool`, which writes each index, serialized as it will
stand in the summary, to an unnamed temporary file and hands the bytes back at
``finish()``. The file's content is unchanged, chunk and message indexes included
(Foxglove's indexed reader refuses a chunk index without message indexes: mcap's
``ChunkCursor``; the Python reader does not need them).

Assumption (named once, here): mcap 1.x keeps the chunk indexes in the private list
``Writer._Writer__chunk_indices``, appends each finished ``ChunkIndex`` to it and only
iterates it in ``finish()``, calling ``write(builder)`` on each item (mcap 1.6.0,
``mcap/writer.py``). When that attribute is not there, the writer is left as it is and
the recording works with the library's in-memory list (:func:`spool_chunk_indexes`
returns None); the recorder test asserts that the spool is in use.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import IO, Iterator

from mcap.data_stream import RecordBuilder
from mcap.records import ChunkIndex
from mcap.writer import Writer

#: the private attribute of mcap's Writer that holds the chunk indexes (see the module doc)
_ATTR = "_Writer__chunk_indices"
#: bytes handed back per item in ``finish()`` (bounds the read-back copy, not the summary)
_READ_BACK = 1 << 20


class _Serialized:
    """Already serialized summary records, written as they are."""

    __slots__ = ("data",)

    def __init__(self, data: bytes) -> None:
        self.data = data

    def write(self, stream: RecordBuilder) -> None:
        stream.write(self.data)


class ChunkIndexSpool:
    """A stand-in for the writer's list of chunk indexes: ``append`` serializes the index
    to a temporary file, iterating yields the serialized records in order.

    :param dir: where the temporary file goes (the recording's directory; default: the
        system's temporary directory); it has no name and is gone when closed or when the
        process ends
    """

    def __init__(self, dir: str | Path | None = None) -> None:
        self._f: IO[bytes] = tempfile.TemporaryFile(prefix="pfma-chunk-index-", dir=dir)
        self.count = 0          #: chunk indexes spooled
        self.bytes = 0          #: their serialized size (what the summary's index group holds)

    def append(self, index: ChunkIndex) -> None:
        b = RecordBuilder()
        index.write(b)
        data = b.end()
        self._f.write(data)
        self.count += 1
        self.bytes += len(data)

    def __len__(self) -> int:
        return self.count

    def __iter__(self) -> Iterator[_Serialized]:
        f = self._f
        f.flush()
        f.seek(0)
        try:
            while True:
                data = f.read(_READ_BACK)
                if not data:
                    return
                # whole records only matter to the summary as a whole: the group is the
                # concatenation, so any split of the bytes writes the same summary
                yield _Serialized(data)
        finally:
            f.seek(0, 2)

    def close(self) -> None:
        self._f.close()


def spool_chunk_indexes(writer: Writer, dir: str | Path | None = None) -> ChunkIndexSpool | None:
    """Make ``writer`` (before its first chunk) keep its chunk indexes in a
    :class:`ChunkIndexSpool`; returns it (close it after ``finish()``), or None when this
    mcap keeps them elsewhere (the assumption in the module doc does not hold)."""
    held = getattr(writer, _ATTR, None)
    if not isinstance(held, list) or held:
        return None
    spool = ChunkIndexSpool(dir)
    setattr(writer, _ATTR, spool)
    return spool
