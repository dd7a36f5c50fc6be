"""A plan whose later runs fail numerically still exports the best it has: a planner pass
after the first that moves the centre where the model fails (det F < 0 at the tip), or a
verification replay on the refined model that fails where the planning model did not. Each
used to end the whole command with exit 1, the usable trajectory discarded; now an event
says what failed and the plan stands (small blocks, about a second each)."""

from __future__ import annotations

import time

import numpy as np
import pytest
import yaml

from stitchplan.config.scenario import parse_scenario
from stitchplan.errors import InsertionFailure
from stitchplan.events import EventKind
from stitchplan.planning.planner import run_plan
from stitchplan.planning.verification import plan_verified

from conftest import CONFIGS

FAILED_ROUND_SECONDS = 0.3  # how long the failing round of the wall-time test takes


def block(model: str, thickness: float, friction: float, cutting_force: float) -> dict:
    """40 x 30 mm block clamped on the right, an 8 mm needle entering (0, 22) cw in 0.2 rad
    steps, 4 mm particles, loads far past the phantom's."""
    return {"tissue": {"size": [40.0, 30.0], "thickness": thickness, "clamped": ["right"],
                       "material": {"model": model, "lame_lambda": 0.189151, "lame_mu": 0.147688}},
            "needle": {"radius": 8.0, "entry": [0.0, 22.0], "turn": "cw", "step": 0.2, "friction": friction,
                       "cutting_force": cutting_force},
            "discretization": {"spacing": 4.0}}


def test_a_later_pass_that_fails_leaves_the_best_pass_before_it():
    scenario = parse_scenario(block("saint-venant-kirchhoff", 5.0, 0.2, 1.5))
    plan = run_plan(scenario, compare=False)
    assert len(plan.passes) == 1  # the second pass failed: only the first ran to the exit
    failed = [event for event in plan.planned.events if event.kind == EventKind.PASS_FAILED]
    assert len(failed) == 1
    assert failed[0].message.startswith("planner pass 2 (offset (")
    assert "step 14 (needle rotation 2.800 rad)" in failed[0].message
    # the collapse in front of the tip ends the ramp's last increment: det F < 0, the ramp
    # stalling on it, or Newton's constraints stalling in it (which of them, round-off decides:
    # CHOLMOD's factors or SuperLU's, the order of the saddle-point solver's products)
    assert ("det F = " in failed[0].message or "Saint Venant-Kirchhoff is unstable" in failed[0].message
            or "the needle constraints stall above their tolerance" in failed[0].message), failed[0].message
    assert "the needle's load could not be carried: " in failed[0].message
    assert failed[0].message.endswith("the best of the 1 pass before it is exported")
    assert plan.planned.exit_error_mm == pytest.approx(plan.passes[0]["exit_error_mm"])


def test_a_first_pass_that_fails_is_still_an_error():
    """With no pass to export the failure is the command's, naming step and angle."""
    scenario = parse_scenario(block("saint-venant-kirchhoff", 2.0, 0.2, 3.0))
    with pytest.raises(InsertionFailure, match=r"step \d+ \(needle rotation [\d.]+ rad\)"):
        run_plan(scenario, compare=False)


def test_a_verification_replay_that_fails_leaves_the_plan_unverified():
    scenario = parse_scenario(block("neo-hookean", 3.0, 0.3, 1.5))
    plan = plan_verified(scenario, compare=False)
    assert plan.verification.result is None and plan.verification.exit_error_mm is None
    assert plan.verification.no_replay.startswith("the replay on the refined model failed (step 4 (needle "
                                                  "rotation 0.800 rad): ")
    assert plan.verification.rounds[0]["no_replay"] == plan.verification.no_replay
    checks = [event.message for event in plan.planned.events if event.kind == EventKind.ACCURACY_CHECK]
    assert any(message.startswith("verification: the replay on the refined model failed (step 4") and
               message.endswith("(spacing 2 mm); verified exit error unknown") for message in checks)


def test_a_best_pass_that_left_early_is_run_again_braking_toward_its_exit():
    """The first pass brakes toward the step before the undeformed circle's exit; on a soft
    block its tip leaves three steps earlier, from full speed, and here it is the best pass.
    It is run once more with its offset, braking toward the step its tip left after: that
    path keeps the move limits and is exported, its exit a little further off."""
    from stitchplan.planning.move_limits import MoveLimits, path_smoothness

    scenario = parse_scenario(block("neo-hookean", 3.0, 0.3, 1.5))
    plan = run_plan(scenario, compare=False)
    limits = MoveLimits.for_needle(plan.planned.geometry, scenario.planner)
    first, braked = plan.passes[0], plan.passes[-1]
    assert first["braking_step"] == limits.last_step
    assert braked["braking_step"] == len(plan.shooting.prefix.reference.steps) < limits.last_step - 1
    np.testing.assert_array_equal(braked["offset_mm"], first["offset_mm"])
    assert min(record["exit_error_mm"] for record in plan.passes[:-1]) == first["exit_error_mm"]
    assert plan.planned.exit_error_mm == braked["exit_error_mm"]
    assert braked["exit_error_mm"] == pytest.approx(first["exit_error_mm"], abs=0.05)
    moves, second = path_smoothness(plan.exported_centers)
    assert moves <= limits.step_mm + 1e-6 and second <= limits.second_difference_mm + 1e-6
    assert not [event for event in plan.planned.events if event.kind == EventKind.PATH_LIMITS_EXCEEDED]


