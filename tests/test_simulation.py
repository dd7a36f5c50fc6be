"""Needle insertion (thesis section 3.1.5, Algorithm 1) on small, coarse scenes:

- the constraint rows G and the tangent K + H of the saddle system against central finite
  differences of the constraint violation and of the residual;
- after every converged step each needle point lies on the needle, and the tip leaves the
  tissue on its boundary;
- without friction and cutting force nothing deforms and the tip exits where the rigid
  needle does, whichever tip tracking is used;
- MINRES with the block preconditioner and the direct solve give the same insertion;
- the inverse-gradient jump detector fires on a large-deformation scene ('auto' falls back
  to Levenberg-Marquardt and says so; 'inverse-gradient' alone fails naming step and angle);
- Algorithm 1's load ramp ends at the state the full load reaches at once, and stops with
  an InsertionFailure naming the step, the angle and SVK's compression instability where
  no increment is carried;
- pinned results of the shipped needle20 scenarios.

Tests that pin the thesis's point coupling's behaviour use `coupling: points`; the
linearisation checks run on both couplings (tests/test_needle_coupling.py has the mortar
coupling's own checks).
"""

from __future__ import annotations

import contextlib
import logging
import math
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import CONFIGS, TIGHT_NEEDLE_NEWTON

from stitchplan.config.scenario import load_scenario, parse_scenario
from stitchplan.errors import InsertionFailure
from stitchplan.events import EventKind
from stitchplan.needle import tip_tracking
from stitchplan.needle.equilibrium import RAMP_SMALLEST, NeedleInsertion
from stitchplan.needle.newton import newton_tolerances
from stitchplan.needle.prepared_tissue import PreparedTissue
from stitchplan.needle.insertion import FixedCenter, run_insertion
from stitchplan.needle.tip_tracking import track_step
from stitchplan.planning.planner import run_plan

PHANTOM = {"lame_lambda": 0.189151, "lame_mu": 0.147688}  # MPa, thesis appendix A.2


def small_scene(*, friction=0.0602, cutting_force=0.7, material=PHANTOM, spacing=4.0, thickness=10.0,
                solver=None, **needle):
    """40 x 30 mm phantom block clamped on the right, 8 mm needle entering (0, 22) turning cw
    in steps of 0.2 rad: 15 steps on 99 particles, the desired exit at (0, 6)."""
    raw = {"tissue": {"size": [40.0, 30.0], "thickness": thickness, "clamped": ["right"],
                      "material": dict(material)},
           "discretization": {"spacing": spacing},
           "needle": {"radius": 8.0, "entry": [0.0, 22.0], "turn": "cw", "step": 0.2,
                      "friction": friction, "cutting_force": cutting_force, **needle}}
    if solver is not None:
        raw["solver"] = solver
    return parse_scenario(raw)


def track_tolerance(result) -> float:
    """The largest |g| (mm) a converged needle step of `result` leaves: its Newton tolerance x R."""
    return newton_tolerances(result.scenario)[1] * result.geometry.radius


def advance(insertion: NeedleInsertion, steps: int) -> None:
    """Drive `steps` steps of Algorithm 1 on an insertion that holds only its entry point."""
    geometry = insertion.geometry
    for step in range(1, steps + 1):
        rotation = step * geometry.step
        point, _ = track_step(insertion, step, rotation)
        insertion.add_point(point)
        insertion.equilibrate(rotation, step)


def started(scenario, steps: int = 0, **options) -> NeedleInsertion:
    insertion = NeedleInsertion(scenario, **options)
    insertion.add_point(insertion.geometry.entry.copy())
    advance(insertion, steps)
    return insertion


def linearised(insertion: NeedleInsertion, free, multipliers, center):
    """The residuals of eq. 3.62 at a state, with G and the constraint curvature H there."""
    state = insertion.residuals(free, multipliers, center)
    coupling = insertion.coupling
    return state, coupling.constraint_matrix(state.normal), coupling.curvature(multipliers, state.normal, state.rho)


def on_edge_distance(point, size) -> float:
    x, y = point
    return min(abs(x), abs(x - size[0]), abs(y), abs(y - size[1]))


@pytest.fixture(scope="module")
def direct_run():
    """The small scene (point coupling) with the direct solver and Levenberg-Marquardt tip tracking, with each
    converged step's needle-point distances to the needle, recomputed from the state, and its particle
    displacements made as the step ended."""
    distances, particles = [], []

    class Inspect(FixedCenter):
        def correct(self, insertion, step, rotation):
            coefficients = insertion.model.boundary.free_map @ insertion.free  # (NP, 2)
            u = insertion.model.shape_functions_at(insertion.points).values @ coefficients  # (k, 2)
            distances.append(np.linalg.norm(insertion.points + u - insertion.center, axis=1)
                             - insertion.geometry.radius)
            particles.append(insertion.particle_displacements())  # the step's, made as it ends
            return 0

    result = run_insertion(small_scene(coupling="points"), control=Inspect(), linear_solver="direct",
                           tip_tracking="levenberg-marquardt")
    return result, distances, particles


def test_a_run_along_an_earlier_runs_centres_takes_its_steps_over():
    """run_insertion `start_from`: while a run follows an earlier run's centres on the same
    model, each step's tip point, state and needle coupling are the earlier run's (taken
    over, no Newton iteration); from the first step whose centre differs it solves again."""
    scenario = small_scene()
    tissue = PreparedTissue(scenario)
    first = run_insertion(scenario, tissue=tissue)
    centers = np.array([first.center_after(n) for n in range(len(first.steps) + 1)])
    again = run_insertion(scenario, center_path=centers, tissue=tissue, start_from=first)
    assert [s.newton_iterations for s in again.steps] == [0] * len(first.steps)
    np.testing.assert_array_equal(again.achieved_exit, first.achieved_exit)
    for mine, earlier in zip(again.states, first.states, strict=True):
        np.testing.assert_array_equal(mine.free, earlier.free)
        np.testing.assert_array_equal(mine.multipliers, earlier.multipliers)
    moved = centers.copy()
    moved[6:] += [0.02, 0.0]  # from step 6 on
    apart = run_insertion(scenario, center_path=moved, tissue=tissue, start_from=first)
    assert [s.newton_iterations for s in apart.steps[:5]] == [0] * 5
    assert min(s.newton_iterations for s in apart.steps[5:]) > 0
    assert apart.exit_error_mm != first.exit_error_mm


