"""The F/T and CRL byte streams into their decoders (issue 20 item 3).

Arbitrary bytes, fed in arbitrary pieces, into the F/T stream decoders (ASCII; binary
with and without the checksum) and the CRL hand controller's frame decoder (both
directions): ``feed`` never raises, what it holds stays bounded, everything it delivers
is a well-formed record or frame, and after the garbage a run of good records is decoded
exactly (resync) -- all but the first (ASCII, binary) or first two (binary without the
checksum, CRL: the confirming frame) of six. The one-record decoders take any bytes:
the F/T ones answer None, the CRL ones a frame or their documented ``CodecError``.

The good binary F/T records here have counts whose bytes are no status code (0x00,
0x01): the binary format has no sync byte, so a count byte that looks like a status
byte can hold a misaligned decoder longer (docs/ft-protocol.md says what framing can
and cannot detect); that limit is the format's, not something to fuzz.

Not repeated here: the seeded random-damage tests of tests/drivers/crl/test_codec.py and
tests/drivers/serial_ft/ (noise on a line that carries good records).
"""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.crl.crl_codec import (
    BUTTONS_RESERVED, FLAGS_RESERVED, FRAME_LEN, CodecError, FrameDecoder, check_frame, decode_force_frame,
    decode_master_frame, encode_force_frame, encode_master_frame,
)
from drivers.serial_ft.protocol import (
    STATUS_CODES, AsciiStreamDecoder, BinaryStreamDecoder, decode_ascii_line, decode_binary, encode_ascii,
    encode_binary, record_bytes,
)
from tests.fuzz._mutate import FUZZ

GOOD = 6  #: good records after the garbage
garbage = st.binary(max_size=400)
chunks = st.lists(st.integers(1, 64), min_size=1, max_size=20)
int16 = st.integers(-32768, 32767)
#: a count whose two big-endian bytes are no status code (see the module docstring)
distinct16 = int16.filter(lambda c: not {(c >> 8) & 0xFF, c & 0xFF} & set(STATUS_CODES))


def feed_in_pieces(dec, data: bytes, sizes: list[int], bound: int) -> list:
    """Feed ``data`` cut by ``sizes`` (cycled); check the decoder's bound after each piece."""
    out, i, k = [], 0, 0
    while i < len(data):
        n = sizes[k % len(sizes)]
        out += dec.feed(data[i:i + n])
        held = getattr(dec, "buffered", None)
        held = dec.pending if held is None else held
        assert held <= bound, (held, bound)
        i, k = i + n, k + 1
    return out


def assert_tail(out: list, sent: list, lost: int) -> None:
    want = sent[lost:]
    assert out[-len(want):] == want, (out[-len(want):], want)


# --- F/T -------------------------------------------------------------------------------------


@settings(FUZZ, max_examples=150)
@given(garbage, chunks, st.lists(st.tuples(st.sampled_from(sorted(STATUS_CODES)), st.tuples(*[int16] * 6)),
                                 min_size=GOOD, max_size=GOOD))
def test_ft_ascii_stream_garbage_then_records(junk, sizes, records):
    dec = AsciiStreamDecoder()
    dec.reset(synced=True)
    data = junk + b"".join(encode_ascii(s, c) for s, c in records)
    out = feed_in_pieces(dec, data, sizes, AsciiStreamDecoder.MAX_LINE)
    for status, counts in out:
        assert status in STATUS_CODES and len(counts) == 6 and all(-32768 <= c <= 32767 for c in counts)
    assert_tail(out, records, 1)


@settings(FUZZ, max_examples=150)
@given(st.booleans(), garbage, chunks,
       st.lists(st.tuples(st.sampled_from(sorted(STATUS_CODES)), st.tuples(*[distinct16] * 6)),
                min_size=GOOD, max_size=GOOD))
def test_ft_binary_stream_garbage_then_records(checksum_on, junk, sizes, records):
    dec = BinaryStreamDecoder(checksum_on)
    n = record_bytes("binary", checksum_on)
    data = junk + b"".join(encode_binary(s, c, checksum_on) for s, c in records)
    out = feed_in_pieces(dec, data, sizes, 2 * n)
    for status, counts in out:
        assert status in STATUS_CODES and len(counts) == 6
    out += dec.finish()  # end of stream: the last record needs no look-ahead
    assert_tail(out, records, 1 if checksum_on else 2)


@settings(FUZZ, max_examples=200)
@given(st.binary(max_size=160))
def test_ft_one_record_decoders_take_any_bytes(raw):
    assert decode_ascii_line(raw) is None or decode_ascii_line(raw)[0] in STATUS_CODES
    for checksum_on in (False, True):
        rec = decode_binary(raw, checksum_on)
        assert rec is None or (len(raw) == record_bytes("binary", checksum_on) and rec[0] in STATUS_CODES)


# --- CRL -------------------------------------------------------------------------------------


@settings(FUZZ, max_examples=150)
@given(st.sampled_from(["master", "force"]), garbage, chunks, st.integers(0, 255),
       st.lists(st.tuples(st.tuples(*[int16] * 6), st.integers(0, 7)), min_size=GOOD, max_size=GOOD))
def test_crl_stream_garbage_then_frames(kind, junk, sizes, seq0, frames):
    enc = encode_master_frame if kind == "master" else encode_force_frame
    reserved = BUTTONS_RESERVED if kind == "master" else FLAGS_RESERVED
    bits_ok = [b & ~reserved & 0xFF for _, b in frames]
    sent = [enc((seq0 + i) & 0xFF, vals, b) for i, ((vals, _), b) in enumerate(zip(frames, bits_ok))]
    dec = FrameDecoder(kind)
    out = feed_in_pieces(dec, junk + b"".join(sent), sizes, 2 * FRAME_LEN)
    got = []
    for f in out:
        vals = f.axes_counts if kind == "master" else f.wrench_counts
        bits = f.buttons if kind == "master" else f.flags
        raw = enc(f.seq, vals, bits)  # everything delivered re-encodes to a good frame
        assert not check_frame(raw, reserved)
        got.append(raw)
    assert_tail(got, sent, 2)


@settings(FUZZ, max_examples=200)
@given(st.binary(min_size=0, max_size=40))
def test_crl_one_frame_decoders_answer_a_frame_or_codec_error(raw):
    for decode in (decode_master_frame, decode_force_frame):
        try:
            decode(raw)
        except CodecError:
            pass
