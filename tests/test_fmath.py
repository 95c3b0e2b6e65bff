"""The all-float build's own cube root and axis atan2 (firmware_ref/src/fmath.c) against the host's libm.

firmware_ref/tests/test_fmath.c is compiled with the all-float flags and run: cbrt within 1 ulp of the
correctly rounded cube root over 2 million arguments (subnormal to 2^139) and its special values; atan2
at every signed zero and axis equal to atan2f bit for bit (the only arguments the library gives it).
"""
from __future__ import annotations

import os
import pathlib
import shutil
import subprocess

import pytest

FW = pathlib.Path(__file__).resolve().parents[1] / "firmware_ref"
CC = os.environ.get("CC", "cc")
ALL_FLOAT = ["-DMKC_USE_FLOAT", "-DMKC_ACC_DOUBLE=0", "-DMKC_ESTEP_DOUBLE=0"]


@pytest.mark.skipif(shutil.which(CC) is None, reason=f"no C compiler: `{CC}` is not on PATH (set CC)")
def test_own_cbrt_and_axis_atan2_follow_libm(tmp_path):
    exe = tmp_path / "test_fmath"
    build = subprocess.run([CC, "-std=c99", "-O2", "-ffp-contract=off", "-Wall", "-Wextra", "-Werror",
                            "-Wdouble-promotion", *ALL_FLOAT, "-I", str(FW / "include"), "-I", str(FW / "src"),
                            str(FW / "tests" / "test_fmath.c"), str(FW / "src" / "fmath.c"), "-lm", "-o", str(exe)],
                           capture_output=True, text=True)
    assert build.returncode == 0, build.stderr
    run = subprocess.run([str(exe)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr
    worst = float(run.stdout.split("max_ulp_cbrt")[1])
    assert 0.0 < worst <= 1.0

