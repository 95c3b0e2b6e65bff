"""Hostile input to the C port's replay tool (firmware_ref/build/mkc_replay).

Its recording reader (firmware_ref/tools/recording.c) must agree with
mkc_stream.io.recording.read_recording on every input: the same samples kept (bit for bit), the
same bad rows (line and kind), or both refuse the file (mkc_replay with exit 2 and one capped
line on stderr). It never crashes, stays linear in time and memory, and its ASan/UBSan build
replays the malformed corpus (firmware_ref/tests/malformed/, written by
firmware_ref/tests/make_malformed.py) without a report.
"""
from __future__ import annotations

import json
import os
import pathlib
import resource
import subprocess
import tempfile
import time
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mkc_stream import cport as FW
from mkc_stream.io.recording import RecordingError, read_recording, write_recording

WHY = FW.toolchain_problem()
pytestmark = pytest.mark.skipif(WHY is not None, reason=f"C port not buildable here: {WHY}")

CORPUS = FW.FIRMWARE_DIR / "tests" / "malformed"
CORPUS_FILES = sorted(p.name for p in CORPUS.iterdir()) if CORPUS.is_dir() else []


@pytest.fixture(scope="module")
def replay() -> pathlib.Path:
    FW.build("build/mkc_replay")
    return FW.BUILD_DIR / "mkc_replay"


def run(binary, *args, timeout=60, **kw):
    return subprocess.run([str(binary), *map(str, args)], capture_output=True, timeout=timeout, **kw)


def c_read(binary, path):
    """mkc_replay --read-only: the reader's result as a dict, or the refusal's stderr (exit 2)."""
    p = run(binary, "--read-only", path)
    assert p.returncode in (0, 2), (p.returncode, p.stderr[-2000:])
    if p.returncode == 2:
        assert_one_capped_line(p.stderr)
        return p.stderr.decode("ascii")
    return json.loads(p.stdout)


def py_read(path):
    """read_recording's Recording, or the text of its refusal (RecordingError or OSError)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")          # RecordingWarning: an unknown unit
            return read_recording(path)
    except (RecordingError, OSError) as exc:
        return str(exc)


def assert_one_capped_line(stderr: bytes, limit: int = 1200):
    """A refusal: one line `mkc_replay: error: ...`, printable ASCII, echoes of the file capped."""
    assert stderr.startswith(b"mkc_replay: error: ") and stderr.endswith(b"\n"), stderr[:300]
    assert stderr.count(b"\n") == 1 and len(stderr) <= limit, stderr[:300]
    assert all(32 <= b < 127 for b in stderr[:-1]), stderr[:300]


def assert_agree(binary, path):
    """C and Python read `path` alike; returns the Python result."""
    c, py = c_read(binary, path), py_read(path)
    if isinstance(py, str) or isinstance(c, str):
        assert isinstance(py, str) and isinstance(c, str), f"only one refuses: C {c!r:.300}, Python {py!r:.300}"
        return py
    assert c["samples"] == len(py)
    assert [tuple(b) for b in c["bad_rows"]] == [(line, why.split(": ", 1)[0]) for line, why in py.bad_rows]
    assert np.array_equal(np.array(c["t"], dtype=float), py.t)
    assert np.array_equal(np.array(c["mag"], dtype=float).reshape(-1, 3), py.mag)
    return py


# ---- the issue's probes -------------------------------------------------------------------------------

def test_repeated_column_is_refused_like_python(replay, tmp_path):
    """Was a use after free: exit -11 (SIGSEGV). Now exit 2 and read_recording's reason."""
    path = tmp_path / "dup.csv"
    path.write_text("t,mx,my,mz,mx\n" + "".join(f"{k * 0.02},{k % 7},2,3,1\n" for k in range(2000)))
    p = run(replay, path)
    assert p.returncode == 2
    assert_one_capped_line(p.stderr)
    assert b"line 1: duplicate column name(s) ['mx'] in header" in p.stderr
    with pytest.raises(RecordingError, match="duplicate column name"):
        read_recording(path)


