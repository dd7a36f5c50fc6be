"""Stability limits: each test reproduces where the weaker method fails and checks what the
tool does about it (README, "Stability limits").

1. Inverse-gradient tip tracking against Levenberg-Marquardt as the cutting force (and with
   it the deformation at the tip) grows: the inverse-gradient path drifts from LM's without
   any jump being detected, and from 2.7 N on the jump detector fires at step 3: strict
   'inverse-gradient' raises InsertionFailure naming the step and angle, 'auto' falls back
   to LM and records an event.
2. MINRES with the thesis's block preconditioner as needle points accumulate: iterations
   per solve and the preconditioned condition number grow with the number of constraints
   (the unpreconditioned one by eight orders of magnitude); a MINRES that stagnates falls
   back to the direct solve with an event and the same answer.
3. Newton with St. Venant-Kirchhoff under strong compression: a punch pressed into a block
   needs load-step cutting at 3.5 mm and fails beyond ~3.9 mm with a SolverDivergence
   naming the load step and fraction; neo-Hookean solves 8 mm without a cut.
4. A dilation too small for the moment matrix (here a quadratic basis): a ScenarioError
   naming the dilation, spacing and orders, raised before any solve.
5. Needle loads that overflow: a failure that blames the overflow, one line in the CLI.
6. Point constraints closer together than the particles resolve: the constraint violation
   stalls just above its tolerance, and the failure says so (not the material).
7. A kernel four spacings wide: the stiffness is nearly singular and the run is refused; a
   Newton whose steps on fresh tangents raise the residual gives up on that load.
8. The needle a line the tissue is held to, on tissue soft against its loads: the free edge
   at the entry creases further at every refinement (the exit error does not settle there).
9. Where a step's load cannot be carried, the tangent's least stiffness on the needle's
   constraints (needle/stability.py) tells the tissue giving way (falling toward zero, or
   negative: an unstable state) from Newton failing; checked against the dense null-space
   eigenvalue.
"""

from __future__ import annotations

import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from stitchplan.cli import app
from stitchplan.config.scenario import ScenarioError, load_scenario, parse_scenario, with_discretization
from stitchplan.errors import InputError, InsertionFailure
from stitchplan.events import EventKind
from stitchplan.needle.insertion import run_insertion
from stitchplan.needle.saddle_point import SaddlePointSolver
from stitchplan.planning.verification import exit_deviations
from stitchplan.tissue.deform import run_deform
from stitchplan.tissue.material import determinant
from stitchplan.tissue.solver import SolverDivergence

from conftest import TIGHT_NEEDLE_NEWTON

PHANTOM = {"lame_lambda": 0.189151, "lame_mu": 0.147688}  # MPa, thesis appendix A.2


def needle_scene(*, cutting_force=0.7, spacing=4.0, step=0.2, coupling="points", solver=None, **needle):
    """40 x 30 mm phantom block clamped on the right, 8 mm needle entering (0, 22) cw: 99
    particles at 4 mm, well under a second per insertion. The thesis's point coupling, whose
    limits these tests document."""
    return parse_scenario({
        "tissue": {"size": [40.0, 30.0], "thickness": 10.0, "clamped": ["right"], "material": dict(PHANTOM)},
        "discretization": {"spacing": spacing},
        "needle": {"radius": 8.0, "entry": [0.0, 22.0], "turn": "cw", "step": step, "friction": 0.0602,
                   "cutting_force": cutting_force, "coupling": coupling, **needle},
        **({"solver": solver} if solver is not None else {})})


# --- 1. tip tracking ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tracking_sweep():
    """Per cutting force (N): the LM run, and the strict inverse-gradient run (or its failure)."""
    sweep = {}
    for force in (0.7, 1.5, 2.5, 2.7):
        lm = run_insertion(needle_scene(cutting_force=force, tip_tracking="levenberg-marquardt"))
        try:
            strict = run_insertion(needle_scene(cutting_force=force, tip_tracking="inverse-gradient"))
        except InsertionFailure as failure:
            strict = failure
        sweep[force] = lm, strict
    return sweep


