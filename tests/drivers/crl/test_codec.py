"""CRL placeholder codec: golden bytes, round trips, bad frames, incremental resync."""

from __future__ import annotations

import math
import random

import pytest

from drivers.crl import crl_codec as codec
from drivers.crl.crl_codec import (CodecError, FrameDecoder, decode_force_frame, decode_master_frame,
                                   encode_force_frame, encode_master_frame)

# Checksums worked out by hand: 8-bit sum of bytes 0..14, two's complement.
GOLDEN_MASTER = bytes.fromhex("7e 05 0001 ffff 0100 ff00 7fff 8000 01 7f")
GOLDEN_FORCE = bytes.fromhex("7e ff 7fff 0000 0000 0000 0000 8001 01 83")


def test_golden_frames():
    assert encode_master_frame(5, (1, -1, 256, -256, 32767, -32768), codec.BTN_DEADMAN) == GOLDEN_MASTER
    assert encode_force_frame(0xFF, (32767, 0, 0, 0, 0, -32767), codec.FLAG_FORCE_ENABLE) == GOLDEN_FORCE
    m = decode_master_frame(GOLDEN_MASTER)
    assert (m.seq, m.axes_counts, m.buttons, m.deadman) == (5, (1, -1, 256, -256, 32767, -32768), 1, True)
    f = decode_force_frame(GOLDEN_FORCE)
    assert f.enabled and f.wrench_counts == (32767, 0, 0, 0, 0, -32767)
    force_n, torque_nm = f.wrench()
    assert force_n[0] == pytest.approx(40.0) and torque_nm[2] == pytest.approx(-2.0)


def test_frame_length_and_checksum_rule():
    frame = encode_master_frame(200, (-5, 4, 3, 2, 1, 0), codec.BTN_INDEX | codec.BTN_TRIGGER)
    assert len(frame) == codec.FRAME_LEN == 16
    assert frame[0] == codec.SOF and sum(frame) % 256 == 0


def test_round_trips_both_directions():
    rng = random.Random(1)
    for seq in range(0, 512, 7):
        counts = tuple(rng.randint(-32768, 32767) for _ in range(6))
        buttons = rng.randint(0, 7)
        m = decode_master_frame(encode_master_frame(seq, counts, buttons))
        assert (m.seq, m.axes_counts, m.buttons) == (seq & 0xFF, counts, buttons)
        f = decode_force_frame(encode_force_frame(seq, counts, buttons & 3))
        assert (f.seq, f.wrench_counts, f.flags) == (seq & 0xFF, counts, buttons & 3)


@pytest.mark.parametrize("mangle, why", [
    (lambda b: b[:-1], "length"),
    (lambda b: b"\x7d" + b[1:], "start byte"),
    (lambda b: b[:5] + bytes([b[5] ^ 1]) + b[6:], "checksum"),
])
def test_bad_frames_raise(mangle, why):
    with pytest.raises(CodecError, match=why):
        decode_master_frame(mangle(GOLDEN_MASTER))


def test_reserved_bits_are_bad_even_with_a_good_checksum():
    body = bytes([0x7E, 1] + [0] * 12 + [0x08])
    frame = body + bytes([codec.checksum8(body)])
    with pytest.raises(CodecError, match="reserved"):
        decode_master_frame(frame)


def test_encode_refuses_bad_values():
    with pytest.raises(ValueError, match="6 values"):
        encode_master_frame(0, (0,) * 5, 0)
    with pytest.raises(ValueError, match="int16"):
        encode_master_frame(0, (40000, 0, 0, 0, 0, 0), 0)
    with pytest.raises(ValueError, match="reserved"):
        encode_force_frame(0, (0,) * 6, 0x04)


def test_unit_conversions():
    assert codec.unit_to_counts(1.0) == 32767 and codec.unit_to_counts(-2.0) == -32767
    assert codec.unit_to_counts(math.nan) == 0
    assert codec.counts_to_unit(-32768) == -1.0
    assert codec.wrench_to_counts((40.0, -20.0, 0.0), (2.0, 0.0, -1.0)) == (32767, -16384, 0, 32767, 0, -16384)
    xyz_m, rpy_rad = codec.counts_to_pose((32767, 0, -32767, 32767, 0, 0))
    assert xyz_m == pytest.approx((0.20, 0.0, -0.20)) and rpy_rad[0] == pytest.approx(math.radians(60))
    assert len(codec.ASSUMPTIONS) >= 5 and all(a.startswith("assumed") for a in codec.ASSUMPTIONS)


def _frames(n: int, seed: int = 7) -> list[bytes]:
    rng = random.Random(seed)
    return [encode_master_frame(i, tuple(rng.randint(-32768, 32767) for _ in range(6)), rng.randint(0, 7))
            for i in range(n)]


def _feed_bytewise(dec: FrameDecoder, stream: bytes) -> list:
    out = []
    for b in stream:
        out += dec.feed(bytes([b]))
    return out


