"""Accuracy you can trust: exit error estimates, plans verified on a refined model, and a
centre path a robot can follow.

- the move limits' projection is the nearest point of the two discs (against a brute-force
  search), and the passes' secant starts with de/dc = -1 along the exit edge;
- on a small planned scene (30 x 30 mm, 4 mm spacing, 0.08 rad steps, where the limits
  bind: without them its centre path exceeds the second-difference bound) no step moves
  the centre more than 0.3 mm, the second difference stays within 0.15 mm and the planned
  exit error within 0.005 mm;
- `plan` reports the verification keys, `--no-verify` nulls them, and the verified exit
  error is what `simulate --center-path trajectory.csv --spacing verification_spacing_mm`
  gives;
- the exit error estimate (runs at h and 2h) bounds and tracks the actual deviation from a
  run at h/2;
- the predicted aim is the refined model's offset predicted from a replay at 2h, and on a
  block where the unaimed plan misses on the refined model it saves the second round.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from stitchplan.cli import app
from stitchplan.config.scenario import parse_scenario
from stitchplan.needle.insertion import run_insertion
from stitchplan.planning.move_limits import MoveLimits, path_smoothness
from stitchplan.planning.pass_offsets import PassOffsets
from stitchplan.planning.planner import run_plan
from stitchplan.planning.trajectory import DECIMALS_MM
from stitchplan.planning.verification import (
    PREDICTED_RATIO,
    VERIFIED_FACTOR,
    exit_deviations,
    plan_verified,
    prediction_replays,
    simulate_with_estimate,
)
from stitchplan.planning.replay_models import rescaled

from conftest import TIGHT_NEEDLE_NEWTON

RADIUS = 8.88
VERIFICATION_KEYS = ("verified_exit_error_mm", "verification_spacing_mm", "verification")


def scene_raw(size: float, entry_y: float, spacing: float, step: float, **extra) -> dict:
    """An SH 1/2 needle entering the left edge of a square block clamped on the right."""
    return {"tissue": {"size": [size, size], "thickness": 10.0, "clamped": ["right"],
                       "material": {"lame_lambda": 0.189151, "lame_mu": 0.147688}},
            "discretization": {"spacing": spacing},
            "needle": {"radius": RADIUS, "entry": [0.0, entry_y], "turn": "cw", "step": step,
                       "friction": 0.0602, "cutting_force": 0.7},
            **extra}


def invoke(command: str, *args):
    result = CliRunner().invoke(app, [command, *map(str, args)])
    assert result.exit_code == 0, result.output
    return result


def test_move_limits_project_onto_the_nearest_point_of_both_discs(rng):
    limits = MoveLimits(step_mm=0.3, second_difference_mm=0.15, last_step=100)
    centers = [np.array([1.0, 2.0]), np.array([1.25, 2.1])]  # last move 0.27 mm
    grid = np.stack(np.meshgrid(np.linspace(0.8, 2.0, 1201), np.linspace(1.5, 2.8, 1301)), axis=-1).reshape(-1, 2)
    inside = grid[(np.linalg.norm(grid - centers[-1], axis=1) <= 0.3)
                  & (np.linalg.norm(grid - (2 * centers[-1] - centers[-2]), axis=1) <= 0.15)]
    for candidate in rng.uniform([0.5, 1.5], [2.5, 3.0], size=(20, 2)):
        projected = limits.project(candidate, centers, step=5)
        assert np.linalg.norm(projected - centers[-1]) <= 0.3 + 1e-12
        assert np.linalg.norm(projected - (2 * centers[-1] - centers[-2])) <= 0.15 + 1e-12
        nearest = np.linalg.norm(inside - candidate, axis=1).min()
        assert np.linalg.norm(projected - candidate) <= nearest + 1e-3  # grid pitch 1e-3 mm
    # braking: two steps before the last the move is held to one second difference
    assert limits.speed(99) == pytest.approx(0.15) and limits.speed(10) == pytest.approx(0.3)


def test_pass_offsets_start_with_unit_slope_along_the_exit_edge_then_take_the_secant():
    offsets = PassOffsets()
    offsets.record(np.array([0.0, 0.04]))  # pass 1 at c = 0 missed by 0.04 mm along y
    offsets.advance(np.zeros(2))
    np.testing.assert_allclose(offsets.offset, [0.0, 0.04])  # de/dc = -1
    offsets.record(np.array([0.0, 0.02]))  # half the expected response: slope -0.5
    offsets.advance(np.zeros(2))
    np.testing.assert_allclose(offsets.offset, [0.0, 0.04 + 0.02 / 0.5])
    offsets.record(np.array([0.0, 0.001]))
    offsets.advance(np.array([0.0, 0.005]))  # another aim moves the next offset the other way
    assert offsets.offset[1] < 0.08


def test_symmetric_pass_offsets_take_the_bites_secant_once_a_pass_overshoots():
    """The symmetric target's aim follows each pass (p: the exit error at equal bites its own
    bites set). While the passes stay on one side of it the secant is t . e's, as for the
    exit; once one falls on the other side it is t . (e - p)'s, which puts the next offset
    where the bites' difference crosses zero between the two (t . e's, 0.4 here as through a
    hole, took it to 0.35, back past equal bites by 0.19 mm where this pass was 0.1 mm past: an
    overshoot growing each pass)."""
    offsets = PassOffsets()
    offsets.record(np.array([0.0, 0.0]), follows=np.array([0.0, 0.6]))  # bites 0.6 mm apart
    offsets.advance(np.array([0.0, 0.6]))
    np.testing.assert_allclose(offsets.offset, [0.0, -0.6])  # de/dc = -1
    offsets.record(np.array([0.0, 0.24]), follows=np.array([0.0, 0.14]))  # beyond: 0.1 mm the other way
    offsets.advance(np.array([0.0, 0.14]))
    assert offsets.overshot
    # the bites' difference along t went from -0.6 to 0.1 over 0.6 mm of offset
    np.testing.assert_allclose(offsets.offset, [0.0, -0.6 + 0.1 * 0.6 / 0.7])


def test_passes_short_of_their_aim_are_said_to_overshoot_or_be_held_not_guessed():
    """The target-missed note's cause comes from the passes' misses (planner.why_short):
    misses that swing from side to side and grow are no convergence, not move limits."""
    from stitchplan.planning.planner import why_short

    offsets = PassOffsets()
    offsets.direction = np.array([1.0, 0.0])
    swinging = [{"exit_error_vector_mm": np.array([x, 0.0]), "aim_mm": np.zeros(2)} for x in (0.55, -0.24, 0.59)]
    assert why_short(swinging, offsets, 4) == ("the passes did not converge: they missed their aim by 0.55, 0.24, "
                                               "0.59 mm, overshooting it from side to side (see planner_passes)")
    offsets.searching = True
    assert why_short(swinging, offsets, 4).startswith("the move limits held the centre back")


def test_planned_centre_path_is_smooth_and_still_hits_the_exit():
    scenario = parse_scenario(scene_raw(30.0, 24.0, 4.0, 0.08))
    result = run_plan(scenario, compare=False)
    max_step, max_second = path_smoothness(result.exported_centers)
    figures = f"largest move {max_step:.4f} mm, second difference {max_second:.4f} mm"
    assert max_step <= 0.3 and max_second <= 0.15, figures
    assert result.planned.exit_error_mm <= scenario.planner.exit_tolerance
    assert any(p["limited_steps"] for p in result.passes)  # the limits were needed here


def test_move_limits_come_from_the_scenario_and_scale_with_the_step():
    """planner.center_step_limit and center_second_difference_limit are stated per 0.08 rad:
    tighter limits at a 0.16 rad step bound the path at twice them, and still plan."""
    raw = scene_raw(30.0, 24.0, 4.0, 0.16, planner={"center_step_limit": 0.1, "center_second_difference_limit": 0.05})
    result = run_plan(parse_scenario(raw), compare=False)
    max_step, max_second = path_smoothness(result.exported_centers)
    # the CSV's centres are rounded to 1e-9 mm: a move can grow by two roundings of both
    # coordinates, a second difference by four
    half_unit = 0.5 * 10.0 ** -DECIMALS_MM
    assert max_step <= 0.2 + 2 * half_unit * np.sqrt(2) and max_second <= 0.1 + 4 * half_unit * np.sqrt(2), \
        (max_step, max_second)
    assert max_step > 0.15  # the limit was reached, so it is what held the path
    assert result.planned.exit_error_mm < 0.1


@pytest.fixture(scope="module")
def planned_small(tmp_path_factory) -> tuple[Path, dict, Path]:
    folder = tmp_path_factory.mktemp("verify")
    scenario = folder / "scene.yaml"
    # solved tightly: the verified exit error is compared with a cold replay to ~1e-7 mm
    raw = {**scene_raw(20.0, 18.0, 5.0, 0.3, planner={"max_passes": 2}), "solver": TIGHT_NEEDLE_NEWTON}
    scenario.write_text(yaml.safe_dump(raw))
    invoke("plan", scenario, "--export", folder / "t.csv", "--summary", folder / "s.json", "--no-compare")
    return scenario, json.loads((folder / "s.json").read_text()), folder / "t.csv"


def test_plan_reports_verification_and_smoothness(planned_small):
    _, summary, _ = planned_small
    assert summary["verification_spacing_mm"] == pytest.approx(2.5)
    assert summary["verification"]["discretization"]["particles"] > summary["particles"]
    assert math.isfinite(summary["verified_exit_error_mm"])
    assert summary["verified_exit_error_mm"] == pytest.approx(summary["verification"]["rounds"][-1]
                                                              ["verified_exit_error_mm"]) or len(
        summary["verification"]["rounds"]) > 1
    assert summary["exit_error_estimate"]["basis"] == "refined"
    assert summary["verification"]["replayed_in"] in ("helper process", "this process")
    assert summary["exit_error_estimate_mm"] >= summary["exit_error_estimate"]["exit_error_deviation_mm"]
    assert summary["max_center_step_mm"] <= 0.3 * 0.3 / 0.08 + 1e-12  # limits scale with the step
    assert summary["max_center_second_difference_mm"] <= 0.15 * 0.3 / 0.08 + 1e-12
    assert summary["discretization"]["spacing_mm"] > 0 and summary["discretization"]["particles"] > 0
    # the spacing --spacing takes: the verification's is half the plan's
    assert summary["verification_spacing_mm"] == 0.5 * summary["discretization"]["requested_spacing_mm"]
    assert summary["verification"]["discretization"]["requested_spacing_mm"] == summary["verification_spacing_mm"]


def test_verified_exit_error_is_a_replay_at_the_verification_spacing(planned_small, tmp_path):
    scenario, summary, trajectory = planned_small
    replay = tmp_path / "replay.json"
    invoke("simulate", scenario, "--center-path", trajectory, "--spacing", summary["verification_spacing_mm"],
           "--summary", replay, "--no-estimate")
    replayed = json.loads(replay.read_text())
    assert replayed["exit_error_estimate_mm"] is None
    assert replayed["particles"] == summary["verification"]["discretization"]["particles"]
    # a later round's replay starts each step's Newton solve from the round before
    # (run_insertion start_from): the same equilibria to the residual tolerance, 5e-6 of the
    # needle force here (the fixture's solver), which moves the exit by ~1e-7 mm
    assert replayed["exit_error_mm"] == pytest.approx(summary["verified_exit_error_mm"], abs=1e-6)
    np.testing.assert_allclose(replayed["achieved_exit_def"], summary["verification"]["achieved_exit_def"],
                               atol=1e-6)


def test_no_verify_nulls_the_verification_keys(planned_small, tmp_path):
    scenario, _, _ = planned_small
    invoke("plan", scenario, "--export", tmp_path / "t.csv", "--summary", tmp_path / "s.json",
           "--no-compare", "--no-verify")
    summary = json.loads((tmp_path / "s.json").read_text())
    for key in VERIFICATION_KEYS:
        assert summary[key] is None, key
    assert "exit_error_estimate_mm" in summary and "max_center_step_mm" in summary


def test_exit_error_estimate_tracks_the_deviation_from_a_finer_run():
    """At h = 4 mm the estimate from (h, 2h) bounds the exit point's actual deviation from
    the run at h/2 and stays within 4 x of it: with order 1 the error of the h run is about
    twice that deviation (observed with two needle couplings during development: 0.072
    against 0.065 mm, 0.079 against 0.033 mm)."""
    scenario = parse_scenario(scene_raw(30.0, 24.0, 4.0, 0.16))
    result, estimate = simulate_with_estimate(scenario)
    assert estimate.basis == "coarse" and estimate.other_spacing_mm == pytest.approx(8.0)
    finer = run_insertion(rescaled(scenario, 0.5))
    actual = exit_deviations(result, finer)["deviation_mm"]
    assert actual > 0.01  # a deviation worth estimating
    assert actual <= estimate.estimate_mm <= 4.0 * actual, (estimate.estimate_mm, actual)


def test_both_richardson_estimates_are_exact_for_an_exit_that_converges_at_the_assumed_order():
    """With the exit point x(h) = x* + C h^p at the assumed order p, the estimate of the h
    run's error |x(h) - x*| is exact from a coarser run (2h: d / (2^p - 1)) and from a finer
    one (h/2: d / (1 - 2^-p), a verified plan's): d alone is half the error at p = 1."""
    from types import SimpleNamespace

    from stitchplan.planning.verification import ASSUMED_ORDER, estimate_from

    converged, slope, h = np.array([31.2, 4.5]), np.array([0.03, -0.04]), 2.0

    def run(spacing: float) -> SimpleNamespace:
        exit_point = converged + slope * spacing**ASSUMED_ORDER
        return SimpleNamespace(achieved_exit_def=exit_point, achieved_exit=exit_point - 0.5, steps=[0] * 20,
                               desired_exit_def=np.array([31.0, 4.0]), model=SimpleNamespace(n_particles=100))

    error = float(np.linalg.norm(slope * h**ASSUMED_ORDER))
    coarse = estimate_from(run(h), run(2.0 * h), 2.0, 2.0 * h)
    refined = estimate_from(run(h), run(0.5 * h), 0.5, 0.5 * h)
    assert (coarse.basis, refined.basis) == ("coarse", "refined")
    assert coarse.estimate_mm == pytest.approx(error, rel=1e-12)
    assert refined.estimate_mm == pytest.approx(error, rel=1e-12)


def test_the_predicted_aim_re_aims_before_the_refined_replay_and_saves_a_round():
    """With planner.predicted_aim the passes after the first aim at minus the refined model's
    offset predicted from a replay of the first pass's trajectory at 2h, (e(h) - e(2h)) /
    PREDICTED_RATIO, before any refined replay: on this block one round then verifies within
    VERIFIED_FACTOR x the exit tolerance, where the unaimed plan misses on the refined model
    and takes a second, aimed at minus the offset, that verifies."""
    raw = scene_raw(30.0, 24.0, 4.0, 0.16)
    scenario = parse_scenario(raw)
    aimed = plan_verified(scenario, compare=False)
    plain = plan_verified(parse_scenario({**raw, "planner": {"predicted_aim": False}}), compare=False)
    threshold = VERIFIED_FACTOR * scenario.planner.exit_tolerance
    first = aimed.verification.rounds[0]
    first_pass = run_plan(parse_scenario({**raw, "planner": {"max_passes": 1}}), compare=False)
    coarse = run_insertion(rescaled(scenario, 2.0), center_path=first_pass.exported_centers)
    expected = (first_pass.planned.exit_error_vector_mm - coarse.exit_error_vector_mm) / PREDICTED_RATIO
    assert first["aimed_by"] == "predicted offset"
    np.testing.assert_allclose(first["predicted_offset_mm"], expected, rtol=1e-9, atol=1e-12)
    assert len(aimed.verification.rounds) == 1 and aimed.verification.exit_error_mm <= threshold
    assert plain.verification.rounds[0]["aimed_by"] == "none"
    assert plain.verification.rounds[0]["verified_exit_error_mm"] > threshold
    assert len(plain.verification.rounds) > 1
    assert plain.verification.exit_error_mm <= threshold  # its second round, aimed at minus the offset


def test_the_predicted_aim_replays_in_this_process_by_default():
    """The replay at 2h for the predicted aim runs in the command's process after the first
    pass (the refined replay in the helper is a verified plan's longest path; a second helper
    took CPU from it: benchmarks/results/prediction_in_process.md); `background` asks for a
    helper of its own, and with no predicted aim there is none."""
    scenario = parse_scenario(scene_raw(30.0, 24.0, 4.0, 0.16))
    with prediction_replays(scenario) as predictions:
        assert predictions.where == "this process"
    with prediction_replays(parse_scenario({**scene_raw(30.0, 24.0, 4.0, 0.16),
                                            "planner": {"predicted_aim": False}})) as predictions:
        assert predictions is None



def _shoot(offsets, exit_along, passes):
    """The offsets s of `passes` passes whose exit error along y is exit_along(s), aimed at zero."""
    run = []
    for _ in range(passes):
        position = offsets.offset[1]
        run.append(position)
        offsets.record(np.array([0.0, exit_along(position)]))
        offsets.advance(np.zeros(2))
    return np.array(run)


def test_pass_offsets_search_between_the_passes_once_the_exit_moves_with_the_offset():
    # the exit comes no closer to the aim than 0.2 mm, at s = 0.7 mm (the move limits hold it)
    def exit_along(s):
        return 0.2 + 0.6 * (s - 0.7) ** 2 if s > 0.3 else 0.5 - 0.55 * s

    offsets = PassOffsets()
    run = _shoot(offsets, exit_along, 4)
    # s = 0, then 0.5 (de/ds = -1), then the secant (slope -0.55) to 0.906, past the nearest exit:
    # the exit moved with the offset there, so the fourth pass is the parabola's vertex between
    np.testing.assert_allclose(run[:3], [0.0, 0.5, 0.5 + 0.224 / 0.552], rtol=1e-3)
    assert offsets.searching
    assert 0.5 < run[3] < run[2] and abs(run[3] - 0.7) < 1e-3
    assert abs(offsets.offset[1] - 0.7) < 1e-3 and offsets.closest_tried() < 1e-3  # settled: run_plan stops
    # without the search the secant (its slope clipped at -1/3) would have gone on to 0.906 + 3 x 0.2254 mm


def test_pass_offsets_search_takes_the_root_between_passes_on_either_side_of_the_aim():
    # after s = 0.5 the exit first runs back past the aim (roots at 0.794 and 1.456 mm), then away
    def exit_along(s):
        return 0.5 - 0.1 * s if s < 0.5 else 0.45 - 2.0 * (s - 0.5) + 1.6 * (s - 0.5) ** 2

    offsets = PassOffsets()
    run = _shoot(offsets, exit_along, 5)
    assert offsets.searching  # 0.5 -> 1.85 (slope -0.1 clipped to -1/3) moved the exit away: 0.45 -> 0.666
    assert np.all((run[3:] > 0.5) & (run[3:] < 1.85))  # between the passes run
    assert exit_along(run[3]) > 0.0 > exit_along(run[4])  # the vertex, then past the aim: a bracket
    root = 0.5 + (2.0 - np.sqrt(4.0 - 4 * 1.6 * 0.45)) / 3.2
    assert abs(offsets.offset[1] - root) < 1e-9  # the parabola's root in it (exit_along is one there)
