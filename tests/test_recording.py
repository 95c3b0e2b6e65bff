"""The recording file format, the dataset loaders and the bundled recording."""
import gzip
import pathlib

import numpy as np
import pytest

from mkc_stream.io import (
    Recording,
    RecordingError,
    bundled_recording,
    bundled_recording_path,
    load_broad,
    load_cave_survey_json,
    load_ck_explorer_csv,
    load_qmc5883l_csv,
    load_rasteiro_mat,
    read_recording,
    write_recording,
)

DATA = pathlib.Path(__file__).parent / "data"


def _bits(a):
    return np.ascontiguousarray(a, dtype=np.float64).view(np.uint64)


def _awkward_floats(rng, n):
    x = rng.normal(0, 1, n) * 10.0 ** rng.integers(-300, 300, n)
    x[:8] = [0.1, -0.0, 0.0, 1e-310, 5e-324, 1.7976931348623157e308, 1 / 3, 2.0**53 + 2]
    return x


# ----------------------------------------------------------------------------------------------
# round trip
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["rec.csv", "rec.csv.gz"])
def test_round_trip_is_bit_exact(tmp_path, rng, name):
    n = 500
    t = np.cumsum(rng.uniform(0.001, 0.02, n))
    mag = np.column_stack([_awkward_floats(rng, n), rng.normal(0, 50, n), rng.integers(-9000, 9000, n)])
    temp = rng.normal(25, 3, n)
    temp[[3, 7]] = np.nan
    aux = {"ax": rng.normal(0, 9.8, n), "gz": _awkward_floats(rng, n), "temp": temp,
           "motor_rpm": rng.integers(0, 12000, n).astype(float)}
    meta = {"sensor": "QMC5883L", "units.mag": "counts", "rate_hz": 50, "my.custom-key": "a: b, c"}
    path = write_recording(tmp_path / name, t, mag, aux, meta)
    if name.endswith(".gz"):
        assert path.read_bytes()[:2] == b"\x1f\x8b"
    rec = read_recording(path)
    assert isinstance(rec, Recording)
    assert rec.bad_rows == []
    assert np.array_equal(_bits(rec.t), _bits(t))
    assert np.array_equal(_bits(rec.mag), _bits(mag))
    assert list(rec.aux) == list(aux)
    for k, v in aux.items():
        assert np.array_equal(_bits(rec.aux[k]), _bits(v)), k
    assert rec.meta == {k: str(v) for k, v in meta.items()}
    assert rec.mag_unit == "counts"
    assert rec.columns == ["t", "mx", "my", "mz", "ax", "gz", "temp", "motor_rpm"]
    assert rec.counts() == {"samples": n, "bad_frames": 0, "drops": 0, "gaps": rec.counts()["gaps"]}
    # writing what was read gives the same file
    again = rec.write(tmp_path / ("again_" + name))
    assert read_recording(again).meta == rec.meta
    if not name.endswith(".gz"):
        assert again.read_bytes() == path.read_bytes()


def test_write_is_plain_text_with_metadata_first(tmp_path):
    path = write_recording(tmp_path / "r.csv", [0.0, 0.5], [[1.0, 2.5, -3.0], [4.0, 5.0, 6.0]],
                           meta={"sensor": "x"})
    assert path.read_text() == "# sensor: x\nt,mx,my,mz\n0,1,2.5,-3\n0.5,4,5,6\n"
    assert read_recording(path).mag_unit == "uT"  # the default


def test_write_rejects_what_cannot_round_trip(tmp_path):
    with pytest.raises(ValueError):
        write_recording(tmp_path / "a.csv", [0.0], [[1, 2, 3]], meta={"note": "two\nlines"})
    with pytest.raises(ValueError):
        write_recording(tmp_path / "a.csv", [0.0], [[1, 2, 3]], meta={"a:b": "x"})
    with pytest.raises(ValueError):
        write_recording(tmp_path / "a.csv", [0.0], [[1, 2, 3]], aux={"mx": [1.0]})
    with pytest.raises(ValueError):
        write_recording(tmp_path / "a.csv", [0.0], [[1, 2, 3]], aux={"a,b": [1.0]})
    with pytest.raises(ValueError):
        write_recording(tmp_path / "a.csv", [0.0, 1.0], [[1, 2, 3]])
    assert not list(tmp_path.iterdir())  # nothing half-written left behind


