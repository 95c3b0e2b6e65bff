#!/usr/bin/env python
"""The calibrator measured on the emulated Cortex-M4F (qemu-system-arm -M mps2-an386): flash, RAM,
stack high-water mark and instructions per sample, per precision, at the firmware capacity (n = 9,
m = 1, W = 256).

    python tools/bench_firmware_target.py                       # double and all-float, syn_s3_b25
    python tools/bench_firmware_target.py --precisions double float floatonly --json out/target.json
    python tools/bench_firmware_target.py --board an505         # the Cortex-M33 board
    python tools/bench_firmware_target.py --precisions floatonly --estep-every 128   # another E-step period
    python tools/bench_firmware_target.py --flash-only --precisions double float floatonly   # no emulator

It runs `make -C firmware_ref measure` (BUILD=--build), then per precision:
- flash and RAM of BOARD_footprint_PRECISION.elf (target/footprint_main.c: the smallest firmware using
  the calibrator) from `arm-none-eabi-size` (text holds code and constants: the linker script puts
  .rodata in .text), split by the link map into the library (libmkc_*.a) and the runtime (newlib's
  libm and libc, libgcc's software double); the state is `cal` in `arm-none-eabi-nm -S`;
- the flash the library adds to a firmware: text + data (the initial values of .data are stored in
  flash) of that firmware minus the same of BOARD_footprint_base_PRECISION.elf
  (target/footprint_base_main.c: the same reset, vectors and sensor loop without the calibrator),
  linked with the same flags; it is the library's code and constants plus the libm, libc and libgcc
  functions it pulls in (listed by archive member);
- a whole replay of a golden vector through BOARD_measure_PRECISION.elf (target/measure_main.c) under
  `-icount shift=S,sleep=off`: every guest instruction takes 2^S virtual ns, the board's 25 MHz FPGAIO
  counter reads floor(virtual ns / 40), so instructions = ticks * 40 / 2^S, each per-sample figure
  exact to +-40 / 2^S instructions (target/virtual_clock.h; AN505: 20 MHz, 50 ns). A loop of known length (2 instructions
  per iteration, two lengths, the difference removes the fixed part) checks that model on every run;
  the stack high-water mark comes from painting.
Instructions are not cycles: on a real Cortex-M4F a load takes 2 cycles, VDIV/VSQRT 14, a taken branch
1-3; the counts are -Os code, deterministic, and comparable between builds.
Prints a markdown table; --json writes the figures.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import re
import shutil
import struct
import subprocess
import sys
import tempfile

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

import golden as GV  # noqa: E402  (tools/golden.py: the golden vectors' files)

from mkc_stream import cport as FW  # noqa: E402

BOARDS = {"an386": "mps2-an386", "an505": "mps2-an505"}   # Cortex-M4F, Cortex-M33
CORES = {"an386": "Cortex-M4F", "an505": "Cortex-M33"}
#: virtual ns per tick of the FPGAIO counter (and SysTick): qemu's AN386 runs them at 25 MHz, its AN505
#: at 20 MHz (the calibration loop confirms both on every run)
COUNTER_NS_PER_TICK = {"an386": 40.0, "an505": 50.0}
PRECISION_NAMES = {"double": "double", "float": "float (double accumulators and E-step)", "floatonly": "all-float"}
#: the acceptance targets (M4F, W = 256, all-float), bytes and instructions
#: (flash: the bytes the library adds to a firmware, flash_added_bytes)
TARGETS = {"state_bytes": 8 * 1024, "flash_bytes": 24 * 1024, "stack_bytes": 2 * 1024, "insns_per_sample": 3000}
COST_ESTEP, COST_CHECKPOINT = 1, 2
IN_MAGIC, IO_VERSION = 0x49434B4D, 1
QEMU_TIMEOUT_S = 600
#: how far the calibration loop may be from the model (fraction): the model is exact up to one tick
CALIBRATION_TOLERANCE = 0.01


class MeasureError(RuntimeError):
    """The build, the emulator or the measuring harness failed; the message says how."""


def missing_tools() -> str | None:
    for tool, package in (("make", "make"), ("arm-none-eabi-gcc", "gcc-arm-none-eabi libnewlib-arm-none-eabi"),
                          ("qemu-system-arm", "qemu-system-arm")):
        if shutil.which(tool) is None:
            return f"no `{tool}` on PATH (apt-get install {package})"
    return None


def build(build_dir: pathlib.Path | None = None, targets: tuple[str, ...] = ("measure",)) -> None:
    """make -C firmware_ref [BUILD=build_dir] TARGETS, under the build lock the tests share. Without
    build_dir the Makefile's own build/ (no BUILD= argument, so its targets keep the names the other
    builds use); targets may name single programs, e.g. build/qemu/an386_measure_floatonly.elf."""
    proc = FW.run_make("-j2", *([f"BUILD={build_dir}"] if build_dir is not None else []), *targets)
    if proc.returncode != 0:
        raise MeasureError(f"make {' '.join(targets)} failed:\n{proc.stdout[-3000:]}{proc.stderr[-3000:]}")


def footprint_targets(build_dir: pathlib.Path | None, board: str, precisions) -> tuple[str, ...]:
    """The make targets of the footprint programs, named as the Makefile names them: under
    BUILD=build_dir when given, else relative to firmware_ref/ (its default BUILD is `build`; an
    absolute path there names no rule, and make then reports nothing to do or fails)."""
    root = str(build_dir) if build_dir is not None else "build"
    return tuple(f"{root}/qemu/{board}_{kind}_{p}.elf" for p in precisions for kind in ("footprint", "footprint_base"))


def write_input(name: str, path: pathlib.Path, samples: int = 0, estep_every: int = 0) -> int:
    """Golden vector `name`'s stored input as the harness's mkc_in.bin (first `samples`, 0: all), with
    the vector's configuration (estep_every > 0: that E-step period K instead). Returns the samples
    written."""
    index = json.loads((GV.GOLDEN_DIR / "index.json").read_text())
    vectors = {v["name"]: v for v in index["vectors"]}
    if name not in vectors:
        raise MeasureError(f"no golden vector {name!r}")
    v = vectors[name]
    if v["kind"] != "mag":
        raise MeasureError(f"golden vector {name!r} is not a magnetometer stream")
    inp = GV.stored_input(v)
    mags = np.ascontiguousarray(inp["mags"], dtype="<f8")
    if samples:
        mags = mags[:samples]
    cfg = v["config"]
    policy = {"fifo": 0, "direction": 1}[cfg["policy"]]
    head = struct.pack("<8i", IN_MAGIC, IO_VERSION, cfg["window"], estep_every or cfg["estep_every"], policy,
                       int(inp["unit"] == "uT"), 0, len(mags))
    path.write_bytes(head + mags.tobytes())
    return len(mags)


#: the figures the measuring harness prints (target/measure_main.c)
MEASURE_KEYS = ("samples", "checkpoints", "esteps", "ticks_sum", "worst_ticks", "worst_sample", "worst_flags",
                "empty_ticks", "loop_a_iters", "loop_a_ticks", "loop_b_iters", "loop_b_ticks", "systick_b_ticks",
                "stack_call_bytes", "stack_top_bytes", "stack_painted_bytes", "stack_overflow", "state_bytes",
                "clock_end_ticks")


def parse_measure_line(text: str, required=()) -> dict:
    """The harness's "MKC_MEASURE key=value ..." line as a dict of ints; MeasureError when it is missing
    or lacks one of the `required` keys."""
    for line in text.splitlines():
        if line.startswith("MKC_MEASURE "):
            out = {k: int(v) for k, v in (kv.split("=", 1) for kv in line.split()[1:])}
            missing = [k for k in required if k not in out]
            if missing:
                raise MeasureError(f"the MKC_MEASURE line lacks {missing}: {line!r}")
            return out
    raise MeasureError(f"no MKC_MEASURE line in the emulator's output: {text[-500:]!r}")


def run_measure(elf: pathlib.Path, workdir: pathlib.Path, board: str = "an386", shift: int = 0,
                plugin: pathlib.Path | None = None, profile: bool = False) -> dict:
    """One replay of workdir/mkc_in.bin through the measuring harness under -icount shift=`shift`.

    Returns the harness's figures converted to instructions and bytes, with the per-sample costs. With
    `plugin` (target/insn_count_plugin.c built), qemu also counts every instruction of the run, and
    "plugin_check" compares that with the counter's whole-run reading; with `profile` too, "profile"
    gives the whole run's instructions per function (profile_by_function)."""
    (workdir / "mkc_cost.bin").unlink(missing_ok=True)
    args = ["qemu-system-arm", "-M", BOARDS[board], "-icount", f"shift={shift},sleep=off", "-nographic",
            "-monitor", "none", "-serial", "none", "-semihosting-config", "enable=on,target=native",
            "-kernel", str(elf)]
    counted = workdir / "plugin_insns.txt"
    counted.unlink(missing_ok=True)
    blocks = workdir / "plugin_blocks.txt"
    if plugin is not None:
        args += ["-plugin", f"{plugin},out={counted}" + (f",profile={blocks}" if profile else "")]
    try:
        proc = subprocess.run(args, cwd=workdir, capture_output=True, text=True, timeout=QEMU_TIMEOUT_S)
    except subprocess.TimeoutExpired as exc:
        raise MeasureError(f"{elf.name}: no exit within {QEMU_TIMEOUT_S} s") from exc
    if proc.returncode != 0:
        raise MeasureError(f"{elf.name}: exit {proc.returncode}: {proc.stdout[-500:]} {proc.stderr[-500:]}")
    raw = parse_measure_line(proc.stdout + proc.stderr, MEASURE_KEYS)
    insns_per_tick = COUNTER_NS_PER_TICK[board] / 2.0 ** shift
    cost = np.fromfile(workdir / "mkc_cost.bin", dtype="<u4").reshape(-1, 2)
    if len(cost) != raw["samples"]:
        raise MeasureError(f"{elf.name}: {len(cost)} per-sample records for {raw['samples']} samples")
    insns = cost[:, 0].astype(np.float64) * insns_per_tick
    flags = cost[:, 1]
    quiet = (flags & (COST_ESTEP | COST_CHECKPOINT)) == 0
    # calibration: the loop's b - a iterations of 2 instructions, against the ticks they took
    loop_insns = 2 * (raw["loop_b_iters"] - raw["loop_a_iters"])
    loop_counted = (raw["loop_b_ticks"] - raw["loop_a_ticks"]) * insns_per_tick
    worst = int(np.argmax(insns))
    plugin_check = None
    if plugin is not None:
        if not counted.exists():
            raise MeasureError(f"{elf.name}: the instruction-counting plugin wrote nothing")
        total = int(counted.read_text())
        clock = raw["clock_end_ticks"] * insns_per_tick
        plugin_check = {"plugin_instructions": total, "clock_instructions": clock,
                        "relative_difference": abs(total - clock) / total}
        if profile:
            plugin_check["profile"] = profile_by_function(blocks, elf)
    return {
        "samples": raw["samples"], "checkpoints": raw["checkpoints"], "esteps": raw["esteps"],
        "insns_per_tick": insns_per_tick,
        "insns_per_sample": float(insns.mean()),
        "insns_total": float(insns.sum()),
        "insns_worst": float(insns[worst]), "worst_sample": worst + 1,
        "worst_is_checkpoint": bool(flags[worst] & COST_CHECKPOINT), "worst_has_estep": bool(flags[worst] & COST_ESTEP),
        "insns_quiet_median": float(np.median(insns[quiet])) if quiet.any() else None,
        "insns_quiet_max": float(insns[quiet].max()) if quiet.any() else None,
        "insns_checkpoint_mean": float(insns[~quiet].mean()) if (~quiet).any() else None,
        "checkpoint_share": float(insns[~quiet].sum() / insns.sum()) if insns.sum() else None,
        "calibration": {"loop_instructions": loop_insns, "counted_instructions": loop_counted,
                        "relative_error": abs(loop_counted - loop_insns) / loop_insns,
                        "systick_ticks": raw["systick_b_ticks"], "counter_ticks": raw["loop_b_ticks"]},
        "plugin_check": plugin_check,
        "empty_interval_insns": raw["empty_ticks"] * insns_per_tick,
        "stack_bytes": raw["stack_call_bytes"], "stack_from_top_bytes": raw["stack_top_bytes"],
        "stack_painted_bytes": raw["stack_painted_bytes"], "stack_overflow": bool(raw["stack_overflow"]),
        "state_bytes_sizeof": raw["state_bytes"],
        "per_sample_insns": insns, "per_sample_flags": flags,
    }


