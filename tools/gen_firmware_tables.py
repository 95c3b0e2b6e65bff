#!/usr/bin/env python
"""Generate the C port's headers that mirror the Python reference, so the two cannot drift.

    python tools/gen_firmware_tables.py            # (re)write the headers
    python tools/gen_firmware_tables.py --check    # exit 1 if a checked-in header is stale

firmware_ref/include/mkc_fields.h (public): the named fields of a state's settings, counters and fit
figures (`core.cfg.window`, `core.counters.esteps`, `core.fit.cond`), in the order of the Python
state's icfg + fcfg, cnt and fst arrays. The names and their one-line meanings are the tables below;
the order and completeness come from the index constants of mkc_stream/kernels/window.py (I_*, F_*,
C_*, S_*): a constant added, removed or reordered there stops this script until the table follows.

firmware_ref/src/mkc_tables.h (internal): every constant the C port shares with the Python reference.

The Gauss-Legendre table (GL10 on [0, 1]), the normaliser's cut-off TAU and log(TAU), the status
codes, the counter / configuration indices of the state, the kernel thresholds, the direction-cell
grid, the StreamConfig and AcceptanceRules defaults and the MagCalibrator constants are read from
mkc_stream itself, so the C port cannot drift from the Python reference without this check failing
(tests/test_firmware.py runs it). Floating-point constants are written as C99 hexadecimal literals:
exactly the float64 values Python uses.
"""
from __future__ import annotations

import argparse
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

OUT = ROOT / "firmware_ref" / "src" / "mkc_tables.h"
FIELDS_OUT = ROOT / "firmware_ref" / "include" / "mkc_fields.h"

# (index constant of kernels/window.py, C field name, what it holds). A field's type is its array's:
# icfg int32_t, fcfg mkc_real, cnt int64_t, fst mkc_real.
CFG_INT_FIELDS = [
    ("I_N", "n", "parameters per sample row (9: the ellipsoid)"),
    ("I_M", "m", "residual channels"),
    ("I_W", "window", "W, samples kept in the window"),
    ("I_K", "estep_every", "K, samples between E-steps (each followed by a rebuild)"),
    ("I_FP_ROUNDS", "fp_rounds", "fixed-point rounds per rebuild (stops early at fp_tol)"),
    ("I_ES_MAX_ITER", "estep_max_iter", "BFGS iterations per channel per E-step"),
    ("I_MIN_SAMPLES", "min_samples", "samples before the first solve (never 0)"),
    ("I_REFACTOR", "refactor_every", "tracking steps between Cholesky refreshes (never 0)"),
]
CFG_REAL_FIELDS = [
    ("F_SIG_LO", "sigma_lo", "lower bound of the kernel bandwidth sigma (in units of d)"),
    ("F_SIG_HI", "sigma_hi", "upper bound of sigma (dimensionless)"),
    ("F_DLO", "d_lo", "lower bound of d, as a fraction of the truncation bound a"),
    ("F_DHI", "d_hi", "upper bound of d, as a fraction of a"),
    ("F_AFAC", "a_factor", "a = a_factor * max|residual| when a is not fixed"),
    ("F_FIXED_A", "a", "fixed truncation bound (residual units); <= 0: use a_factor"),
    ("F_ES_GTOL", "estep_gtol", "E-step BFGS stop: projected gradient of the objective"),
    ("F_FP_TOL", "fp_tol", "fixed-point stop: |theta change| <= fp_tol |theta| (relative)"),
    ("F_SIG_START", "sigma_start", "sigma after a restart (dimensionless)"),
    ("F_SIG_PULL", "sigma_pull", "weak prior on sigma, nats per e-fold (0: maximum likelihood)"),
]
COUNTER_FIELDS = [
    ("C_HEAD", "head", "ring-buffer slot the next sample is written to"),
    ("C_COUNT", "count", "samples in the window (<= window)"),
    ("C_SEEN", "seen", "samples added since init"),
    ("C_REJECTED", "rejected", "samples refused (NaN, inf or too large) and not added"),
    ("C_ESTEPS", "esteps", "E-steps done"),
    ("C_SINCE", "since", "samples since the last E-step"),
    ("C_STATUS", "status", "status code of the last step (MKC_OK ... MKC_REJECTED)"),
    ("C_SINGULAR", "singular", "solves that found the normal matrix A not positive definite"),
    ("C_FP_ITERS", "fp_iters", "fixed-point rounds done"),
    ("C_LAST_SLOT", "last_slot", "slot the last sample was written to"),
    ("C_RESTARTS", "restarts", "restarts (sigma, d and theta re-initialised from the window)"),
    ("C_FACTOR_AGE", "factor_age", "samples since L, D were factored from A (-1: no valid factor)"),
    ("C_FACTORS", "factors", "Cholesky factorisations (checkpoints, refreshes, fall-backs)"),
]
FIT_FIELDS = [
    ("S_COND", "cond", "condition estimate of A at the last solve (inf before the first)"),
    ("S_LAST_F", "last_objective", "last E-step objective, summed over channels (nats per sample)"),
]
# (Python state array, its count constant, the table naming its entries)
NAMED_ARRAYS = [("icfg", "N_ICFG", CFG_INT_FIELDS), ("fcfg", "N_FCFG", CFG_REAL_FIELDS),
                ("cnt", "N_COUNTERS", COUNTER_FIELDS), ("fst", "N_FSTATE", FIT_FIELDS)]



