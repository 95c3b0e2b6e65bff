#!/usr/bin/env python
"""Ingestion benchmarks and robustness figures (run on demand; targets live here, not in unit tests).

    python tools/bench_ingest.py                     # decoders, corruption study, 10^6-sample replay
    python tools/bench_ingest.py --quick             # 10^5-sample replay
    python tools/bench_ingest.py --pty-seconds 60    # also: live over a pty at 1 kHz for 60 s
    python tools/bench_ingest.py --json out/bench_ingest.json
    python tools/bench_ingest.py --readers           # only: the recording reader on 1, 10, 100 MB inputs
    python tools/bench_ingest.py --flightlogs        # only: flight-log read speed beside each format's library
    python tools/bench_ingest.py --mavlink-seconds 60  # only: live MAVLink over loopback UDP at 200 Hz

Measures:
  - decode rate of every serial decoder (bytes fed in 4 KB chunks) and of the CAN decoders
  - the binary protocol under 1% random byte corruption: intact frames lost (target 0), damaged
    frames counted (target: all of them)
  - replay of a 10^6-sample recording at 1 kHz (1000 s of data) through `mkc-stream replay`:
    target >= 20x faster than real time
  - optionally `mkc-stream live` over a pty at 1 kHz: samples lost (target 0) and CPU use
  - --readers: `read_recording` on inputs of 1, 10 and 100 MB (a valid recording, one line of
    garbage, a header of many commas, the last also with the header-line limit lifted), each in a
    fresh process: seconds and peak memory per MB, which must stay flat (linear reading)
  - --flightlogs: magnetometer samples per second of `read_flight_log` (every format, the real logs
    of ../shared/data where present, else tests/data) beside the format's own library reading the
    same file alone (pyulog, pymavlink, rosbags; numpy.loadtxt for a recording CSV); each side is
    timed with time.perf_counter, the two alternating, best of --repeats runs
  - --mavlink-seconds S: `mkc-stream live --mavlink udpin:...` while an emulator process sends
    the QMC5883L recording's samples as RAW_IMU at 200 Hz over loopback UDP: samples sent and
    received, values checked bit for bit in the recording, loss (target 0), CPU share of the
    live process; the emulator's end is a silent link, which must end the run cleanly
"""
from __future__ import annotations

import argparse
import io
import json
import pathlib
import random
import subprocess
import sys
import tempfile
import time
from contextlib import redirect_stdout

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from mkc_stream.cli import main as cli_main  # noqa: E402
from mkc_stream.ingest import make_decoder  # noqa: E402
from mkc_stream.ingest.binary import IMU_F32, MAG_F32, MAG_I16, BinaryDecoder, encode_frame  # noqa: E402
from mkc_stream.ingest.csvlines import encode_csv_header, encode_csv_row  # noqa: E402
from mkc_stream.ingest.emulator import CSV_COLUMNS, DeviceModel  # noqa: E402
from mkc_stream.ingest.motioncal import encode_motioncal  # noqa: E402
from mkc_stream.ingest.vectornav import encode_vn  # noqa: E402
from mkc_stream.io.recording import write_recording  # noqa: E402


def device_rows(n, seed=0):
    t, m, a, g, tc = DeviceModel(seed, 1000.0).block(0, n)
    return [(k, float(t[k]), tuple(m[k].tolist()), tuple(a[k].tolist()), tuple(g[k].tolist()), float(tc[k]))
            for k in range(n)]


def streams(n):
    rows = device_rows(n)
    return {
        "binary (IMU_F32)": b"".join(encode_frame(k, int(t * 1e6), m, a, g, tc, ftype=IMU_F32) for k, t, m, a, g, tc in rows),
        "binary (MAG_I16)": b"".join(encode_frame(k, int(t * 1e6), m, ftype=MAG_I16) for k, t, m, a, g, tc in rows),
        "motioncal (Raw)": b"".join(encode_motioncal(a, g, m, "Raw") for k, t, m, a, g, tc in rows),
        "motioncal (Uni)": b"".join(encode_motioncal(a, g, m, "Uni") for k, t, m, a, g, tc in rows),
        "csv": encode_csv_header(CSV_COLUMNS) + b"".join(encode_csv_row([t, *m, *a, *g, tc, k]) for k, t, m, a, g, tc in rows),
        "vectornav ($VNYMR)": b"".join(encode_vn("VNYMR", m, a, g) for k, t, m, a, g, tc in rows),
    }


