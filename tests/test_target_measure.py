"""The calibrator measured on the emulated Cortex-M4F: stack painting and instruction counts.

firmware_ref/target/measure_main.c replays a stream under qemu-system-arm -icount (every instruction a
fixed 2^shift virtual ns) and times every mkc_mag_push with the board's 25 MHz counter; it paints the
stack before the replay and reports the deepest word overwritten. tools/bench_firmware_target.py
converts and tabulates. Here, on the first 400 samples of the W = 256 golden vector (about 10
checkpoints): the counter counts instructions (a loop of known length, and the same replay at two
icount shifts giving the same counts), the stack figure lies inside the painted region, the most
expensive sample is a checkpoint and costs more than the average, and the sizes from nm and the
harness's sizeof agree.

Skipped, saying why, without arm-none-eabi-gcc (Debian: gcc-arm-none-eabi, libnewlib-arm-none-eabi)
or qemu-system-arm (qemu-system-arm).
"""
from __future__ import annotations

import pathlib
import sys

import pytest

REPO_ROOT = pathlib.Path(__file__).resolve().parents[1]
BUILD_DIR = REPO_ROOT / "firmware_ref" / "build"
sys.path.insert(0, str(REPO_ROOT / "tools"))

import bench_firmware_target as BT  # noqa: E402  (tools/bench_firmware_target.py)

WHY = BT.missing_tools()
VECTOR, SAMPLES = "syn_s3_b25", 400          # W = 256, K = 32
PROGRAMS = [f"build/qemu/an386_{kind}_{p}.elf" for kind in ("measure", "footprint") for p in ("double", "floatonly")] \
    + ["build/qemu/insn_count_plugin.so"]                 # make targets, relative to firmware_ref/
#: instructions the harness runs after its last counter reading (formatting its line with 64-bit
#: divisions, the console, the exit): the plugin counts them, the counter cannot
TAIL_INSNS = 20_000


@pytest.fixture(scope="module")
def built():
    if WHY is not None:
        pytest.skip(f"Cortex-M toolchain or emulator missing: {WHY}")
    BT.build(None, tuple(PROGRAMS))
    return BUILD_DIR / "qemu"


@pytest.fixture(scope="module")
def replays(built, tmp_path_factory):
    """all-float at icount shifts 0 and 2, double at shift 0, each on the same 400 samples"""
    work = tmp_path_factory.mktemp("measure")
    assert BT.write_input(VECTOR, work / "mkc_in.bin", SAMPLES) == SAMPLES
    return {(p, s): BT.run_measure(built / f"an386_measure_{p}.elf", work, "an386", s)
            for p, s in (("floatonly", 0), ("floatonly", 2), ("double", 0))}


@pytest.mark.parametrize("precision", ["floatonly", "double"])
def test_the_counter_counts_instructions(replays, precision):
    """A loop of 2 x 200,000 instructions (two lengths, so the fixed part cancels) reads as that many,
    by the FPGAIO counter and by SysTick alike."""
    cal = replays[(precision, 0)]["calibration"]
    assert cal["loop_instructions"] == 400_000
    assert abs(cal["counted_instructions"] - cal["loop_instructions"]) <= 0.01 * cal["loop_instructions"]
    assert abs(cal["systick_ticks"] - cal["counter_ticks"]) <= 1     # each reading rounds to its tick


