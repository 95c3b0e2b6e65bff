"""Study: the attitude-aided calibration on simulated flights with known truth, four methods side by side.

Flights (mkc_stream.flight.simulated): level flight with turns (coordinated bank, 12 m/s) and a slow
pitch wave, the field from WMM2025 at one of four places (2026.5), a random hard iron (+-30 uT per
axis), a random symmetric soft iron within +-5% of identity (det 1), current 0-40 A
(sim.profiles.flight_power), interference k * current(t - delay) with |k_i| in 0.01-0.5 uT/A (random
signs), delay 0-50 ms, logged attitude with a wandering yaw error of 2-5 deg RMS and 0.3 deg tilt error,
white noise 0.1 uT, and 0/10/25% of the samples in disturbance bursts of 5-40 uT.

Methods (the first three on the vector model m = A R^T h_E + b + K c(t - tau), mkc_stream/flight/vector_fit.py):
  ours   MKC-EM (robust), delay searched over 0-100 ms, the yaw error as a nuisance
  ls     plain least squares on the same model (same delay search, same yaw-error nuisance)
  px4    PX4's published power compensation (PX4 user guide, "Compass Power Compensation"): per-axis
         linear least squares of the magnetometer against the current, the lag searched up to 80 ms.
         Published for a vehicle held still while the throttle is ramped; in flight the attitude
         changes the field, so here it runs on the residual of a plain least-squares vector fit without
         current terms (stage 1), and the calibration is refitted by least squares on the compensated
         field (stage 3). The lag is a grid of 5 ms.
  stream the same vector model in fixed memory (mkc_stream/flight/streaming.py, as `calibrate --stream`):
         window 512, E-step every 32, the pooled (accepted) calibration with its yaw-error term (one
         offset per 10 s); no delay search (the current used without delay). Its record also holds
         the last window's own trial (b_err_window), the estimate before pooling.
  magfit ArduPilot's MagFit (MAVProxy): offsets, symmetric soft iron, motor-current compensation (no
         delay) by SLSQP within its default bounds, minimising the mean vector error against the model
         field turned by the log's roll and pitch and the corrected sample's own heading
         (tools/peer_magfit.py has the cost, the bounds and why it is reimplemented).
Figures per run: hard-iron error |b - b_true| (uT), current-coefficient error |K - K_true| / |K_true|,
delay error (ms), and the heading RMS (deg) of the noise-free field corrected by the calibration as
delivered (the symmetric matrix the parameter files hold, delivered_matrix) along the flight, turned by
the true attitude (so it measures the calibration, not the attitude's error). A fit against the log's
attitude takes the log's mean yaw error over the flight into its rotation about z (it cannot be told
from a mounting rotation); that rotation is reported as the misalignment and not delivered, and
heading_rms_full_model_deg is the heading RMS with it applied (the whole fitted A). Each run also
records the log's mean yaw error (the logged yaw minus the true yaw, deg), the mean heading error and
the heading RMS about its mean.
With --level-hard-iron each run also records b_err_level = |b - b_true + e_z (A_22 - A_22,true) mean(h_z)|
(uT, h_z the true body field's z): in level flight b_z and the vertical gain A_22 trade along a ridge
(b_z + A_22 h_z is what the flight determines, VIF of h_z 200-700), and this figure is the hard-iron
error with that trade removed, i.e. the error of the calibrated field at the flight's mean attitude.
--tilt-sd-deg S|auto|off: the attitude's roll/pitch error corrected for (corrected least squares,
vector_fit.py): S deg as stated (ours and ls), estimated from the residuals (auto, the default, as
fit_flight: ours only, least squares has no weights for the estimate), or none; the simulated log's is
0.3 deg.

    python tools/study_flight.py --seeds 4 [--minutes 30 30] [--rate 10] [--json out.json] [--plot out.png]
        [--methods ours,ls,px4,magfit,stream] [--first-seed 0] [--mounting-deg 0] [--yaw-error-deg X]
        [--level-hard-iron] [--tilt-sd-deg S|auto|off]
        [--from-json a.json b.json --plot out.png]    # summarise and plot stored runs
"""
from __future__ import annotations

import argparse
import json
import math
import time
import warnings

import numpy as np

from mkc_stream.flight import fit_flight
from mkc_stream.flight.earthfield import earth_field
from mkc_stream.flight.simulated import simulated_flight
from mkc_stream.flight.streaming import recording_inputs
from mkc_stream.flight.vector_fit import VectorFitSettings, fit_vector, rotation_matrices

try:                                   # run as a script (tools/ on sys.path) or imported from the repository root
    from peer_magfit import magfit
