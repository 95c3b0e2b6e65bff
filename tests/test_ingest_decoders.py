"""Serial decoders: formats, round trips, and fuzzing (chunk splits, corruption, random bytes)."""
import math
import random

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mkc_stream.ingest import make_decoder
from mkc_stream.ingest.binary import (IMU_F32, MAG_F32, MAG_I16, BinaryDecoder, crc16_ccitt_false,
                                      encode_frame)
from mkc_stream.ingest.csvlines import CsvDecoder, encode_csv_header, encode_csv_row
from mkc_stream.ingest.decoder import LineDecoder
from mkc_stream.ingest.motioncal import RAW_ACC, RAW_GYRO, MotionCalDecoder, encode_motioncal
from mkc_stream.ingest.vectornav import VectorNavDecoder, crc16_xmodem, encode_vn, xor8

FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def feed_chunks(dec, data, cuts, t_host=0.0):
    """Feed ``data`` split at the (sorted, deduplicated) positions ``cuts``; then flush."""
    out, prev = [], 0
    for c in sorted(set(min(max(0, c), len(data)) for c in cuts)) + [len(data)]:
        out += dec.feed(data[prev:c], t_host)
        prev = c
    return out + dec.flush()


def random_imu(rng, n):
    rows = []
    for k in range(n):
        mag = tuple(rng.uniform(-80, 80) for _ in range(3))
        acc = tuple(rng.uniform(-20, 20) for _ in range(3))
        gyro = tuple(rng.uniform(-5, 5) for _ in range(3))
        rows.append((k, k * 1e-3, mag, acc, gyro, rng.uniform(-10, 60)))
    return rows


# --- one stream per protocol, for the generic properties ---------------------------------------

def stream_binary(rng, n=60):
    out = b""
    for k, t, m, a, g, tc in random_imu(rng, n):
        ftype = (IMU_F32, MAG_F32, MAG_I16)[k % 3]
        out += encode_frame(k, int(t * 1e6), m, a, g, tc, ftype=ftype)
    return out


def stream_motioncal(rng, n=40):
    out = b"Adafruit AHRS calibration\r\n"
    for k, t, m, a, g, tc in random_imu(rng, n):
        out += encode_motioncal(a, g, m, "Raw") + encode_motioncal(a, g, m, "Uni")
    return out


def stream_csv(rng, n=40):
    cols = ["t", "mx", "my", "mz", "ax", "ay", "az", "gx", "gy", "gz", "temp", "seq", "current"]
    out = encode_csv_header(cols, {"units.mag": "uT"})
    for k, t, m, a, g, tc in random_imu(rng, n):
        out += encode_csv_row([t, *m, *a, *g, tc, k, rng.uniform(0, 3)])
    return out


def stream_vn(rng, n=40):
    out = b""
    for k, t, m, a, g, tc in random_imu(rng, n):
        out += encode_vn("VNYMR" if k % 2 else "VNIMU", m, a, g, tc, checksum=("xor", "crc")[k % 2])
    return out


STREAMS = {"binary": stream_binary, "motioncal": stream_motioncal, "csv": stream_csv, "vectornav": stream_vn}


# --- formats ----------------------------------------------------------------------------------

def test_crc_check_values():
    assert crc16_ccitt_false(b"123456789") == 0x29B1          # the catalogue's check value
    assert crc16_xmodem(b"123456789") == 0x31C3


def _vn_crc_reference(data):
    # VectorNav's documented byte-wise CRC-16 (a different formulation of CRC-CCITT/XMODEM)
    crc = 0
    for b in data:
        crc = ((crc >> 8) | (crc << 8)) & 0xFFFF
        crc ^= b
        crc ^= (crc & 0xFF) >> 4
        crc ^= (crc << 12) & 0xFFFF
        crc ^= ((crc & 0xFF) << 5) & 0xFFFF
    return crc


def test_vectornav_crc_matches_the_vendor_algorithm():
    for text in (b"VNYMR,+010.071,-000.278", b"VNRRG,08", b""):
        assert crc16_xmodem(text) == _vn_crc_reference(text)


