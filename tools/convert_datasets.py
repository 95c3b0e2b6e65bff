"""Developer tool: build the bundled recording and the test data from the shared dataset copies.

    python tools/convert_datasets.py [--shared /work/shared]

Reads the third-party datasets under ``<shared>/data`` (see each folder's SOURCE.txt) and writes

* ``mkc_stream/data/qmc5883l_noisy.csv``: the QMC5883L "noisy" capture of
  tomisuarez2/MagnetometerCalibration (MIT) in the recording format (the package's demo);
* ``tests/data/<dataset>/``: the small real files the tests use, each with its SOURCE.txt;
  the BROAD trial is larger than 3 MB, so the tests get a 12 s excerpt of it (same variables,
  CC BY 4.0, the change is stated in its SOURCE.txt and in the file's ``info`` variable);
* ``tests/data/mkc_normaliser.csv``: the reference normaliser grid (copied unchanged).

The licence files next to the data (``mkc_stream/data/LICENSES.md``, ``tests/data/*/LICENSE*``,
``*.json.license``) are kept in the repository and not regenerated here. Neither the package nor
the tests need the shared folder: only this script reads it.
"""
from __future__ import annotations

import argparse
import filecmp
import io
import pathlib
import shutil
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mkc_stream.io.recording import load_qmc5883l_csv, read_recording, write_recording  # noqa: E402

MAX_BUNDLED_BYTES = 1_000_000
BROAD_MAX_BYTES = 3_000_000
BROAD_TRIAL = "26_disturbed_phone_vibration_A.mat"
BROAD_EXCERPT = (40.0, 52.0)  # seconds: rest, the start of the movement phase (45.3 s), motion


