"""Geometric MKC-EM: the correntropy EM on the field-strength residual, by reweighted Gauss-Newton.

The algebraic fit (calib/fit.py, "mkc-em") regresses the quadric's features on 1: its residual
x_k^T theta - 1 is not a distance. To first order it is the geometric error times the gradient of
the quadric's form at the sample, which varies over the ellipsoid with its shape and with where the
normalisation origin lies, so samples count unequally and the kernel weights compare unlike
quantities; a cluster of samples near that origin has almost no gradient at all (a rest phase that
holds half a recording pulls the per-axis median onto itself, and the algebraic fit goes blind to
it). The MKC paper's conclusion names nonlinear regression as the next step; this module takes the
geometric one and refines the algebraic MKC-EM solution on the field-strength residual.

Model and parametrisation
-------------------------
    r_k(p) = |S (m_k - b)| - F,     p = (b, s),  S = [[s0, s3, s4], [s3, s1, s5], [s4, s5, s2]]

r_k is the field-strength error, i.e. the orthogonal distance from the calibrated sample
S (m_k - b) to the sphere of radius F (in the calibrated frame, in the field's units).
S is symmetric with FREE scale and F is FIXED (at the algebraic start's value): these are the 9
numbers of an ellipsoid (3 centre + 6 shape; |S x| = F describes x^T (S^2 / F^2) x = 1, and a
symmetric positive square root is unique), with no constraint to carry. Why not the others:
  * S free and F free: (S, F) -> (c S, c F) scales every residual by c, so the objective falls
    to 0 as c -> 0; one of the two must be pinned.
  * det S = 1 with F free (the package's output convention): a nonlinear constraint the
    Gauss-Newton step would have to be projected onto. Pinning F instead is the same model
    (only the overall scale of the residual differs: F fixed here, det(S)^(-1/3) F there, apart
    by the relative change of F during the refinement, < 0.2% measured on BROAD and < 0.02% on
    the synthetic sweeps); the result is converted to det S = 1 at the end:
    P = (S^T S)^(1/2), k = det(P)^(1/3), S_out = P / k, F_out = F / k.
  * upper-triangular S (also 6 numbers, any ellipsoid up to a rotation of the output frame):
    as good a chart, but the package reports a symmetric S, and a triangular one would need
    a polar decomposition to be compared with the start.
The fit runs in the algebraic fit's normalised coordinates m' = (m - c0) / s0 (ellipsoid.py), so
b' and S are O(1); b = c0 + s0 b', F_out carries s0.

The correntropy objective (one channel: the residual is a scalar per sample, m = 1)
    J(p) = sigma^2 sum_k [1 - exp(-r_k(p)^2 / (2 d^2 sigma^2))]          (paper eq. (13), times N)
    grad J = (1/d^2) sum_k w_k r_k g_k,  w_k = exp(-r_k^2 / (2 d^2 sigma^2)),  g_k = dr_k/dp
with the Jacobian row (u_k = S x_k / |S x_k|, x_k = m_k - b):
    dr_k/db = -S u_k;   dr_k/dS_ii = u_i x_i;   dr_k/dS_ij = u_i x_j + u_j x_i  (i < j).

M-step (Algorithm 1 for a nonlinear residual). Freeze the weights at p_t and linearise
r_k(p_t + delta) ~ r_k + g_k^T delta: the weighted least-squares step is
    delta = -(sum_k w_k g_k g_k^T)^-1 sum_k w_k g_k r_k                   (reweighted Gauss-Newton)
and delta = 0 exactly where sum_k w_k r_k g_k = 0, i.e. where grad J = 0: the fixed points of the
iteration are the stationary points of the correntropy objective, as eq. (15)/(16) are for the
linear model. Indeed for r_k = y_k - x_k^T theta (g_k = -x_k) the step lands on
theta_t+1 = (sum w x x^T)^-1 sum w x y, which IS eq. (16). Since 1 - exp(-t) is concave in t = r^2,
J is majorised at p_t by (1/2d^2) sum_k w_k r_k^2 + const (half-quadratic), so a step that lowers the
weighted sum of squares lowers J. The Gauss-Newton step is a descent direction of J (its matrix is
positive definite); for a nonlinear r it can overshoot, so each step is accepted only if J falls,
and otherwise damped Levenberg-Marquardt style: (A + lambda diag(A)) delta = -grad, lambda x10
until it does. The iteration stops when max|delta| <= tol (1 + max|p|).

E-step (Algorithm 2), unchanged: (sigma, d) by maximum likelihood of the truncated MKC-induced pdf
of the current residuals r_k, with the package's E-step kernel (kernels.estep.estep_channel: projected
BFGS in (log sigma, log d), the same boxes DEFAULT_SIGMA_BOUNDS / DEFAULT_D_BOUNDS and truncation
a = DEFAULT_A_FACTOR max|r| from kernels.em.truncation_bound) and the same warm-carried curvature, as
batch.MKCRegressor does. Start (as MKCRegressor from a high-breakdown theta0): p from
fit_ellipsoid(raw, "mkc-em"), d = 1.4826 MAD of its geometric residuals (batch.robust_scale), sigma =
START_SIGMA_ROBUST; one M-step, then E/M rounds (Algorithm 3) until the parameters move less than
em_tol (relative) and (sigma, d) less than 0.1% (or max_em_iter rounds).

Direction weighting (directions=True): samples are not equal. A recording that rests for a minute
in one orientation, or passes slowly through some, holds thousands of near-identical samples there;
with equal weights they decide the fit (BROAD's rest phases, 41% of trial 03, read ~0.6 uT low against
the movement phase's ellipsoid and pull the whole fit towards them). So every sample gets a direction
weight v_k: the calibrated directions u_k = S (m_k - b) / |S (m_k - b)| are binned into the 72
equal-area cells of calib.quality.direction_cells, and
    v_k = min(1, c / n_cell(k)),   c = the median sample count over the occupied cells,
so each cell holds total weight min(n_cell, c): lingering cells are capped at c, sparse cells keep
weight 1 per sample (a cell holding three burst samples is not amplified to a full cell's weight).
The M-step minimises sum_k v_k rho(r_k) (weights v_k w_k in the Gauss-Newton step; all samples still
average the noise within their cell). The E-step, whose kernel takes no weights, runs on a thinned
subset with the same per-cell totals (a cell holding more than c samples gives c of them, evenly
spread in time), so it fits the pdf of the direction-balanced residuals. v and the subset are
recomputed from the current calibration before the first M-step and after each of the first
THIN_ROUNDS EM rounds, then frozen so that the EM ends on one fixed objective.

Safeguards: the geometric residual is ill-posed where the samples cover only part of the sphere (the
shape along the unseen axis is nearly free, and the residual falls towards ever larger ellipsoids);
the refinement runs only when the Gauss-Newton matrix at the start is well conditioned
(GEOMETRIC_COND_MAX) and stays near the start (MAX_FIELD_CHANGE, MAX_CENTRE_SHIFT); otherwise the
algebraic fit is returned with a warning. Each constant's comment gives the measurements.

Cost: per Gauss-Newton iteration one residual/Jacobian evaluation and the 9x9 weighted normal
matrix, O(9^2 N) flops, plus one objective evaluation per trial step; per E-step O(N) per BFGS
iteration (tens). Measured: 2-5 EM rounds and 14-45 Gauss-Newton iterations in all (the weights
change with every step, so the iteration converges linearly, as Algorithm 1 does), i.e. some tens
of O(N) passes on top of the algebraic start: measured (tools/study_ellipsoid.py --truth) the refinement
alone takes 0.3-0.7x the time of the "mkc-em" fit it starts from, on 2000 to 58000 samples.
"""
from __future__ import annotations