except ImportError:                    # pragma: no cover
    from tools.peer_magfit import magfit

PLACES = [(-35.0, 149.0, 600.0), (10.0, -84.0, 1200.0), (47.4, 8.5, 500.0), (65.0, -18.0, 100.0)]
PX4_MAX_LAG = 0.08
PX4_LAG_STEP = 0.005
METHODS = ("ours", "ls", "px4", "magfit", "stream")
LABELS = {"ours": "ours (MKC-EM)", "ls": "least squares", "px4": "PX4 method", "magfit": "MagFit",
          "stream": "ours, streaming"}


def px4_power_compensation(t, mag, q, h_ned, current):
    """Stage 1-3 of the module doc: returns (A, b, K (3,), lag)."""
    s = VectorFitSettings(robust=False, yaw_knot_s=None)
    stage1 = fit_vector(t, mag, q, h_ned, None, (), s)
    r = stage1.residuals
    best = None
    for lag in np.arange(0.0, PX4_MAX_LAG + 1e-9, PX4_LAG_STEP):
        c = np.interp(t - lag, t, current)
        X = np.stack([np.ones_like(c), c], axis=1)
        coef, *_ = np.linalg.lstsq(X, r, rcond=None)
        sse = float(np.sum((r - X @ coef) ** 2))
        if best is None or sse < best[0]:
            best = (sse, lag, coef[1].copy())
    _, lag, K = best
    comp = mag - np.interp(t - lag, t, current)[:, None] * K[None, :]
    stage3 = fit_vector(t, comp, q, h_ned, None, (), s)
    return stage3.A, stage3.b, K, float(lag)


def delivered_matrix(A) -> np.ndarray:
    """The correction matrix a calibration delivers: the symmetric polar factor P of A^-1 = Q P. The parameter
    files (ArduPilot's DIA/ODI, PX4's scales and off-diagonals, calibrate.package_form's S) hold a symmetric
    matrix; the rotation Q (the misalignment, which takes in the log's mean yaw error) is reported, not applied."""
    _, sv, Vt = np.linalg.svd(np.linalg.inv(A))
    return (Vt.T * sv) @ Vt


def heading_errors(truth, rec, A, b, K, delay, delivered=True):
    """Heading error (deg, per sample) of M (m_clean - b - K c(t - delay)) rotated to NED by the true attitude,
    M = delivered_matrix(A) (delivered) or A^-1 (the whole fitted model, misalignment included)."""
    t, cur = rec.t, rec.aux["current"]
    R, h = truth["R_true"], truth["h_ned"]
    hb = np.einsum("kji,j->ki", R, h)
    m_clean = hb @ truth["A"].T + truth["b"] + np.interp(t - truth["delay_s"], t, cur)[:, None] * truth["K"]
    c_est = np.interp(t - (delay or 0.0), t, cur)
    M = delivered_matrix(A) if delivered else np.linalg.inv(A)
    m_cal = (m_clean - b - c_est[:, None] * np.asarray(K)[None, :]) @ M.T
    n = np.einsum("kij,kj->ki", R, m_cal)
    err = np.degrees(np.arctan2(n[:, 1], n[:, 0]) - math.atan2(h[1], h[0]))
    return (err + 180.0) % 360.0 - 180.0


def heading_figures(err) -> dict:
    """RMS, mean and RMS about the mean (deg) of a heading-error series."""
    mean = float(np.mean(err))
    return {"heading_rms_deg": float(np.sqrt(np.mean(err ** 2))), "heading_mean_deg": mean,
            "heading_rms_about_mean_deg": float(np.std(err))}


def log_yaw_error(rec, truth) -> np.ndarray:
    """The logged attitude's yaw minus the true yaw (deg, per sample)."""
    q = np.stack([rec.aux[c] for c in ("qw", "qx", "qy", "qz")], axis=1)
    R_log, R = rotation_matrices(q), truth["R_true"]
    d = np.arctan2(R_log[:, 1, 0], R_log[:, 0, 0]) - np.arctan2(R[:, 1, 0], R[:, 0, 0])
    return np.degrees(np.angle(np.exp(1j * d)))


def magfit_peer(rec, q, h_ned):
    """MagFit (tools/peer_magfit.py) in the study's form: (A, b, K, delay 0)."""
    r = magfit(rec.mag, rotation_matrices(q), h_ned, rec.aux["current"])
    A, b, K = r.vector_model()
    return A, b, K, 0.0


