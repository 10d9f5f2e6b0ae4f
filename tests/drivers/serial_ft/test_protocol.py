"""Codecs and stream decoders, fed byte by byte, deterministic (no pty, no threads)."""

from __future__ import annotations

import random

import pytest

from drivers.serial_ft import protocol as P

# Sourced capture (KonstantinosAng/ATI-FT-Gamma FTsensor3.py, via hardware-registers.md section 7)
CAPTURE = bytes.fromhex("00" "FF93" "FF98" "FE69" "FFBB" "0006" "FFDB")
CAPTURE_COUNTS = (-109, -104, -407, -69, 6, -37)
ASCII_EXAMPLE = b"0,  -102,   -99,  -225,   -20,    39,   -39"


def test_binary_capture_decodes_to_status_and_six_counts():
    assert P.decode_binary(CAPTURE) == (0, CAPTURE_COUNTS)
    assert P.encode_binary(0, CAPTURE_COUNTS) == CAPTURE


def test_ascii_example_line_round_trips_at_45_bytes():
    assert P.decode_ascii_line(ASCII_EXAMPLE) == (0, (-102, -99, -225, -20, 39, -39))
    line = P.encode_ascii(0, (-102, -99, -225, -20, 39, -39))
    assert line == ASCII_EXAMPLE + b"\r\n" and len(line) == P.ASCII_RECORD_BYTES == 45


@pytest.mark.parametrize("line", [
    ASCII_EXAMPLE[:10] + ASCII_EXAMPLE[11:],  # a character lost
    ASCII_EXAMPLE[:10] + b"7" + ASCII_EXAMPLE[10:],  # a character inserted
    b"9" + ASCII_EXAMPLE[1:],  # unknown status
    ASCII_EXAMPLE.replace(b"  -102", b"  -1x2"),  # not a number
])
def test_ascii_line_check_is_strict(line):
    assert P.decode_ascii_line(line) is None


def test_checksum_is_low_seven_bits_of_sum_and_is_checked():
    rec = P.encode_binary(0, CAPTURE_COUNTS, checksum_on=True)
    assert len(rec) == 14 and rec[-1] == sum(CAPTURE) & 0x7F
    assert P.decode_binary(rec, True) == (0, CAPTURE_COUNTS)
    assert P.decode_binary(rec[:-1] + bytes([rec[-1] ^ 1]), True) is None


def test_max_rates_match_the_computed_table():
    # hardware-registers.md section 7 table: 147.7 / 137.1 / 42.7 records/s at 19200 baud
    assert P.max_rate_hz("binary") == pytest.approx(147.7, abs=0.05)
    assert P.max_rate_hz("binary", checksum_on=True) == pytest.approx(137.1, abs=0.05)
    assert P.max_rate_hz("ascii") == pytest.approx(42.7, abs=0.05)
    with pytest.raises(ValueError):
        P.max_rate_hz("hex")


def _records(n: int, seed: int, safe: bool = True):
    rnd = random.Random(seed)
    out = []
    for _ in range(n):
        if safe:  # no count byte is 0x00/0x01 (see conftest.safe_load)
            counts = tuple(rnd.choice([1, -1]) * ((rnd.randrange(2, 0x7F) << 8) | rnd.randrange(2, 0x100))
                           for _ in range(6))
            counts = tuple(c if (c & 0xFF) > 1 and ((c >> 8) & 0xFF) > 1 else 0x0505 for c in counts)
        else:
            counts = tuple(rnd.randrange(-300, 300) for _ in range(6))
        out.append((0, counts))
    return out


def _feed_bytewise(dec, data: bytes):
    out = []
    for b in data:
        out += dec.feed(bytes([b]))
    return out


@pytest.mark.parametrize("checksum_on", [False, True])
def test_binary_decoder_clean_stream_byte_by_byte(checksum_on):
    recs = _records(50, 1, safe=False)
    wire = b"".join(P.encode_binary(s, c, checksum_on) for s, c in recs)
    dec = P.BinaryStreamDecoder(checksum_on)
    got = _feed_bytewise(dec, wire) + dec.finish()
    assert got == recs
    assert dec.stats.bad_records == 0 and dec.stats.records == 50 and dec.stats.bytes_in == len(wire)