def test_inverse_gradient_drifts_from_levenberg_marquardt_as_the_tip_force_grows(tracking_sweep):
    """Below the jump threshold every inverse-gradient step passes the jump checks, yet the
    exit drifts from LM's by 0.33 mm at the phantom's 0.7 N and by 0.60 mm at 2.5 N (where
    inverse-gradient tracking exits a needle step earlier, so its spatial exit, 0.71 mm off,
    does not count: exit_deviations), growing with the largest displacement (0.45 -> 0.94
    mm): X + F^-1 dx moves the tip a rotation step
    along the deformed circle, LM an insertion step R theta through the material, and the two
    part as the tissue stretches along the needle."""
    drift, largest = [], []
    for force in (0.7, 1.5, 2.5):
        lm, strict = tracking_sweep[force]
        assert not isinstance(strict, Exception) and not strict.events
        assert {s.tracking for s in strict.steps} == {"inverse-gradient"}
        drift.append(exit_deviations(strict, lm)["deviation_mm"])
        largest.append(float(np.linalg.norm(lm.displacements[-1], axis=1).max()))
    assert drift[0] > 0.3 and drift[-1] > 0.55
    assert np.all(np.diff(drift) > 0) and np.all(np.diff(largest) > 0)


def test_strict_inverse_gradient_fails_at_the_jump_and_auto_falls_back(tracking_sweep):
    """At 2.7 N (largest displacement ~1 mm) the step-3 inverse-gradient point misses the
    needle by more than 5 % of the step: strict tracking stops with InsertionFailure naming
    the step and angle; 'auto' switches to LM for that step, says so, and exits closer to the
    LM exit than strict tracking did at any smaller force."""
    lm, strict = tracking_sweep[2.7]
    assert isinstance(strict, InsertionFailure)
    assert str(strict).startswith("inverse-gradient tip tracking jumped at step 3 (needle rotation 0.600 rad)")
    auto = run_insertion(needle_scene(cutting_force=2.7, tip_tracking="auto"))
    assert auto.events and all(e.kind is EventKind.TIP_TRACKING_FALLBACK for e in auto.events)
    assert (auto.events[0].step, auto.events[0].angle_rad) == (3, pytest.approx(0.6))
    assert [s.tracking for s in auto.steps][2] == "levenberg-marquardt"
    drift_auto = exit_deviations(auto, lm)["deviation_mm"]
    drift_before = exit_deviations(tracking_sweep[2.5][1], tracking_sweep[2.5][0])["deviation_mm"]
    assert drift_auto < drift_before


# --- 2. MINRES --------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def minres_run():
    """MINRES with diag(K0^-1, S^-1) on the coarse scene in 0.1 rad steps: 30 needle
    points, condition numbers (dense) recorded at every step."""
    return run_insertion(needle_scene(step=0.1), linear_solver="minres", tip_tracking="levenberg-marquardt",
                         condition_numbers=True)


def test_minres_iterations_and_preconditioned_condition_grow_with_the_constraints(minres_run):
    """Observed: about 9 iterations per Newton solve with 2 needle points and roughly three
    times that with 30; the preconditioned condition number 2.6 -> 2.9 while the saddle
    matrix's own goes from 5e2 to 1e11. The preconditioner keeps MINRES usable, but its work per solve grows with k."""
    steps = minres_run.steps
    points = np.array([s.needle_points for s in steps])
    per_solve = np.array([s.minres_iterations / s.newton_iterations for s in steps])
    preconditioned = np.array([s.condition_preconditioned for s in steps])
    saddle = np.array([s.condition_saddle for s in steps])
    assert points[0] == 2 and points[-1] >= 30
    first, last = slice(0, 5), slice(-5, None)
    assert per_solve[last].mean() > 1.6 * per_solve[first].mean()
    # the preconditioner (S refreshed with the current normals) keeps the condition bounded
    # while the saddle matrix's grows by orders of magnitude
    assert preconditioned.max() < 10 and saddle[-1] > 1e6 * saddle[0]
    slope = np.polyfit(points, per_solve, 1)[0]
    assert slope > 0.15  # iterations per solve grow with each added needle point (measured ~0.28)


