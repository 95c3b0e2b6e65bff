"""Loaders of the public third-party datasets, each in its own upstream format.

The ``load_*`` functions read the public datasets used by the studies in ``tools/`` (and by the
tests on the copies in ``tests/data``) into :class:`~mkc_stream.io.recording.Recording` objects;
they are never needed at run time. Bad rows follow the recording rules of
:mod:`mkc_stream.io.recording` (``(line number, reason)``, nothing dropped silently). For datasets
stored as arrays (``.mat``, ``.hdf5``, ``.json``), the "line number" of a bad row is its 1-based
sample index in the source array.
"""
from __future__ import annotations

import json
import math
import pathlib
import warnings

import numpy as np

from .recording import (
    Recording,
    RecordingError,
    _decode,
    _drop_decreasing,
    _parse_body,
    _read_bytes,
    excerpt,
)

__all__ = [
    "load_broad",
    "load_cave_survey_json",
    "load_ck_explorer_csv",
    "load_qmc5883l_csv",
    "load_rasteiro_mat",
]


def _finish(t, mag, aux, labels, bad, meta, path, what="t") -> Recording:
    t = np.asarray(t, dtype=np.float64)
    names = list(aux)
    cols = [np.asarray(mag, dtype=np.float64)] + [np.asarray(aux[n], dtype=np.float64) for n in names]
    t, cols, labels = _drop_decreasing(t, cols, np.asarray(labels), bad, what=what)
    bad.sort(key=lambda b: b[0])
    return Recording(t=t, mag=cols[0], aux=dict(zip(names, cols[1:])), meta=meta, bad_rows=bad,
                     path=pathlib.Path(path))


def _text_lines(path: pathlib.Path) -> tuple[str, bool]:
    data, truncated = _read_bytes(path)
    return _decode(data), truncated


def _lines(text: str):
    """(line number from 1, the line stripped, the offset just past its newline) for each line."""
    pos, lineno = 0, 0
    while pos < len(text):
        end = text.find("\n", pos)
        end = len(text) if end < 0 else end
        lineno += 1
        yield lineno, text[pos:end].strip(), end + 1
        pos = end + 1


def load_qmc5883l_csv(path) -> Recording:
    """tomisuarez2/MagnetometerCalibration QMC5883L capture (MIT, (c) 2025 Tomas Suarez).

    Three header lines (``Fs,50.00``, ``Initialization time,60``, ``mx,my,mz``) then integer
    counts. ``t = i / Fs`` with ``i`` the index of the data line (bad lines keep their time slot);
    ``units.mag = counts``.
    """
    path = pathlib.Path(path)
    text, truncated = _text_lines(path)
    header_meta: dict[str, str] = {}
    lineno, pos, found = 0, 0, False
    for lineno, line, pos in _lines(text):
        if not line:
            continue
        if [c.strip() for c in line.split(",")] == ["mx", "my", "mz"]:
            found = True
            break
        key, _, value = line.partition(",")
        header_meta[key.strip()] = value.strip()
    if not found:
        raise RecordingError(f"{path}: no 'mx,my,mz' header line; not a QMC5883L capture of this format")
    try:
        fs = float(header_meta["Fs"])
    except (KeyError, ValueError):
        raise RecordingError(f"{path}: missing or invalid 'Fs,<rate>' header line") from None
    if not (math.isfinite(fs) and fs > 0):
        raise RecordingError(f"{path}: invalid sample rate Fs={fs!r}")
    first = lineno + 1
    body = text[pos:] if pos <= len(text) else ""
    values, linenos, bad = _parse_body(body, first, ["mx", "my", "mz"], [0, 1, 2], truncated)
    t = (linenos - first) / fs
    meta = {
        "source": str(path.name),
        "sensor": "QMC5883L (GY-273)",
        "units.mag": "counts",
        "rate_hz": f"{fs:g}",
        "origin": "https://github.com/tomisuarez2/MagnetometerCalibration",
        "licence": "MIT, Copyright (c) 2025 Tomas Suarez",
    }
    if "Initialization time" in header_meta:
        meta["initialization_time"] = header_meta["Initialization time"]
    return _finish(t, values, {}, linenos, bad, meta, path)


