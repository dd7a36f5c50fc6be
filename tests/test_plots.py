"""The figures tell the truth: every plot function runs on a small input, writes a PNG and
returns its figure, which these tests read back: the key figure in the title, one colour
scale per figure, units on the axes, legends below the data, the tissue, clamps, loads and
probes where they are, and each run's exit error next to its own desired exit."""

from __future__ import annotations

import math
import re
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from typer.testing import CliRunner

from stitchplan.cli import app
from stitchplan.config.scenario import parse_scenario
from stitchplan.io import calibration_plots, needle_plots, plots

REPOSITORY = Path(__file__).resolve().parents[1]
PNG = b"\x89PNG\r\n\x1a\n"
MATERIAL = {"lame_lambda": 0.189151, "lame_mu": 0.147688}


def is_png(path: Path) -> bool:
    return path.read_bytes()[:8] == PNG


def colour_bars(fig) -> list:
    return [ax for ax in fig.axes if hasattr(ax, "_colorbar")]


def data_axes(fig) -> list:
    return [ax for ax in fig.axes if not hasattr(ax, "_colorbar") and ax.axison]


UNIT = re.compile(r"\((mm|mm²|s|N|MPa|rad|N/mm)\)")


def has_unit(label: str) -> bool:
    """A unit in brackets: x (mm), wall time (s), ..."""
    return UNIT.search(label) is not None


def shows_y_values(ax) -> bool:
    return ax.yaxis.get_tick_params().get("labelleft", True)


def title_of(fig) -> str:
    return " ".join([fig._suptitle.get_text() if fig._suptitle else ""] + [ax.get_title() for ax in fig.axes])


def assert_readable(fig, colour_bar_count: int = 1) -> None:
    """Units on every axis and colour bar, the number of colour bars, legends below the data."""
    assert len(colour_bars(fig)) == colour_bar_count
    for ax in data_axes(fig):
        assert has_unit(ax.get_xlabel()), ax.get_xlabel()
        assert has_unit(ax.get_ylabel()) or not shows_y_values(ax), ax.get_ylabel()  # panels sharing y
    for bar in colour_bars(fig):
        assert has_unit(bar.get_ylabel()), bar.get_ylabel()
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)  # the saved figure is closed: a canvas to measure it on
    canvas.draw()
    renderer = canvas.get_renderer()
    bottom = min(ax.get_window_extent(renderer).y0 for ax in data_axes(fig))
    for legend in fig.legends:
        assert legend.get_window_extent(renderer).y1 <= bottom + 1.0  # below every axes box


def marker_at(ax, point, tolerance: float = 1e-9) -> bool:
    """A line of `ax` has a vertex at `point`."""
    return any(np.min(np.linalg.norm(line.get_xydata() - np.asarray(point), axis=1)) <= tolerance
               for line in ax.get_lines() if len(line.get_xydata()))


# --- deform ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def deformed():
    from stitchplan.tissue.deform import run_deform

    raw = {"name": "small-slab", "tissue": {"size": [40.0, 20.0], "thickness": 10.0, "clamped": ["right"],
                                           "material": MATERIAL},
           "discretization": {"spacing": 4.0}, "load_steps": 2,
           "loads": [{"segment": [[0.0, 6.0], [0.0, 14.0]], "force": [-1.0, 0.5]}],
           "probes": [[0.0, 10.0], [20.0, 10.0]]}
    return run_deform(parse_scenario(raw))


def test_deformed_plot_draws_outline_clamps_loads_and_probes_at_the_chosen_scale(deformed, tmp_path):
    scale = 3.0
    fig = plots.plot_deformed(tmp_path / "deformed.png", deformed, scale=scale)
    assert is_png(tmp_path / "deformed.png")
    assert_readable(fig)
    ax = data_axes(fig)[0]
    title = ax.get_title()
    largest = np.linalg.norm(deformed.particle_displacements, axis=1).max()
    assert "small-slab" in title and f"{largest:.3g} mm" in title and "3x enlarged" in title
    # the deformed outline runs through particles moved by 3 u, and the clamped edge stays put
    moved = deformed.model.particles + scale * deformed.particle_displacements
    outline = next(line for line in ax.get_lines() if line.get_label() == "tissue outline, deformed")
    vertices = outline.get_xydata()
    assert len(vertices) >= 4
    assert np.max(np.min(np.linalg.norm(vertices[:, None] - moved[None], axis=2), axis=1)) < 1e-9
    assert np.all(np.abs(vertices[np.isclose(vertices[:, 0], 40.0), 0] - 40.0) < 1e-12)
    labels = [handle_label for handle_label in ax.get_legend_handles_labels()[1]]
    assert {"clamped edge", "load: force (N, total)", "probe at rest", "probe, displaced"} <= set(labels)
    displaced = deformed.probes + scale * deformed.probe_displacements
    assert all(marker_at(ax, point) for point in displaced)
    assert any("F1 = (-1, 0.5) N" in text.get_text() for text in ax.texts)


