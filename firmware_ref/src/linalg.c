/* linalg.c: small dense solves; kernels/linalg.py spd_solve line by line, plus the 3x3 solve and
 * the symmetric eigen-decomposition the calibration needs (numpy/LAPACK in the Python reference).
 */
#include "mkc_internal.h"

/* mkc_internal.h's float min/max (Numba's semantics: the first argument on ties, NaN wins). */
float mkc__min_f(float a, float b) { return (a != a) ? a : ((b != b || b < a) ? b : a); }
float mkc__max_f(float a, float b) { return (a != a) ? a : ((b != b || b > a) ? b : a); }
int mkc__finite_f(float x) { return isfinite(x); }
void mkc__count(int64_t *counter) { *counter += 1; }

/* Solve A x = b for symmetric positive definite A[:n, :n] (lower triangle and diagonal read).
 * Jacobi equilibration D A D y = D b, x = D y with D = diag(A_ii^-1/2), then Cholesky; the diagonal
 * of L holds the inverse pivots 1/l_jj. *cond = (max l_jj / min l_jj)^2, a cheap lower estimate of
 * cond(DAD). Returns MKC_OK, MKC_SINGULAR (not positive definite) or MKC_NONFINITE. */
int mkc__spd_solve(const mkc_acc A[MKC_N][MKC_N], const mkc_acc *b, mkc_acc *x, mkc_acc L[MKC_N][MKC_N],
                   mkc_acc *D, int n, mkc_acc *cond)
{
    int i, j, k;
    mkc_acc lmax = AC(0.0), lmin = AC(HUGE_VAL), r;
    for (i = 0; i < n; i++) {
        mkc_acc aii = A[i][i];
        if (!(aii > AC(0.0)) || !MKC_ISFINITE(aii)) {
            *cond = AC(HUGE_VAL);
            return MKC_SINGULAR;
        }
        D[i] = AC(1.0) / MKC_SQRT_A(aii);
    }
    for (j = 0; j < n; j++) {
        mkc_acc s = AC(1.0);                      /* (D A D)_jj = 1 exactly */
        mkc_acc ljj, inv;
        for (k = 0; k < j; k++)
            s -= L[j][k] * L[j][k];
        if (!(s > AC(1e-14))) {                   /* not positive definite to working precision */
            *cond = AC(HUGE_VAL);
            return MKC_SINGULAR;
        }
        ljj = MKC_SQRT_A(s);
        inv = AC(1.0) / ljj;
        L[j][j] = inv;
        lmax = mkc__max_a(lmax, ljj);
        lmin = mkc__min_a(lmin, ljj);
        for (i = j + 1; i < n; i++) {
            s = A[i][j] * D[i] * D[j];
            for (k = 0; k < j; k++)
                s -= L[i][k] * L[j][k];
            L[i][j] = s * inv;
        }
    }
    /* forward: L z = D b ; backward: L^T y = z ; x = D y */
    for (i = 0; i < n; i++) {
        mkc_acc s = b[i] * D[i];
        for (k = 0; k < i; k++)
            s -= L[i][k] * x[k];
        x[i] = s * L[i][i];
    }
    for (i = n - 1; i >= 0; i--) {
        mkc_acc s = x[i];
        for (k = i + 1; k < n; k++)
            s -= L[k][i] * x[k];
        x[i] = s * L[i][i];
    }
    for (i = 0; i < n; i++) {
        x[i] *= D[i];
        if (!MKC_ISFINITE(x[i])) {
            *cond = AC(HUGE_VAL);
            return MKC_NONFINITE;
        }
    }
    r = lmax / lmin;
    *cond = r * r;
    return MKC_OK;
}

/* Cyclic Jacobi (Rutishauser's formulation): rotate away each off-diagonal a_pq in turn until all
 * are negligible against the diagonal. Every rotation is orthogonal, so the eigenvalues come out
 * with high relative accuracy for the positive definite matrices used here (3x3 shape matrices,
 * the 9x9 equilibrated normal matrix), and the eigenvectors are orthonormal to working precision.
 * Why Jacobi: short, branch-light, no LAPACK, bounded (at most MAX_SWEEPS sweeps; quadratic
 * convergence makes 6-10 the norm). The symmetric square root Q diag(sqrt l) Q^T built from it
 * does not depend on the order or signs of the eigenvectors, so it equals numpy.linalg.eigh's. */
#define MKC_JACOBI_MAX_SWEEPS 60
/* stop when sum of squared off-diagonals <= OFF2 * sum of squared diagonals: ~1e-20 of the diagonal
 * in double; in float (MKC_CHECKPOINT_DOUBLE=0) ~3e-7, the level float rotations reach */
