"""``mkc-stream inspect`` on every log format in tests/data, and the round trip log -> recording
CSV -> read back, bit for bit."""
import json
import pathlib

import numpy as np
import pytest

from mkc_stream.cli import main
from mkc_stream.io.recording import bundled_recording_path, read_recording

DATA = pathlib.Path(__file__).parent / "data"
DATAFLASH = DATA / "flightlog-dronekit-log171" / "log171_excerpt.bin"
TLOG = DATA / "flightlog-tlog-from-log171" / "log171_excerpt.tlog"
ULOG = DATA / "flightlog-pyulog-sample" / "sample_log_small.ulg"
ULOG_ESC = DATA / "flightlog-px4-ulog-rs" / "esc_status_log.ulg"
BAG = DATA / "rosbag-ck-explorer-ros2" / "ck_explorer_bag"
RECORDING = bundled_recording_path()             # the QMC5883L demo recording
SPEC_KEYS = {"id", "samples", "rate_hz", "duration_s", "aux", "applied_calibration"}

# (path, extra needed, format, instances)
CASES = [(DATAFLASH, "pymavlink", "dataflash", 3), (TLOG, "pymavlink", "tlog", 2), (ULOG, "pyulog", "ulog", 2),
         (ULOG_ESC, "pyulog", "ulog", 1), (BAG, "rosbags", "rosbag2", 1),
         (BAG / "ck_explorer_bag.mcap", "rosbags", "mcap", 1), (RECORDING, None, "recording", 1)]


def inspect_json(capsys, path):
    code = main(["inspect", str(path), "--json", "-"])
    out = capsys.readouterr()
    return code, json.loads(out.out), out.err


@pytest.mark.parametrize("path,lib,fmt,n", CASES, ids=[c[2] + "-" + c[0].name for c in CASES])
def test_inspect_gives_the_format_and_every_instance(capsys, path, lib, fmt, n):
    if lib:
        pytest.importorskip(lib)
    code, obj, err = inspect_json(capsys, path)
    assert code == 0 and obj["format"] == fmt and len(obj["instances"]) == n
    for k, inst in enumerate(obj["instances"]):
        assert SPEC_KEYS <= set(inst) and isinstance(inst["id"], str)
        assert inst["samples"] > 0 and inst["rate_hz"] > 0 and inst["duration_s"] > 0
    assert f"{n} magnetometer instance" in err          # the human report goes to stderr with --json -


def test_inspect_matches_the_recording_each_id_reads(capsys):
    pytest.importorskip("pymavlink")
    from mkc_stream.ingest.flightlogs import read_flight_log

    _, obj, _ = inspect_json(capsys, DATAFLASH)
    for inst in obj["instances"]:
        rec = read_flight_log(f"{DATAFLASH}#instance={inst['id']}")
        assert len(rec) == inst["samples"] and sorted(rec.aux) == inst["aux"]
    assert obj["instances"][0]["applied_calibration"]["matrix"][0][0] == pytest.approx(0.99573, abs=1e-5)


@pytest.mark.parametrize("content,why", [(b"", "empty"), (b"\xa3\x95" + bytes(range(256)) * 4, "cannot read"),
                                         (b"not,a,recording\n1,2\n", "cannot read")])
def test_a_bad_file_is_exit_2_with_a_clear_message(tmp_path, capsys, content, why):
    pytest.importorskip("pymavlink")
    f = tmp_path / ("bad.bin" if content.startswith(b"\xa3") else "bad.csv" if content else "bad.tlog")
    f.write_bytes(content)
    assert main(["inspect", str(f)]) == 2
    err = capsys.readouterr().err
    assert str(f) in err and why in err and "Traceback" not in err


def test_a_missing_file_and_a_can_log_are_exit_2(tmp_path, capsys):
    assert main(["inspect", str(tmp_path / "nope.ulg")]) == 2
    assert "no such file" in capsys.readouterr().err
    can = tmp_path / "bus.log"
    can.write_text("(1.0) can0 110#0102030405060708\n")
    assert main(["inspect", str(can)]) == 2
    assert "CAN log" in capsys.readouterr().err


# ---- round trip: a log written as a recording CSV and read back is the log's Recording, bit for bit


def same(a, b):
    return np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)


ROUND_TRIP = [(DATAFLASH, "pymavlink"), (f"{DATAFLASH}#instance=1", "pymavlink"), (TLOG, "pymavlink"),
              (ULOG, "pyulog"), (ULOG_ESC, "pyulog"), (BAG, "rosbags")]


@pytest.mark.parametrize("path,lib", ROUND_TRIP, ids=["dataflash", "dataflash-1", "tlog", "ulog", "ulog-esc", "ros2"])
def test_a_log_written_as_a_recording_reads_back_bit_identical(tmp_path, path, lib):
    pytest.importorskip(lib)
    from mkc_stream.ingest.flightlogs import read_flight_log

    rec = read_flight_log(path)
    back = read_recording(rec.write(tmp_path / "rec.csv"))
    assert same(back.t, rec.t) and same(back.mag, rec.mag) and back.aux.keys() == rec.aux.keys()
    assert all(same(back.aux[k], rec.aux[k]) for k in rec.aux)


def test_replay_out_writes_the_log_bit_identical(tmp_path, capsys):
    pytest.importorskip("pymavlink")
    from mkc_stream.ingest.flightlogs import read_flight_log

    out = tmp_path / "replayed.csv"
    log = f"{DATAFLASH}#instance=1"
    assert main(["replay", log, "--out", str(out), "--quiet", "--window", "64"]) in (0, 1)
    rec, back = read_flight_log(log), read_recording(out)
    assert same(back.t, rec.t) and same(back.mag, rec.mag)
    assert set(rec.aux) <= set(back.aux) and all(same(back.aux[k], rec.aux[k]) for k in rec.aux)