import math
import warnings

import numpy as np

from .._validation import MKCInputError
from .ellipsoid import (EllipsoidError, EllipsoidFit, EllipsoidGeometry, design_matrix, gross_outlier_mask)
from .quality import direction_cells, quality_figures

#: Direction weights are recomputed after this many EM rounds, then frozen (see module doc).
THIN_ROUNDS = 3
#: Largest Levenberg-Marquardt damping tried before the M-step is declared stuck at float resolution.
LM_MAX_DAMPING = 1e12
#: The geometric problem must be well posed for the refinement to run: the condition number of the
#: Jacobi-equilibrated Gauss-Newton matrix sum_k g_k g_k^T at the start (unit weights) at most
#: GEOMETRIC_COND_MAX. Measured: full-sphere sweeps 2.6-3.1, BROAD 03 / 26 16 / 24, samples on a cap
#: of 240-degree opening (75% of the sphere) 15-16, on a hemisphere 210-310, on a cap of 120-degree
#: opening (25%) 1000-16000. With partial
#: coverage the shape along the unseen axis is nearly free, and the geometric residual falls along a
#: valley towards ever larger, elongated ellipsoids: on a hemisphere with 1 uT noise the geometric fit
#: was 4x worse than the algebraic one (hard iron 2.1 vs 0.55 uT), with 2 uT (or on a 120-degree cap)
#: it ran off to a field 20x too large. The algebraic fit's own bias holds it there, so above the
#: bound mkc-em-geo returns the algebraic fit (with a warning; refined_ = False).
GEOMETRIC_COND_MAX = 100.0
#: Backstop: a refinement that moves the field by more than MAX_FIELD_CHANGE (relative) or the centre
#: by more than MAX_CENTRE_SHIFT fields from the algebraic start has run away (samples that fill a
#: volume: rasteiro's MARG-robot recordings, 10% norm spread around the algebraic fit, went to a field
#: 3-5x larger), and the algebraic fit is returned as above. On calibration recordings (synthetic,
#: BROAD, QMC5883L, cave survey, CK-Explorer) the refinement moved the field by < 4% and the centre by
#: < 0.05 field (the largest with 25% bursts and 1% spikes, where it repairs the algebraic fit).
MAX_FIELD_CHANGE = 0.2
MAX_CENTRE_SHIFT = 0.5


