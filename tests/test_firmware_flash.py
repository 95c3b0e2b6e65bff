"""What the C port costs a firmware in flash, and the all-float build's freedom from software double.

- The flash the library adds (tools/bench_firmware_target.py flash_added): text + data of the smallest
  firmware using the calibrator (firmware_ref/target/footprint_main.c) minus the same firmware without
  it (target/footprint_base_main.c), on the Cortex-M4F board. Checked: the difference is that, the
  firmware without the library is small, and the all-float build links none of libgcc's software
  double, neither arithmetic nor conversions (the double build does: the check can see it). Skipped,
  saying why, without arm-none-eabi-gcc (Debian: gcc-arm-none-eabi, libnewlib-arm-none-eabi).
- The public API's settings and reason values (mkc_api_real) are float in the all-float build and
  double in the others.
- A float build checks its real settings as the state holds them, after rounding to float: a setting
  that becomes inf or 0 in float is refused there, accepted by the double build.
The host-compiler parts skip without a C compiler (CC).
"""
from __future__ import annotations

import os
import pathlib
import shutil
import subprocess
import sys

import pytest

REPO_ROOT = pathlib.Path(__file__).resolve().parents[1]
FW = REPO_ROOT / "firmware_ref"
sys.path.insert(0, str(REPO_ROOT / "tools"))

import bench_firmware_target as BT  # noqa: E402  (tools/bench_firmware_target.py)

CC = os.environ.get("CC", "cc")
STRICT = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-Wdouble-promotion", "-Wconversion",
          "-Wshadow", "-Wstrict-prototypes", "-ffp-contract=off", "-fno-fast-math", "-O2"]
ALL_FLOAT = ["-DMKC_USE_FLOAT", "-DMKC_ACC_DOUBLE=0", "-DMKC_ESTEP_DOUBLE=0"]
LIB_SRC = sorted(str(p) for p in (FW / "src").glob("*.c"))
#: libgcc's software double arithmetic (add/sub, mul/div, compare)
SOFT_DOUBLE_ARITHMETIC = ("_arm_addsubdf3.o", "_arm_muldivdf3.o", "_arm_cmpdf2.o", "_arm_unorddf2.o")

needs_cc = pytest.mark.skipif(shutil.which(CC) is None, reason=f"no C compiler: `{CC}` is not on PATH (set CC)")


