"""The seeds' comparison estimators, all with the linear-model API of mkc_stream.

Every class takes X (N, m, n) with Y (N, m) - the multi-channel model y_k = X_k theta + v_k -
or X (N, n) with y (N,), stacks the N*m rows into one regression (optionally dividing channel
i by ``channel_scale[i]``), fits no intercept unless stated, and sets ``coef_`` (n,).

numpy/scipy only: LAD (exact LP), LEL, LMS, LTS, R3. Thin scikit-learn wrappers (optional
extra ``baselines``, imported inside fit()): ridge, lasso, RANSAC, Huber.
"""
from .high_breakdown import LMSRegressor, LTSRegressor
from .huber import HuberRegressor
from .lad import LADRegressor
from .lel import LeastEntropyLikeRegressor, entropy_like
from .penalized import LassoRegressor, RidgeRegressor
from .r3 import R3HuberEpsRegressor, R3HuberRegressor, RobustKernelRegressor
from .ransac import RANSACRegressor

#: CLI method name -> estimator class (each constructible with no arguments).
BASELINES = {
    "lad": LADRegressor,
    "ridge": RidgeRegressor,
    "lasso": LassoRegressor,
    "lel": LeastEntropyLikeRegressor,
    "lms": LMSRegressor,
    "lts": LTSRegressor,
    "ransac": RANSACRegressor,
    "huber": HuberRegressor,
    "r3-huber": R3HuberRegressor,
    "r3-huber-eps": R3HuberEpsRegressor,
}

__all__ = [
    "BASELINES",
    "HuberRegressor",
    "LADRegressor",
    "LMSRegressor",
    "LTSRegressor",
    "LassoRegressor",
    "LeastEntropyLikeRegressor",
    "R3HuberEpsRegressor",
    "R3HuberRegressor",
    "RANSACRegressor",
    "RidgeRegressor",
    "RobustKernelRegressor",
    "entropy_like",
]