#if MKC_CREAL_FLOAT
#define MKC_JACOBI_OFF2 1e-13
#define MKC_JACOBI_BIG 1e18
#else
#define MKC_JACOBI_OFF2 1e-40
#define MKC_JACOBI_BIG 1e150
#endif
int mkc__jacobi_eigen(mkc_creal a[9][9], int k, mkc_creal *w, mkc_creal V[9][9])
{
    int sweep, p, q, r, i, j;
    if (V) {
        for (i = 0; i < k; i++)
            for (j = 0; j < k; j++)
                V[i][j] = (i == j) ? CR(1.0) : CR(0.0);
    }
    for (sweep = 1; sweep <= MKC_JACOBI_MAX_SWEEPS; sweep++) {
        mkc_creal off = CR(0.0), diag = CR(0.0);
        for (p = 0; p < k; p++) {
            diag += a[p][p] * a[p][p];
            for (q = p + 1; q < k; q++)
                off += a[p][q] * a[p][q];
        }
        if (!(off > CR(MKC_JACOBI_OFF2) * diag) || !isfinite(off))   /* off-diagonal negligible */
            break;
        for (p = 0; p < k - 1; p++) {
            for (q = p + 1; q < k; q++) {
                mkc_creal apq = a[p][q], theta, t, c, s, tau;
                if (apq == CR(0.0))
                    continue;
                theta = (a[q][q] - a[p][p]) / (CR(2.0) * apq);
                /* t = tan of the rotation angle: the smaller root of t^2 + 2 t theta - 1 = 0 */
                if (MKC_FABS_C(theta) > CR(MKC_JACOBI_BIG))   /* theta^2 would overflow */
                    t = CR(0.5) / theta;
                else
                    t = (theta >= CR(0.0) ? CR(1.0) : -CR(1.0)) / (MKC_FABS_C(theta) + MKC_SQRT_C(theta * theta + CR(1.0)));
                c = CR(1.0) / MKC_SQRT_C(t * t + CR(1.0));
                s = t * c;
                tau = s / (CR(1.0) + c);
                a[p][p] -= t * apq;
                a[q][q] += t * apq;
                a[p][q] = a[q][p] = CR(0.0);
                for (r = 0; r < k; r++) {
                    if (r != p && r != q) {
                        mkc_creal arp = a[r][p], arq = a[r][q];
                        a[r][p] = a[p][r] = arp - s * (arq + tau * arp);
                        a[r][q] = a[q][r] = arq + s * (arp - tau * arq);
                    }
                    if (V) {
                        mkc_creal vrp = V[r][p], vrq = V[r][q];
                        V[r][p] = vrp - s * (vrq + tau * vrp);
                        V[r][q] = vrq + s * (vrp - tau * vrq);
                    }
                }
            }
        }
    }
    for (i = 0; i < k; i++)
        w[i] = a[i][i];
    /* ascending order (numpy.linalg.eigh's), eigenvectors along */
    for (i = 1; i < k; i++) {
        for (j = i; j > 0 && w[j] < w[j - 1]; j--) {
            mkc_creal t = w[j];
            w[j] = w[j - 1];
            w[j - 1] = t;
            if (V) {
                for (r = 0; r < k; r++) {
                    t = V[r][j];
                    V[r][j] = V[r][j - 1];
                    V[r][j - 1] = t;
                }
            }
        }
    }
    return sweep > MKC_JACOBI_MAX_SWEEPS ? -1 : sweep;
}

/* Gaussian elimination with partial pivoting (LAPACK getrf's pivot choice). */
int mkc__solve3(const mkc_creal A[3][3], const mkc_creal *b, mkc_creal *x)
{
    mkc_creal M[3][4];
    int i, j, k;
    for (i = 0; i < 3; i++) {
        for (j = 0; j < 3; j++)
            M[i][j] = A[i][j];
        M[i][3] = b[i];
    }
    for (k = 0; k < 3; k++) {
        int piv = k;
        mkc_creal r;
        for (i = k + 1; i < 3; i++)
            if (MKC_FABS_C(M[i][k]) > MKC_FABS_C(M[piv][k]))
                piv = i;
        if (M[piv][k] == CR(0.0) || !isfinite(M[piv][k]))
            return MKC_SINGULAR;
        if (piv != k) {
            for (j = 0; j < 4; j++) {
                mkc_creal t = M[k][j];
                M[k][j] = M[piv][j];
                M[piv][j] = t;
            }
        }
        r = CR(1.0) / M[k][k];
        for (i = k + 1; i < 3; i++) {
            mkc_creal l = M[i][k] * r;
            for (j = k; j < 4; j++)
                M[i][j] -= l * M[k][j];
        }
    }
    for (i = 2; i >= 0; i--) {
        mkc_creal s = M[i][3];
        for (j = i + 1; j < 3; j++)
            s -= M[i][j] * x[j];
        x[i] = s / M[i][i];
    }
    for (i = 0; i < 3; i++)
        if (!isfinite(x[i]))
            return MKC_NONFINITE;
    return MKC_OK;
}
