"""Sources, open_source, pacing (fake clock), the reader thread, the recorder and the run loop."""
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from mkc_stream.calib.synthetic import synthetic_mag
from mkc_stream.ingest import FakeClock, Paced, Sample, SourceError, SourceLost, open_source
from mkc_stream.ingest.binary import BinaryDecoder, encode_frame
from mkc_stream.ingest.counters import GapCounter
from mkc_stream.ingest.live import Run
from mkc_stream.ingest.logs import CanLogSource, RecordingSource
from mkc_stream.ingest.recorder import RecordingWriter
from mkc_stream.ingest.serial_source import SerialSource
from mkc_stream.ingest.source import BaseSource, Source
from mkc_stream.ingest.vectornav import encode_vn
from mkc_stream.io.recording import read_recording, write_recording


class ListSource(BaseSource):
    """A file-like source over a list of samples, ``per_read`` at a time; optional failure at the end."""

    live = False

    def __init__(self, samples, per_read=7, fail=None):
        super().__init__("list://")
        self._s, self._i, self.per_read, self.fail = list(samples), 0, per_read, fail

    def read(self, timeout=0.05):
        if self._i >= len(self._s):
            if self.fail is not None:
                raise self.fail
            self.eof = True
            return []
        out = self._s[self._i:self._i + self.per_read]
        self._i += len(out)
        if self._i >= len(self._s) and self.fail is None:
            self.eof = True
        return self._account(out)


def samples_at(times):
    return [Sample(float(t), (1.0 * k, 2.0, 3.0), seq=k) for k, t in enumerate(times)]


# --- open_source ------------------------------------------------------------------------------

def test_open_source_dispatch(tmp_path):
    rec = tmp_path / "r.csv"
    write_recording(rec, [0, 1], [[1, 2, 3], [4, 5, 6]])
    with open_source(rec) as s:
        assert isinstance(s, RecordingSource) and isinstance(s, Source) and not s.live
    log = tmp_path / "f.log"
    log.write_text("(1.000000) vcan0 110#0100020003000000\n")
    with open_source(log) as s:
        assert isinstance(s, CanLogSource) and [x.mag for x in s] == [(0.01, 0.02, 0.03)]
    with open_source("loop://", protocol="binary") as s:
        assert isinstance(s, SerialSource) and s.live
    with pytest.raises(SourceError, match="needs --protocol"):
        open_source("loop://")
    with pytest.raises(SourceError, match="no such file"):
        open_source(tmp_path / "missing.csv")
    with pytest.raises(SourceError, match="unknown protocol"):
        open_source("loop://", protocol="nmea")
    with pytest.raises(SourceError, match="cannot open serial port"):
        open_source("/dev/does-not-exist-mkc", protocol="binary")
    with pytest.raises(SourceError, match="CAN logs only"):
        open_source(rec, dbc="x.dbc", mapping=["mx=a,my=b,mz=c"])
    with open_source("can://virtual/mkc-open-test?can_id=0x120") as s:
        assert s.decoder.can_id == 0x120 and s.meta["time_source"] == "host"


def test_loop_url_binary_and_host_time_text():
    with open_source("loop://", protocol="binary") as s:
        s._ser.write(b"".join(encode_frame(k, 1000 * k, (k, 2, 3)) for k in range(50)))
        got = []
        while len(got) < 50:
            got += s.read(0.2)
        assert [x.seq for x in got] == list(range(50)) and got[3].t == pytest.approx(0.003)
        assert s.counts() == {"samples": 50, "bad_frames": 0, "drops": 0, "gaps": 0}
    with open_source("serial:loop://", protocol="motioncal") as s:
        before = time.time()
        s._ser.write(b"Raw:0,0,8192,0,0,0,100,200,300\r\n" * 3)
        got = []
        while len(got) < 3:
            got += s.read(0.2)
        assert all(x.host_time and before <= x.t <= time.time() for x in got)
        assert s.meta["time_source"] == "host" and got[0].mag == pytest.approx((10, 20, 30))


def test_socket_url_vectornav_and_every_byte_before_the_disconnect():
    srv = socket.create_server(("127.0.0.1", 0))
    port = srv.getsockname()[1]
    lines = b"".join(encode_vn("VNYMR", (20, 0, 40), (0, 0, 9.8), (0, 0, 0)) for _ in range(20))

    def serve():
        conn, _ = srv.accept()
        time.sleep(0.3)                   # pyserial flushes what arrives while the port opens, like a UART
        conn.sendall(lines)
        conn.close()                                              # the device goes away right after

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    got = []
    with open_source(f"socket://127.0.0.1:{port}", protocol="vectornav") as s:
        with pytest.raises(SourceLost, match="disappeared"):
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline:
                got += s.read(0.1)
    srv.close()
    assert len(got) == 20 and got[0].mag == pytest.approx((20, 0, 40))


