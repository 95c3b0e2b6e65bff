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
"""
from __future__ import annotations

import numpy as np

from .base import Effect, Param, SimContext


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


LATENCY = Effect(
    name="latency", family="timing", stage="field", kind="mean",
    params=(Param("delay", "ms", 1.0, 100.0, 20.0),
            Param("spread", "ms", 0.0, 60.0, 0.0, "RMS width of the output filter around the delay (0: pure delay)")),
    needs=("acc",), forward=_latency_forward, testable=_needs_acc_and_motion,
    doc="magnetometer samples the field delay ms earlier than stamped, averaged over +-spread ms")

TIMESTAMP_JITTER = Effect(
    name="timestamp_jitter", family="timing", stage="clock", kind="clock",
    params=(Param("sigma", "ms", 0.05, 5.0, 1.0, "RMS timestamp error"),
            Param("kurtosis", "1", 0.0, 20.0, 0.0, "excess kurtosis of the error (0 Gaussian, 3 Laplace)")),
    needs=(), forward=_jitter_forward, testable=_needs_clock,
    doc="reported t = true t + e, e of RMS sigma (generalised normal with the given kurtosis)")

SAMPLE_DROPS = Effect(
    name="sample_drops", family="timing", stage="clock", kind="clock",
    params=(Param("fraction", "1", 0.001, 0.1, 0.02, "fraction of samples lost"),
            Param("run", "samples", 1.0, 10.0, 1.5, "mean length of a run of lost samples")),
    needs=(), forward=_drops_forward, testable=_needs_clock,
    doc="samples lost in short runs")

EFFECTS = (LATENCY, TIMESTAMP_JITTER, SAMPLE_DROPS)