def test_probe_numbers_round_a_small_hole_are_set_off_away_from_each_other(tmp_path):
    """hole_near_stitch's four probes round a 2.5 mm hole had every number set up and right of
    its probe: P2's and P3's fell on the other probes' circles. Crowded probes now set theirs
    off away from their neighbours (P1 above, P2 below, P3 left, P4 right), and a probe with
    none near keeps its number up and right."""
    import matplotlib.pyplot as plt

    from stitchplan.io.plot_elements import draw_probes

    probes = np.array([[21.12, 19.0], [21.12, 14.0], [18.62, 16.5], [23.62, 16.5], [60.0, 15.0]])
    fig, ax = plt.subplots()
    draw_probes(ax, probes, probes + 0.1, size=60.0)
    offsets = {text.get_text(): np.array(text.xyann) for text in ax.texts}
    plt.close(fig)
    assert offsets["P1"][1] > 0 and abs(offsets["P1"][0]) < 1e-9
    assert offsets["P2"][1] < 0 and abs(offsets["P2"][0]) < 1e-9
    assert offsets["P3"][0] < 0 and abs(offsets["P3"][1]) < 1e-9
    assert offsets["P4"][0] > 0 and abs(offsets["P4"][1]) < 1e-9
    assert offsets["P5"][0] > 0 and offsets["P5"][1] > 0 and np.isclose(*offsets["P5"])


def test_exit_zoom_outline_is_the_rk_interpolant_recovered_from_particle_displacements(deformed):
    """The zooms draw the tissue edge with u(X) rebuilt from u(X_I) (insertion results keep
    particle displacements only): at the probes it must equal deform's own interpolant."""
    interpolant = needle_plots._interpolant(deformed.model, deformed.particle_displacements)
    assert np.allclose(interpolant(deformed.probes), deformed.probe_displacements, rtol=0.0, atol=1e-12)


def test_deformed_plot_at_true_scale_says_nothing_about_enlargement(deformed, tmp_path):
    fig = plots.plot_deformed(tmp_path / "deformed.png", deformed)
    assert "enlarged" not in data_axes(fig)[0].get_title()


def test_deform_plot_scale_option(slab_path, tmp_path):
    runner = CliRunner()
    bad = runner.invoke(app, ["deform", str(slab_path), "--plot", str(tmp_path / "bad.png"), "--plot-scale", "0"])
    assert bad.exit_code == 2
    assert "--plot-scale" in bad.output and "got 0.0" in bad.output
    assert not (tmp_path / "bad.png").exists()
    good = runner.invoke(app, ["deform", str(slab_path), "--plot", str(tmp_path / "d.png"), "--plot-scale", "5"])
    assert good.exit_code == 0, good.output
    assert is_png(tmp_path / "d.png")
    # without a --plot to draw it in, the scale would be dropped without a word
    alone = runner.invoke(app, ["deform", str(slab_path), "--summary", str(tmp_path / "s.json"), "--plot-scale", "5"])
    assert alone.exit_code == 2
    assert alone.stderr.strip() == ("error: --plot-scale: got 5 without --plot, expected it with the --plot PNG it "
                                    "enlarges the displacements in")
    assert not (tmp_path / "s.json").exists()


# --- needle insertion and plan --------------------------------------------------------------


@pytest.fixture(scope="module")
def plan_result():
    from stitchplan.planning.planner import run_plan

    raw = {"name": "tiny-needle",
           "tissue": {"size": [30.0, 24.0], "thickness": 10.0, "clamped": ["right"],
                      "material": MATERIAL},
           "discretization": {"spacing": 4.0},
           "needle": {"radius": 6.0, "entry": [0.0, 16.0], "turn": "cw", "step": 0.3,
                      "friction": 0.0602, "cutting_force": 0.7}}
    return run_plan(parse_scenario(raw), compare=True)


