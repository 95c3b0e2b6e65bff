"""Hostile input at the command line: absurd arguments, unwritable outputs, unreadable
inputs, a closed pipe, a log with a pause of hours, a source faster than the calibrator.

Every case asserts the exit-code contract (0 ok, 1 rejected/mismatch, 2 usage error, unreadable
input or unwritable result, 130 interrupted, 141 closed pipe) and the class of the message.
"""
import io
import json
import math
import os
import pathlib
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from mkc_stream.calib.synthetic import synthetic_mag
from mkc_stream.cli import main
from mkc_stream.commands import calibrate as calibrate_command
from mkc_stream.commands import common
from mkc_stream.ingest.live import Run
from mkc_stream.ingest.threaded import QueuedReader
from mkc_stream.ingest.pacing import FakeClock, Paced
from mkc_stream.ingest.sample import Sample
from mkc_stream.ingest.source import BaseSource
from mkc_stream.io.recording import write_recording


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("hostile")
    s = synthetic_mag(seed=1, N=2000)
    write_recording(d / "good.csv", s.t, s.raw, meta={"units.mag": "uT"})
    (d / "header_only.csv").write_text("t,mx,my,mz\n")
    s5 = synthetic_mag(seed=1, N=5)
    write_recording(d / "five.csv", s5.t, s5.raw)
    (d / "all_bad.csv").write_text("t,mx,my,mz\n" + "".join(f"{i},x,y,z\n" for i in range(2000)))
    t = s.t[:300].copy()
    t[150:] += 1e6                                   # a clock that jumps by 11 days
    write_recording(d / "jump.csv", t, s.raw[:300])
    (d / "existing.csv").write_text("t,mx,my,mz\n0,1,2,3\n")
    (d / "garbage.csv").write_bytes(bytes(range(256)) * 40)
    (d / "a_file").write_text("x")
    return d


def run(capsys, argv):
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


