"""Attitude-aided robust calibration: the vector model against a known Earth field, by MKC-EM.

Model (sensor frame = body frame up to the fitted misalignment; units: m in the sensor's unit, h in uT)
    m_k = A h_k + b + K c_k(tau) + e_k,     h_k = R(q_k)^T h_E,     c_k(tau) = c(t_k - tau)
R(q_k) the attitude (body -> NED) from the log, h_E the Earth field in NED (WMM2025, or a unit field
with an estimated inclination), A = S_phys^-1 a general 3x3 matrix (soft iron, sensor gain, e.g.
counts per uT, and a constant rotation between the magnetometer and the attitude frame: a mounting
misalignment, or a constant heading offset of the attitude, which in level flight is the same thing),
b the hard iron, K (3 x n_c) the interference per unit of the power signals c (current in A,
throttle 0..1), tau their delay: the magnetometer sees the signal tau seconds late; a negative tau
means the logged signal is the late one (a filtered or late-logged current sensor: dronekit's log171
reads its current about 0.2 s after the compasses see it).

The attitude's wandering yaw error enters as a nuisance term dpsi(t_k) g_k, g_k = A R_k^T (e_z x h_E),
dpsi a piecewise-linear function of time with a Gaussian prior (yaw_error.py has its derivation);
its coefficients beta join q in every M-step below (g_k taken at the previous A).

Per sample and output axis i the model is linear in theta_i = (A_i0, A_i1, A_i2, b_i, K_i.) with
the regressor x_k = (h_k, 1, c_k(tau)): three residual channels
    e_ki = m_ki - x_k^T theta_i,   i = 0, 1, 2,
each with its own kernel (sigma_i, d_i), which is the paper's multi-kernel setting (eq. (13)):
    J(theta) = sum_i sigma_i^2 sum_k [1 - exp(-e_ki^2 / (2 d_i^2 sigma_i^2))].
Held parameters (below) enter as linear constraints theta = T q (T fixed, q free), so the
Jacobian of e in q is -blockdiag(X, X, X) T for every tau and h_E: Gauss-Newton is exact in one
step and the reweighted Gauss-Newton of calib/geometric.py becomes Algorithm 1's fixed point:
M-step (weights frozen, c_ki = w_ki / d_i^2, w_ki = exp(-e_ki^2 / (2 d_i^2 sigma_i^2)))
    q <- (T^T blockdiag(X^T C_i X) T)^-1 T^T [X^T C_i m_i]_i                (eq. (16), stacked)
repeated until q moves less than tol (J falls at every step: half-quadratic majorisation); with
the yaw-error term the normal matrix is bordered by the beta block (_normal) and the yaw prior.
E-step (Algorithm 2): (sigma_i, d_i) per channel by maximum likelihood of the truncated
MKC-induced pdf of e_.i, with calib.geometric's E-step helper (the package's kernel). Start: least
squares trimmed to the better half of the samples by a few LTS concentration steps (_trimmed_start),
d_i = 1.4826 MAD of its residuals, sigma_i = START_SIGMA_ROBUST; one M-step, then E/M rounds until
theta moves less than em_tol (relative) and (sigma, d) by < 0.1%.
robust=False gives plain (unweighted) least squares on the same model.

The attitude's roll/pitch error (tilt_sd_deg: given, or "auto", estimated from the first fit's residuals
by tilt_error.py from the robust fit's residuals and kernel weights, and the EM rerun corrected; least
squares has no weights to keep the disturbances out of that estimate and is not corrected by "auto"):
the regressor h_k is computed from the logged
attitude, so it carries the error u_k = delta_k x h_k (delta_k the tilt error about the body's x and y,
each of sd s rad), and least squares on an error-laden regressor shrinks the slopes (errors in
variables): A_22, whose only information is the small tilt-driven variation of h_z, is pulled towards 0
and b_z moves along the ridge b_z + A_22 mean(h_z). Corrected least squares removes the error's
expected contribution from each channel's normal matrix:
    X^T C_i X  ->  X^T C_i X - sum_k C_ki Sigma_k  (h block),
    Sigma_k = s^2 [[h_z^2, 0, -h_x h_z], [0, h_z^2, -h_y h_z], [-h_x h_z, -h_y h_z, h_x^2 + h_y^2]]
(E[u u^T] for independent errors about x and y). It removes the expected shrinkage only; it needs the
roll/pitch error's sd s, stated or estimated (an estimated correction that would remove more than
MAX_TILT_CORRECTION of the normal matrix's information in some direction, or whose refit loses its
minimum, is not applied: the plain fit is kept and the estimate reported). Under the kernel weights it assumes the weights independent of u;
they are not quite (a sample with a large u gets a smaller weight), so it over-corrects a little (measured
in tests/test_flight_tilt_error.py with a white 2 deg error: b_z off by 2.76 uT without, -0.58 with).

Scalars profiled by a 1-D search (each point an M-step at the current (sigma, d), the objective J
compared): tau on a grid of delay.DELAY_COARSE over [-max_delay, max_delay], then of delay.DELAY_STEP
around the coarse grid's best point, refined by a parabola through the best point and its
neighbours (delay.search_delay; its interval: delay.delay_standard_error); the inclination (when
h_E is not given) on a grid of 1 deg refined the same way; the EM then runs at the optimum.

Observability: the weighted normal matrix is blockdiag(X^T C_i X); the information a column j of
X carries independently of the others is measured by its variance inflation factor
    VIF_j = [(X^T C X)^-1]_jj [X^T C X]_jj   (on the column-equilibrated matrix; 1 = orthogonal).
In level flight h_z (the vertical field in the body frame) is nearly constant, so its column is
collinear with the constant (b): VIF_hz is large and A_.2 (the response to the vertical field, the
"vertical soft iron") is not determined by the data. Where VIF_j > max_vif the parameters of
column j are held at a prior instead of being fitted: for h_z, A_02 = A_20, A_12 = A_21 (the
soft iron symmetric, no tilt misalignment) and A_22 = (A_00 + A_11) / 2 (isotropic vertical gain);
for a power signal, K_.j = 0 (it does not vary independently of the rest: constant, or collinear
with another signal). The hard iron b then carries (A_22 - A_22,prior) mean(h_z) along z: the held
terms are reported, with that caveat. Between MAX_VIF_TILT and MAX_VIF only A_02 and A_12 are held
(the tilt terms; see the constant). Yaw-only mode holds all three h_z terms whatever the VIF.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np

from .._validation import MKCInputError
from .delay import delayed, profile_search, search_delay

#: A regressor column whose variance inflation exceeds this is held at its prior (module doc).
#: Measured on simulated flights (tools/study_flight.py): truly level flight with yaw gives VIF_hz
#: > 1e4; banked turns of ~10 deg RMS roll, 5 deg pitch give 200-400; hand rotation gives < 5.
MAX_VIF = 1000.0
#: Above this VIF of h_z (and up to MAX_VIF) only the x and y responses to the vertical field are held
#: (A02 = A20, A12 = A21: symmetric soft iron, no tilt misalignment) and A22 is fitted. Measured on the
#: simulated level flights of tools/study_flight.py (VIF_hz 200-300): fitting A02 and A12 let them trade
#: with b_x, b_y (hard-iron errors up to 1.4 uT), holding them removed that (0.04 uT); holding A22 too
#: moved b_z by its prior's error times the vertical field (2.1 uT for a 4.6% vertical gain).
#: Level flight cannot tell a tilt misalignment from b_x, b_y: the held form gives the same field in
#: level flight, so the heading is unaffected.
MAX_VIF_TILT = 30.0
#: The estimated tilt correction (tilt_sd_deg="auto") is applied only while it removes at most this fraction
#: of the normal matrix's information along any direction (correction_fraction). Measured: 0.14% on a
#: simulated flight with 0.3 deg of tilt error (1.6% expected at 1 deg, the fraction grows as its square),
#: 0.5-1.3% on the three compasses of the real log171; with the current effect left out of the model
#: (power=()), the estimate reads the unmodelled current as tilt error (1.4-2.8 deg) and would remove
#: 3% (simulated) and 11-17% (log171), where the corrected fit became singular.
MAX_TILT_CORRECTION = 0.05
#: M-step iterations per point of a profile search (the point's objective needs no full convergence:
#: the search starts each point from the fit at the current delay).
PROFILE_ITER = 10
#: The EM's trimmed start (_trimmed_start): concentration steps and the fraction of samples kept.
START_CSTEPS = 4
START_KEEP = 0.5
#: Blocks of this duration (s) form the cluster-robust covariance of the parameters (residuals of
#: a flight are correlated over seconds: attitude error, gusts); see parameter_covariance.
COVARIANCE_BLOCK_S = 10.0


def rotation_matrices(q) -> np.ndarray:
    """(N, 3, 3) body -> NED rotation matrices of unit quaternions q (N, 4) = (w, x, y, z)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    R = np.empty((q.shape[0], 3, 3))
    R[:, 0, 0] = 1 - 2 * (y * y + z * z)
    R[:, 0, 1] = 2 * (x * y - w * z)
    R[:, 0, 2] = 2 * (x * z + w * y)
    R[:, 1, 0] = 2 * (x * y + w * z)
    R[:, 1, 1] = 1 - 2 * (x * x + z * z)
    R[:, 1, 2] = 2 * (y * z - w * x)
    R[:, 2, 0] = 2 * (x * z - w * y)
    R[:, 2, 1] = 2 * (y * z + w * x)
    R[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def body_field(R, h_ned) -> np.ndarray:
    """h_k = R_k^T h_ned, (N, 3)."""
    return np.einsum("kji,j->ki", R, np.asarray(h_ned, dtype=np.float64))


def _vif(X, c=None) -> np.ndarray:
    """Variance inflation factor of each column of X under weights c (module doc)."""
    Xw = X if c is None else X * c[:, None]
    N = Xw.T @ X
    dg = np.sqrt(np.diag(N))
    if not np.all(dg > 0):
        return np.where(dg > 0, 1.0, math.inf)
    Ns = N / np.outer(dg, dg)
    try:
        return np.diag(np.linalg.inv(Ns)) * 1.0
    except np.linalg.LinAlgError:
        return np.full(X.shape[1], math.inf)


def constraint_matrix(n_c, hold_vertical, hold_power) -> tuple[np.ndarray, list[str]]:
    """T (3 n_x, n_q) with theta = T q (module doc), and the names of the held parameters.

    hold_vertical: None, "tilt" (A02 = A20, A12 = A21) or "all" (also A22 = (A00 + A11) / 2). theta stacks theta_0, theta_1, theta_2, each (A_i0, A_i1, A_i2, b_i, K_i0 ...), n_x = 4 + n_c.
    hold_power: a bool per power signal."""
    nx = 4 + n_c
    P = 3 * nx
    idx = lambda i, j: i * nx + j          # noqa: E731  (theta index of row i, column j)
    rows = {}                               # held theta index -> {free theta index: coefficient}
    held = []
    if hold_vertical:
        rows[idx(0, 2)] = {idx(2, 0): 1.0}
        rows[idx(1, 2)] = {idx(2, 1): 1.0}
        held += ["A02=A20", "A12=A21"]
    if hold_vertical == "all":
        rows[idx(2, 2)] = {idx(0, 0): 0.5, idx(1, 1): 0.5}
        held += ["A22=(A00+A11)/2"]
    for j, h in enumerate(hold_power):
        if h:
            for i in range(3):
                rows[idx(i, 4 + j)] = {}
            held.append(f"K_.{j}=0")
    free = [k for k in range(P) if k not in rows]
    T = np.zeros((P, len(free)))
    col = {k: n for n, k in enumerate(free)}
    for k in free:
        T[k, col[k]] = 1.0
    for k, combo in rows.items():
        for src, a in combo.items():
            T[k, col[src]] = a
    return T, held


class _Problem:
    """The design of one fit: X (N, n_x), Y (N, 3), T, and the yaw-error nuisance (yaw_error.py):
    basis (None: none), R (N, 3, 3) and h_E, from which its regressor is formed with A."""

    def __init__(self, X, Y, T, R=None, h=None, basis=None, tilt_var=None):
        self.X, self.Y, self.T, self.R, self.h, self.basis = X, Y, T, R, h, basis
        self.tilt_var = tilt_var            # rad^2: the roll/pitch error's variance, None: not corrected

    def yaw_g(self, theta):
        from .yaw_error import yaw_regressor

        return yaw_regressor(self.R, self.h, theta.reshape(3, -1)[:, :3])


def tilt_error_covariance(h, tilt_var) -> np.ndarray:
    """Sigma_k (N, 3, 3) of the module doc: E[u u^T], u = delta x h, delta = (dx, dy, 0), var(dx) = var(dy) = tilt_var."""
    S = np.zeros((h.shape[0], 3, 3))
    S[:, 0, 0] = S[:, 1, 1] = h[:, 2] ** 2
    S[:, 0, 2] = S[:, 2, 0] = -h[:, 0] * h[:, 2]
    S[:, 1, 2] = S[:, 2, 1] = -h[:, 1] * h[:, 2]
    S[:, 2, 2] = h[:, 0] ** 2 + h[:, 1] ** 2
    return tilt_var * S


def _residuals(P, z):
    """E = Y - X theta_i - dpsi(t) g for z = (theta, beta)."""
    theta, beta = z
    E = P.Y - P.X @ theta.reshape(3, -1).T
    if P.basis is not None:
        E -= P.basis.eval(beta)[:, None] * P.yaw_g(theta)
    return E


def _normal(P, C, g):
    """(Nz, rz) of the weighted least squares in (q, beta) at weights C (N, 3) and yaw regressor g."""
    X, Y, T = P.X, P.Y, P.T
    nx = X.shape[1]
    Nb = np.zeros((3 * nx, 3 * nx))
    rb = np.zeros(3 * nx)
    for i in range(3):
        Xw = X * C[:, i:i + 1]
        Nb[i * nx:(i + 1) * nx, i * nx:(i + 1) * nx] = Xw.T @ X
        rb[i * nx:(i + 1) * nx] = Xw.T @ Y[:, i]
    if P.tilt_var:               # corrected least squares (module doc)
        Sig = tilt_error_covariance(X[:, :3], P.tilt_var)
        for i in range(3):
            Nb[i * nx:i * nx + 3, i * nx:i * nx + 3] -= np.einsum("k,kab->ab", C[:, i], Sig)
    Nq = T.T @ Nb @ T
    rq = T.T @ rb
    if P.basis is None:
        return Nq, rq
    B = P.basis
    Xb = np.concatenate([B.cross(X, C[:, i] * g[:, i]) for i in range(3)], axis=0)     # (3 n_x, n_knots)
    Nqb = T.T @ Xb
    Nbb = B.gram(np.sum(C * g * g, axis=1)) + B.prior_precision * (np.eye(B.n) + B.MEAN_WEIGHT * np.ones((B.n, B.n)))
    rbeta = B.project(np.sum(C * g * Y, axis=1))
    return np.block([[Nq, Nqb], [Nqb.T, Nbb]]), np.concatenate([rq, rbeta])


def correction_fraction(N_plain, N_corrected) -> float:
    """The largest fraction of the normal matrix's information along any direction that the tilt correction
    removes: max eig of N_plain^-1 (N_plain - N_corrected) (inf when N_plain is not positive definite). At 1
    the corrected matrix is singular; near it corrected least squares divides by almost nothing."""
    dg = np.sqrt(np.abs(np.diag(N_plain)))
    if not np.all(dg > 0):
        return math.inf
    try:
        L = np.linalg.cholesky(N_plain / np.outer(dg, dg))
    except np.linalg.LinAlgError:
        return math.inf
    D = (N_plain - N_corrected) / np.outer(dg, dg)
    Li = np.linalg.inv(L)
    return float(np.max(np.linalg.eigvalsh(Li @ D @ Li.T)))


def _solve_normal(Nz, rz):
    dg = np.sqrt(np.diag(Nz))
    if not np.all(dg > 0):
        raise MKCInputError("the vector model is singular on these samples (a regressor never varies)")
    return np.linalg.solve(Nz / np.outer(dg, dg), rz / dg) / dg


def _mstep_solve(P, C, z):
    """z = (theta, beta) minimising sum_i sum_k C_ki e_ki^2 (+ the yaw prior), theta = T q, with the yaw
    regressor taken at z's A."""
    g = P.yaw_g(z[0]) if P.basis is not None else None
    sol = _solve_normal(*_normal(P, C, g))
    nq = P.T.shape[1]
    return P.T @ sol[:nq], sol[nq:]


def _objective(E, sigma, d):
    """J of the module doc times d^2 per channel (geometric.correntropy_objective per channel)."""
    from ..calib.geometric import correntropy_objective

    return sum(correntropy_objective(E[:, i], sigma[i], d[i]) for i in range(3))


def _weights(E, sigma, d):
    from ..calib.geometric import kernel_weights

    return np.stack([kernel_weights(E[:, i], sigma[i], d[i]) for i in range(3)], axis=1)


def _flat(z):
    return np.concatenate([z[0], z[1]])


def _mstep(P, z, sigma, d, max_iter, tol):
    """Algorithm 1 at fixed (sigma, d) from z = (theta, beta): (z, iterations, converged). Least squares
    (sigma infinite) iterates only for the yaw regressor's dependence on A."""
    robust = math.isfinite(sigma[0])
    if not robust and P.basis is None:
        return _mstep_solve(P, np.ones_like(P.Y), z), 1, True
    for it in range(1, max_iter + 1):
        if robust:
            C = _weights(_residuals(P, z), sigma, d) / (np.asarray(d) ** 2)[None, :]
        else:
            C = np.ones_like(P.Y)
        new = _mstep_solve(P, C, z)
        step = np.max(np.abs(_flat(new) - _flat(z)))
        z = new
        if step <= tol * (1.0 + np.max(np.abs(z[0]))):
            return z, it, True
    return z, max_iter, False


@dataclass
class VectorFitSettings:
    robust: bool = True
    max_em_iter: int = 10
    em_tol: float = 1e-6
    max_iter: int = 50
    tol: float = 1e-9
    max_vif: float = MAX_VIF
    max_vif_tilt: float = MAX_VIF_TILT
    yaw_only: bool = False
    max_delay: float = 0.5          # s; the search covers [-max_delay, max_delay]; None or 0: none
    delay: float | None = None      # s; a fixed delay instead of the search
    yaw_knot_s: float | None = 10.0  # s; knot spacing of the yaw-error nuisance (None: no yaw error modelled)
    yaw_prior_deg: float = 5.0       # prior sd of the yaw error, deg
    tilt_sd_deg: float | str | None = None  # the attitude's roll/pitch error sd, deg; "auto": estimated
    # from the fit's residuals (tilt_error.py); None: not corrected


@dataclass
class VectorFit:
    """The fitted vector model (module doc): A (3, 3), b (3,), K (3, n_c), tau (s) and diagnostics."""

    A: np.ndarray
    b: np.ndarray
    K: np.ndarray
    delay_s: float | None
    h_ned: np.ndarray
    sigma: np.ndarray
    d: np.ndarray
    weights: np.ndarray                   # (N, 3) final kernel weights (1: least squares)
    residuals: np.ndarray                 # (N, 3) in the sensor's unit
    vif: dict                             # regressor name -> VIF (unit weights, at the final tau)
    held: list                            # names of the parameters held at their prior
    observable: dict                      # regressor name -> bool
    cov: np.ndarray | None = None         # (3 n_x, 3 n_x) cluster-robust covariance of theta
    yaw_error_deg: np.ndarray | None = None   # (N,) the fitted yaw error of the attitude, deg
    n_em: int = 0
    converged: bool = True
    delay_profile: list = field(default_factory=list)       # [(tau, J)]
    inclination_profile: list = field(default_factory=list)  # [(deg, J)]
    power_names: tuple = ()
    tilt_sd_deg: float | None = None      # the roll/pitch error sd corrected for, deg (None: no correction)
    tilt_sd_estimated: float | None = None  # the estimate from the residuals (tilt_sd_deg="auto"), deg

    def theta_sd(self, i, j):
        if self.cov is None:
            return math.nan
        nx = 4 + self.K.shape[1]
        return float(math.sqrt(max(self.cov[i * nx + j, i * nx + j], 0.0)))


def _fit_at(P, s: VectorFitSettings, z=None, sigma=None, d=None):
    """The EM of the module doc on a fixed design: (z, sigma, d, rounds, converged)."""
    from ..batch import DEFAULT_A_FACTOR, DEFAULT_D_BOUNDS, DEFAULT_SIGMA_BOUNDS, START_SIGMA_ROBUST, robust_scale
    from ..calib.geometric import _estep

    nb = 0 if P.basis is None else P.basis.n
    if z is None:
        z = _mstep_solve(P, np.ones_like(P.Y), (np.zeros(P.T.shape[0]), np.zeros(nb)))
    if not s.robust:
        z, _, ok = _mstep(P, z, np.full(3, math.inf), np.ones(3), s.max_iter, s.tol)
        return z, np.full(3, math.inf), np.ones(3), 0, ok
    if sigma is None:
        z = _trimmed_start(P, z, robust_scale)
    if sigma is None:
        sigma = np.full(3, float(START_SIGMA_ROBUST))
        d = np.asarray(robust_scale(_residuals(P, z)), dtype=np.float64).copy()
    z, _, ok = _mstep(P, z, sigma, d, s.max_iter, s.tol)
    H = [np.zeros(3) for _ in range(3)]
    converged = False
    rounds = 0
    for rounds in range(1, s.max_em_iter + 1):
        E = _residuals(P, z)
        moved = 0.0
        for i in range(3):
            s_new, d_new, _, good = _estep(E[:, i], sigma[i], d[i], H[i], DEFAULT_A_FACTOR, DEFAULT_SIGMA_BOUNDS,
                                           DEFAULT_D_BOUNDS, 100, 1e-9, 0.0)
            if good:
                moved = max(moved, abs(math.log(s_new / sigma[i])), abs(math.log(d_new / d[i])))
                sigma[i], d[i] = s_new, d_new
        prev = _flat(z)
        z, _, ok = _mstep(P, z, sigma, d, s.max_iter, s.tol)
        if np.linalg.norm(_flat(z) - prev) <= s.em_tol * max(np.linalg.norm(prev), 1e-300) and moved <= 1e-3:
            converged = ok
            break
    return z, sigma, d, rounds, converged


def _trimmed_start(P, z, robust_scale):
    """A high-breakdown start for the EM (as geometric.py starts from the algebraic MKC-EM fit): least
    squares refitted START_CSTEPS times on the START_KEEP fraction of samples with the smallest
    scaled residual sum_i (e_ki / s_i)^2, s_i = 1.4826 MAD (LTS concentration steps). The plain
    least-squares start is pulled by the disturbances (measured: 16 uT off with 25% in bursts), and
    the EM from it can stop in the disturbed basin."""
    for _ in range(START_CSTEPS):
        E = _residuals(P, z)
        sc = np.sum((E / np.asarray(robust_scale(E))[None, :]) ** 2, axis=1)
        keep = sc <= np.quantile(sc, START_KEEP)
        z = _mstep_solve(P, np.repeat(keep[:, None].astype(np.float64), 3, axis=1), z)
    return z


def parameter_covariance(P, z, C, t, block_s=COVARIANCE_BLOCK_S):
    """Cluster-robust (sandwich) covariance of theta: Nz^-1 M Nz^-1 with Nz the weighted normal matrix in
    (q, beta) (_normal) and M the sum over time blocks of block_s seconds of the outer products of the
    blocks' score sums (the per-sample gradients of the weighted squares). It allows residuals
    correlated within a block, where the independent-sample formula would be far too narrow."""
    E = _residuals(P, z)
    g = P.yaw_g(z[0]) if P.basis is not None else None
    Nz, _ = _normal(P, C, g)
    blk = np.floor((t - t[0]) / block_s).astype(np.int64)
    nblk = int(blk.max()) + 1
    sq = np.concatenate([P.X * (C[:, i] * E[:, i])[:, None] for i in range(3)], axis=1) @ P.T
    S = np.zeros((nblk, Nz.shape[0]))
    for col in range(sq.shape[1]):
        S[:, col] = np.bincount(blk, sq[:, col], nblk)
    if P.basis is not None:
        v = np.sum(C * g * E, axis=1)
        j, rows = P.basis.scores(v)
        nq = sq.shape[1]
        for off in (0, 1):
            np.add.at(S, (blk, nq + j + off), rows[:, off])
    try:
        Ni = np.linalg.inv(Nz)
    except np.linalg.LinAlgError:
        return None
    nq = P.T.shape[1]
    cq = (Ni @ (S.T @ S) @ Ni)[:nq, :nq]
    return P.T @ cq @ P.T.T


def fit_vector(t, mag, q, h_ned=None, power=None, power_names=(), settings: VectorFitSettings | None = None):
    """Fit the vector model of the module doc.

    t (N,) s; mag (N, 3) in the sensor's unit; q (N, 4) body -> NED unit quaternions (w, x, y, z);
    h_ned (3,) the Earth field in NED, uT (None: a unit field with the inclination estimated,
    declination 0, which the misalignment absorbs); power (N, n_c) current (A) / throttle signals.
    Returns a VectorFit. Rows with a non-finite value are the caller's to remove (fit_flight does)."""
    from .yaw_error import YawBasis

    s = settings or VectorFitSettings()
    t = np.asarray(t, dtype=np.float64)
    Y = np.asarray(mag, dtype=np.float64)
    R = rotation_matrices(q)
    c0 = np.zeros((t.shape[0], 0)) if power is None else np.asarray(power, dtype=np.float64).reshape(t.shape[0], -1)
    n_c = c0.shape[1]
    if Y.shape != (t.shape[0], 3) or R.shape[0] != t.shape[0]:
        raise MKCInputError("t, mag and q must have the same number of rows")
    if t.shape[0] < 50 + 10 * n_c:
        raise MKCInputError(f"{t.shape[0]} samples are too few for the vector model")
    names = ["h_x", "h_y", "h_z", "1"] + [f"power:{n}" for n in (power_names or [f"c{j}" for j in range(n_c)])]
    basis = YawBasis(t, s.yaw_knot_s, s.yaw_prior_deg) if s.yaw_knot_s else None
    auto_tilt = isinstance(s.tilt_sd_deg, str) and s.tilt_sd_deg == "auto"
    if not (s.tilt_sd_deg is None or auto_tilt or (isinstance(s.tilt_sd_deg, (int, float))
                                                   and math.isfinite(s.tilt_sd_deg) and s.tilt_sd_deg >= 0)):
        raise MKCInputError(f"tilt_sd_deg must be >= 0 (deg), 'auto' or None; got {s.tilt_sd_deg!r}")
    tilt_var = math.radians(s.tilt_sd_deg) ** 2 if (s.tilt_sd_deg and not auto_tilt) else None

    def design(h, tau):
        return np.concatenate([body_field(R, h), np.ones((t.shape[0], 1)), delayed(t, c0, tau)], axis=1)

    # observability from the design at unit weights (the profile scalars do not change it much)
    h_try = np.asarray(h_ned, dtype=np.float64) if h_ned is not None else np.array([0.5, 0.0, 0.866])
    vif = _vif(design(h_try, 0.0 if s.delay is None else s.delay))
    for j, n in enumerate(names[:2]):
        if not vif[j] <= s.max_vif:
            raise MKCInputError(f"the flight does not turn enough for the horizontal field ({n}: variance inflation "
                                f"{vif[j]:.3g} > {s.max_vif:g}): yaw through a good part of a circle")
    hold_v = "all" if (s.yaw_only or not vif[2] <= s.max_vif) else ("tilt" if not vif[2] <= s.max_vif_tilt else None)
    hold_p = [not vif[4 + j] <= s.max_vif for j in range(n_c)]
    # two collinear power signals: keep the first (current before throttle) when it is observable alone
    if n_c > 1 and all(hold_p):
        v1 = _vif(design(h_try, 0.0)[:, :5])
        if v1[4] <= s.max_vif:
            hold_p[0] = False
    T, held = constraint_matrix(n_c, hold_v, hold_p)
    held = [h.replace("K_.", "K_") for h in held]
    for j, n in enumerate(power_names or []):
        held = [h.replace(f"K_{j}=0", f"K[{n}]=0") for h in held]

    def problem(h, tau):
        return _Problem(design(h, tau), Y, T, R, h, basis, tilt_var)

    incl_profile = []
    if h_ned is None:
        def J_incl(deg):
            Pi = problem(np.array([math.cos(math.radians(deg)), 0.0, math.sin(math.radians(deg))]), 0.0)
            zi, sg, dd, _, _ = _fit_at(Pi, VectorFitSettings(robust=s.robust, max_em_iter=2, yaw_knot_s=s.yaw_knot_s))
            E = _residuals(Pi, zi)
            return _objective(E, sg, dd) if s.robust else float(np.sum(E * E))
        coarse, _ = profile_search(np.arange(-85.0, 86.0, 5.0), J_incl)
        inc, incl_profile = profile_search(np.arange(coarse - 5.0, coarse + 5.01, 1.0), J_incl)
        h = np.array([math.cos(math.radians(inc)), 0.0, math.sin(math.radians(inc))])
    else:
        h = np.asarray(h_ned, dtype=np.float64)

    tau = float(s.delay or 0.0)
    P = problem(h, tau)
    z, sigma, d, rounds, converged = _fit_at(P, s)
    delay_profile = []
    if n_c and not all(hold_p) and s.delay is None and s.max_delay:
        def J_tau(tv):
            Pt = problem(h, tv)
            zt, _, _ = _mstep(Pt, z, sigma, d, PROFILE_ITER, s.tol)
            E = _residuals(Pt, zt)
            return _objective(E, sigma, d) if s.robust else 0.5 * float(np.sum(E * E))
        tau, delay_profile = search_delay(s.max_delay, J_tau)
        P = problem(h, tau)
        z, sigma, d, r2, converged = _fit_at(P, s, z, sigma.copy(), d.copy())
        rounds += r2
    tilt_est = None
    if auto_tilt and s.robust:  # estimate the tilt error from this fit, then refit corrected (tilt_error.py)
        from .tilt_error import estimate_tilt_sd_deg

        E = _residuals(P, z)
        W = _weights(E, sigma, d)
        tilt_est = estimate_tilt_sd_deg(R, h, z[0].reshape(3, -1)[:, :3], E, W)
        P_c = problem(h, tau)
        P_c.tilt_var = math.radians(tilt_est) ** 2
        C = W / (d ** 2)[None, :]
        g = P.yaw_g(z[0]) if basis is not None else None
        if tilt_est > 0 and correction_fraction(_normal(P, C, g)[0], _normal(P_c, C, g)[0]) <= MAX_TILT_CORRECTION:
            try:
                z_c, sigma_c, d_c, r3, conv_c = _fit_at(P_c, s, z, sigma.copy(), d.copy())
            except MKCInputError:      # the weights moved and the corrected matrix lost its minimum: keep the plain fit
                pass
            else:
                P, tilt_var, z, sigma, d, converged = P_c, P_c.tilt_var, z_c, sigma_c, d_c, conv_c
                rounds += r3
    if not converged:
        warnings.warn("vector fit: stopped at an iteration cap; the last iterate is returned", UserWarning,
                      stacklevel=2)
    E = _residuals(P, z)
    W = _weights(E, sigma, d) if s.robust else np.ones_like(E)
    C = W / (d ** 2)[None, :] if s.robust else W
    cov = parameter_covariance(P, z, C, t)
    X = P.X
    # the VIF of each column among the columns still fitted (a held column no longer confounds the rest)
    fitted = [j for j in range(X.shape[1]) if not ((j == 2 and hold_v == "all") or (j >= 4 and hold_p[j - 4]))]
    vif_final = _vif(X)
    vif_final[fitted] = _vif(X[:, fitted])
    th = z[0].reshape(3, -1)
    observable = {n: bool(v <= s.max_vif) for n, v in zip(names, vif_final)}
    if hold_v == "all":
        observable["h_z"] = False
    return VectorFit(A=th[:, :3].copy(), b=th[:, 3].copy(), K=th[:, 4:].copy(),
                     delay_s=(tau if n_c and not all(hold_p) else None), h_ned=h, sigma=sigma, d=d, weights=W,
                     residuals=E, vif=dict(zip(names, map(float, vif_final))), held=held, observable=observable,
                     cov=cov, yaw_error_deg=None if basis is None else np.degrees(basis.eval(z[1])), n_em=rounds,
                     converged=converged, delay_profile=delay_profile, inclination_profile=incl_profile,
                     power_names=tuple(power_names or ()),
                     tilt_sd_deg=None if not tilt_var else (tilt_est if auto_tilt else float(s.tilt_sd_deg)),
                     tilt_sd_estimated=tilt_est)
