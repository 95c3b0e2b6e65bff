"""CAN: the built-in frame, DBC mappings, python-can logs (incl. a real CANedge MF4), virtual and slcan buses."""
import json
import os
import pathlib
import subprocess
import sys
import threading
import uuid

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mkc_stream.cli import main
from mkc_stream.ingest import SourceError, open_log
from mkc_stream.ingest.candecoder import MagFrameDecoder
from mkc_stream.ingest.canframe import decode_mag_frame, encode_mag_frame
from mkc_stream.ingest.dbc import MappingError, parse_map
from mkc_stream.ingest.emulator import DeviceModel, run_can
from mkc_stream.io.recording import read_recording

DATA = pathlib.Path(__file__).parent / "data" / "canmod-gps-canedge"
MF4 = DATA / "2F6913DB_00000004_00000001.MF4"
DBC = DATA / "canmod-gps.dbc"
IMU_MAP = ("mx=AccelerationX,my=AccelerationY,mz=AccelerationZ,gx=AngularRateX*0.017453292519943295,"
           "gy=AngularRateY*0.017453292519943295,gz=AngularRateZ*0.017453292519943295,imu_valid=ImuValid")


def msg(data, can_id=0x110, t=0.0, **kw):
    return can.Message(arbitration_id=can_id, data=data, timestamp=t, is_extended_id=False, **kw)


def mag_messages(n, t0=100.0, rate=100.0, skip=()):
    mags = DeviceModel(1, rate).block(0, n)[1]
    return [msg(encode_mag_frame(mags[k], k), t=t0 + k / rate) for k in range(n) if k not in skip], mags


# --- the built-in frame -------------------------------------------------------------------------

def test_frame_layout_and_range():
    data = encode_mag_frame((12.34, -0.01, 327.67), 0xABCD)
    assert data == bytes.fromhex("d204ffffff7fcdab")
    assert decode_mag_frame(data) == (pytest.approx((12.34, -0.01, 327.67)), 0xABCD)
    with pytest.raises(ValueError, match="327.67"):
        encode_mag_frame((400, 0, 0), 1)
    with pytest.raises(ValueError, match="8 data bytes"):
        decode_mag_frame(b"\x00" * 6)


def test_frame_decoder_counts():
    msgs, mags = mag_messages(20, skip={5, 6, 12})
    msgs.insert(3, msg(b"\x01\x02", t=100.03))                     # wrong length on the sample id
    msgs.insert(4, msg(b"\x00" * 8, can_id=0x111))                 # another id
    msgs.insert(5, can.Message(is_error_frame=True))
    msgs.insert(6, msg(b"", is_remote_frame=True))
    dec = MagFrameDecoder()
    out = dec.feed(msgs)
    assert [s.seq for s in out] == [k for k in range(20) if k not in {5, 6, 12}]
    assert out[0].mag == pytest.approx(tuple(mags[0]), abs=0.005) and out[1].t == pytest.approx(100.01)
    c = dec.counts
    assert (c.frames, c.drops, c.bad_frames, c.ignored) == (17, 3, 2, 2)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 0x7FF), st.binary(max_size=8), st.booleans()), max_size=40))
def test_fuzz_frame_decoder_random_frames(frames):
    dec = MagFrameDecoder()
    out = dec.feed([msg(d, can_id=i, is_remote_frame=r and not d) for i, d, r in frames])
    assert dec.counts.frames == len(out) and dec.counts.frames + dec.counts.bad_frames + dec.counts.ignored == len(frames)


# --- DBC mappings -------------------------------------------------------------------------------

def test_parse_map():
    m = parse_map(["mx=imu.MagX*0.1, my=MagY", "mz=MagZ", "seq=Counter"])
    assert m[0].message == "imu" and m[0].scale == 0.1 and m[1].message is None and m[3].column == "seq"
    for bad, why in [("mx=a", "missing my, mz"), ("mx=a,my=b,mz=c,ax=d", "all of ax"), ("mx=a,mx=b,my=c,mz=d", "more than once"),
                     ("t=a,mx=a,my=b,mz=c", "timestamp"), ("mx=a*x,my=b,mz=c", "not a number"), ("mx,my=b,mz=c", "COLUMN=")]:
        with pytest.raises(MappingError, match=why):
            parse_map(bad)