def profile_by_function(blocks: pathlib.Path, elf: pathlib.Path) -> dict:
    """Instructions per function over the whole run, from the plugin's per-block counts: each block's
    instructions x executions go to the function whose symbol (arm-none-eabi-nm) starts at or before
    the block's address (a block never crosses into the next function: a call or return ends it)."""
    out = subprocess.run(["arm-none-eabi-nm", "-S", "--defined-only", str(elf)], capture_output=True, text=True,
                         check=True).stdout
    funcs = sorted((int(a, 16) & ~1, name) for a, _size, kind, name in
                   (line.split() for line in out.splitlines() if len(line.split()) == 4) if kind in "tTwW")
    starts = np.array([a for a, _ in funcs])
    totals: dict[str, int] = {}
    for line in blocks.read_text().splitlines():
        vaddr, insns, executions = line.split()
        i = int(np.searchsorted(starts, int(vaddr, 16), side="right")) - 1
        name = funcs[i][1] if i >= 0 else "?"
        totals[name] = totals.get(name, 0) + int(insns) * int(executions)
    return dict(sorted(totals.items(), key=lambda kv: -kv[1]))


def size_of(elf: pathlib.Path) -> dict:
    """text, data, bss of an ELF (arm-none-eabi-size, Berkeley format)."""
    out = subprocess.run(["arm-none-eabi-size", str(elf)], capture_output=True, text=True, check=True).stdout
    text, data, bss = (int(x) for x in out.splitlines()[1].split()[:3])
    return {"text": text, "data": data, "bss": bss}