PROTO = {"binary (IMU_F32)": "binary", "binary (MAG_I16)": "binary", "motioncal (Raw)": "motioncal-raw",
         "motioncal (Uni)": "motioncal-uni", "csv": "csv", "vectornav ($VNYMR)": "vectornav"}


def bench_decoders(n):
    out = {}
    for name, data in streams(n).items():
        dec = make_decoder(PROTO[name])
        t0 = time.perf_counter()
        got = 0
        for i in range(0, len(data), 4096):
            got += len(dec.feed(data[i:i + 4096], 0.0))
        got += len(dec.flush())
        dt = time.perf_counter() - t0
        assert got == n and dec.counts.bad_frames == 0, (name, got, dec.counts)
        out[name] = {"samples_per_s": n / dt, "MB_per_s": len(data) / dt / 1e6, "bytes_per_sample": len(data) / n}
    return out


def bench_can(n):
    import can

    from mkc_stream.ingest.candecoder import MagFrameDecoder
    from mkc_stream.ingest.canframe import encode_mag_frame

    rows = device_rows(n)
    msgs = [can.Message(arbitration_id=0x110, data=encode_mag_frame(m, k), timestamp=t) for k, t, m, a, g, tc in rows]
    dec = MagFrameDecoder()
    t0 = time.perf_counter()
    got = len(dec.feed(msgs))
    res = {"built-in frame": {"samples_per_s": got / (time.perf_counter() - t0)}}
    try:
        from mkc_stream.ingest.dbc import DbcDecoder
        dbc = pathlib.Path(__file__).resolve().parents[1] / "tests/data/canmod-gps-canedge/canmod-gps.dbc"
        import cantools
        db = cantools.database.load_file(str(dbc))
        m = db.get_message_by_name("gnss_imu")
        data = m.encode({"ImuValid": 1, "AccelerationX": 1.0, "AccelerationY": 2.0, "AccelerationZ": 9.75,
                         "AngularRateX": 0.25, "AngularRateY": 0.5, "AngularRateZ": 0.0})
        msgs = [can.Message(arbitration_id=9, data=data, timestamp=k * 1e-3) for k in range(n)]
        dec = DbcDecoder(str(dbc), ["mx=AccelerationX,my=AccelerationY,mz=AccelerationZ"])
        t0 = time.perf_counter()
        got = len(dec.feed(msgs))
        res["DBC (cantools)"] = {"samples_per_s": got / (time.perf_counter() - t0)}
    except ImportError:
        res["DBC (cantools)"] = None
    return res


def corruption_study(n_frames, rate, seeds):
    lost = bad_true = bad_counted = drops = false_frames = 0
    for seed in range(seeds):
        rng = random.Random(seed)
        frames = [encode_frame(k, k * 1000, (rng.uniform(-60, 60), 1.0, 2.0), ftype=(IMU_F32, MAG_F32, MAG_I16)[k % 3])
                  if k % 3 != 0 else encode_frame(k, k * 1000, (1.0, 2.0, 3.0), (0, 0, 9.8), (0, 0, 0), 20.0)
                  for k in range(n_frames)]
        data, touched = bytearray(), set()
        for k, f in enumerate(frames):
            f = bytearray(f)
            if 0 < k < n_frames - 1:
                for i in range(len(f)):
                    if rng.random() < rate:
                        f[i] ^= rng.randrange(1, 256)
                        touched.add(k)
            data += f
        dec = BinaryDecoder()
        out = []
        pos = 0
        while pos < len(data):
            step = rng.randrange(1, 600)
            out += dec.feed(bytes(data[pos:pos + step]))
            pos += step
        out += dec.flush()
        seqs = {s.seq for s in out}
        good = set(range(n_frames)) - touched
        lost += len(good - seqs)
        false_frames += len(seqs - good)
        bad_true += len(touched)
        bad_counted += dec.counts.bad_frames
        drops += dec.counts.drops
    return {"frames": n_frames * seeds, "byte_corruption": rate, "damaged_frames": bad_true,
            "intact_frames_lost": lost, "false_frames": false_frames, "bad_frames_counted": bad_counted,
            "drops_counted": drops}