DBC_TEXT = '''VERSION ""
NS_ :
BS_:
BU_:
BO_ 288 imu_mag: 8 Vector__XXX
 SG_ MagX : 0|16@1- (0.1,0) [-3276.8|3276.7] "uT" Vector__XXX
 SG_ MagY : 16|16@1- (0.1,0) [-3276.8|3276.7] "uT" Vector__XXX
 SG_ MagZ : 32|16@1- (0.1,0) [-3276.8|3276.7] "uT" Vector__XXX
 SG_ Counter : 48|8@1+ (1,0) [0|255] "" Vector__XXX
BO_ 289 imu_temp: 2 Vector__XXX
 SG_ Temp : 0|16@1- (0.01,0) [-327.68|327.67] "degC" Vector__XXX
'''


def test_dbc_decoder_signals_latest_values_and_drops(tmp_path):
    cantools = pytest.importorskip("cantools")
    dbc = tmp_path / "imu.dbc"
    dbc.write_text(DBC_TEXT)
    db = cantools.database.load_file(str(dbc))
    from mkc_stream.ingest.dbc import DbcDecoder

    dec = DbcDecoder(str(dbc), ["mx=MagX,my=MagY,mz=MagZ,seq=Counter,temp=Temp"])
    mag_msg, temp_msg = db.get_message_by_name("imu_mag"), db.get_message_by_name("imu_temp")
    msgs = []
    for k in range(300):
        if k == 10:
            msgs.append(msg(temp_msg.encode({"Temp": 21.5}), can_id=289, t=k))
        if k in (50, 51):
            continue                                                 # two frames lost
        msgs.append(msg(mag_msg.encode({"MagX": 20.0, "MagY": -3.5, "MagZ": 41.2, "Counter": k % 256}), can_id=288, t=k))
    msgs.append(msg(b"\x01", can_id=288, t=400))                    # too short for the message
    out = dec.feed(msgs)
    assert len(out) == 298 and out[0].mag == pytest.approx((20.0, -3.5, 41.2))
    assert out[5].temp is not None and out[5].temp != out[5].temp and out[20].temp == pytest.approx(21.5)
    assert dec.counts.drops == 2 and dec.counts.bad_frames == 1 and dec.units_mag == "uT"
    assert dec.meta["seq_modulus"] == "256"
    with pytest.raises(MappingError, match="one message"):
        DbcDecoder(str(dbc), ["mx=MagX,my=MagY,mz=Temp"])
    with pytest.raises(MappingError, match="no signal"):
        DbcDecoder(str(dbc), ["mx=MagX,my=MagY,mz=MagW"])


# --- python-can logs ----------------------------------------------------------------------------

@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf", ".trc", ".csv"])
def test_can_logs_replay_every_format(tmp_path, suffix):
    msgs, mags = mag_messages(300, skip={100})
    path = tmp_path / f"frames{suffix}"
    with can.Logger(str(path)) as w:
        for m in msgs:
            w.on_message_received(m)
    with open_log(path) as src:
        out = list(src)
        counts = src.counts()
    assert counts == {"samples": 299, "bad_frames": 0, "drops": 1, "gaps": 0}   # 2 periods: no gap
    assert [s.seq for s in out][:101] == [*range(100), 101]
    assert out[7].mag == pytest.approx(tuple(mags[7]), abs=0.006) and not out[7].host_time


def test_damaged_candump_line_is_counted_and_reading_goes_on(tmp_path):
    msgs, _ = mag_messages(50)
    path = tmp_path / "d.log"
    with can.Logger(str(path)) as w:
        for m in msgs:
            w.on_message_received(m)
    lines = path.read_text().splitlines()
    lines[20] = "(garbage"
    path.write_text("\n".join(lines) + "\n")
    with open_log(path) as src:
        out = list(src)
        assert len(out) == 49 and src.counts()["bad_frames"] == 1 and src.counts()["drops"] == 0


