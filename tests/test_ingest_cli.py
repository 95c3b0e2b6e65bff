"""live / record / replay end to end: a separate emulator process talks over a pty at a real rate."""
import json
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from mkc_stream.calib.synthetic import synthetic_mag
from mkc_stream.cli import main
from mkc_stream.ingest.emulator import CSV_COLUMNS, DeviceModel
from mkc_stream.io.recording import read_recording, write_recording

pytestmark = pytest.mark.skipif(not hasattr(os, "openpty"), reason="the emulator needs a pty (POSIX)")

TRUE_B = DeviceModel(0).hard_iron                     # the emulator's hard iron (seed 0)
DECODER = {"binary-mag": "binary", "binary-i16": "binary", "vnimu": "vectornav"}


def emulator(*args, link=None):
    cmd = [sys.executable, "-m", "mkc_stream.ingest.emulator", *args, "--pty"] + (["--link", link] if link else [])
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = p.stdout.readline().split()
    assert line and line[0] == "PTY", p.stderr.read()
    return p, line[1]


def stop(p):
    p.terminate()
    _, err = p.communicate(timeout=10)
    return err


def live_json(capsys, argv):
    code = main(argv + ["--json", "-"])
    out = capsys.readouterr()
    return code, json.loads(out.out), out.err


@pytest.mark.parametrize("proto", ["binary", "binary-mag", "binary-i16", "motioncal", "motioncal-uni", "csv",
                                   "vectornav", "vnimu"])
def test_live_every_serial_protocol_over_a_pty(capsys, proto):
    emu, pty = emulator("--protocol", proto, "--rate", "1000", "--duration", "30", "--sweep-s", "0.6")
    argv = ["live", "--port", pty, "--protocol", DECODER.get(proto, proto), "--max-samples", "1500"]
    if proto == "csv":        # the header went out before the port was opened, as after a device's boot
        argv += ["--columns", ",".join(CSV_COLUMNS)]
    try:
        code, obj, err = live_json(capsys, argv)
    finally:
        stop(emu)
    c = obj["counts"]
    assert c["samples"] == 1500 and c["bad_frames"] == 0 and c["drops"] == 0
    assert obj["ended"] == "max samples" and obj["cpu_percent"] > 0
    assert obj["time_source"] == ("device" if proto.startswith(("binary", "csv")) else "host")
    assert code == 0 and obj["status"] == "accepted", obj["reason"]
    assert np.allclose(obj["hard_iron"], TRUE_B, atol=0.5)
    assert "hard iron" in err                               # the human report went to stderr


def test_live_1khz_binary_loses_nothing_short(capsys, tmp_path):
    """The default-run version of the 60 s study: 3 s at 1 kHz, every frame arrives, CPU reported."""
    emu, pty = emulator("--protocol", "binary", "--rate", "1000", "--duration", "30", "--sweep-s", "1")
    try:
        code, obj, err = live_json(capsys, ["live", "--port", pty, "--protocol", "binary", "--max-samples", "3000",
                                            "--out", str(tmp_path / "r.csv")])
    finally:
        stop(emu)
    c = obj["counts"]
    assert c == {"samples": 3000, "bad_frames": 0, "drops": 0, "gaps": 0}
    assert obj["sample_rate_hz"] == pytest.approx(1000, rel=1e-6) and obj["ingest"]["resyncs"] == 0
    assert 2.5 < obj["elapsed_s"] < 6
    rec = read_recording(tmp_path / "r.csv")
    assert len(rec) == 3000 and np.all(np.diff(rec.aux["seq"]) == 1) and rec.meta["time_source"] == "device"
    print(f"\n1 kHz x 3 s over a pty: cpu {obj['cpu_percent']:.1f}%")


@pytest.mark.slow
def test_live_1khz_binary_60s_loses_nothing(capsys, tmp_path):
    emu, pty = emulator("--protocol", "binary", "--rate", "1000", "--duration", "120")
    try:
        code, obj, err = live_json(capsys, ["live", "--port", pty, "--protocol", "binary", "--max-samples", "60000",
                                            "--out", str(tmp_path / "r.csv")])
    finally:
        emu_err = stop(emu)
    c = obj["counts"]
    assert c == {"samples": 60000, "bad_frames": 0, "drops": 0, "gaps": 0}, (c, emu_err)
    assert 59 < obj["elapsed_s"] < 63 and len(read_recording(tmp_path / "r.csv")) == 60000
    print(f"\n1 kHz x 60 s over a pty: {c}, cpu of the live process {obj['cpu_percent']:.1f}%; {emu_err.strip()}")