def test_a_run_that_takes_steps_over_only_ends_as_if_made_alone():
    """run_insertion `take_over_only`: the steps whose centres are the earlier run's are taken
    over with its needle coupling and its solver's factor and kept columns
    (SaddlePointSolver.state), the others start from this run's previous step alone; so the
    run is, to the last bit, the one made from no earlier run. A state sent to another
    process leaves the factor behind."""
    import pickle

    scenario = small_scene()
    tissue = PreparedTissue(scenario)
    first = run_insertion(scenario, tissue=tissue)
    moved = np.array([first.center_after(n) for n in range(len(first.steps) + 1)])
    moved[6:] += [0.02, 0.0]  # from step 6 on
    alone = run_insertion(scenario, center_path=moved, tissue=tissue)
    taken = run_insertion(scenario, center_path=moved, tissue=tissue, start_from=first, take_over_only=True)
    assert [s.newton_iterations for s in taken.steps[:5]] == [0] * 5
    assert [s.newton_iterations for s in taken.steps[5:]] == [s.newton_iterations for s in alone.steps[5:]]
    assert taken.achieved_exit.tolist() == alone.achieved_exit.tolist()
    for mine, made_alone in zip(taken.states, alone.states, strict=True):
        np.testing.assert_array_equal(mine.free, made_alone.free)
        np.testing.assert_array_equal(mine.multipliers, made_alone.multipliers)
    assert first.states[-1].solver is not None
    assert pickle.loads(pickle.dumps(first.states[-1])).solver is None


def test_the_steps_a_stopped_run_had_done_are_taken_over_alike():
    """A centre control that stops a run (InsertionStopped, a replay helper's dropped pass)
    gets the steps done so far; a later run along centres that agree with them up to some
    step (its entry centre too, which need not be the scenario's) takes those over and solves
    on from there, to the last bit the run made alone, also past the last step the stopped
    run had done."""
    from stitchplan.needle.insertion import CenterReplay, InsertionStopped

    class StopAt(CenterReplay):
        def predict(self, center, step):
            if step == 9:
                raise InsertionStopped
            return super().predict(center, step)

    scenario = small_scene()
    tissue = PreparedTissue(scenario)
    first = run_insertion(scenario, tissue=tissue)
    centers = np.array([first.center_after(n) for n in range(len(first.steps) + 1)])
    centers[0] = np.nextafter(centers[0], np.inf)  # an entry centre not the scenario's (a rounded trajectory.csv)
    with pytest.raises(InsertionStopped) as stopped:
        run_insertion(scenario, control=StopAt(centers), tissue=tissue)
    done = stopped.value.done
    assert len(done.steps) == len(done.states) == 8
    for moved_from in (6, len(centers)):  # leaving the stopped run's centres at step 6; never
        moved = centers.copy()
        moved[moved_from:] += [0.02, 0.0]
        alone = run_insertion(scenario, center_path=moved, tissue=tissue)
        taken = run_insertion(scenario, center_path=moved, tissue=tissue, start_from=done, take_over_only=True)
        shared = min(moved_from - 1, 8)
        assert [s.newton_iterations for s in taken.steps[:shared]] == [0] * shared
        assert ([s.newton_iterations for s in taken.steps[shared:]]
                == [s.newton_iterations for s in alone.steps[shared:]])
        assert taken.achieved_exit_def.tolist() == alone.achieved_exit_def.tolist()

def test_a_steps_first_residual_reuses_the_stress_where_the_step_before_ended(monkeypatch):
    """Each step's Newton solve starts where the step before ended, at the displacements of
    its last residual: the internal force there is kept, not evaluated again, and the run
    is the same to the last bit as one that evaluates every residual's stress."""
    from stitchplan.tissue.assembly import Assembler

    scenario = small_scene()
    reference = run_insertion(scenario)
    counts = {"updates": 0, "residuals": 0}
    update, residuals = Assembler.update, NeedleInsertion.residuals

    def counted_update(self, *args):
        counts["updates"] += 1
        return update(self, *args)

    def counted_residuals(self, *args):
        counts["residuals"] += 1
        return residuals(self, *args)

    monkeypatch.setattr(Assembler, "update", counted_update)
    monkeypatch.setattr(NeedleInsertion, "residuals", counted_residuals)
    result = run_insertion(scenario)
    assert counts["updates"] <= counts["residuals"] - (len(result.steps) - 1)
    np.testing.assert_array_equal(result.achieved_exit, reference.achieved_exit)

    def uncached(self, *args):  # every residual evaluates the stress
        self._last_internal = None
        return residuals(self, *args)

    monkeypatch.setattr(NeedleInsertion, "residuals", uncached)
    np.testing.assert_array_equal(run_insertion(scenario).achieved_exit, reference.achieved_exit)


# --- linearisation against finite differences --------------------------------------------