def test_a_stagnating_minres_falls_back_to_the_direct_solve(monkeypatch):
    """With its iteration budget cut to 3, MINRES cannot converge: every Newton step falls
    back to the direct solve, each fallback is an event naming the step and angle, and the
    insertion is the direct one (exit to 1e-7 mm)."""
    from stitchplan.needle import equilibrium

    original = equilibrium.SaddlePointSolver

    def starved(stiffness_at_rest, **options):
        return original(stiffness_at_rest, **{**options, "minres_maxiter": 3})

    monkeypatch.setattr(equilibrium, "SaddlePointSolver", starved)
    scenario = needle_scene(solver=TIGHT_NEEDLE_NEWTON)
    fallback = run_insertion(scenario, linear_solver="minres", tip_tracking="levenberg-marquardt")
    monkeypatch.setattr(equilibrium, "SaddlePointSolver", original)
    direct = run_insertion(scenario, linear_solver="direct", tip_tracking="levenberg-marquardt")
    assert fallback.solver_counts["minres_fallbacks"] == len(fallback.events) > 0
    assert fallback.events[0].kind is EventKind.MINRES_FALLBACK and fallback.events[0].step == 1
    np.testing.assert_allclose(fallback.achieved_exit_def, direct.achieved_exit_def, atol=1e-7)


# --- 3. St. Venant-Kirchhoff under compression --------------------------------------------------


def punch(model: str, depth: float, load_steps: int = 10, max_step_cuts: int = 6):
    """20 x 20 mm phantom block clamped at the bottom, an 8 mm punch in the middle of the top
    edge pressed down by `depth` mm (prescribed displacement). The punch ends lie on the 2 mm
    grid and the particles stay uniform at them (segment_end_levels 0): graded toward those
    singular points, SVK inverts next to the corners already at 3.5 mm, which is not what
    this test is about. (Before load segments got a particle on each end, the 10 mm punch
    [5, 15] held the particles 6..14, this same 8 mm.)"""
    return parse_scenario({
        "tissue": {"size": [20.0, 20.0], "thickness": 10.0, "clamped": ["bottom"],
                   "material": {"model": model, **PHANTOM}},
        "discretization": {"spacing": 2.0, "segment_end_levels": 0},
        "loads": [{"segment": [[6.0, 20.0], [14.0, 20.0]], "displacement": [0.0, -depth]}],
        "load_steps": load_steps, "solver": {"max_step_cuts": max_step_cuts}})


def min_jacobian(result) -> float:
    return float(determinant(result.model.deformation_gradient(result.coefficients)).min())


def test_saint_venant_kirchhoff_needs_step_cutting_then_fails_under_the_punch():
    """3.5 mm in one load step: the full step inverts the material (det F = -0.89), two cuts
    make it converge (min det F 0.53). 3.9 mm: Newton fails at load fraction 0.995 even in
    40 load steps with 6 cuts each: past the SVK stress maximum in compression there is no
    nearby equilibrium to converge to. The error names the load step and fraction."""
    with pytest.raises(SolverDivergence, match=r"Newton failed at load step 1 \(load fraction 1\.0000\) "
                                               r"after 0 step cuts: det F = -"):
        run_deform(punch("saint-venant-kirchhoff", 3.5, load_steps=1, max_step_cuts=0))
    cut = run_deform(punch("saint-venant-kirchhoff", 3.5, load_steps=1))
    assert cut.report.cuts >= 1 and 0.3 < min_jacobian(cut) < 0.6
    with pytest.raises(SolverDivergence) as failure:
        run_deform(punch("saint-venant-kirchhoff", 3.9))
    match = re.match(r"Newton failed at load step (\d+) \(load fraction (0\.\d+)\) after 6 step cuts: ",
                     str(failure.value))
    assert match and int(match.group(1)) == 10 and 0.9 < float(match.group(2)) < 1.0


