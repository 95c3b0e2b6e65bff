"""Several compasses of one flight calibrated and compared; the one that disagrees is named."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mkc_stream.cli import main
from mkc_stream.flight import fit_flight
from mkc_stream.flight.compare import compare_compasses
from mkc_stream.flight.simulated import simulated_flight


@pytest.fixture(scope="module")
def flight():
    f = simulated_flight(seed=2, pitch_amp=0.25, bank_gain=25.0, duration=300.0, rate=20.0)
    return f, fit_flight(f.recording, earth=f.truth["h_ned"])


def test_agreeing_compasses_are_not_named(flight):
    f, fc = flight
    out = compare_compasses([("0", f.recording, fc), ("1", f.recording, fc)], float(np.linalg.norm(f.truth["h_ned"])))
    assert out["inconsistent"] == []
    for row in out["compasses"]:
        assert max(row["heading_rms_deg"].values()) < 1e-6 and abs(row["field_vs_model"]) < 0.02


def test_the_compass_that_disagrees_alone_is_named(flight):
    f, fc = flight
    wrong = dataclasses.replace(fc, hard_iron=fc.hard_iron + np.array([8.0, 0.0, 0.0]))   # uT: a bad calibration
    items = [("0", f.recording, fc), ("1", f.recording, fc), ("2", f.recording, wrong)]
    out = compare_compasses(items, float(np.linalg.norm(f.truth["h_ned"])))
    assert [b["id"] for b in out["inconsistent"]] == ["2"]
    assert "heading" in out["inconsistent"][0]["reason"]
    # two compasses that disagree: said, but neither named (two cannot tell which)
    out = compare_compasses(items[1:], None)
    assert out["inconsistent"] == [] and "cannot tell" in out["note"]


def test_all_instances_on_a_log_that_cannot_calibrate_says_so(capsys):
    import json
    import pathlib

    log = pathlib.Path(__file__).parent / "data" / "flightlog-dronekit-log171" / "log171_excerpt.bin"
    pytest.importorskip("pymavlink")
    code = main(["calibrate", str(log), "--all-instances", "--json", "-", "--quiet"])
    obj = json.loads(capsys.readouterr().out)
    assert code == 1 and len(obj["instances"]) == 3
    assert all(i["status"] == "rejected" and i["reason"] for i in obj["instances"])
    assert "nothing to compare" in obj["comparison"]["note"]


def test_all_instances_write_one_parameter_file_for_every_compass(flight, tmp_path):
    from types import SimpleNamespace

    from mkc_stream.commands.calibrate import _write_params
    from mkc_stream.commands.common import Outputs
    from mkc_stream.params import read_params

    _, fc = flight
    path = tmp_path / "all.param"
    outputs = Outputs()
    _write_params(SimpleNamespace(params=[("ardupilot", str(path))]), outputs, [(0, fc), (1, fc)], None)
    assert outputs.failed == []
    compasses = read_params("ardupilot", path)
    assert len(compasses) == 2
    text = path.read_text()
    assert "COMPASS_OFS_X" in text and "COMPASS_OFS2_X" in text and "COMPASS_MOT2_X" in text
