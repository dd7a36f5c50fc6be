"""The study's Pareto front is one set of runs: the runs flagged `pareto` (found on
`deviation_mm`) are the ones study.csv and study.json list and the ones
speed_accuracy.png rings, on both of its panels, under a single legend entry.

The right panel plots the spatial exit deviation alone, whose own front can hold other
runs (a run that exits a needle step early has a large spatial deviation that
`deviation_mm` does not count); ringing that front there as "the Pareto front" put two
different sets under one name. The studies here are made by hand (no insertions run).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from stitchplan.config.scenario import load_scenario
from stitchplan.io import plots
from stitchplan.io.study_reports import COLUMNS, study_record, study_row
from stitchplan.study.sweep import StudyResult, StudyRun, compared_run, pareto_front

SCENARIO = Path(__file__).resolve().parents[1] / "configs" / "sh12_100x30.yaml"

# family, spacing, wall time (s), deviation_mm, spatial exit deviation (mm): the shape of
# sh12_100x30 swept at 6, 4.5 and 3 mm, where the coarse runs exit a step early, so their
# spatial deviation is large but not counted in deviation_mm.
SWEPT = [("uniform", 6.0, 0.46, 0.023, 0.227), ("uniform", 4.5, 0.69, 0.041, 0.182),
         ("uniform", 3.0, 0.76, 0.062, 0.062), ("minres", 6.0, 0.98, 0.023, 0.227),
         ("minres", 4.5, 0.94, 0.041, 0.183)]


def study_run(scenario, family, spacing, seconds, deviation, spatial, status="ok") -> StudyRun:
    run = StudyRun(family=family, label=f"{family} h={spacing:g} mm", scenario=scenario, spacing=spacing,
                   particles=int(600 / spacing), wall_seconds=seconds, status=status)
    if status != "ok":
        run.reason = "InsertionFailure: made by hand"
    else:
        run.deviations = {"deviation_mm": deviation, "exit_deviation_mm": spatial,
                          "material_exit_deviation_mm": deviation, "exit_error_deviation_mm": deviation / 2}
    return run


def made_study(reference_failed: bool = False) -> StudyResult:
    """A study as run_study leaves it: deviations measured, the front flagged. With the
    reference failed, the finest successful run stands in for it (deviation 0) and is
    kept out of the front, as run_study does."""
    scenario = load_scenario(SCENARIO)
    runs = [study_run(scenario, *row) for row in SWEPT]
    reference = study_run(scenario, "reference", 1.5, 0.34, 0.0, 0.0, "failed" if reference_failed else "ok")
    notes: list[str] = []
    compared = compared_run(runs, reference, notes)
    if reference_failed:
        assert compared is runs[2] and "finest successful run, uniform h=3 mm" in notes[0]
        compared.deviations = {key: 0.0 for key in compared.deviations}
    for run in pareto_front([r for r in runs if r is not compared]):
        run.pareto = True
    return StudyResult(scenario=scenario, runs=[*runs, reference], reference=compared)


def ringed_points(ax) -> set[tuple[float, float]]:
    """(deviation, wall time) of the markers drawn as open rings on the panel."""
    return {(float(x), float(y)) for line in ax.get_lines()
            if line.get_marker() == "o" and str(line.get_markerfacecolor()) == "none"
            for x, y in zip(line.get_xdata(), line.get_ydata())}


def panel_points(runs, key: str) -> set[tuple[float, float]]:
    return {(run.deviations[key], run.wall_seconds) for run in runs}


@pytest.fixture(params=[False, True], ids=["reference ok", "reference failed"])
def study(request) -> StudyResult:
    return made_study(reference_failed=request.param)


def test_the_spatial_panel_has_a_front_of_its_own_that_differs():
    """The premise of the other tests: a front found on the right panel's measure would
    ring other runs than the study's."""
    runs = made_study().runs[:-1]
    by_spatial = {r.label for r in runs if r.deviations["exit_deviation_mm"] <= min(
        o.deviations["exit_deviation_mm"] for o in runs if o.wall_seconds <= r.wall_seconds)}
    assert {r.label for r in runs if r.pareto} == {"uniform h=6 mm"}
    assert by_spatial == {"uniform h=6 mm", "uniform h=4.5 mm", "uniform h=3 mm"}


def test_both_panels_ring_exactly_the_runs_study_csv_and_study_json_call_the_front(study, tmp_path):
    fig = plots.plot_speed_accuracy(tmp_path / "speed.png", study)
    left, right = fig.axes[:2]
    csv_front = {run.label for run in study.runs
                 if dict(zip(COLUMNS, study_row(run)))["pareto"] == "true"}
    json_front = study_record(study, provenance={})["pareto"]
    front = [run for run in study.runs if run.label in csv_front]
    assert set(json_front) == csv_front == {"uniform h=6 mm"}
    assert ringed_points(left) == panel_points(front, "deviation_mm")
    assert ringed_points(right) == panel_points(front, "exit_deviation_mm")


def test_the_legend_names_one_pareto_front_and_says_what_it_is_found_on(study, tmp_path):
    fig = plots.plot_speed_accuracy(tmp_path / "speed.png", study)
    entries = [text.get_text() for legend in fig.legends for text in legend.get_texts()]
    pareto_entries = [entry for entry in entries if "pareto" in entry.lower()]
    assert pareto_entries == [plots.PARETO_LABEL] and "deviation_mm" in plots.PARETO_LABEL
    for ax in fig.axes[:2]:
        assert [line.get_label() for line in ax.get_lines()
                if "pareto" in line.get_label().lower()] == [plots.PARETO_LABEL]


def test_a_study_without_a_front_rings_nothing_and_claims_none(tmp_path):
    study = made_study()
    for run in study.runs:
        run.pareto = False
    fig = plots.plot_speed_accuracy(tmp_path / "speed.png", study)
    assert all(not ringed_points(ax) for ax in fig.axes[:2])
    entries = [text.get_text() for legend in fig.legends for text in legend.get_texts()]
    assert not any("pareto" in entry.lower() for entry in entries)


def test_the_spatial_panel_squares_the_runs_of_another_number_of_needle_steps(tmp_path):
    """A run that took another number of needle steps than the finest run (it exits a step
    early, or the reference takes a smaller step) has a spatial exit deviation of another
    needle state, which deviation_mm leaves out: the right panel draws it squared, and says
    why in the legend; the left panel does not."""
    study = made_study()
    apart = [run for run in study.runs[:-1] if run.spacing > 3.0]  # SWEPT's coarse runs: a step early
    for run in apart:
        run.deviations["spatial_compared"] = False
    fig = plots.plot_speed_accuracy(tmp_path / "speed.png", study)
    left, right = fig.axes[:2]

    def squared(ax):
        return {(float(x), float(y)) for line in ax.get_lines() if line.get_marker() == "s"
                for x, y in zip(line.get_xdata(), line.get_ydata())}

    assert squared(right) == panel_points(apart, "exit_deviation_mm") and not squared(left)
    entries = [text.get_text() for legend in fig.legends for text in legend.get_texts()]
    assert plots.SPATIAL_APART_LABEL in entries
