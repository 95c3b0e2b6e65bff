"""The all-float build of the C port (no double arithmetic) follows the double reference.

The all-float build (`-DMKC_USE_FLOAT -DMKC_ACC_DOUBLE=0 -DMKC_ESTEP_DOUBLE=0`, for an FPU without
double; its checkpoint code is float too, MKC_CHECKPOINT_DOUBLE defaults to 0 there) runs free on
every golden magnetometer vector and must make the reference's decisions (checkpoints, accepts,
trials) and, at every accepted checkpoint, give theta and the calibration within 1e-4 relative
(theta: max |dtheta| / max |theta|; b: max |db| / F; S: max |dS| / max |S|; F: |dF| / F).
tools/measure_float_precision.py builds it and reports the same figures with where a departure
starts. Its sphere fit (float-float residuals and sums) rounds to the floats the double checkpoint
code gives, at every checkpoint. Its cross objects (make cross) call no software double-precision
arithmetic, only conversions into the public structs' double fields.
"""
from __future__ import annotations

import ctypes
import json
import pathlib
import shutil
import subprocess
import sys

import numpy as np
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
             "qmc5883l_filtered", "qmc5883l_noisy_demo_w512", "ck_explorer", "syn_s4009_b25_pool_refit",
             "syn_s3299_b25_wrong_mode"}

#: libgcc's software double-precision helpers (ARM EABI names and the generic ones)
SOFT_DOUBLE = ("__aeabi_d", "__aeabi_f2d", "__aeabi_i2d", "__aeabi_ui2d", "__aeabi_l2d", "__aeabi_ul2d",
               "__adddf3", "__subdf3", "__muldf3", "__divdf3", "__extendsfdf2", "__truncdfsf2", "__fixdf",
               "__floatsidf", "__floatunsidf", "__floatdidf", "__eqdf2", "__nedf2", "__ltdf2", "__gtdf2", "__ledf2",
               "__gedf2", "__unorddf2")
#: objects of the all-float library that must not touch double: the estimator's numerics
#: (normal equations, E-step, normaliser, statistics) and the checkpoint code's (sphere fit,
#: eigen-decompositions, switching test)
DOUBLE_FREE_OBJECTS = ("estep.o", "normaliser.o", "stats.o", "magwindow.o", "stream.o", "linalg.o", "sphere.o",
                       "confidence.o")
#: objects that only convert into the public structs' double fields (mkc_mag_reason.v, mkc_config)
CONVERSIONS_ONLY = ("ellipsoid.o", "quality.o", "mag.o")
CONVERSIONS = ("__aeabi_f2d", "__aeabi_i2d", "__aeabi_l2d")


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
    """make cross's all-float library for the Cortex-M4F (single-precision FPU): its numerics and
    checkpoint objects reference no libgcc soft-double helper (each such call is a software double
    operation); the calibration, quality and calibrator objects only convert into double fields."""
    found = soft_double_calls(tmp_path / "build")
    assert set(DOUBLE_FREE_OBJECTS) <= set(found)
    bad = {name: found[name] for name in DOUBLE_FREE_OBJECTS if found[name]}
    assert not bad, bad
    for name in CONVERSIONS_ONLY:
        assert set(found[name]) <= set(CONVERSIONS), (name, found[name])


@needs_cross
def test_checkpoint_code_in_double_calls_soft_double(tmp_path):
    """-DMKC_CHECKPOINT_DOUBLE=1 puts the checkpoint code of the all-float build back in double: then
    those objects call the helpers (the check recognises them) and the estimator's still do not."""
    flags = "PREC_floatonly=-DMKC_USE_FLOAT -DMKC_ACC_DOUBLE=0 -DMKC_ESTEP_DOUBLE=0 -DMKC_CHECKPOINT_DOUBLE=1"
    found = soft_double_calls(tmp_path / "build", [flags])
    for name in ("estep.o", "normaliser.o", "stats.o", "magwindow.o", "stream.o"):
        assert not found[name], (name, found[name])
    for name in ("linalg.o", "sphere.o", "ellipsoid.o"):
        assert set(found[name]) - set(CONVERSIONS), (name, found[name])


# ---- the sphere fit: float-float residuals round to the double checkpoint code's floats ----

@pytest.fixture(scope="module")
def checkpoint_double_library(tmp_path_factory):
    """the all-float library with the checkpoint code in double (-DMKC_CHECKPOINT_DOUBLE=1)"""
    from mkc_stream.cport import bindings as B

    if shutil.which("make") is None or shutil.which("cc") is None:
        pytest.skip("no make or C compiler on PATH")
    path, _ = MFP.build(tmp_path_factory.mktemp("cpdouble"), "-DMKC_CHECKPOINT_DOUBLE=1", with_double=False)
    return B._Lib("float", path)