@pytest.mark.parametrize("coupling", ["points", "mortar"])
def test_constraint_rows_match_finite_differences(rng, coupling):
    """G (n_dof x m) of the coupling equals the central difference of the violation
    (points: g_k = |X_k + u(X_k) - C| - R; mortar: the weighted means of it along the track)
    with respect to the free coefficients, in random directions and along single
    coefficients of the track's neighbourhood (h = 1e-6 mm: the truncation error
    h^2 |g''| ~ 1e-13 and round-off 1e-16 / h ~ 1e-10 stay below 1e-8)."""
    insertion = started(small_scene(coupling=coupling, spacing=2.0), steps=4)
    free = insertion.free + 0.05 * rng.standard_normal(insertion.free.shape)
    multipliers = rng.standard_normal(insertion.coupling.multiplier_count)
    center = insertion.center
    state, constraints, _ = linearised(insertion, free, multipliers, center)
    count = 5 if coupling == "points" else insertion.coupling.multiplier_count
    assert constraints.shape == (free.size, count) and len(state.violation) == count >= 2
    dense = constraints.toarray()

    def violation_at(vector):
        return insertion.residuals(vector.reshape(free.shape), multipliers, center).violation

    h = 1e-6
    directions = list(rng.standard_normal((6, free.size)))
    directions += [np.eye(free.size)[j] for j in np.flatnonzero(np.abs(dense).sum(axis=1))]
    assert len(directions) > 20
    for direction in directions:
        difference = (violation_at(free.ravel() + h * direction) - violation_at(free.ravel() - h * direction)) / (2 * h)
        np.testing.assert_allclose(difference, dense.T @ direction, rtol=0, atol=1e-8)


@pytest.mark.parametrize("coupling", ["points", "mortar"])
def test_tangent_matches_finite_differences_of_the_residual(rng, coupling):
    """Without needle loads the residual is f_int(d) + G(d) lambda, and its derivative is the
    saddle block K + H (H: the multiplier-weighted curvature of the constraints, eq. 3.62);
    its derivative with respect to lambda is G. Checked on a deformed state with random
    multipliers, in random directions (relative error below 1e-6)."""
    insertion = started(small_scene(friction=0.0, cutting_force=0.0, coupling=coupling, spacing=2.0), steps=3)
    free = 0.05 * rng.standard_normal(insertion.free.shape)
    multipliers = 0.1 * rng.standard_normal(insertion.coupling.multiplier_count)
    center = insertion.center
    state, constraints, curvature = linearised(insertion, free, multipliers, center)
    assert state.needle_force == 0.0
    tangent = insertion.assembler.tangent_matrix() + curvature
    assert abs(curvature).sum() > 0.0

    def residual(vector, lam):
        return insertion.residuals(vector.reshape(free.shape), lam, center).residual

    h = 1e-6
    for direction in rng.standard_normal((4, free.size)):
        difference = (residual(free.ravel() + h * direction, multipliers)
                      - residual(free.ravel() - h * direction, multipliers)) / (2 * h)
        exact = tangent @ direction
        assert np.linalg.norm(difference - exact) <= 1e-6 * np.linalg.norm(exact)
    direction = rng.standard_normal(len(multipliers))
    difference = (residual(free.ravel(), multipliers + h * direction)
                  - residual(free.ravel(), multipliers - h * direction)) / (2 * h)
    np.testing.assert_allclose(difference, constraints @ direction, rtol=0, atol=1e-9)


# --- converged steps ---------------------------------------------------------------------


def test_needle_points_stay_on_the_needle_after_every_step(direct_run):
    """After each converged step every needle point's spatial position X_k + u(X_k), computed
    afresh from the RK interpolant of the state, is on the circle to 1e-6 mm; the steps report
    the constraint violation below the solver's tolerance."""
    result, distances, _ = direct_run
    assert len(distances) == len(result.steps) == 15
    for step, distance in enumerate(distances, start=1):
        assert len(distance) == step + 1  # entry plus one point per step
        assert np.abs(distance).max() <= 1e-6, step
    assert max(s.constraint_violation for s in result.steps) <= track_tolerance(result)
    assert all(s.newton_iterations >= 1 for s in result.steps)
    # the tissue does deform: the needle drags it by a good fraction of a millimetre
    assert np.linalg.norm(result.displacements[-1], axis=1).max() > 0.2


def test_the_particle_displacements_made_when_read_are_each_steps_to_the_last_bit(direct_run):
    """InsertionResult.displacements makes every step's particle displacements in one
    product from the coefficients the run kept: the values a product as each step ended gave."""
    result, _, particles = direct_run
    assert result.displacements.shape == (len(result.steps) + 1, len(result.model.particles), 2)
    assert not result.displacements[0].any()  # at rest
    for step, made_then in enumerate(particles, start=1):
        assert np.array_equal(result.displacements[step], made_then), step


def test_tip_leaves_the_tissue_on_its_boundary(direct_run):
    """The achieved exit is a boundary point (1e-9 mm), reached after the last step, whose
    spatial position lies on the needle; the exit errors are the distances the summary reports."""
    result, _, _ = direct_run
    size = result.scenario.tissue.size
    assert on_edge_distance(result.achieved_exit, size) <= 1e-9
    assert on_edge_distance(result.desired_exit, size) <= 1e-9
    assert result.steps[-1].rotation < result.exit_rotation <= result.steps[-1].rotation + result.geometry.step
    center = result.steps[-1].center
    assert abs(np.linalg.norm(result.achieved_exit_def - center) - result.geometry.radius) <= 1e-6
    assert result.exit_error_mm == pytest.approx(np.linalg.norm(result.achieved_exit_def - result.desired_exit_def))
    assert 0.05 < result.exit_error_mm < 2.0  # the tissue was dragged: the exit moved