def test_drops_and_corruption_are_counted_end_to_end(capsys, tmp_path):
    emu, pty = emulator("--protocol", "binary", "--rate", "1000", "--duration", "30", "--drop-every", "100",
                        "--corrupt", "0.002")
    try:
        code, obj, err = live_json(capsys, ["live", "--port", pty, "--protocol", "binary", "--max-samples", "2000",
                                            "--out", str(tmp_path / "r.csv")])
    finally:
        stop(emu)
    c = obj["counts"]
    seq = read_recording(tmp_path / "r.csv").aux["seq"]
    span = int(seq[-1] - seq[0]) + 1                          # frames the device generated meanwhile
    assert c["samples"] == 2000 and c["bad_frames"] > 0 and 15 <= c["drops"] <= 25
    assert c["samples"] + c["bad_frames"] + c["drops"] == span


def test_port_that_disappears_ends_cleanly_with_the_recording_intact(capsys, tmp_path):
    emu, pty = emulator("--protocol", "binary", "--rate", "500", "--duration", "2.5")
    code, obj, err = live_json(capsys, ["live", "--port", pty, "--protocol", "binary", "--out", str(tmp_path / "r.csv")])
    stop(emu)
    assert code == 2 and obj["ended"] == "source lost" and "disappeared" in obj["message"]
    assert "the run ended" in err and "r.csv" in err
    rec = read_recording(tmp_path / "r.csv")
    assert len(rec) == obj["counts"]["samples"] > 200 and rec.bad_rows == []