def test_insertion_plot_shares_one_colour_scale_and_zooms_on_the_exit(plan_result, tmp_path):
    run = plan_result.unplanned
    fig = needle_plots.plot_insertion(tmp_path / "insertion.png", run, [2, 5, len(run.steps)])
    assert is_png(tmp_path / "insertion.png")
    assert_readable(fig)
    assert "tiny-needle" in fig._suptitle.get_text()
    assert f"exit error {run.exit_error_mm:.3g} mm" in fig._suptitle.get_text()
    norms = {(c.norm.vmin, c.norm.vmax) for ax in data_axes(fig) for c in ax.collections if c.get_array() is not None}
    largest = max(np.linalg.norm(run.displacements[s], axis=1).max() for s in (2, 5, len(run.steps)))
    assert len(norms) == 1  # one colour scale for every panel, the zoom included
    assert next(iter(norms)) == (0.0, pytest.approx(largest))
    zoom = data_axes(fig)[-1]
    achieved = np.asarray(run.achieved_exit_def) - run.desired_exit_def
    (x0, x1), (y0, y1) = zoom.get_xlim(), zoom.get_ylim()
    assert x0 < 0 < x1 and y0 < 0 < y1 and x0 < achieved[0] < x1 and y0 < achieved[1] < y1
    assert x1 - x0 < 3 * run.exit_error_mm + 0.01  # sized to the error, so the error shows


def test_insertion_plot_draws_steps_past_the_runs_end_once(plan_result, tmp_path):
    """Steps the run did not reach draw its last step, one panel for all of them."""
    run = plan_result.unplanned
    last = len(run.steps)
    fig = needle_plots.plot_insertion(tmp_path / "insertion.png", run, [2, last + 1, last + 2])
    titles = [ax.get_title() for ax in data_axes(fig)[:-1]]  # the step panels, the zoom last
    assert titles == [f"step 2 of {last}, needle rotated {run.steps[1].rotation:.2f} rad",
                      f"step {last} of {last}, needle rotated {run.steps[-1].rotation:.2f} rad"]


def test_insertion_plot_names_the_exits_markers_where_no_step_panel_draws_them(plan_result, tmp_path):
    """The exits are drawn in the last step's panel and the zoom: without the last step the
    zoom's markers give the legend its entries."""
    run = plan_result.unplanned
    for steps in ([2], [2, len(run.steps)]):
        fig = needle_plots.plot_insertion(tmp_path / "insertion.png", run, steps)
        entries = [text.get_text() for legend in fig.legends for text in legend.get_texts()]
        assert entries.count("desired exit, deformed") == 1 and entries.count("achieved exit") == 1, entries


def test_plan_plot_marks_each_runs_error_at_its_own_desired_exit(plan_result, tmp_path):
    fig = needle_plots.plot_plan(tmp_path / "plan.png", plan_result)
    assert is_png(tmp_path / "plan.png")
    assert_readable(fig)
    planned, unplanned = plan_result.planned, plan_result.unplanned
    headline = fig._suptitle.get_text()
    assert "tiny-needle" in headline
    assert f"{planned.exit_error_mm:.3g} mm planned" in headline
    assert f"{unplanned.exit_error_mm:.3g} mm unplanned" in headline
    main, zoom_planned, zoom_unplanned, trajectory = data_axes(fig)
    for run, who in ((planned, "planned"), (unplanned, "unplanned")):
        assert marker_at(main, run.desired_exit_def) and marker_at(main, run.achieved_exit_def)
        note = next(t for t in main.texts if t.get_text().startswith(who))
        assert f"{run.exit_error_mm:.3g} mm" in note.get_text()
        assert np.allclose(note.xy, run.desired_exit_def)
    for zoom, run in ((zoom_planned, planned), (zoom_unplanned, unplanned)):
        width = np.diff(zoom.get_xlim())[0]
        assert run.exit_error_mm < width < 3 * run.exit_error_mm + 0.01
        assert marker_at(zoom, np.asarray(run.achieved_exit_def) - run.desired_exit_def)
    assert "O(t)" in trajectory.get_title()


def test_plan_plot_draws_the_centre_trajectory_in_colours_no_run_has(plan_result, tmp_path):
    """O_y(t) was drawn in matplotlib's default orange, beside the unplanned run's dark orange
    in the one legend under all panels: its curve read as the unplanned run's."""
    from matplotlib.colors import to_rgb

    fig = needle_plots.plot_plan(tmp_path / "plan.png", plan_result)
    main, *_, trajectory = data_axes(fig)
    runs = {to_rgb(line.get_color()) for line in main.get_lines() if "tip path" in line.get_label()}
    assert len(runs) == 2
    for curve in trajectory.get_lines():
        for run in runs:
            assert np.linalg.norm(np.subtract(to_rgb(curve.get_color()), run)) > 0.3, curve.get_label()