def _c_table(ctype, name, size, values, literal) -> str:
    """`static const CTYPE NAME[SIZE] = { ... };`, one value per line written by literal(v)."""
    body = ",\n".join(f"    {literal(v)}" for v in values)
    return f"static const {ctype} {name}[{size}] = {{\n{body}\n}};"

def _hex(v: float) -> str:
    v = float(v)
    if v == float("inf"):
        return "HUGE_VAL"
    return v.hex()


def _hex_float32(v: float) -> str:
    """v rounded to the nearest float32, as a C float literal."""
    import numpy as np

    return float(np.float32(v)).hex() + "f"


def render() -> str:
    from mkc_stream import kernels as KS
    from mkc_stream.calib import acceptance
    from mkc_stream.calib.streaming import MagCalibrator
    from mkc_stream.calib.confidence import DOMINANCE, Z_RESTART, Z_SWITCH
    from mkc_stream.defaults import DEFAULT_WINDOW
    from mkc_stream.kernels import estep as ES
    from mkc_stream.kernels import magwindow as MW
    from mkc_stream.kernels import normaliser as NZ
    from mkc_stream.kernels import window as K
    from mkc_stream.kernels.quadrature import GL_NODES, GL_ORDER, GL_WEIGHTS
    from mkc_stream.state import StreamConfig

    out = []
    p = out.append
    p("/* GENERATED by tools/gen_firmware_tables.py from the Python reference (mkc_stream): do not edit.")
    p(" * Regenerate with `python tools/gen_firmware_tables.py`; tests/test_firmware.py checks it is current. */")
    p("#ifndef MKC_TABLES_H")
    p("#define MKC_TABLES_H")
    p("")
    p("/* status codes: mkc_stream/kernels/__init__.py and kernels/window.py */")
    for name in ("OK", "NOT_CONVERGED", "SINGULAR", "NONFINITE", "BAD_INPUT"):
        p(f"#define MKC_T_{name} {getattr(KS, name)}")
    p(f"#define MKC_T_WARMING_UP {K.WARMING_UP}")
    p(f"#define MKC_T_REJECTED {K.REJECTED}")
    p("")
    checked_field_tables(K)      # the named fields of mkc_fields.h follow these indices
    p("/* integer configuration indices (icfg) */")
    for name in ("I_N", "I_M", "I_W", "I_K", "I_FP_ROUNDS", "I_ES_MAX_ITER", "I_MIN_SAMPLES", "I_REFACTOR"):
        p(f"#define MKC_{name} {getattr(K, name)}")
    p(f"#define MKC_N_ICFG {K.N_ICFG}")
    p("/* float configuration indices (fcfg) */")
    for name in ("F_SIG_LO", "F_SIG_HI", "F_DLO", "F_DHI", "F_AFAC", "F_FIXED_A", "F_ES_GTOL", "F_FP_TOL",
                 "F_SIG_START", "F_SIG_PULL"):
        p(f"#define MKC_{name} {getattr(K, name)}")
    p(f"#define MKC_N_FCFG {K.N_FCFG}")
    p("/* counters (cnt) */")
    for name in ("C_HEAD", "C_COUNT", "C_SEEN", "C_REJECTED", "C_ESTEPS", "C_SINCE", "C_STATUS", "C_SINGULAR",
                 "C_FP_ITERS", "C_LAST_SLOT", "C_RESTARTS", "C_FACTOR_AGE", "C_FACTORS"):
        p(f"#define MKC_{name} {getattr(K, name)}")
    p(f"#define MKC_N_COUNTERS {K.N_COUNTERS}")
    p("/* float state scalars (fst) */")
    p(f"#define MKC_S_COND {K.S_COND}")
    p(f"#define MKC_S_LAST_F {K.S_LAST_F}")
    p(f"#define MKC_N_FSTATE {K.N_FSTATE}")
    p("")
    p("/* kernel thresholds */")
    p(f"#define MKC_REFINE_MAX_STEP {_hex(K.REFINE_MAX_STEP)} /* {K.REFINE_MAX_STEP!r} */")
    p(f"#define MKC_START_SIGMA_ROBUST {_hex(K.START_SIGMA_ROBUST)} /* {K.START_SIGMA_ROBUST!r}: restart_at */")
    p(f"#define MKC_TAU {_hex(NZ.TAU)} /* {NZ.TAU!r} */")
    p(f"#define MKC_FAR_GTOL {_hex(ES.FAR_GTOL)} /* {ES.FAR_GTOL!r}: kernels/estep.py */")
    p(f"#define MKC_FAR_EXTRA_ITER {ES.FAR_EXTRA_ITER}")
    p(f"#define MKC_LOG_TAU {_hex(NZ.LOG_TAU)} /* {NZ.LOG_TAU!r} */")
    p("")
    p(f"/* Gauss-Legendre, {GL_ORDER} nodes mapped to [0, 1] (kernels/quadrature.py) */")
    p(f"#define MKC_GL_ORDER {GL_ORDER}")
    p("#ifdef MKC_TABLES_WANT_GL /* only the normaliser's translation unit holds the table */")
    double = lambda v: f"{_hex(v)} /* {float(v)!r} */"     # noqa: E731
    p("#if MKC_ESTEP_DOUBLE")
    for name, values in (("mkc_gl_nodes", GL_NODES), ("mkc_gl_weights", GL_WEIGHTS)):
        p(_c_table("double", name, "MKC_GL_ORDER", values, double))
    p("#else /* a single-precision E-step: the same values rounded to float (no conversion at run time) */")
    for name, values in (("mkc_gl_nodes", GL_NODES), ("mkc_gl_weights", GL_WEIGHTS)):
        p(_c_table("float", name, "MKC_GL_ORDER", values, _hex_float32))
    p("#endif")
    p("#endif")
    p("")
    p("/* direction cells (kernels/magwindow.py) */")
    p(f"#define MKC_N_BANDS {MW.N_BANDS}")
    p(f"#define MKC_N_SECTORS {MW.N_SECTORS}")
    p(f"#define MKC_N_CELLS {MW.N_CELLS}")
    p("")
    cfg = StreamConfig(n=9)
    p("/* StreamConfig defaults (state.py) */")
    for name in ("fp_rounds", "estep_max_iter", "refactor_every", "min_samples"):
        p(f"#define MKC_DEF_{name.upper()} {getattr(cfg, name)}")
    for name in ("sigma_lo", "sigma_hi", "d_lo", "d_hi", "a_factor", "a", "estep_gtol", "fp_tol", "sigma_start",
                 "sigma_pull"):
        v = getattr(cfg, name)
        p(f"#define MKC_DEF_{name.upper()} {_hex(v)} /* {v!r} */")
    from mkc_stream.batch import DEFAULT_SIGMA_START
    p(f"#define MKC_DEF_SIGMA0 {_hex(DEFAULT_SIGMA_START)} /* {DEFAULT_SIGMA_START!r}: batch.DEFAULT_SIGMA_START */")
    p("")
    r = acceptance.AcceptanceRules()
    p("/* AcceptanceRules defaults (calib/acceptance.py) */")
    p(f"#define MKC_DEF_MIN_COVERAGE {_hex(r.min_coverage)} /* {r.min_coverage!r} */")
    p(f"#define MKC_DEF_MAX_CONDITION {_hex(r.max_condition)} /* {r.max_condition!r} */")
    p(f"#define MKC_DEF_MAX_OUTLIER_FRACTION {_hex(r.max_outlier_fraction)} /* {r.max_outlier_fraction!r} */")
    p(f"#define MKC_DEF_MAX_RESIDUAL_REL {_hex(r.max_residual_rel)} /* {r.max_residual_rel!r} */")
    p(f"#define MKC_DEF_FIELD_LO_UT {_hex(r.field_range_ut[0])} /* {r.field_range_ut[0]!r} */")
    p(f"#define MKC_DEF_FIELD_HI_UT {_hex(r.field_range_ut[1])} /* {r.field_range_ut[1]!r} */")
    p(f"#define MKC_DEF_MAX_DISAGREEMENT_REL {_hex(r.max_disagreement_rel)} /* {r.max_disagreement_rel!r} */")
    p("")
    p(f"#define MKC_DEFAULT_WINDOW {DEFAULT_WINDOW} /* defaults.py: min(MKC_W, this) is a config's default window */")
    p("")
    p("/* MagCalibrator (calib/streaming.py) */")
    p(f"#define MKC_MIN_SPHERE_COVERAGE {_hex(MagCalibrator.MIN_SPHERE_COVERAGE)} /* {MagCalibrator.MIN_SPHERE_COVERAGE!r} */")
    p(f"#define MKC_MAX_SPHERE_SPREAD {_hex(MagCalibrator.MAX_SPHERE_SPREAD)} /* {MagCalibrator.MAX_SPHERE_SPREAD!r} */")
    p(f"#define MKC_Z_SWITCH {_hex(Z_SWITCH)} /* {Z_SWITCH!r}: calib/confidence.py */")
    p(f"#define MKC_Z_RESTART {_hex(Z_RESTART)} /* {Z_RESTART!r}: calib/confidence.py */")
    p(f"#define MKC_DOMINANCE {_hex(DOMINANCE)} /* {DOMINANCE!r}: calib/confidence.py */")
    p(f"#define MKC_MAX_FAILED_CHECKPOINTS {MagCalibrator.MAX_FAILED_CHECKPOINTS}")
    p(f"#define MKC_MAX_MISFIT_TRIALS {MagCalibrator.MAX_MISFIT_TRIALS}")
    p(f"#define MKC_POOL_WINDOWS {MagCalibrator.POOL_WINDOWS}")
    p(f"#define MKC_COLD_START_ROUNDS {MagCalibrator.COLD_START_ROUNDS}")
    p("#define MKC_DEF_INIT_SAMPLES 64 /* min(window, 64) */")
    p("")
    p("#endif /* MKC_TABLES_H */")
    return "\n".join(out) + "\n"