class ByteChunkSource(BaseSource):
    """A binary-protocol device whose bytes arrive in the given chunks, one chunk per read."""

    def __init__(self, chunks):
        super().__init__("bytes://", decoder=BinaryDecoder())
        self._chunks = list(chunks)

    def read(self, timeout=0.05):
        if not self._chunks:
            self.eof = True
            return []
        return self._account(self.decoder.feed(self._chunks.pop(0)))


def _frames(seqs, damaged=()):
    out = b""
    for q in seqs:
        f = bytearray(encode_frame(q, 1000 * q, (1.0, 2.0, 3.0)))
        if q in damaged:
            f[-1] ^= 0xFF                                          # a CRC that fails
        out += bytes(f)
    return out


def test_a_run_that_stops_inside_a_chunk_counts_no_damage_after_its_last_sample():
    """Damage and drops are counted when the next good frame shows them; a run that stops at its
    n-th sample counts those before that sample, not those the rest of its chunk showed (the
    end-to-end serial test saw samples + bad + drops exceed the device's frames by one)."""
    # one chunk: seq 0-9 good, 10 damaged, 11-14 good, 15 lost, 16-19 good; then a second chunk
    src = ByteChunkSource([_frames([q for q in range(20) if q != 15], damaged={10}),
                           _frames(range(20, 25), damaged={22})])
    got = src.read() + src.read()
    assert [g.seq for g in got] == [q for q in range(25) if q not in (10, 15, 22)]
    # sample 10 is seq 9 (before the damage), 11 is seq 11, 15 is seq 16 (after the drop), 21 is seq 23
    want = {10: (0, 0), 11: (1, 0), 14: (1, 0), 15: (1, 1), 18: (1, 1), 20: (1, 1), 21: (2, 1), 22: (2, 1)}
    for n, (bad, drops) in want.items():
        c = src.counts(n)
        assert (c["bad_frames"], c["drops"]) == (bad, drops), n
    assert src.counts()["bad_frames"] == 2 and src.counts()["drops"] == 1


# --- recordings as sources -----------------------------------------------------------------------

def test_recording_source_round_trip_and_counts(tmp_path):
    s = synthetic_mag(seed=3, N=3000)
    t = s.t.copy()
    t[2000:] += 5.0                                                # one time gap
    seq = np.arange(3000, dtype=float)
    seq[1500:] += 2                                                # two frames dropped
    aux = {"ax": np.zeros(3000), "ay": np.ones(3000), "az": np.full(3000, 9.8), "temp": np.full(3000, 20.5),
           "seq": seq, "current": np.linspace(0, 1, 3000)}
    path = tmp_path / "r.csv"
    write_recording(path, t, s.raw, aux, {"units.mag": "uT", "time_source": "host", "seq_modulus": 65536})
    lines = path.read_text().splitlines()
    lines[100] = "1,2"                                             # a bad row
    path.write_text("\n".join(lines) + "\n")
    rec = read_recording(path)
    with RecordingSource(path) as src:
        got = list(src)
        assert src.counts() == rec.counts() | {"drops": 2}
    assert len(got) == len(rec) == 2999
    assert [g.t for g in got] == rec.t.tolist() and [g.mag for g in got] == [tuple(m) for m in rec.mag.tolist()]
    g = got[10]
    assert g.acc == (0.0, 1.0, 9.8) and g.gyro is None and g.temp == 20.5 and g.seq == 10 and g.host_time
    assert set(g.aux) == {"current"}
    assert rec.counts()["gaps"] == 1 and rec.counts()["bad_frames"] == 1


def test_gap_counter_matches_the_file_reader(tmp_path):
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.009, 0.011, 5000))
    t[[100, 2000, 4000]] += [0.05, 0.5, 0.03]
    gc = GapCounter()
    for x in t:
        gc.update(float(x))
    write_recording(tmp_path / "g.csv", t, np.ones((5000, 3)))
    assert gc.final() == read_recording(tmp_path / "g.csv").counts()["gaps"] == 3


# --- pacing --------------------------------------------------------------------------------------

def test_paced_real_time_with_a_fake_clock_never_sleeps():
    times = np.arange(0, 100, 0.1)                                  # 100 s of samples at 10 Hz
    fc = FakeClock(1000.0)
    paced = Paced(ListSource(samples_at(times), per_read=64), speed=1.0, clock=fc.now, sleep=fc.sleep)
    released = []
    t_wall = time.monotonic()
    while not paced.eof:
        for s in paced.read(0.5):
            released.append((fc.now() - 1000.0, s.t))
    assert time.monotonic() - t_wall < 10.0     # a hang guard: a real-time wait would take 100 s
    assert len(released) == len(times)
    assert all(wall >= t - 1e-9 for wall, t in released)           # never early
    assert all(wall - t < 0.5 + 1e-9 for wall, t in released)      # never late by more than one read
    assert fc.slept == pytest.approx(99.9, abs=0.5)