def test_neo_hookean_solves_the_deeper_punch_without_cutting():
    """8 mm (40 % of the block) in 10 load steps, no cut: ln J in the energy keeps det F away
    from 0 (min 0.38) and the equilibrium residual is at Newton's tolerance."""
    result = run_deform(punch("neo-hookean", 8.0))
    assert result.report.cuts == 0
    assert 0.2 < min_jacobian(result) < 0.5
    assert result.report.steps[-1].residual < 1e-6
    # the punch really went 8 mm down: the displacement at its centre
    centre = result.model.shape_functions_at(np.array([[10.0, 20.0]])).values @ result.coefficients
    assert centre[0, 1] == pytest.approx(-8.0, abs=1e-6)


# --- 4. moment matrix ------------------------------------------------------------------------------


@pytest.mark.parametrize("dilation", [1.5, 2.0])
def test_a_dilation_too_small_for_the_moment_matrix_is_refused_before_any_solve(dilation, monkeypatch):
    """A quadratic basis needs 6 particles under every kernel; at an edge a support of
    2 spacings reaches only two columns of particles (the third lies exactly on the support's
    edge), so dilation 2 is too small there and 1.5 already inside. The model build raises a
    ScenarioError naming dilation, spacing and orders; no tangent is ever assembled."""
    from stitchplan.tissue import assembly

    def no_solve(*args, **kwargs):
        raise AssertionError("a solve started")

    monkeypatch.setattr(assembly.Assembler, "update", no_solve)
    scenario = needle_scene(spacing=4.0)
    from dataclasses import replace

    scenario = replace(scenario, discretization=replace(scenario.discretization, basis_order=2, dilation=dilation))
    with pytest.raises(ScenarioError) as error:
        run_insertion(scenario)
    message = str(error.value)
    assert message.startswith(f"discretization: dilation {dilation:g} with spacing 4 mm (basis order 2, "
                              "quadrature order 2) gives a singular RK moment matrix")
    assert "increase the dilation" in message


def test_the_cli_turns_the_moment_matrix_error_into_one_line(tmp_path, write_scenario):
    raw = {"tissue": {"size": [40.0, 30.0], "thickness": 10.0, "clamped": ["right"], "material": dict(PHANTOM)},
           "discretization": {"spacing": 4.0, "dilation": 1.5, "basis_order": 2},
           "needle": {"radius": 8.0, "entry": [0.0, 22.0], "turn": "cw", "step": 0.2, "friction": 0.06}}
    summary = tmp_path / "summary.json"
    scenario = write_scenario(raw)
    result = CliRunner().invoke(app, ["simulate", str(scenario), "--summary", str(summary)])
    assert result.exit_code == 2 and len(result.output.strip().splitlines()) == 1
    assert result.output.startswith(f"error: {scenario}: discretization: dilation 1.5 with spacing 4 mm (basis order 2")
    assert not summary.exists()


def test_a_linear_basis_at_dilation_one_is_refused_by_the_config():
    with pytest.raises(ScenarioError, match=r"discretization.dilation: got 1.0, expected a number > 1"):
        parse_scenario({"tissue": {"size": [40.0, 30.0], "thickness": 10.0, "material": dict(PHANTOM)},
                        "discretization": {"dilation": 1.0}})


# --- 5. loads that overflow -------------------------------------------------------------------


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")  # numpy's, true of this input
@pytest.mark.parametrize("load", [{"friction": 1e200}, {"cutting_force": 1e300}])
def test_a_needle_load_whose_norm_overflows_is_a_failure_not_a_converged_step(load):
    """|f_needle| = inf made every residual look small against the relative tolerance, so the
    run 'converged' in 0 iterations to an exit error of 0; now Newton refuses a residual that
    is not finite, and the message blames the overflow, not the material. (A scenario file
    refuses such loads as unit mistakes: the scenario is built past its checks.)"""
    scenario = needle_scene(coupling="mortar")
    scenario = replace(scenario, needle=replace(scenario.needle, **load))
    with pytest.raises(InsertionFailure, match=r"step 1 .*residual is not finite") as failure:
        run_insertion(scenario)
    assert "Saint Venant-Kirchhoff" not in str(failure.value)