@pytest.mark.parametrize("tracking", ["levenberg-marquardt", "inverse-gradient"])
def test_without_friction_and_cutting_the_tissue_does_not_deform(tracking):
    """No needle load: the constrained equilibrium is u = 0, the needle points are the rigid
    needle's, and the tip exits at the desired exit (< 1e-6 mm) with either tip tracking
    (mortar coupling: its Gauss points ask for the chord's distance from C, so the rigid
    needle's track is satisfied at u = 0 and nothing is pushed outward by the chord's sag)."""
    result = run_insertion(small_scene(friction=0.0, cutting_force=0.0), tip_tracking=tracking)
    assert np.abs(result.displacements).max() <= 1e-10
    assert result.exit_error_mm < 1e-6 and result.exit_error_material_mm < 1e-6
    geometry = result.geometry
    for record in result.steps:
        np.testing.assert_allclose(record.tip_reference, geometry.tip(record.rotation), atol=1e-8)
    assert {s.tracking for s in result.steps} == {tracking} and not result.events


def test_newton_tolerances_follow_the_coupling_unless_the_scenario_sets_them():
    """A needle step's Newton stops at 1e-3 of the needle force and 1e-7 R with the mortar
    coupling and at 5e-6 and 1e-9 R with the point coupling (nearly dependent constraint rows);
    a solver block's values win, and a run records the tolerances it stopped at."""
    assert newton_tolerances(small_scene()) == (1e-3, 1e-7)
    assert newton_tolerances(small_scene(coupling="points")) == (5e-6, 1e-9)
    assert newton_tolerances(small_scene(solver={"needle_residual_tolerance": 2e-4})) == (2e-4, 1e-7)
    assert newton_tolerances(small_scene(coupling="points", solver={"needle_constraint_tolerance": 3e-8})) == (
        5e-6, 3e-8)
    insertion = NeedleInsertion(small_scene(coupling="points"))
    assert (insertion.residual_tolerance, insertion.constraint_tolerance) == (5e-6, pytest.approx(1e-9 * 8.0))


def test_minres_and_direct_solves_agree(direct_run):
    """MINRES with diag(K0^-1, S^-1) (S by bordering) reproduces the direct insertion: exit
    points to 1e-7 mm and every particle's final displacement to 1e-7 mm (both Newton runs
    stop at a residual of 1e-9 of the needle force, so both are converged to well below that)."""
    scenario = replace(direct_run[0].scenario, solver=replace(direct_run[0].scenario.solver, needle_residual_tolerance=1e-9))
    direct = run_insertion(scenario, tip_tracking="levenberg-marquardt")
    minres = run_insertion(scenario, linear_solver="minres", tip_tracking="levenberg-marquardt")
    assert len(minres.steps) == len(direct.steps)
    assert minres.solver_counts["minres_iterations"] > 0 and minres.solver_counts["factorizations"] == 1  # K0's
    assert sum(s.minres_iterations for s in minres.steps) == minres.solver_counts["minres_iterations"]
    assert minres.solver_counts["minres_fallbacks"] == 0 and not minres.events
    np.testing.assert_allclose(minres.achieved_exit, direct.achieved_exit, rtol=0, atol=1e-7)
    np.testing.assert_allclose(minres.achieved_exit_def, direct.achieved_exit_def, rtol=0, atol=1e-7)
    np.testing.assert_allclose(minres.displacements[-1], direct.displacements[-1], rtol=0, atol=1e-7)
    assert minres.exit_error_mm == pytest.approx(direct.exit_error_mm, abs=1e-7)


# --- tip-tracking jumps ------------------------------------------------------------------


def jumping_scene(tip_tracking):
    """The small scene with a 3 N cutting force: the tip drags the soft phantom by ~1 mm and
    F at the tip no longer describes the field one step ahead."""
    return small_scene(cutting_force=3.0, tip_tracking=tip_tracking, coupling="points")


def test_auto_tip_tracking_falls_back_to_levenberg_marquardt_at_a_jump():
    result = run_insertion(jumping_scene("auto"))
    assert result.events and all(e.kind is EventKind.TIP_TRACKING_FALLBACK for e in result.events)
    assert (result.events[0].step, result.events[0].angle_rad) == (3, pytest.approx(0.6))
    used = [s.tracking for s in result.steps]
    assert used[:2] == ["inverse-gradient"] * 2 and used[2] == "levenberg-marquardt"
    assert used.count("levenberg-marquardt") == len(result.events)
    assert on_edge_distance(result.achieved_exit, result.scenario.tissue.size) <= 1e-9
    assert max(s.constraint_violation for s in result.steps) <= track_tolerance(result)
    assert np.linalg.norm(result.displacements[-1], axis=1).max() > 0.5


def test_strict_inverse_gradient_fails_at_the_jump_naming_step_and_angle():
    with pytest.raises(InsertionFailure) as failure:
        run_insertion(jumping_scene("inverse-gradient"))
    message = str(failure.value)
    assert message.startswith("inverse-gradient tip tracking jumped at step 3 (needle rotation 0.600 rad)")


# --- Algorithm 1's ramp -----------------------------------------------------------------------


@pytest.mark.parametrize("coupling", ["points", "mortar"])
def test_ramped_load_ends_at_the_state_the_full_load_reaches_at_once(coupling, monkeypatch):
    """Equilibrium is path-independent for a hyperelastic tissue: a step whose whole-load try
    fails is ramped through half its cutting force and added friction, then the rest, and
    ends at the state the full load reaches in one Newton solve, to 1e-8 mm, over three
    steps (the tracked points agree as well). Both converge to 1e-10 of the needle force, so
    that the two paths' own residuals stay far below that."""
    scenario = small_scene(coupling=coupling)
    scenario = replace(scenario, solver=replace(scenario.solver, needle_residual_tolerance=1e-10))
    direct = started(scenario, steps=3)
    assert direct.ramp_increments == 0
    ramped = started(scenario)
    first_tries = []
    original = NeedleInsertion._newton

    def halved_first(self, rotation, step, aim=None):  # fail the whole-load try, once per step
        if self.coupling.load_factor == 1.0 and step not in first_tries:
            first_tries.append(step)
            raise InsertionFailure("forced")
        return original(self, rotation, step, aim)

    monkeypatch.setattr(NeedleInsertion, "_newton", halved_first)
    counts = []
    for step in range(1, 4):
        before = ramped.ramp_increments
        advance_one(ramped, step)
        counts.append(ramped.ramp_increments - before)
    assert counts == [1, 1, 1]
    np.testing.assert_allclose(ramped.points, direct.points, rtol=0, atol=1e-8)
    np.testing.assert_allclose(ramped.particle_displacements(), direct.particle_displacements(), rtol=0, atol=1e-8)


