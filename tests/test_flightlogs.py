"""Flight and robot logs read as recordings (mkc_stream/ingest/flightlogs): PX4 ULog, ArduPilot
DataFlash, ROS 2 bag (stored real or generated logs in tests/data, each with its SOURCE.txt), and
hostile copies of them. The readers are the optional extra ``logs``: each test skips without its
library, and the ``test`` extra installs them."""
from __future__ import annotations

import json
import pathlib
import shutil

import numpy as np
import pytest

from mkc_stream.ingest.flightlogs import (FlightLogError, inspect_flight_log, is_flight_log, read_flight_log,
                                          sniff_format)
from mkc_stream.ingest.flightlogs._common import align

DATA = pathlib.Path(__file__).parent / "data"
ULOG_SMALL = DATA / "flightlog-pyulog-sample" / "sample_log_small.ulg"
ULOG_V19 = DATA / "flightlog-px4-ulog-rs" / "esc_status_log.ulg"
DATAFLASH = DATA / "flightlog-dronekit-log171" / "log171_excerpt.bin"
TLOG = DATA / "flightlog-tlog-from-log171" / "log171_excerpt.tlog"
ROS2_BAG = DATA / "rosbag-ck-explorer-ros2" / "ck_explorer_bag"
#: the command line takes files: a ROS 2 bag is named by a file in its folder
ROS2_FILE = ROS2_BAG / "ck_explorer_bag.mcap"
SHARED = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data"


def need(module):
    return pytest.importorskip(module, reason=f"{module} missing: pip install 'mkc-stream[logs]'")


def median_norm(rec):
    return float(np.median(np.linalg.norm(rec.mag, axis=1)))


# ----------------------------------------------------------------------------------------------
# format choice
# ----------------------------------------------------------------------------------------------

def test_format_by_suffix_and_content(tmp_path):
    assert sniff_format(ULOG_SMALL) == "ulog"
    assert sniff_format(DATAFLASH) == "dataflash"
    assert sniff_format(TLOG) == "tlog"
    assert sniff_format(ROS2_BAG) == "rosbag2"
    assert sniff_format(ROS2_BAG / "ck_explorer_bag.mcap") == "rosbag2"
    candump = tmp_path / "bus.log"
    candump.write_text("(1.000000) can0 110#0102030405060708\n")
    assert not is_flight_log(candump)                      # a candump .log stays a CAN log
    renamed = tmp_path / "flight.log"
    shutil.copy(DATAFLASH, renamed)
    assert sniff_format(renamed) == "dataflash"            # a DataFlash .log by its A3 95 head
    other = tmp_path / "firmware.bin"
    other.write_bytes(b"\x00" * 64)
    assert not is_flight_log(other)
    assert not is_flight_log(tmp_path / "rec.csv")


def test_align_interpolates_and_never_bridges_a_gap():
    ts = np.array([0.0, 1.0, 2.0, 10.0, 11.0])
    v = np.array([0.0, 10.0, 20.0, 100.0, 110.0])
    out = align(np.array([-1.0, 0.5, 1.5, 5.0, 10.5, 12.0]), ts, v)
    assert out[1] == pytest.approx(5.0) and out[2] == pytest.approx(15.0) and out[4] == pytest.approx(105.0)
    assert np.isnan(out[0]) and np.isnan(out[3]) and np.isnan(out[5])   # before, across the gap, after


# ----------------------------------------------------------------------------------------------
# PX4 ULog
# ----------------------------------------------------------------------------------------------

def test_ulog_instances_units_and_metadata():
    need("pyulog")
    info = inspect_flight_log(ULOG_SMALL)
    assert info["format"] == "PX4 ULog"
    assert [(i["id"], i["topic"], i["device_id"], i["samples"]) for i in info["instances"]] == [
        (0, "sensor_mag", 589858, 6), (1, "sensor_mag", 592905, 6)]
    r0, r1 = read_flight_log(ULOG_SMALL), read_flight_log(ULOG_SMALL, instance=1)
    assert r0.meta["mag.instance"] == "0" and r1.meta["mag.instance"] == "1"
    assert r1.meta["mag.device_id"] == "592905" and r1.meta["units.mag"] == "uT"
    assert not np.array_equal(r0.mag, r1.mag)
    # v1.11: the driver applied CAL_MAG1; undone: raw = m / scale + off, off in gauss x 100
    applied = json.loads(r1.meta["applied_calibration"])
    assert applied["slot"] == "CAL_MAG1" and applied["offset_uT"][1] == pytest.approx(55.55, abs=0.01)
    assert r1.meta["calibration"].startswith("raw:")
    assert 20 < median_norm(r1) < 100
    assert np.all(np.diff(r1.t) >= 0)
    assert {"qw", "qx", "qy", "qz", "current", "voltage", "lat", "lon", "alt"} <= set(r1.aux)
    assert r1.meta["param.CAL_MAG1_YOFF"].startswith("0.555")