def symbol_size(elf: pathlib.Path, name: str) -> int:
    """Size in bytes of the symbol `name` (arm-none-eabi-nm -S)."""
    out = subprocess.run(["arm-none-eabi-nm", "-S", str(elf)], capture_output=True, text=True, check=True).stdout
    for line in out.splitlines():
        parts = line.split()
        if len(parts) == 4 and parts[3] == name:
            return int(parts[1], 16)
    raise MeasureError(f"{elf.name}: no symbol {name!r}")


_INPUT_SECTION = re.compile(r"^\s+(?:(\S+)\s+)?0x([0-9a-f]+)\s+0x([0-9a-f]+)\s+(\S+\.(?:o|a\(\S+\)|o\)))\s*$")


def text_by_member(map_path: pathlib.Path) -> dict:
    """Bytes of the output section .text (code and constants) by the object or archive member they come
    from, from the link map, e.g. {"libm.a(lib_a-sf_expm1.o)": 624, "footprint_main.o": 156}."""
    out: dict[str, int] = {}
    in_text = False
    for line in map_path.read_text().splitlines():
        if re.match(r"^\.\S+", line):               # an output section starts
            in_text = line.split()[0] == ".text"
            continue
        if not in_text:
            continue
        m = _INPUT_SECTION.match(line)
        if not m or int(m.group(3), 16) == 0:
            continue
        member = m.group(4).rsplit("/", 1)[-1]
        out[member] = out.get(member, 0) + int(m.group(3), 16)
    return out