def advance_one(insertion: NeedleInsertion, step: int) -> None:
    rotation = step * insertion.geometry.step
    point, _ = track_step(insertion, step, rotation)
    insertion.add_point(point)
    insertion.equilibrate(rotation, step)


def failing_first_tries(insertion: NeedleInsertion, failures: int) -> list[float]:
    """Make the insertion's Newton fail its first `failures` tries; returns the load factors
    it is tried at, as they come."""
    original, tried = NeedleInsertion._newton, []

    def limited(rotation, step, aim=None):
        tried.append(insertion.coupling.load_factor)
        if len(tried) <= failures:
            raise InsertionFailure("forced")
        return original(insertion, rotation, step, aim)

    insertion._newton = limited
    return tried


def test_ramp_halves_the_increment_until_newton_converges():
    """A Newton that fails above 30 % of the step's load: the ramp halves its increment
    (1, 1/2, 1/4) and then climbs 1/4 -> 1/2 -> 1 in doubling increments, the load carried."""
    insertion = started(small_scene())
    tried = failing_first_tries(insertion, 2)
    advance_one(insertion, 1)
    assert tried == [1.0, 0.5, 0.25, 0.75, 1.0]
    assert insertion.coupling.load_factor == 1.0 and insertion.ramp_increments == 2


def test_ramp_does_not_try_the_whole_load_again_from_where_it_failed():
    """Carried to 50 %, the doubled increment is capped at the whole load; when that fails,
    its half reaches the whole load again from the same state: the ramp goes on to 75 %
    instead of a second, identical try (and a third at a quarter)."""
    insertion = started(small_scene())
    original, tried = NeedleInsertion._newton, []

    def failing_whole_twice(rotation, step, aim=None):
        tried.append(insertion.coupling.load_factor)
        if tried.count(1.0) <= 2 and insertion.coupling.load_factor == 1.0:
            raise InsertionFailure("forced")
        return original(insertion, rotation, step, aim)

    insertion._newton = failing_whole_twice
    advance_one(insertion, 1)
    assert tried == [1.0, 0.5, 1.0, 0.75, 1.0]
    assert insertion.coupling.load_factor == 1.0


def test_a_long_ramp_reports_its_cuts_and_warns_once(monkeypatch, caplog):
    """The ramp reports each cut and each increment carried (on_ramp: the progress bar's note),
    and a step still cutting after LONG_STEP_SECONDS says so once by a warning, which is shown
    without -v (a 100 mm x 0.5 mm strip's first step cut for minutes with nothing on screen).
    The limit is patched to 0 here; at its 30 s this step gives no warning."""
    insertion = started(small_scene())
    reported = []
    failing_first_tries(insertion, 2)
    insertion.on_ramp = lambda *state: reported.append(state)
    monkeypatch.setattr("stitchplan.needle.equilibrium.LONG_STEP_SECONDS", 0.0)
    with caplog.at_level("WARNING", logger="stitchplan"):
        advance_one(insertion, 1)
    assert reported == [(1, 0.0, 0.5), (1, 0.0, 0.25), (1, 0.25, 0.5), (1, 0.75, 1.0)]
    (record,) = caplog.records
    assert record.levelname == "WARNING" and record.getMessage().startswith(
        f"step 1 (needle rotation {insertion.geometry.step:.3f} rad) is still cutting its load after ")
    assert record.getMessage().endswith("0 % carried, the ramp goes on in increments of 50 % down to 1.56 % "
                                        "(-v shows each cut)")
    caplog.clear()
    monkeypatch.undo()
    again = started(small_scene())
    failing_first_tries(again, 1)
    with caplog.at_level("WARNING", logger="stitchplan"):
        advance_one(again, 1)
    assert not caplog.records


def test_the_progress_bar_notes_a_step_cutting_its_load(monkeypatch):
    """simulate hands the run an on_ramp that sets the bar's label to the ramp's state, and its
    step callback puts the label back."""
    from stitchplan.cli import runs
    from stitchplan.io import progress

    calls = []

    @contextlib.contextmanager
    def bar(label, total):
        yield lambda n=1, description=None: calls.append((n, description))

    def simulated(scenario, **options):
        options["on_ramp"](4, 0.375, 0.125)
        options["on_step"](None)
        return "result", None

    monkeypatch.setattr(progress, "progress_bar", bar)
    monkeypatch.setattr("stitchplan.planning.verification.simulate_with_estimate", simulated)
    scenario = small_scene()
    assert runs.simulate_with_replays(Path("scene.yaml"), scenario, None, None, False, False) == ("result", None)
    assert calls == [(0, "needle steps (step 4: 38 % of its load carried, increments of 12.5 %)"),
                     (1, "needle steps")]