def test_a_modulus_that_overflows_every_stress_is_one_error_line_without_numpy_warnings(tmp_path, write_scenario):
    """A shear modulus of 1e300 MPa makes every stress overflow: the run failed at step 1 with
    one line, numpy's RuntimeWarnings about it kept out of the user's terminal; the file's
    moduli are now bounded, and the same line-and-nothing-else holds for the refusal."""
    material = {**PHANTOM, "lame_mu": 1e300}
    raw = {"tissue": {"size": [40.0, 30.0], "thickness": 10.0, "clamped": ["right"], "material": material},
           "discretization": {"spacing": 4.0},
           "needle": {"radius": 8.0, "entry": [0.0, 22.0], "turn": "cw", "step": 0.2, "cutting_force": 0.7}}
    # a process of its own: pytest would catch the warnings before a CliRunner sees them
    result = subprocess.run([sys.executable, "-m", "stitchplan", "simulate", str(write_scenario(raw)),
                             "--no-estimate"], capture_output=True, text=True, timeout=300)
    assert result.returncode == 2 and result.stdout == ""
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert "tissue.material.lame_mu: got 1e+300" in result.stderr


# --- 6. needle points closer together than the particles resolve -----------------------------------


def test_point_constraints_closer_than_the_particles_stall_and_the_failure_says_so():
    """Point constraints 0.16 mm apart (step 0.02 rad) on 5 mm particles: their rows are nearly
    dependent, and at step 18 the constraint violation stalls at 8.01e-9 mm, just above the
    points coupling's 1e-9 R (8e-9 mm), while the force residual is 1e-12 N. The failure names
    the stall and its causes, not Saint Venant-Kirchhoff's compression (the block is SVK, and
    the load ramp's message blamed it before); the mortar coupling runs the same scene."""
    with pytest.raises(InsertionFailure) as failure:
        run_insertion(needle_scene(spacing=5.0, step=0.02))
    message = str(failure.value)
    assert re.match(r"step \d+ \(needle rotation 0\.\d{3} rad\): ", message), message
    assert "the forces balance, but the needle constraints stall above their tolerance of 8.000e-09 mm" in message
    assert "use `needle.coupling: mortar`" in message and "Saint Venant-Kirchhoff" not in message
    result = run_insertion(needle_scene(spacing=5.0, step=0.02, coupling="mortar"))
    assert result.exit_rotation is not None and not result.events


# --- 7. a kernel too wide for its particles; Newton steps that lose on fresh tangents -----------


def test_a_kernel_four_spacings_wide_makes_the_stiffness_nearly_singular_and_the_run_is_refused():
    """The cubic-spline kernel of support 4 spacings cancels the particles' alternating mode: on
    the block at 2 mm K0's condition number is 1.4e13 at dilation 4 against 5e5 at dilation 3
    (eigsh). The run is refused before its first step, naming the dilation, the spacing and
    what to use instead; at dilation 3 it runs."""
    scene = needle_scene(spacing=2.0, coupling="mortar")
    with pytest.raises(InputError) as refused:
        run_insertion(with_discretization(scene, dilation=4.0))
    message = str(refused.value)
    assert message.startswith("discretization: dilation 4 with spacing 2 mm makes the tissue's stiffness nearly "
                              "singular (condition number ~"), message
    assert float(re.search(r"condition number ~(\S+), ", message).group(1)) > 1e12
    assert message.endswith("use a dilation of 3 or less (2 is the default)")
    assert run_insertion(with_discretization(scene, dilation=3.0)).exit_rotation is not None