def test_ctrl_c_ends_cleanly_with_the_final_result(tmp_path):
    emu, pty = emulator("--protocol", "binary", "--rate", "1000", "--duration", "60", "--sweep-s", "0.6")
    live = subprocess.Popen([sys.executable, "-m", "mkc_stream", "live", "--port", pty, "--protocol", "binary",
                             "--out", str(tmp_path / "r.csv"), "--json", "-", "--progress"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONFAULTHANDLER": "1"})
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not (tmp_path / "r.csv").exists():
            time.sleep(0.1)                                     # the port is open once the recording exists
        time.sleep(1.5)
        live.send_signal(signal.SIGINT)
        try:
            out, err = live.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            live.send_signal(signal.SIGABRT)             # faulthandler prints every thread's stack
            out, err = live.communicate(timeout=30)
            pytest.fail(f"live still running 30 s after Ctrl-C; its stderr ends:\n{err[-6000:]}")
    finally:
        stop(emu)
    obj = json.loads(out)
    assert live.returncode == 0 and obj["ended"] == "interrupted" and obj["status"] == "accepted"
    assert " Hz  bad 0  drops 0" in err and "ACCEPTED" in err            # the status line, then the report
    assert len(read_recording(tmp_path / "r.csv")) == obj["counts"]["samples"] > 500


def test_reconnect_when_asked(tmp_path):
    link = str(tmp_path / "ttyEMU")
    emu1, _ = emulator("--protocol", "binary", "--rate", "1000", "--duration", "60", link=link)
    js = tmp_path / "r.json"
    result = {}
    th = threading.Thread(target=lambda: result.setdefault("code", main(
        ["live", "--port", link, "--protocol", "binary", "--reconnect", "--max-samples", "3000", "--json", str(js),
         "--quiet", "--out", str(tmp_path / "r.csv")])))
    th.start()
    time.sleep(2.0)
    stop(emu1)                                                  # unplugged ...
    time.sleep(0.5)
    emu2, _ = emulator("--protocol", "binary", "--rate", "1000", "--duration", "60", link=link)   # ... and back
    th.join(timeout=30)
    stop(emu2)
    assert not th.is_alive()
    obj = json.loads(js.read_text())
    assert obj["ended"] == "max samples" and obj["counts"]["samples"] == 3000
    assert obj["ingest"]["reconnects"] == 1 and obj["counts"]["gaps"] >= 1
    # the device restarted (its counter and clock began again): time goes on, the recording stays in order
    assert obj["ingest"]["time_resets"] == 1
    rec = read_recording(tmp_path / "r.csv")
    assert len(rec) == 3000 and rec.bad_rows == []


def test_replay_matches_calibrate_stream_and_reports_counts(capsys, tmp_path):
    s = synthetic_mag(seed=4, N=6000, burst_fraction=0.1)
    path = tmp_path / "rec.csv"
    write_recording(path, s.t, s.raw, meta={"units.mag": "uT"})
    code, obj, _ = live_json(capsys, ["replay", str(path), "--out", str(tmp_path / "copy.csv")])
    ref = json.loads((capsys.readouterr(), main(["calibrate", str(path), "--stream", "--json", "-", "--quiet"]),
                      capsys.readouterr().out)[2])
    assert code == 0 and obj["status"] == "accepted"
    assert obj["counts"] == ref["counts"] and obj["hard_iron"] == pytest.approx(ref["hard_iron"], abs=1e-9)
    assert obj["first_accepted_at_sample"] == ref["first_accepted_at_sample"]
    copy = read_recording(tmp_path / "copy.csv")
    assert copy.t.tolist() == s.t.tolist() and copy.mag.tolist() == s.raw.tolist()


def test_replay_realtime_takes_real_time(capsys, tmp_path):
    s = synthetic_mag(seed=5, N=200, rate_hz=100.0)                      # 2 s of samples
    path = tmp_path / "rec.csv"
    write_recording(path, s.t, s.raw)
    t0 = time.monotonic()
    code, obj, _ = live_json(capsys, ["replay", str(path), "--speed", "5"])
    assert 0.35 < time.monotonic() - t0 < 3 and obj["counts"]["samples"] == 200
    code, obj, _ = live_json(capsys, ["replay", str(path), "--duration", "0.5"])
    assert obj["counts"]["samples"] == 50 and obj["ended"] == "duration"


@pytest.mark.parametrize("argv, message", [
    (["live"], "no source"),
    (["live", "--port", "loop://"], "needs --protocol"),
    (["live", "--port", "loop://", "--protocol", "binary", "-i", "virtual"], "not both"),
    (["live", "--port", "/dev/no-such-port-mkc", "--protocol", "binary"], "cannot open serial port"),
    (["live", "--port", "loop://", "--protocol", "binary", "--can-id", "0x10"], "apply to CAN"),
    (["record", "-i", "virtual", "-c", "x", "--dbc", "nope.dbc", "--map", "mx=a,my=b,mz=c", "--out", "x.csv"], "nope.dbc"),
    (["replay", "missing.csv"], "no such file"),
    (["replay", "x.csv", "--speed", "0"], "--speed"),
])
def test_usage_errors(capsys, tmp_path, monkeypatch, argv, message):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_record_serial_then_replay(capsys, tmp_path):
    emu, pty = emulator("--protocol", "vectornav", "--rate", "200", "--duration", "30", "--sweep-s", "1")
    try:
        code = main(["record", "--port", pty, "--protocol", "vectornav", "--max-samples", "400",
                     "--out", str(tmp_path / "vn.csv.gz"), "--quiet"])
    finally:
        stop(emu)
    assert code == 0
    rec = read_recording(tmp_path / "vn.csv.gz")
    assert len(rec) == 400 and rec.meta["time_source"] == "host" and rec.meta["protocol"] == "vectornav"
    assert set(rec.aux) == {"ax", "ay", "az", "gx", "gy", "gz"}        # $VNYMR: no temperature
    code, obj, _ = live_json(capsys, ["replay", str(tmp_path / "vn.csv.gz")])
    assert obj["counts"]["samples"] == 400 and obj["time_source"] == "host"


@pytest.mark.skipif(not os.environ.get("MKC_TEST_SERIAL_PORT"), reason="set MKC_TEST_SERIAL_PORT (and "
                    "MKC_TEST_SERIAL_PROTOCOL, MKC_TEST_SERIAL_BAUD) to test a real device")
def test_real_serial_device(capsys):
    argv = ["live", "--port", os.environ["MKC_TEST_SERIAL_PORT"], "--protocol",
            os.environ.get("MKC_TEST_SERIAL_PROTOCOL", "motioncal"), "--baud", os.environ.get("MKC_TEST_SERIAL_BAUD",
                                                                                              "115200"),
            "--duration", os.environ.get("MKC_TEST_DURATION", "10")]
    code, obj, _ = live_json(capsys, argv)
    assert code in (0, 1) and obj["counts"]["samples"] > 0 and obj["ended"] == "duration"