def checked_field_tables(K=None) -> list[tuple[str, list[tuple[str, str, str]]]]:
    """NAMED_ARRAYS, each table checked against kernels/window.py: the same constants in index order 0..N-1."""
    if K is None:
        from mkc_stream.kernels import window as K
    out = []
    for array, count_name, table in NAMED_ARRAYS:
        prefix = table[0][0].split("_")[0] + "_"
        indices = {k: v for k, v in vars(K).items() if k.startswith(prefix) and isinstance(v, int)}
        python_order = sorted(indices, key=indices.get)
        if [indices[k] for k in python_order] != list(range(getattr(K, count_name))):
            raise SystemExit(f"kernels/window.py: the {prefix}* constants are not 0..{count_name}-1: {indices}")
        if [py for py, _, _ in table] != python_order:
            raise SystemExit(f"kernels/window.py indexes {array} as {python_order}; tools/gen_firmware_tables.py "
                             f"names {[py for py, _, _ in table]}: update the table (C field name and meaning)")
        out.append((array, table))
    return out


def _struct(p, name, members):
    """members: (C type, field, comment); comments aligned after the longest declaration."""
    width = max(len(f"    {ctype} {field};") for ctype, field, _ in members) + 1
    p(f"typedef struct {name} {{")
    for ctype, field, comment in members:
        p(f"{f'    {ctype} {field};':<{width}}/* {comment} */")
    p(f"}} {name};")