def bench_replay(n, tmp):
    path = pathlib.Path(tmp) / "replay.csv"
    rate = 1000.0
    t, m, a, g, tc = DeviceModel(7, rate, sweep_s=20.0).block(0, n)
    t0 = time.perf_counter()
    write_recording(path, t, m, {"seq": np.arange(n, dtype=float)}, {"units.mag": "uT", "rate_hz": rate})
    t_write = time.perf_counter() - t0
    buf = io.StringIO()
    t0 = time.perf_counter()
    with redirect_stdout(buf):
        code = cli_main(["replay", str(path), "--json", "-", "--quiet"])
    wall = time.perf_counter() - t0
    obj = json.loads(buf.getvalue())
    return {"samples": n, "recording_seconds": n / rate, "write_s": t_write, "replay_wall_s": wall,
            "x_real_time": (n / rate) / wall, "exit_code": code, "status": obj["status"], "counts": obj["counts"],
            "cpu_percent": obj["cpu_percent"], "file_MB": path.stat().st_size / 1e6}


def bench_pty(seconds, rate=1000):
    emu = subprocess.Popen([sys.executable, "-m", "mkc_stream.ingest.emulator", "--protocol", "binary", "--rate",
                            str(rate), "--duration", str(seconds + 30), "--pty"], stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True)
    pty = emu.stdout.readline().split()[1]
    buf = io.StringIO()
    with redirect_stdout(buf):
        cli_main(["live", "--port", pty, "--protocol", "binary", "--max-samples", str(int(seconds * rate)),
                  "--json", "-", "--quiet"])
    emu.terminate()
    _, err = emu.communicate(timeout=10)
    obj = json.loads(buf.getvalue())
    return {"seconds": seconds, "rate_hz": rate, "counts": obj["counts"], "elapsed_s": obj["elapsed_s"],
            "cpu_percent_live": obj["cpu_percent"], "emulator": err.strip()}


_READ_ONE = """
import json, sys, time
from mkc_stream.io import recording
if sys.argv[2] == "lift":
    recording.MAX_HEADER_LINE = 1 << 40


def hwm():   # peak resident memory of this process in kB (VmHWM; ru_maxrss survives exec: the parent's)
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmHWM"))


base = hwm()
t0 = time.perf_counter()
try:
    rec = recording.read_recording(sys.argv[1])
    out = f"{len(rec)} samples, {len(rec.bad_rows)} bad rows"
except recording.RecordingError as exc:
    out = f"RecordingError, {len(str(exc))}-character message"
dt = time.perf_counter() - t0
peak = hwm() - base
print(json.dumps({"seconds": dt, "peak_MB": peak / 1024, "outcome": out}))
"""


def reader_inputs(kind, mb, path):
    """Write an input of about ``mb`` MB: a valid recording, one line of garbage, or a header of many commas."""
    size = int(mb * 1e6)
    if kind == "recording":
        n = size // 31                       # ~31 bytes per row of t, mx, my, mz
        rng = np.random.default_rng(0)
        write_recording(path, np.arange(n) / 100.0, rng.normal(0, 30, (n, 3)).round(3), None, {"units.mag": "uT"})
    elif kind == "garbage":                  # printable bytes, no line ending, no NUL
        rng = np.random.default_rng(1)
        path.write_bytes((rng.integers(33, 127, size, dtype=np.uint8)).tobytes())
    else:                                    # a header row of many commas (repeated names), then one row
        k = (size - 20) // 4
        path.write_text("t,mx,my,mz" + ",x" * k + "\n0,1,2,3" + ",0" * k + "\n")
    return path.stat().st_size / 1e6