# (argv with {d} for the fixture directory, exit code, fragment of the stderr message)
CASES = [
    # 1. unwritable outputs are refused before the work
    (["calibrate", "{d}/good.csv", "--json", "{d}/no/such/dir/x.json"], 2, "does not exist"),
    (["calibrate", "{d}/good.csv", "--plot", "{d}/no/x.png"], 2, "does not exist"),
    (["calibrate", "{d}/good.csv", "--json", "{d}"], 2, "is a directory"),
    (["diagnose", "{d}/good.csv", "--json", "{d}/no/x.json"], 2, "does not exist"),
    (["diagnose", "{d}/good.csv", "--report", "{d}/a_file/sub"], 2, "is not a directory"),
    (["replay", "{d}/good.csv", "--json", "{d}/no/x.json"], 2, "does not exist"),
    (["live", "--port", "loop://", "--protocol", "binary", "--json", "{d}/no/x.json"], 2, "does not exist"),
    (["crosscheck", "{d}/good.csv", "--json", "{d}/no/x.json"], 2, "does not exist"),
    # 1. absurd sizes and counts
    (["calibrate", "{d}/good.csv", "--stream", "--window", "100000000"], 2, "outside 16..65536"),
    (["calibrate", "{d}/good.csv", "--stream", "--window", "8"], 2, "outside 16..65536"),
    (["calibrate", "{d}/good.csv", "--stream", "--estep-every", "0"], 2, "less than 1"),
    (["replay", "{d}/good.csv", "--window", "100000"], 2, "outside 16..65536"),
    (["crosscheck", "{d}/good.csv", "--window", "100000"], 2, "outside 16..65536"),
    (["diagnose", "{d}/good.csv", "--replicas", "0"], 2, "less than 2"),
    (["diagnose", "{d}/good.csv", "--seed", "-1"], 2, "less than 0"),
    (["simulate", "--duration", "inf", "--out", "{d}/s.csv"], 2, "not a finite number"),
    (["simulate", "--duration", "1e9", "--out", "{d}/s.csv"], 2, "at most 2,000,000"),
    (["simulate", "--rate", "0", "--out", "{d}/s.csv"], 2, "must be > 0"),
    # 1. unreadable inputs
    (["calibrate", "/dev/zero"], 2, "is a device"),
    (["calibrate", "{d}"], 2, "is a directory"),
    (["calibrate", "{d}/garbage.csv"], 2, "cannot read"),
    (["calibrate", "{d}/missing.csv"], 2, "cannot read"),
    (["diagnose", "/dev/zero"], 2, "is a device"),
    (["replay", "/dev/zero"], 2, "is a device"),
    # 3. simulate never writes a NaN or emptied recording
    (["simulate", "--noise", "nan", "--out", "{d}/s.csv"], 2, "not a finite number"),
    (["simulate", "--hard-iron", "nan,1,2", "--out", "{d}/s.csv"], 2, "not a finite number"),
    (["simulate", "--hard-iron", "1,2", "--out", "{d}/s.csv"], 2, "three numbers"),
    (["simulate", "--field", "inf", "--out", "{d}/s.csv"], 2, "not a finite number"),
    (["simulate", "--field", "0", "--out", "{d}/s.csv"], 2, "must be > 0"),
    (["simulate", "--bursts", "1.5", "--out", "{d}/s.csv"], 2, "must be <= 1"),
    (["simulate", "--effect", "sample_drops:fraction=1.5", "--out", "{d}/s.csv"], 2, "out of range"),
    (["simulate", "--effect", "sample_drops:fraction=1", "--out", "{d}/s.csv"], 2, "out of range"),
    (["simulate", "--effect", "saturation:limit=0", "--out", "{d}/s.csv"], 2, "out of range"),
    (["simulate", "--effect", "quantization:lsb=-0.1", "--out", "{d}/s.csv"], 2, "out of range"),
    (["simulate", "--effect", "latency:delay=nan", "--out", "{d}/s.csv"], 2, "not a finite number"),
    (["simulate", "--effect", "colored_noise:tau=-1", "--out", "{d}/s.csv"], 2, "out of range"),
    (["simulate", "--duration", "20", "--effect", "sample_drops:fraction=0.999", "--out", "{d}/s.csv"], 2,
     "kept 1 sample(s) of 1000; nothing written"),
    # 3. --out never replaces its input, nor (without --force) any file
    (["replay", "{d}/good.csv", "--out", "{d}/good.csv"], 2, "is the input file"),
    (["replay", "{d}/good.csv", "--out", "{d}/../{dn}/good.csv", "--force"], 2, "is the input file"),
    (["replay", "{d}/good.csv", "--out", "{d}/existing.csv"], 2, "already exists; give --force"),
    (["simulate", "--duration", "2", "--out", "{d}/existing.csv"], 2, "already exists; give --force"),
    (["simulate", "--trajectory", "recording:{d}/good.csv", "--out", "{d}/good.csv", "--force"], 2,
     "is the input file"),
    (["live", "--port", "loop://", "--protocol", "binary", "--out", "{d}/existing.csv"], 2, "already exists"),
    (["record", "--port", "loop://", "--protocol", "binary", "--out", "{d}/existing.csv"], 2, "already exists"),
    # 4. misleading arguments
    (["replay", "{d}/good.csv", "--max-samples", "-5"], 2, "less than 1"),
    (["replay", "{d}/good.csv", "--max-samples", "0"], 2, "less than 1"),
    (["replay", "{d}/good.csv", "--duration", "nan"], 2, "not a finite number"),
    (["replay", "{d}/good.csv", "--duration", "-1"], 2, "must be > 0"),
    (["replay", "{d}/good.csv", "--speed", "nan"], 2, "not a finite number"),
    (["replay", "{d}/good.csv", "--speed", "0"], 2, "must be > 0"),
    (["replay", "{d}/good.csv", "--can-id", "0x1000000000"], 2, "29-bit"),
    (["replay", "{d}/good.csv", "--can-id", "-1"], 2, "not a CAN id"),
    (["live", "-i", "virtual", "-c", "x", "--can-id", "0x20000000"], 2, "not a CAN id"),
    (["live", "--port", "loop://", "--protocol", "binary", "--baud", "0"], 2, "less than 1"),
    (["live", "--port", "loop://", "--protocol", "binary", "--duration", "inf"], 2, "not a finite number"),
    # 4. a comparison that was not made is not OK
    (["crosscheck", "{d}/header_only.csv"], 2, "nothing was compared"),
    (["crosscheck", "{d}/five.csv"], 2, "nothing was compared"),
    # 4. what the reader skipped is part of the reason
    (["diagnose", "{d}/all_bad.csv"], 2, "2000 bad rows were skipped"),
]