def test_ulog_selector_in_the_path_and_bad_instance():
    need("pyulog")
    rec = read_flight_log(f"{ULOG_SMALL}#instance=1")
    assert rec.meta["mag.device_id"] == "592905"
    with pytest.raises(FlightLogError, match=r"no sensor_mag instance 5; instances: \[0, 1\]"):
        read_flight_log(ULOG_SMALL, instance=5)


def test_ulog_vehicle_magnetometer_when_there_is_no_sensor_mag():
    need("pyulog")
    rec = read_flight_log(ULOG_V19)
    assert rec.meta["mag.topic"] == "vehicle_magnetometer"
    assert len(rec) == 117
    assert 30 < median_norm(rec) < 70                           # 47 uT
    assert "not undone" in rec.meta["calibration"]              # SENS_BOARD_ROT=7: said, not guessed
    cur = rec.aux["current"]
    assert 20 < np.nanmax(cur) < 80                            # battery current, A
    esc = [rec.aux[f"current_esc{k}"] for k in range(4)]      # per-ESC current, A (four ESCs report)
    assert "current_esc4" not in rec.aux
    assert all(5 < np.nanmax(c) < 30 for c in esc)


# ----------------------------------------------------------------------------------------------
# ArduPilot DataFlash
# ----------------------------------------------------------------------------------------------

def test_dataflash_three_compasses_offsets_undone():
    need("pymavlink")
    info = inspect_flight_log(DATAFLASH)
    assert [(i["id"], i["topic"]) for i in info["instances"]] == [(0, "MAG"), (1, "MAG2"), (2, "MAG3")]
    assert all(650 < i["samples"] < 720 and 9 < i["rate_hz"] < 11 for i in info["instances"])
    rec = read_flight_log(DATAFLASH, instance=1)
    assert rec.meta["mag.topic"] == "MAG2" and rec.meta["units.mag"] == "uT"
    assert np.all(np.diff(rec.t) >= 0)
    # logged MAG2 = M (raw + ofs): undoing moves the mean by about -ofs (x0.1 uT per milligauss)
    logged_first = np.array([222, -5, -532]) * 0.1
    ofs = np.array([-141, -67, -255]) * 0.1
    assert np.allclose(rec.mag[0], logged_first - ofs, atol=3.0)
    assert 20 < median_norm(rec) < 100
    cur = rec.aux["current"]
    assert np.nanmin(cur) >= 0 and np.nanmax(cur) < 60        # centi-amps converted to A
    q = np.c_[rec.aux["qw"], rec.aux["qx"], rec.aux["qy"], rec.aux["qz"]]
    ok = np.all(np.isfinite(q), axis=1)
    assert ok.mean() > 0.9 and np.allclose(np.linalg.norm(q[ok], axis=1), 1.0)