def origin_of(member: str) -> str:
    """"library" (libmkc_*.a), "runtime" (libm, libc, libgcc and the other toolchain archives) or
    "program" (the firmware's own objects: reset, vectors, main)."""
    return "library" if member.startswith("libmkc_") else "runtime" if ".a(" in member else "program"


def text_by_origin(map_path: pathlib.Path) -> dict:
    """Bytes of the output section .text (code and constants) by where they come from (origin_of)."""
    out = {"library": 0, "runtime": 0, "program": 0}
    for member, n in text_by_member(map_path).items():
        out[origin_of(member)] += n
    return out


def flash_added(build_dir: pathlib.Path, board: str, precision: str) -> dict:
    """The flash the library adds to a firmware: text + data of BOARD_footprint_PRECISION.elf (the
    smallest firmware using the calibrator) minus the same of BOARD_footprint_base_PRECISION.elf (that
    firmware without the calibrator), both linked with the same flags. "added_by_origin" splits it
    into the library's own code and constants and the runtime functions it pulls in (by_member: each
    archive member it adds, largest first); "program" is main's own change. The members' sum and the
    data differ from the whole by the alignment fill between sections (tens of bytes)."""
    app_elf = build_dir / "qemu" / f"{board}_footprint_{precision}.elf"
    base_elf = build_dir / "qemu" / f"{board}_footprint_base_{precision}.elf"
    for elf in (app_elf, base_elf):
        if not elf.exists():
            raise MeasureError(f"{elf} not built (make -C firmware_ref measure)")
    app, base = size_of(app_elf), size_of(base_elf)
    app_members, base_members = text_by_member(app_elf.with_suffix(".map")), text_by_member(base_elf.with_suffix(".map"))
    added = {k: app_members.get(k, 0) - base_members.get(k, 0) for k in app_members.keys() | base_members.keys()
             if app_members.get(k, 0) != base_members.get(k, 0)}
    by_origin = {"library": 0, "runtime": 0, "program": 0}
    for member, n in added.items():
        by_origin[origin_of(member)] += n
    return {"flash_added_bytes": (app["text"] + app["data"]) - (base["text"] + base["data"]),
            "flash_app_bytes": app["text"] + app["data"], "flash_base_bytes": base["text"] + base["data"],
            "added_data_bytes": app["data"] - base["data"], "added_by_origin": by_origin,
            "added_by_member": dict(sorted(added.items(), key=lambda kv: -kv[1]))}


