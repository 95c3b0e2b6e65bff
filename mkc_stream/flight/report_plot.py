"""The report of an attitude-aided flight calibration (calibrate.fit_flight) as a PNG (optional extra [plot]).

Four panels over the samples the fit used (time t in s from the first):
  1. field strength, uT: |m_raw| / g as logged and |S (m_raw - b - K c(t - tau))| / g after the
     calibration (g its gain, sensor unit per uT), against the model's |h_E| (without a field model the
     gain is unknown: the sensor's unit, against the fitted field);
  2. heading, deg: the change the calibration makes, wrap(psi_cal - psi_raw), with psi = atan2(e_E, e_N)
     of the field turned into north-east-down by the log's attitude (compare.navigation_field); and the
     calibrated heading against the model's declination, wrap(psi_cal - D), which is where the
     magnetometer and the attitude disagree;
  3. residual vs current (uT vs A): the partial residual e_ki + K_i c_k(tau) of each axis against the
     delayed current c_k(tau), with the fitted line K_i c (the throttle instead when only it is fitted);
     samples treated as disturbed (panel 4) in grey, the scale set by the others;
  4. per-sample kernel weights (vector_fit.VectorFit.weights, 1 = fully trusted), the smallest of the
     three axes, shaded where it is below DISTURBED_WEIGHT (the samples the fit treated as disturbed).
``report_arrays`` returns what is drawn; ``plot_flight_report`` draws and writes it.
"""
from __future__ import annotations

import math
import os

import numpy as np

#: A sample whose smallest axis weight is below this counts as treated as disturbed (shaded in panel 4).
DISTURBED_WEIGHT = 0.5
#: At most this many points per axis in the residual scatter (a random subset; the arrays are complete).
SCATTER_POINTS = 4000
PLOT_EXTRA_HINT = "plots need matplotlib: pip install 'mkc-stream[plot]'"
QUAT = ("qw", "qx", "qy", "qz")


def fitted_rows(rec, fc) -> np.ndarray:
    """The rows of rec that fit_flight used (finite field, attitude and power signals), as a bool mask."""
    names = list(fc.fit.power_names)
    q = np.stack([rec.aux[c] for c in QUAT], axis=1)
    c = np.stack([rec.aux[n] for n in names], axis=1) if names else np.zeros((rec.t.shape[0], 0))
    ok = np.isfinite(rec.mag).all(axis=1) & np.isfinite(q).all(axis=1) & (np.linalg.norm(q, axis=1) > 0.5)
    ok &= np.isfinite(c).all(axis=1) & np.isfinite(rec.t)
    if int(ok.sum()) != fc.samples:
        raise ValueError(f"this recording has {int(ok.sum())} usable rows, the calibration was fitted on {fc.samples}: "
                         "not the recording it was fitted on")
    return ok


def _power_column(fc):
    """(index, name) of the power signal drawn in panel 3: the current when fitted, else the throttle, else None."""
    names = list(fc.fit.power_names)
    for name in ("current", "throttle"):
        if name in names and f"K[{name}]=0" not in fc.held:
            return names.index(name), name
    return None, None


def report_arrays(rec, fc) -> dict:
    """The arrays of the four panels (module doc); units in the keys."""
    from .compare import navigation_field
    from .delay import delayed
    from .vector_fit import rotation_matrices

    ok = fitted_rows(rec, fc)
    gain = fc.scale if math.isfinite(fc.scale) and fc.scale > 0 else 1.0
    t = np.asarray(rec.t, dtype=np.float64)[ok]
    _, e_cal = navigation_field(rec, fc)
    e_cal = e_cal[ok]
    raw = np.asarray(rec.mag, dtype=np.float64)[ok]
    R = rotation_matrices(np.stack([rec.aux[c][ok] for c in QUAT], axis=1))
    e_raw = np.einsum("kij,kj->ki", R, raw) / gain
    psi_cal = np.arctan2(e_cal[:, 1], e_cal[:, 0])
    psi_raw = np.arctan2(e_raw[:, 1], e_raw[:, 0])
    h = np.asarray(fc.fit.h_ned, dtype=np.float64)
    decl = math.atan2(h[1], h[0])
    wrap = lambda a: np.degrees(np.angle(np.exp(1j * a)))          # noqa: E731  (rad -> deg in (-180, 180])
    model = float(fc.earth.intensity_uT) if fc.earth is not None else float(fc.field / gain)
    out = {"t_s": t - t[0], "field_model_uT": model, "field_unit": "uT" if gain == fc.scale else fc.unit,
           "field_before_uT": np.linalg.norm(raw, axis=1) / gain, "field_after_uT": np.linalg.norm(e_cal, axis=1),
           "heading_change_deg": wrap(psi_cal - psi_raw), "heading_vs_model_deg": wrap(psi_cal - decl),
           "weights": np.asarray(fc.fit.weights, dtype=np.float64)}
    out["weight_min"] = out["weights"].min(axis=1)
    out["disturbed_fraction"] = float(np.mean(out["weight_min"] < DISTURBED_WEIGHT))
    j, name = _power_column(fc)
    out["power_name"] = name
    if j is not None:
        delay = fc.fit.delay_s or 0.0
        sig = np.stack([rec.aux[n][ok] for n in fc.fit.power_names], axis=1)
        x = delayed(t, sig, delay)[:, j]
        k = np.asarray(fc.fit.K[:, j], dtype=np.float64) / gain
        out.update(power=x, power_coeff=k, power_delay_s=float(delay),
                   partial_residual_uT=np.asarray(fc.fit.residuals, dtype=np.float64) / gain + x[:, None] * k[None, :])
    return out