def _robust_sphere_fit(lib, state_bytes: bytes, count: int) -> tuple:
    buf = ctypes.create_string_buffer(state_bytes, len(state_bytes))
    b, F = (ctypes.c_float * 3)(), ctypes.c_float()
    f = lib.dll.mkc__robust_sphere_fit
    f.restype = ctypes.c_int
    f.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p]
    ok = f(ctypes.addressof(buf), count, b, ctypes.byref(F))
    return ok, (*b[:], F.value)


@pytest.mark.parametrize("name", ["qmc5883l_filtered", "syn_s2_b10"])
def test_all_float_sphere_fit_rounds_like_the_double_one(libraries, checkpoint_double_library, name):
    """At every checkpoint of a free all-float run, the robust sphere fit of the window (which sets the
    normalisation and starts every cold start) is the same floats in float-float as in double: on
    QMC5883L one ulp of its radius, fed to a cold start, is enough to move the stream by 6.5e-4."""
    from mkc_stream.cport.bindings import CMagCalibrator

    fo, _ = libraries
    cd = checkpoint_double_library
    assert (cd.real_bytes, cd.acc_bytes, cd.ereal_bytes) == (4, 4, 4) and cd.sizeof_mag == fo.sizeof_mag
    meta = VECTORS[name]
    inp = GV.stored_input(meta)
    fits, differ = [], []

    def on_checkpoint(cal):
        count = int(cal.cnt[1])
        if count < 8:
            return
        state = ctypes.string_at(cal._addr, fo.sizeof_mag)
        (ok_f, x_f), (ok_d, x_d) = _robust_sphere_fit(fo, state, count), _robust_sphere_fit(cd, state, count)
        fits.append(ok_f)
        if ok_f != ok_d or (ok_f and x_f != x_d):
            differ.append((int(cal.cnt[2]), x_f, x_d))

    cfg = meta["config"]
    CMagCalibrator(window=cfg["window"], estep_every=cfg["estep_every"], unit=inp["unit"], precision="floatonly",
                   policy=cfg["policy"], on_checkpoint=on_checkpoint).learn_many(inp["mags"])
    assert sum(fits) >= 50
    assert not differ, differ[:3]


@pytest.mark.skipif(shutil.which("clang") is None or shutil.which("make") is None,
                    reason="clang or make is not installed (apt install clang make)")
def test_all_float_builds_with_clang_strict_warnings(tmp_path):
    """clang's -Wdouble-promotion also flags a float assigned to a double (gcc's only in arithmetic): the
    all-float build, whose checkpoint code is float, converts into the public double fields explicitly.
    Its self-test passes."""
    from mkc_stream import cport as FW

    build = tmp_path / "clang"
    flags = f"V_host_float=-O2 {MFP.HOST_CAPACITY} {MFP.ALL_FLOAT}"
    proc = FW.run_make("-j2", "CC=clang", f"BUILD={build}", flags, str(build / "test_c_float"))
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    run = subprocess.run([str(build / "test_c_float")], capture_output=True, text=True)
    assert run.returncode == 0 and " 0 failures" in run.stdout, run.stdout[-2000:] + run.stderr[-2000:]


def test_all_float_direction_cells_are_the_reference_cells(libraries):
    """The all-float build finds a unit vector's longitude sector by comparisons (no atan2f): the same cell
    as calib/quality.py direction_cells in double for random directions, the axes and the signed zeros."""
    from mkc_stream.calib.quality import direction_cells

    fo, _ = libraries
    f = fo.dll.mkc__unit_direction_cell
    f.restype = ctypes.c_int
    f.argtypes = [ctypes.c_float] * 3
    rng = np.random.default_rng(7)
    v = rng.standard_normal((20000, 3))
    u = (v / np.linalg.norm(v, axis=1)[:, None]).astype(np.float32)
    axes = [(sx * a, sy * b, c) for a, b in ((1.0, 0.0), (0.0, 1.0), (0.0, 0.0), (0.6, 0.8))
            for sx in (1.0, -1.0) for sy in (1.0, -1.0) for c in (0.0, 0.5, -1.0)]
    u = np.vstack([u, np.array(axes, np.float32)])
    got = np.array([f(*map(float, row)) for row in u])
    want = direction_cells(u.astype(np.float64))
    assert (got == want).all(), u[got != want][:5]