def test_plan_plot_says_when_the_plan_was_aimed_for_the_refined_model(plan_result, tmp_path):
    """A plan re-aimed by the refined model's offset misses on its own model on purpose: the
    headline says so, beside its planned exit error; a plan not aimed so says nothing."""
    from dataclasses import replace

    from stitchplan.planning.verification import Verification

    for aimed_by, said in (("predicted offset", True), ("refined offset", True), ("none", False)):
        verified = replace(plan_result, verification=Verification(2.0, None, [], aimed_by=aimed_by))
        headline = needle_plots.plot_plan(tmp_path / "plan.png", verified)._suptitle.get_text()
        assert ("(aimed for the refined model)" in headline) is said, aimed_by
        assert f"{plan_result.planned.exit_error_mm:.3g} mm planned" in headline


def test_plan_plot_gives_both_runs_bites_across_a_wound(plan_result, tmp_path):
    """Across a wound the surgeon judges a stitch by its bites: the headline gives the
    planned and the unplanned run's (entry / exit side); a stitch across none gives none."""
    from dataclasses import replace

    bites = {"entry_side_mm": 6.8921, "exit_side_mm": 6.8824, "difference_mm": -0.0097}
    unplanned = {"entry_side_mm": 6.877, "exit_side_mm": 6.2515, "difference_mm": -0.6255}
    across = replace(plan_result, planned=replace(plan_result.planned, bites=bites),
                     unplanned=replace(plan_result.unplanned, bites=unplanned))
    headline = needle_plots.plot_plan(tmp_path / "plan.png", across)._suptitle.get_text()
    assert "bites (entry / exit side) 6.892 / 6.882 mm planned vs 6.877 / 6.252 mm unplanned" in headline
    assert "bites" not in needle_plots.plot_plan(tmp_path / "plan.png", plan_result)._suptitle.get_text()


def test_plan_plot_keeps_both_error_labels_inside_the_panel_at_a_top_edge_exit(tmp_path):
    """An exit on a top or bottom edge: side by side the two labels would need more width than
    the panel has (the unplanned one was cut by the colour bar); each leans to its own side,
    the second one row further out, and both lie inside the tissue panel."""
    from stitchplan.planning.planner import run_plan

    raw = {"name": "top-edge-stitch",
           "tissue": {"size": [30.0, 16.0], "thickness": 10.0, "clamped": ["bottom"], "material": MATERIAL},
           "discretization": {"spacing": 4.0},
           "needle": {"radius": 6.0, "entry": [20.0, 16.0], "turn": "cw", "step": 0.3,
                      "friction": 0.0602, "cutting_force": 0.7}}
    result = run_plan(parse_scenario(raw), compare=True)
    fig = needle_plots.plot_plan(tmp_path / "plan.png", result)
    main = data_axes(fig)[0]
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)  # the saved figure's canvas is closed
    canvas.draw()
    renderer = canvas.get_renderer()
    panel = main.get_window_extent(renderer)
    notes = [t for t in main.texts if "exit error" in t.get_text()]
    assert len(notes) == 2
    for note in notes:
        box = note.get_bbox_patch().get_window_extent(renderer)
        assert panel.x0 <= box.x0 and box.x1 <= panel.x1 and panel.y0 <= box.y0 and box.y1 <= panel.y1, \
            (note.get_text(), box, panel)


# --- calibration ----------------------------------------------------------------------------


def test_cost_surface_names_the_fit_and_keeps_white_marks_visible_in_the_legend(tmp_path):
    lam, mu = np.geomspace(0.01, 2.0, 4), np.geomspace(0.01, 2.0, 4)
    cost = np.add.outer(np.log(lam / 0.2) ** 2, np.log(mu / 0.15) ** 2) + 0.5
    cost[0, 0] = np.nan
    fig = calibration_plots.plot_cost_surface(tmp_path / "cost.png", lam, mu, cost, (0.19, 0.17), (0.2, 0.15),
                                  np.array([[0.19, 0.17], [0.2, 0.15]]), name="calib",
                                  residual=(0.057, 0.027), uncertainty=(0.013, None))
    assert is_png(tmp_path / "cost.png")
    assert_readable(fig)
    title = data_axes(fig)[0].get_title()
    assert "calib" in title and "0.057 ± 0.027 mm" in title and "0.2 ± 0.013 MPa" in title
    legend = fig.legends[0]
    for handle, text in zip(legend.legend_handles, legend.get_texts()):
        if handle.get_color() == "white" or text.get_text().startswith("grid best"):
            assert handle.get_path_effects(), text.get_text()  # a dark edge around the white
    ax = data_axes(fig)[0]
    assert ax.xaxis.get_major_formatter()(0.1) == "0.1"  # plain numbers on log axes