def test_an_instruction_counting_plugin_agrees_with_the_counter(built, tmp_path):
    """qemu's TCG plugin interface counts every executed instruction (target/insn_count_plugin.c): over the
    whole run it equals the counter's reading since reset, up to the harness's short tail after it."""
    plugin = built / "insn_count_plugin.so"
    why = BT.plugin_problem(plugin, built / "an386_footprint_floatonly.elf")
    if why:
        pytest.skip(f"no instruction-counting plugin: {why}")
    BT.write_input(VECTOR, tmp_path / "mkc_in.bin", SAMPLES)
    check = BT.run_measure(built / "an386_measure_floatonly.elf", tmp_path, "an386", 0, plugin, profile=True)[
        "plugin_check"]
    assert check["plugin_instructions"] > 1_000_000
    assert 0 <= check["plugin_instructions"] - check["clock_instructions"] <= TAIL_INSNS, check
    # the per-block profile accounts for the same run (a block counts whole: within 1 %), by function
    prof = check["profile"]
    assert abs(sum(prof.values()) - check["plugin_instructions"]) <= 0.01 * check["plugin_instructions"]
    assert prof.get("mkc__learn_one", 0) > 0 and "?" not in prof


def test_counts_do_not_depend_on_the_icount_shift(replays):
    """At shift 2 an instruction is 4 virtual ns (10 per counter tick instead of 40): the per-sample counts
    are the same instructions, each within its quantisation (40 + 10), the totals within 0.1 %."""
    a, b = replays[("floatonly", 0)], replays[("floatonly", 2)]
    assert a["insns_per_tick"] == 40.0 and b["insns_per_tick"] == 10.0
    diff = abs(a["per_sample_insns"] - b["per_sample_insns"])
    assert diff.max() <= 50.0, diff.max()
    assert abs(a["insns_total"] - b["insns_total"]) <= 1e-3 * a["insns_total"]
    assert b["calibration"]["relative_error"] <= 0.01


@pytest.mark.parametrize("precision", ["floatonly", "double"])
def test_instruction_counts_are_sane(replays, precision):
    r = replays[(precision, 0)]
    assert r["samples"] == SAMPLES and r["checkpoints"] >= 5
    assert (r["per_sample_insns"] > 0).all()
    assert 0 < r["insns_quiet_median"] < r["insns_per_sample"] < r["insns_worst"]
    assert r["worst_is_checkpoint"]                  # the expensive sample is the E-step / checkpoint
    assert r["per_sample_flags"][r["worst_sample"] - 1] & BT.COST_CHECKPOINT
    assert r["insns_total"] == pytest.approx(r["insns_per_sample"] * SAMPLES)


def test_software_double_costs_more_instructions_than_all_float(replays):
    """On the M4F (single-precision FPU) every double operation is a libgcc call."""
    assert replays[("double", 0)]["insns_quiet_median"] > 3 * replays[("floatonly", 0)]["insns_quiet_median"]


@pytest.mark.parametrize("precision", ["floatonly", "double"])
def test_stack_high_water_is_inside_the_painted_region(replays, precision):
    r = replays[(precision, 0)]
    assert not r["stack_overflow"]
    assert 256 < r["stack_bytes"] < r["stack_painted_bytes"]
    assert r["stack_bytes"] < r["stack_from_top_bytes"] < r["stack_painted_bytes"]   # main's own frame above


@pytest.mark.parametrize("precision", ["floatonly", "double"])
def test_footprint_sizes_agree_with_the_state_type(built, replays, precision):
    fp = BT.footprint(BUILD_DIR, "an386", precision)
    assert fp["state_bytes"] == replays[(precision, 0)]["state_bytes_sizeof"]   # nm's `cal` = sizeof(mkc_mag_t)
    assert fp["bss_bytes"] >= fp["state_bytes"]
    origin = fp["text_by_origin"]
    assert min(origin.values()) > 0
    assert origin["library"] > origin["program"]
    assert sum(origin.values()) <= fp["text_bytes"] <= sum(origin.values()) + 1024   # the rest: alignment fill


def test_a_harness_output_without_the_figures_is_an_error():
    with pytest.raises(BT.MeasureError, match="no MKC_MEASURE line"):
        BT.parse_measure_line("mkc target replay: cannot read mkc_in.bin\n")
    assert BT.parse_measure_line("x\nMKC_MEASURE samples=3 worst_ticks=7\n") == {"samples": 3, "worst_ticks": 7}