class _NotRefined(Exception):
    """The geometric refinement is not made (ill-posed or run away); the message says why."""


def _check_not_run_away(p, p0, F):
    """Raise _NotRefined when p (normalised, F fixed) left the start p0's neighbourhood (see above)."""
    k = abs(float(np.linalg.det(sym_from_params(p[3:])))) ** (1.0 / 3.0)
    k0 = abs(float(np.linalg.det(sym_from_params(p0[3:])))) ** (1.0 / 3.0)
    ratio = k0 / k if k > 0 else math.inf
    shift = float(np.linalg.norm(p[:3] - p0[:3])) / F
    if not (abs(ratio - 1.0) <= MAX_FIELD_CHANGE and shift <= MAX_CENTRE_SHIFT):
        raise _NotRefined(f"the geometric refinement ran away from the algebraic fit (field x{ratio:.3g}, centre "
                          f"moved {shift:.3g} fields): the samples do not determine an ellipsoid geometrically "
                          "(they fill a volume or cover only part of the sphere, or disturbances dominate)")


def geometric_condition(p, mag, field):
    """cond of the Jacobi-equilibrated Gauss-Newton matrix sum_k g_k g_k^T at p (unit weights)."""
    _, J = geometric_jacobian(p, mag, field)
    A = J.T @ J
    dg = np.sqrt(np.diag(A))
    if not np.all(dg > 0) or not np.all(np.isfinite(A)):
        return math.inf
    return float(np.linalg.cond(A / np.outer(dg, dg)))


def sym_from_params(s):
    """S (3x3 symmetric) from s = (S00, S11, S22, S01, S02, S12)."""
    return np.array([[s[0], s[3], s[4]], [s[3], s[1], s[5]], [s[4], s[5], s[2]]], dtype=np.float64)


def params_from_sym(S):
    S = 0.5 * (np.asarray(S, dtype=np.float64) + np.asarray(S, dtype=np.float64).T)
    return np.array([S[0, 0], S[1, 1], S[2, 2], S[0, 1], S[0, 2], S[1, 2]])


def geometric_residuals(p, mag, field):
    """r_k = |S (m_k - b)| - F for p = (b (3), s (6)); mag (N, 3)."""
    x = mag - p[:3]
    y = x @ sym_from_params(p[3:])          # S symmetric: row k is (S x_k)^T
    return np.sqrt(np.einsum("ij,ij->i", y, y)) - field