def test_log_axes_write_thousands_as_plain_numbers():
    """A misfit colour bar from 50 to 1500 mm² was labelled 100 and 1e+03."""
    from stitchplan.io.plot_elements import pyplot, readable_log_axis

    fig, ax = pyplot().subplots()
    ax.set_yscale("log")
    ax.set_ylim(50.0, 1500.0)
    readable_log_axis(ax.yaxis)
    formatter = ax.yaxis.get_major_formatter()
    assert [formatter(v) for v in (100.0, 1000.0, 20000.0, 0.001)] == ["100", "1000", "20000", "0.001"]
    pyplot().close(fig)


def test_marker_residuals_draw_the_tissue_clamps_and_loads(tmp_path):
    scenario = parse_scenario({"tissue": {"size": [50.0, 30.0], "thickness": 10.0, "clamped": ["right"],
                                          "material": MATERIAL},
                               "loads": [{"segment": [[0.0, 10.0], [0.0, 20.0]], "force": [1.0, 0.0]}]})
    markers = np.array([[10.0, 10.0], [20.0, 15.0], [30.0, 20.0]])
    measured = markers + [0.5, 0.1]
    experiment = SimpleNamespace(name="pull", markers=markers, measured=measured, loads=scenario.loads)
    simulated = [measured + [[0.02, 0.0], [0.0, -0.01], [0.01, 0.01]]]
    fig = calibration_plots.plot_marker_residuals(tmp_path / "markers.png", scenario.tissue, [experiment], simulated,
                                      name="calib")
    assert is_png(tmp_path / "markers.png")
    assert_readable(fig, colour_bar_count=0)
    assert "calib" in fig._suptitle.get_text() and "largest 0.02 mm" in fig._suptitle.get_text()
    labels = data_axes(fig)[0].get_legend_handles_labels()[1]
    assert {"tissue at rest", "clamped edge", "load: force (N, total)"} <= set(labels)


def test_needle_forces_title_carries_the_fit(tmp_path):
    from stitchplan.calibration import calibrate_needle

    folder = REPOSITORY / "sample_runs" / "calibration"
    result = calibrate_needle(folder / "air.csv", folder / "tissue.csv", 8.88)
    fig = calibration_plots.plot_needle_forces(tmp_path / "forces.png", result)
    assert is_png(tmp_path / "forces.png")
    assert_readable(fig, colour_bar_count=0)
    headline = fig._suptitle.get_text()
    assert f"friction {result.friction:.4g}" in headline and f"cutting force {result.cutting_force:.4g}" in headline


# --- study ----------------------------------------------------------------------------------


def fake_study(failed: bool):
    """A study record with four runs (no insertions needed by the plot)."""
    from stitchplan.study.sweep import StudyResult, StudyRun

    scenario = parse_scenario({"name": "sweep", "tissue": {"size": [30.0, 20.0], "thickness": 10.0, "clamped": ["left"],
                                                           "material": MATERIAL}})

    def run(family, spacing, seconds, deviation, status="ok"):
        deviations = {"deviation_mm": deviation, "exit_deviation_mm": deviation / 2} if status == "ok" else {}
        return StudyRun(family=family, label=f"{family} h={spacing} mm", scenario=scenario, spacing=spacing,
                        particles=int(1000 / spacing), wall_seconds=seconds, status=status,
                        deviations=deviations)

    reference = run("reference", 0.5, 9.0, 0.0)
    runs = [run("uniform", 2.0, 0.6, 0.07), run("uniform", 1.0, 1.3, 0.03), run("graded x4", 2.0, 0.7, 0.04),
            run("graded x4", 1.0, 0.9, math.nan, "failed" if failed else "ok")]
    if not failed:
        runs[-1].deviations = {"deviation_mm": 0.02, "exit_deviation_mm": 0.01}
    return StudyResult(scenario=scenario, runs=[*runs, reference], reference=reference)


@pytest.mark.parametrize("failed", [False, True])
def test_speed_accuracy_mentions_failures_only_when_there_are_some(failed, tmp_path):
    fig = plots.plot_speed_accuracy(tmp_path / "speed.png", fake_study(failed))
    assert is_png(tmp_path / "speed.png")
    assert_readable(fig, colour_bar_count=0)
    headline = fig._suptitle.get_text()
    assert "sweep" in headline and "5 runs" in headline
    assert ("1 failed" in headline) == failed
    assert "failed" in headline or not failed
    for ax in data_axes(fig):
        for axis in (ax.xaxis, ax.yaxis):
            assert axis.get_major_formatter()(0.01) == "0.01"
            shown = [label.get_text() for label in axis.get_ticklabels(minor=True) if label.get_text()]
            assert all("10^" not in text and "$" not in text for text in shown)