@pytest.mark.parametrize("argv, code, fragment", CASES, ids=[" ".join(c[0])[:60] for c in CASES])
def test_hostile_arguments(capsys, files, argv, code, fragment):
    if argv[0] == "crosscheck":
        from mkc_stream import cport

        if cport.toolchain_problem():
            pytest.skip("no C toolchain")
    argv = [a.format(d=files, dn=files.name) for a in argv]
    before = {p.name: p.stat().st_mtime_ns for p in files.iterdir()}
    got, out, err = run(capsys, argv)
    assert got == code, err
    assert fragment in err
    assert err.startswith("mkc-stream: error:") and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1                      # one clear line
    assert {p.name: p.stat().st_mtime_ns for p in files.iterdir()} == before     # nothing written


def test_help_and_bad_command_exit_codes(capsys):
    assert main(["--help"]) == 0
    assert main(["calibrat"]) == 2 and "invalid choice" in capsys.readouterr().err
    assert main([]) == 2


# --- a result is never lost ---------------------------------------------------------------------

def test_result_is_printed_when_its_file_cannot_be_written(capsys, files):
    """/dev/full passes every up-front check and fails at the write (a disk that filled meanwhile)."""
    code, out, err = run(capsys, ["calibrate", files / "good.csv", "--json", "/dev/full", "--quiet"])
    assert code == 2 and "cannot write /dev/full" in err and "printed to stdout" in err
    assert json.loads(out)["status"] == "accepted"
    code, out, err = run(capsys, ["replay", files / "good.csv", "--json", "/dev/full", "--quiet"])
    assert code == 2 and "printed to stdout" in err
    assert json.loads(out)["counts"]["samples"] == 2000


def test_a_failing_plot_does_not_take_the_json_with_it(capsys, files, tmp_path, monkeypatch):
    pytest.importorskip("matplotlib")
    import mkc_stream.plots

    def disk_full(raw, fit, path, title=""):            # the plot's directory passed the check, then filled up
        raise OSError(28, "No space left on device", str(path))

    monkeypatch.setattr(mkc_stream.plots, "plot_calibration", disk_full)
    js = tmp_path / "r.json"
    png = tmp_path / "fit.png"
    code, out, err = run(capsys, ["calibrate", files / "good.csv", "--json", js, "--plot", png, "--quiet"])
    assert code == 2 and f"cannot write {png}: No space left on device" in err and "Traceback" not in err
    assert json.loads(js.read_text())["status"] == "accepted"


def test_force_overwrites_and_the_file_is_the_replay(capsys, files, tmp_path):
    out_csv = tmp_path / "copy.csv"
    out_csv.write_text("t,mx,my,mz\n0,1,2,3\n")
    code, _, err = run(capsys, ["replay", files / "good.csv", "--out", out_csv, "--force", "--quiet"])
    assert code == 0, err
    from mkc_stream.io.recording import read_recording

    assert len(read_recording(out_csv)) == 2000
    code, out, err = run(capsys, ["simulate", "--duration", "4", "--rate", "25", "--out", out_csv, "--force"])
    assert code == 0 and len(read_recording(out_csv)) == 100


