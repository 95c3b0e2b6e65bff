"""The all-float build of the C port (no double anywhere) follows the double reference.

The all-float build (`-DMKC_USE_FLOAT -DMKC_ACC_DOUBLE=0 -DMKC_ESTEP_DOUBLE=0`, for an FPU without
double) runs free on every golden magnetometer vector and must make the reference's decisions
(checkpoints, accepts, trials) and, at every accepted checkpoint, give theta and the calibration
within 1e-4 relative (theta: max |dtheta| / max |theta|; b: max |db| / F; S: max |dS| / max |S|;
F: |dF| / F). tools/measure_float_precision.py builds it and reports the same figures with where a
departure starts. Its cross objects (make cross) must call no software double-precision helper.
"""
from __future__ import annotations

import json
import pathlib
import shutil
import subprocess
import sys

import pytest

REPO_ROOT = pathlib.Path(__file__).resolve().parents[1]
FIRMWARE_DIR = REPO_ROOT / "firmware_ref"
sys.path.insert(0, str(REPO_ROOT / "tools"))

import golden as GV  # noqa: E402
import measure_float_precision as MFP  # noqa: E402

TOL = 1e-4
INDEX = json.loads((GV.GOLDEN_DIR / "index.json").read_text())
MAG = [v["name"] for v in INDEX["vectors"] if v["kind"] == "mag"]
VECTORS = {v["name"]: v for v in INDEX["vectors"]}
#: vectors that reach accepted checkpoints (the others never accept, in the reference too)
ACCEPTING = {"syn_s1_b00", "syn_s2_b10", "syn_s3_b25", "syn_s4_b10_w128_k16", "syn_s7_b10_spikes", "syn_s6_b10_nan",
             "qmc5883l_filtered", "qmc5883l_noisy_demo_w512", "ck_explorer"}

#: libgcc's software double-precision helpers (ARM EABI names and the generic ones)
SOFT_DOUBLE = ("__aeabi_d", "__aeabi_f2d", "__aeabi_i2d", "__aeabi_ui2d", "__aeabi_l2d", "__aeabi_ul2d",
               "__adddf3", "__subdf3", "__muldf3", "__divdf3", "__extendsfdf2", "__truncdfsf2", "__fixdf",
               "__floatsidf", "__floatunsidf", "__floatdidf", "__eqdf2", "__nedf2", "__ltdf2", "__gtdf2", "__ledf2",
               "__gedf2", "__unorddf2")
#: objects of the all-float library that must not touch double: the estimator's numerics
#: (normal equations, E-step, normaliser, window, statistics). The checkpoint code and the public
#: configuration / reason structs (double in include/mkc.h) are measured, listed below when they
#: still do.
DOUBLE_FREE_OBJECTS = ("estep.o", "normaliser.o", "stats.o", "magwindow.o", "stream.o")


@pytest.fixture(scope="module")
def libraries(tmp_path_factory):
    if shutil.which("make") is None or shutil.which("cc") is None:
        pytest.skip("no make or C compiler on PATH")
    return MFP.load(*MFP.build(tmp_path_factory.mktemp("allfloat")))


@pytest.mark.parametrize("name", MAG)
def test_all_float_follows_the_double_reference(libraries, name):
    r = MFP.free_running(VECTORS[name], TOL)
    assert not r["decision_mismatches"], r["decision_mismatches"][:3]
    assert r["checkpoints_float"] == r["checkpoints"]
    assert r["first_beyond_tol"] is None, r["first_beyond_tol"]
    for q in MFP.QUANTITIES:
        assert r["worst"][q] <= TOL, (q, r["worst"][q], r["worst_at"][q])
    # the comparison has something to compare on the vectors that accept
    assert (r["accepted"] > 0) == (name in ACCEPTING)


def test_the_measure_sees_a_departure(libraries):
    """The free-running measure flags a calibration beyond the tolerance (it can fail)."""
    r = MFP.free_running(VECTORS["syn_s2_b10"], 1e-9)
    assert r["first_beyond_tol"] is not None
    assert r["first_beyond_tol"]["departure"]["stage"] in ("E-step sigma/d", "normal-equation solve",
                                                           "checkpoint code")


def test_the_all_float_build_is_the_one_measured(libraries):
    fo, dbl = libraries
    assert (fo.real_bytes, fo.acc_bytes, fo.ereal_bytes) == (4, 4, 4)
    assert (dbl.real_bytes, dbl.acc_bytes, dbl.ereal_bytes) == (8, 8, 8)


def _cross_tools():
    for tool in ("arm-none-eabi-gcc", "arm-none-eabi-nm"):
        if shutil.which(tool) is None:
            return f"no `{tool}` on PATH"
    return None


def soft_double_calls(build: pathlib.Path, extra_make_args=()) -> dict:
    """{object: [soft-double helpers it calls]} of the all-float Cortex-M4F library built in build."""
    lib = build / "cross" / "m4f" / "libmkc_floatonly.a"
    proc = subprocess.run(["make", "-j2", "-C", str(FIRMWARE_DIR), f"BUILD={build}", *extra_make_args, str(lib)],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    found = {}
    for obj in sorted((build / "obj" / "cross_m4f_floatonly" / "src").glob("*.o")):
        nm = subprocess.run(["arm-none-eabi-nm", "-u", str(obj)], capture_output=True, text=True, check=True)
        found[obj.name] = sorted({line.split()[-1] for line in nm.stdout.splitlines()
                                  if line.split() and line.split()[-1].startswith(SOFT_DOUBLE)})
    return found


needs_cross = pytest.mark.skipif(_cross_tools() is not None,
                                 reason=f"Cortex-M cross toolchain missing: {_cross_tools()}")


@needs_cross
def test_all_float_cross_objects_call_no_soft_double(tmp_path):
    """make cross's all-float library for the Cortex-M4F (single-precision FPU): its numerics objects
    reference no libgcc soft-double helper (each such call is a software double operation)."""
    found = soft_double_calls(tmp_path / "build")
    assert set(DOUBLE_FREE_OBJECTS) <= set(found)
    bad = {name: found[name] for name in DOUBLE_FREE_OBJECTS if found[name]}
    assert not bad, bad
    # the helpers are recognised: the checkpoint code, double by default, does call them
    assert found["linalg.o"] and found["ellipsoid.o"]


@needs_cross
def test_checkpoint_code_in_float_calls_no_soft_double_arithmetic(tmp_path):
    """With -DMKC_CHECKPOINT_DOUBLE=0 the checkpoint code (sphere fit, eigen-decompositions, geometry,
    switching test) runs in float too: those objects call no soft-double helper; what remains are
    conversions into the public structs' double fields (mkc_mag_reason.v, mkc_config)."""
    flags = "PREC_floatonly=-DMKC_USE_FLOAT -DMKC_ACC_DOUBLE=0 -DMKC_ESTEP_DOUBLE=0 -DMKC_CHECKPOINT_DOUBLE=0"
    found = soft_double_calls(tmp_path / "build", [flags])
    for name in DOUBLE_FREE_OBJECTS + ("linalg.o", "sphere.o", "confidence.o"):
        assert not found[name], (name, found[name])
    conversions = ("__aeabi_f2d", "__aeabi_i2d", "__aeabi_l2d")
    for name in ("ellipsoid.o", "quality.o", "mag.o"):
        assert set(found[name]) <= set(conversions), (name, found[name])