def geometric_jacobian(p, mag, field):
    """(r (N,), J (N, 9)): the residuals and their derivatives in p = (b, s) (module doc)."""
    x = mag - p[:3]
    S = sym_from_params(p[3:])
    y = x @ S
    n = np.sqrt(np.einsum("ij,ij->i", y, y))
    u = y / np.maximum(n, 1e-300)[:, None]
    J = np.empty((mag.shape[0], 9))
    J[:, 0:3] = -(u @ S)                     # -(S u)^T, S symmetric
    J[:, 3] = u[:, 0] * x[:, 0]
    J[:, 4] = u[:, 1] * x[:, 1]
    J[:, 5] = u[:, 2] * x[:, 2]
    J[:, 6] = u[:, 0] * x[:, 1] + u[:, 1] * x[:, 0]
    J[:, 7] = u[:, 0] * x[:, 2] + u[:, 2] * x[:, 0]
    J[:, 8] = u[:, 1] * x[:, 2] + u[:, 2] * x[:, 1]
    return n - field, J


def correntropy_objective(r, sigma, d, v=None):
    """sigma^2 d^2 sum_k v_k (1 - exp(-r_k^2 / (2 d^2 sigma^2))) (J of the module doc times d^2, v_k the
    direction weights, 1 if None); sum v_k r_k^2 / 2 when sigma is infinite (least squares)."""
    if not math.isfinite(sigma):
        return 0.5 * float(np.dot(r * r, v) if v is not None else np.dot(r, r))
    s2d2 = sigma * sigma * d * d
    rho = -np.expm1(-(r * r) / (2.0 * s2d2))
    return float(s2d2 * (np.dot(rho, v) if v is not None else np.sum(rho)))


def kernel_weights(r, sigma, d):
    if not math.isfinite(sigma):
        return np.ones_like(r)
    return np.exp(-(r * r) / (2.0 * sigma * sigma * d * d))


def gauss_newton_mstep(p, mag, field, sigma, d, max_iter=50, tol=1e-10, v=None):
    """Minimise the correntropy objective at fixed (sigma, d) from p by reweighted Gauss-Newton
    with Levenberg-Marquardt damping (module doc); v: per-sample direction weights (None: all 1).
    Returns (p, iterations, converged)."""
    p = np.array(p, dtype=np.float64)
    r, J = geometric_jacobian(p, mag, field)
    obj = correntropy_objective(r, sigma, d, v)
    lam = 0.0
    for it in range(1, max_iter + 1):
        w = kernel_weights(r, sigma, d)
        if v is not None:
            w = w * v
        Jw = J * w[:, None]
        A = Jw.T @ J
        g = Jw.T @ r
        dg = np.sqrt(np.diag(A))
        if not np.all(dg > 0) or not np.all(np.isfinite(A)):
            return p, it, False
        As = A / np.outer(dg, dg)
        gs = g / dg
        while True:
            try:
                delta = -np.linalg.solve(As + lam * np.eye(9), gs) / dg
            except np.linalg.LinAlgError:
                delta = None
            if delta is not None and np.all(np.isfinite(delta)):
                p_new = p + delta
                r_new = geometric_residuals(p_new, mag, field)
                obj_new = correntropy_objective(r_new, sigma, d, v)
                if np.isfinite(obj_new) and obj_new <= obj:
                    break
            lam = 1e-6 if lam == 0.0 else 10.0 * lam
            if lam > LM_MAX_DAMPING:             # no decrease at float resolution: at the minimum
                return p, it, True
        small = np.max(np.abs(delta)) <= tol * (1.0 + np.max(np.abs(p)))
        p = p_new
        obj = obj_new
        lam = 0.0 if lam <= 1e-6 else 0.1 * lam
        if small:
            return p, it, True
        r, J = geometric_jacobian(p, mag, field)
    return p, max_iter, False


def direction_weights(m_cal):
    """(v, keep) of direction weighting (module doc) for calibrated samples m_cal (N, 3).

    v_k = min(1, c / n_cell(k)) over the 72 equal-area cells of the calibrated directions, c the median
    count over the occupied cells: a cell holds total weight min(n_cell, c). keep marks a thinned
    subset with the same per-cell totals (c samples evenly spread in time in each cell holding more),
    on which the E-step runs. Samples at the centre (m_cal = 0) get v = 0."""
    N = m_cal.shape[0]
    n = np.linalg.norm(m_cal, axis=1)
    idx = np.flatnonzero(n > 0)
    v = np.zeros(N)
    keep = np.zeros(N, dtype=bool)
    if idx.size == 0:
        return v, keep
    cells = direction_cells(m_cal[idx] / n[idx, None])
    counts = np.bincount(cells, minlength=72)
    c = max(1.0, float(np.median(counts[counts > 0])))
    nc = counts[cells]
    v[idx] = np.minimum(1.0, c / nc)
    order = np.argsort(cells, kind="stable")                # time order within each cell
    sc = cells[order]
    j = np.arange(sc.size) - np.searchsorted(sc, sc, side="left")       # rank in its cell
    ns = counts[sc]
    kept = (ns <= c) | (np.floor(j * c / ns) > np.floor((j - 1) * c / ns))
    keep[idx[order[kept]]] = True
    return v, keep