def test_binary_frame_layout_byte_by_byte():
    f = encode_frame(0x1234, 0x89ABCDEF, (1.0, -2.0, 0.5), ftype=MAG_F32)
    assert f[:2] == b"\xa5\x5a" and f[2] == 0x11 and f[3] == 12
    assert f[4:6] == b"\x34\x12" and f[6:10] == b"\xef\xcd\xab\x89"
    assert f[10:14] == b"\x00\x00\x80\x3f"                      # float32 1.0, little-endian
    assert len(f) == 24 and int.from_bytes(f[22:24], "little") == crc16_ccitt_false(f[2:22])
    s = BinaryDecoder().feed(f)[0]
    assert s.mag == (1.0, -2.0, 0.5) and s.seq == 0x1234 and s.t == pytest.approx(0x89ABCDEF * 1e-6)
    assert not s.host_time


def test_binary_round_trip_all_types_and_time_unwrap():
    dec = BinaryDecoder()
    t_us = [0xFFFFFF00, 0xFFFFFFF0, 0x10, 0x100]                # wraps between the 2nd and 3rd frame
    frames = [encode_frame(k, t, (1.5, 2.5, -3.25), (0.0, 0.0, 9.81), (0.1, 0.2, 0.3), 21.5, ftype=ft)
              for k, (t, ft) in enumerate(zip(t_us, (IMU_F32, MAG_F32, MAG_I16, IMU_F32)))]
    out = dec.feed(b"".join(frames))
    assert [s.seq for s in out] == [0, 1, 2, 3]
    assert out[0].acc == pytest.approx((0, 0, 9.81), abs=1e-6) and out[0].temp == 21.5
    assert out[1].acc is None and out[2].mag == pytest.approx((1.5, 2.5, -3.25))
    assert [s.t for s in out] == pytest.approx([(t + (1 << 32) * (i >= 2)) * 1e-6 for i, t in enumerate(t_us)])
    assert dec.counts.drops == 0 and dec.counts.bad_frames == 0


def test_binary_counts_drops_and_restarts():
    dec = BinaryDecoder()
    seqs = [10, 11, 14, 15, 0xFFFF, 0, 1, 3]                     # 2 lost, a restart, a wrap, 1 lost
    out = dec.feed(b"".join(encode_frame(s, 0, (1, 2, 3)) for s in seqs))
    assert len(out) == len(seqs)
    # 11 -> 14: 2 dropped; 15 -> 0xFFFF: "65519 missing" is more than half the range, so a restart;
    # 0xFFFF -> 0: the wrap; 1 -> 3: 1 dropped
    assert dec.counts.drops == 2 + 1 and dec.counts.seq_resets == 1


def test_binary_unknown_type_with_good_crc_is_ignored():
    good = encode_frame(1, 0, (1, 2, 3))
    body = bytes([0x1F, 4]) + (2).to_bytes(2, "little") + (0).to_bytes(4, "little") + b"abcd"
    unknown = b"\xa5\x5a" + body + crc16_ccitt_false(body).to_bytes(2, "little")
    dec = BinaryDecoder()
    out = dec.feed(good + unknown + encode_frame(3, 0, (1, 2, 3)))
    assert [s.seq for s in out] == [1, 3] and dec.counts.ignored == 1 and dec.counts.drops == 1


def test_motioncal_units_and_kind_lock():
    dec = MotionCalDecoder()
    data = b"Raw:8192,0,-8192,16,0,0,100,-200,300\r\nUni:9.81,0.00,-9.81,0.0175,0.0000,0.0000,10.05,-20.00,30.00\r\n"
    out = dec.feed(b"banner\r\n" + data + data, t_host=12.5)
    assert len(out) == 2 and dec.counts.ignored == 3             # banner + the 2 Uni lines
    s = out[0]
    assert s.mag == pytest.approx((10.0, -20.0, 30.0)) and s.acc[0] == pytest.approx(9.80665)
    assert s.gyro[0] == pytest.approx(math.radians(1.0)) and s.t == 12.5 and s.host_time
    uni = make_decoder("motioncal-uni").feed(data)
    assert len(uni) == 1 and uni[0].mag == pytest.approx((10.05, -20.0, 30.0))
    assert RAW_ACC * 8192 == pytest.approx(9.80665) and RAW_GYRO * 16 == pytest.approx(math.pi / 180)