# ----------------------------------------------------------------------------------------------
# bad input
# ----------------------------------------------------------------------------------------------

BAD_FILE = (
    "# sensor: test\n"          # 1
    "# units.mag: counts\n"     # 2
    "t,mx,my,mz,temp\n"         # 3
    "0,1,2,3,20\n"              # 4  ok
    "0.1,1,abc,3,20\n"          # 5  non-numeric required
    "0.2,1,,3,20\n"             # 6  empty required
    "0.3,1,2,3\n"               # 7  too few cells
    "0.4,1,2,3,\n"              # 8  ok, temp missing
    "0.5,1,2,3,nan\n"           # 9  ok, temp missing
    "\n"                        # 10 blank: no sample
    "0.35,1,2,3,20\n"           # 11 t goes backwards
    "0.6,nan,2,3,1\n"           # 12 nan required
    "0.7,1,2,3,x\n"             # 13 garbled optional cell
    "0.8,1,2,3,20,9\n"          # 14 too many cells
    "0.8,4,5,6,21\n"            # 15 ok (equal t is allowed)
    "0.9,1,2,inf,1\n"           # 16 non-finite required
    "1.0,1,2"                   # 17 file cut mid-row
)


@pytest.mark.parametrize("gz", [False, True])
def test_bad_rows_are_counted_with_line_numbers(tmp_path, gz):
    path = tmp_path / ("bad.csv.gz" if gz else "bad.csv")
    data = BAD_FILE.encode()
    path.write_bytes(gzip.compress(data) if gz else data)
    rec = read_recording(path)
    assert rec.t.tolist() == [0.0, 0.4, 0.5, 0.8]
    assert rec.mag.tolist() == [[1, 2, 3], [1, 2, 3], [1, 2, 3], [4, 5, 6]]
    assert np.isnan(rec.aux["temp"][[1, 2]]).all() and rec.aux["temp"][[0, 3]].tolist() == [20, 21]
    lines = [line for line, _ in rec.bad_rows]
    assert lines == [5, 6, 7, 11, 12, 13, 14, 16, 17]
    kinds = [reason.split(": ")[0] for _, reason in rec.bad_rows]
    assert kinds == ["non-numeric", "missing", "cell count", "t decreasing", "missing", "non-numeric",
                     "cell count", "non-finite", "truncated"]
    reasons = dict(rec.bad_rows)
    assert "'my'" in reasons[5] and "'abc'" in reasons[5]
    assert "'my'" in reasons[6]
    assert reasons[11] == "t decreasing: t=0.35 is below the earlier t=0.5"
    assert reasons[16] == "non-finite: required column 'mz' is inf"
    assert "'temp'" in reasons[13]
    assert rec.counts() == {"samples": 4, "bad_frames": 9, "drops": 0, "gaps": rec.counts()["gaps"]}
    assert rec.bad_summary()["cell count"] == 2
    assert rec.meta == {"sensor": "test", "units.mag": "counts"}


def test_decreasing_time_is_bad_not_reordered(tmp_path):
    path = tmp_path / "r.csv"
    path.write_text("t,mx,my,mz\n0,1,1,1\n1,2,2,2\n2,3,3,3\n1.5,4,4,4\n1.9,5,5,5\n2,6,6,6\n3,7,7,7\n")
    rec = read_recording(path)
    assert rec.t.tolist() == [0, 1, 2, 2, 3]
    assert rec.mag[:, 0].tolist() == [1, 2, 3, 6, 7]
    assert [line for line, _ in rec.bad_rows] == [5, 6]
    assert all(r.startswith("t decreasing") for _, r in rec.bad_rows)


