"""The replay harness of firmware_ref/target/ (replay_main.c) from Python: its input file, its output
records, and a run on the host or on an emulated board (qemu-system-arm with semihosting).

`make -C firmware_ref qemu` builds the programs into firmware_ref/build/qemu/: host_PRECISION (the
host compiler, stdio) and BOARD_PRECISION.elf (BOARD an386: Cortex-M4F, an505: Cortex-M33), PRECISION
double, float (double normal equations and E-step) or floatonly (all-float). Each reads mkc_in.bin in
its working directory and writes mkc_out.bin there: one record of RECORD doubles per checkpoint, then
a final record whose first value is -1.
"""
from __future__ import annotations

import pathlib
import struct
import subprocess

import numpy as np

BOARDS = {"an386": "mps2-an386", "an505": "mps2-an505"}   # Cortex-M4F, Cortex-M33
PRECISIONS = ("double", "float", "floatonly")

# the input header: magic, version, window W, E-step period K, policy (0 fifo, 1 direction), unit
# (1 uT, 0 raw counts), reserved, samples T; then T x 3 little-endian doubles
IN_MAGIC, IO_VERSION = 0x49434B4D, 1
POLICIES = {"fifo": 0, "direction": 1}

# the record layout (doubles): samples seen, E-steps, status, accepted, has a trial, reason code,
# theta (9), sigma, d, a, c0 s0 (4), hard iron b (3), soft iron S (9, row-major), field F, quality (7)
N_QUALITY = 7
O_SEEN, O_ESTEPS, O_STATUS, O_ACCEPTED, O_HAS_TRIAL, O_REASON, O_THETA = range(7)
O_SIGMA, O_D, O_A, O_C0S0 = 15, 16, 17, 18
O_HARD, O_SOFT, O_FIELD, O_QUALITY = 22, 25, 34, 35
RECORD = O_QUALITY + N_QUALITY
DISCRETE = slice(O_SEEN, O_REASON + 1)


class HarnessError(RuntimeError):
    """The harness failed (exit status, missing output, no exit in time); the message says how."""


def write_input(path: pathlib.Path, mags: np.ndarray, window: int = 256, estep_every: int = 32,
                policy: str = "direction", unit_uT: bool = True) -> None:
    """mags (T, 3) as the harness's mkc_in.bin at path, with the stream's configuration."""
    mags = np.ascontiguousarray(mags, dtype="<f8")
    if mags.ndim != 2 or mags.shape[1] != 3:
        raise ValueError(f"mags must be (T, 3), not {mags.shape}")
    head = struct.pack("<8i", IN_MAGIC, IO_VERSION, window, estep_every, POLICIES[policy], int(unit_uT), 0,
                       len(mags))
    path.write_bytes(head + mags.tobytes())


def read_output(path: pathlib.Path) -> np.ndarray:
    """The records of mkc_out.bin, (checkpoints + 1, RECORD); the last is the final one."""
    recs = np.fromfile(path, dtype="<f8")
    if recs.size % RECORD != 0:
        raise HarnessError(f"{path}: {recs.size} doubles, not whole records")
    recs = recs.reshape(-1, RECORD)
    if len(recs) == 0 or recs[-1, O_SEEN] != -1.0:
        raise HarnessError(f"{path}: the final record is missing")
    return recs


def run_host(qemu_dir: pathlib.Path, precision: str, workdir: pathlib.Path) -> np.ndarray:
    """host_PRECISION over workdir/mkc_in.bin; its records."""
    (workdir / "mkc_out.bin").unlink(missing_ok=True)
    proc = subprocess.run([str(qemu_dir / f"host_{precision}")], cwd=workdir, capture_output=True, text=True)
    if proc.returncode != 0:
        raise HarnessError(f"host {precision}: exit {proc.returncode}: {proc.stderr[-500:]}")
    return read_output(workdir / "mkc_out.bin")


def run_board(qemu_dir: pathlib.Path, board: str, precision: str, workdir: pathlib.Path,
              timeout_s: float = 300.0) -> np.ndarray:
    """BOARD_PRECISION.elf in qemu-system-arm over workdir/mkc_in.bin; its records."""
    (workdir / "mkc_out.bin").unlink(missing_ok=True)
    args = ["qemu-system-arm", "-M", BOARDS[board], "-nographic", "-monitor", "none", "-serial", "none",
            "-semihosting-config", "enable=on,target=native", "-kernel", str(qemu_dir / f"{board}_{precision}.elf")]
    try:
        proc = subprocess.run(args, cwd=workdir, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired as exc:
        raise HarnessError(f"{board} {precision}: no exit within {timeout_s:g} s") from exc
    if proc.returncode != 0 or "done" not in proc.stdout + proc.stderr:
        raise HarnessError(f"{board} {precision}: exit {proc.returncode}: {proc.stdout[-500:]} {proc.stderr[-500:]}")
    return read_output(workdir / "mkc_out.bin")


def accepted_differences(recs: np.ndarray, ref: np.ndarray) -> tuple[dict, int]:
    """Largest relative differences of recs from ref over the checkpoints both accepted: theta
    max |dtheta| / max |theta|, b max |db| / F, S max |dS| (S has determinant 1), F |dF| / F; and
    how many checkpoints that is. Both are record arrays without the final record."""
    acc = (recs[:, O_ACCEPTED] == 1) & (ref[:, O_ACCEPTED] == 1)
    if not acc.any():
        return {"theta": 0.0, "b": 0.0, "S": 0.0, "F": 0.0}, 0
    th, F = ref[acc, O_THETA:O_THETA + 9], np.abs(ref[acc, O_FIELD])
    return {"theta": float(np.max(np.abs(recs[acc, O_THETA:O_THETA + 9] - th)) / float(np.max(np.abs(th)))),
            "b": float(np.max(np.abs(recs[acc, O_HARD:O_HARD + 3] - ref[acc, O_HARD:O_HARD + 3]) / F[:, None])),
            "S": float(np.max(np.abs(recs[acc, O_SOFT:O_SOFT + 9] - ref[acc, O_SOFT:O_SOFT + 9]))),
            "F": float(np.max(np.abs(recs[acc, O_FIELD] - ref[acc, O_FIELD]) / F))}, int(acc.sum())