def test_paced_speed_and_as_fast_as_possible():
    fc = FakeClock()
    paced = Paced(ListSource(samples_at(np.arange(0, 10, 0.01))), speed=10.0, clock=fc.now, sleep=fc.sleep)
    n = sum(len(paced.read(1.0)) for _ in range(100000) if not paced.eof)
    assert n == 1000 and fc.slept == pytest.approx(0.999, abs=0.05)
    fc = FakeClock()
    fast = Paced(ListSource(samples_at(np.arange(0, 10, 0.01))), speed=math.inf, clock=fc.now, sleep=fc.sleep)
    n = 0
    while not fast.eof:
        n += len(fast.read())
    assert n == 1000 and fc.slept == 0.0
    with pytest.raises(ValueError):
        Paced(ListSource([]), speed=0)


def test_paced_releases_bad_times_at_once():
    s = [Sample(0.0, (1, 2, 3)), Sample(math.nan, (1, 2, 3)), Sample(5.0, (1, 2, 3)), Sample(1.0, (1, 2, 3))]
    fc = FakeClock()
    paced = Paced(ListSource(s, per_read=10), clock=fc.now, sleep=fc.sleep)
    got = []
    while not paced.eof:
        got += paced.read(10.0)
    assert len(got) == 4 and fc.slept == pytest.approx(5.0)


# --- the recorder ----------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["rec.csv", "rec.csv.gz"])
def test_recorder_round_trip_bit_exact_and_readable_while_open(tmp_path, name):
    rng = np.random.default_rng(1)
    samples = [Sample(float(k) / 3, tuple(rng.normal(size=3) * 50), tuple(rng.normal(size=3)), None,
                      float(rng.normal()), k, False, {"rpm": float(rng.normal())}) for k in range(500)]
    fc = FakeClock()
    w = RecordingWriter(tmp_path / name, {"source": "test", "units.mag": "uT"}, clock=fc.now)
    w.write(samples[:300])
    fc.sleep(1.0)
    w.tick()                                                          # a second later: on disk
    partial = read_recording(tmp_path / name)
    # the reader marks the last line of an unfinished gzip stream as truncated (its documented rule)
    assert len(partial) + len(partial.bad_rows) == 300 and len(partial.bad_rows) == name.endswith(".gz")
    w.write(samples[300:])
    w.write([Sample(999.0, (1.0, 2.0, 3.0), gyro=(0.0, 0.0, 0.0))])   # gyro: not a column of the header
    w.close()
    rec = read_recording(tmp_path / name)
    assert w.unrecorded == {"gyro": 1} and len(rec) == 501 and rec.bad_rows == []
    assert rec.columns == ["t", "mx", "my", "mz", "ax", "ay", "az", "temp", "seq", "rpm"]
    assert rec.t[:500].tolist() == [s.t for s in samples]
    assert [tuple(m) for m in rec.mag[:500].tolist()] == [s.mag for s in samples]
    assert rec.aux["rpm"][:500].tolist() == [s.aux["rpm"] for s in samples] and rec.meta["source"] == "test"


def test_recorder_with_no_samples_writes_a_valid_empty_recording(tmp_path):
    RecordingWriter(tmp_path / "e.csv", {"a": "b"}).close()
    assert len(read_recording(tmp_path / "e.csv")) == 0


CHILD = r"""
import sys, time
from mkc_stream.ingest.recorder import RecordingWriter
from mkc_stream.ingest.sample import Sample
w = RecordingWriter(sys.argv[1], {"source": "crash test"})
k = 0
while True:
    w.write([Sample(k * 0.001 + j * 1e-4, (1.0, 2.0, 3.0)) for j in range(10)])
    k += 1
    print(w.rows, time.monotonic(), flush=True)
    time.sleep(0.01)
"""


def test_recorder_killed_loses_at_most_the_last_second(tmp_path):
    path = tmp_path / "crash.csv"
    p = subprocess.Popen([sys.executable, "-c", CHILD, str(path)], stdout=subprocess.PIPE, text=True)
    log = []
    while True:
        rows, when = p.stdout.readline().split()
        log.append((int(rows), float(when)))
        if log[-1][1] - log[0][1] > 2.5:
            break
    os.kill(p.pid, signal.SIGKILL)
    killed_at = time.monotonic()
    p.communicate()
    rec = read_recording(path)
    written_a_second_before = max(r for r, w in log if w <= killed_at - 1.05)
    assert len(rec) >= written_a_second_before > 0
    assert rec.counts()["bad_frames"] <= 1                            # at most a cut last line


