"""Where the C port's golden vectors live and how their stored inputs are read back.

Shared by tools/gen_golden.py (which writes them) and the tests (tests/test_firmware.py,
tests/test_stream_conditioning.py, which put tools/ on sys.path): the vectors are test data of this
repository, so the package (mkc_stream/) knows nothing of them.
"""
from __future__ import annotations

import hashlib
import pathlib

import numpy as np

REPO_ROOT = pathlib.Path(__file__).resolve().parents[1]
GOLDEN_DIR = REPO_ROOT / "tests" / "data" / "golden"

#: the arrays a vector's input consists of, by kind; each is stored as little-endian float64
INPUT_KEYS = {"mag": ("input_mags", "input_t"), "linear": ("input_X", "input_Y")}


def input_sha256(arrays) -> str:
    """SHA-256 of the input arrays' little-endian float64 bytes, in order (the stored checksum)."""
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a, dtype="<f8").tobytes())
    return h.hexdigest()


def stored_input(meta: dict) -> dict:
    """A golden vector's input as stored in its file, checked against the index's checksum.

    The input is never regenerated at test time: a synthetic stream rebuilt through BLAS differs in
    its last bits from one CPU to another, and the vectors' checkpoints would no longer apply.
    Magnetometer vectors give {"mags" (T, 3), "t" (T,), "unit"}; linear ones {"X" (T, m, n), "Y" (T, m)}.
    """
    with np.load(GOLDEN_DIR / meta["input_file"]) as z:
        arrays = [z[k] for k in INPUT_KEYS[meta["kind"]]]
    digest = input_sha256(arrays)
    if digest != meta["input_sha256"]:
        raise ValueError(f"golden vector {meta['name']}: stored input fails its checksum "
                         f"({digest[:16]} != {meta['input_sha256'][:16]}); regenerate: python tools/gen_golden.py")
    arrays = [np.ascontiguousarray(a, dtype=np.float64) for a in arrays]
    if meta["kind"] == "mag":
        return {"mags": arrays[0], "t": arrays[1], "unit": meta["unit"]}
    return {"X": arrays[0], "Y": arrays[1]}