def bench_readers(sizes=(1, 10, 100)):
    cases = [("recording", ""), ("garbage", ""), ("commas", ""), ("commas", "lift")]
    res = []
    with tempfile.TemporaryDirectory() as tmp:
        for kind, mode in cases:
            for mb in sizes:
                path = pathlib.Path(tmp) / f"{kind}_{mb}.csv"
                real = reader_inputs(kind, mb, path)
                r = subprocess.run([sys.executable, "-c", _READ_ONE, str(path), mode or "-"], capture_output=True,
                                   text=True, check=True, cwd=pathlib.Path(__file__).resolve().parents[1])
                row = json.loads(r.stdout)
                row.update(kind=kind + (" (header-line limit lifted)" if mode else ""), MB=real)
                res.append(row)
                print(f"  {row['kind']:38s} {real:7.1f} MB: {row['seconds']:7.3f} s "
                      f"({row['seconds'] / real:6.3f} s/MB), peak +{row['peak_MB']:7.1f} MB "
                      f"({row['peak_MB'] / real:5.2f} MB/MB); {row['outcome']}")
                path.unlink()
    return res


ROOT = pathlib.Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
QMC = ROOT / "tests/data/qmc5883l-tomisuarez/filtered_raw_data.csv"


def _first(*paths):
    return next((p for p in paths if p.exists()), None)


def _lib_ulog(path):
    from pyulog import ULog

    from mkc_stream.ingest.flightlogs.ulog import AUX_TOPICS, MAG_TOPICS

    u = ULog(str(path), list(dict.fromkeys(MAG_TOPICS + AUX_TOPICS)))
    return sum(len(d.data["timestamp"]) for d in u.data_list if d.name == "sensor_mag")


def _lib_dataflash(path):
    from pymavlink import DFReader

    r = DFReader.DFReader_binary(str(path), zero_time_base=False)
    n = 0
    while (m := r.recv_msg()) is not None:
        n += m.get_type() in ("MAG", "MAG2", "MAG3", "IMU")
    return n


def _lib_tlog(path):
    from pymavlink import mavutil

    c = mavutil.mavlink_connection(str(path))
    n = 0
    while (m := c.recv_msg()) is not None:
        n += m.get_type() in ("RAW_IMU", "SCALED_IMU2")
    c.close()
    return n


def _lib_rosbag(path):
    from rosbags.highlevel import AnyReader

    from mkc_stream.ingest.flightlogs.rosbag import bag_path

    n = 0
    with AnyReader([bag_path(path)]) as r:
        conns = [c for c in r.connections if c.msgtype in ("sensor_msgs/msg/MagneticField",
                                                           "geometry_msgs/msg/Vector3Stamped")]
        for c, _, raw in r.messages(connections=conns):
            r.deserialize(raw, c.msgtype)
            n += 1
    return n


def _lib_recording(path):
    with open(path) as f:
        head = next(i for i, line in enumerate(f) if not line.startswith("#")) + 1    # metadata + header
    return len(np.loadtxt(path, delimiter=",", skiprows=head, ndmin=2))