def random_truth(rng):
    B = rng.uniform(-0.05, 0.05, (3, 3))
    S = np.eye(3) + 0.5 * (B + B.T)
    S /= np.linalg.det(S) ** (1.0 / 3.0)
    k = rng.uniform(0.01, 0.5, 3) * rng.choice([-1.0, 1.0], 3)
    return dict(hard_iron=tuple(rng.uniform(-30, 30, 3)), soft_iron=S, k_current=tuple(k),
                delay=float(rng.uniform(0.0, 0.05)), yaw_error_deg=float(rng.uniform(2.0, 5.0)))


def stream_fit(rec, ef):
    """The attitude-aided stream over the recording: (A, b, K, delay 0, the last window's trial b)."""
    cal, mag, q, power, _ = recording_inputs(rec, earth=ef)
    for s in range(0, mag.shape[0], 1000):
        cal.learn_many(mag[s:s + 1000], q[s:s + 1000], None if power is None else power[s:s + 1000])
    A, b, K = cal.parameters(pooled=cal.accepted is not None)
    return A, b, K[:, 0], 0.0, cal.parameters(pooled=False)[1]


def rotation_z(deg) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])


def level_hard_iron_error(truth, A, b, hz_mean) -> float:
    """|b - b_true + e_z (A_22 - A_22,true) hz_mean| (uT; module doc)."""
    e = np.asarray(b, dtype=np.float64) - truth["b"]
    e[2] += (np.asarray(A)[2, 2] - truth["A"][2, 2]) * hz_mean
    return float(np.linalg.norm(e))


def run(seed, disturbed, minutes, rate, methods=METHODS, mounting_deg=0.0, yaw_error_deg=None, level=False,
        tilt_sd_deg="auto"):
    """One flight and every method on it; mounting_deg: the magnetometer turned by this angle about the
    body's z axis (a mounting rotation: S becomes Rz S, so A = S^-1 is no longer symmetric);
    yaw_error_deg: the logged yaw's RMS error instead of the drawn 2-5 deg; level: record b_err_level too;
    tilt_sd_deg: the roll/pitch error (deg) ours and ls correct for ("auto": estimated; None: not)."""
    rng = np.random.default_rng(1000 + seed)
    lat, lon, alt = PLACES[seed % len(PLACES)]
    ef = earth_field(lat, lon, alt, 2026.5)
    duration = 60.0 * float(rng.uniform(*minutes))
    tr = random_truth(rng)
    if yaw_error_deg is not None:
        tr["yaw_error_deg"] = float(yaw_error_deg)
    if mounting_deg:
        tr["soft_iron"] = rotation_z(mounting_deg) @ tr["soft_iron"]
    f = simulated_flight(duration=duration, rate=rate, seed=seed, h_ned=tuple(ef.ned_uT), disturbed=disturbed,
                         i_max=30.0, **tr)
    rec, truth = f.recording, f.truth
    Kt = truth["K"]
    dpsi = log_yaw_error(rec, truth)
    out = {"seed": seed, "disturbed": disturbed, "minutes": duration / 60.0, "lat": lat, "mounting_deg": mounting_deg,
           "yaw_error_deg": tr["yaw_error_deg"], "log_yaw_error_rms_deg": float(np.sqrt(np.mean(dpsi ** 2))),
           "log_yaw_error_mean_deg": float(np.mean(dpsi)), "k_true": Kt.tolist(), "delay_true_ms": 1e3 * tr["delay"],
           "current_max_A": float(np.max(rec.aux["current"]))}
    q = np.stack([rec.aux[c] for c in ("qw", "qx", "qy", "qz")], axis=1)
    for name in methods:
        t0 = time.process_time()
        extra = {}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if name == "px4":
                A, b, K, delay = px4_power_compensation(rec.t, rec.mag, q, ef.ned_uT, rec.aux["current"])
            elif name == "magfit":
                A, b, K, delay = magfit_peer(rec, q, ef.ned_uT)
            elif name == "stream":
                A, b, K, delay, b_window = stream_fit(rec, ef)
                extra["b_err_window"] = float(np.linalg.norm(b_window - truth["b"]))
            else:
                c = fit_flight(rec, earth=ef, robust=(name == "ours"), tilt_sd_deg=tilt_sd_deg)
                A, b, K, delay = c.fit.A, c.hard_iron, c.current, c.delay_s
                extra["misalignment_z_deg"] = float(c.misalignment_deg[2])
                extra["tilt_sd_estimated_deg"] = c.fit.tilt_sd_estimated
                extra["tilt_sd_applied_deg"] = c.fit.tilt_sd_deg
        if level:
            hz_mean = float(np.mean(np.einsum("kji,j->ki", truth["R_true"], truth["h_ned"])[:, 2]))
            extra["b_err_level"] = level_hard_iron_error(truth, A, b, hz_mean)
        out[name] = {"b_err": float(np.linalg.norm(b - truth["b"])),
                     "k_rel_err": float(np.linalg.norm(K - Kt) / np.linalg.norm(Kt)),
                     "delay_err_ms": 1e3 * abs((delay or 0.0) - tr["delay"]),
                     **heading_figures(heading_errors(truth, rec, A, b, K, delay)),
                     "heading_rms_full_model_deg": heading_figures(heading_errors(truth, rec, A, b, K, delay,
                                                                                  False))["heading_rms_deg"],
                     **extra,
                     "cpu_s": time.process_time() - t0}
    return out