def test_newton_gives_up_on_a_load_whose_steps_on_fresh_tangents_raise_the_residual(monkeypatch):
    """Steps made three times too long (a stand-in for a tangent that no longer describes the
    tissue) raise the residual after every fresh factorization. Newton gives up on a load
    after two such steps instead of running out its 25 iterations, and the ramp's failure
    names the step, the angle and the divergence."""
    solve_direct = SaddlePointSolver.solve_direct
    monkeypatch.setattr(SaddlePointSolver, "solve_direct", lambda *args: 3.0 * solve_direct(*args))
    scene = needle_scene(coupling="mortar")
    with pytest.raises(InsertionFailure) as failure:
        run_insertion(scene)
    message = str(failure.value)
    assert message.startswith("step 1 (needle rotation 0.200 rad): the needle's load could not be carried"), message
    assert "(Newton diverged at step 1 (needle rotation 0.200 rad): 2 steps on a freshly factored tangent " \
           "raised the residual" in message


def test_newton_out_of_the_iterations_it_was_given_blames_the_cap_not_the_material():
    """solver.max_iterations 1: the step fails for want of iterations, and the message says
    so instead of calling Saint Venant-Kirchhoff unstable under compression."""
    from stitchplan.config.scenario import parse_scenario
    from stitchplan.errors import InsertionFailure
    from stitchplan.needle.insertion import run_insertion

    raw = {"tissue": {"size": [40.0, 30.0], "thickness": 10.0, "clamped": ["right"],
                      "material": {"model": "saint-venant-kirchhoff", "lame_lambda": 0.189151, "lame_mu": 0.147688}},
           "needle": {"radius": 8.0, "entry": [0.0, 22.0], "turn": "cw", "step": 0.2, "friction": 0.0602,
                      "cutting_force": 0.7},
           "discretization": {"spacing": 4.0}, "solver": {"max_iterations": 1}}
    with pytest.raises(InsertionFailure) as failure:
        run_insertion(parse_scenario(raw))
    message = str(failure.value)
    assert message.startswith("step 1 (needle rotation 0.200 rad): the needle's load could not be carried")
    assert message.endswith("; solver.max_iterations is 1 (the default 25): give Newton more iterations")
    assert "Saint Venant-Kirchhoff" not in message


def _entry_edge_turn(result, span: float = 3.0) -> tuple[float, float]:
    """The free edge x = 0 within `span` mm of the needle's entry once the tip has left: how
    far its tangent turns (degrees) and its least stretch."""
    entry = np.asarray(result.geometry.entry, dtype=float)
    along = np.linspace(-span, span, 601)
    points = np.column_stack([np.zeros_like(along), entry[1] + along])
    deformed = points + result.model.field_at(points, result.coefficients[-1])[0]
    pieces = np.diff(deformed, axis=0)
    angle = np.degrees(np.unwrap(np.arctan2(pieces[:, 1], pieces[:, 0])))
    stretch = np.linalg.norm(pieces, axis=1) / np.diff(along)
    return float(angle.max() - angle.min()), float(stretch.min())


def test_a_line_needle_in_soft_tissue_creases_the_entry_edge_at_every_refinement():
    """8. The needle a line the tissue is held to: on a slab soft against the SH 1/2 needle's
    loads (configs/sh12_100x100.yaml neo-Hookean, 3 mm thick) the free edge at the entry is
    drawn into a cusp that half the spacing sharpens (its tangent turns 51 then 83 degrees;
    benchmarks/results/softness_sweep.md), while 10 mm thick it stays nearly straight (6 then
    8 degrees). A model of the puncture would change this test."""
    base = load_scenario(Path(__file__).resolve().parent.parent / "configs" / "sh12_100x100.yaml")
    edges = {}
    for thickness in (3.0, 10.0):
        material = replace(base.tissue.material, model="neo-hookean")
        scene = replace(base, tissue=replace(base.tissue, thickness=thickness, material=material))
        edges[thickness] = [_entry_edge_turn(run_insertion(with_discretization(
            scene, spacing=scene.discretization.spacing * factor))) for factor in (1.0, 0.5)]
    (soft_h, soft_stretch_h), (soft_half, soft_stretch_half) = edges[3.0]
    (stiff_h, _), (stiff_half, _) = edges[10.0]
    assert soft_half > soft_h + 20.0, edges
    assert soft_stretch_half < soft_stretch_h - 0.08, edges
    assert abs(stiff_half - stiff_h) < 3.0 and stiff_half < 15.0, edges