def footprint(build_dir: pathlib.Path, board: str, precision: str) -> dict:
    elf = build_dir / "qemu" / f"{board}_footprint_{precision}.elf"
    sizes = size_of(elf)
    return {"text_bytes": sizes["text"], "data_bytes": sizes["data"], "bss_bytes": sizes["bss"],
            "ram_bytes": sizes["data"] + sizes["bss"], "state_bytes": symbol_size(elf, "cal"),
            "text_by_origin": text_by_origin(elf.with_suffix(".map"))}


def plugin_problem(plugin: pathlib.Path, elf: pathlib.Path, board: str = "an386") -> str | None:
    """Why qemu-system-arm cannot count instructions with the plugin here (a run of `elf`, a program that
    exits at once, e.g. the footprint firmware), or None when it can."""
    if not plugin.exists():
        return f"{plugin} not built"
    with tempfile.TemporaryDirectory(prefix="mkc_plugin_") as tmp:
        out = pathlib.Path(tmp) / "n.txt"
        proc = subprocess.run(["qemu-system-arm", "-M", BOARDS[board], "-nographic", "-monitor", "none", "-serial",
                               "none", "-semihosting-config", "enable=on,target=native",
                               "-plugin", f"{plugin},out={out}", "-kernel", str(elf)],
                              capture_output=True, text=True, timeout=QEMU_TIMEOUT_S)
        if proc.returncode != 0 or not out.exists():
            return f"qemu cannot run it (exit {proc.returncode}): {(proc.stdout + proc.stderr).strip()[:300]}"
    return None


def measure(build_dir: pathlib.Path, board: str, precision: str, vector: str, samples: int, shift: int,
            plugin: pathlib.Path | None = None, profile: bool = False, estep_every: int = 0) -> dict:
    fp = {**footprint(build_dir, board, precision), **flash_added(build_dir, board, precision)}
    with tempfile.TemporaryDirectory(prefix="mkc_measure_") as tmp:
        work = pathlib.Path(tmp)
        write_input(vector, work / "mkc_in.bin", samples, estep_every)
        run = run_measure(build_dir / "qemu" / f"{board}_measure_{precision}.elf", work, board, shift, plugin,
                          profile)
    cal = run["calibration"]
    # the two counters time the same loop, each reading rounded to its own tick: one tick apart
    # is their resolution (a code layout can put the readings either side of a tick boundary)
    if cal["relative_error"] > CALIBRATION_TOLERANCE or abs(cal["systick_ticks"] - cal["counter_ticks"]) > 1:
        raise MeasureError(f"the instruction-count model does not hold: {cal}")
    if run["stack_overflow"]:
        raise MeasureError(f"{board} {precision}: the stack went below the painted {run['stack_painted_bytes']} bytes")
    run.pop("per_sample_insns")
    run.pop("per_sample_flags")
    return {"board": board, "core": CORES[board], "precision": precision, "vector": vector, "shift": shift,
            "estep_every": estep_every or None, **fp, **run}


def runtime_groups(by_member: dict) -> dict:
    """The runtime members of flash_added's by_member summed per archive: libm, libc, libgcc."""
    out: dict[str, int] = {}
    for member, n in by_member.items():
        if origin_of(member) == "runtime":
            lib = member.split("(", 1)[0].removesuffix(".a").replace("libc_nano", "libc")
            out[lib] = out.get(lib, 0) + n
    return dict(sorted(out.items(), key=lambda kv: -kv[1]))