def _present(runs):
    return [m for m in METHODS if all(m in r for r in runs)]


def summarise(runs):
    """One line per (disturbance, method): medians (max) over the runs; then the ratio of the hard-iron
    medians and the log's mean yaw error."""
    lines = []
    methods = _present(runs)
    for dist in sorted({r["disturbed"] for r in runs}):
        rs = [r for r in runs if r["disturbed"] == dist]
        med = {}
        for m in methods:
            f = {k: np.array([r[m][k] for r in rs]) for k in ("b_err", "k_rel_err", "delay_err_ms", "heading_rms_deg",
                                                             "heading_rms_about_mean_deg")}
            med[m] = float(np.median(f["b_err"]))
            lines.append(f"disturbed {dist:4.0%} {m:6s} n={len(rs)}  hard iron err median {med[m]:.3f} max "
                         f"{f['b_err'].max():.3f} uT | k_I rel err median {np.median(f['k_rel_err']):.3f} max "
                         f"{f['k_rel_err'].max():.3f} | delay err median {np.median(f['delay_err_ms']):.1f} max "
                         f"{f['delay_err_ms'].max():.1f} ms | heading RMS median {np.median(f['heading_rms_deg']):.2f} "
                         f"max {f['heading_rms_deg'].max():.2f} deg, about its mean median "
                         f"{np.median(f['heading_rms_about_mean_deg']):.2f} max {f['heading_rms_about_mean_deg'].max():.2f}")
            if all("b_err_level" in r[m] for r in rs):
                bl = np.array([r[m]["b_err_level"] for r in rs])
                lines.append(f"disturbed {dist:4.0%} {m:6s} hard iron err with the b_z/A_22 trade removed (--level-hard-iron) "
                             f"median {np.median(bl):.3f} max {bl.max():.3f} uT")
            if m == "stream" and all("b_err_window" in r[m] for r in rs):
                bw = np.array([r[m]["b_err_window"] for r in rs])
                lines.append(f"disturbed {dist:4.0%} stream: the last window's own trial (before pooling) hard iron err "
                             f"median {np.median(bw):.3f} max {bw.max():.3f} uT")
        peers = [m for m in ("magfit", "px4") if m in med]
        if "ours" in med and peers:
            best = min(med[m] for m in peers)
            lines.append(f"disturbed {dist:4.0%} hard-iron median: best peer ({'/'.join(peers)}) {best:.3f} uT = "
                         f"{best / max(med['ours'], 1e-12):.1f} x ours")
    my = np.abs([r["log_yaw_error_mean_deg"] for r in runs])
    lines.append(f"the log's mean yaw error over a flight: |mean| median {np.median(my):.2f} max {my.max():.2f} deg "
                 f"(RMS {np.median([r['log_yaw_error_rms_deg'] for r in runs]):.2f} deg median)")
    return "\n".join(lines)