def _plt():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:  # pragma: no cover - exercised by the extra's absence
        raise ImportError(PLOT_EXTRA_HINT) from exc
    return plt


def instance_path(path, instance) -> str:
    """The PNG of one compass of --all-instances: PATH's name with -instance<id> before its extension."""
    stem, ext = os.path.splitext(str(path))
    return f"{stem}-instance{instance}{ext or '.png'}"


def plot_flight_report(rec, fc, path, title="") -> dict:
    """Draw the four panels of the module doc for ``fc`` fitted on ``rec`` into the PNG ``path``; returns
    report_arrays(rec, fc). ImportError naming the [plot] extra without matplotlib; OSError from the write."""
    from ..plots import save_figure

    a = report_arrays(rec, fc)
    plt = _plt()
    fig, axs = plt.subplots(2, 2, figsize=(13, 8.5))
    t = a["t_s"]
    ax = axs[0, 0]
    ax.plot(t, a["field_before_uT"], lw=0.6, color="0.55", label="as logged")
    ax.plot(t, a["field_after_uT"], lw=0.6, color="C0", label="after the calibration")
    u = a["field_unit"]
    ax.axhline(a["field_model_uT"], color="r", lw=1, label=f"model {a['field_model_uT']:.2f} {u}"
               + (f" ({fc.earth.model})" if fc.earth is not None else " (fitted)"))
    ax.set_xlabel("time (s)")
    ax.set_ylabel(f"field strength ({a['field_unit']})")
    dev = [float(np.median(np.abs(a[k] - a["field_model_uT"]))) for k in ("field_before_uT", "field_after_uT")]
    ax.set_title(f"field strength: median |F - model| {dev[0]:.2f} {u} as logged, {dev[1]:.2f} {u} calibrated")
    ax.legend(loc="upper right", fontsize=8)
    ax = axs[0, 1]
    ax.plot(t, a["heading_change_deg"], lw=0.6, color="C1", label="calibrated - as logged")
    ax.plot(t, a["heading_vs_model_deg"], lw=0.6, color="C2", label="calibrated - (attitude + declination)")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("heading (deg)")
    ax.set_title("heading change the calibration makes")
    ax.legend(loc="upper right", fontsize=8)
    ax = axs[1, 0]
    if a["power_name"] is None:
        ax.text(0.5, 0.5, "no power signal fitted (none in the log, or not observable)", ha="center", va="center",
                transform=ax.transAxes)
        ax.set_axis_off()
    else:
        x, pr, k = a["power"], a["partial_residual_uT"], a["power_coeff"]
        pick = np.random.default_rng(0).permutation(x.size)[:SCATTER_POINTS]
        xs = np.linspace(float(np.min(x)), float(np.max(x)), 2)
        trusted = a["weight_min"][pick] >= DISTURBED_WEIGHT
        for i, axis in enumerate("xyz"):
            ax.plot(x[pick][~trusted], pr[pick, i][~trusted], ".", ms=1.5, alpha=0.3, color="0.7")
            ax.plot(x[pick][trusted], pr[pick, i][trusted], ".", ms=1.5, alpha=0.35, color=f"C{i}")
            ax.plot(xs, k[i] * xs, "-", color=f"C{i}", lw=1.8, label=f"{axis}: {k[i]:+.4f} {u}/"
                    + ("A" if a["power_name"] == "current" else "unit"))
        unit = "A" if a["power_name"] == "current" else "0..1"
        dl = a["power_delay_s"]
        ax.set_xlabel(f"{a['power_name']} at t {'-' if dl >= 0 else '+'} {abs(dl) * 1e3:.0f} ms ({unit})")
        ax.set_ylabel(f"residual + fitted compensation ({u})")
        good = pr[a["weight_min"] >= DISTURBED_WEIGHT]
        if good.size:                      # the trusted samples set the scale; disturbed ones (grey) may lie outside
            lo, hi = np.percentile(good, [0.5, 99.5])
            pad = 0.25 * (hi - lo) + 1e-9
            ax.set_ylim(lo - pad, hi + pad)
        ax.set_title(f"residual vs {a['power_name']} with the fitted compensation")
        ax.legend(loc="upper left", fontsize=8)
    ax = axs[1, 1]
    ax.plot(t, a["weight_min"], lw=0.5, color="C4", label="smallest axis weight")
    low = a["weight_min"] < DISTURBED_WEIGHT
    ax.fill_between(t, 0, 1, where=low, color="r", alpha=0.2, lw=0,
                    label=f"weight < {DISTURBED_WEIGHT:g}: {a['disturbed_fraction']:.1%} of the samples")
    ax.set_ylim(-0.02, 1.05)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("kernel weight")
    ax.set_title("per-sample weights (low = treated as disturbed)")
    ax.legend(loc="lower right", fontsize=8)
    fig.suptitle(f"{os.path.basename(str(title))}  [mkc-em-attitude]")
    fig.tight_layout()
    try:
        save_figure(fig, path)
    finally:
        plt.close(fig)
    return a