def _corrupt(records, checksum_on, seed, events=6):
    """Wire bytes with `events` insertions/drops at random places, spaced 5 records apart."""
    rnd = random.Random(seed)
    L = P.record_bytes("binary", checksum_on)
    chunks = [bytearray(P.encode_binary(s, c, checksum_on)) for s, c in records]
    hit = set()
    for k in range(events):
        r = 3 + 5 * k
        j = rnd.randrange(L)
        if rnd.random() < 0.5:
            chunks[r][j:j] = bytes([rnd.randrange(2, 256) for _ in range(rnd.randrange(1, 4))])
        else:
            del chunks[r][j: j + rnd.randrange(1, 3)]
        hit.add(r)
    return b"".join(chunks), hit


@pytest.mark.parametrize("checksum_on", [False, True])
@pytest.mark.parametrize("seed", range(8))
def test_binary_decoder_never_returns_a_corrupt_record_and_counts_slips(checksum_on, seed):
    recs = _records(40, seed)
    wire, hit = _corrupt(recs, checksum_on, seed)
    dec = P.BinaryStreamDecoder(checksum_on)
    got = _feed_bytewise(dec, wire) + dec.finish()
    it = iter(recs)
    assert all(any(g == r for r in it) for g in got), "a decoded record is not in the ground truth"
    assert dec.stats.bad_records >= len(hit) and dec.stats.resyncs == len(hit)
    assert len(got) >= len(recs) - 2 * len(hit)  # at most the hit record and its neighbour lost


def test_binary_without_checksum_cannot_detect_a_slip_when_the_next_byte_is_zero():
    """The documented limit (docs/ft-protocol.md): no sync byte, no checksum -> a dropped
    byte goes unnoticed when the byte that lands on the status position is 0x00."""
    a, b = (0, (1000, 1000, 1000, 1000, 1000, 1000)), (0, (5, 5, 5, 5, 5, 5))  # b's Fx high byte = 0x00
    wire = P.encode_binary(*a) + P.encode_binary(*b) + P.encode_binary(*b)
    wire = wire[:5] + wire[6:]  # lose one byte inside the first record
    got = P.BinaryStreamDecoder(False).feed(wire)
    assert got and got[0] != a  # a corrupt record passes: hence checksum or Ctrl-T polling
    dec = P.BinaryStreamDecoder(True)  # with the checksum the same slip is caught here
    wire_c = P.encode_binary(*a, True) + P.encode_binary(*b, True) * 2
    assert all(r in (a, b) for r in dec.feed(wire_c[:5] + wire_c[6:]))


def test_binary_decoder_rejects_unknown_status():
    dec = P.BinaryStreamDecoder(False)
    wire = P.encode_binary(0, (700,) * 6) + P.encode_binary(0x55, (700,) * 6) + P.encode_binary(0, (700,) * 6) * 3
    got = dec.feed(wire) + dec.finish()
    assert all(s == 0 for s, _ in got) and dec.stats.bad_records >= 1


def test_ascii_decoder_with_noise_drops_and_merged_lines_byte_by_byte():
    recs = [(0, tuple((i * 37 + k * 1001) % 20000 - 10000 for k in range(6))) for i in range(30)]
    lines = [bytearray(P.encode_ascii(s, c)) for s, c in recs]
    lines[5][10:10] = b"#"  # noise inside a line
    del lines[10][3]  # dropped character
    del lines[15][-2:]  # lost CR LF: two lines merge
    lines[20][0:0] = b"\xff\x00"  # noise between lines
    wire = b"".join(lines)
    dec = P.AsciiStreamDecoder()
    dec.reset(synced=True)
    got = _feed_bytewise(dec, wire)
    expected = [r for i, r in enumerate(recs) if i not in (5, 10, 15, 16, 20)]
    assert got == expected
    assert dec.stats.bad_records == 4 and dec.stats.resyncs == 4


def test_ascii_decoder_skips_echo_and_prompt_and_a_partial_first_line():
    dec = P.AsciiStreamDecoder()  # not synced: the first fragment may be a record's tail
    good = P.encode_ascii(0, (1, 2, 3, 4, 5, 6))
    got = dec.feed(b"  -5,   7\r\n" + good + b"\r\n>" + b"QS\r\n" + good)
    assert got == [(0, (1, 2, 3, 4, 5, 6))] * 2 and dec.stats.bad_records == 0