def make_plot(runs, path):
    """Hard-iron error per method and disturbance (log scale), and our heading error against the log's
    mean yaw error over the flight."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = _present(runs)
    dists = sorted({r["disturbed"] for r in runs})
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(12, 4.6), gridspec_kw={"width_ratios": [1.6, 1]})
    width = 0.8 / len(methods)
    for j, m in enumerate(methods):
        for i, dist in enumerate(dists):
            v = np.array([r[m]["b_err"] for r in runs if r["disturbed"] == dist])
            x = i + (j - (len(methods) - 1) / 2) * width
            ax.plot(np.full(v.size, x), v, "o", ms=4, alpha=0.6, color=f"C{j}", label=LABELS[m] if i == 0 else None)
            ax.plot([x - width / 2.5, x + width / 2.5], [np.median(v)] * 2, "-", color=f"C{j}", lw=2.5)
    ax.set_yscale("log")
    ax.set_xticks(range(len(dists)), [f"{d:.0%} disturbed" for d in dists])
    ax.set_ylabel("hard-iron error |b - b_true| (uT)")
    ax.axhline(0.3, color="k", lw=0.7, ls=":")
    ax.legend(fontsize=8)
    ax.set_title(f"simulated level flights, {np.median([r['minutes'] for r in runs]):.0f} min, "
                 f"{len({r['seed'] for r in runs})} seeds (bar: median)")
    if "ours" in methods:
        my = np.array([abs(r["log_yaw_error_mean_deg"]) for r in runs])
        hd = np.array([r["ours"]["heading_rms_deg"] for r in runs])
        hf = np.array([r["ours"].get("heading_rms_full_model_deg", np.nan) for r in runs])
        ax2.plot(my, hd, "o", label="heading RMS, calibration as delivered (S, b)")
        ax2.plot(my, hf, "s", mfc="none", label="with the fitted misalignment applied too")
        lim = max(1.2, float(np.nanmax(np.concatenate([my, hd, hf]))) * 1.1)
        ax2.plot([0, lim], [0, lim], "k:", lw=0.8, label="= |mean yaw error|")
        ax2.axhline(1.0, color="r", lw=0.7, ls="--")
        ax2.set_xlabel("|the log's mean yaw error over the flight| (deg)")
        ax2.set_ylabel("heading error of our calibration (deg)")
        ax2.legend(fontsize=8)
        ax2.set_title("heading error vs the attitude's mean yaw error")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--minutes", type=float, nargs=2, default=(30.0, 30.0), help="flight duration drawn in this range")
    ap.add_argument("--rate", type=float, default=10.0, help="samples per second")
    ap.add_argument("--disturbed", type=float, nargs="+", default=(0.0, 0.1, 0.25))
    ap.add_argument("--methods", default=",".join(METHODS), help="comma-separated subset of " + ",".join(METHODS))
    ap.add_argument("--mounting-deg", type=float, default=0.0,
                    help="the magnetometer turned by this angle (deg) about the body's z axis (default 0)")
    ap.add_argument("--yaw-error-deg", type=float, default=None,
                    help="the logged yaw's RMS error (deg) instead of one drawn in 2-5 deg per flight")
    ap.add_argument("--level-hard-iron", action="store_true",
                    help="also record the hard-iron error with the b_z/A_22 trade of level flight removed (module doc)")
    ap.add_argument("--tilt-sd-deg", default="auto",
                    type=lambda v: v if v == "auto" else None if v == "off" else float(v),
                    help="the attitude's roll/pitch error (deg) corrected for: a value (ours and ls), 'auto' "
                         "(default: estimated from the residuals, as fit_flight; ours only) or 'off'")
    ap.add_argument("--json", help="write every run's figures here (rewritten after each run)")
    ap.add_argument("--from-json", nargs="+", help="summarise (and plot) these runs' JSON files instead of running")
    ap.add_argument("--plot", help="write the study's PNG here (matplotlib)")
    a = ap.parse_args(argv)
    methods = tuple(m for m in a.methods.split(",") if m)
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        ap.error(f"unknown method(s) {', '.join(unknown)}; choose from {', '.join(METHODS)}")
    runs = []
    if a.from_json:
        merged = {}
        for path in a.from_json:           # the same (seed, disturbed) in several files: their methods merged
            with open(path, encoding="utf-8") as fh:
                for r in json.load(fh):
                    merged.setdefault((r["seed"], r["disturbed"]), {}).update(r)
        runs = [merged[k] for k in sorted(merged)]
    else:
        for seed in range(a.first_seed, a.first_seed + a.seeds):
            for dist in a.disturbed:
                r = run(seed, dist, a.minutes, a.rate, methods, a.mounting_deg, a.yaw_error_deg, a.level_hard_iron,
                          a.tilt_sd_deg)
                runs.append(r)
                print(f"seed {seed} disturbed {dist:.0%} {r['minutes']:.1f} min lat {r['lat']:g} log yaw error RMS "
                      f"{r['log_yaw_error_rms_deg']:.1f} mean {r['log_yaw_error_mean_deg']:+.2f} deg: " + "; ".join(
                          f"{m} b {r[m]['b_err']:.3f} uT k {r[m]['k_rel_err']:.3f} delay {r[m]['delay_err_ms']:.1f} ms "
                          f"heading {r[m]['heading_rms_deg']:.2f} deg ({r[m]['cpu_s']:.1f} s)" for m in methods),
                      flush=True)
                if a.json:
                    with open(a.json, "w", encoding="utf-8") as fh:
                        json.dump(runs, fh, indent=1)
    print(summarise(runs))
    if a.plot:
        make_plot(runs, a.plot)


if __name__ == "__main__":
    main()