def render_fields() -> str:
    tables = dict(checked_field_tables())
    out = []
    p = out.append
    p("/* mkc_fields.h: the named fields of a state's settings, counters and fit figures.")
    p(" *")
    p(" * GENERATED by tools/gen_firmware_tables.py from mkc_stream/kernels/window.py: do not edit. Each")
    p(" * struct holds, in the same order, the entries of the Python state's arrays named in its comment")
    p(" * (the comment after each field gives the Python index), so `core.counters.esteps` is the Python")
    p(" * state's cnt[C_ESTEPS]. tests/test_firmware.py checks the names and the order.")
    p(" */")
    p("#ifndef MKC_FIELDS_H")
    p("#define MKC_FIELDS_H")
    p("")
    p("#include <stdint.h>")
    p("")
    p('#include "mkc_config.h"')
    p("")
    p("/* The settings a state runs with: its mkc_config after mkc_stream_init / mkc_mag_init resolved the")
    p(" * zeros (Python: icfg, then fcfg). Read them; changing them after init is not supported. */")
    members = [("int32_t", field, f"icfg[{py}]: {doc}") for py, field, doc in tables["icfg"]]
    members += [("mkc_real", field, f"fcfg[{py}]: {doc}") for py, field, doc in tables["fcfg"]]
    _struct(p, "mkc_core_cfg", members)
    p("")
    p("/* What the estimator has done (Python: cnt). */")
    _struct(p, "mkc_counters", [("int64_t", field, f"cnt[{py}]: {doc}") for py, field, doc in tables["cnt"]])
    p("")
    p("/* Figures of the last solve and E-step (Python: fst). */")
    _struct(p, "mkc_core_fit", [("mkc_real", field, f"fst[{py}]: {doc}") for py, field, doc in tables["fst"]])
    p("")
    p(f"#define MKC_COUNTERS {len(tables['cnt'])} /* fields of mkc_counters */")
    p("/* Index of each counter in the Python state's cnt and in mkc_get(MKC_F_CNT) (mkc_introspect.h). */")
    names = [f"MKC_CNT_{py[2:]}" for py, _, _ in tables["cnt"]]
    lines, line = [], "    " + names[0] + " = 0"
    for name in names[1:]:
        if len(line) + len(name) + 2 > 104:
            lines.append(line + ",")
            line = "    " + name
        else:
            line += ", " + name
    lines.append(line)
    p("enum {")
    out.extend(lines)
    p("};")
    p("")
    p("#endif /* MKC_FIELDS_H */")
    return "\n".join(out) + "\n"


#: Every generated file and the function that renders it.
GENERATED = {OUT: render, FIELDS_OUT: render_fields}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--check", action="store_true", help="compare with the checked-in header, do not write")
    args = ap.parse_args(argv)
    stale = 0
    for path, render_file in GENERATED.items():
        text = render_file()
        name = path.relative_to(ROOT)
        if args.check:
            if not path.exists() or path.read_text() != text:
                print(f"{name} is stale: run python tools/gen_firmware_tables.py", file=sys.stderr)
                stale += 1
            else:
                print(f"{name} is current")
            continue
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        print(f"wrote {name}")
    return 1 if stale else 0


if __name__ == "__main__":
    sys.exit(main())