def test_clean_stream_byte_by_byte_first_frame_waits_for_a_confirming_frame():
    frames = _frames(10)
    dec = FrameDecoder()
    assert _feed_bytewise(dec, frames[0] + frames[1][:-1]) == []  # hunting: needs frame 1 whole
    got = dec.feed(frames[1][-1:])
    assert [f.seq for f in got] == [0, 1]
    got = _feed_bytewise(dec, b"".join(frames[2:]))
    assert [f.seq for f in got] == list(range(2, 10))  # locked: each frame as it completes
    assert dec.stats.frames_ok == 10 and dec.stats.bytes_discarded == 0 and dec.stats.frames_bad == 0


def test_resync_needs_the_next_sequence_number():
    frames = _frames(4)
    dec = FrameDecoder()
    # 0 then 2: 0 is not confirmed (2 is not its successor); 2 then 3 confirm each other
    assert [f.seq for f in dec.feed(frames[0] + frames[2] + frames[3])] == [2, 3]
    assert dec.stats.bytes_discarded == 16


def test_noise_between_frames_is_skipped_and_counted():
    frames = _frames(6)
    noise = bytes([0x7E, 0x00, 0x7E, 0x7E, 0x13]) + frames[3][:9]  # start bytes and a frame fragment
    stream = frames[0] + frames[1] + noise + frames[2] + frames[3] + frames[4] + frames[5]
    dec = FrameDecoder()
    got = _feed_bytewise(dec, stream)
    assert [f.seq for f in got] == [0, 1, 2, 3, 4, 5]
    assert dec.stats.bytes_discarded == len(noise)
    assert dec.stats.frames_bad == 1  # sync lost once where frame 2 was due
    assert dec.stats.resyncs == 1 and dec.stats.frames_lost == 0


def test_dropped_byte_loses_one_frame_and_resyncs():
    frames = _frames(5)
    damaged = frames[2][:7] + frames[2][8:]
    dec = FrameDecoder()
    got = _feed_bytewise(dec, frames[0] + frames[1] + damaged + frames[3] + frames[4])
    assert [f.seq for f in got] == [0, 1, 3, 4]
    assert dec.stats.frames_lost == 1 and dec.stats.frames_bad == 1


def test_checksum_valid_garbage_is_not_accepted_while_hunting():
    frames = _frames(4)
    impostor = encode_master_frame(99, (1, 2, 3, 4, 5, 6), 1)  # a well-formed frame inside noise
    stream = frames[0] + frames[1] + frames[2][:5] + impostor + b"\x00" + frames[3]
    dec = FrameDecoder()
    got = _feed_bytewise(dec, stream)
    assert [f.seq for f in got] == [0, 1]  # frame 3 is last and has no confirming frame yet
    assert [f.seq for f in dec.feed(encode_master_frame(4, (0,) * 6, 0))] == [3, 4]


def test_bad_since_good_counts_frames_worth_of_garbage():
    dec = FrameDecoder()
    frames = _frames(3)
    dec.feed(frames[0] + frames[1] + frames[2][:1])
    assert dec.bad_since_good == 0
    dec.feed(frames[2][1:])
    dec.feed(bytes(33))  # 33 zeros after the good frame 2
    assert dec.bad_since_good == math.ceil(33 / 16)
    dec.feed(frames[0] + frames[1])
    assert dec.bad_since_good == 0


def test_random_damage_never_yields_a_corrupt_frame():
    rng = random.Random(2024)
    frames = _frames(3000, seed=3)
    sent = {f: decode_master_frame(f) for f in frames}
    truth = set(sent.values())
    stream = bytearray()
    for f in frames:
        r = rng.random()
        if r < 0.05:  # noise before the frame
            stream += bytes(rng.choice((0x7E, rng.randrange(256))) for _ in range(rng.randint(1, 20)))
        if r > 0.95:  # drop a byte inside it
            i = rng.randrange(16)
            f = f[:i] + f[i + 1:]
        elif 0.90 < r <= 0.95:  # flip a bit inside it
            i = rng.randrange(16)
            f = f[:i] + bytes([f[i] ^ (1 << rng.randrange(8))]) + f[i + 1:]
        stream += f
    dec = FrameDecoder()
    got = []
    i = 0
    while i < len(stream):  # uneven chunks, including single bytes
        n = rng.choice((1, 1, 2, 5, 16, 17, 64))
        got += dec.feed(bytes(stream[i:i + n]))
        i += n
    assert got and all(g in truth for g in got)
    assert len(got) > 0.8 * len(frames)
    assert dec.stats.frames_bad > 0 and dec.stats.bytes_discarded > 0


def test_pure_garbage_yields_nothing():
    rng = random.Random(5)
    garbage = bytes(rng.choice((0x7E, rng.randrange(256))) for _ in range(50_000))
    dec = FrameDecoder()
    assert dec.feed(garbage) == []
    assert dec.stats.bytes_discarded >= len(garbage) - codec.FRAME_LEN


def test_force_decoder_and_bad_kind():
    dec = FrameDecoder("force")
    f0 = encode_force_frame(0, (1, 2, 3, 4, 5, 6), 3)
    f1 = encode_force_frame(1, (0,) * 6, 0)
    assert [f.wrench_counts for f in dec.feed(f0 + f1)] == [(1, 2, 3, 4, 5, 6), (0,) * 6]
    with pytest.raises(ValueError, match="kind"):
        FrameDecoder("rate")