def _estep(r, sigma, d, H, a_factor, sigma_bounds, d_bounds, max_iter, gtol, pull):
    """Algorithm 2 on one channel with the package's kernels (as kernels.em.mkc_em calls them)."""
    from ..kernels import NOT_CONVERGED, OK
    from ..kernels.em import truncation_bound
    from ..kernels.estep import estep_channel

    R = np.ascontiguousarray(r, dtype=np.float64)[:, None]
    a = truncation_bound(R, 0, -1.0, float(a_factor), np.zeros_like(R))
    e = np.ascontiguousarray(r, dtype=np.float64)
    s_new, d_new, _, _, st = estep_channel(e, e.shape[0], a, float(sigma), float(d), float(sigma_bounds[0]),
                                           float(sigma_bounds[1]), float(d_bounds[0]) * a, float(d_bounds[1]) * a,
                                           int(max_iter), float(gtol), float(pull), H)
    if st == OK or st == NOT_CONVERGED:
        return s_new, d_new, a, True
    return sigma, d, a, False


class GeometricMKCEM:
    """Geometric MKC-EM calibration (module doc); calibrate(mag) returns an EllipsoidFit.

    directions : bool  direction weighting (module doc).
    robust : bool      False: plain geometric least squares (sigma = inf, no E-step) from the same start.
    max_em_iter, em_tol, max_iter, tol : EM rounds cap and relative stop; Gauss-Newton cap and stop.
    a_factor, sigma_bounds, d_bounds, estep_max_iter, estep_gtol, sigma_pull : the E-step's settings,
        defaults those of batch.MKCRegressor.
    start : an EllipsoidFit to start from (default: fit_ellipsoid(mag, "mkc-em")).

    When the geometric problem is ill-posed (GEOMETRIC_COND_MAX) or the refinement runs away
    (MAX_FIELD_CHANGE, MAX_CENTRE_SHIFT), calibrate warns and returns the start fit itself (method
    "mkc-em"); refined_ is then False and fallback_reason_ says why.

    Attributes after calibrate: refined_, fallback_reason_, condition_geometric_ (at the start);
    after a refinement also sigma_, d_ (normalised units), d_field_ (d in the input unit),
    n_iter_ (EM rounds), n_gn_iter_, converged_, direction_weights_ (v, 1 without directions=True),
    kept_ (the samples the E-step used: the thinned subset, or all but the gross outliers),
    start_ (the algebraic fit), history_ (per-round p, sigma, d), em = True.
    """

    em = True

    def __init__(self, directions=False, robust=True, *, max_em_iter=10, em_tol=1e-6, max_iter=50, tol=1e-10,
                 a_factor=None, sigma_bounds=None, d_bounds=None, estep_max_iter=100, estep_gtol=1e-9,
                 sigma_pull=0.0, start=None):
        from ..batch import DEFAULT_A_FACTOR, DEFAULT_D_BOUNDS, DEFAULT_SIGMA_BOUNDS

        self.directions = bool(directions)
        self.robust = bool(robust)
        self.max_em_iter = max_em_iter
        self.em_tol = em_tol
        self.max_iter = max_iter
        self.tol = tol
        self.a_factor = DEFAULT_A_FACTOR if a_factor is None else a_factor
        self.sigma_bounds = DEFAULT_SIGMA_BOUNDS if sigma_bounds is None else sigma_bounds
        self.d_bounds = DEFAULT_D_BOUNDS if d_bounds is None else d_bounds
        self.estep_max_iter = estep_max_iter
        self.estep_gtol = estep_gtol
        self.sigma_pull = sigma_pull
        self.start = start
        for name, lo in (("max_em_iter", 0), ("max_iter", 1), ("estep_max_iter", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise MKCInputError(f"{name} must be an integer >= {lo}; got {v!r}")
        for name in ("em_tol", "tol", "a_factor", "estep_gtol", "sigma_pull"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float, np.integer, np.floating)) and math.isfinite(v) and v >= 0):
                raise MKCInputError(f"{name} must be a finite number >= 0; got {v!r}")

    @property
    def method_name(self):
        if not self.robust:
            return "ls-geo"
        return "mkc-em-geo-dir" if self.directions else "mkc-em-geo"

    def _refine(self, p, mn, F):
        """The EM of the module doc from p (normalised samples mn, field F): returns
        (p, sigma, d, v, keep, rounds, gn_its, converged, history); raises _NotRefined on a run-away."""
        from ..batch import START_SIGMA_ROBUST, robust_scale

        p_start = p.copy()

        def weigh(p):
            if not self.directions:
                return None, np.ones(mn.shape[0], dtype=bool)
            return direction_weights((mn - p[:3]) @ sym_from_params(p[3:]))

        v, keep = weigh(p)
        r = geometric_residuals(p, mn, F)
        if self.robust:
            sigma = float(START_SIGMA_ROBUST)
            d = float(robust_scale(r[keep][:, None])[0])
        else:
            sigma, d = math.inf, 1.0
        p, gn_its, ok = gauss_newton_mstep(p, mn, F, sigma, d, self.max_iter, self.tol, v)
        _check_not_run_away(p, p_start, F)
        hist = [(p.copy(), sigma, d)]
        H = np.zeros(3)
        rounds = 0
        converged = ok and not self.robust
        if self.robust:
            for rounds in range(1, int(self.max_em_iter) + 1):
                r = geometric_residuals(p, mn, F)
                s_new, d_new, _, good = _estep(r[keep], sigma, d, H, self.a_factor, self.sigma_bounds, self.d_bounds,
                                               self.estep_max_iter, self.estep_gtol, self.sigma_pull)
                dpar = max(abs(math.log(s_new / sigma)), abs(math.log(d_new / d))) if good else 0.0
                sigma, d = s_new, d_new
                moved = 0.0
                if self.directions and rounds <= THIN_ROUNDS:
                    v_new, keep = weigh(p)
                    moved = float(np.max(np.abs(v_new - v)))
                    v = v_new
                p_prev = p
                p, its, ok = gauss_newton_mstep(p, mn, F, sigma, d, self.max_iter, self.tol, v)
                _check_not_run_away(p, p_start, F)
                gn_its += its
                hist.append((p.copy(), sigma, d))
                step = np.linalg.norm(p - p_prev) <= self.em_tol * max(np.linalg.norm(p_prev), 1e-300)
                if step and dpar <= 1e-3 and moved == 0.0:
                    converged = ok
                    break
        return p, sigma, d, v, keep, rounds, gn_its, converged, hist

    def calibrate(self, mag) -> EllipsoidFit:
        from .fit import fit_ellipsoid, weighted_condition

        mag = np.asarray(mag, dtype=np.float64)
        start = self.start if self.start is not None else fit_ellipsoid(mag, "mkc-em")   # validates mag
        if mag.ndim != 2 or mag.shape[1] != 3 or start.weights.shape[0] != mag.shape[0]:
            raise MKCInputError(f"mag must have shape (N, 3) and match the start fit; got {mag.shape}")
        gross = gross_outlier_mask(mag)
        use = ~gross
        norm = start.normalisation
        mn = norm.apply(mag[use])
        F = float(start.field) / norm.scale
        p = np.concatenate([(start.hard_iron - norm.offset) / norm.scale, params_from_sym(start.soft_iron)])
        self.refined_ = False
        self.fallback_reason_ = None
        self.condition_geometric_ = geometric_condition(p, mn, F)
        try:
            if not self.condition_geometric_ <= GEOMETRIC_COND_MAX:
                raise _NotRefined(f"the geometric problem is ill-posed here (condition {self.condition_geometric_:.3g} > "
                                  f"{GEOMETRIC_COND_MAX:g}: the samples cover too little of the sphere)")
            p, sigma, d, v, keep, rounds, gn_its, converged, hist = self._refine(p, mn, F)
        except _NotRefined as why:
            self.fallback_reason_ = str(why)
            warnings.warn(f"{self.method_name}: {why}; returning the algebraic mkc-em fit", UserWarning, stacklevel=2)
            self.start_ = start
            return start
        self.refined_ = True
        if not converged:
            warnings.warn(f"{self.method_name}: stopped at an iteration cap ({rounds} EM rounds, {gn_its} "
                          "Gauss-Newton iterations); the last iterate is returned", UserWarning, stacklevel=2)
        # back to raw units and the package's convention: S symmetric positive definite, det S = 1
        Sf = sym_from_params(p[3:])
        lam, Q = np.linalg.eigh(Sf.T @ Sf)
        if not (lam[0] > 0 and np.all(np.isfinite(lam))):
            raise EllipsoidError("the geometric fit's shape matrix is singular")
        sq = np.sqrt(lam)
        P = (Q * sq) @ Q.T
        k = float(np.prod(sq) ** (1.0 / 3.0))
        S = 0.5 * (P + P.T) / k
        field = norm.scale * F / k
        b = norm.offset + norm.scale * p[:3]
        if not (np.all(np.isfinite(b)) and np.all(np.isfinite(S)) and math.isfinite(field) and field > 0):
            raise EllipsoidError("the geometric fit did not give a finite ellipsoid")
        # per-sample weights: the final kernel weight of every sample (0 for the gross ones)
        w = np.zeros(mag.shape[0])
        r_all = geometric_residuals(p, mn, F)
        w[use] = kernel_weights(r_all, sigma, d)
        with np.errstate(over="ignore", invalid="ignore"):
            m_cal = (mag - b) @ S.T
            Xd = design_matrix(mn)
            quality = quality_figures(m_cal, field, weighted_condition(Xd, w[use]))
        quality["gross_outliers"] = int(gross.sum())
        geom = _geometry(b, S, field)
        theta = _theta_normalised(geom, norm)
        self.sigma_ = np.array([sigma])
        self.d_ = np.array([d])
        self.d_field_ = float(d * norm.scale / k)
        self.n_iter_ = int(rounds)
        self.n_gn_iter_ = int(gn_its)
        self.converged_ = bool(converged)
        self.direction_weights_ = np.zeros(mag.shape[0])
        self.direction_weights_[use] = 1.0 if v is None else v
        kept = np.zeros(mag.shape[0], dtype=bool)
        kept[np.flatnonzero(use)[keep]] = True
        self.kept_ = kept
        self.start_ = start
        self.history_ = {"p": np.array([h[0] for h in hist]), "sigma": np.array([h[1] for h in hist]),
                         "d": np.array([h[2] for h in hist])}
        self.coef_ = theta
        self.weights_ = w
        channels = [{"sigma": float(sigma), "d": float(self.d_field_)}] if self.robust else []
        return EllipsoidFit(hard_iron=b, soft_iron=S, field=float(field), weights=w, quality=quality,
                            method=self.method_name, geometry=geom, theta_normalised=theta, normalisation=norm,
                            channels=channels, estimator=self)