def load_ck_explorer_csv(path, nominal_rate_hz: float = 1.0) -> Recording:
    """CK-Explorer/Magnetometer-and-Accelerometer-Calibration log (Apache-2.0, (c) 2023 CK-Explorer).

    Header ``ax,ay,az,mx,my,mz``; accelerometer in g, magnetometer in gauss-like units; no
    timestamps and no stated rate, so ``t = index / nominal_rate_hz`` (an ordering, not a clock)
    and the metadata says the rate is unknown.
    """
    path = pathlib.Path(path)
    text, truncated = _text_lines(path)
    lineno, pos, names = 0, 0, None
    for lineno, line, pos in _lines(text):
        if line:
            names = [c.strip() for c in line.split(",")]
            break
    if names is None:
        raise RecordingError(f"{path}: the file is empty")
    missing = [c for c in ("mx", "my", "mz") if c not in names]
    if missing:
        raise RecordingError(f"{path}: line {lineno}: missing column(s) {', '.join(missing)} in header "
                             f"{excerpt(', '.join(names))}")
    first = lineno + 1
    body = text[pos:] if pos <= len(text) else ""
    mi = [names.index(c) for c in ("mx", "my", "mz")]
    values, linenos, bad = _parse_body(body, first, names, mi, truncated)
    t = (linenos - first) / float(nominal_rate_hz)
    aux = {n: values[:, j] for j, n in enumerate(names) if n not in ("mx", "my", "mz")}
    meta = {
        "source": str(path.name),
        "sensor": "unknown (CK-Explorer example log)",
        "units.mag": "G",
        "units.mag_note": "gauss-like units, not stated upstream",
        "units.acc": "g",
        "rate_hz": "unknown",
        "t": f"sample index / nominal {nominal_rate_hz:g} Hz; the source has no timestamps",
        "origin": "https://github.com/CK-Explorer/Magnetometer-and-Accelerometer-Calibration",
        "licence": "Apache-2.0, Copyright 2023 CK-Explorer",
    }
    return _finish(t, values[:, mi], aux, linenos, bad, meta, path)