def test_motioncal_damaged_lines_are_bad_not_ignored():
    dec = MotionCalDecoder()
    dec.feed(b"Raw:1,2,3,4,5,6,7,8,9\n")                          # first line (would be lead-in if bad)
    dec.feed(b"Raw:1,2,3,4,5,6,7,8\nRzw:1,2,3,4,5,6,7,8,9\nRaw:1,2,x,4,5,6,7,8,9\nhello world\n")
    assert dec.counts.frames == 1 and dec.counts.bad_frames == 3 and dec.counts.ignored == 1
    assert dec.bad_reasons[0].startswith("Raw: expected 9 fields")


def test_csv_lines_header_meta_seq_and_bad_rows():
    dec = CsvDecoder()
    data = (b"# seq_modulus: 8\n# sensor: X\n"
            b"t,mx,my,mz,temp,seq,rpm\n0,1,2,3,20,6,100\n0.1,1,2,3,,7,nan\n0.2,1,2,3,20,1,5\n"
            b"0.15,1,2,3,20,2,5\n0.3,1,oops,3,20,3,5\n0.4,1,2,3,20,6,5\n0.5,1,2\n")
    out = dec.feed(data)
    assert [s.t for s in out] == [0, 0.1, 0.2, 0.4]
    assert dec.meta == {"seq_modulus": "8", "sensor": "X"}
    assert out[1].temp is not None and math.isnan(out[1].temp) and math.isnan(out[1].aux["rpm"])
    assert out[0].aux == {"rpm": 100.0} and out[0].seq == 6 and not out[0].host_time
    # 7 -> 1 (mod 8): 1 missing = a drop; 1 -> 6: 4 missing, 2 explained by the 2 bad rows between
    assert dec.counts.bad_frames == 3 and dec.counts.drops == 1 + 2
    assert dec.bad_reasons[0].startswith("t decreasing")


def test_csv_rows_before_header_and_given_columns():
    dec = CsvDecoder()
    dec.feed(b"0,1,2,3\n0.1,1,2,3\n")
    assert dec.counts.lead_in_bytes > 0 and dec.counts.bad_frames == 1   # the first is lead-in
    dec = CsvDecoder(["t", "mx", "my", "mz"])
    assert len(dec.feed(b"0,1,2,3\n0.1,1,2,3\n")) == 2


def test_vectornav_messages_and_checksums():
    m, a, g = (21.5, -3.2, 40.0), (0.1, -0.2, 9.8), (0.01, 0.02, -0.03)
    dec = VectorNavDecoder()
    lines = [encode_vn("VNYMR", m, a, g, checksum="xor"), encode_vn("VNIMU", m, a, g, 31.0, 99.5, checksum="crc"),
             encode_vn("VNYMR", m, a, g, checksum="off"), b"$VNYPR,+010.071,-000.278,-000.590*66\r\n"]
    body = b"VNYPR,+010.071,-000.278,-000.590"
    lines[3] = b"$" + body + f"*{xor8(body):02X}\r\n".encode()
    out = dec.feed(b"".join(lines), t_host=5.0)
    assert len(out) == 3 and dec.counts.ignored == 1 and dec.unchecked == 1
    assert out[0].mag == pytest.approx(m, abs=0.01) and out[0].gyro == pytest.approx(g, abs=1e-6)
    assert out[1].temp == pytest.approx(31.0) and out[1].aux == {"pressure": pytest.approx(99.5)}
    assert out[0].host_time and out[0].t == 5.0
    bad = bytearray(lines[0])
    bad[12] = ord("9") if bad[12] != ord("9") else ord("8")
    dec.feed(bytes(bad) + b"garbage\r\n")
    assert dec.counts.bad_frames == 2 and dec.bad_reasons[0] == "checksum mismatch"


def test_overlong_line_is_bad_and_bounded():
    dec = MotionCalDecoder()
    dec.feed(b"Raw:1,2,3,4,5,6,7,8,9\n")
    for _ in range(50):
        dec.feed(b"x" * 1000)                                     # no line ending, ever
    assert len(dec._buf) <= LineDecoder.MAX_LINE and dec.counts.bad_frames == 1
    assert len(dec.feed(b"tail\nRaw:1,2,3,4,5,6,7,8,9\n")) == 1


# --- fuzz: chunking, random bytes, corruption -------------------------------------------------