def test_ramp_refuses_an_unstable_state_and_takes_a_smaller_increment():
    """Within a cut ramp a converged state whose least stiffness on the needle's constraints
    is negative (reported so here, once) is refused like a failed Newton: the whole load
    fails, the half converges to the "unstable" state and is refused, the quarter and then
    3/4 are checked and kept, the whole load carried; the step ends where an unramped step
    does, to 1e-8 mm (hyperelastic equilibrium does not depend on the path; both solved to
    1e-10 of the needle force)."""
    from stitchplan.needle.stability import SoftestMode

    scenario = small_scene()
    scenario = replace(scenario, solver=replace(scenario.solver, needle_residual_tolerance=1e-10))
    direct = started(scenario)
    advance_one(direct, 1)
    insertion = started(scenario)
    original = NeedleInsertion._newton
    tried, checked = [], []

    def limited(rotation, step, aim=None):
        tried.append(insertion.coupling.load_factor)
        if len(tried) == 1:
            raise InsertionFailure("forced")
        return original(insertion, rotation, step, aim)

    softest = insertion.softest_mode

    def reported():
        checked.append(insertion.coupling.load_factor)
        mode = softest()
        return SoftestMode(-1.0, mode.mode) if len(checked) == 1 else mode

    insertion._newton, insertion.softest_mode = limited, reported
    advance_one(insertion, 1)
    assert tried == [1.0, 0.5, 0.25, 0.75, 1.0]
    assert checked == [0.5, 0.25, 0.75]  # the increments of the cut ramp, not the whole load's first try
    assert insertion.coupling.load_factor == 1.0 and insertion.ramp_increments == 2
    np.testing.assert_allclose(insertion.particle_displacements(), direct.particle_displacements(), rtol=0, atol=1e-8)


def test_saint_venant_kirchhoff_too_soft_for_the_cutting_force_stops_naming_step_and_cure(caplog):
    """The small scene at an effective thickness of 1.5 mm (0.7 N / 1.5 mm on the phantom):
    SVK's stress in compression peaks and turns back, so the tissue in front of the tip has no
    equilibrium beyond ~90 % of the first step's load. The ramp carries what it can, then
    stops with an InsertionFailure naming the step, the angle, the share carried, the tissue's
    least stiffness on the needle's constraints falling (at the entry and tip), SVK's
    compression instability and `model: neo-hookean`; neo-Hookean runs the same scene."""
    soft = {"thickness": 1.5}
    with pytest.raises(InsertionFailure) as failure, caplog.at_level("INFO", logger="stitchplan.needle"):
        run_insertion(small_scene(material={"model": "saint-venant-kirchhoff", **PHANTOM}, **soft))
    message = str(failure.value)
    # the last cut the log announces is the increment the error says failed
    announced = [r.getMessage() for r in caplog.records if "the ramp goes on" in r.getMessage()]
    assert announced and announced[-1].endswith(f"in increments of {100 * RAMP_SMALLEST:.3g} %")
    assert message.startswith("step 1 (needle rotation 0.200 rad): the needle's load could not be carried: ")
    carried = float(message.split("carried: ")[1].split(" %")[0])
    assert 50.0 <= carried < 100.0
    assert f"the next {100 * RAMP_SMALLEST:.3g} % increment failed" in message
    # the tissue gives way at the needle: its least stiffness on the constraints falls over the step
    softening = re.search(r"least stiffness on the needle's constraints fell to (\d+) % of the step's start "
                          r"\(at zero the tissue has no stable equilibrium\), its mode largest at \[0, 22.5\] mm, "
                          r"the needle's entry and tip; ", message)
    assert softening is not None and int(softening.group(1)) < 50, message
    assert "Saint Venant-Kirchhoff is unstable under strong compression" in message
    assert "`model: neo-hookean`" in message
    result = run_insertion(small_scene(material={"model": "neo-hookean", **PHANTOM}, **soft))
    assert on_edge_distance(result.achieved_exit, result.scenario.tissue.size) <= 1e-9


# --- shipped scenarios ---------------------------------------------------------------------

# Exit errors (mm) of the shipped needle scenarios at their default spacings with the default
# mortar coupling, pinned to 2 %: the direct and MINRES solves agree to 1e-9 mm and Newton's
# tolerance moves the value by far less, while halving the spacing moves it by 0.03-2.0 %
# (benchmarks/results/needle_coupling.md, coupling `shipped`) - a 2 % change at a fixed spacing means the model
# (loads, constraint, tip tracking, discretization defaults) changed, which should be deliberate.
NEEDLE20_EXIT_ERROR = {30: 0.021317, 25: 0.018737, 20: 0.016987, 18: 0.016304}  # Levenberg-Marquardt tracking
SH12_SERIES_EXIT_ERROR = {"sh12_100x100_mid": 0.360456, "sh12_100x50": 0.490861, "sh12_100x40": 0.565963,
                          "sh12_100x30": 0.711393}


@pytest.mark.parametrize("entry_y", sorted(NEEDLE20_EXIT_ERROR))
def test_shipped_needle20_scenarios_run_to_the_bottom_edge(entry_y):
    result = run_insertion(load_scenario(CONFIGS / f"needle20_entry{entry_y}.yaml"))
    assert abs(result.achieved_exit[1]) <= 1e-9  # out through the bottom edge, as documented
    assert result.exit_error_mm == pytest.approx(NEEDLE20_EXIT_ERROR[entry_y], rel=0.02)
    assert max(s.constraint_violation for s in result.steps) <= track_tolerance(result)
    assert result.steps[-1].rotation < result.geometry.exit_rotation + result.geometry.step


def test_shipped_sh12_block_series_exit_error_grows_as_the_block_narrows():
    """configs/sh12_100x{100_mid,50,40,30}.yaml: each tip leaves through the left edge near
    its desired exit, with the pinned exit error, growing as the block narrows (thesis
    table 5.1's trend)."""
    errors = []
    for name, pinned in SH12_SERIES_EXIT_ERROR.items():
        result = run_insertion(load_scenario(CONFIGS / f"{name}.yaml"))
        assert abs(result.achieved_exit[0]) <= 1e-9
        assert result.exit_error_mm == pytest.approx(pinned, rel=0.02), name
        errors.append(result.exit_error_mm)
    assert errors == sorted(errors)