def _geometry(b, S, field) -> EllipsoidGeometry:
    """(m - b)^T M (m - b) = 1 with M = S^2 / F^2; semi-axes in ascending eigenvalue order of M."""
    M = (S @ S) / (field * field)
    M = 0.5 * (M + M.T)
    lam, Q = np.linalg.eigh(M)
    if np.linalg.det(Q) < 0:
        Q[:, 0] = -Q[:, 0]
    return EllipsoidGeometry(centre=np.array(b, dtype=np.float64), M=M, semi_axes=1.0 / np.sqrt(lam), rotation=Q)


def _theta_normalised(geom, norm):
    """theta of eq. (36) for this ellipsoid in the normalised coordinates (NaN if the normalised
    origin were outside it, which the median centring excludes in practice)."""
    Mn = geom.M * norm.scale ** 2
    bn = (geom.centre - norm.offset) / norm.scale
    kk = 1.0 - bn @ Mn @ bn
    if not kk > 0:
        return np.full(9, np.nan)
    A = Mn / kk
    B = -2.0 * (Mn @ bn) / kk
    return np.array([A[0, 0], A[1, 1], A[2, 2], 2 * A[0, 1], 2 * A[0, 2], 2 * A[1, 2], B[0], B[1], B[2]])


def fit_geometric(mag, directions=False, **params) -> EllipsoidFit:
    """fit_ellipsoid(mag, "mkc-em-geo") (directions=True: "mkc-em-geo-dir"); params go to GeometricMKCEM."""
    return GeometricMKCEM(directions=directions, **params).calibrate(mag)
