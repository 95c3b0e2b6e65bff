"""The robust scale: one constant and one helper for "1.4826 MAD" across the package.

MAD_SCALE turns a median absolute deviation into a standard deviation for Gaussian data
(1/Phi^-1(3/4) to the 4 significant digits the C port uses, firmware_ref/src/quality.c
MKC_MAD_SCALE): the calibration's outlier mask, the sphere fit's trimming, the window's restart
scale d, the batch fit's start scale and the diagnosis's noise figures all use it.
(The literature baselines in mkc_stream/baselines/ keep their own exact MAD_TO_SIGMA and their
zero-centred mad_scale: their results are compared with the papers', not with the C port.)

kernels/window.py compiles MAD_SCALE into its cached kernels; mkc_stream._numba stamps this file
with the kernel sources (it names `import kernel`) so that a change here recompiles them.
"""
from __future__ import annotations

import numpy as np

#: Normal-consistency factor of the median absolute deviation (1.4826 MAD ~ sigma).
MAD_SCALE = 1.4826


def mad_sd(x, center=None, axis=None):
    """Robust standard deviation MAD_SCALE * median(|x - center|), center the median of x (along axis)
    unless given (0.0 for residuals whose location belongs to a fit). No NaN filtering, no floor."""
    x = np.asarray(x)
    if center is None:
        center = np.median(x) if axis is None else np.median(x, axis=axis, keepdims=True)
    return MAD_SCALE * np.median(np.abs(x - center), axis=axis)
