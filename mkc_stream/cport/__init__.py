"""The bridge to the C99 reference port (firmware_ref/): build it, load it through ctypes, cross-check it.

    toolchain.py where the port is, whether it can be built here (toolchain_problem), `make` (build)
    bindings.py  the ctypes library (load), CStreamingMKC, CMagCalibrator, the field and reason ids
    compare.py   checkpoint records of the Python reference and of the C port, compare_checkpoints,
                 the teacher-forced segment comparison, TOLERANCES

    from mkc_stream import cport
    cal = cport.CMagCalibrator(window=256, estep_every=32, precision="double")   # or "float"
    py, _ = cport.python_checkpoints(mags); c, _ = cport.c_checkpoints(mags)
    cport.compare_checkpoints(py, c).failures("double")

Nothing here is a second production API: the objects mirror StreamingMKC and MagCalibrator closely
enough for the tests, the tools and `mkc-stream crosscheck`. The golden vectors' files belong to the
tests and tools (tools/golden.py), not to the package.
"""
from .bindings import (  # noqa: F401
    F_A, F_C, F_C0S0, F_CELL_COUNT, F_CNT, F_COND, F_D, F_DEQ, F_HES, F_L, F_LAST_F, F_MAG_FLAGS, F_NORMAL_A,
    F_NORMAL_B, F_RAW, F_SIGMA, F_SLOT_AGE, F_SLOT_CELL, F_THETA, F_TPREV, F_X, F_XS, F_Y, FAIL_CONDITION,
    FAIL_COVERAGE, FAIL_DISAGREEMENT, FAIL_FIELD_NONPOSITIVE, FAIL_FIELD_RANGE, FAIL_OUTLIERS, FAIL_RESIDUAL,
    NOT_CALIBRATED, QUALITY_KEYS, REASON_COVERAGE_WAIT, REASON_EMPTY, REASON_INDEFINITE, REASON_INITIAL,
    REASON_NONE, REASON_NOT_FINITE, REASON_PENDING, REASON_REJECTED, REASON_SINGULAR, REASON_WINDOW,
    CCalibration, CCheckpointEvent, CMagCalibrator, CStreamingMKC, load, reason_text,
)
from .toolchain import (  # noqa: F401
    BUILD_DIR, FIRMWARE_DIR, PRECISIONS, FirmwareUnavailable, binary_path, build, replay_path, run_make,
    toolchain_problem,
)
from .compare import (  # noqa: F401
    CORE_QUANTITIES, TOLERANCES, Comparison, c_checkpoints, c_segment, compare_checkpoints, load_reference_state,
    python_checkpoints, reason_kind, reference_state, rel_diff, segment_comparison, stream_records_c,
    stream_records_python, well_posed,
)

__all__ = sorted(name for name in dir() if not name.startswith("_") and name not in ("bindings", "compare", "toolchain"))