def _compile_and_run(tmp_path: pathlib.Path, source: str, flags: list[str], sources=()) -> str:
    src = tmp_path / "probe.c"
    src.write_text(source)
    exe = tmp_path / "probe"
    cmd = [CC, *STRICT, *flags, f"-I{FW / 'include'}", f"-I{FW / 'src'}", "-o", str(exe), str(src), *sources, "-lm"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    run = subprocess.run([str(exe)], capture_output=True, text=True)
    assert run.returncode == 0, run.stdout + run.stderr
    return run.stdout


API_TYPES_PROBE = r"""
#include <stdio.h>
#include "mkc.h"

int main(void)
{
    mkc_config cfg;
    mkc_mag_reason r;
    printf("%u %u\n", (unsigned)sizeof cfg.sigma_pull, (unsigned)sizeof r.v[0]);
    return 0;
}
"""


@needs_cc
@pytest.mark.parametrize("precision,expected", [("double", "8 8"), ("all-float", "4 4"), ("float", "8 8")])
def test_the_api_settings_and_reason_values_are_float_only_in_the_all_float_build(tmp_path, precision, expected):
    flags = {"double": [], "float": ["-DMKC_USE_FLOAT"], "all-float": ALL_FLOAT}[precision]
    assert " ".join(_compile_and_run(tmp_path, API_TYPES_PROBE, flags).split()) == expected


CONFIG_PROBE = r"""
#include <stdio.h>
#include "mkc.h"

static mkc_stream_t st;

static int init_with(mkc_api_real sigma_lo, mkc_api_real sigma_hi)
{
    mkc_config cfg;
    mkc_config_default(&cfg, 4, 1);
    cfg.sigma_lo = sigma_lo;
    cfg.sigma_hi = sigma_hi;
    return mkc_stream_init(&st, &cfg, NULL, NULL, NULL);
}

int main(void)
{
    mkc_config cfg;
    mkc_config_default(&cfg, 4, 1);
    printf("%d %d %d\n", init_with(cfg.sigma_lo, cfg.sigma_hi), init_with(cfg.sigma_lo, (mkc_api_real)1e300),
           init_with((mkc_api_real)1e-60, cfg.sigma_hi));
    return 0;
}
"""


@needs_cc
@pytest.mark.parametrize("precision,expected", [("double", "0 0 0"), ("all-float", "0 4 4"), ("float", "0 4 4")])
def test_settings_are_checked_in_the_precision_the_state_holds(tmp_path, precision, expected):
    """sigma_hi = 1e300 is inf as a float and sigma_lo = 1e-60 is 0: a float build refuses both
    (MKC_BAD_INPUT = 4; the all-float build's settings are float, so they arrive as inf and 0); the
    double build takes them; the defaults pass everywhere (MKC_OK = 0)."""
    flags = {"double": [], "float": ["-DMKC_USE_FLOAT"], "all-float": ALL_FLOAT}[precision]
    out = _compile_and_run(tmp_path, CONFIG_PROBE, flags, LIB_SRC).split()
    assert " ".join(out) == expected


WHY = BT.missing_tools()


@pytest.fixture(scope="module")
def flash():
    if WHY is not None:
        pytest.skip(f"Cortex-M toolchain missing: {WHY}")
    build_dir = FW / "build"
    # the tool's own target names (relative to firmware_ref/: an absolute path names no rule)
    targets = BT.footprint_targets(None, "an386", ("double", "floatonly"))
    assert targets[0] == "build/qemu/an386_footprint_double.elf"
    BT.build(None, targets)
    return {p: BT.flash_added(build_dir, "an386", p) for p in ("double", "floatonly")}


@pytest.mark.parametrize("precision", ["double", "floatonly"])
def test_flash_added_is_the_firmware_with_the_library_minus_without(flash, precision):
    f = flash[precision]
    assert f["flash_added_bytes"] == f["flash_app_bytes"] - f["flash_base_bytes"]
    assert 0 < f["flash_base_bytes"] < 2048                     # reset, vectors and a sensor loop
    origin = f["added_by_origin"]
    assert origin["library"] > 10_000 and origin["runtime"] > 1_000
    # what the members add (text), with the initialised data, is the whole difference up to the
    # alignment fill between input sections
    assert 0 <= f["flash_added_bytes"] - (sum(origin.values()) + f["added_data_bytes"]) < 128
    assert 0 < origin["program"] < 512                           # main's own calls


def test_all_float_build_links_no_software_double(flash):
    def soft(precision, arithmetic_only=True):
        # libgcc's soft-float routines carry their mode in the name: df is double (adddf3,
        # truncdfsf2, fixdfsi ...)
        members = [m.split("(", 1)[1].rstrip(")") for m in flash[precision]["added_by_member"]
                   if m.startswith("libgcc.a(")]
        return [m for m in members if (m in SOFT_DOUBLE_ARITHMETIC if arithmetic_only else "df" in m)]

    assert soft("double")                                        # the check sees it where it is
    assert soft("floatonly", arithmetic_only=False) == []        # nor a conversion: the settings are float
    assert flash["floatonly"]["flash_added_bytes"] < flash["double"]["flash_added_bytes"]


def test_all_float_build_adds_at_most_24_kib_to_a_cortex_m4f_firmware(flash):
    """The port's flash line (all-float, Cortex-M4F, -Os, W = 256): at most 24 KiB added. Measured
    with Debian's arm-none-eabi-gcc 12.2 and newlib nano; another toolchain may differ by some bytes."""
    f = flash["floatonly"]
    version = subprocess.run(["arm-none-eabi-gcc", "-dumpversion"], capture_output=True, text=True).stdout.strip()
    assert f["flash_added_bytes"] <= 24 * 1024, (f"{f['flash_added_bytes']} B added (gcc {version}): "
                                                 f"library {f['added_by_origin']['library']} B, "
                                                 f"runtime {f['added_by_origin']['runtime']} B")