def bench_flightlogs(repeats=3):
    """Samples/s of read_flight_log (one magnetometer stream with its aux) beside the format's library
    reading the same file alone; best of ``repeats``, the two alternating."""
    from mkc_stream.ingest.flightlogs import read_flight_log
    from mkc_stream.io.recording import bundled_recording_path, read_recording

    cases = [
        ("ULog (pyulog)", _first(SHARED / "flightlog-pyulog-sample/sample.ulg",
                                 ROOT / "tests/data/flightlog-pyulog-sample/sample_log_small.ulg"), _lib_ulog),
        ("DataFlash (pymavlink)", _first(SHARED / "flightlog-dronekit-log171/log171.bin",
                                         ROOT / "tests/data/flightlog-dronekit-log171/log171_excerpt.bin"),
         _lib_dataflash),
        ("px4log (pymavlink)", _first(SHARED / "flightlog-px4tools-px4log/01_07_59.px4log"), _lib_dataflash),
        ("tlog (pymavlink)", ROOT / "tests/data/flightlog-tlog-from-log171/log171_excerpt.tlog", _lib_tlog),
        ("ROS 1 bag (rosbags)", _first(SHARED / "rosbag-imu-tools/phidgets_imu_upside_down.bag"), _lib_rosbag),
        ("ROS 2 MCAP bag (rosbags)", ROOT / "tests/data/rosbag-ck-explorer-ros2/ck_explorer_bag", _lib_rosbag),
        ("recording CSV (numpy.loadtxt)", bundled_recording_path(), _lib_recording),
    ]
    out = {}
    for name, path, lib in cases:
        if path is None:
            out[name] = None
            continue
        ours_s, lib_s = [], []
        n = 0
        ours = read_recording if name.startswith("recording") else read_flight_log
        for _ in range(repeats):
            t0 = time.perf_counter()
            n = len(ours(path))
            ours_s.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            lib(path)
            lib_s.append(time.perf_counter() - t0)
        out[name] = {"file": str(path), "MB": path.stat().st_size / 1e6 if path.is_file() else None,
                     "samples": n, "ours_s": min(ours_s), "library_s": min(lib_s),
                     "ours_samples_per_s": n / min(ours_s), "library_samples_per_s": n / min(lib_s)}
    return out


_MAVLINK_EMULATOR = """
import sys, numpy as np
from mkc_stream.ingest.emulator import send_mavlink
mag = np.loadtxt(sys.argv[1], delimiter=",", skiprows=3).astype(int)[: int(sys.argv[3])]
st = send_mavlink(("127.0.0.1", int(sys.argv[2])), mag, float(sys.argv[4]), wait_s=60.0)
print(st["imu_sent"], st["frames_sent"], len(st["commands"]))
"""


