"""`stitchplan study` and the auto discretization, on a tiny scene that runs in seconds:

- the `study:` block is validated like the rest of the scenario (unknown keys, bad values
  and a reference with more than one spacing refused, naming the field);
- the CLI writes study.csv with every promised column, one row per run, the reference
  last at zero deviation, a failing configuration (a quadratic basis with a dilation too
  small for its moment matrix) recorded with its reason instead of dropped, and the PNG;
- the Pareto front and the exit-point deviations on hand-made records;
- graded particles: volumes tile the slab, the spacing is fine in the needle zone and the
  2:1 balance holds, and the RK functions with per-particle supports reproduce linear
  fields to round-off;
- the auto discretization meets its accuracy against a finer run, says what it relied on
  and what it chose, and runs once per scenario when simulate asks for it.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import os
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from stitchplan import __version__
from stitchplan.cli import app
from stitchplan.config.scenario import ScenarioError, parse_scenario, with_discretization
from stitchplan.config.study import StudyFamily
from stitchplan.io.study_reports import COLUMNS
from stitchplan.planning.verification import exit_deviations
from stitchplan.errors import InputError
from stitchplan.study.sweep import StudyRun, pareto_front, plan_runs, run_study

PHANTOM = {"lame_lambda": 0.189151, "lame_mu": 0.147688}  # MPa, thesis appendix A.2
REQUIRED_COLUMNS = ("family", "spacing_mm", "dilation", "quadrature_order", "basis_order", "step_rad",
                    "tip_tracking", "linear_solver", "wall_seconds", "particles", "exit_error_mm",
                    "exit_deviation_mm", "status", "reason")


def tiny_raw(study: dict | None = None, **needle) -> dict:
    """40 x 30 mm phantom block clamped on the right, 8 mm needle entering (0, 22) cw in
    0.4 rad steps (8 steps): a run on 5 mm particles takes a fraction of a second."""
    raw = {"name": "tiny", "tissue": {"size": [40.0, 30.0], "thickness": 10.0, "clamped": ["right"],
                                      "material": dict(PHANTOM)},
           "discretization": {"spacing": 5.0},
           "needle": {"radius": 8.0, "entry": [0.0, 22.0], "turn": "cw", "step": 0.4, "friction": 0.0602,
                      "cutting_force": 0.7, **needle}}
    if study is not None:
        raw["study"] = study
    return raw


SWEEP = {"spacing": [6.0, 5.0],
         "families": [{"name": "uniform"},
                      {"name": "graded x2", "grading": 2},
                      {"name": "quadratic, dilation 1.5", "basis_order": 2, "dilation": 1.5}],
         "reference": {"spacing": 3.0}}


# --- the study block -----------------------------------------------------------------------


def test_study_block_is_parsed_into_families_and_reference():
    spec = parse_scenario(tiny_raw(SWEEP)).study
    assert spec.spacing == (6.0, 5.0) and spec.repeats == 1
    assert [f.name for f in spec.families] == ["uniform", "graded x2", "quadratic, dilation 1.5"]
    assert spec.families[1].grading == 2 and spec.families[2].basis_order == 2
    assert spec.reference.spacing == (3.0,) and spec.reference.name == "reference"
    runs, reference, _ = plan_runs(parse_scenario(tiny_raw(SWEEP)))
    assert len(runs) == 6 and reference.scenario.discretization.spacing == 3.0
    graded = [r for r in runs if r.family == "graded x2"][0].scenario.discretization
    assert (graded.spacing, graded.needle_spacing) == (12.0, 6.0)


@pytest.mark.parametrize("study, fragment", [
    ({"spacings": [4.0]}, "study: unknown key 'spacings', expected one of: spacing, families"),
    ({"spacing": []}, "study.spacing: got [], expected a non-empty list of spacings (mm)"),
    ({"spacing": [4.0, -1.0]}, "study.spacing[1]: got -1.0, expected a positive number (mm)"),
    ({"families": [{"name": "a", "solver": "minres"}]}, "study.families[0]: unknown key 'solver'"),
    ({"families": [{"tip_tracking": "newton"}]}, "study.families[0].tip_tracking: got 'newton', expected one of"),
    ({"families": [{"grading": 3}]}, "study.families[0].grading: got 3, expected one of 2, 4, 8, 16"),
    ({"families": [{"dilation": 0.9}]}, "dilation: got 0.9, expected a number > 1"),
    ({"families": [{"name": "a"}, {"name": "a"}]}, "study.families: got ['a', 'a'], expected families with distinct names"),
    ({"reference": {"spacing": 2.0, "name": "myref"}},  # taken and dropped before
     "study.reference.name: got 'myref', expected no name: the reference's runs are named 'reference'"),
    ({"reference": {"spacing": [1.0, 2.0]}}, "study.reference.spacing: got [1.0, 2.0], expected one spacing (mm)"),
    ({"repeats": 0}, "study.repeats: got 0, expected an integer between 1 and 20"),
    ({"spacing": [6.0, 6.0]}, "study.spacing: got [6.0, 6.0], expected spacings each given once"),
    # a graded run's coarse spacing overflowed to inf, told as `study 'graded x4'.spacing: got inf`
    ({"spacing": [1e308]}, "study.spacing[0]: got 1e+308, expected a positive number of at most 10000 (mm; a spacing"),
    ({"families": [{"spacing": [4.0, 2e4]}]}, "study.families[0].spacing[1]: got 20000.0, expected a positive number "
                                             "of at most 10000"),
    ({"families": [{"spacing": [4.0, 4]}]}, "study.families[0].spacing: got [4.0, 4.0], expected spacings each"),
    # the study's own runs' families: a user's would share study.csv's family column with them
    ({"families": [{"name": "a"}, {"name": "auto"}]}, ("study.families[1].name: got 'auto', expected a name other "
                                                       "than 'reference' and 'auto'")),
    ({"families": [{"name": "reference"}]}, "study.families[0].name: got 'reference', expected a name other than"),
])
def test_bad_study_blocks_are_refused_naming_the_field(study, fragment):
    with pytest.raises(ScenarioError) as error:
        parse_scenario(tiny_raw(study))
    assert fragment in str(error.value)


def test_a_study_run_too_big_names_the_study_field_that_set_its_spacing(tmp_path):
    """The resource guard's refusal of a study run names the study's own field (a family's
    spacing list, the reference's), with the value given there, not discretization.spacing."""
    scenario = tmp_path / "huge.yaml"
    scenario.write_text(yaml.safe_dump(tiny_raw({"families": [{"name": "a"}, {"name": "tiny", "spacing": [0.05]}],
                                                 "spacing": [6.0], "reference": {"spacing": 0.04}}),
                                       sort_keys=False))
    result = CliRunner().invoke(app, ["study", str(scenario), "--out", str(tmp_path / "out")])
    assert result.exit_code == 2
    assert f"error: {scenario}: study.families[1].spacing: got 0.05 mm, expected a spacing giving at most" in result.output
    assert f"error: {scenario}: study.reference.spacing: got 0.04 mm, expected a spacing" in result.output
    assert not (tmp_path / "out").exists()


def test_the_reference_takes_the_sweeps_smallest_needle_step():
    """A family with half the needle step was compared with a reference at the scenario's step,
    which then was the coarser of the two in time (the default sweep's `step 0.05` against a
    0.1 rad reference): the reference takes the smallest step of the sweep, unless it sets
    its own, which may be no coarser (as its spacing may not: the deviations are measured
    from it)."""
    halved = {**SWEEP, "families": [*SWEEP["families"], {"name": "step 0.2", "step": 0.2}]}
    _, reference, _ = plan_runs(parse_scenario(tiny_raw(halved)))
    assert reference.scenario.needle.step == 0.2
    _, reference, _ = plan_runs(parse_scenario(tiny_raw(SWEEP)))
    assert reference.scenario.needle.step == 0.4
    own = {**halved, "reference": {"spacing": 3.0, "step": 0.15}}
    _, reference, _ = plan_runs(parse_scenario(tiny_raw(own)))
    assert reference.scenario.needle.step == 0.15
    coarser = {**halved, "reference": {"spacing": 3.0, "step": 0.3}}
    with pytest.raises(InputError, match=r"^study\.reference\.step: got 0\.3 rad, expected at most the finest step "
                                         r"of the sweep, 0\.2 rad"):
        plan_runs(parse_scenario(tiny_raw(coarser)))


def test_the_guard_counts_the_reference_once_as_it_runs(caplog):
    """`repeats` times the runs' timings; the reference runs once, and the guard said it ran
    `repeats` times."""
    import logging

    from stitchplan.cli.guards import guard_study
    from stitchplan.resources.limits import Limits

    runs, reference, repeats = plan_runs(parse_scenario(tiny_raw({**SWEEP, "repeats": 3})))
    with caplog.at_level(logging.INFO, logger="stitchplan.resources"):
        guard_study(Path("tiny.yaml"), Limits(), runs, reference, repeats, workers=0)
    lines = [record.getMessage() for record in caplog.records]
    assert all("in each of 3 runs" in line for line in lines if "'reference h=3 mm'" not in line)
    (line,) = [line for line in lines if "'reference h=3 mm'" in line]
    assert "in each of" not in line


@pytest.mark.parametrize("study, fragment", [
    ({"families": [{"name": "a"}, {"name": "wide", "dilation": 11}]}, "study.families[1].dilation: got 11, expected at most 10"),
    ({"reference": {"spacing": 3.0, "dilation": 11}}, "study.reference.dilation: got 11, expected at most 10"),
    ({"families": [{"name": "a"}, {"name": "fine", "step": 0.0001}]},
     "study.families[1].step: got 0.0001 rad, expected a step giving at most 2000 needle steps"),
    ({"reference": {"spacing": 3.0, "step": 0.0001}}, "study.reference.step: got 0.0001 rad, expected a step giving"),
])
def test_a_study_choice_the_guard_refuses_is_named_by_the_study_field_that_set_it(study, fragment):
    """A family's or the reference's dilation or needle step beyond the guard's limits was
    named as the scenario's discretization.dilation or needle.step, which the file gave
    otherwise or not at all."""
    from stitchplan.cli.guards import guard_study
    from stitchplan.resources.limits import Limits

    runs, reference, repeats = plan_runs(parse_scenario(tiny_raw({**SWEEP, **study})))
    with pytest.raises(InputError) as error:
        guard_study(Path("tiny.yaml"), Limits(), runs, reference, repeats, workers=0)
    assert fragment in str(error.value)
    assert "discretization.dilation" not in str(error.value) and "needle.step" not in str(error.value)


def test_the_default_quadrature_family_stays_within_the_largest_order():
    """A scenario at quadrature_order 10, its largest, made the default sweep's `quadrature 11`
    family: a traceback."""
    raw = tiny_raw()
    raw["discretization"]["quadrature_order"] = 10
    runs, _, _ = plan_runs(parse_scenario(raw))
    orders = {run.family: run.scenario.discretization.quadrature_order for run in runs}
    assert orders["quadrature 9"] == 9 and max(orders.values()) == 10


def test_quick_study_is_two_families_of_two_spacings_and_a_finer_reference():
    runs, reference, _ = plan_runs(parse_scenario(tiny_raw(SWEEP)), quick=True)
    assert len(runs) == 4 and {r.family for r in runs} == {"uniform", "graded x4"}
    assert reference.spacing < min(r.spacing for r in runs)


def test_a_quick_study_says_it_left_the_scenarios_study_block_aside():
    result = run_study(parse_scenario(tiny_raw(SWEEP)), quick=True)
    assert {run.family for run in result.runs} == {"uniform", "graded x4", "reference"}
    assert any(note.startswith("--quick: the scenario's study: block was not used") for note in result.notes)
    assert not any(note.startswith("--quick") for note in run_study(parse_scenario(tiny_raw()), quick=True).notes)


# --- the CLI on real files -------------------------------------------------------------------


@pytest.fixture(scope="module")
def studied(tmp_path_factory):
    folder = tmp_path_factory.mktemp("study")
    scenario = folder / "tiny.yaml"
    scenario.write_text(yaml.safe_dump(tiny_raw(SWEEP), sort_keys=False))
    result = CliRunner().invoke(app, ["study", str(scenario), "--out", str(folder / "out")])
    with open(folder / "out" / "study.csv") as handle:
        rows = list(csv.DictReader(handle))
    return folder, result, rows


def test_study_csv_has_every_column_and_one_row_per_run(studied):
    folder, result, rows = studied
    assert result.exit_code == 0, result.output
    assert list(rows[0]) == list(COLUMNS) and set(REQUIRED_COLUMNS) <= set(COLUMNS)
    assert len(rows) == 3 * 2 + 1 and rows[-1]["family"] == "reference"
    assert [r["family"] for r in rows[:-1]] == ["uniform"] * 2 + ["graded x2"] * 2 + ["quadratic, dilation 1.5"] * 2
    ok = [r for r in rows if r["status"] == "ok"]
    assert len(ok) == 5
    for row in ok:
        assert float(row["wall_seconds"]) > 0 and int(row["particles"]) > 0
        assert math.isfinite(float(row["exit_error_mm"]))
        assert float(row["deviation_mm"]) >= float(row["exit_deviation_mm"]) >= 0
    assert float(rows[-1]["deviation_mm"]) == 0.0  # the reference against itself
    assert any(float(r["deviation_mm"]) > 1e-4 for r in ok[:-1])  # coarser runs do differ
    assert sum(r["pareto"] == "true" for r in rows) >= 1 and rows[-1]["pareto"] == "false"
    assert "Pareto:" in result.output and "study: wrote" in result.output


def test_a_failing_configuration_is_recorded_with_its_reason(studied):
    _, _, rows = studied
    failed = [r for r in rows if r["status"] == "failed"]
    assert [r["family"] for r in failed] == ["quadratic, dilation 1.5"] * 2
    for row in failed:
        assert row["reason"].startswith("InputError: discretization: dilation 1.5 with spacing")
        assert "singular RK moment matrix" in row["reason"] and "basis order 2" in row["reason"]
        assert row["deviation_mm"] == "nan" and row["pareto"] == "false"


def test_study_json_records_provenance_and_outcome(studied):
    folder, result, rows = studied
    assert result.exit_code == 0, result.output
    record = json.loads((folder / "out" / "study.json").read_text())
    assert record["stitchplan_version"] == __version__ and record["command"][1] == "study"
    assert record["scenario"] == str(folder / "tiny.yaml")
    assert record["working_directory"] == os.getcwd()
    assert record["scenario_sha256"] == hashlib.sha256((folder / "tiny.yaml").read_bytes()).hexdigest()
    assert (record["runs"], record["ok"], record["failed"]) == (len(rows), 5, 2)
    assert record["reference"]["label"] == rows[-1]["label"]
    assert set(record["pareto"]) == {r["label"] for r in rows if r["pareto"] == "true"}
    assert record["linear_solver_backends"] == sorted({r["linear_solver_backend"] for r in rows if r["status"] == "ok"})
    # the sweep as run, its reference's needle step (the sweep's smallest)
    families = {}
    for r in rows:
        families.setdefault(r["family"], []).append(float(r["spacing_mm"]))
    assert record["families"] == families and record["reference"]["step_rad"] == float(rows[-1]["step_rad"])
    # where the runs ran, which their wall times depend on (the default: a local cluster)
    assert record["executor"].startswith("local Dask cluster of "), record["executor"]


def test_study_writes_the_speed_accuracy_png(studied):
    folder, _, _ = studied
    png = (folder / "out" / "speed_accuracy.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000
    assert not list((folder / "out").glob(".*"))  # no temporary files left behind


def test_study_without_a_needle_is_one_error_line_and_no_output(tmp_path, write_scenario):
    raw = tiny_raw()
    del raw["needle"]
    scenario = write_scenario(raw)
    result = CliRunner().invoke(app, ["study", str(scenario), "--out", str(tmp_path / "out")])
    assert result.exit_code == 2
    assert result.output.strip() == f"error: {scenario}: needle: missing, required by simulate, plan and study"
    assert not (tmp_path / "out").exists()


def test_a_study_whose_every_run_is_refused_by_its_choices_is_an_input_error(tmp_path, write_scenario):
    """Every run refused by its discretization (a quadratic basis on too narrow a kernel) was
    exit 1, "every run failed", naming no file: the study's choices are an input to mend, as
    `simulate` refuses them: exit 2, the file named, no output."""
    scenario = write_scenario(tiny_raw({"spacing": [6.0], "families": [{"name": "q2", "basis_order": 2,
                                                                         "dilation": 1.1}],
                                        "reference": {"spacing": 5.0, "basis_order": 2, "dilation": 1.1}}))
    result = CliRunner().invoke(app, ["study", str(scenario), "--out", str(tmp_path / "out"), "--workers", "0"])
    assert result.exit_code == 2, result.output
    (line,) = result.output.splitlines()
    assert line.startswith(f"error: {scenario}: study: every one of its 2 runs was refused by its choices, the "
                           "reference 'reference h=5 mm' as: discretization: dilation 1.1 with spacing 5 mm"), line
    assert line.endswith("; expected families and a reference whose choices make a model")
    assert not (tmp_path / "out").exists()


def test_a_study_whose_every_run_fails_is_a_numerical_failure(tmp_path, write_scenario):
    """Exit 1 as `simulate` gives for the same scene: the input was accepted, the method failed."""
    scenario = write_scenario(tiny_raw({"spacing": [6.0], "families": [{"name": "uniform"}],
                                        "reference": {"spacing": 5.0}}, friction=1e6))
    result = CliRunner().invoke(app, ["study", str(scenario), "--out", str(tmp_path / "out"), "--workers", "0"])
    assert result.exit_code == 1, result.output
    # each reason once, the reference's first, each with a run that failed so (the families'
    # were lost: only the reference's was said)
    assert result.output.startswith(f"error: {scenario}: study: every one of its 2 runs failed, 'reference h=5 mm' as: "
                                    "InsertionFailure: step 1"), result.output
    assert "'uniform h=6 mm' as: InsertionFailure: step 1" in result.output
    assert not (tmp_path / "out").exists()


# --- Pareto front and deviations ------------------------------------------------------------


def record(label: str, wall: float, deviation: float, status: str = "ok") -> StudyRun:
    run = StudyRun("f", label, None, 1.0, wall_seconds=wall, status=status)
    if status == "ok":
        run.deviations = {"deviation_mm": deviation}
    return run


def test_pareto_front_keeps_the_runs_nothing_beats_in_both_time_and_deviation():
    runs = [record("a", 1.0, 0.30), record("b", 2.0, 0.10), record("c", 3.0, 0.20), record("d", 4.0, 0.05),
            record("e", 0.5, math.nan, "failed"), record("f", 2.0, 0.10)]
    assert [r.label for r in pareto_front(runs)] == ["a", "b", "d"]


def test_exit_deviations_in_the_spatial_the_material_frame_and_of_the_error_vector():
    def fake(achieved_def, achieved, desired_def, steps=37):
        return SimpleNamespace(achieved_exit_def=np.array(achieved_def), achieved_exit=np.array(achieved),
                               desired_exit_def=np.array(desired_def), steps=[None] * steps)

    reference = fake([0.0, 10.0], [0.0, 10.5], [0.0, 9.5])
    run = fake([0.0, 10.03], [0.0, 10.4], [0.04, 9.5])
    deviation = exit_deviations(run, reference)
    assert deviation["exit_deviation_mm"] == pytest.approx(0.03)
    assert deviation["material_exit_deviation_mm"] == pytest.approx(0.1)
    assert deviation["exit_error_deviation_mm"] == pytest.approx(0.05)
    assert deviation["deviation_mm"] == pytest.approx(0.1) and deviation["spatial_compared"] is True
    # a run that ended a needle step earlier ends in another needle state: its spatial exit
    # is reported but not counted
    earlier = exit_deviations(fake([0.0, 10.3], [0.0, 10.52], [0.0, 9.78], steps=36), reference)
    assert earlier["exit_deviation_mm"] == pytest.approx(0.3) and earlier["spatial_compared"] is False
    assert earlier["deviation_mm"] == pytest.approx(0.02)


# --- graded particles --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def graded():
    from stitchplan.tissue.particles import graded_particles

    center, radius = np.array([0.0, 21.12]), 13.32  # SH 1/2 needle zone: 1.5 R about the centre
    return graded_particles((100.0, 100.0), 6.0, 1.5, center, radius), center, radius


def test_graded_particles_tile_the_slab_and_are_fine_in_the_needle_zone(graded):
    particles, center, radius = graded
    assert particles.volumes.sum() == pytest.approx(100.0 * 100.0, rel=1e-12)
    assert particles.cells[:, 2:].prod(axis=1).sum() == pytest.approx(1e4, rel=1e-12)
    assert particles.fine_spacing == pytest.approx(100 / 68) and particles.coarse_spacing == pytest.approx(100 / 17)
    cell_centres = particles.cells[:, :2] + 0.5 * particles.cells[:, 2:]
    in_zone = np.linalg.norm(cell_centres - center, axis=1) < radius
    assert np.allclose(particles.cells[in_zone, 2], particles.fine_spacing)
    far = np.linalg.norm(cell_centres - center, axis=1) > radius + 20.0
    assert np.allclose(particles.cells[far, 2], particles.coarse_spacing)
    assert len(particles.particles) < 0.2 * 69 * 69  # a uniform fine grid has 69^2 particles


def assert_balanced(cells: np.ndarray) -> None:
    """Leaves that touch (edge or corner) differ by at most a factor 2 in size (brute force)."""
    lo, hi = cells[:, :2], cells[:, :2] + cells[:, 2:]
    gap = np.maximum(lo[:, None] - hi[None], lo[None] - hi[:, None]).max(axis=2)  # <= 0: touching
    touching = gap <= 1e-9
    ratio = cells[:, 2][:, None] / cells[:, 2][None]
    assert ratio[touching].max() <= 2.0 + 1e-9


def test_graded_leaves_are_2_to_1_balanced(graded):
    assert_balanced(graded[0].cells)


def test_every_leaf_is_at_most_the_zones_spacing_plus_the_grading_times_its_distance():
    """graded_lattice's rule, by brute force over the leaves: a leaf's side is at most the
    zone's spacing plus `growth` x the distance from the zone to the nearest finest-cell
    centre inside the leaf (the finest cells are what it refines), and the leaves at the
    zone have its spacing."""
    from stitchplan.tissue.particles import RefinementZone, graded_lattice

    zone = RefinementZone(np.array([13.3, 21.7]), 2.0, 0.5)
    particles = graded_lattice((40.0, 40.0), 8.0, (zone,), growth=0.5)
    cells, finest = particles.cells, particles.fine_spacing
    low, side = cells[:, :2] + 0.5 * finest, cells[:, 2]
    nearest = np.clip(zone.center, low, cells[:, :2] + cells[:, 2:] - 0.5 * finest)  # finest-cell centre
    distance = np.maximum(np.linalg.norm(nearest - zone.center, axis=1) - zone.radius, 0.0)
    assert np.all(side <= (zone.spacing + 0.5 * distance) * (1.0 + 1e-9))
    assert side.min() == pytest.approx(0.5) and side.max() == pytest.approx(8.0)


def test_a_steep_grading_is_balanced_where_the_zone_alone_would_not_be():
    """A point zone off the lattice graded at 2 mm per mm asks for leaves four times the
    size of their neighbours; the balance splits them until touching leaves differ by 2x."""
    from stitchplan.tissue.particles import RefinementZone, graded_lattice

    zone = RefinementZone(np.array([5.3, 7.1]), 0.0, 0.25)
    particles = graded_lattice((16.0, 16.0), 4.0, (zone,), growth=2.0)
    assert particles.cells[:, 2].min() == pytest.approx(0.25) and particles.cells[:, 2].max() == pytest.approx(4.0)
    assert_balanced(particles.cells)


def test_rk_functions_on_the_graded_set_reproduce_linear_fields(graded, rng):
    """Partition of unity and linear reproduction to round-off, with each particle's support
    the dilation times its local spacing (eq. 3.20)."""
    from stitchplan.tissue.shape_functions import rk_shape_functions

    particles = graded[0]
    support = 2.0 * particles.local_spacing
    points = rng.uniform([0.0, 0.0], [100.0, 100.0], size=(400, 2))
    shape = rk_shape_functions(points, particles.particles, support, particles.volumes, 1, True)
    field = 0.3 + 0.02 * particles.particles[:, 0] - 0.05 * particles.particles[:, 1]
    np.testing.assert_allclose(shape.values.sum(axis=1).A1, 1.0, atol=1e-12)
    np.testing.assert_allclose(shape.values @ field, 0.3 + 0.02 * points[:, 0] - 0.05 * points[:, 1], atol=1e-11)
    np.testing.assert_allclose(shape.grad_x @ field, 0.02, atol=1e-11)
    np.testing.assert_allclose(shape.grad_y @ field, -0.05, atol=1e-11)


def test_a_steeper_needle_grading_coarsens_sooner_and_keeps_the_needle_zone(graded):
    """discretization.needle_grading: the leaf side may grow by that many mm per mm beyond the
    needle zone (0.5 by default, the fixture's); at 1.0 the zone's leaves are the same, a leaf
    beyond it is never finer than at 0.5, and the slab, still tiled, holds fewer particles."""
    from stitchplan.tissue.particles import graded_particles

    default, center, radius = graded
    steep = graded_particles((100.0, 100.0), 6.0, 1.5, center, radius, 1.0)
    assert steep.cells[:, 2:].prod(axis=1).sum() == pytest.approx(1e4, rel=1e-12)
    assert len(steep.particles) < len(default.particles)  # 538 against 603

    def side_at(particles, points):  # the leaf side holding each point
        cells = particles.cells
        inside = ((points[:, None, :] >= cells[None, :, :2]) & (points[:, None, :] < cells[None, :, :2] + cells[None, :, 2:])).all(axis=2)
        return cells[inside.argmax(axis=1), 2]

    points = np.stack(np.meshgrid(np.linspace(0.5, 99.5, 60), np.linspace(0.5, 99.5, 60)), axis=-1).reshape(-1, 2)
    zone = np.linalg.norm(points - center, axis=1) < radius
    np.testing.assert_allclose(side_at(steep, points[zone]), side_at(default, points[zone]))
    assert np.all(side_at(steep, points) >= side_at(default, points) - 1e-12)


def test_needle_spacing_without_a_needle_is_refused():
    from stitchplan.tissue.model import model_for_scenario

    raw = tiny_raw()
    del raw["needle"]
    raw["discretization"]["needle_spacing"] = 2.0
    with pytest.raises(ScenarioError, match="discretization.needle_spacing: needs a needle"):
        model_for_scenario(parse_scenario(raw))


@pytest.mark.parametrize("block, fragment", [
    ({"spacing": 4.0, "needle_spacing": 5.0}, "discretization.needle_spacing: got 5.0, expected a spacing (mm) no larger than spacing = 4 mm"),
    ({"accuracy": 0.0}, "discretization.accuracy: got 0.0, expected a number >= 0.001 (mm, exit point"),
    ({"needle_refinement": 0.5}, "discretization.needle_refinement: got 0.5, expected a number >= 1"),
    ({"needle_grading": 0}, "discretization.needle_grading: got 0, expected a positive number (mm per mm)"),
    # two ways to one value: the one not taken would be dropped without a word
    ({"spacing": 4.0, "needle_spacing": 1.0, "needle_refinement": 2},
     "discretization.needle_spacing: got 1.0, expected either needle_spacing or needle_refinement "
     "(needle_refinement 2 sets needle_spacing = spacing / 2 = 2 mm)"),
    ({"accuracy": 0.5, "spacing": 6.0}, "discretization.spacing: got 6.0, expected no spacing with accuracy "
                                        "0.5 mm (the auto discretization chooses the spacings"),
    ({"accuracy": 0.5, "needle_refinement": 3}, "discretization.needle_refinement: got 3"),
])
def test_bad_graded_and_accuracy_fields_are_refused(block, fragment):
    raw = tiny_raw()
    raw["discretization"] = block
    with pytest.raises(ScenarioError) as error:
        parse_scenario(raw)
    assert fragment in str(error.value)


# --- the auto discretization ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def auto_choice():
    from stitchplan.study.auto import choose_discretization

    return choose_discretization(parse_scenario(tiny_raw(step=0.2)), accuracy=0.05)


def test_auto_discretization_meets_its_accuracy_against_a_finer_run(auto_choice):
    from stitchplan.needle.insertion import run_insertion
    from stitchplan.study.sweep import configure

    assert auto_choice.estimate_mm <= 0.05 and auto_choice.verified
    chosen = auto_choice.discretization
    assert chosen.needle_spacing == auto_choice.needle_spacing and chosen.accuracy is None
    finer = run_insertion(configure(auto_choice.scenario, StudyFamily("finer", grading=2),
                                    chosen.needle_spacing / 3))
    assert exit_deviations(auto_choice.result, finer)["deviation_mm"] <= 0.05
    # the estimate rests on the last two resolutions of the ladder, both run
    resolutions = [t for t in auto_choice.trials if t.family == "resolution" and t.status == "ok"]
    assert len(resolutions) >= 2


def test_auto_discretization_reports_its_estimate_and_choices(auto_choice):
    message = auto_choice.message
    assert message.startswith("auto discretization: accuracy 0.05 mm on the exit point; chose graded")
    assert f"estimated error {auto_choice.estimate_mm:.3g} mm (runs at needle spacing" in message
    assert "order 1 assumed; meets the target" in message
    assert auto_choice.tip_tracking in ("auto", "levenberg-marquardt")
    assert auto_choice.linear_solver in ("direct", "minres")
    assert f"tip tracking {auto_choice.tip_tracking} (" in message
    assert f"linear solver {auto_choice.linear_solver} (" in message
    # every trial is recorded, the chosen run among them
    assert auto_choice.result is next(t.result for t in auto_choice.trials if t.family == "chosen")


def test_an_accuracy_is_resolved_once_before_the_run():
    from stitchplan.errors import InputError
    from stitchplan.needle.insertion import run_insertion
    from stitchplan.study.auto import resolve_accuracy

    scenario = parse_scenario({**tiny_raw(step=0.2), "discretization": {"accuracy": 0.2}})
    with pytest.raises(InputError, match="discretization.accuracy: got an accuracy target"):
        run_insertion(scenario)  # the run itself never starts a selection
    resolved, note = resolve_accuracy(scenario)
    assert note.kind.value == "auto-discretization"
    assert note.message.startswith("auto discretization: accuracy 0.2 mm")
    assert resolved.discretization.accuracy is None
    first, second = run_insertion(resolved), run_insertion(resolved)
    assert first.model.n_particles == second.model.n_particles
    assert first.exit_error_mm == second.exit_error_mm
    # an explicit spacing switches the auto discretization off
    assert with_discretization(scenario, spacing=5.0).discretization.accuracy is None


def test_a_plan_on_an_auto_discretization_says_how_to_reproduce_its_verification(tmp_path):
    """`--spacing` replaces an auto discretization by the scene's default one, so the summary
    gives the refined model as a `discretization` block and the needle methods the auto
    discretization chose: with them in the file, simulate --center-path replays the
    trajectory on the same particles to the same exit."""
    raw = {**tiny_raw(step=0.2), "discretization": {"accuracy": 0.2}}
    (tmp_path / "auto.yaml").write_text(yaml.safe_dump(raw))
    result = CliRunner().invoke(app, ["plan", str(tmp_path / "auto.yaml"), "--no-compare", "-q", "--export",
                                      str(tmp_path / "trajectory.csv"), "--summary", str(tmp_path / "plan.json")])
    assert result.exit_code == 0, result.output
    verification = json.loads((tmp_path / "plan.json").read_text())["verification"]
    keys = verification["scenario_keys"]
    assert keys["discretization"]["spacing"] == verification["spacing_mm"]
    refined = {**raw, "discretization": keys["discretization"], "needle": {**raw["needle"], **keys["needle"]}}
    (tmp_path / "refined.yaml").write_text(yaml.safe_dump(refined))
    result = CliRunner().invoke(app, ["simulate", str(tmp_path / "refined.yaml"), "--no-estimate", "-q",
                                      "--center-path", str(tmp_path / "trajectory.csv"),
                                      "--summary", str(tmp_path / "replay.json")])
    assert result.exit_code == 0, result.output
    replay = json.loads((tmp_path / "replay.json").read_text())
    assert replay["particles"] == verification["discretization"]["particles"]
    # a later verification round's replay starts its steps from the round before's (run_insertion
    # start_from): the same equilibria to within the Newton tolerance, not always to the bit
    np.testing.assert_allclose(replay["achieved_exit_def"], verification["achieved_exit_def"], rtol=0, atol=1e-4)


@pytest.mark.parametrize("reference", [10.0, 5.0])
def test_a_reference_not_finer_than_the_sweep_is_refused(reference):
    """The runs' deviations are measured from the reference: one coarser than (or as coarse
    as) a swept spacing would rank the runs against a worse answer."""
    scenario = parse_scenario(tiny_raw({"spacing": [6.0, 5.0], "families": [{"name": "uniform"}],
                                        "reference": {"spacing": reference}}))
    with pytest.raises(ScenarioError, match=rf"study.reference.spacing: got {reference:g} mm, expected less "
                                            r"than the finest spacing of the sweep, 5 mm"):
        plan_runs(scenario)


@pytest.mark.parametrize("study, discretization", [
    ({"spacing": [0.00009]}, {}),  # its half rounded to 4 decimals was 0: a traceback
    ({"spacing": [0.0001]}, {}),  # its half rounded up to it: refused as a reference the user never gave
    ({}, {"spacing": 0.004}),  # the default spacings to 3 decimals: 0.006, 0.005, 0.005, 0.004, 0.003, 0.003
])
def test_the_default_spacings_and_reference_stay_apart_and_positive_at_small_spacings(study, discretization):
    raw = tiny_raw(study)
    raw["discretization"].update(discretization)
    runs, reference, _ = plan_runs(parse_scenario(raw))
    spacings = [run.spacing for run in runs if run.family == runs[0].family]
    assert len(set(spacings)) == len(spacings) and min(spacings) > 0
    assert 0 < reference.spacing < min(run.spacing for run in runs)


def test_the_default_spacings_keep_their_three_decimals():
    runs, reference, _ = plan_runs(parse_scenario(tiny_raw()))
    assert sorted({run.spacing for run in runs}) == [3.5, 4.25, 5.0, 5.75, 6.75, 8.0]
    assert reference.spacing == 1.75


def test_a_default_reference_no_finer_than_the_sweep_is_not_named_as_the_users():
    with pytest.raises(ScenarioError, match=r"^the study's default reference spacing: got 4\.94066e-324 mm, "
                                            r"expected less than the finest spacing"):
        plan_runs(parse_scenario(tiny_raw({"spacing": [5e-324]})))


@pytest.mark.parametrize("direct_seconds, minres_seconds, chosen", [(1.0, 0.5, "minres"), (1.0, 0.9, "direct"),
                                                                    (1.0, 1.5, "direct")])
def test_the_auto_discretization_takes_minres_only_when_it_is_a_fifth_faster(direct_seconds, minres_seconds,
                                                                            chosen):
    """choose_linear_solver on two agreeing runs without fallbacks: MINRES where it takes at
    most 0.8 x the direct solve's time, the direct solve otherwise."""
    from stitchplan.study.auto import choose_linear_solver

    def run(seconds: float) -> SimpleNamespace:
        exit_point = np.array([30.0, 2.0])
        result = SimpleNamespace(events=[], steps=[0] * 10, achieved_exit_def=exit_point, achieved_exit=exit_point,
                                 desired_exit_def=exit_point)
        return SimpleNamespace(ok=True, reason="", result=result, wall_seconds=seconds)

    runs = {"direct": run(direct_seconds), "minres": run(minres_seconds)}
    trials = SimpleNamespace(run=lambda purpose, h, tracking, solver: runs[solver])
    assert choose_linear_solver(trials, 2.0, "levenberg-marquardt", 0.05)[0] == chosen
