"""The MKC-induced pdf, eq. (17), on the truncated domain [-a, a] (Remark 3, Section III-D)."""
from __future__ import annotations

import numpy as np

from .kernels.normaliser import log_normaliser


def mkc_logpdf(e, sigma, d, a=np.inf):
    """log p(e) = -sigma^2 (1 - exp(-e^2 / (2 d^2 sigma^2))) - log(d Z(sigma, a/d)), |e| <= a.

    a = inf is allowed only as sigma -> inf (the Gaussian of Corollary 1): for finite sigma the
    pdf has a floor exp(-sigma^2) and is not normalisable on the whole line. Outside [-a, a]
    the density is 0 (log = -inf).
    """
    e = np.asarray(e, dtype=np.float64)
    if not (sigma > 0 and d > 0 and a > 0):
        raise ValueError(f"need sigma > 0, d > 0, a > 0; got {sigma}, {d}, {a}")
    if np.isinf(sigma):
        logc = -np.log(d * np.sqrt(2 * np.pi))
        if np.isfinite(a):
            from scipy.special import erf

            logc -= np.log(erf(a / (d * np.sqrt(2))))
        out = logc - 0.5 * (e / d) ** 2
    else:
        if not np.isfinite(a):
            raise ValueError("a finite sigma needs a finite truncation bound a (the pdf has a floor exp(-sigma^2))")
        q = e * e / (2 * d * d * sigma * sigma)
        out = -sigma * sigma * (-np.expm1(-q)) - np.log(d) - log_normaliser(float(sigma), float(a / d))
    return np.where(np.abs(e) <= a, out, -np.inf)


def mkc_pdf(e, sigma, d, a=np.inf):
    return np.exp(mkc_logpdf(e, sigma, d, a))
