"""Small dense linear algebra of the calibration's feedback path, bit-reproducible everywhere.

The sphere fit (normalisation) and the calibration (re-centring) feed back into the streaming
estimate, which is sensitive to their last bits (firmware_ref/README.md, "Why portable feedback").
numpy's LAPACK results depend on the BLAS build and the CPU; these plain-float loops do not, and the
C port (firmware_ref/src/linalg.c, sphere.c, ellipsoid.c) runs the same operations in the same order.
"""
from __future__ import annotations

import math


def jacobi_eigen(a, want_vectors):
    """Cyclic Jacobi on a symmetric k x k list-of-lists (destroyed); firmware_ref/src/linalg.c."""
    k = len(a)
    V = [[1.0 if i == j else 0.0 for j in range(k)] for i in range(k)] if want_vectors else None
    for _sweep in range(60):
        off = 0.0
        diag = 0.0
        for p in range(k):
            diag += a[p][p] * a[p][p]
            for q in range(p + 1, k):
                off += a[p][q] * a[p][q]
        if not (off > 1e-40 * diag) or not math.isfinite(off):
            break
        for p in range(k - 1):
            for q in range(p + 1, k):
                apq = a[p][q]
                if apq == 0.0:
                    continue
                theta = (a[q][q] - a[p][p]) / (2.0 * apq)
                if abs(theta) > 1e150:
                    t = 0.5 / theta
                else:
                    t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                tau = s / (1.0 + c)
                a[p][p] -= t * apq
                a[q][q] += t * apq
                a[p][q] = a[q][p] = 0.0
                for r in range(k):
                    if r != p and r != q:
                        arp, arq = a[r][p], a[r][q]
                        a[r][p] = a[p][r] = arp - s * (arq + tau * arp)
                        a[r][q] = a[q][r] = arq + s * (arp - tau * arq)
                    if V is not None:
                        vrp, vrq = V[r][p], V[r][q]
                        V[r][p] = vrp - s * (vrq + tau * vrp)
                        V[r][q] = vrq + s * (vrp - tau * vrq)
    w = [a[i][i] for i in range(k)]
    for i in range(1, k):                       # ascending, vectors along (insertion sort)
        j = i
        while j > 0 and w[j] < w[j - 1]:
            w[j], w[j - 1] = w[j - 1], w[j]
            if V is not None:
                for r in range(k):
                    V[r][j], V[r][j - 1] = V[r][j - 1], V[r][j]
            j -= 1
    return w, V


def solve3(A, b):
    """Gaussian elimination with partial pivoting; None when a pivot is 0 (firmware_ref/src/linalg.c)."""
    M = [[float(A[i][0]), float(A[i][1]), float(A[i][2]), float(b[i])] for i in range(3)]
    for k in range(3):
        piv = k
        for i in range(k + 1, 3):
            if abs(M[i][k]) > abs(M[piv][k]):
                piv = i
        if M[piv][k] == 0.0 or not math.isfinite(M[piv][k]):
            return None
        if piv != k:
            M[k], M[piv] = M[piv], M[k]
        r = 1.0 / M[k][k]
        for i in range(k + 1, 3):
            lk = M[i][k] * r
            for j in range(k, 4):
                M[i][j] -= lk * M[k][j]
    x = [0.0, 0.0, 0.0]
    for i in range(2, -1, -1):
        s = M[i][3]
        for j in range(i + 1, 3):
            s -= M[i][j] * x[j]
        x[i] = s / M[i][i]
    return x


def lstsq_sphere(u):
    """min |[2u, 1] x - |u|^2| by the normal equations and two refinement passes (sphere.c)."""
    N = [[0.0] * 4 for _ in range(4)]
    x = [0.0, 0.0, 0.0, 0.0]
    rows = [(2.0 * float(r[0]), 2.0 * float(r[1]), 2.0 * float(r[2]), 1.0,
             float(r[0]) * float(r[0]) + float(r[1]) * float(r[1]) + float(r[2]) * float(r[2])) for r in u]
    for it in range(3):
        rhs = [0.0, 0.0, 0.0, 0.0]
        for row in rows:
            res = row[4] - (row[0] * x[0] + row[1] * x[1] + row[2] * x[2] + row[3] * x[3])
            for p in range(4):
                rhs[p] += row[p] * res
                if it == 0:
                    for q in range(p + 1):
                        N[p][q] += row[p] * row[q]
        L = [[0.0] * 4 for _ in range(4)]
        for j in range(4):
            s = N[j][j]
            for k in range(j):
                s -= L[j][k] * L[j][k]
            if not (s > 0.0) or not math.isfinite(s):
                return None
            L[j][j] = math.sqrt(s)
            for i in range(j + 1, 4):
                t = N[i][j]
                for k in range(j):
                    t -= L[i][k] * L[j][k]
                L[i][j] = t / L[j][j]
        dx = [0.0] * 4
        for i in range(4):
            s = rhs[i]
            for k in range(i):
                s -= L[i][k] * dx[k]
            dx[i] = s / L[i][i]
        for i in range(3, -1, -1):
            s = dx[i]
            for k in range(i + 1, 4):
                s -= L[k][i] * dx[k]
            dx[i] = s / L[i][i]
        for p in range(4):
            x[p] += dx[p]
    return x