def bench_mavlink(seconds, rate=200.0):
    """live --mavlink over loopback UDP while a separate emulator process sends ``seconds`` x ``rate``
    RAW_IMU samples of the QMC5883L recording; the run ends when the emulator stops (a silent link)."""
    import socket

    from mkc_stream.io.recording import read_recording

    n = int(seconds * rate)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    emu = subprocess.Popen([sys.executable, "-c", _MAVLINK_EMULATOR, str(QMC), str(port), str(n), str(rate)],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    with tempfile.TemporaryDirectory() as tmp:
        out = pathlib.Path(tmp) / "mavlink.csv"
        buf = io.StringIO()
        with redirect_stdout(buf):
            code = cli_main(["live", "--mavlink", f"udpin:127.0.0.1:{port}", "--mavlink-rate", str(rate),
                             "--link-timeout", "2", "--out", str(out), "--json", "-", "--quiet"])
        emu_out, emu_err = emu.communicate(timeout=60)
        obj = json.loads(buf.getvalue())
        rec = read_recording(out)
    sent = int(emu_out.split()[0]) if emu_out.strip() else None
    mag = np.loadtxt(QMC, delimiter=",", skiprows=3).astype(int)[:n] * 0.1
    k = np.rint(rec.t / (1.0 / rate)).astype(int)           # the sample index from time_usec
    exact = bool(len(k) and np.array_equal(rec.mag, mag[k]) and np.array_equal(k, np.arange(len(k))))
    return {"seconds": seconds, "rate_hz": rate, "sent": sent, "received": obj["counts"]["samples"],
            "lost": None if sent is None else sent - obj["counts"]["samples"], "counts": obj["counts"],
            "values_bit_identical_in_order": exact, "ended": obj["ended"], "message": obj["message"],
            "exit_code": code, "elapsed_s": obj["elapsed_s"], "cpu_percent_live": obj["cpu_percent"],
            "status": obj["status"], "emulator_stderr": emu_err.strip()[-300:]}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="10^5-sample replay instead of 10^6")
    p.add_argument("--pty-seconds", type=float, default=0.0, help="also run live over a pty at 1 kHz this long")
    p.add_argument("--json", help="write the figures here")
    p.add_argument("--readers", action="store_true", help="only the recording reader on 1, 10, 100 MB inputs")
    p.add_argument("--flightlogs", action="store_true", help="only: flight-log read speed beside each library")
    p.add_argument("--repeats", type=int, default=3, help="--flightlogs: best of this many runs (default 3)")
    p.add_argument("--mavlink-seconds", type=float, default=0.0,
                   help="only: live MAVLink over loopback UDP at 200 Hz for this many seconds")
    a = p.parse_args(argv)
    res = {}
    if a.flightlogs or a.mavlink_seconds:
        if a.flightlogs:
            print(f"flight-log read speed, magnetometer samples/s (best of {a.repeats}):")
            res["flightlogs"] = bench_flightlogs(a.repeats)
            for k, v in res["flightlogs"].items():
                print(f"  {k:30s} " + ("no file" if v is None else
                      f"{v['samples']:7d} samples: ours {v['ours_samples_per_s']:12,.0f}/s ({v['ours_s']:.3f} s), "
                      f"library alone {v['library_samples_per_s']:12,.0f}/s ({v['library_s']:.3f} s)"))
        if a.mavlink_seconds:
            res["mavlink"] = m = bench_mavlink(a.mavlink_seconds)
            print(f"live MAVLink over loopback UDP, {m['rate_hz']:g} Hz for {m['seconds']:g} s: sent {m['sent']}, "
                  f"received {m['received']}, lost {m['lost']}, counts {m['counts']}, values bit-identical in "
                  f"order: {m['values_bit_identical_in_order']}; ended: {m['ended']} ({m['message']}), exit "
                  f"{m['exit_code']}; cpu of the live process {m['cpu_percent_live']:.1f}% over "
                  f"{m['elapsed_s']:.1f} s; calibration {m['status']}")
        if a.json:
            pathlib.Path(a.json).parent.mkdir(parents=True, exist_ok=True)
            pathlib.Path(a.json).write_text(json.dumps(res, indent=2))
        return 0
    if a.readers:
        print("read_recording, each input in a fresh process (peak = max RSS growth while reading):")
        res["readers"] = bench_readers()
        if a.json:
            pathlib.Path(a.json).parent.mkdir(parents=True, exist_ok=True)
            pathlib.Path(a.json).write_text(json.dumps(res, indent=2))
        return 0
    print("decoders (100k samples each, 4 KB chunks):")
    res["decoders"] = bench_decoders(100_000)
    for k, v in res["decoders"].items():
        print(f"  {k:20s} {v['samples_per_s']:12,.0f} samples/s  {v['MB_per_s']:6.1f} MB/s  {v['bytes_per_sample']:5.1f} B/sample")
    res["can"] = bench_can(100_000)
    for k, v in res["can"].items():
        print(f"  CAN {k:16s} " + ("not installed" if v is None else f"{v['samples_per_s']:12,.0f} samples/s"))
    res["corruption"] = corruption_study(10_000, 0.01, 10)
    c = res["corruption"]
    print(f"binary protocol, 1% of bytes corrupted, {c['frames']} frames: {c['damaged_frames']} damaged, "
          f"{c['bad_frames_counted']} counted bad, {c['intact_frames_lost']} intact frames lost, "
          f"{c['false_frames']} false frames, {c['drops_counted']} drops counted")
    n = 100_000 if a.quick else 1_000_000
    with tempfile.TemporaryDirectory() as tmp:
        res["replay"] = r = bench_replay(n, tmp)
    print(f"replay of {n} samples at 1 kHz ({r['recording_seconds']:.0f} s, {r['file_MB']:.0f} MB): "
          f"{r['replay_wall_s']:.1f} s wall = {r['x_real_time']:.1f}x real time (target >= 20x), "
          f"cpu {r['cpu_percent']:.0f}%, {r['status']}, counts {r['counts']}")
    if a.pty_seconds:
        res["pty"] = q = bench_pty(a.pty_seconds)
        print(f"live over a pty at 1 kHz for {a.pty_seconds:g} s: {q['counts']} in {q['elapsed_s']:.1f} s, "
              f"cpu of the live process {q['cpu_percent_live']:.1f}%\n  {q['emulator']}")
    if a.json:
        pathlib.Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        pathlib.Path(a.json).write_text(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