# --- saddle-point solves -------------------------------------------------------------------


def dense_rest_stiffness(insertion: NeedleInsertion) -> np.ndarray:
    """K0, the tangent at zero deformation, as a dense matrix."""
    from stitchplan.tissue.assembly import Assembler

    assembler = Assembler(insertion.model)
    assembler.update(np.tile(np.eye(2), (len(insertion.model.quadrature_weights), 1, 1)))
    return assembler.tangent_matrix().toarray()


def test_schur_preconditioner_stays_positive_definite_with_nearly_dependent_points():
    """60 needle points 0.16 mm apart on a 4 mm particle grid make S = G^T K0^-1 G nearly
    singular (cond > 1e8). The Cholesky factor bordered row by row still reproduces S to 1e-8
    of its norm (it factors S + 1e-12 diag S) with positive pivots, so S^-1 x stays an SPD map."""
    scenario = small_scene(step=0.02, linear_solver="minres", coupling="points")
    insertion = NeedleInsertion(scenario)
    for rotation in np.arange(60) * 0.02:
        insertion.add_point(insertion.geometry.tip(rotation))
    state, constraints, _ = linearised(insertion, insertion.free, insertion.multipliers, insertion.center)
    schur = insertion.saddle.schur
    schur.refresh(constraints, insertion.coupling.expanded_rows, insertion.coupling.weights_matrix(state.normal))
    k0 = dense_rest_stiffness(insertion)
    g = constraints.toarray()
    exact = g.T @ np.linalg.solve(k0, g)
    assert np.linalg.cond(exact) > 1e8
    lower = schur.cholesky
    assert np.all(np.diag(lower) > 0.0) and np.allclose(lower, np.tril(lower))
    assert np.linalg.norm(lower @ lower.T - exact) <= 1e-8 * np.linalg.norm(exact)
    probes = np.random.default_rng(3).standard_normal((60, 10))
    assert np.all(np.einsum("ij,ij->j", probes, schur.solve(probes)) > 0.0)


@pytest.mark.parametrize("minres_rtol", [None, 1e-3])  # the default; loose: MINRES stops early and restarts
def test_minres_solution_meets_its_true_residual_tolerance(rng, minres_rtol):
    """solve_minres returns a Newton step whose true residual |b - A x| / |b| is below
    minres_true_rtol (scipy's own stopping test is a backward error in the preconditioned
    norm that can pass at 1e-4 ... 1 on these systems), also where it gets there by
    restarting MINRES on the remainder and adding up the corrections."""
    insertion = started(small_scene(linear_solver="minres"), steps=5)
    if minres_rtol is not None:
        insertion.saddle.minres_rtol = minres_rtol
    free, multipliers = insertion.free + 0.02 * rng.standard_normal(insertion.free.shape), insertion.multipliers
    state, constraints, curvature = linearised(insertion, free, multipliers, insertion.center)
    rhs = -np.concatenate([state.residual, state.violation])
    solver = insertion.saddle
    solution, iterations = solver.solve_minres(lambda v: insertion.assembler.tangent_product(v) + curvature @ v,
                                               constraints, rhs, insertion.coupling.expanded_rows,
                                               insertion.coupling.weights_matrix(state.normal))
    assert solution is not None and 0 < iterations <= solver.minres_maxiter
    n = constraints.shape[0]
    tangent = insertion.assembler.tangent_matrix() + curvature
    true = np.concatenate([tangent @ solution[:n] + constraints @ solution[n:], constraints.T @ solution[:n]]) - rhs
    assert np.linalg.norm(true) <= solver.minres_true_rtol * np.linalg.norm(rhs)


def test_stagnating_minres_falls_back_to_the_direct_solve_and_says_so():
    """With a MINRES budget of 3 iterations every linear solve falls back: the step still
    converges (through the direct solve) and each fallback is logged as an event."""
    insertion = started(small_scene(linear_solver="minres"))
    insertion.saddle.minres_maxiter = 3
    advance(insertion, 2)
    assert insertion.saddle.fallbacks >= 2 and insertion.saddle.factorizations >= 1
    assert len(insertion.events) == insertion.saddle.fallbacks
    assert all(e.kind is EventKind.MINRES_FALLBACK for e in insertion.events)
    assert (insertion.events[0].step, insertion.events[0].angle_rad) == (1, pytest.approx(0.2))
    assert insertion.events[0].message.startswith("MINRES stagnated after 3 iterations")
    assert insertion.last_violation <= insertion.constraint_tolerance


@pytest.mark.parametrize("linear_solver", ["minres", "direct"])
def test_condition_numbers_match_generalised_eigenvalues(linear_solver):
    """NeedleInsertion.condition_numbers: cond of the saddle matrix A, and of P^-1 A with
    P = diag(K0, G^T K0^-1 G), against dense (generalised) symmetric eigenvalue problems,
    with either linear solver (the direct one builds K0 only for this)."""
    import scipy.linalg

    insertion = started(small_scene(spacing=5.0, linear_solver=linear_solver), steps=3)
    saddle_cond, preconditioned_cond = insertion.condition_numbers()
    _, constraints, curvature = linearised(insertion, insertion.free, insertion.multipliers, insertion.center)
    g = constraints.toarray()
    n, k = g.shape
    stiffness = insertion.assembler.tangent_matrix().toarray() + curvature.toarray()
    saddle = np.block([[stiffness, g], [g.T, np.zeros((k, k))]])
    k0 = dense_rest_stiffness(insertion)
    preconditioner = scipy.linalg.block_diag(k0, g.T @ np.linalg.solve(k0, g))
    plain = np.abs(np.linalg.eigvalsh(saddle))
    general = np.abs(scipy.linalg.eigh(saddle, preconditioner, eigvals_only=True))
    assert saddle_cond == pytest.approx(plain.max() / plain.min(), rel=1e-6)
    assert preconditioned_cond == pytest.approx(general.max() / general.min(), rel=1e-6)
    assert preconditioned_cond < 10.0 < saddle_cond