def test_speed_accuracy_counts_failed_runs_drawn_at_one_place(tmp_path):
    """Failures before a solve take no time: a family's crosses fell on one spot at the right
    edge, and the plot showed one where three runs failed. Crosses at one time are counted
    beside them ("3x"), on both panels."""
    study = fake_study(failed=True)
    graded = next(run for run in study.runs if run.family == "graded x4" and not run.ok)
    for spacing in (3.0, 4.0):
        study.runs.insert(0, replace(graded, label=f"graded x4 h={spacing} mm", spacing=spacing, status="failed",
                                     deviations={}))
    fig = plots.plot_speed_accuracy(tmp_path / "speed.png", study)
    for ax in data_axes(fig):
        assert [text.get_text() for text in ax.texts if text.get_text().endswith("x")] == ["3x"]


@pytest.mark.parametrize("scale", ["1e308", "1e7"])
def test_deform_plot_scale_beyond_a_million_is_refused(slab_path, tmp_path, scale):
    """1e308 x the displacements overflowed the axis limits: a matplotlib traceback."""
    plot, probes = tmp_path / "big.png", tmp_path / "probes.csv"
    bad = CliRunner().invoke(app, ["deform", str(slab_path), "--plot", str(plot), "--probes-out", str(probes),
                                   "--plot-scale", scale])
    assert bad.exit_code == 2, bad.output
    lines = bad.output.strip().splitlines()
    assert lines == [f"error: --plot-scale: got {float(scale)!r}, expected a positive number of at most 1e+06 "
                     "(1 = true scale)"], bad.output
    assert not plot.exists() and not probes.exists()


def test_deformed_plot_at_the_largest_scale_stays_finite(deformed, tmp_path):
    from stitchplan.errors import InputError

    fig = plots.plot_deformed(tmp_path / "deformed.png", deformed, scale=plots.MAX_PLOT_SCALE)
    ax = data_axes(fig)[0]
    assert np.all(np.isfinite(ax.get_xlim() + ax.get_ylim())) and "1e+06x enlarged" in ax.get_title()
    with pytest.raises(InputError, match=r"^--plot-scale: got 1e\+308"):
        plots.plot_deformed(tmp_path / "huge.png", deformed, scale=1e308)
    assert not (tmp_path / "huge.png").exists()


def test_load_labels_on_the_edges_of_a_narrow_hole_sit_beside_their_own_segments():
    """An arrow as long as the hole is wide would carry each label across to the other
    edge's load: the arrows stay within the hole and the labels on their own side."""
    from stitchplan.io.plot_elements import draw_loads, pyplot

    scenario = parse_scenario({
        "tissue": {"size": [60.0, 30.0], "thickness": 10.0, "clamped": ["bottom"],
                   "material": {"model": "neo-hookean", "lame_lambda": 0.189151, "lame_mu": 0.147688},
                   "holes": [{"polygon": [[20, 10], [30, 10], [30, 20], [20, 20]]}]},
        "loads": [{"segment": [[20, 12], [20, 18]], "force": [1.0, 0.0]},
                  {"segment": [[30, 10], [30, 20]], "displacement": [0.5, 0.0]},
                  {"segment": [[0, 10], [0, 20]], "force": [-1.0, 0.0]}]})
    plt = pyplot()
    fig, ax = plt.subplots()
    try:
        draw_loads(ax, scenario.loads, scenario.tissue.domain, arrow=0.15 * 60.0)
        labels = {text.get_text().split(" =")[0]: text for text in ax.texts if text.get_text()}
        arrows = [text for text in ax.texts if not text.get_text()]
    finally:
        plt.close(fig)
    # F1 on the hole's left edge (x = 20) is labelled left of it, u2 (x = 30) right of it
    assert labels["F1"].xy[0] <= 20.0 and labels["F1"].get_ha() == "right"
    assert labels["u2"].xy[0] >= 30.0 and labels["u2"].get_ha() == "left"
    # the hole-edge arrows end inside the 10 mm hole; the outer edge's keeps its length
    for arrow in arrows[:2]:
        for x in (arrow.xy[0], arrow.xyann[0]):
            assert 20.0 <= x <= 30.0
    assert arrows[2].xy[0] == pytest.approx(-9.0)
    assert labels["F3"].xy[0] == pytest.approx(-9.0) and labels["F3"].get_ha() == "right"