def _copy(src: pathlib.Path, dst: pathlib.Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    if dst.exists() and filecmp.cmp(src, dst, shallow=False):
        return
    shutil.copyfile(src, dst)
    print(f"  {dst.relative_to(ROOT)}  ({dst.stat().st_size} bytes)")


def bundled_qmc(shared: pathlib.Path) -> None:
    src_dir = shared / "data" / "qmc5883l-tomisuarez"
    rec = load_qmc5883l_csv(src_dir / "noisy_raw_data.csv")
    if rec.bad_rows:
        raise SystemExit(f"unexpected bad rows in the source: {rec.bad_rows[:5]}")
    step = 1
    out = ROOT / "mkc_stream" / "data" / "qmc5883l_noisy.csv"
    while True:
        meta = {
            "source": 'tomisuarez2/MagnetometerCalibration, "calibration data/noisy_raw_data.csv"',
            "origin": "https://github.com/tomisuarez2/MagnetometerCalibration",
            "commit": "eb93f820ffc06155579b7d86928795915eef714a",
            "licence": "MIT (see mkc_stream/data/LICENSES.md)",
            "copyright": "Copyright (c) 2025 Tomas Suarez",
            "sensor": "QMC5883L (GY-273)",
            "units.mag": "counts",
            "rate_hz": f"{50 / step:g}",
            "t": "sample index / Fs (the source has no timestamps; Fs,50.00 in its header)",
            "initialization_time": rec.meta.get("initialization_time", ""),
            "content": "raw counts, unfiltered, full-sphere hand rotation on an Arduino UNO",
            "converted_by": "tools/convert_datasets.py (values unchanged)",
        }
        if step > 1:
            meta["decimated"] = f"every {step}th sample kept to stay under 1 MB"
        write_recording(out, rec.t[::step], rec.mag[::step], meta=meta)
        if out.stat().st_size <= MAX_BUNDLED_BYTES:
            break
        step += 1
    back = read_recording(out)
    assert np.array_equal(back.mag, rec.mag[::step]) and not back.bad_rows
    print(f"  {out.relative_to(ROOT)}  ({out.stat().st_size} bytes, {len(back)} samples, step {step})")


def test_data(shared: pathlib.Path) -> None:
    data = shared / "data"
    tests = ROOT / "tests" / "data"
    cave = data / "mag-cal-cave-survey"
    for f in sorted(cave.glob("*.json")) + [cave / "SOURCE.txt"]:
        _copy(f, tests / cave.name / f.name)
    qmc = data / "qmc5883l-tomisuarez"
    for name in ("filtered_raw_data.csv", "SOURCE.txt"):
        _copy(qmc / name, tests / qmc.name / name)
    ck = data / "ck-explorer-accmag"
    for name in ("acc_mag_log.csv", "SOURCE.txt"):
        _copy(ck / name, tests / ck.name / name)
    broad_excerpt(data / "broad", tests / "broad")
    _copy(shared / "reference" / "mkc_normaliser.csv", tests / "mkc_normaliser.csv")


def broad_excerpt(src_dir: pathlib.Path, dst_dir: pathlib.Path) -> None:
    from scipy.io import loadmat, savemat

    src = src_dir / BROAD_TRIAL
    dst_dir.mkdir(parents=True, exist_ok=True)
    if src.stat().st_size < BROAD_MAX_BYTES:
        _copy(src, dst_dir / src.name)
        _copy(src_dir / "SOURCE.txt", dst_dir / "SOURCE.txt")
        return
    d = loadmat(src)
    fs = float(d["sampling_rate"].item())
    i0, i1 = (int(round(s * fs)) for s in BROAD_EXCERPT)
    names = ("imu_gyr", "imu_acc", "imu_mag", "opt_quat", "opt_pos", "movement")
    out = {n: d[n][i0:i1] for n in names}
    out["sampling_rate"] = d["sampling_rate"]
    note = (f"\n\nEXCERPT made by mkc_stream tools/convert_datasets.py: samples {i0}..{i1 - 1} "
            f"(t = {BROAD_EXCERPT[0]:g} s to {BROAD_EXCERPT[1]:g} s) of {src.name}; values unchanged.")
    out["info"] = np.array([str(d["info"].reshape(-1)[0]) + note])
    dst = dst_dir / (src.stem + "_excerpt.mat")
    buf = io.BytesIO()
    savemat(buf, out, do_compression=True, oned_as="column")
    blob = bytearray(buf.getvalue())
    # the MAT header holds the creation time; a fixed text keeps the file reproducible
    fixed = b"MATLAB 5.0 MAT-file, excerpt of BROAD " + src.stem.encode() + b" by mkc_stream"
    blob[:116] = fixed[:116].ljust(116, b" ")
    if not (dst.exists() and dst.read_bytes() == bytes(blob)):
        dst.write_bytes(bytes(blob))
        print(f"  {dst.relative_to(ROOT)}  ({dst.stat().st_size} bytes, {i1 - i0} samples)")
    text = (src_dir / "SOURCE.txt").read_text(encoding="utf-8")
    text += (
        "\nTests copy (mkc_stream): the full trial is 3.9 MB, so tests/data/broad holds\n"
        f"  {dst.name}: an EXCERPT (changed: cut to samples {i0}..{i1 - 1}, t = {BROAD_EXCERPT[0]:g}-"
        f"{BROAD_EXCERPT[1]:g} s,\n  rest then the start of the movement phase) of data_mat/{src.name},"
        " saved with scipy.io.savemat\n  (compressed); variables and values unchanged, a note appended to"
        " `info`. Licence CC BY 4.0\n  (https://creativecommons.org/licenses/by/4.0/); cite the paper above.\n"
    )
    (dst_dir / "SOURCE.txt").write_text(text, encoding="utf-8")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--shared", type=pathlib.Path, default=ROOT.parent / "shared",
                    help="folder holding data/ and reference/ (default: ../shared)")
    args = ap.parse_args(argv)
    if not (args.shared / "data").is_dir():
        ap.error(f"{args.shared}/data not found")
    print("bundled recording:")
    bundled_qmc(args.shared)
    print("test data:")
    test_data(args.shared)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