def test_nul_in_a_row_is_one_bad_row(replay, tmp_path):
    """Was: reading stopped at the NUL (80 of 2000 samples kept). Now the row is one bad row."""
    from mkc_stream.calib.synthetic import synthetic_mag

    s = synthetic_mag(seed=3, N=2000)
    path = tmp_path / "rec.csv"
    write_recording(path, s.t, s.raw, meta={"units.mag": "uT"})
    data = path.read_bytes()
    cut = data.index(b"\n", len(data) // 25) - 3
    path.write_bytes(data[:cut] + b"\0" + data[cut:])
    py = assert_agree(replay, path)
    assert len(py) == 1999 and len(py.bad_rows) == 1 and py.bad_rows[0][1].startswith("non-numeric")
    p = run(replay, path, "--window", 256)
    assert p.returncode in (0, 1)
    assert json.loads(p.stdout)["counts"]["samples"] == 1999
    assert f"1 bad rows skipped (first: line {py.bad_rows[0][0]}, non-numeric".encode() in p.stderr


def test_directory_is_refused(replay, tmp_path):
    """Was: 'the file has no header row'. Now it says it is a directory (exit 2), as Python does."""
    p = run(replay, tmp_path)
    assert p.returncode == 2
    assert_one_capped_line(p.stderr)
    assert b"is a directory" in p.stderr
    assert isinstance(py_read(tmp_path), str)
    p = run(replay, tmp_path / "missing.csv")
    assert p.returncode == 2 and b"No such file" in p.stderr


def test_gzip_is_refused_with_the_reason(replay, tmp_path):
    """A documented difference: mkc_replay reads plain CSV only (Python reads .csv.gz)."""
    path = write_recording(tmp_path / "rec.csv.gz", [0.0, 1.0], [[1.0, 2.0, 3.0]] * 2)
    assert len(read_recording(path)) == 2
    p = run(replay, path)
    assert p.returncode == 2 and b"gunzip it first" in p.stderr


# ---- the corpus and random damage -----------------------------------------------------------------------

@pytest.mark.parametrize("name", CORPUS_FILES)
def test_malformed_corpus_agrees(replay, name):
    path = CORPUS / name
    py = assert_agree(replay, path)
    # the replay itself: exit 2 exactly when the reader refuses, and the same counts
    p = run(replay, path, "--window", 64)
    if isinstance(py, str):
        assert p.returncode == 2
        assert_one_capped_line(p.stderr)
        return
    assert p.returncode in (0, 1), p.stderr[-2000:]
    assert json.loads(p.stdout)["counts"]["samples"] == len(py)
    if py.bad_rows:
        assert f"mkc_replay: {len(py.bad_rows)} bad rows skipped (first: line {py.bad_rows[0][0]}, ".encode() \
            in p.stderr
    else:
        assert b"bad rows" not in p.stderr


def test_corpus_covers_the_issue():
    """The corpus holds the kinds of damage the issue lists (make_malformed.py writes them)."""
    for stem in ("cut_random_0", "flip_random_0", "nul_in_row", "crlf", "bom", "dup_column", "missing_column",
                 "huge_values", "nonfinite", "empty", "header_only", "long_body_line", "meta_line_over_limit"):
        assert f"{stem}.csv" in CORPUS_FILES


#: a small valid recording (metadata, an optional column with a NaN, a last line without line end)
SMALL = ("# units.mag: uT\n# sensor: test\nt,mx,my,mz,temp\n"
         + "".join(f"{k * 0.05:.2f},{20 + k * 1.5:.1f},{-3 - k:.0f},{41.25 - k * 0.5},{'nan' if k == 3 else k}\n"
                   for k in range(16))
         + "0.80,1e3,2,3,4").encode()
TOKENS = [b"\0", b"\r", b"\r\n", b"\xef\xbb\xbf", b",", b"\n", b"#", b" ", b"\x1c", "\u00a0".encode(), b"nan",
          b"inf", b"1e999", b"_", "\u0661".encode(), b"\xff", b"\xe2\x80", b"-", b".", b"e", b"\x7f", b"# k: 1\n",
          b"# k: 2\n", b"mx", b"\xfe\xff"]


@settings(max_examples=150, deadline=None)
@given(cut=st.integers(0, len(SMALL)),
       flips=st.lists(st.tuples(st.integers(0, len(SMALL) - 1), st.integers(0, 255)), max_size=4),
       inserts=st.lists(st.tuples(st.integers(0, len(SMALL)), st.sampled_from(TOKENS)), max_size=2))
def test_random_truncations_and_flips_agree(replay, cut, flips, inserts):
    data = bytearray(SMALL)
    for pos, value in flips:
        data[pos] = value
    for pos, token in inserts:
        data[pos:pos] = token
    with tempfile.TemporaryDirectory() as d:
        path = pathlib.Path(d) / "damaged.csv"
        path.write_bytes(bytes(data[:cut + sum(len(t) for _, t in inserts)]))
        assert_agree(replay, path)


# ---- size: linear time and memory, capped echoes --------------------------------------------------------

MB50 = 50_000_000


def _limit_memory():
    # 1 GiB of address space: a 50 MB input needs ~120 MB; anything quadratic would need far more
    resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30))