def flash_markdown(rows: list[dict]) -> str:
    """The flash the library adds per build, split into its own code and the runtime it pulls in."""
    lines = ["| build | flash added by the library, B | its own code and constants | runtime it pulls in "
             "(by archive) | firmware with / without it |", "|---|---:|---:|---|---:|"]
    for r in rows:
        o = r["added_by_origin"]
        groups = ", ".join(f"{k} {n:,}" for k, n in runtime_groups(r["added_by_member"]).items())
        lines.append(f"| {PRECISION_NAMES[r['precision']]} | {r['flash_added_bytes']:,} | {o['library']:,} | "
                     f"{o['runtime']:,} ({groups}) | {r['flash_app_bytes']:,} / {r['flash_base_bytes']:,} |")
    return "\n".join(lines)


def markdown(rows: list[dict]) -> str:
    head = ("| build | flash added, B | text+rodata B (library / runtime / program) | state B | data+bss B "
            "| stack B | instructions/sample, amortised | between checkpoints (median) | worst sample | at sample |")
    lines = [head, "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        o = r["text_by_origin"]
        kind = "checkpoint" if r["worst_is_checkpoint"] else "E-step" if r["worst_has_estep"] else "sample"
        lines.append(f"| {PRECISION_NAMES[r['precision']]} | {r['flash_added_bytes']:,} | {r['text_bytes']:,} "
                     f"({o['library']:,} / {o['runtime']:,} / "
                     f"{o['program']:,}) | {r['state_bytes']:,} | {r['ram_bytes']:,} | {r['stack_bytes']:,} | "
                     f"{r['insns_per_sample']:,.0f} | {r['insns_quiet_median']:,.0f} | {r['insns_worst']:,.0f} | "
                     f"{r['worst_sample']} ({kind}) |")
    return "\n".join(lines)


def target_table(rows: list[dict]) -> str:
    """Each build against the acceptance targets (met: yes / no)."""
    checks = (("state", "state_bytes", "state_bytes"), ("flash added", "flash_bytes", "flash_added_bytes"),
              ("stack", "stack_bytes", "stack_bytes"), ("instructions/sample", "insns_per_sample", "insns_per_sample"))
    lines = ["| figure | target | " + " | ".join(PRECISION_NAMES[r["precision"]] for r in rows) + " |",
             "|---|---:|" + "---:|" * len(rows)]
    for label, tkey, rkey in checks:
        cells = [f"{r[rkey]:,.0f} ({'met' if r[rkey] <= TARGETS[tkey] else 'not met'})" for r in rows]
        lines.append(f"| {label} | <= {TARGETS[tkey]:,} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def flash_main(args) -> int:
    """--flash-only: the footprint firmware with and without the library, per precision (arm-none-eabi-gcc
    only: no qemu needed)."""
    if shutil.which("arm-none-eabi-gcc") is None:
        print("cannot measure: no `arm-none-eabi-gcc` on PATH (apt-get install gcc-arm-none-eabi "
              "libnewlib-arm-none-eabi)", file=sys.stderr)
        return 2
    build_dir = args.build.resolve() if args.build else None
    bdir = build_dir or FW.FIRMWARE_DIR / "build"
    try:
        build(build_dir, footprint_targets(build_dir, args.board, args.precisions))
        rows = [{"board": args.board, "core": CORES[args.board], "precision": p, **flash_added(bdir, args.board, p)}
                for p in args.precisions]
    except MeasureError as exc:
        print(f"measurement failed: {exc}", file=sys.stderr)
        return 1
    print(f"{CORES[args.board]}: the flash the library adds to a firmware (text + data of "
          f"target/footprint_main.c minus target/footprint_base_main.c; -Os, --gc-sections, newlib nano)\n")
    print(flash_markdown(rows))
    for r in rows:
        ok = "met" if r["flash_added_bytes"] <= TARGETS["flash_bytes"] else "not met"
        print(f"\n{PRECISION_NAMES[r['precision']]}: {r['flash_added_bytes']:,} B against <= "
              f"{TARGETS['flash_bytes']:,} ({ok}); the runtime members it adds: " + ", ".join(
                  f"{k} {n:,}" for k, n in r["added_by_member"].items() if origin_of(k) == "runtime"))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"rows": rows, "targets": TARGETS}, indent=2) + "\n")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--board", choices=sorted(BOARDS), default="an386")
    ap.add_argument("--precisions", nargs="+", choices=sorted(PRECISION_NAMES), default=["double", "floatonly"])
    ap.add_argument("--vector", default="syn_s3_b25", help="golden vector to replay (W = 256, K = 32 by default)")
    ap.add_argument("--samples", type=int, default=0, help="replay only the first N samples (0: all)")
    ap.add_argument("--estep-every", type=int, default=0, metavar="K",
                    help="E-step period K instead of the vector's (how the checkpoints' share scales)")
    ap.add_argument("--shift", type=int, default=0, help="qemu -icount shift (2^shift virtual ns per instruction)")
    ap.add_argument("--build", type=pathlib.Path, help="build directory (default: firmware_ref/build)")
    ap.add_argument("--no-plugin", action="store_true",
                    help="skip the cross-check by the instruction-counting qemu plugin (it slows qemu ~1.5x)")
    ap.add_argument("--profile", type=int, default=0, metavar="N",
                    help="also list the N functions that execute the most instructions over the whole run (plugin)")
    ap.add_argument("--flash-only", action="store_true",
                    help="only the flash the library adds (builds the footprint programs; no emulator)")
    ap.add_argument("--json", type=pathlib.Path, help="write the figures here")
    args = ap.parse_args(argv)
    if args.flash_only:
        return flash_main(args)
    why = missing_tools()
    if why:
        print(f"cannot measure: {why}", file=sys.stderr)
        return 2
    try:
        build_dir = args.build.resolve() if args.build else None
        build(build_dir)
        build_dir = build_dir or FW.FIRMWARE_DIR / "build"
        plugin = build_dir / "qemu" / "insn_count_plugin.so"
        why_no_plugin = None if args.no_plugin else plugin_problem(
            plugin, build_dir / "qemu" / f"{args.board}_footprint_{args.precisions[0]}.elf", args.board)
        use_plugin = None if args.no_plugin or why_no_plugin else plugin
        if args.profile and not use_plugin:
            raise MeasureError(f"--profile needs the instruction-counting plugin: {why_no_plugin or '--no-plugin'}")
        if args.estep_every < 0:
            raise MeasureError(f"--estep-every must be >= 1, not {args.estep_every}")
        rows = [measure(build_dir, args.board, p, args.vector, args.samples, args.shift, use_plugin,
                        args.profile > 0, args.estep_every) for p in args.precisions]
    except MeasureError as exc:
        print(f"measurement failed: {exc}", file=sys.stderr)
        return 1
    r0 = rows[0]
    period = f", K = {args.estep_every}" if args.estep_every else ""
    print(f"{CORES[args.board]} (qemu-system-arm -M {BOARDS[args.board]} -icount shift={args.shift},sleep=off), "
          f"W = 256{period}, golden vector {args.vector}: {r0['samples']} samples, {r0['checkpoints']} checkpoints; "
          f"bytes and instructions (-Os)\n")
    print(markdown(rows))
    print()
    print(target_table(rows))
    print(f"\ncalibration: a loop of {r0['calibration']['loop_instructions']:,} instructions counted as "
          f"{r0['calibration']['counted_instructions']:,.0f} (FPGAIO counter; SysTick agrees: "
          f"{abs(r0['calibration']['systick_ticks'] - r0['calibration']['counter_ticks']) <= 1})")
    for r in rows:
        pc = r["plugin_check"]
        if pc:
            print(f"cross-check, {PRECISION_NAMES[r['precision']]}: the whole run is {pc['plugin_instructions']:,} "
                  f"instructions by the counting plugin, {pc['clock_instructions']:,.0f} by the counter "
                  f"(relative difference {pc['relative_difference']:.1e})")
    for r in rows if args.profile else ():
        prof = r["plugin_check"]["profile"]
        total = sum(prof.values())
        print(f"\nwhole run, {PRECISION_NAMES[r['precision']]}: the {args.profile} functions executing the most "
              f"instructions (their own, not their callees')\n\n| function | instructions | share |\n|---|---:|---:|")
        for name, n in list(prof.items())[:args.profile]:
            print(f"| `{name}` | {n:,} | {n / total:.1%} |")
    if not args.no_plugin and why_no_plugin:
        print(f"cross-check by the instruction-counting plugin not run: {why_no_plugin}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"rows": rows, "targets": TARGETS}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
