"""The `calibrate material` input file (stitchplan.config.calibration): validated like a
scenario, every problem of the file at once; the marker files are read by
stitchplan.calibration.inputs, whose problems join those of the YAML."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from stitchplan.calibration import load_material_calibration
from stitchplan.config import Material
from stitchplan.config.calibration import parse_calibration
from stitchplan.errors import InputError

SAMPLES = Path(__file__).resolve().parents[1] / "sample_runs" / "calibration"


def calibration_raw() -> dict:
    return {"tissue": {"size": [100.0, 60.0], "thickness": 10.0, "clamped": ["right"]},
            "experiments": [{"loads": [{"segment": [[0.0, 24.0], [0.0, 36.0]], "force": [2.0, 1.0]}],
                             "markers": "markers.csv"}],
            "fit": {"lame_lambda": [0.01, 2.0], "lame_mu": [0.01, 2.0]}}


def test_defaults_of_a_minimal_file():
    spec = parse_calibration(calibration_raw())
    assert spec.discretization.spacing == pytest.approx(3.0)  # min(W, H) / 20
    assert (spec.fit.grid, spec.fit.grid_scale, spec.fit.model) == (6, "log", "saint-venant-kirchhoff")
    assert spec.experiments[0].load_steps == 10 and spec.experiments[0].name == ""
    raw = calibration_raw()
    raw["fit"]["lame_lambda"] = [0.0, 2.0]
    assert parse_calibration(raw).fit.grid_scale == "linear"  # a log grid needs positive bounds


def test_segment_ends_moved_onto_the_boundary_are_logged_by_their_fields(caplog):
    """As in a scenario: a clamped piece's and an experiment load's segment ends typed a little
    off the edge are moved onto it, each logged with its field (the segments of every
    experiment's loads, the tissue's clamps as the tissue places them)."""
    import logging

    caplog.set_level(logging.INFO, logger="stitchplan")
    raw = calibration_raw()
    raw["tissue"]["clamped"] = [{"segment": [[100.0004, 10.0], [100.0, 50.0]]}]
    raw["experiments"][0]["loads"][0]["segment"] = [[0.0, 24.0], [0.0002, 36.0]]
    parse_calibration(raw, "calibration.yaml")  # named as the file's errors name it
    records = [(r.levelname, r.getMessage()) for r in caplog.records]
    assert [(level, message.split(": [")[0]) for level, message in records] == [
        ("WARNING", "calibration.yaml: tissue.clamped[0].segment[0]"),
        ("WARNING", "calibration.yaml: experiments[0].loads[0].segment[1]")]
    assert records[1][1].startswith("calibration.yaml: experiments[0].loads[0].segment[1]: [0.0002, 36.0] lies "
                                    "0.0002 mm off the "
                                    "boundary of the ")


def test_every_problem_of_the_file_at_once():
    raw = calibration_raw()
    raw["tissue"].update(thickness=0, clamped=[], material={"lame_lambda": 0.2, "lame_mu": 0.1})
    raw["experiments"].append({"loads": [], "markers": ""})
    raw["fit"].update(lame_mu=[2.0, 0.01], grdi=5)
    with pytest.raises(InputError) as error:
        parse_calibration(raw)
    assert error.value.lines == [
        "tissue.thickness: got 0, expected a positive number (mm)",
        ("tissue.material: got {'lame_lambda': 0.2, 'lame_mu': 0.1}, expected no material in a "
         "calibration file (the moduli are what is fitted; choose the model with fit.model)"),
        ("experiments[0].loads: got only forces on a tissue with no clamped edge, expected "
         "tissue.clamped or a displacement load to hold the slab in place"),
        "experiments[1].loads: got [], expected a non-empty list of loads (force or displacement)",
        "experiments[1].markers: got '', expected a CSV file name (relative to the YAML file)",
        "fit.lame_mu: got [2.0, 0.01], expected [low, high] with 0 < low < high (MPa)",
        ("fit: unknown key 'grdi', expected one of: lame_lambda, lame_mu, model, grid, grid_scale, "
         "max_evaluations, regions (did you mean 'grid'?)"),
    ]


def test_a_log_grid_needs_positive_bounds():
    raw = calibration_raw()
    raw["fit"].update(lame_lambda=[0.0, 2.0], grid_scale="log")
    with pytest.raises(InputError, match=r"^fit.grid_scale: got 'log', expected linear when the "
                                         r"lame_lambda range starts at 0"):
        parse_calibration(raw)


def test_yaml_and_marker_problems_come_together_naming_the_file(tmp_path):
    raw = calibration_raw()
    raw["experiments"].append({"loads": raw["experiments"][0]["loads"], "markers": "absent.csv"})
    raw["experiments"][0]["markers"] = "markers.csv"
    (tmp_path / "markers.csv").write_text("x,y,x_def,y_def\n10,10,10,10\n120,10,121,10\n")
    path = tmp_path / "calib.yaml"
    path.write_text(yaml.safe_dump(raw))
    with pytest.raises(InputError) as error:
        load_material_calibration(path)
    assert len(error.value.lines) == 2
    assert all(line.startswith(f"{path}: experiments[") for line in error.value.lines)
    # worded as the other CSV readers' lines: `file: line N, column: got ...`, a missing file
    # as a missing scenario
    assert "markers.csv: line 3, x, y: got the rest position [120, 10] mm, expected a point inside" \
        in error.value.lines[0]
    assert error.value.lines[1].endswith("absent.csv: cannot be read (No such file or directory)")


def test_shipped_calibration_input_validates():
    spec = parse_calibration(yaml.safe_load((SAMPLES / "calibration.yaml").read_text()))
    assert [e.name for e in spec.experiments] == ["left-edge pull", "top-edge press"]
    tissue = spec.tissue.tissue(Material())
    assert tissue.clamped == ("right",) and tissue.size == (100.0, 60.0)


def test_an_experiment_whose_loads_are_all_zero_is_refused():
    """Markers that stay put whatever the moduli carry nothing to fit (the fit used to
    report lambda/mu = 1 as determined)."""
    raw = calibration_raw()
    raw["experiments"][0]["loads"] = [{"segment": [[0.0, 24.0], [0.0, 36.0]], "force": [0.0, 0.0]},
                                      {"segment": [[40.0, 60.0], [60.0, 60.0]], "displacement": [0.0, 0.0]}]
    with pytest.raises(InputError, match=r"^experiments\[0\].loads: got only zero loads, expected a non-zero "
                                         r"force or displacement"):
        parse_calibration(raw)


def test_a_marker_given_twice_is_refused_naming_both_lines(tmp_path):
    """A repeated row would weigh that marker twice in the least squares."""
    raw = calibration_raw()
    (tmp_path / "markers.csv").write_text("x,y,x_def,y_def\n10,10,10.5,10\n20,10,20.2,10\n10,10,10.4,10\n")
    path = tmp_path / "calib.yaml"
    path.write_text(yaml.safe_dump(raw))
    with pytest.raises(InputError, match=r"experiments\[0\].markers: .*markers.csv: line 4, x, y: got the rest position "
                                         r"\[10, 10\] mm again \(first at line 2\), expected each marker once"):
        load_material_calibration(path)