def test_truncated_gzip_stream_is_a_bad_last_row(tmp_path, rng):
    n = 20000
    t = np.arange(n) / 100.0
    mag = rng.normal(0, 40, (n, 3))
    full = write_recording(tmp_path / "r.csv.gz", t, mag).read_bytes()
    cut = tmp_path / "cut.csv.gz"
    cut.write_bytes(full[: len(full) // 2])
    rec = read_recording(cut)
    assert 0 < len(rec) < n
    assert np.array_equal(rec.mag, mag[: len(rec)])
    assert len(rec.bad_rows) == 1 and rec.bad_rows[0][1].startswith("truncated")
    assert rec.bad_rows[0][0] == len(rec) + 2  # header on line 1, the row after the last kept one


def test_well_formed_last_line_without_newline_is_kept(tmp_path):
    path = tmp_path / "r.csv"
    path.write_text("t,mx,my,mz\n0,1,2,3\n1,4,5,6")
    rec = read_recording(path)
    assert len(rec) == 2 and rec.bad_rows == []


def test_crlf_bom_blank_lines_spaces_and_comment_in_body(tmp_path):
    path = tmp_path / "r.csv"
    text = "\ufeff# rate_hz : 10\r\n\r\n t , mx,my ,mz \r\n0, 1 ,2,3\r\n\r\n0.1,4,5,6\r\n# note\r\n0.2,7,8,9\r\n"
    path.write_bytes(text.encode("utf-8"))
    rec = read_recording(path)
    assert rec.meta == {"rate_hz": "10"}
    assert rec.mag.tolist() == [[1, 2, 3], [4, 5, 6], [7, 8, 9]]
    assert rec.bad_rows == [(7, "unexpected comment: comment line after the header")]
    assert rec.rate_hz == 10.0


def test_missing_required_column(tmp_path):
    path = tmp_path / "r.csv"
    path.write_text("# sensor: x\nt,mx,my,temp\n0,1,2,3\n")
    with pytest.raises(RecordingError, match="mz") as err:
        read_recording(path)
    assert isinstance(err.value, ValueError)
    assert "line 2" in str(err.value)


@pytest.mark.parametrize("text", ["", "\n\n  \n", "# sensor: x\n# units.mag: uT\n"])
def test_empty_or_metadata_only_file(tmp_path, text):
    path = tmp_path / "r.csv"
    path.write_text(text)
    with pytest.raises(RecordingError):
        read_recording(path)


def test_empty_gzip_file(tmp_path):
    path = tmp_path / "r.csv.gz"
    path.write_bytes(gzip.compress(b""))
    with pytest.raises(RecordingError, match="empty"):
        read_recording(path)


def test_duplicate_column_is_an_error(tmp_path):
    path = tmp_path / "r.csv"
    path.write_text("t,mx,my,mz,mx\n0,1,2,3,4\n")
    with pytest.raises(RecordingError, match="duplicate"):
        read_recording(path)


def test_header_only_gives_an_empty_recording(tmp_path):
    path = tmp_path / "r.csv"
    path.write_text("t,mx,my,mz,ax\n")
    rec = read_recording(path)
    assert len(rec) == 0 and rec.mag.shape == (0, 3) and rec.aux["ax"].shape == (0,)
    assert rec.counts() == {"samples": 0, "bad_frames": 0, "drops": 0, "gaps": 0}


def test_gaps_are_counted(tmp_path, rng):
    dt = np.full(999, 0.01)
    dt[100] = 0.05   # gap
    dt[500] = 1.0    # gap
    dt[700] = 0.02   # late sample, not a gap (2x < 2.5x)
    dt[800] = 0.0    # duplicate time stamp, allowed
    t = np.concatenate([[0.0], np.cumsum(dt)])
    path = write_recording(tmp_path / "r.csv", t, rng.normal(size=(1000, 3)))
    rec = read_recording(path)
    assert rec.counts()["gaps"] == 2
    assert rec.gap_indices().tolist() == [100, 500]
    assert rec.bad_rows == []


def test_many_rows_with_a_few_bad_ones(tmp_path, rng):
    # exercises the chunked numpy parser and its per-line fallback
    n = 70000
    t = np.arange(n) / 50.0
    mag = rng.integers(-5000, 5000, (n, 3)).astype(float)
    path = write_recording(tmp_path / "r.csv", t, mag, meta={"sensor": "x"})
    lines = path.read_text().split("\n")
    lines[2 + 40000] = "800,1,2"        # file line 40003
    lines[2 + 65000] = "1300.0,1,2,zz"  # file line 65003
    path.write_text("\n".join(lines))
    rec = read_recording(path)
    assert [line for line, _ in rec.bad_rows] == [40003, 65003]
    keep = np.ones(n, bool)
    keep[[40000, 65000]] = False
    assert np.array_equal(rec.mag, mag[keep]) and np.array_equal(rec.t, t[keep])
    assert rec.counts()["gaps"] == 0  # one missing sample doubles a step: below 2.5x


# ----------------------------------------------------------------------------------------------
# dataset loaders on the tests/data copies
# ----------------------------------------------------------------------------------------------


def test_load_qmc5883l():
    rec = load_qmc5883l_csv(DATA / "qmc5883l-tomisuarez" / "filtered_raw_data.csv")
    assert rec.mag.shape == (22745, 3) and rec.bad_rows == []
    assert rec.mag_unit == "counts" and rec.meta["sensor"].startswith("QMC5883L")
    assert rec.meta["rate_hz"] == "50" and rec.rate_hz == 50.0
    assert np.allclose(np.diff(rec.t), 0.02)
    assert np.array_equal(rec.mag, np.round(rec.mag))  # integer counts
    centre = (rec.mag.min(0) + rec.mag.max(0)) / 2
    assert np.allclose(centre, [6197, 250, 3479], atol=150)


def test_load_qmc5883l_reports_bad_lines(tmp_path):
    path = tmp_path / "q.csv"
    path.write_text("Fs,10.00\nInitialization time,60\nmx,my,mz\n1,2,3\n4,x,6\n7,8,9\n10,11")
    rec = load_qmc5883l_csv(path)
    assert rec.mag.tolist() == [[1, 2, 3], [7, 8, 9]]
    assert rec.t.tolist() == [0.0, 0.2]  # a bad line keeps its time slot
    assert [line for line, _ in rec.bad_rows] == [5, 7]


def test_load_cave_survey():
    files = sorted((DATA / "mag-cal-cave-survey").glob("*.json"))
    assert len(files) == 9
    for f in files:
        rec = load_cave_survey_json(f)
        assert rec.mag.shape == (24, 3) and rec.bad_rows == [] and rec.meta["device"]
        assert rec.t.tolist() == list(range(24))
        g = np.column_stack([rec.aux[k] for k in ("ax", "ay", "az")])
        assert np.allclose(np.linalg.norm(g, axis=1), 1.0, atol=0.1)  # raw gravity, in g
        assert 50 < np.linalg.norm(rec.mag, axis=1).mean() < 130


def test_load_ck_explorer():
    rec = load_ck_explorer_csv(DATA / "ck-explorer-accmag" / "acc_mag_log.csv")
    assert rec.mag.shape == (12000, 3) and rec.bad_rows == []
    assert list(rec.aux) == ["ax", "ay", "az"]
    assert rec.meta["rate_hz"] == "unknown" and rec.meta["units.acc"] == "g"
    assert rec.t.tolist()[:3] == [0.0, 1.0, 2.0]
    acc = np.column_stack([rec.aux[k] for k in ("ax", "ay", "az")])
    assert abs(np.median(np.linalg.norm(acc, axis=1)) - 1.0) < 0.05
    centre = (rec.mag.min(0) + rec.mag.max(0)) / 2
    assert np.allclose(centre, [0.148, 0.390, -0.059], atol=0.02)


def test_load_broad_excerpt():
    rec = load_broad(DATA / "broad" / "26_disturbed_phone_vibration_A_excerpt.mat")
    assert rec.mag.shape == (3428, 3) and rec.bad_rows == []
    assert rec.mag_unit == "uT" and "Laidig" in rec.meta["citation"]
    assert rec.rate_hz == pytest.approx(285.714, abs=1e-3)
    assert rec.t[1] == pytest.approx(1 / 285.714285714, rel=1e-9)
    assert set(rec.aux) == {"ax", "ay", "az", "gx", "gy", "gz", "px", "py", "pz", "movement"}
    assert abs(np.median(np.linalg.norm(rec.mag, axis=1)) - 44.5) < 2.5  # calibrated field ~44-46 uT
    # the motion capture's position in m: the sensor is held about 1.2-1.8 m above the floor
    assert rec.meta["units.pos"].startswith("m ") and 1.0 < np.nanmedian(rec.aux["pz"]) < 2.0
    acc = np.column_stack([rec.aux[k] for k in ("ax", "ay", "az")])
    assert abs(np.median(np.linalg.norm(acc, axis=1)) - 9.81) < 0.3
    assert set(np.unique(rec.aux["movement"])) == {0.0, 1.0}


def test_load_broad_hdf5_needs_h5py(tmp_path):
    import importlib.util

    if importlib.util.find_spec("h5py") is not None:
        pytest.skip("h5py is installed")
    with pytest.raises(ImportError, match="pip install h5py"):
        load_broad(tmp_path / "trial.hdf5")


def test_load_rasteiro_reports_dropouts(tmp_path):
    from scipy.io import savemat

    n = 10
    t = np.arange(n) * 0.01
    mag = np.tile([[20.0], [-5.0], [130.0]], n) + np.arange(n)
    acc = np.tile([[0.0], [0.0], [1.0]], n)
    gyr = np.full((3, n), 0.01)
    mag[:, 0] = 0.0                       # sample 1: dropout (all zero)
    mag[:, 4] = np.nan                    # sample 5: NaN frame
    t[4] = 0.0
    acc[:, 6] = 0.0
    gyr[:, 6] = 0.0                       # sample 7: acc+gyro dropout
    t[8] = 0.05                           # sample 9: time goes back
    path = tmp_path / "LSM9DS0.mat"
    savemat(path, {"SENSmag": mag, "SENSacc": acc, "SENSgyro": gyr, "MATLABtime": t[None, :]})
    rec = load_rasteiro_mat(path)
    assert [line for line, _ in rec.bad_rows] == [1, 5, 7, 9]
    assert [r.split(": ")[0] for _, r in rec.bad_rows] == ["dropout", "dropout", "dropout", "t decreasing"]
    assert rec.t.tolist() == pytest.approx([0.01, 0.02, 0.03, 0.05, 0.07, 0.09])
    assert rec.mag.shape == (6, 3) and not np.any(np.all(rec.mag == 0, axis=1))
    assert rec.meta["sensor"] == "LSM9DS0" and list(rec.aux) == ["ax", "ay", "az", "gx", "gy", "gz"]


# ----------------------------------------------------------------------------------------------
# bundled recording and test data provenance
# ----------------------------------------------------------------------------------------------


def test_bundled_recording():
    path = bundled_recording_path()
    assert path.is_file() and path.stat().st_size < 1_000_000
    rec = bundled_recording()
    assert rec.mag.shape == (22743, 3) and rec.bad_rows == []
    assert rec.meta["sensor"] == "QMC5883L (GY-273)"
    assert rec.mag_unit == "counts" and rec.meta["rate_hz"] == "50"
    assert "MIT" in rec.meta["licence"] and "Tomas Suarez" in rec.meta["copyright"]
    assert rec.meta["commit"] == "eb93f820ffc06155579b7d86928795915eef714a"
    assert rec.counts() == {"samples": 22743, "bad_frames": 0, "drops": 0, "gaps": 0}
    centre = (rec.mag.min(0) + rec.mag.max(0)) / 2
    assert np.all(np.abs(centre - [6197, 250, 3479]) < 600)
    licences = (path.parent / "LICENSES.md").read_text()
    assert "Copyright (c) 2025 Tomas Suarez" in licences and "eb93f820ffc0" in licences
    with pytest.raises(FileNotFoundError):
        bundled_recording_path("no_such_recording.csv")


def test_test_data_carry_their_licences():
    for folder in ("mag-cal-cave-survey", "qmc5883l-tomisuarez", "ck-explorer-accmag", "broad"):
        assert (DATA / folder / "SOURCE.txt").is_file(), folder
    assert "Apache License" in (DATA / "ck-explorer-accmag" / "LICENSE").read_text()
    assert "Copyright 2023 CK-Explorer" in (DATA / "ck-explorer-accmag" / "LICENSE").read_text()
    assert "CC BY 4.0" in (DATA / "broad" / "SOURCE.txt").read_text()
    assert "10.3390/data6070072" in (DATA / "broad" / "SOURCE.txt").read_text()
    assert (DATA / "mkc_normaliser.csv").read_text().startswith("#")