@pytest.mark.parametrize("proto", sorted(STREAMS))
@FUZZ
@given(seed=st.integers(0, 2**32 - 1), cuts=st.lists(st.integers(0, 20000), max_size=40))
def test_fuzz_any_chunking_gives_identical_samples(proto, seed, cuts):
    data = STREAMS[proto](random.Random(seed))
    whole_dec, split_dec = make_decoder(proto), make_decoder(proto)
    whole = whole_dec.feed(data, 0.0) + whole_dec.flush()
    split = feed_chunks(split_dec, data, [c % (len(data) + 1) for c in cuts])
    assert repr(split) == repr(whole)
    assert split_dec.counts == whole_dec.counts
    assert whole_dec.counts.bad_frames == 0 and len(whole) > 0


@pytest.mark.parametrize("proto", sorted(STREAMS))
@FUZZ
@given(seed=st.integers(0, 2**32 - 1), cuts=st.lists(st.integers(0, 20000), max_size=20), rate=st.sampled_from([0.01, 0.05]))
def test_fuzz_corruption_never_crashes_and_chunking_still_does_not_matter(proto, seed, cuts, rate):
    rng = random.Random(seed)
    data = bytearray(STREAMS[proto](rng))
    for i in range(len(data)):
        if rng.random() < rate:
            data[i] ^= rng.randrange(1, 256)
    data = bytes(data)
    a, b = make_decoder(proto), make_decoder(proto)
    whole = a.feed(data, 0.0) + a.flush()
    split = feed_chunks(b, data, [c % (len(data) + 1) for c in cuts])
    assert repr(split) == repr(whole) and a.counts == b.counts
    assert a.counts.frames == len(whole)


@pytest.mark.parametrize("proto", sorted(STREAMS) + ["motioncal-uni"])
@FUZZ
@given(data=st.binary(max_size=3000), cuts=st.lists(st.integers(0, 3000), max_size=10))
def test_fuzz_random_bytes_never_crash(proto, data, cuts):
    dec = make_decoder(proto)
    out = feed_chunks(dec, data, cuts)
    assert dec.counts.frames == len(out)
    assert all(len(s.mag) == 3 for s in out)


@FUZZ
@given(seed=st.integers(0, 2**32 - 1), cuts=st.lists(st.integers(0, 100000), max_size=30))
def test_fuzz_binary_1pct_corruption_loses_no_good_frame_and_counts_every_bad_one(seed, cuts):
    rng = random.Random(seed)
    frames = []
    for k, t, m, a, g, tc in random_imu(rng, 400):
        frames.append(encode_frame(k, int(t * 1e6), m, a, g, tc, ftype=(IMU_F32, MAG_F32, MAG_I16)[rng.randrange(3)]))
    data, touched = bytearray(), set()
    for k, f in enumerate(frames):
        f = bytearray(f)
        if 0 < k < len(frames) - 1:           # the first and last frame stay intact (nothing brackets them)
            for i in range(len(f)):
                if rng.random() < 0.01:
                    f[i] ^= rng.randrange(1, 256)
                    touched.add(k)
        data += f
    dec = BinaryDecoder()
    out = feed_chunks(dec, bytes(data), [c % (len(data) + 1) for c in cuts])
    good = [k for k in range(len(frames)) if k not in touched]
    assert [s.seq for s in out] == good                          # every intact frame, nothing else
    ref = BinaryDecoder().feed(b"".join(frames[k] for k in good))
    ref_by_seq = {s.seq: s for s in ref}
    assert all(repr(s) == repr(ref_by_seq[s.seq]) for s in out)
    assert dec.counts.bad_frames == len(touched) and dec.counts.drops == 0


def test_binary_false_sync_at_the_end_does_not_hide_the_last_frames():
    # a damaged frame whose header claims a 40-byte payload, right before the last good frame
    fake = bytearray(encode_frame(1, 0, (1, 2, 3), (0, 0, 0), (0, 0, 0), 0.0, ftype=IMU_F32)[:12])
    last = encode_frame(2, 0, (4, 5, 6))
    dec = BinaryDecoder()
    out = dec.feed(encode_frame(0, 0, (1, 2, 3)) + bytes(fake) + last)
    assert [s.seq for s in out] == [0]                           # still waiting for the claimed bytes
    assert [s.seq for s in dec.flush()] == [2] and dec.counts.bad_frames == 1