# --- 9. the tissue's least stiffness on the needle's constraints ----------------------------


def _null_space_least(tangent: np.ndarray, constraints: np.ndarray) -> float:
    """The smallest eigenvalue of `tangent` on null(constraints^T), densely."""
    import scipy.linalg

    basis = scipy.linalg.null_space(constraints.T)
    return float(np.linalg.eigvalsh(basis.T @ tangent @ basis).min())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_least_stiffness_on_the_constraints_is_the_null_space_eigenvalue(seed):
    """A tangent with three negative directions, two of them held by constraint columns that
    mix them with the others: softest_mode gives the smallest eigenvalue on null(G^T) (to
    1e-6 of K's mean diagonal), its mode satisfies G^T v = 0, and its sign follows whether
    the constraints leave a negative direction free."""
    import scipy.sparse as sp

    from stitchplan.needle.stability import softest_mode

    rng = np.random.default_rng(seed)
    n, m = 60, 8
    rotation, _ = np.linalg.qr(rng.standard_normal((n, n)))
    values = np.concatenate([[-0.4, -0.2, -0.1], rng.uniform(0.05, 2.0, n - 3)])
    tangent = rotation @ np.diag(values) @ rotation.T
    tangent = 0.5 * (tangent + tangent.T)
    scale = np.abs(np.diag(tangent)).mean()
    for held in (3, 2):  # all three negative directions held by the constraints, then two of them
        constraints = np.column_stack([rotation[:, :held] + 0.3 * rotation[:, held:held + 1] @ rng.standard_normal(
            (1, held)), rng.standard_normal((n, m - held))])
        found = softest_mode(sp.csr_matrix(tangent), sp.csc_matrix(constraints))
        expected = _null_space_least(tangent, constraints) / scale
        assert found is not None
        assert found.stiffness == pytest.approx(expected, abs=1e-6), (held, found.stiffness, expected)
        assert np.abs(constraints.T @ found.mode).max() < 1e-9
        assert (found.stiffness < 0.0) == (held < 3)


def test_without_constraints_the_least_stiffness_is_the_smallest_eigenvalue():
    """No constraint columns (m = 0): the smallest eigenvalue of the tangent itself."""
    import scipy.sparse as sp

    from stitchplan.needle.stability import softest_mode

    tangent = sp.diags([2.0, 3.0, 4.0, 5.0, 6.0, -1.0]).tocsr()
    found = softest_mode(tangent, sp.csc_matrix((6, 0)))
    assert found.stiffness == pytest.approx(-1.0 / (21.0 / 6.0))
    assert abs(found.mode[5]) == pytest.approx(1.0)
    held = softest_mode(tangent, sp.csc_matrix(np.eye(6)[:, 5:]))
    assert held.stiffness == pytest.approx(2.0 / (21.0 / 6.0))


def test_the_least_stiffness_is_found_through_one_factor_of_the_runs_kind(monkeypatch):
    """The shift-invert solves go through one factor of the shifted matrix made as the runs
    make theirs (tissue.factorization.factorize: a symmetric fill-reducing ordering), not
    eigsh's own splu, whose COLAMD ordering took 14.5 s a factor against CHOLMOD's 0.12 s on
    a 10 mm x 0.5 mm strip (10 850 unknowns); the answer is the same eigenvalue."""
    import scipy.sparse as sp

    from stitchplan.needle import stability

    made = []
    original = stability.factorize
    monkeypatch.setattr(stability, "factorize", lambda *args, **kwargs: made.append(1) or original(*args, **kwargs))
    tangent = sp.diags([2.0, 3.0, 4.0, 5.0, 6.0, -1.0]).tocsr()
    found = stability.softest_mode(tangent, sp.csc_matrix((6, 0)))
    assert made == [1]
    assert found.stiffness == pytest.approx(-1.0 / (21.0 / 6.0))