def test_dataflash_corruption_is_counted_not_fatal(tmp_path):
    need("pymavlink")
    whole = read_flight_log(DATAFLASH)
    data = bytearray(DATAFLASH.read_bytes())
    cut = tmp_path / "cut.bin"
    cut.write_bytes(data[: len(data) // 2 + 7])
    half = read_flight_log(cut)
    assert 0 < len(half) < len(whole)
    np.testing.assert_array_equal(half.mag, whole.mag[: len(half)])   # every sample before the cut kept
    assert any(why.startswith("truncated") for _, why in half.bad_rows)
    flipped = tmp_path / "flipped.bin"
    rng = np.random.default_rng(1)
    for i in rng.choice(np.arange(20_000, len(data)), size=len(data) // 100, replace=False):
        data[i] ^= 0xFF
    flipped.write_bytes(bytes(data))
    rec = read_flight_log(flipped)
    assert len(rec) > 0.5 * len(whole)
    assert len(rec.bad_rows) > 0                                        # the damage is reported


# ----------------------------------------------------------------------------------------------
# ROS 2 bag
# ----------------------------------------------------------------------------------------------

def test_ros2_bag_by_type_and_by_topic():
    need("rosbags")
    rec = read_flight_log(ROS2_BAG)
    assert rec.meta["mag.topic"] == "/imu/mag" and rec.meta["format"] == "ROS 2 bag"
    assert len(rec) == 800 and np.all(np.diff(rec.t) > 0)
    assert 30 < median_norm(rec) < 70                                   # tesla x1e6
    assert np.nanmedian(np.linalg.norm(np.c_[rec.aux["ax"], rec.aux["ay"], rec.aux["az"]], axis=1)) == \
        pytest.approx(9.8, abs=0.5)
    same = read_flight_log(ROS2_BAG / "ck_explorer_bag.mcap", topic="/imu/mag")
    np.testing.assert_array_equal(same.mag, rec.mag)
    with pytest.raises(FlightLogError, match=r"/imu/data is sensor_msgs/msg/Imu, not a magnetometer"):
        read_flight_log(ROS2_BAG, topic="/imu/data")


def test_ros2_bag_without_a_magnetometer_lists_the_topics(tmp_path):
    need("rosbags")
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    Temp = ts.types["sensor_msgs/msg/Temperature"]
    hdr = ts.types["std_msgs/msg/Header"](stamp=ts.types["builtin_interfaces/msg/Time"](sec=1, nanosec=0),
                                          frame_id="x")
    with Writer(tmp_path / "bag", version=8, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection("/board/temp", Temp.__msgtype__, typestore=ts)
        w.write(c, 1_000_000_000, ts.serialize_cdr(Temp(header=hdr, temperature=25.0, variance=0.0),
                                                   Temp.__msgtype__))
    with pytest.raises(FlightLogError, match=r"no magnetometer topic .*/board/temp \(sensor_msgs/msg/Temperature\)"):
        read_flight_log(tmp_path / "bag")


# ----------------------------------------------------------------------------------------------
# hostile files, every format
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name,module", [("x.ulg", "pyulog"), ("x.px4log", "pymavlink"), ("x.bag", "rosbags")])
def test_empty_file_is_a_clear_error(tmp_path, name, module):
    path = tmp_path / name
    path.write_bytes(b"")
    with pytest.raises(FlightLogError, match="empty"):
        read_flight_log(path)


def test_ulog_cut_and_flipped(tmp_path):
    need("pyulog")
    data = bytearray(ULOG_V19.read_bytes())
    whole = read_flight_log(ULOG_V19)
    cut = tmp_path / "cut.ulg"
    cut.write_bytes(data[: len(data) // 2])
    try:
        half = read_flight_log(cut)
    except FlightLogError as exc:                                       # a clear error is allowed ...
        assert "cut.ulg" in str(exc)
    else:                                                               # ... or the samples before the cut
        assert 0 < len(half) < len(whole)
        np.testing.assert_array_equal(half.mag, whole.mag[: len(half)])
        assert any(why.startswith("truncated") for _, why in half.bad_rows)
    flipped = tmp_path / "flipped.ulg"
    rng = np.random.default_rng(2)
    for i in rng.choice(np.arange(4096, len(data)), size=len(data) // 100, replace=False):
        data[i] ^= 0xFF
    flipped.write_bytes(bytes(data))
    try:
        rec = read_flight_log(flipped)
    except FlightLogError as exc:
        assert "flipped.ulg" in str(exc)
    else:
        assert len(rec) + len(rec.bad_rows) > 0


ROS1_BAG = DATA / "rosbag-ck-explorer-ros1" / "ck_explorer.bag"


def test_ros1_bag_reads_as_the_ros2_bag_of_the_same_messages():
    need("rosbags")
    r1, r2 = read_flight_log(ROS1_BAG), read_flight_log(ROS2_BAG)
    assert r1.meta["format"] == "ROS 1 bag" and len(r1) == 800 and r1.mag_unit == "uT"
    np.testing.assert_array_equal(r1.mag, r2.mag)
    np.testing.assert_array_equal(r1.t, r2.t)


def test_ros1_bag_cut_keeps_every_message_before_the_cut(tmp_path):
    """rosbags needs the index at a ROS 1 bag's end; the salvage reader walks its (bz2) chunks."""
    need("rosbags")
    whole = read_flight_log(ROS1_BAG)
    data = ROS1_BAG.read_bytes()
    rng = np.random.default_rng(13)
    for cut in rng.integers(len(data) // 3, len(data) - 1, 10):
        path = tmp_path / "cut.bag"
        path.write_bytes(data[:cut])
        rec = read_flight_log(path)
        assert 0 < len(rec) <= len(whole)
        np.testing.assert_array_equal(rec.mag, whole.mag[: len(rec)])
        np.testing.assert_array_equal(rec.t, whole.t[: len(rec)])
        truncated = [why for _, why in rec.bad_rows if why.startswith("truncated")]
        assert len(truncated) == 1, (cut, rec.bad_rows)          # every cut file says so, once


def test_ros2_bag_cut_keeps_every_message_before_the_cut(tmp_path):
    need("rosbags")
    whole = read_flight_log(ROS2_BAG)
    data = (ROS2_BAG / "ck_explorer_bag.mcap").read_bytes()
    rng = np.random.default_rng(11)
    for cut in rng.integers(len(data) // 3, len(data) - 1, 10):
        bag = tmp_path / f"bag{cut}"
        shutil.copytree(ROS2_BAG, bag)
        (bag / "ck_explorer_bag.mcap").write_bytes(data[:cut])
        try:
            rec = read_flight_log(bag)
        except FlightLogError as exc:        # cut in the summary after the data: the bag still opens,
            raise AssertionError(f"cut at {cut}: {exc}") from None
        assert 0 < len(rec) <= len(whole)
        np.testing.assert_array_equal(rec.mag, whole.mag[: len(rec)])
        np.testing.assert_array_equal(rec.t, whole.t[: len(rec)])
        truncated = [why for _, why in rec.bad_rows if why.startswith("truncated")]
        assert len(truncated) <= 1 and (truncated or len(rec) == len(whole)), (cut, rec.bad_rows)


# ----------------------------------------------------------------------------------------------
# every command that takes a recording
# ----------------------------------------------------------------------------------------------

def run_cli(*args):
    from mkc_stream.cli import main
    return main([str(a) for a in args])


@pytest.mark.parametrize("log,module", [(DATAFLASH, "pymavlink"), (ROS2_FILE, "rosbags"),
                                        (f"{ULOG_SMALL}#instance=1", "pyulog")])
def test_calibrate_json_on_a_flight_log(tmp_path, log, module):
    need(module)
    out = tmp_path / "cal.json"
    code = run_cli("calibrate", log, "--json", out, "--quiet")
    obj = json.loads(out.read_text())
    assert code in (0, 1)
    assert obj["status"] in ("accepted", "rejected")
    assert obj["counts"]["samples"] == len(read_flight_log(log))
    if obj["status"] == "rejected":
        assert obj["reason"]
    else:
        assert 20 < obj["field"] < 100


def test_ros2_bag_calibrates_and_replays(tmp_path):
    need("rosbags")
    out = tmp_path / "cal.json"
    assert run_cli("calibrate", ROS2_FILE, "--json", out, "--quiet") == 0
    obj = json.loads(out.read_text())
    assert obj["status"] == "accepted" and 30 < obj["field"] < 70
    rep = tmp_path / "rep.json"
    run_cli("replay", ROS2_FILE, "--json", rep, "--quiet", "--out", tmp_path / "rec.csv")
    robj = json.loads(rep.read_text())
    assert robj["counts"]["samples"] == 800
    from mkc_stream.io.recording import read_recording
    back = read_recording(tmp_path / "rec.csv")
    np.testing.assert_array_equal(back.mag, read_flight_log(ROS2_BAG).mag)  # the round trip is bit-identical


def test_round_trip_through_the_recording_file(tmp_path):
    need("pymavlink")
    rec = read_flight_log(DATAFLASH, instance=2)
    rec.write(tmp_path / "mag3.csv")
    from mkc_stream.io.recording import read_recording
    back = read_recording(tmp_path / "mag3.csv")
    np.testing.assert_array_equal(back.mag, rec.mag)
    np.testing.assert_array_equal(back.t, rec.t)
    assert back.meta["mag.topic"] == "MAG3"


def test_stream_diagnose_crosscheck_accept_a_flight_log(tmp_path):
    need("rosbags")
    assert run_cli("calibrate", ROS2_FILE, "--stream", "--json", tmp_path / "s.json", "--quiet") in (0, 1)
    assert json.loads((tmp_path / "s.json").read_text())["counts"]["samples"] == 800
    from mkc_stream.commands.common import load_recording
    assert len(load_recording(str(ROS2_FILE))) == 800


@pytest.mark.skipif(not (SHARED / "flightlog-pyulog-sample" / "sample.ulg").exists(), reason="shared data absent")
def test_attitude_and_undone_offsets_agree_on_the_field_in_ned():
    """The old-PX4 sample.ulg: sensor_combined magnetometer, CAL_MAG0 offsets undone; rotating the
    calibrated field (raw + b) into north-east-down with vehicle_attitude gives one constant
    vector: the quaternion convention (body -> NED) and the frames agree."""
    need("pyulog")
    rec = read_flight_log(SHARED / "flightlog-pyulog-sample" / "sample.ulg")
    off = np.array(json.loads(rec.meta["applied_calibration"])["offset_uT"])
    m = rec.mag - off
    q = np.c_[rec.aux["qw"], rec.aux["qx"], rec.aux["qy"], rec.aux["qz"]]
    ok = np.all(np.isfinite(q), axis=1)
    w, x, y, z = q[ok].T
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]).transpose(2, 0, 1)
    ned = np.einsum("nij,nj->ni", R, m[ok])
    assert np.all(ned.std(axis=0) < 2.0)                                # uT
    assert 40 < np.linalg.norm(ned.mean(axis=0)) < 60 and ned.mean(axis=0)[2] > 0   # down: northern hemisphere


@pytest.mark.parametrize("log,module,cuts", [(ULOG_V19, "pyulog", 10), (ULOG_SMALL, "pyulog", 10),
                                             (DATAFLASH, "pymavlink", 10), (TLOG, "pymavlink", 10)])
def test_random_cuts_keep_every_sample_before_the_cut(tmp_path, log, module, cuts):
    need(module)
    whole = read_flight_log(log)
    data = log.read_bytes()
    rng = np.random.default_rng(7)
    for cut in rng.integers(len(data) // 3, len(data) - 1, cuts):
        path = tmp_path / f"cut{log.suffix}"
        path.write_bytes(data[:cut])
        rec = read_flight_log(path)
        assert len(rec) <= len(whole)
        np.testing.assert_array_equal(rec.mag, whole.mag[: len(rec)])
        np.testing.assert_array_equal(rec.t, whole.t[: len(rec)])
        truncated = [why for _, why in rec.bad_rows if why.startswith("truncated")]
        assert len(truncated) == 1, (cut, rec.bad_rows)


def test_a_dataflash_log_cut_after_a_message_header_is_truncated(tmp_path):
    """A cut that leaves only the 3-byte header (A3 95, type) of the last message: pymavlink's parser
    steps over the header before it finds the body missing, so its offset is the file's end. Found by
    random cuts (6 of 100 landed there, one inside a MAG message): the loss was silent before."""
    need("pymavlink")
    data = DATAFLASH.read_bytes()
    path = tmp_path / "cut.bin"
    start = data.index(b"\xa3\x95", len(data) // 2)
    while True:                       # a real message start: cutting there is a clean end
        path.write_bytes(data[:start])
        if not read_flight_log(path).bad_rows:
            break
        start = data.index(b"\xa3\x95", start + 1)
    path.write_bytes(data[:start + 3])
    rec = read_flight_log(path)
    assert rec.bad_rows == [(start, f"truncated: the log ends inside its last message (3 bytes left over "
                                     f"at byte {start})")]


def test_ulog_logger_dropouts_are_in_the_metadata():
    need("pyulog")
    assert read_flight_log(ULOG_SMALL).meta["logger_dropouts"].startswith("1 (30 ms")
    assert read_flight_log(ULOG_V19).meta["logger_dropouts"].startswith("0 ")


def test_dataflash_instance_on_the_command_line(tmp_path):
    need("pymavlink")
    out = tmp_path / "rep.json"
    run_cli("replay", f"{DATAFLASH}#instance=2", "--json", out, "--quiet", "--out", tmp_path / "mag3.csv")
    from mkc_stream.io.recording import read_recording
    back = read_recording(tmp_path / "mag3.csv")
    np.testing.assert_array_equal(back.mag, read_flight_log(DATAFLASH, instance=2).mag)
    assert json.loads(out.read_text())["counts"]["samples"] == len(back)


def test_missing_library_names_the_extra(monkeypatch, tmp_path):
    import builtins

    real = builtins.__import__

    def no_rosbags(name, *args, **kwargs):
        if name.startswith("rosbags"):
            raise ImportError("no rosbags here")
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_rosbags)
    with pytest.raises(ImportError, match=r'pip install "mkc-stream\[ros\]"'):
        read_flight_log(ROS2_BAG)


@pytest.mark.skipif(not (SHARED / "flightlog-px4tools-px4log").exists(), reason="shared data absent")
def test_px4log_magnetometer_temperature_and_current():
    need("pymavlink")
    rec = read_flight_log(SHARED / "flightlog-px4tools-px4log" / "01_07_59.px4log")
    assert rec.meta["format"] == "PX4 sdlog2 px4log"
    assert len(rec) == 5664 and 75 < (len(rec) - 1) / (rec.t[-1] - rec.t[0]) < 85     # 80 Hz
    assert 40 < median_norm(rec) < 70
    assert 20 < np.nanmedian(rec.aux["temp"]) < 40 and 40 < np.nanmax(rec.aux["current"]) < 60
    assert "not undone" in rec.meta["calibration"]                      # two CAL_MAG slots in use


@pytest.mark.skipif(not (SHARED / "rosbag-plotjuggler").exists(), reason="shared data absent")
def test_ros1_bag_vector3_has_no_unit():
    need("rosbags")
    rec = read_flight_log(SHARED / "rosbag-plotjuggler" / "tilt_laser.bag")
    assert rec.meta["format"] == "ROS 1 bag" and rec.meta["mag.topic"] == "/magnetic_vector"
    assert rec.meta["units.mag"] == "raw" and "no unit" in rec.meta["mag.unit_in_log"]
    assert len(rec) == 356


# ----------------------------------------------------------------------------------------------
# MAVLink telemetry log (generated from the DataFlash excerpt: the two must agree)
# ----------------------------------------------------------------------------------------------

def test_tlog_agrees_with_the_dataflash_log_it_was_made_from():
    need("pymavlink")
    info = inspect_flight_log(TLOG)
    assert [(i["id"], i["topic"], i["samples"]) for i in info["instances"]] == [(0, "RAW_IMU", 706),
                                                                               (1, "SCALED_IMU2", 706)]
    for k in (0, 1):
        tl, df = read_flight_log(TLOG, instance=k), read_flight_log(DATAFLASH, instance=k)
        assert tl.meta["calibration"].startswith("raw:")
        np.testing.assert_allclose(tl.t, df.t, rtol=0, atol=1e-9)          # us and ms clocks
        # the .tlog undoes the float COMPASS_OFS parameters, the DataFlash the integer OfsX logged
        np.testing.assert_allclose(tl.mag, df.mag, atol=0.11)          # uT
        # SYS_STATUS has no boot time: it is placed by the receive times (a sample at the very edge
        # of its span may fall out, by float rounding of the 1.43e9 s receive clock)
        a, b = tl.aux["current"], df.aux["current"]
        both = np.isfinite(a) & np.isfinite(b)
        assert both.sum() >= np.isfinite(b).sum() - 2
        np.testing.assert_allclose(a[both], b[both], atol=0.01)
        np.testing.assert_allclose(tl.aux["qw"], df.aux["qw"], atol=1e-6, equal_nan=True)


def test_tlog_damage_is_counted(tmp_path):
    need("pymavlink")
    whole = read_flight_log(TLOG)
    data = bytearray(TLOG.read_bytes())
    cut = tmp_path / "cut.tlog"
    cut.write_bytes(data[: len(data) // 2 + 5])
    half = read_flight_log(cut)
    assert 0 < len(half) < len(whole)
    np.testing.assert_array_equal(half.mag, whole.mag[: len(half)])
    flipped = tmp_path / "flipped.tlog"
    rng = np.random.default_rng(3)
    for i in rng.choice(np.arange(5000, len(data)), size=len(data) // 100, replace=False):
        data[i] ^= 0xFF
    flipped.write_bytes(bytes(data))
    rec = read_flight_log(flipped)
    assert 0.3 * len(whole) < len(rec) < len(whole)
    assert sum(why.startswith("corrupt") for _, why in rec.bad_rows) > 10   # every frame with a bad CRC


@pytest.mark.parametrize("name,module,says", [("x.ulg", "pyulog", "cannot read ULog"),
                                              ("x.px4log", "pymavlink", "does not start with the message header"),
                                              ("x.tlog", "pymavlink", "no magnetometer message"),
                                              ("x.bag", "rosbags", "cannot read the bag"),
                                              ("x.mcap", "rosbags", "cannot read the bag")])
def test_random_bytes_are_a_clear_error(tmp_path, name, module, says):
    need(module)
    path = tmp_path / name
    path.write_bytes(np.random.default_rng(4).integers(0, 256, 50_000, dtype=np.uint8).tobytes())
    with pytest.raises(FlightLogError, match=says):
        read_flight_log(path)
