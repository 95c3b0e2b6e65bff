"""One decorator policy for every jitted kernel.

cache=True so a second process starts fast; nogil so callers may thread; never fastmath,
because kernels are cross-checked bit-for-bit-ish against the C port and against NumPy.

Numba keys a cached kernel on its own file's timestamp only: when a kernel's callee in another
file changes (say estep.py under window.py), the caller's cached machine code keeps the old
callee. So on import we stamp every kernel source file together and drop the package's cached
kernels when any of them changed. (An installed package never hits this; a working tree does.)
"""
import hashlib
import pathlib

import numba

_PKG = pathlib.Path(__file__).resolve().parent


def _drop_stale_kernel_cache():
    try:
        sources = sorted(p for p in _PKG.rglob("*.py") if "import kernel" in p.read_text(encoding="utf-8"))
        stamp = hashlib.sha1("".join(f"{p}:{p.stat().st_mtime_ns}:{p.stat().st_size};" for p in sources)
                             .encode()).hexdigest()
        marker = _PKG / "__pycache__" / "kernel_sources.stamp"
        if marker.is_file() and marker.read_text() == stamp:
            return
        for pattern in ("*.nbi", "*.nbc"):
            for f in _PKG.rglob(pattern):
                f.unlink(missing_ok=True)
        marker.parent.mkdir(exist_ok=True)
        tmp = marker.with_suffix(".tmp")
        tmp.write_text(stamp)
        tmp.replace(marker)
    except OSError:
        pass          # a read-only install: nothing to drop, numba caches elsewhere


_drop_stale_kernel_cache()


def kernel(fn=None, **overrides):
    opts = dict(cache=True, nogil=True, fastmath=False, error_model="numpy")
    opts.update(overrides)
    if fn is None:
        return lambda f: numba.njit(**opts)(f)
    return numba.njit(**opts)(fn)