def load_cave_survey_json(path) -> Recording:
    """circuitpython-mag-cal test fixture of a cave-survey device (MIT, Phil Underwood).

    ``shots.mag`` / ``shots.grav`` are flat lists NaN-padded to 256 values; reshaped to (-1, 3),
    all-NaN rows are padding and are dropped (not bad rows); a partly missing magnetometer shot
    is a bad row. The accelerometer (in g) goes to ``aux`` ``ax, ay, az``; ``t`` is the shot
    index (shots are not a time series).
    """
    path = pathlib.Path(path)
    with open(path, encoding="utf-8") as f:
        doc = json.load(f)
    shots = doc.get("shots") or {}
    if "mag" not in shots:
        raise RecordingError(f"{path}: no shots.mag list; not a circuitpython-mag-cal fixture")

    def triplets(values):
        a = np.asarray([math.nan if v is None else v for v in values], dtype=np.float64)
        return a[: a.size // 3 * 3].reshape(-1, 3)

    mag = triplets(shots["mag"])
    grav = triplets(shots.get("grav", []))
    n = mag.shape[0]
    if grav.shape[0] < n:
        grav = np.vstack([grav, np.full((n - grav.shape[0], 3), math.nan)])
    grav = grav[:n]
    present = np.isfinite(mag).any(axis=1) | np.isfinite(grav).any(axis=1)
    ok = np.isfinite(mag).all(axis=1)
    bad = [(int(i) + 1, "missing: magnetometer shot is incomplete") for i in np.flatnonzero(present & ~ok)]
    keep = present & ok
    idx = np.flatnonzero(keep)
    meta = {
        "source": str(path.name),
        "device": str(doc.get("name", "")),
        "sensor": "cave-survey device (circuitpython-mag-cal fixture)",
        "units.mag": "uT",
        "units.mag_note": "as stored by the device firmware (nominally uT, not stated)",
        "units.acc": "g",
        "t": "shot index (not a time series)",
        "origin": "https://github.com/furbrain/CircuitPython_mag_cal (PyPI circuitpython-mag-cal 1.4.1)",
        "licence": "MIT, Phil Underwood",
    }
    aux = {"ax": grav[idx, 0], "ay": grav[idx, 1], "az": grav[idx, 2]}
    return _finish(idx.astype(np.float64), mag[idx], aux, idx + 1, bad, meta, path)


def _load_broad_arrays(path: pathlib.Path) -> dict:
    names = ("imu_mag", "imu_acc", "imu_gyr", "opt_pos", "movement", "sampling_rate")
    if path.suffix.lower() in (".hdf5", ".h5"):
        try:
            import h5py
        except ImportError:
            raise ImportError(f"reading {path.name} needs h5py: pip install h5py "
                              f"(or pip install 'mkc-stream[hdf5]') "
                              f"(or use the .mat version of the trial)") from None
        out = {}
        with h5py.File(path, "r") as f:
            for n in names:
                if n in f:
                    out[n] = np.asarray(f[n][()])
                elif n in f.attrs:
                    out[n] = np.asarray(f.attrs[n])
        return out
    from scipy.io import loadmat

    return loadmat(path, variable_names=list(names))


def _nx3(a, name, path) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim == 2 and a.shape[1] != 3 and a.shape[0] == 3:
        a = a.T
    if a.ndim != 2 or a.shape[1] != 3:
        raise RecordingError(f"{path}: {name} has shape {a.shape}, expected (N, 3)")
    return a


def load_broad(path) -> Recording:
    """One BROAD trial (``.mat`` via scipy, ``.hdf5`` via h5py); CC BY 4.0, cite Laidig et al. 2021.

    ``imu_mag`` [uT] -> ``mag``; ``imu_acc`` [m/s^2] -> ``ax, ay, az``; ``imu_gyr`` [rad/s] ->
    ``gx, gy, gz``; ``opt_pos`` [m] (the motion capture's position of the sensor) -> ``px, py, pz``
    (NaN where the markers were lost); ``movement`` -> aux ``movement`` (1 in motion phases); ``t = i /
    sampling_rate``. BROAD's magnetometer is already calibrated (|m| ~ 44-50 uT). Samples with a
    non-finite magnetometer value are bad rows (numbered by 1-based sample index).
    """
    path = pathlib.Path(path)
    d = _load_broad_arrays(path)
    for n in ("imu_mag", "sampling_rate"):
        if n not in d:
            raise RecordingError(f"{path}: no {n!r} variable; not a BROAD trial")
    mag = _nx3(d["imu_mag"], "imu_mag", path)
    fs = float(np.asarray(d["sampling_rate"], dtype=np.float64).reshape(-1)[0])
    n = mag.shape[0]
    aux = {}
    for key, cols in (("imu_acc", ("ax", "ay", "az")), ("imu_gyr", ("gx", "gy", "gz")), ("opt_pos", ("px", "py", "pz"))):
        if key in d:
            a = _nx3(d[key], key, path)
            for j, c in enumerate(cols):
                aux[c] = a[:, j]
    if "movement" in d:
        aux["movement"] = np.asarray(d["movement"], dtype=np.float64).reshape(-1)
    for k, v in aux.items():
        if v.shape != (n,):
            raise RecordingError(f"{path}: {k} has {v.shape[0]} samples, imu_mag has {n}")
    ok = np.isfinite(mag).all(axis=1)
    bad = [(int(i) + 1, "non-finite: magnetometer sample is not finite") for i in np.flatnonzero(~ok)]
    idx = np.flatnonzero(ok)
    meta = {
        "source": str(path.name),
        "trial": path.stem,
        "sensor": "myon aktos-t",
        "units.mag": "uT",
        "units.mag_note": "already calibrated by BROAD",
        "units.acc": "m/s^2",
        "units.gyr": "rad/s",
        "units.pos": "m (optical motion capture)",
        "rate_hz": repr(fs),
        "origin": "https://github.com/dlaidig/broad",
        "licence": "CC BY 4.0",
        "citation": ("D. Laidig, M. Caruso, A. Cereatti, T. Seel. BROAD - A Benchmark for Robust "
                     "Inertial Orientation Estimation. Data 6(7):72, 2021. https://doi.org/10.3390/data6070072"),
    }
    t = np.arange(n, dtype=np.float64) / fs
    return _finish(t[idx], mag[idx], {k: v[idx] for k, v in aux.items()}, idx + 1, bad, meta, path)


def load_rasteiro_mat(path) -> Recording:
    """miguelrasteiro/IMU_dataset MATLAB file (MIT, (c) 2015 Miguel Rasteiro; cite the papers).

    ``SENSmag``/``SENSacc``/``SENSgyro`` (3 x N) raw outputs, ``MATLABtime`` (1 x N) seconds.
    A dropout (all-zero or all-NaN magnetometer triplet, or accelerometer and gyroscope both
    all-zero) is a bad row, as is any other non-finite magnetometer value or time and a sample
    whose time goes backwards; rows are numbered by 1-based sample index.
    The sensor name is taken from the file name (``LSM9DS0.mat`` ...).
    """
    path = pathlib.Path(path)
    from scipy.io import loadmat

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the files hold MATLAB objects scipy cannot read
        d = loadmat(path, variable_names=["SENSmag", "SENSacc", "SENSgyro", "MATLABtime"])
    for n in ("SENSmag", "MATLABtime"):
        if n not in d:
            raise RecordingError(f"{path}: no {n!r} variable; not an IMU_dataset file")
    mag = _nx3(d["SENSmag"], "SENSmag", path)
    n = mag.shape[0]
    t = np.asarray(d["MATLABtime"], dtype=np.float64).reshape(-1)
    if t.shape != (n,):
        raise RecordingError(f"{path}: MATLABtime has {t.size} samples, SENSmag has {n}")
    aux = {}
    acc = _nx3(d["SENSacc"], "SENSacc", path) if "SENSacc" in d else None
    gyr = _nx3(d["SENSgyro"], "SENSgyro", path) if "SENSgyro" in d else None
    for a, cols in ((acc, ("ax", "ay", "az")), (gyr, ("gx", "gy", "gz"))):
        if a is not None:
            if a.shape[0] != n:
                raise RecordingError(f"{path}: {cols} have {a.shape[0]} samples, SENSmag has {n}")
            for j, c in enumerate(cols):
                aux[c] = a[:, j]
    bad = []
    mag_zero = np.all(mag == 0, axis=1)
    frame_zero = np.zeros(n, dtype=bool)
    if acc is not None and gyr is not None:
        frame_zero = np.all(acc == 0, axis=1) & np.all(gyr == 0, axis=1)
    finite = np.isfinite(mag).all(axis=1) & np.isfinite(t)
    mag_nan = np.isnan(mag).all(axis=1)
    for i in range(n):
        if mag_nan[i]:
            bad.append((i + 1, "dropout: NaN magnetometer sample"))
        elif not finite[i]:
            bad.append((i + 1, "non-finite: magnetometer sample or time is not finite"))
        elif mag_zero[i]:
            bad.append((i + 1, "dropout: all-zero magnetometer sample"))
        elif frame_zero[i]:
            bad.append((i + 1, "dropout: all-zero accelerometer and gyroscope sample"))
    ok = finite & ~mag_zero & ~frame_zero
    idx = np.flatnonzero(ok)
    meta = {
        "source": str(path.name),
        "sensor": path.stem,
        "units.mag": "raw",
        "units.mag_note": "sensor output as recorded (LSM9DS0/RM3100 ~uT, MPU9150 scaled raw units)",
        "units.acc": "raw",
        "units.gyr": "raw",
        "rate_hz": "100",
        "t": "MATLABtime [s]",
        "origin": "https://github.com/miguelrasteiro/IMU_dataset",
        "licence": "MIT, Copyright (c) 2015 Miguel Rasteiro",
    }
    return _finish(t[idx], mag[idx], {k: v[idx] for k, v in aux.items()}, idx + 1, bad, meta, path,
                   what="MATLABtime")