@pytest.mark.parametrize("exc, code, fragment", [
    (OSError(5, "Input/output error", "/dev/ttyX"), 2, "/dev/ttyX: Input/output error"),
    (MemoryError(), 2, "out of memory"),
    (BrokenPipeError(32, "Broken pipe"), 141, None),
    (KeyboardInterrupt(), 130, "interrupted"),
])
def test_top_level_handler_maps_the_environment_to_exit_codes(capsys, monkeypatch, exc, code, fragment):
    def boom(args):
        raise exc

    monkeypatch.setattr(calibrate_command, "cmd_methods", boom)
    got, _, err = run(capsys, ["methods"])
    assert got == code and "Traceback" not in err
    if fragment is None:
        assert err == ""                                          # a closed pipe is quiet
    else:
        assert fragment in err


@pytest.mark.parametrize("argv", [["calibrate", "{rec}"], ["methods"]])
def test_closed_pipe_is_quiet_with_exit_141(files, argv):
    """`mkc-stream ... | head -1` once head has gone: a real pipe whose reader closed before the
    output came (before: a BrokenPipeError traceback and exit 1)."""
    p = subprocess.Popen([sys.executable, "-m", "mkc_stream"] + [a.format(rec=files / "good.csv") for a in argv],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    p.stdout.close()
    err = p.stderr.read().decode()
    assert p.wait(timeout=120) == 141, err
    assert err == ""


# --- diagnose: the reason names the cause ------------------------------------------------------

def test_diagnose_singular_fit_names_the_geometry(capsys, files, monkeypatch):
    import mkc_stream.diagnose as D

    def singular(*a, **k):
        raise np.linalg.LinAlgError("Singular matrix")

    monkeypatch.setattr(D, "diagnose", singular)
    code, _, err = run(capsys, ["diagnose", files / "good.csv"])
    assert code == 2 and "does not span the sphere" in err and "Traceback" not in err


def test_diagnose_planar_recording_is_refused_clearly(capsys, tmp_path):
    ang = np.linspace(0, 6 * np.pi, 2000)
    mag = np.stack([30 * np.cos(ang), 30 * np.sin(ang), np.full_like(ang, 20.0)], 1)
    write_recording(tmp_path / "flat.csv", np.arange(2000) / 50, mag)
    code, _, err = run(capsys, ["diagnose", tmp_path / "flat.csv", "--quiet"])
    assert code == 2 and err.startswith("mkc-stream: error:") and "Singular matrix" not in err


# --- crosscheck: no "OK" without a comparison ---------------------------------------------------

def test_crosscheck_float_on_collinear_data_is_not_ok(capsys, tmp_path):
    from mkc_stream import cport

    if cport.toolchain_problem():
        pytest.skip("no C toolchain")
    rng = np.random.default_rng(0)
    x = np.linspace(-1, 1, 1200)[:, None] * np.array([[30.0, 20.0, 10.0]]) + 5.0 + 0.1 * rng.normal(size=(1200, 3))
    write_recording(tmp_path / "line.csv", np.arange(1200) / 50, x)
    js = tmp_path / "cc.json"
    code, out, err = run(capsys, ["crosscheck", tmp_path / "line.csv", "--precision", "float", "--window", "256",
                                 "--json", js])
    assert code == 2 and "nothing was compared" in err and "no well-posed checkpoint" in err
    assert "NOT COMPARED" in out and "status        : OK" not in out
    res = json.loads(js.read_text())["results"]["float"]
    assert res["compared"] is False and res["ok"] is False and res["teacher_forced"]["checkpoints"] == 0


# --- replay --realtime across a clock jump ------------------------------------------------------

def test_realtime_replay_shortens_a_huge_time_step_and_reports_it(capsys, files):
    t0 = time.monotonic()
    code, out, err = run(capsys, ["replay", files / "jump.csv", "--speed", "10", "--json", "-", "--quiet"])
    took = time.monotonic() - t0
    obj = json.loads(out)
    assert obj["counts"]["samples"] == 300 and obj["ended"] == "end of stream"
    assert obj["ingest"]["paced_long_steps"] == 1
    assert obj["ingest"]["paced_skipped_s"] == pytest.approx(1e5 - 1.0, rel=1e-3)   # 1e6 s at 10x, less 1 s
    assert took < 30                                    # before: waited 1e5 s (the probe hung)


def test_paced_caps_each_step_and_repaces_after_a_backward_jump():
    t = [0.0, 0.1, 0.2, 5000.2, 5000.3, 10.0, 10.1, 10.2]
    src = _ListSource([Sample(x, (1.0, 2.0, 3.0)) for x in t])
    fc = FakeClock()
    paced = Paced(src, speed=1.0, clock=fc.now, sleep=fc.sleep, max_step_s=1.0)
    released = []
    while not paced.eof:
        released += [(fc.now(), s.t) for s in paced.read(0.5)]
    assert [x for _, x in released] == t
    assert paced.long_steps == 1 and paced.skipped_s == pytest.approx(4999.0)
    assert fc.slept == pytest.approx(0.2 + 1.0 + 0.1 + 0.0 + 0.2)        # the backward step: at once, then paced
    assert paced.detail()["paced_long_steps"] == 1


# --- live: a source faster than the calibrator -------------------------------------------------

class _ListSource(BaseSource):
    live = False

    def __init__(self, samples, per_read=3):
        super().__init__("list://")
        self._s, self._i, self.per_read = list(samples), 0, per_read

    def read(self, timeout=0.05):
        out = self._s[self._i:self._i + self.per_read]
        self._i += len(out)
        self.eof = self._i >= len(self._s)
        return self._account(out)


class _Firehose(BaseSource):
    """A device far faster than any calibrator: ``per_read`` samples of a sphere sweep per read."""

    def __init__(self, per_read=3000):
        super().__init__("firehose://", time_source="device")
        self.per_read, self.k = per_read, 0

    def read(self, timeout=0.05):
        time.sleep(0.002)
        k = np.arange(self.k, self.k + self.per_read)
        self.k += self.per_read
        z = np.cos(k * 1e-4)
        r = np.sqrt(1 - z * z)
        m = 50 * np.stack([r * np.cos(k * 3e-3), r * np.sin(k * 3e-3), z], 1) + [10.0, -5.0, 3.0]
        return self._account([Sample(i / 30000.0, tuple(row), seq=i) for i, row in zip(k.tolist(), m.tolist())])


def test_queue_is_bounded_drops_are_counted_and_stop_is_prompt():
    cal = common.compiled_calibrator(512, 32)
    src = _Firehose()
    reader = QueuedReader(src, capacity=20000, max_read=4096)
    run_ = Run(reader, cal)
    asked = {}

    def stop_later():
        time.sleep(1.5)
        asked["t"] = time.monotonic()
        run_.request_stop()

    th = threading.Thread(target=stop_later)
    th.start()
    result = run_.run()
    stopped_in = time.monotonic() - asked["t"]
    reader.close()
    th.join()
    # a hang guard, not a speed target: before, 17.6 s at 30 kHz; a loaded machine answers in 1-2 s
    assert result.ended == "interrupted" and stopped_in < 5.0, stopped_in
    assert reader.peak <= 20000 + src.per_read                                 # bounded
    assert reader.dropped > 0 and run_.counts()["drops"] == reader.dropped     # counted, reported
    d = reader.detail()
    assert d["queue_dropped"] == reader.dropped and d["queue_capacity"] == 20000
    # nothing vanishes: every sample the device produced was used, dropped or still queued at the stop,
    # and every sample used was calibrated or counted as cut off by the stop
    assert src.samples == result.samples + reader.dropped + reader.unprocessed_at_close
    assert cal.counts()["samples"] + result.unfed == result.samples


def test_queued_reader_delivers_everything_in_bounded_reads_then_the_failure():
    from mkc_stream.ingest.source import SourceLost

    class Failing(_ListSource):
        def read(self, timeout=0.05):
            if self._i >= len(self._s):
                raise SourceLost("port gone")
            return super().read(timeout)

        eof = property(lambda self: False, lambda self, v: None)

    src = Failing([Sample(float(k), (1.0, 2.0, 3.0), seq=k) for k in range(1000)], per_read=50)
    reader = QueuedReader(src, capacity=100000, max_read=128)
    got, sizes = [], []
    with pytest.raises(SourceLost, match="port gone"):
        for _ in range(10000):
            batch = reader.read(0.5)
            sizes.append(len(batch))
            got += batch
    reader.close()
    assert [s.seq for s in got] == list(range(1000)) and max(sizes) <= 128 + 50
    assert reader.dropped == 0


# --- long work shows progress without a terminal ------------------------------------------------

def test_progress_lines_without_a_terminal():
    clock = iter([0.0, 3.0, 10.5, 12.0, 21.0]).__next__
    buf = io.StringIO()
    p = common.Progress(clock=clock, stream=buf)
    for k in range(4):
        p(f"step {k}")
    assert buf.getvalue().splitlines() == ["step 1 (10 s)", "step 3 (21 s)"]
    quiet = common.Progress(enabled=False, stream=io.StringIO())
    quiet("x")
    assert quiet.stream.getvalue() == ""


def test_calibrate_stream_reports_progress_on_stderr_when_not_a_tty(capsys, files, monkeypatch):
    monkeypatch.setattr(common.Progress, "EVERY_S", 0.0)
    code, _, err = run(capsys, ["calibrate", files / "good.csv", "--stream"])
    assert code == 0 and "streaming 2000/2000 samples (100%)" in err
    code, _, err = run(capsys, ["calibrate", files / "good.csv", "--stream", "--quiet"])
    assert "streaming" not in err


def test_json_never_holds_nan(tmp_path):
    dest = tmp_path / "x.json"
    common.write_json({"a": math.nan, "b": [1.0, math.inf], "c": np.float64(2.5), "d": np.int64(3)}, str(dest))
    assert json.loads(dest.read_text()) == {"a": None, "b": [1.0, None], "c": 2.5, "d": 3}
    assert os.path.getsize(dest) > 0


@pytest.mark.skipif(not pathlib.Path("/dev/full").exists(), reason="no /dev/full on this system")
def test_a_plot_that_cannot_be_written_raises():
    """matplotlib's PNG writer drops a failed write silently; save_figure must raise instead."""
    pytest.importorskip("matplotlib")
    from mkc_stream.plots import _plt, save_figure

    plt = _plt()
    fig = plt.figure()
    try:
        with pytest.raises(OSError):
            save_figure(fig, "/dev/full")
    finally:
        plt.close(fig)


def test_a_reader_warning_is_one_line_in_the_tools_voice(tmp_path, capsys):
    """An unknown unit warns (the field-range check is skipped) as 'mkc-stream: warning: ...'; the Greek
    mu spelling of microtesla is a known unit, so the range check applies and nothing is warned."""
    s = synthetic_mag(seed=3, N=600)
    for unit, warned in (("furlongs", True), ("\u03bcT", False)):
        path = tmp_path / f"rec_{warned}.csv"
        write_recording(path, s.t, s.raw, meta={"units.mag": unit})
        main(["calibrate", str(path), "--quiet"])
        err = capsys.readouterr().err
        lines = [ln for ln in err.splitlines() if "warning" in ln]
        if warned:
            assert len(lines) == 1 and lines[0].startswith("mkc-stream: warning:") and "furlongs" in lines[0]
        else:
            assert lines == []


def test_the_field_range_check_applies_to_every_microtesla_spelling():
    from mkc_stream.calib.acceptance import check

    q = {"coverage": 0.9, "condition": 10.0, "outlier_fraction": 0.0, "residual_rms": 0.1}
    for unit in ("uT", "\u00b5T", "\u03bcT", "microtesla", " UT "):
        ok, why = check(q, 500.0, unit)
        assert not ok and "physical range" in why, unit
    assert check(q, 500.0, "counts")[0]
