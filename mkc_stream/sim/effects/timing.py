"""Timing effects: the magnetometer sample is late, its timestamp wanders, samples go missing.

* latency: the magnetometer reports the field of ``delay`` ms earlier than the accelerometer
  and gyroscope samples it is stamped with (1-100 ms: filters, bus scheduling); visible only
  against the accelerometer while the sensor rotates. ``spread`` is the RMS width of the
  sensor's output filter around that delay (0: a pure transport delay). A filter averages field
  directions that a turn spreads apart, so the field strength it reports drops at fast turns,
  by spread^2 |dB/dt|^2 / (2 |B|) to second order: seen in the field strength too, not only
  against the accelerometer. A sampled first-order filter of time constant T (ODR averaging) has a
  delay of about T and a spread of about sqrt(T (T + dt)).
* timestamp_jitter: reported timestamps scatter around the true sampling instants
  (0.05-5 ms RMS: host-side stamping), Gaussian or heavier-tailed (scheduling delays).
* sample_drops: samples are lost (0.1-10 %), in runs of ``run`` samples on average.

Diagnosis: latency is fitted as a delay and a filter variance, linear to second order in time;
jitter and drops are estimated from the statistics of the time steps and carried by the replicas.
"""
from __future__ import annotations

import numpy as np

from .base import Effect, Param, SimContext
from .form import EstimatedForm, MeanForm, single_design


#: Gauss-Hermite nodes of the output filter (probabilists'): exact mean and variance, and its
#: higher moments are those of a Gaussian impulse response
_FILTER_NODES = 7


def _latency_forward(ctx: SimContext, delay, spread=0.0):
    if ctx.field_at is None:
        raise ValueError("latency needs a trajectory that can be evaluated between samples")
    t0 = ctx.t - delay * 1e-3
    if spread <= 0:
        ctx.B[:] = ctx.field_at(t0)
        return
    x, w = np.polynomial.hermite_e.hermegauss(_FILTER_NODES)
    w = w / w.sum()
    ctx.B[:] = sum(wi * ctx.field_at(t0 - xi * spread * 1e-3) for xi, wi in zip(x, w))


def gennorm_beta(excess_kurtosis: float) -> float:
    """Shape beta of the generalised normal distribution with this excess kurtosis (2 = Gaussian)."""
    from scipy.optimize import brentq
    from scipy.special import gammaln

    if excess_kurtosis <= 1e-6:
        return 2.0
    f = lambda b: np.exp(gammaln(5 / b) + gammaln(1 / b) - 2 * gammaln(3 / b)) - 3.0 - excess_kurtosis  # noqa: E731
    return float(brentq(f, 0.15, 2.0)) if f(0.15) > 0 else 0.15


def _jitter_forward(ctx: SimContext, sigma, kurtosis):
    if kurtosis > 1e-6:
        from scipy.stats import gennorm

        beta = gennorm_beta(kurtosis)
        e = gennorm.rvs(beta, size=ctx.n, random_state=ctx.rng)
        e *= sigma * 1e-3 / gennorm.std(beta)
    else:
        e = ctx.rng.normal(0.0, sigma * 1e-3, ctx.n)
    ctx.t_out[:] = np.maximum.accumulate(ctx.t_out + e)      # a reader refuses decreasing time


def _drops_forward(ctx: SimContext, fraction, run):
    """Runs of geometric length (mean ``run``) start at random until ``fraction`` is lost."""
    n = ctx.n
    target = int(round(fraction * n))
    lost = 0
    guard = 0
    while lost < target and guard < 100 * n:
        guard += 1
        start = int(ctx.rng.integers(1, max(2, n - 1)))
        length = int(min(ctx.rng.geometric(1.0 / max(run, 1.0)), target - lost))
        seg = ctx.keep[start:start + length]
        lost += int(seg.sum())
        seg[:] = False


def _needs_acc_and_motion(ev):
    if not ev.has_acc:
        return False, "needs an accelerometer (ax, ay, az) to time the magnetometer against"
    if ev.rotation_rate < 0.3:
        return False, f"the sensor turns at most ~{ev.rotation_rate:.2f} rad/s (needs >= 0.3)"
    return True, f"accelerometer present, turning at up to ~{ev.rotation_rate:.2f} rad/s"


def _needs_clock(ev):
    if not ev.timestamps_real:
        return False, "the timestamps were made from the sample index, not recorded"
    return True, "recorded timestamps"


# -- diagnosis forms ---------------------------------------------------------------------------

#: the latency form's second parameter is the output filter's variance in units of (0.1 s)^2. In
#: ms^2 its column is so small beside the calibration's that the solver's relative ridge
#: (mkc_stream.diagnose.model._solve) held it far from its value (40 against 230 ms^2 after the
#: fit's three steps)
_SPREAD_UNIT_MS = 100.0


