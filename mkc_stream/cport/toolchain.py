"""Building the C99 reference port (firmware_ref/) with its Makefile: where it is, whether it can be built here.

The shared objects firmware_ref/build/libmkc_{double,float}.so and the replay binaries are built on
demand with `make` (a C compiler and make are needed; FirmwareUnavailable says why when they are not).
"""
from __future__ import annotations

import contextlib
import os
import pathlib
import shutil
import subprocess
import threading

try:
    import fcntl
except ImportError:  # not POSIX: the lock holds between threads only
    fcntl = None

FIRMWARE_DIR = pathlib.Path(__file__).resolve().parents[2] / "firmware_ref"
BUILD_DIR = FIRMWARE_DIR / "build"
PRECISIONS = ("double", "float")


class FirmwareUnavailable(RuntimeError):
    """The C port cannot be built or loaded here (no compiler, no make, no source tree)."""


def toolchain_problem() -> str | None:
    """None when the C port can be built here, else the reason it cannot."""
    if not (FIRMWARE_DIR / "Makefile").is_file():
        return f"the C sources are not here ({FIRMWARE_DIR} has no Makefile; an installed package has no firmware_ref/)"
    if shutil.which("make") is None:
        return "no `make` on PATH"
    cc = os.environ.get("CC", "cc")
    if shutil.which(cc) is None:
        return f"no C compiler: `{cc}` is not on PATH (set CC)"
    return None


_build_lock = threading.Lock()


@contextlib.contextmanager
def _make_lock():
    """One `make` in firmware_ref/ at a time, across threads and processes (parallel test workers
    would otherwise compile the same objects at once). POSIX file lock; without fcntl, threads only."""
    with _build_lock:
        if fcntl is None:
            yield
            return
        BUILD_DIR.mkdir(parents=True, exist_ok=True)
        with open(BUILD_DIR / ".make-lock", "a") as fh:
            fcntl.flock(fh, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(fh, fcntl.LOCK_UN)


def run_make(*args: str) -> subprocess.CompletedProcess:
    """`make -C firmware_ref ARGS` under the build lock; the caller judges the return code."""
    with _make_lock():
        return subprocess.run(["make", "-C", str(FIRMWARE_DIR), *args], capture_output=True, text=True)


def build(*targets: str) -> None:
    """Run `make -C firmware_ref TARGETS` (default: all). Raises FirmwareUnavailable on failure."""
    why = toolchain_problem()
    if why:
        raise FirmwareUnavailable(why)
    proc = run_make(*targets)
    if proc.returncode != 0:
        raise FirmwareUnavailable(f"make -C firmware_ref {' '.join(targets)} failed:\n{proc.stdout[-3000:]}"
                                  f"{proc.stderr[-3000:]}")


def binary_path(name: str) -> pathlib.Path:
    return BUILD_DIR / name


def replay_path(precision: str = "double", sanitize: bool = False) -> pathlib.Path:
    name = "mkc_replay" if precision == "double" else "mkc_replay_float"
    return BUILD_DIR / ("asan" if sanitize else "") / name