def test_an_eigensolver_that_does_not_settle_gives_up_after_its_restarts(monkeypatch):
    """Lowest eigenvalues crowded together far closer than the shift is to them (a 100 mm x
    0.5 mm strip's: ~1e-10 of K's diagonal, the shift at -1e-3) kept Lanczos going for 17 358
    solves, 168 s; it now stops after RESTARTS restarts (~17 solves each) and the diagnosis
    gives no answer, as for any eigensolver that does not converge."""
    import scipy.sparse as sp

    from stitchplan.needle import stability

    solves = []
    original = stability.factorize

    def counted(*args, **kwargs):
        factor = original(*args, **kwargs)
        solve = factor.solve
        factor.solve = lambda rhs: solves.append(1) or solve(rhs)
        return factor

    monkeypatch.setattr(stability, "factorize", counted)
    rng = np.random.default_rng(0)
    n = 3000
    values = np.concatenate([1e-10 * (1.0 + rng.uniform(0.0, 1.0, 200)), rng.uniform(0.5, 1.5, n - 200)])
    found = stability.softest_mode(sp.diags(values).tocsr(), sp.csc_matrix((n, 0)))
    assert len(solves) <= 20 * (stability.RESTARTS + 2)
    assert found is None or found.stiffness < 1e-8


def test_a_step_the_tissue_cannot_carry_names_its_softening_and_where(monkeypatch):
    """Neo-Hookean phantom 0.7 mm thick on the 40 x 30 mm block: the ramp carries 91 % of
    step 2's load, and the failure says the tangent's least stiffness on the needle's
    constraints fell over the step (to a few % of the step's start: a limit point ahead) with
    its mode largest at the needle's entry (the tip 3.2 mm from it, within two spacings of
    it too). 10 mm thick, with Newton made to fail beyond half of step 3's load, the failure
    says the stiffness did not fall: Newton's failure, not the tissue's."""
    from stitchplan.errors import InsertionFailure
    from stitchplan.needle.equilibrium import NeedleInsertion
    from stitchplan.needle.insertion import run_insertion

    def phantom(thickness: float):
        return parse_scenario({
            "tissue": {"size": [40.0, 30.0], "thickness": thickness, "clamped": ["right"],
                       "material": {"model": "neo-hookean", "lame_lambda": 0.189151, "lame_mu": 0.147688}},
            "needle": {"radius": 8.0, "entry": [0.0, 22.0], "turn": "cw", "step": 0.2, "friction": 0.0602,
                       "cutting_force": 0.7},
            "discretization": {"spacing": 4.0}})

    with pytest.raises(InsertionFailure) as failure:
        run_insertion(phantom(0.7))
    message = str(failure.value)
    assert message.startswith("step 2 (needle rotation 0.400 rad): the needle's load could not be carried: 90.6 %")
    percent = int(re.search(r"least stiffness on the needle's constraints fell to (\d+) % of the step's start", message)
                  .group(1))
    assert percent < 20, message
    assert message.endswith("its mode largest at [0, 22.5] mm, the needle's entry and tip"), message

    newton = NeedleInsertion._newton

    def failing_beyond_half(insertion, rotation, step, aim=None):
        if step == 3 and insertion.coupling.load_factor > 0.5:
            raise InsertionFailure("forced")
        return newton(insertion, rotation, step, aim)

    monkeypatch.setattr(NeedleInsertion, "_newton", failing_beyond_half)
    with pytest.raises(InsertionFailure) as failure:
        run_insertion(phantom(10.0))
    message = str(failure.value)
    assert message.startswith("step 3 (needle rotation 0.600 rad): the needle's load could not be carried: 50 %")
    assert message.endswith("did not fall over the step (100 % of the step's start): the tissue is not "
                            "softening, Newton's steps failed"), message
