"""The baseline model: what a plain simulator knows about the sensor, fitted to the recording.

Baseline = the MKC-EM calibration (b, S, F) refined by the same Gauss-Newton fit the effects
use, the dip angle when there is an accelerometer, white noise per axis, disturbance bursts
(their rate, length and size taken from where the robust fit down-weighted samples), and a
regular clock (plus the timestamp quantum, if the timestamps lie on one). Whether the
calibrator would accept that calibration, and so what the recording can test, is its
:class:`~.scope.Scope`.

Dip and inclination: the model's dip parameter (``State.dip0``) is the angle between the
calibrated field and the accelerometer's specific force, which points up at rest (about 150 deg
where the field dips 60 deg below the horizontal). It is reported as the geomagnetic inclination,
the angle of the field below the horizontal, positive downward (northern hemisphere):
I = dip0 - 90 deg.

Noise level: from third differences (m_{k+3} - 3 m_{k+2} + 3 m_{k+1} - m_k, variance 20 sigma^2
for white noise), robustly (MAD). Third differences cancel the motion (to second order) and
anything slow, so the estimate is the sensor's white noise even when slow effects are present;
those then show up as a gap instead of being absorbed into a larger noise.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from ..robust import mad_sd
from ..sim.effects.base import Evidence
from ..sim.sensor import SensorModel
from ..sim.trajectory import Trajectory, moving_average
from .frame import DiagnoseError, Frame
from .model import ModelFit, State, channels, far_neighbours, fit_model, n_channels
from .scope import Scope, baseline_scope

#: how the reported inclination is defined (stated beside it in the JSON)
INCLINATION_CONVENTION = ("angle of the field below the horizontal, positive downward (northern hemisphere), deg; "
                          "from the angle between the field and the accelerometer's specific force (up at rest) "
                          "minus 90 deg")


def inclination_deg(dip0: float) -> float:
    """The geomagnetic inclination (deg, positive down) from the model's field-to-specific-force
    angle dip0 (rad): I = dip0 - 90 deg (the specific force points up, so a field I below the
    horizontal is 90 + I deg from it). NaN when dip0 lies outside 0-180 deg: the angle between two
    vectors cannot, and a fit that put its constant there (a baseline the calibrator rejects, seen
    at -40 deg on a flight log) has not determined the inclination."""
    deg = float(np.degrees(dip0))
    return deg - 90.0 if 0.0 <= deg <= 180.0 else float("nan")


@dataclass
class Baseline:
    fit: ModelFit                # on all samples
    sigma: np.ndarray            # (C,) channel noise scale
    sigma_axis: np.ndarray       # (3,) white noise per raw axis
    sensor: SensorModel          # for replicas
    traj: Trajectory             # the recording's directions and times
    valid: np.ndarray            # (N, C)
    lattice: dict                # q (3,), phase (3,), strength (3,)
    clock: dict                  # dt0, quantum, phase
    evidence: Evidence
    bursts: dict
    ellipsoid: object
    scope: Scope | None = None       # what the recording can test (the calibrator's verdict on the fit)


def robust_sd(x) -> float:
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]
    if x.size < 2:
        return float("nan")
    return float(mad_sd(x))


def hf_sigma(x) -> float:
    """White-noise sigma from third differences (robust)."""
    d3 = x[3:] - 3 * x[2:-1] + 3 * x[1:-2] - x[:-3]
    return robust_sd(d3) / np.sqrt(20.0)


def detect_lattice(x: np.ndarray, max_n: int = 20000):
    """(q, phase, strength): the step of a lattice the values lie on, or strength ~ 0 when none."""
    x = np.asarray(x, dtype=np.float64)
    if x.size > max_n:
        x = x[:: int(np.ceil(x.size / max_n))]
    u = np.unique(x)
    if u.size < 5:
        return float("nan"), 0.0, 0.0
    d = np.diff(u)
    d = d[d > 1e-12 * max(1.0, float(np.abs(u).max()))]
    if d.size < 3:
        return float("nan"), 0.0, 0.0
    q0 = float(np.percentile(d, 5))
    q = float(np.median(d[d < 1.5 * q0]))
    ph = np.exp(2j * np.pi * x / q)
    z = ph.mean()
    return q, float(np.angle(z) / (2 * np.pi) * q), float(abs(z))


MERGE_GAP = 10   # samples: down-weighted runs closer than this are one burst (a burst's norm residual
                 # dips below the cut wherever its offset happens to be perpendicular to the field)


BURST_WINDOW = 151   # samples: a burst is an excursion from the residual's running median over this window


AXIS_NOISE_PASSES = 3
AXIS_NOISE_CUT = 10.83    # chi2(1) at 0.999: a standardised squared third difference beyond it is a burst edge


def axis_noise(fit, s_hf):
    """White noise per raw axis, from the norm channel itself: the third differences of the norm
    residual have variance sum_i c_i^2 sum_j (S^T v_i)_j^2 sigma_j^2 (c = 1, -3, 3, -1 over the
    four samples), and v turns, so a least-squares fit of their squares on (S^T v)_j^2 separates
    the axes. (The raw axes' own differences would be cheaper but carry the motion, differently
    on each axis.) Isotropic when the fit is not determined or not positive.

    The level is then read robustly from the third differences standardised by the fitted
    per-sample spread: with unequal axis noise the norm channel's noise changes with the
    direction, so its third differences are a scale mixture of normals, whose MAD (``s_hf``)
    reads the RMS 3-7% low (measured with 1.5-2x between the axes); replicas that quiet fail the
    high-frequency statistics (Allan variance at 1-2 samples, the top band) of a null."""
    e, ok = fit.e[:, 0], fit.inlier[:, 0]
    JS2 = (fit.v @ fit.state.S) ** 2
    d3 = e[3:] - 3 * e[2:-1] + 3 * e[1:-2] - e[:-3]
    good = ok[3:] & ok[2:-1] & ok[1:-2] & ok[:-3]
    y = d3[good] ** 2 / 20.0
    X = ((JS2[3:] + 9.0 * JS2[2:-1] + 9.0 * JS2[1:-2] + JS2[:-3]) / 20.0)[good]
    iso = float(np.sqrt(np.mean(np.sum(JS2, axis=1))))
    if y.size > 200:
        keep = y <= np.percentile(y, 99)                 # keep the odd burst edge out
        for _ in range(AXIS_NOISE_PASSES):
            coef, *_ = np.linalg.lstsq(X[keep], y[keep], rcond=None)
            if not np.all(coef > 0):
                break
            # cut on the standardised square, so the cut takes the same share of every
            # direction (a cut on y itself takes more from the noisier directions and draws
            # the axes together)
            keep = y / (X @ coef) <= AXIS_NOISE_CUT
        else:
            # z_i^2 = y_i / (X_i coef) is chi2(1) times k^2 when the shape is right; the level
            # k^2 from its mean below the cut, E[z^2 1(z^2 <= c)] = P(chi2_3 <= c) for a
            # standard normal (a trimmed variance: near the mean square's precision, which the
            # high-frequency statistics compared with the replicas have, and bursts cut away)
            z2 = y / (X @ coef)
            k2 = float(np.mean(np.where(z2 <= AXIS_NOISE_CUT, z2, 0.0))) / chi2.cdf(AXIS_NOISE_CUT, 3)
            if np.isfinite(k2) and k2 > 0:
                return np.sqrt(coef * k2)
    return np.full(3, s_hf / iso)


#: samples: the window lengths of the hidden-burst scan (a burst of 20-60 samples is caught by the
#: shorter ones, and a window no longer than 32 follows an effect that turns with the sensor)
SCAN_WINDOWS = (4, 8, 16, 32)
#: the scan's cut on a window's standardised sum: the two-sided normal tail beyond 5.5 is 3.8e-8, so
#: white noise gives at most len(SCAN_WINDOWS) x N x 3.8e-8 = 1.5e-3 flagged windows per 10^4
#: samples (a union bound; overlapping windows share their exceedances)
SCAN_CUT = 5.5


def running_median(x, ok, size=BURST_WINDOW):
    """The running median of x over ``size`` samples (fewer on short series), with the samples
    not ``ok`` set to the median of the rest. A median follows a drift and drops a run shorter
    than half its window."""
    from scipy.ndimage import median_filter

    x = np.asarray(x, dtype=np.float64)
    good = ok & np.isfinite(x)
    fill = np.where(good, x, np.median(x[good]) if good.any() else 0.0)
    # mirrored at the ends: "nearest" repeats the end sample over half the window, and the median
    # near an end is then that one sample
    return median_filter(fill, size=min(size, max(3, x.size // 4 * 2 + 1)), mode="mirror")


def _excess(C, K, med, half, i, j):
    """The box [i, j)'s summed excess over the level before it and over the level after it (the
    medians of the ``2 half + 1`` samples on either side), and its count of samples."""
    n = med.size
    k = K[j] - K[i]
    s = C[j] - C[i]
    return s - k * med[np.clip(i - half - 1, 0, n - 1)], s - k * med[np.clip(j + half, 0, n - 1)], k


def _window_excess(C, K, med, half, L):
    """:func:`_excess` of every box [i, i + L), i = 0 .. n - L, by slices (the same values)."""
    n = med.size
    m = n - L + 1
    k = K[L:L + m] - K[:m]
    s = C[L:L + m] - C[:m]
    # med[clip(i - half - 1)] and med[clip(i + L + half)]
    before = np.concatenate([np.full(min(half + 1, m), med[0]), med[:max(m - half - 1, 0)]])
    after = np.concatenate([med[min(L + half, n - 1):n], np.full(max(m - (n - L - half), 0), med[n - 1])])[:m]
    return s - k * before, s - k * after, k


def scan_runs(z, ok, windows=SCAN_WINDOWS, cut=SCAN_CUT, longest=BURST_WINDOW // 2):
    """(N,) bool: the short runs of ``z`` (a residual in white-noise units) that stand out from the
    level before them AND from the level after them, jointly improbable although no sample is an
    outlier. A disturbance burst whose offset lies almost across the field moves the field
    strength by a sigma or two per sample, below any per-sample cut, for tens of samples, and
    then returns. A step stands out from one side only, a drift from the two sides with opposite
    signs, a slow effect from neither: none is flagged.

    The statistic of a box of L samples (the ``ok`` ones among them, k >= L/2), against each side's
    level (the median of BURST_WINDOW ``ok`` samples): T = sum(z - level) / (s_L sqrt(k)), with s_L
    the larger of 1 and the robust spread of all half-overlapping L-sample sums over sqrt(L) (the
    levels' own noise, and a coloured noise's excursions, which are not bursts); the box's
    statistic is the smaller |T| of the two sides when both have the same sign. Windows of
    ``windows`` samples with |T| > ``cut`` mark a region; in each region the box of
    ``windows[0]`` to ``longest`` samples with the largest statistic is flagged and the rest of the
    region searched again (one region can hold two bursts), so a flag covers the burst, not the
    windows that overlap it."""
    n = z.size
    flag = np.zeros(n, dtype=bool)
    if n < 2 * windows[0]:
        return flag
    good = ok & np.isfinite(z)
    med = running_median(z, good)
    half = min(BURST_WINDOW, max(3, n // 4 * 2 + 1)) // 2
    C = np.concatenate([[0.0], np.cumsum(np.where(good, z, 0.0))])
    K = np.concatenate([[0.0], np.cumsum(good.astype(np.float64))])
    scale = np.ones(len(windows))
    mark = np.zeros(n + 1)

    def statistic(left, right, k, s_box):
        same = np.sign(left) == np.sign(right)
        return np.where(same, np.minimum(np.abs(left), np.abs(right)), 0.0) / (s_box * np.sqrt(np.maximum(k, 1.0)))

    def both_sides(i, j, s_box):
        left, right, k = _excess(C, K, med, half, i, j)
        return statistic(left, right, k, s_box), k

    for w, L in enumerate(windows):
        if L > n:
            scale[w:] = scale[w - 1] if w else 1.0
            break
        i = np.arange(n - L + 1)
        left, right, k = _window_excess(C, K, med, half, L)
        full = (k >= L)[:: max(1, L // 2)]
        if full.sum() > 20:
            scale[w] = max(1.0, mad_sd(left[:: max(1, L // 2)][full]) / np.sqrt(L))
        T = statistic(left, right, k, scale[w])
        start = np.flatnonzero((T > cut) & (k >= L / 2))
        np.add.at(mark, start, 1.0)
        np.add.at(mark, start + L, -1.0)
    region = np.cumsum(mark[:-1]) > 0
    if not region.any():
        return flag
    edges = np.flatnonzero(np.diff(np.concatenate([[0], region.astype(np.int8), [0]])))
    todo = list(zip(edges[0::2], edges[1::2]))
    span = np.arange(windows[0], longest + 1)                 # box lengths j - i
    span_scale = scale[np.searchsorted(windows, span, side="right") - 1]
    while todo:
        a, b = todo.pop()
        if b - a < windows[0]:
            continue
        i = np.arange(a, b - windows[0] + 1)[:, None]
        j = i + span[None, :]
        inside = j <= b
        T, k = both_sides(i, np.minimum(j, b), span_scale)
        T[~inside | (k < span / 2)] = 0.0
        best = np.unravel_index(int(np.argmax(T)), T.shape)
        if T[best] <= cut:
            continue
        lo, hi = a + int(best[0]), a + int(best[0]) + int(span[best[1]])
        flag[lo:hi] = True
        todo += [(a, lo), (hi, b)]
    return flag & good


def hidden_bursts(z, ok):
    """(N,) bool: :func:`scan_runs` of the standardised residual ``z`` over the ``ok`` samples
    (the inliers: an outlier is flagged already)."""
    return scan_runs(z, ok)


def estimate_bursts(e, valid, sigma):
    """Disturbance bursts: runs of samples more than 4 sigma away from the residual's running
    median and the runs :func:`hidden_bursts` finds among the rest (merged over short gaps),
    with each run's length and median |excursion|.

    Against the running median, not zero: a slow unmodelled effect (a wander, a drift, a
    temperature offset) moves the residual for minutes and is not a burst; counting it as bursts
    would give the replicas spurious disturbances and hide the effect."""
    dev = e - running_median(e, valid)
    # 4 of the larger of sigma (the kernel's white core) and the deviations' own robust spread:
    # a coloured noise a few times the core turns with the sensor faster than the running
    # median follows, and its peaks are not bursts (counted as bursts, they were put into every
    # replica on top of the noise that made them)
    spread = robust_sd(dev[valid])
    sigma = max(float(sigma), spread if np.isfinite(spread) else 0.0)
    out = valid & (np.abs(dev) > 4.0 * sigma)
    # the bursts no sample of which is an outlier (an offset almost across the field): the
    # panel's scan (:func:`hidden_bursts`) over the samples that are not
    hidden = hidden_bursts(e / sigma, valid & ~out)
    e = dev
    idx = np.flatnonzero(out | hidden)
    if idx.size == 0:
        return {"fraction": 0.0, "lengths": (), "sizes": (), "count": 0}
    splits = np.flatnonzero(np.diff(idx) > MERGE_GAP) + 1
    runs = [(int(r[0]), int(r[-1]) + 1, r.size) for r in np.split(idx, splits)]
    # a burst lasts (several excursions), is large or is a scan's run; a lone 4-5 sigma sample is
    # the noise's own tail, which the replicas' noise already has
    runs = [(a, b) for a, b, k in runs if k >= 3 or np.abs(dev[a:b]).max() > 8.0 * sigma or hidden[a:b].any()]
    if not runs:
        return {"fraction": 0.0, "lengths": (), "sizes": (), "count": 0}
    lengths = tuple(b - a for a, b in runs)
    sizes = tuple(round(float(np.median(np.abs(e[a:b]))), 6) for a, b in runs)
    return {"fraction": float(sum(lengths)) / e.size, "lengths": lengths, "sizes": sizes, "count": len(runs)}


class BurstReplica:
    """Replica bursts: the recording's own bursts (lengths and sizes) at random places, each a
    constant raw offset in a random direction (an offset d shows about |d|/2 in the norm)."""

    name, stage = "bursts", "offset"

    def __init__(self, bursts):
        self.lengths, self.sizes = bursts["lengths"], bursts["sizes"]

    def apply(self, ctx, params):
        n = ctx.n
        used = np.zeros(n, dtype=bool)
        for L, size in zip(self.lengths, self.sizes):
            L = int(min(L, n // 4))
            for _ in range(50):
                a = int(ctx.rng.integers(0, max(1, n - L)))
                if not used[max(0, a - 5):a + L + 5].any():
                    break
            d = ctx.rng.normal(size=3)
            ctx.m[a:a + L] += 2.0 * size * d / np.linalg.norm(d)
            used[a:a + L] = True


def _rotation_rate(frame: Frame, v: np.ndarray) -> float:
    if frame.gyro is not None:
        w = np.linalg.norm(frame.gyro, axis=1)
        w = w[np.isfinite(w)]
        return float(np.percentile(w, 90)) if w.size else 0.0
    vs = moving_average(v, 5)
    vs /= np.linalg.norm(vs, axis=1, keepdims=True)
    ang = np.arccos(np.clip(np.sum(vs[1:] * vs[:-1], axis=1), -1, 1))
    dt = np.maximum(np.diff(frame.t), 1e-9)
    return float(np.percentile(ang / dt, 90))


def sphere_stand_in(m: np.ndarray):
    """The baseline calibration when the samples give no ellipsoid: a robust sphere (hard iron and
    field strength, S = I), only so that the residual channels exist. The scope rejects it, so no
    statistic or effect that reads the calibration is tested."""
    from types import SimpleNamespace

    from ..calib.ellipsoid import robust_sphere_fit
    from ..calib.quality import quality_figures

    fit = robust_sphere_fit(m) if m.shape[0] >= 8 else None
    if fit is None or not (np.all(np.isfinite(fit[0])) and np.isfinite(fit[1]) and fit[1] > 0):
        raise DiagnoseError("the baseline calibration failed: the samples give neither an ellipsoid nor a sphere")
    b, F = np.asarray(fit[0], dtype=np.float64), float(fit[1])
    return SimpleNamespace(hard_iron=b, soft_iron=np.eye(3), field=F, weights=None, method="sphere",
                           quality=quality_figures(m - b, F, float("inf")))


def fit_baseline(frame: Frame) -> Baseline:
    from ..calib.ellipsoid import EllipsoidError
    from ..calib.fit import fit_ellipsoid
    from ..calib.quality import sphere_coverage

    no_ellipsoid = None
    try:
        ell = fit_ellipsoid(frame.m, "mkc-em")
    except EllipsoidError as exc:
        # the samples give no ellipsoid (a flight that never tilts, a robot on the floor): the
        # calibration-free part (raw values, timestamps) is still tested, around a sphere stand-in
        ell = sphere_stand_in(frame.m)
        no_ellipsoid = f"the samples give no ellipsoid: {exc}"
    C = n_channels(frame)
    st = State(ell.hard_iron.copy(), ell.soft_iron.copy(), float(ell.field), 0.0)
    ch = channels(frame.m, frame, st)
    valid = np.ones((frame.n, C), dtype=bool)
    if C == 2:
        valid[:, 1] = frame.acc_ok
        st.dip0 = float(np.median(ch.r[frame.acc_ok, 1]))
        ch = channels(frame.m, frame, st)
    w_ok = ell.weights > 0.5 if ell.weights is not None else np.ones(frame.n, bool)
    sigma = np.array([robust_sd(ch.r[w_ok, 0])] + ([robust_sd(ch.r[frame.acc_ok, 1])] if C == 2 else []))
    if not np.all(sigma > 0):
        raise DiagnoseError("the residuals have no spread (a constant or synthetic signal?)")
    fit = fit_model(frame, st, [], valid, sigma)
    # noise scales: white part of the norm channel; robust spread of the dip channel
    s_hf = hf_sigma(fit.e[fit.valid[:, 0], 0])
    sigma = np.array([s_hf] + ([robust_sd(fit.e[valid[:, 1], 1])] if C == 2 else []))
    if not np.all(sigma > 0):
        raise DiagnoseError("the residual noise is zero: nothing to compare against")
    fit = fit_model(frame, fit.state, [], valid, sigma, iters=2)

    sigma_axis = axis_noise(fit, s_hf)
    bursts = estimate_bursts(fit.e[:, 0], valid[:, 0], sigma[0])
    sensor = SensorModel(field=fit.state.F, hard_iron=tuple(fit.state.b), soft_iron=fit.state.S,
                         noise=tuple(sigma_axis), lsb=0.0, burst_fraction=0.0, acc_noise=0.0, gyro_noise=0.0)
    # the replicas' field directions: a 5-sample average (smooths the sample's noise out of its
    # direction), but the sample's own fitted direction where its neighbours are far apart (the
    # rule of .model.noise_free_point): there the average points elsewhere (a median 0.74 rad off
    # at 0.8 rad between samples), and as the noise along the field depends on the direction,
    # replicas along it are not as noisy as the recording (figure-8 nulls decimated by 50: ~3%
    # quieter in the norm channel, a false gap)
    u = moving_average(fit.v, 5)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    far = far_neighbours(fit.m_corr, fit.state)
    u[far] = fit.v[far]
    traj = Trajectory(t=frame.t, field_dir=u, acc=None, gyro=None, aux=dict(frame.aux), name="recording")

    lat = [detect_lattice(frame.m[:, j]) for j in range(3)]
    lattice = {"q": np.array([x[0] for x in lat]), "phase": np.array([x[1] for x in lat]),
               "strength": np.array([x[2] for x in lat])}
    tq, tph, tR = detect_lattice(frame.t - frame.t[0])
    quantum = tq if (tR > 0.9 and np.isfinite(tq) and tq < 0.5 * frame.dt0) else 0.0
    clock = {"dt0": frame.dt0, "quantum": quantum, "phase": tph if quantum else 0.0, "t0": float(frame.t[0])}

    spans = {}
    for name, x in frame.aux.items():
        spans[name] = float(np.percentile(x, 97.5) - np.percentile(x, 2.5))
    ev = Evidence(n=frame.n, duration=frame.duration, rate=1.0 / frame.dt0, aux_span=spans,
                  has_acc=frame.acc_unit is not None, has_gyro=frame.gyro is not None,
                  coverage=sphere_coverage(fit.v), rotation_rate=_rotation_rate(frame, fit.v),
                  timestamps_real=frame.timestamps_real)
    return Baseline(fit=fit, sigma=sigma, sigma_axis=sigma_axis, sensor=sensor, traj=traj,
                    valid=valid, lattice=lattice, clock=clock, evidence=ev, bursts=bursts, ellipsoid=ell,
                    scope=baseline_scope(ell, frame.unit, ev.coverage, no_ellipsoid))