def test_a_path_that_stops_short_of_its_braking_says_it_breaks_the_move_limits(monkeypatch):
    """Were the best pass not run again braking toward its exit (a rerun that fails), its
    centre stops at the exit row from full speed. The summary's
    max_center_second_difference_mm shows it; an event says so and why."""
    from stitchplan.planning import planner
    from stitchplan.planning.move_limits import MoveLimits, path_smoothness

    monkeypatch.setattr(planner._PlanPasses, "_brake_for_exit", lambda passes, number: None)
    scenario = parse_scenario(block("neo-hookean", 3.0, 0.3, 1.5))
    plan = run_plan(scenario, compare=False)
    limits = MoveLimits.for_needle(plan.planned.geometry, scenario.planner)
    _, second = path_smoothness(plan.exported_centers)
    assert second > limits.second_difference_mm + 1e-6
    events = [event.message for event in plan.planned.events if event.kind == EventKind.PATH_LIMITS_EXCEEDED]
    assert len(events) == 1
    assert f"a second difference of {second:.3g} mm at row" in events[0]
    assert f"(limit {limits.second_difference_mm:.3g} mm)" in events[0]
    assert plan.passes[0]["exit_error_mm"] == plan.planned.exit_error_mm
    assert (f"the tip left the tissue after step {len(plan.planned.steps)}, before step {limits.last_step}, "
            "the step the centre brakes toward") in events[0]


def test_passes_after_the_first_brake_toward_where_its_tip_left():
    """On a 2.5 mm neo-Hookean slab (sh12_100x100 softened) the tip leaves steps before the
    undeformed circle would; the passes after the first brake toward the first pass's last
    step in the tissue, so the exported path (a later pass's) stops within the move limits."""
    from stitchplan.planning.move_limits import MoveLimits, path_smoothness

    raw = yaml.safe_load((CONFIGS / "sh12_100x100.yaml").read_text())
    raw["tissue"]["thickness"] = 2.5
    raw["tissue"]["material"]["model"] = "neo-hookean"
    scenario = parse_scenario(raw)
    plan = run_plan(scenario, compare=False)
    undeformed = MoveLimits.for_needle(plan.planned.geometry, scenario.planner)
    first = plan.shooting.prefix.reference
    assert len(first.steps) < undeformed.last_step
    # the exported pass left two steps or more before the undeformed circle's braking step
    assert len(plan.planned.steps) < undeformed.last_step - 1
    exported = [record["pass"] for record in plan.passes if record["exit_error_mm"] == plan.planned.exit_error_mm]
    assert exported[0] > 1
    moves, second = path_smoothness(plan.exported_centers)
    assert moves <= undeformed.step_mm + 1e-6 and second <= undeformed.second_difference_mm + 1e-6
    assert not [event for event in plan.planned.events if event.kind == EventKind.PATH_LIMITS_EXCEEDED]


def test_minres_asked_for_a_plan_says_the_planner_steps_solve_directly():
    """The planner's steps carry the centre as an unknown and solve directly whatever
    --linear-solver says; the run says so instead of reporting MINRES with no iterations."""
    raw = block("saint-venant-kirchhoff", 10.0, 0.0602, 0.7)
    raw["needle"]["linear_solver"] = "minres"
    plan = run_plan(parse_scenario(raw), compare=False)
    told = [event for event in plan.planned.events if event.kind == EventKind.MINRES_FALLBACK]
    assert len(told) == 1 and told[0].message.startswith("the planner's steps solve directly, not by MINRES")
    assert plan.planned.solver_counts["minres_iterations"] == 0


def test_a_failed_re_aimed_round_counts_in_the_planned_wall_time(monkeypatch):
    """The time a verification round's failed passes took is the plan's too: the summary's
    wall_seconds counts it, not only the rounds that ran to the exit."""
    from stitchplan.planning import verification

    scenario = parse_scenario({**block("saint-venant-kirchhoff", 10.0, 0.06, 0.7),
                               "planner": {"predicted_aim": False}})
    first_rounds = []

    def failing_re_aim(*args, **kwargs):
        if kwargs.get("aim") is None:
            plan = run_plan(*args, **kwargs)
            first_rounds.append(plan.planned.wall_seconds)
            return plan
        time.sleep(FAILED_ROUND_SECONDS)
        raise InsertionFailure("step 3 (needle rotation 0.600 rad): det F = -0.1 at (1, 2) mm")

    monkeypatch.setattr(verification, "run_plan", failing_re_aim)
    monkeypatch.setattr(verification, "VERIFIED_FACTOR", 0.0)  # every round misses: a re-aimed one follows
    plan = plan_verified(scenario, compare=False)
    assert len(first_rounds) == 1 and len(plan.verification.rounds) == 1
    assert any(event.kind == EventKind.PASS_FAILED and "verification round 2" in event.message
               for event in plan.planned.events)
    assert plan.planned.wall_seconds >= first_rounds[0] + FAILED_ROUND_SECONDS
