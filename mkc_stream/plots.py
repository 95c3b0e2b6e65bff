"""Plots for people (optional extra [plot]): the fit, the weights, the field norm."""
from __future__ import annotations

import numpy as np


def _plt():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:  # pragma: no cover - exercised by the extra's absence
        raise ImportError("plots need matplotlib: pip install 'mkc-stream[plot]'") from exc
    return plt


def save_figure(fig, path, dpi=110):
    """Render to memory, then write the file ourselves: matplotlib's own writer can drop a failed
    write (a full disk) without raising, and a plot the user asked for must not vanish silently."""
    import io

    buf = io.BytesIO()
    fig.savefig(buf, dpi=dpi, format="png")
    with open(path, "wb") as fh:            # OSError (ENOSPC, EACCES) reaches the caller
        fh.write(buf.getvalue())


def plot_calibration(raw, fit, path, title=""):
    """Raw samples coloured by weight with the fitted ellipsoid, and |m_cal| against time."""
    plt = _plt()
    raw = np.asarray(raw)
    w = np.clip(fit.weights / max(fit.weights.max(), 1e-300), 0, 1)
    m_cal = fit.apply(raw)
    fig = plt.figure(figsize=(11, 4.5))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    # low weight (treated as disturbed) = dark, full weight = bright
    ax.scatter(raw[:, 0], raw[:, 1], raw[:, 2], c=w, cmap="viridis", s=3, vmin=0, vmax=1)
    surf = fit.geometry.surface(16, 32)
    ax.plot_wireframe(surf[..., 0], surf[..., 1], surf[..., 2], color="k", linewidth=0.3, alpha=0.5)
    ax.set_title("raw samples (dark = down-weighted) and fit")
    ax2 = fig.add_subplot(1, 2, 2)
    k = np.arange(raw.shape[0])
    norm = np.linalg.norm(m_cal, axis=1)
    sc = ax2.scatter(k, norm, c=w, cmap="viridis", s=2, vmin=0, vmax=1)
    fig.colorbar(sc, ax=ax2, label="kernel weight")
    ax2.axhline(fit.field, color="r", lw=1, label=f"F = {fit.field:.4g}")
    ax2.set_xlabel("sample")
    ax2.set_ylabel("|S (m - b)|")
    ax2.legend(loc="upper right")
    ax2.set_title("calibrated field norm")
    import os

    fig.suptitle(f"{os.path.basename(str(title))}  [{fit.method}]")
    fig.tight_layout()
    try:
        save_figure(fig, path)
    finally:
        plt.close(fig)
