"""The recording as the diagnoser sees it: checked, decimated if asked, split into time blocks.

Blocks: the recording is cut into ``N_BLOCKS`` blocks of equal duration; models are fitted on
the even blocks and scored on the odd ones, and the other way round (cross-fitting, so no data
are wasted). Why interleaved blocks rather than a first/second half: effects that depend on time
(drift, steps, temperature cycles) must be seen in training wherever they act; held-out blocks
between training blocks test the model on the same conditions without having fitted on them.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

MIN_SAMPLES = 1000
N_BLOCKS = 32
IMU_COLUMNS = ("ax", "ay", "az", "gx", "gy", "gz")


class DiagnoseError(ValueError):
    """The recording cannot be diagnosed (too short, not finite, no motion ...); the message says why."""


@dataclass
class Frame:
    t: np.ndarray
    m: np.ndarray
    acc_unit: np.ndarray | None          # (N, 3) accelerometer direction
    acc_ok: np.ndarray                   # (N,) accelerometer usable for the dip (|a| near g)
    gyro: np.ndarray | None
    aux: dict                            # usable aux signals (N,) each
    aux_notes: dict                      # aux columns left out, with why
    block: np.ndarray                    # (N,) block index
    n_blocks: int
    train: np.ndarray                    # (N,) bool
    dt0: float                           # median sample period, s
    duration: float
    timestamps_real: bool
    unit: str
    decimation: int = 1
    meta: dict = field(default_factory=dict)
    bad_rows: int = 0

    @property
    def n(self) -> int:
        return int(self.t.shape[0])

    @cached_property
    def m_smooth(self) -> np.ndarray:
        """The raw magnetometer averaged over 3 samples: where the effects' forms are read when
        the fit inverts them (:func:`.model._effect_offsets`), so the noise is not passed
        through the form's slope a second time."""
        from ..sim.trajectory import moving_average

        return moving_average(self.m, 3)

    @property
    def test(self) -> np.ndarray:
        return ~self.train

    def block_slices(self):
        edges = np.searchsorted(self.block, np.arange(self.n_blocks + 1))
        return [slice(int(edges[i]), int(edges[i + 1])) for i in range(self.n_blocks)]

    @property
    def train_blocks(self) -> np.ndarray:
        return np.arange(self.n_blocks) % 2 == 0


def _timestamps_real(meta: dict) -> bool:
    note = str(meta.get("t", "")).lower()
    return not any(w in note for w in ("index", "nominal", "shot"))


def prepare(rec, max_samples: int | None = 20000, n_blocks: int = N_BLOCKS) -> Frame:
    """Check a Recording and build the Frame; decimate by an integer factor above max_samples."""
    n = len(rec)
    if n < MIN_SAMPLES:
        raise DiagnoseError(f"too short to diagnose: {n} samples; a diagnosis needs at least {MIN_SAMPLES} "
                            f"(the gap statistics are compared over {n_blocks} time blocks)")
    if not np.isfinite(rec.mag).all() or not np.isfinite(rec.t).all():
        bad = int((~np.isfinite(rec.mag).all(axis=1) | ~np.isfinite(rec.t)).sum())
        raise DiagnoseError(f"{bad} samples have a non-finite time or magnetometer value; "
                            "remove them (read_recording skips such rows and reports them)")
    if np.any(np.diff(rec.t) < 0):
        raise DiagnoseError("time goes backwards; samples must be in time order")
    dec = 1
    if max_samples and n > max_samples:
        dec = int(np.ceil(n / max_samples))
    idx = np.arange(0, n, dec)
    t = rec.t[idx]
    duration = float(t[-1] - t[0])
    if not duration > 0:
        raise DiagnoseError("all samples have the same time stamp")
    m = rec.mag[idx]
    if np.ptp(m, axis=0).min() <= 0:
        raise DiagnoseError("one magnetometer axis never changes: the sensor did not move or is stuck")

    acc_unit, acc_ok, gyro = None, np.zeros(len(idx), dtype=bool), None
    if all(c in rec.aux for c in IMU_COLUMNS[:3]):
        acc = np.stack([rec.aux[c][idx] for c in IMU_COLUMNS[:3]], axis=1)
        na = np.linalg.norm(acc, axis=1)
        fin = np.isfinite(na) & (na > 0)
        if fin.mean() > 0.5:
            g = np.median(na[fin])
            acc_unit = np.full_like(acc, np.nan)
            acc_unit[fin] = acc[fin] / na[fin, None]
            acc_ok = fin & (np.abs(na / g - 1.0) < 0.1)
            if acc_ok.mean() < 0.3:
                acc_unit, acc_ok = None, np.zeros(len(idx), dtype=bool)
    if all(c in rec.aux for c in IMU_COLUMNS[3:]):
        gy = np.stack([rec.aux[c][idx] for c in IMU_COLUMNS[3:]], axis=1)
        if np.isfinite(gy).all(axis=1).mean() > 0.5:
            gyro = gy

    aux, notes = {}, {}
    for name, col in rec.aux.items():
        if name in IMU_COLUMNS:
            continue
        x = col[idx]
        fin = np.isfinite(x)
        if fin.mean() < 0.5:
            notes[name] = f"{(~fin).mean():.0%} of its values are missing"
            continue
        if np.unique(x[fin]).size < 5:
            notes[name] = "takes fewer than 5 distinct values"
            continue
        if (~fin).any():      # hold the last value over short holes
            x = x.copy()
            good = np.flatnonzero(fin)
            x[~fin] = x[good[np.clip(np.searchsorted(good, np.flatnonzero(~fin)) - 1, 0, None)]]
        aux[name] = x
    block = np.minimum(((t - t[0]) / duration * n_blocks).astype(np.int64), n_blocks - 1)
    dt = np.diff(t)
    dt0 = float(np.median(dt[dt > 0])) if (dt > 0).any() else duration / n
    return Frame(t=t, m=m, acc_unit=acc_unit, acc_ok=acc_ok, gyro=gyro, aux=aux, aux_notes=notes,
                 block=block, n_blocks=n_blocks, train=(block % 2 == 0), dt0=dt0, duration=duration,
                 timestamps_real=_timestamps_real(rec.meta), unit=rec.mag_unit, decimation=dec,
                 meta=dict(rec.meta), bad_rows=len(rec.bad_rows))