BIG = {
    "one_line": lambda: b"t,mx,my,mz\n" + b"x" * MB50,
    "long_cell": lambda: b"t,mx,my,mz\n0,1,2," + b"7" * MB50 + b"\n0.1,1,2,3\n",
    "commas_row": lambda: b"t,mx,my,mz\n" + b"," * MB50 + b"\n0,1,2,3",
    "garbage": lambda: np.random.default_rng(26).integers(1, 256, MB50, dtype=np.uint8).tobytes(),
    "many_commas_header": lambda: b"t,mx,my,mz" + b",c" * (MB50 // 2) + b"\n0,1,2,3\n",
    "wide_rows": lambda: (b"t,mx,my,mz" + b"".join(b",%03x" % k for k in range(4000)) + b"\n"
                          + b"".join(b"%d,1,2,3" % k + b",0" * 4000 + b"\n" for k in range(6000))),
}


@pytest.mark.parametrize("kind", list(BIG))
def test_large_input_is_linear_and_its_echo_capped(replay, tmp_path, kind):
    """50 MB in one line, one cell, one row of commas, random bytes, a header of 25 million names, 4000
    columns x 6000 rows: a few seconds (measured <= 1.5 s), bounded memory, at most a short line on
    stderr. Before: a header with over 256 columns was refused ('more than 256 columns')."""
    path = tmp_path / f"{kind}.csv"
    path.write_bytes(BIG[kind]())
    t0 = time.perf_counter()
    p = run(replay, path, "--window", 64, timeout=120, preexec_fn=_limit_memory)
    elapsed = time.perf_counter() - t0
    assert p.returncode in (1, 2), p.stderr[-500:]
    assert elapsed < 30, elapsed
    assert len(p.stderr) <= 1200 and p.stderr.count(b"\n") <= 1
    assert all(32 <= b < 127 or b == 10 for b in p.stderr)
    if kind in ("one_line", "garbage", "many_commas_header"):   # Python's read is quick on these
        assert_agree(replay, path)


def test_message_echoes_are_capped_and_escaped(replay, tmp_path):
    """A 60 kB header of control bytes and a 1 MB cell of terminal escapes: each echo is at most
    80 (40 for a cell) characters of the file, escaped."""
    rng = np.random.default_rng(7)
    junk = bytes(b for b in rng.integers(1, 32, 60_000, dtype=np.uint8).tobytes() if b not in (10, 13))
    path = tmp_path / "header.csv"
    path.write_bytes(b"t,mx,my,m" + junk + b"\n0,1,2,3\n")
    p = run(replay, path)
    assert p.returncode == 2
    assert_one_capped_line(p.stderr, limit=700)
    assert b"missing required column(s) mz" in p.stderr and b"...'" in p.stderr
    path = tmp_path / "cell.csv"
    path.write_bytes(b"t,mx,my,mz\n0,1,2,3\n0.1,\x1b[2J\x1b]0;pwned\x07" + b"\x1b[31m" * 200_000 + b",2,3\n0.2,1,2,3\n")
    p = run(replay, path)
    assert p.returncode in (0, 1)
    line = p.stderr.decode("ascii")
    assert line.startswith("mkc_replay: 1 bad rows skipped (first: line 3, non-numeric: column 'mx' has '\\x1b[2J")
    assert len(line) < 400 and all(32 <= ord(ch) < 127 for ch in line.rstrip("\n"))


# ---- sanitizers -----------------------------------------------------------------------------------------

def _sanitizer_problem() -> str | None:
    cc = os.environ.get("CC", "cc")
    with tempfile.TemporaryDirectory() as d:
        src = pathlib.Path(d) / "t.c"
        src.write_text("int main(void) { return 0; }\n")
        p = subprocess.run([cc, "-fsanitize=address,undefined", str(src), "-o", str(pathlib.Path(d) / "t")],
                           capture_output=True, text=True)
        if p.returncode != 0:
            return f"`{cc}` cannot link -fsanitize=address,undefined: {p.stderr.strip()[-300:]}"
    return None


def test_sanitized_replay_over_the_malformed_corpus():
    """`make sanitize-replay` (part of `make sanitize`): build/asan/mkc_replay, --read-only and a full
    replay, over every corpus file, a directory, a missing file and 5 MB generated inputs: exit 0, 1
    or 2 and no ASan/UBSan/LSan report. (The use after free of a repeated column failed it.)"""
    why = _sanitizer_problem()
    if why:
        pytest.skip(why)
    p = FW.run_make("sanitize-replay")
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    n = 2 * (len(CORPUS_FILES) + 9)      # 7 generated inputs, a directory, a missing file; two modes each
    assert f"sanitize-replay: {n} runs of build/asan/mkc_replay over the malformed inputs, 0 failures" in p.stdout
