"""tools/bench_diagnose.py measures what it says (fields present and sane); no timing bound here."""
from __future__ import annotations

import math
import pathlib
import sys

TOOLS = pathlib.Path(__file__).resolve().parents[1] / "tools"
sys.path.insert(0, str(TOOLS))

import bench_diagnose  # noqa: E402

VERDICTS = {"no_gap", "explained", "partially_explained", "unexplained", "baseline_rejected"}  # docs/diagnosis.md


def test_measure_reports_seconds_memory_and_verdict_of_a_tiny_case():
    row = bench_diagnose.measure({"kind": "hand", "n": 1500, "rate": 50.0, "seed": 1, "profile": "fast",
                                  "replicas": 8})
    assert row["samples"] == 1500
    assert math.isclose(row["duration_s"], 1499 / 50.0, rel_tol=1e-9)
    for key in ("build_s", "diagnose_s", "import_s"):
        assert row[key] >= 0.0
    assert row["diagnose_s"] > 0.0 and row["build_s"] > 0.0
    assert row["rss_before_diagnose_mb"] > 0.0
    assert row["peak_rss_mb"] >= row["peak_rss_before_diagnose_mb"] > 0.0
    assert row["tracemalloc_peak_mb"] is None          # only on request
    assert row["verdict"] in VERDICTS
    assert row["decimation"] == 1 and row["samples_used"] == 1500    # fast decimates above 20,000 only
    assert row["replicas"] == 8
    assert math.isfinite(row["gap_before"]) and row["gap_before"] > 0.0
    assert math.isfinite(row["alarm"]) and row["alarm"] > 0.0
    text = bench_diagnose.table([{**row, "kind": "hand", "rate": 50.0, "profile": "fast", "load_before": 1.0,
                                  "load_after": 1.0, "status": "ok"}], [])
    assert "| 1500 | hand | 50 | fast | 1 |" in text and row["verdict"] in text


def test_child_peak_memory_is_that_childs_own():
    """A child that fills 200 MB shows at least that, an empty one little. Run from a small process:
    on Linux a child's ru_maxrss starts at its parent's resident memory (a pytest worker's 600 MB),
    which is why the tool's own process stays small."""
    import json
    import subprocess

    probe = ("import json, sys; sys.path.insert(0, sys.argv[1]); import bench_diagnose as B; "
             "big = B._run_child([sys.executable, '-c', 's = b\"x\" * (200 * 2**20); print(len(s))'], timeout=60.0); "
             "small = B._run_child([sys.executable, '-c', 'pass'], timeout=60.0); "
             "print(json.dumps([big[0], big[1].strip(), big[2], big[3], small[0], small[3]]))")
    out = subprocess.run([sys.executable, "-c", probe, str(TOOLS)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    code, text, wall, rss, code_small, small = json.loads(out.stdout.strip().splitlines()[-1])
    assert code == 0 and text == str(200 * 2 ** 20)
    assert wall > 0.0
    assert rss >= 200.0
    assert code_small == 0 and small < 100.0


def test_own_peak_is_this_process_high_water_mark():
    """_peak_rss_mb reads the process's own high-water mark, which 200 MB filled here raises by that."""
    import subprocess

    probe = ("import sys; sys.path.insert(0, sys.argv[1]); import bench_diagnose as B; a = B._peak_rss_mb(); "
             "s = b'x' * (200 * 2**20); b = B._peak_rss_mb(); print(a, b)")
    out = subprocess.run([sys.executable, "-c", probe, str(TOOLS)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    before, after = map(float, out.stdout.split())
    assert before < 100.0 and after - before >= 190.0


def test_auto_rate_makes_a_million_samples_1000_s_at_1_khz():
    assert bench_diagnose.auto_rate(1_000_000) == 1000.0
    assert bench_diagnose.auto_rate(10_000) == 50.0