def test_a_circular_holes_deformed_outline_follows_its_vertices_not_only_its_particles():
    """A circular hole's wall carries a particle one spacing apart, not one at each of its
    vertices: its deformed outline takes every vertex, moved by the particles' displacement
    interpolated along the wall, so a translated hole stays the same round 96-gon (drawn
    through the particles alone it was a coarse polygon)."""
    from stitchplan.io.plot_elements import deformed_loops, outline_loops
    from stitchplan.tissue.model import model_for_scenario

    scenario = parse_scenario({
        "tissue": {"size": [40.0, 30.0], "thickness": 10.0, "clamped": ["right"],
                   "material": {"lame_lambda": 0.189151, "lame_mu": 0.147688},
                   "holes": [{"circle": {"center": [20.0, 15.0], "radius": 4.0}}]},
        "discretization": {"spacing": 3.0}})
    model = model_for_scenario(scenario)
    shift = np.array([0.3, -0.2])
    loops = deformed_loops(scenario.tissue.domain, model.particles, np.tile(shift, (len(model.particles), 1)))
    hole = outline_loops(scenario.tissue.domain)[1]
    drawn = loops[1][:-1]
    assert len(drawn) >= len(hole)  # every vertex, and the wall's particles
    radius = np.linalg.norm(drawn - (np.array([20.0, 15.0]) + shift), axis=1)
    assert np.all(radius <= 4.0 + 1e-9) and np.all(radius >= 4.0 * np.cos(np.pi / len(hole)) - 1e-9)
    np.testing.assert_allclose(np.sort(np.linalg.norm(hole - [20.0, 15.0], axis=1)), 4.0, atol=1e-9)
    at_vertices = np.min(np.linalg.norm(drawn[:, None] - (hole + shift)[None], axis=2), axis=0)
    assert np.max(at_vertices) < 1e-9


# --- uncertainty ----------------------------------------------------------------------------


def fake_uncertainty():
    """Held-out exit errors of the unplanned path and a plan (robust = nominal), and the
    sensitivities of configs/uncertainty/uncertainty_sample.yaml on sh12_100x100."""
    from stitchplan.uncertainty.robust import Sensitivity

    rng = np.random.default_rng(3)
    errors = {"unplanned": rng.normal([-0.006, 0.49], [0.002, 0.03], (16, 2)),
              "nominal": rng.normal(0.0, [0.0005, 0.02], (16, 2))}
    sensitivities = [Sensitivity(name, std, 0.5 * std, np.array([value, 0.0]), None) for name, value, std in
                     (("lame_lambda", 0.372, 0.0129), ("lame_mu", 2.58, 0.00167), ("friction", 4.81, 0.000264),
                      ("cutting_force", 0.232, 0.00385), ("thickness", 0.0452, 0.5))]
    return SimpleNamespace(robust_is_nominal=True, exported="nominal", evaluated=np.ones(16, dtype=bool),
                           errors=errors.__getitem__, sensitivities=sensitivities, refined_offset=None,
                           statistics={"unplanned": {"p95_mm": 0.535}, "nominal": {"p95_mm": 0.0436}},
                           failed_held_out_samples=0, uncertainty=SimpleNamespace(samples=16))


def test_uncertainty_sensitivity_labels_stay_inside_their_panel_as_saved(tmp_path):
    """The room for the sensitivities' labels was measured at matplotlib's 100 dpi, the PNG drawn
    at 120, where 7 pt text is relatively wider: the thickness label ran through the panel's
    right edge. Measured on the figure at the dpi it is saved at."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from stitchplan.io.uncertainty_reports import plot_uncertainty

    fig = plot_uncertainty(tmp_path / "uncertainty.png", fake_uncertainty(), "sh12")
    assert is_png(tmp_path / "uncertainty.png")
    fig.set_dpi(plots.SAVED_DPI)
    canvas = FigureCanvasAgg(fig)  # the saved figure is closed: a canvas to measure it on
    canvas.draw()
    renderer = canvas.get_renderer()
    panel = fig.axes[2]
    edge = panel.get_window_extent(renderer).x1
    labels = [text for text in panel.texts if " x 1.96 x " in text.get_text()]
    assert len(labels) == 5
    for label in labels:
        assert label.get_window_extent(renderer).x1 <= edge, label.get_text()


def test_an_axis_scaled_by_a_power_of_ten_says_so_in_its_label():
    """Ticks of millimetre thousandths are labelled "(x 10^-3 mm)" in the axis label, with
    matplotlib's detached "1e-3" hidden; ticks of whole millimetres keep "(mm)"."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from stitchplan.io.plot_elements import label_with_multiplier

    fig, (small, plain) = plt.subplots(1, 2)
    small.plot([0.0, 0.004], [0.0, 1.0])
    plain.plot([0.0, 5.0], [0.0, 1.0])
    fig.canvas.draw()
    import warnings

    with warnings.catch_warnings():  # no deprecated matplotlib attribute read
        warnings.simplefilter("error")
        label_with_multiplier(small.xaxis, "exit error", "mm")
        label_with_multiplier(plain.xaxis, "exit error", "mm")
    fig.canvas.draw()
    assert small.get_xlabel() == r"exit error ($\times 10^{-3}$ mm)" and not small.xaxis.offsetText.get_visible()
    assert plain.get_xlabel() == "exit error (mm)"
    plt.close(fig)


