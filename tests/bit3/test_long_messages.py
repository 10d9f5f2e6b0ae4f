"""Messages reach the Bit3 queues whole: a text longer than one entry's 56 bytes takes the
next entries (at most MESSAGE_MAX_ENTRIES: MESSAGE_MAX_BYTES of text), joined by every reader;
cut only between UTF-8 characters; a reader's cursor (the last entry's seq) and the gap count
stay right; a reader whose window starts inside a message skips it rather than show its tail."""

from __future__ import annotations

import uuid

import pytest

from bit3.buffer import Bit3Buffer, split_text
from bit3.layout import (
    MESSAGE_CONTINUED, MESSAGE_CONTINUES, MESSAGE_MAX_BYTES, MESSAGE_MAX_ENTRIES, MESSAGE_QUEUE_LEN,
    MESSAGE_TEXT_BYTES, Severity,
)


@pytest.fixture
def queue():
    name = "pfma-test-msg-" + uuid.uuid4().hex[:8]
    buf = Bit3Buffer.create(name)
    buf.claim("service", "test")
    q = buf.queue("service_messages")
    yield q
    buf.close()
    Bit3Buffer.unlink(name)


def test_a_long_message_is_read_whole_with_its_first_and_last_entry(queue):
    text = "rtd1 failed 3 samples in a row: bus error: read16 rtd1 STATUS at A16 0x0108: " \
           "gateway 10.0.0.5:502 unreachable"
    assert len(text.encode()) > MESSAGE_TEXT_BYTES
    queue.post("short one", Severity.INFO, code=1)
    last = queue.post(text, Severity.ERROR, code=5, source=2)
    queue.post("after", Severity.WARNING, code=6)
    msgs = queue.read()
    assert [m.text for m in msgs] == ["short one", text, "after"]
    long = msgs[1]
    assert long.seq == last and long.first_seq == 2 and last == 2 + len(split_text(text.encode())) - 1
    assert (long.severity, long.code, long.source) == (Severity.ERROR, 5, 2)
    assert [m.text for m in queue.read(since_seq=long.seq)] == ["after"]  # the cursor


def test_pieces_are_cut_between_characters_and_the_rest_beyond_the_limit_marked():  # noqa: D103
    text = "é" * MESSAGE_MAX_BYTES  # 2 bytes each: a cut at 56 bytes of a byte-odd prefix must not split one
    pieces = split_text(("x" + text).encode())
    assert len(pieces) == MESSAGE_MAX_ENTRIES
    assert all(len(p) <= MESSAGE_TEXT_BYTES for p in pieces)
    joined = b"".join(pieces).decode()  # decodes: no character was split
    assert joined.endswith("~") and joined[:-1] == ("x" + text)[:len(joined) - 1]
    assert split_text(b"") == [b""]


def test_a_reader_that_missed_entries_counts_them_from_the_first_entry(queue):
    for k in range(MESSAGE_QUEUE_LEN + 5):
        queue.post(f"m{k}", Severity.INFO)
    long_text = "L" * (MESSAGE_TEXT_BYTES * 2 + 3)  # three entries
    queue.post(long_text, Severity.INFO)
    msgs = queue.read(since_seq=MESSAGE_QUEUE_LEN + 5)
    assert len(msgs) == 1 and msgs[0].text == long_text
    assert msgs[0].first_seq == MESSAGE_QUEUE_LEN + 6 and msgs[0].seq == MESSAGE_QUEUE_LEN + 8


def test_a_600_byte_message_is_read_whole_from_eleven_entries(queue):
    text = "".join(f"[{k:03d} bus error at A16 0x{k:04X}: gateway 127.0.0.1:1502 timed out] " for k in range(12))
    text = text[:600]
    assert len(text.encode()) == 600 and 600 <= MESSAGE_MAX_BYTES
    queue.post("before", Severity.INFO)
    last = queue.post(text, Severity.ERROR, code=152)
    msgs = queue.read()
    assert [m.text for m in msgs] == ["before", text]  # whole: no "~", nothing lost
    m = msgs[1]
    n = -(-600 // MESSAGE_TEXT_BYTES)  # 11 entries
    assert (m.first_seq, m.seq) == (2, 1 + n) and last == m.seq and m.code == 152
    assert m.severity is Severity.ERROR  # the continuation bits are not part of the severity


def test_the_limit_is_max_bytes_and_a_longer_text_ends_with_a_tilde(queue):
    fits = "a" * MESSAGE_MAX_BYTES
    too_long = "b" * (MESSAGE_MAX_BYTES + 1)
    queue.post(fits)
    queue.post(too_long)
    got = queue.read()
    assert got[0].text == fits and got[1].text == "b" * (MESSAGE_MAX_BYTES - 1) + "~"
    assert got[1].seq - got[1].first_seq + 1 == MESSAGE_MAX_ENTRIES


def test_entries_carry_continues_and_continued_bits(queue):
    queue.post("c" * (MESSAGE_TEXT_BYTES * 2 + 1))  # three entries
    entries = queue._reader.record["entries"]
    queue.read()
    bits = [int(entries[i]["severity"]) & (MESSAGE_CONTINUES | MESSAGE_CONTINUED) for i in range(3)]
    assert bits == [MESSAGE_CONTINUES, MESSAGE_CONTINUES | MESSAGE_CONTINUED, MESSAGE_CONTINUED]


def test_a_window_that_starts_inside_a_message_skips_its_tail(queue):
    long_text = "T" * (MESSAGE_TEXT_BYTES * 9 + 5)  # ten entries
    queue.post(long_text, Severity.WARNING)  # entries 1..10
    for k in range(MESSAGE_QUEUE_LEN - 5):  # 45 more: entries 11..55; the ring holds 6..55
        queue.post(f"m{k}")
    got = queue.read()  # a reader from the start: the long message's first five entries are gone
    assert got[0].text == "m0" and got[0].first_seq == 11  # not "TTTT..." (its tail) as a message
    assert len(got) == MESSAGE_QUEUE_LEN - 5 and all(not m.text.startswith("T") for m in got)