# --- the run loop ----------------------------------------------------------------------------------

class Cal:
    """The calibrator interface the loop uses, recording the batches it gets."""

    def __init__(self):
        self.batches, self.accepted = [], None

    def learn_many(self, mags):
        self.batches.append(len(mags))
        return []

    def counts(self):
        return {"bad_frames": 0}


def test_run_stops_at_max_samples_and_feeds_everything(tmp_path):
    cal = Cal()
    w = RecordingWriter(tmp_path / "r.csv")
    run = Run(ListSource(samples_at(np.arange(1000) * 0.01), per_read=64), cal, w, max_samples=500)
    res = run.run()
    assert res.ended == "max samples" and res.samples == 500 and sum(cal.batches) == 500
    assert len(read_recording(tmp_path / "r.csv")) == 500 and run.counts()["samples"] == 500


def test_run_duration_in_sample_time_and_source_lost(tmp_path):
    res = Run(ListSource(samples_at(np.arange(1000) * 0.01)), Cal(), duration=2.0,
              duration_in_sample_time=True).run()
    assert res.ended == "duration" and res.samples == 200
    w = RecordingWriter(tmp_path / "lost.csv")
    res = Run(ListSource(samples_at(range(50)), fail=SourceLost("gone")), Cal(), w).run()
    assert res.ended == "source lost" and res.message == "gone" and len(read_recording(tmp_path / "lost.csv")) == 50


def test_run_ctrl_c_ends_cleanly(tmp_path):
    w = RecordingWriter(tmp_path / "int.csv")
    res = Run(ListSource(samples_at(range(30)), fail=KeyboardInterrupt()), Cal(), w).run()
    assert res.ended == "interrupted" and len(read_recording(tmp_path / "int.csv")) == 30


class SigintInUpdate(Cal):
    """A calibrator that receives Ctrl-C in the middle of its second update."""

    def __init__(self):
        super().__init__()
        self.finished = 0

    def learn_many(self, mags):
        self.batches.append(len(mags))
        if len(self.batches) == 2:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.01)                     # the handler runs here, mid-update
        self.finished += len(mags)               # an update that was cut short never gets here
        return []


def test_ctrl_c_stops_between_updates_never_inside_one(tmp_path):
    cal = SigintInUpdate()
    w = RecordingWriter(tmp_path / "int.csv")
    before = signal.getsignal(signal.SIGINT)
    run = Run(ListSource(samples_at(range(10_000)), per_read=50), cal, w, feed_every_s=0.0)
    res = run.run()
    assert res.ended == "interrupted" and 100 <= res.samples < 10_000
    assert cal.finished == sum(cal.batches) == res.samples          # every update ran to its end
    assert len(read_recording(tmp_path / "int.csv")) == res.samples
    assert signal.getsignal(signal.SIGINT) is before                 # the caller's handler is back


def test_a_second_ctrl_c_interrupts_a_stuck_loop(tmp_path):
    class Stuck(Cal):
        def learn_many(self, mags):
            self.batches.append(len(mags))
            if len(self.batches) == 1:
                os.kill(os.getpid(), signal.SIGINT)      # the polite request ...
                time.sleep(0.01)
                os.kill(os.getpid(), signal.SIGINT)      # ... and the one that insists
                time.sleep(1.0)                          # (never slept through: interrupted)
            return []

    res = Run(ListSource(samples_at(range(1000)), per_read=50), Stuck(), feed_every_s=0.0).run()
    assert res.ended == "interrupted" and res.samples == 50


def test_counts_of_a_run_that_stops_while_the_reader_decodes_ahead():
    """A reader thread may decode chunks the run never consumes; their bad frames and drops are not
    the run's: counts(consumed) is what the decoder had counted by the end of the chunk that held the
    last consumed sample."""
    from mkc_stream.ingest.counters import DecodeCounts

    class Decoder:
        counts = DecodeCounts()

    src = BaseSource("test://", decoder=Decoder())
    chunk = [Sample(t=0.01 * k, mag=(1.0, 2.0, 3.0)) for k in range(10)]
    Decoder.counts.bad_frames, Decoder.counts.drops = 1, 2
    src._account(chunk)                                   # samples 1-10: 1 bad frame, 2 drops so far
    Decoder.counts.bad_frames, Decoder.counts.drops = 4, 5
    src._account(chunk)                                   # samples 11-20, decoded ahead
    assert src.counts(consumed=7) == {"samples": 7, "bad_frames": 1, "drops": 2, "gaps": src.gaps.final()}
    assert src.counts(consumed=10)["bad_frames"] == 1
    assert src.counts(consumed=15)["bad_frames"] == 4
    assert src.counts()["bad_frames"] == 4 and src.counts()["drops"] == 5