# --- a user's text in the figures -----------------------------------------------------------

DOLLARS = "a $x^{$ b"  # a lone `$` ... `$` pair matplotlib read as mathtext, which failed to parse


def shown_as_written(text, written: str) -> bool:
    """The figure draws `written` as plain text, its `$` signs included (no mathtext)."""
    return text._preprocess_math(text.get_text()) == (written, False)


def test_a_scenario_name_with_dollar_signs_is_drawn_as_written(slab_raw, write_scenario, tmp_path):
    """A scenario, calibration, experiment or study family named with `$` (or a recording's
    file name) ended every figure of it in a matplotlib traceback, and the command wrote none
    of its files."""
    scenario = write_scenario({**slab_raw, "name": DOLLARS})
    result = CliRunner().invoke(app, ["deform", str(scenario), "--plot", str(tmp_path / "d.png"),
                                      "--summary", str(tmp_path / "s.json")])
    assert result.exit_code == 0, result.output
    assert is_png(tmp_path / "d.png") and (tmp_path / "s.json").exists()


def test_calibration_names_and_recording_files_with_dollar_signs_are_drawn_as_written(tmp_path):
    from stitchplan.calibration import calibrate_needle

    scenario = parse_scenario({"tissue": {"size": [50.0, 30.0], "thickness": 10.0, "clamped": ["right"],
                                          "material": MATERIAL},
                               "loads": [{"segment": [[0.0, 10.0], [0.0, 20.0]], "force": [1.0, 0.0]}]})
    markers = np.array([[10.0, 10.0], [20.0, 15.0], [30.0, 20.0]])
    experiment = SimpleNamespace(name=DOLLARS, markers=markers, measured=markers + 0.5, loads=scenario.loads)
    fig = calibration_plots.plot_marker_residuals(tmp_path / "markers.png", scenario.tissue, [experiment],
                                                  [markers + 0.4], name="$")
    assert is_png(tmp_path / "markers.png")
    assert shown_as_written(data_axes(fig)[0].title, f"{DOLLARS}: rms residual 0.141 mm")
    assert fig._suptitle.get_text().startswith(r"\$: marker residuals")
    folder = REPOSITORY / "sample_runs" / "calibration"
    tissue = tmp_path / "tissue $x^{$.csv"
    tissue.write_bytes((folder / "tissue.csv").read_bytes())
    fig = calibration_plots.plot_needle_forces(tmp_path / "forces.png", calibrate_needle(folder / "air.csv", tissue,
                                                                                         8.88))
    assert is_png(tmp_path / "forces.png")
    assert fig._suptitle.get_text().startswith(r"calibrate needle (air.csv / tissue \$x^{\$.csv)")


def test_study_family_names_with_dollar_signs_are_drawn_as_written(tmp_path):
    study = fake_study(failed=True)
    for run in study.runs:
        if run.family == "uniform":
            run.family, run.label = DOLLARS, run.label.replace("uniform", DOLLARS)
    fig = plots.plot_speed_accuracy(tmp_path / "speed.png", study)
    assert is_png(tmp_path / "speed.png")
    legend = [text for text in fig.legends[0].get_texts() if "x^" in text.get_text()]
    assert legend and all(shown_as_written(text, DOLLARS) for text in legend)


def test_a_saved_figure_names_the_code_that_drew_it(tmp_path):
    """A PNG kept alone says which code drew it: the version and the sources' SHA-256, as the
    summaries and run logs record them (stitchplan_source_sha256)."""
    import matplotlib.pyplot as plt
    from PIL import Image

    import stitchplan

    fig, _ = plt.subplots()
    plots.save(fig, tmp_path / "figure.png")
    with Image.open(tmp_path / "figure.png") as image:
        software = image.text["Software"]
    assert software == f"stitchplan {stitchplan.__version__} (sources SHA-256 {stitchplan.source_sha256()})"