@pytest.mark.parametrize("suffix", [".asc", ".trc", ".csv"])
def test_damaged_record_in_other_formats_is_never_silent(tmp_path, suffix):
    """python-can's ASC/TRC readers skip a line they cannot parse (the frame counter shows the loss);
    its CSV reader stops there (reported, with the damage counted)."""
    msgs, _ = mag_messages(50)
    path = tmp_path / f"d{suffix}"
    with can.Logger(str(path)) as w:
        for m in msgs:
            w.on_message_received(m)
    text = path.read_text().splitlines()
    mid = len(text) // 2
    text[mid] = text[mid][: len(text[mid]) // 2] + " zz q"
    path.write_text("\n".join(text) + "\n")
    with open_log(path) as src:
        out = list(src)
        c, d = src.counts(), src.detail()
    if "stopped_early" in d:
        assert c["bad_frames"] == 1 and 0 < len(out) < 50
    else:
        assert len(out) == 49 and c["bad_frames"] + c["drops"] == 1


def test_canedge_mf4_replays_through_the_dbc(capsys):
    pytest.importorskip("cantools")
    pytest.importorskip("asammdf")
    if not MF4.is_file():
        pytest.skip(f"{MF4} is not present")
    code = main(["replay", str(MF4), "--dbc", str(DBC), "--map", IMU_MAP, "--json", "-"])
    out = capsys.readouterr()
    obj = json.loads(out.out)
    assert code == 1 and obj["status"] == "rejected" and "coverage" in obj["reason"]
    assert obj["counts"] == {"samples": 4724, "bad_frames": 0, "drops": 0, "gaps": obj["counts"]["gaps"]}
    assert obj["units"]["mag"] == "m/s^2" and obj["time_source"] == "log"
    assert obj["ingest"]["ignored"] > 0 and 95 < obj["sample_rate_hz"] < 105
    assert "4724 samples" in out.err


def test_canedge_mf4_with_the_default_frame_says_which_ids_exist(capsys):
    pytest.importorskip("asammdf")
    if not MF4.is_file():
        pytest.skip(f"{MF4} is not present")
    code = main(["replay", str(MF4)])
    out = capsys.readouterr().out
    assert code == 1 and "0 samples" in out and "0x9 x4724" in out and "--can-id" in out


def test_map_without_dbc_is_a_usage_error(tmp_path, capsys):
    p = tmp_path / "x.log"
    p.write_text("")
    assert main(["replay", str(p), "--map", "mx=a,my=b,mz=c"]) == 2
    assert "--map needs --dbc" in capsys.readouterr().err
    with pytest.raises(SourceError):
        open_log(tmp_path / "none.log")


# --- live buses ---------------------------------------------------------------------------------

def _virtual_sender(channel, rate, stop, **kw):
    with can.Bus(interface="virtual", channel=channel) as bus:
        run_can(bus, rate, duration=30, stop=stop, sweep_s=1.5, **kw)


def test_live_from_a_virtual_bus(capsys, tmp_path):
    channel = f"mkc-{uuid.uuid4().hex[:8]}"
    stop = threading.Event()
    th = threading.Thread(target=_virtual_sender, args=(channel, 1000, stop), kwargs={"drop_every": 250}, daemon=True)
    th.start()
    try:
        code = main(["live", "-i", "virtual", "-c", channel, "--max-samples", "3000", "--out", str(tmp_path / "v.csv"),
                     "--json", "-"])
    finally:
        stop.set()
        th.join()
    obj = json.loads(capsys.readouterr().out)
    assert obj["counts"]["samples"] == 3000 and obj["counts"]["bad_frames"] == 0
    assert 11 <= obj["counts"]["drops"] <= 13                         # every 250th frame is never sent
    assert obj["status"] == "accepted" and code == 0 and obj["time_source"] == "host"
    assert len(read_recording(tmp_path / "v.csv")) == 3000


def test_record_from_a_virtual_bus_writes_raw_frames_too(capsys, tmp_path):
    channel = f"mkc-{uuid.uuid4().hex[:8]}"
    stop = threading.Event()
    th = threading.Thread(target=_virtual_sender, args=(channel, 500, stop), daemon=True)
    th.start()
    try:
        code = main(["record", "-i", "virtual", "-c", channel, "--max-samples", "400", "--out", str(tmp_path / "r.csv"),
                     "--quiet"])
    finally:
        stop.set()
        th.join()
    assert code == 0
    rec = read_recording(tmp_path / "r.csv")
    frames = list(can.LogReader(str(tmp_path / "r.log")))
    assert len(rec) == 400 and len(frames) >= 400
    with open_log(tmp_path / "r.log") as src:
        replayed = list(src)[:400]
    assert [s.mag for s in replayed] == [tuple(m) for m in rec.mag.tolist()]


def _emulator(*args):
    p = subprocess.Popen([sys.executable, "-m", "mkc_stream.ingest.emulator", *args, "--pty"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = p.stdout.readline().split()
    assert line and line[0] == "PTY", p.stderr.read()
    return p, line[1]


@pytest.mark.skipif(not hasattr(os, "openpty"), reason="the emulator needs a pty (POSIX)")
def test_live_through_slcan_on_a_pty(capsys):
    """python-can's slcan driver against a separate process that speaks slcan (the adapter code path)."""
    emu, pty = _emulator("--protocol", "slcan", "--rate", "500", "--duration", "30", "--sweep-s", "1.5")
    try:
        code = main(["live", "-i", "slcan", "-c", pty, "-b", "500000", "--bus-kwargs", "sleep_after_open=0",
                     "--max-samples", "1500", "--json", "-"])
    finally:
        emu.terminate()
        emu.communicate(timeout=10)
    obj = json.loads(capsys.readouterr().out)
    assert obj["counts"]["samples"] == 1500 and obj["counts"]["drops"] == 0 and obj["counts"]["bad_frames"] == 0
    assert obj["status"] == "accepted" and code == 0


@pytest.mark.skipif(not hasattr(os, "openpty"), reason="the emulator needs a pty (POSIX)")
def test_can_adapter_that_disappears_ends_cleanly(capsys, tmp_path):
    emu, pty = _emulator("--protocol", "slcan", "--rate", "500", "--duration", "2")
    code = main(["live", "-i", "slcan", "-c", pty, "--bus-kwargs", "sleep_after_open=0", "--out", str(tmp_path / "s.csv"),
                 "--json", "-"])
    emu.communicate(timeout=10)
    out = capsys.readouterr()
    obj = json.loads(out.out)
    assert code == 2 and obj["ended"] == "source lost" and "the run ended" in out.err
    assert len(read_recording(tmp_path / "s.csv")) == obj["counts"]["samples"] > 100


@pytest.mark.skipif(not os.environ.get("MKC_TEST_CAN_INTERFACE"), reason="set MKC_TEST_CAN_INTERFACE and "
                    "MKC_TEST_CAN_CHANNEL (and MKC_TEST_CAN_BITRATE) to test a real bus with an IMU on it")
def test_real_can_bus(capsys):
    argv = ["live", "-i", os.environ["MKC_TEST_CAN_INTERFACE"], "-c", os.environ["MKC_TEST_CAN_CHANNEL"],
            "--duration", os.environ.get("MKC_TEST_DURATION", "10"), "--json", "-"]
    if os.environ.get("MKC_TEST_CAN_BITRATE"):
        argv += ["-b", os.environ["MKC_TEST_CAN_BITRATE"]]
    if os.environ.get("MKC_TEST_CAN_ID"):
        argv += ["--can-id", os.environ["MKC_TEST_CAN_ID"]]
    code = main(argv)
    obj = json.loads(capsys.readouterr().out)
    assert code in (0, 1) and obj["counts"]["samples"] > 0 and obj["ended"] == "duration"