def _latency_G(env, d):
    """A delay and an output filter, to second order in time: any filter with impulse-response
    mean mu and variance s^2 turns a field B(t) into B - mu B' + (s^2 + mu^2) / 2 B'' + ...
    The first-order term turns the field (tangent to the ellipsoid: the dip channel). The
    second-order term's radial part is all that changes the strength: |B_out| = |B| - s^2
    |B'|^2 / (2 |B|) (B . B' = 0 and B . B'' = -|B'|^2 for a constant strength), so a pure
    delay (s = 0) keeps it and a filter lowers it at fast turns (the norm channel, where the
    noise is the magnetometer's own and white). Its tangential part (from the angular
    acceleration) is left out: it needs the field's second derivative, noisy at 20 Hz, and the
    strength term alone explained the benchmark's filtered latencies."""
    md = env.mdot() * 1e-3                     # per ms of delay
    # |B'|^2 in (uT/s)^2 = |tan|^2 1e6; times s^2 / 2 with s in units of _SPREAD_UNIT_MS
    scale = 0.5 * (_SPREAD_UNIT_MS * 1e-3) ** 2 * 1e6

    def g(frame, m, st):
        mc = (m - st.b) @ st.S.T
        r = np.linalg.norm(mc, axis=1, keepdims=True)
        v = mc / r
        Sinv_t = np.linalg.inv(st.S).T
        mdc = md @ st.S.T
        tan = mdc - np.sum(v * mdc, axis=1, keepdims=True) * v
        out = np.empty((m.shape[0], 3, 2))
        out[:, :, 0] = -tan @ Sinv_t
        out[:, :, 1] = (-scale * np.sum(tan * tan, axis=1, keepdims=True) / r * v) @ Sinv_t
        return out
    return g


def _latency_magnitude(env, d, th):
    spread = _SPREAD_UNIT_MS * float(np.sqrt(max(th[1], 0.0)))
    return {"value": float(th[0]), "unit": "ms", "filter_spread_ms": spread,
            "meaning": "magnetometer later than the accelerometer (filter_spread_ms: RMS width "
                       "of its output filter; 0 for a pure delay)"}


def _clock_sums(bs, mult):
    return bs["clock"] @ mult


def _jitter_estimate(env, ctx, mult):
    """RMS from the variance of the time steps above the replicas' (a step is the difference of
    two independent errors: twice their variance); the shape from the steps' excess kurtosis
    (half that of the errors)."""
    ck = _clock_sums(ctx.real_bs, mult)
    n = max(ck[0], 1)
    v = ck[2] / n
    vr = np.array([(lambda c: c[2] / max(c[0], 1))(_clock_sums(bs, mult)) for bs in ctx.rep_bs])
    ex = v - vr.mean()
    se = max(vr.std(ddof=1) if vr.size > 2 else 0.0, v * np.sqrt(2.0 / n))
    if not ex > 3 * se or not ex > 1e-8:
        return None
    mu = ck[7] / n
    m2 = v - mu * mu
    m4 = ck[6] / n - 4 * mu * (ck[2] / n) * mu + 6 * mu * mu * v - 3 * mu ** 4  # central 4th moment (approx.)
    kd = m4 / max(m2 * m2, 1e-300) - 3.0
    return {"sigma": float(np.sqrt(ex / 2.0) * env.frame.dt0 * 1e3), "kurtosis": float(np.clip(2.0 * kd, 0.0, 20.0))}


def _drops_estimate(env, ctx, mult):
    ck = _clock_sums(ctx.real_bs, mult)
    lost, events = ck[3], ck[5]
    if lost < 1:
        return None
    steps = ck[0] + ck[3] + ck[4]
    return {"fraction": float(lost / max(steps + lost, 1)), "run": float(lost / max(events, 1))}


# -- the library's entries ------------------------------------------------------------------------

LATENCY = Effect(
    name="latency", family="timing", stage="field",
    params=(Param("delay", "ms", 1.0, 100.0, 20.0),
            Param("spread", "ms", 0.0, 60.0, 0.0, "RMS width of the output filter around the delay (0: pure delay)")),
    needs=("acc",), forward=_latency_forward, testable=_needs_acc_and_motion,
    form=MeanForm(single_design, _latency_G, 2, _latency_magnitude),
    doc="magnetometer samples the field delay ms earlier than stamped, averaged over +-spread ms")

TIMESTAMP_JITTER = Effect(
    name="timestamp_jitter", family="timing", stage="clock",
    params=(Param("sigma", "ms", 0.05, 5.0, 1.0, "RMS timestamp error"),
            Param("kurtosis", "1", 0.0, 20.0, 0.0, "excess kurtosis of the error (0 Gaussian, 3 Laplace)")),
    needs=(), forward=_jitter_forward, testable=_needs_clock,
    form=EstimatedForm("clock", _jitter_estimate,
                       lambda env, p: [(TIMESTAMP_JITTER, {"sigma": p["sigma"], "kurtosis": p["kurtosis"]})],
                       lambda env, p: {"value": p["sigma"], "unit": "ms", "meaning": "RMS timestamp error"}),
    doc="reported t = true t + e, e of RMS sigma (generalised normal with the given kurtosis)")

SAMPLE_DROPS = Effect(
    name="sample_drops", family="timing", stage="clock",
    params=(Param("fraction", "1", 0.001, 0.1, 0.02, "fraction of samples lost"),
            Param("run", "samples", 1.0, 10.0, 1.5, "mean length of a run of lost samples")),
    needs=(), forward=_drops_forward, testable=_needs_clock,
    form=EstimatedForm("clock", _drops_estimate,
                       lambda env, p: [(SAMPLE_DROPS, {"fraction": p["fraction"], "run": p["run"]})],
                       lambda env, p: {"value": p["fraction"], "unit": "fraction", "run": p["run"]}),
    doc="samples lost in short runs")

EFFECTS = (LATENCY, TIMESTAMP_JITTER, SAMPLE_DROPS)