# --- tip tracking: Newton first, Levenberg-Marquardt where it fails ---------------------------


def test_newton_tip_tracking_finds_levenberg_marquardts_point_in_fewer_evaluations(monkeypatch):
    """Three steps into the phantom block, the next tip point by Newton's method on eq. 3.68's
    two terms and by Levenberg-Marquardt alone (NEWTON_TIP_ITERATIONS 0) agree to 1e-10 mm,
    and Newton needs fewer evaluations of u."""
    insertion = started(small_scene(), steps=3)
    geometry = insertion.geometry
    previous = insertion.points[-1]
    chord = 2.0 * geometry.radius * math.sin(0.5 * geometry.step)
    rest_angle = math.atan2(*(previous - geometry.center)[::-1])
    start = previous + chord * geometry.tangent(rest_angle + 0.5 * geometry.sense * geometry.step)

    def field(x):
        u, grad = insertion.displacement(x, gradient=True)
        return u[0], grad[0]

    found = {}
    for label, iterations in (("newton", tip_tracking.NEWTON_TIP_ITERATIONS), ("lm", 0)):
        monkeypatch.setattr(tip_tracking, "NEWTON_TIP_ITERATIONS", iterations)
        found[label] = tip_tracking.levenberg_marquardt_tip(previous, insertion.center, geometry.radius, chord,
                                                            start, field)
    np.testing.assert_allclose(found["newton"][0], found["lm"][0], rtol=0, atol=1e-10)
    assert found["newton"][1] < found["lm"][1]


# --- one prepared tissue per command ------------------------------------------------------


def test_the_runs_of_a_plan_share_one_model_and_one_factor_of_k0():
    """plan's passes and its comparison run use one PreparedTissue: the same model object, and
    K0 factorized once (by the first pass, which runs first), so the comparison run after the
    passes made no factorization of its own where it kept K0's factor; a prepared tissue of
    another discretization is refused."""
    scenario = small_scene()
    result = run_plan(scenario, compare=True)
    assert result.planned.model is result.unplanned.model
    first_pass = result.passes[0]["solver"]["factorizations"]
    assert first_pass >= 1
    assert result.unplanned.solver_counts["factorizations"] < first_pass
    with pytest.raises(ValueError, match="another scenario's tissue or discretization"):
        NeedleInsertion(small_scene(spacing=3.0), tissue=PreparedTissue(scenario))


# --- a run started from an earlier one on the same model -----------------------------------


def test_a_replay_started_from_a_nearby_run_reaches_the_same_exit_in_fewer_iterations():
    """run_insertion start_from: each step's Newton solve starts from this run's previous state
    plus the earlier run's change over the step. Replaying a centre path 0.02 mm off an earlier
    run's ends where the cold replay does (to the residual tolerance) with fewer Newton
    iterations; a run of another model is not used."""
    scenario = small_scene(solver=TIGHT_NEEDLE_NEWTON)
    tissue = PreparedTissue(scenario)
    earlier = run_insertion(scenario, tissue=tissue)
    assert len(earlier.states) == len(earlier.steps)
    path = np.vstack([earlier.geometry.center] * (len(earlier.steps) + 1))
    path += np.linspace(0.0, 0.02, len(path))[:, None] * np.array([1.0, -1.0])
    cold = run_insertion(scenario, center_path=path, tissue=tissue)
    warm = run_insertion(scenario, center_path=path, tissue=tissue, start_from=earlier)
    np.testing.assert_allclose(warm.achieved_exit_def, cold.achieved_exit_def, rtol=0, atol=1e-6)
    assert warm.exit_error_mm == pytest.approx(cold.exit_error_mm, abs=1e-6)
    iterations = {name: sum(s.newton_iterations for s in run.steps) for name, run in (("cold", cold), ("warm", warm))}
    assert iterations["warm"] < 0.8 * iterations["cold"], iterations
    other = run_insertion(scenario, center_path=path, start_from=earlier)  # its own model: starts cold
    assert sum(s.newton_iterations for s in other.steps) == iterations["cold"]


def test_a_start_that_newton_cannot_use_falls_back_to_the_previous_step(caplog):
    """A guess far off (every earlier state's displacement x 50, det F < 0 in places) fails
    under the whole load; the step starts again from the previous step's state and the run
    ends where a cold run does. (The run's centres leave the earlier run's at step 1, so no
    step is taken over.)"""
    scenario = small_scene(solver=TIGHT_NEEDLE_NEWTON)
    tissue = PreparedTissue(scenario)
    earlier = run_insertion(scenario, tissue=tissue)
    earlier.states = [replace(state, free=50.0 * state.free) for state in earlier.states]
    path = np.array([earlier.center_after(n) for n in range(len(earlier.steps) + 1)])
    path[1:] += [0.001, 0.0]
    cold = run_insertion(scenario, tissue=tissue, center_path=path)
    with caplog.at_level(logging.INFO, logger="stitchplan.needle.equilibrium"):
        warm = run_insertion(scenario, tissue=tissue, center_path=path, start_from=earlier)
    assert "Newton from the earlier run's state failed" in caplog.text
    np.testing.assert_allclose(warm.achieved_exit_def, cold.achieved_exit_def, rtol=0, atol=1e-6)
