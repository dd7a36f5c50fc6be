"""Whether the 2.5 mm soft slab's stop at a quarter spacing is Newton's doing or the tissue's.

At h/4 (h the file's spacing) the neo-Hookean 2.5 mm slab (needle_coupling's soft_t2.5)
stops at step 16 with 94 % of the step's load carried (entry_stability.md: the tangent's
least stiffness falls toward zero, its mode at the needle's entry). Newton there keeps the
symmetric tangent K + H: the follower loads' own stiffness, d f_needle / dd (friction and
cutting force along the needle's tangent, which turns with the track's points), is left out,
so that K + H can be factored by Cholesky (needle/equilibrium.py). Near a fold that omission
could be what stalls Newton. Here the shipped Newton is set beside `exact` Newton, patched in
for the runs (a probe of the model, not an option of the package): every iteration on the
full Jacobian, K + H + F with F = -d f_needle / dd (non-symmetric), the whole saddle matrix
[[K + H + F, G], [G^T, 0]] LU-factored (scipy's SuperLU) at every iteration, no Anderson
mixing, from the step RUNS gives on (the steps before as shipped, for time).

Runs: sh12_100x100 at h (exact from step 1: where Newton converges, what F changes) and
soft_t2.5 at h/4 (exact from step 14). Then, at the last load exact Newton carried at step 16
(the state restored after the stop), a Taylor test of the residual R = [r_u; g] of eq. 3.62
under the step's full load: |R(x + t d) - R(x) - t J d| for t = 1 .. 1e-4 along the Newton
direction d = -J^-1 R(x) and along a random direction, for J with and without F. A remainder
falling like t^2 says J is R's exact derivative; like t, that a term is missing. Along the
Newton direction, |R(x + t d)| against t says how far Newton's linear model holds. Last,
whether an equilibrium exists there at all: damped Newton (the full Jacobian with Armijo
backtracking on |W R|, W scaling R by the step's tolerances) under rising loads of step 16
(FLOOR_LOADS, each from the last load it converged under) and the least merit it reaches, with
the free edge at the entry where it stops (entry_flanks: how far it folds, and how near its two
sides, drawn along the needle, come to each other). Past a
limit point of the equilibrium path that least residual is not zero (where it is least,
J^T W^2 R = 0 with R != 0: J is singular).

Writes benchmarks/results/entry_newton.{csv,md,png}. About 15 minutes; `--report` redraws the
table and chart from the CSV.
Run from the repository root:  python benchmarks/entry_newton.py
"""

from __future__ import annotations

import os

# single-threaded BLAS, as the `stitchplan` command sets it
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import contextlib  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402
from types import SimpleNamespace  # noqa: E402

import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402
import scipy.sparse.linalg as spla  # noqa: E402

import _common as common  # noqa: E402
import exit_components  # noqa: E402
import needle_coupling  # noqa: E402
from stitchplan.errors import InsertionFailure, InvertedMaterial  # noqa: E402
from stitchplan.needle import newton as newton_module  # noqa: E402
from stitchplan.needle.equilibrium import NeedleInsertion  # noqa: E402
from stitchplan.needle.insertion import run_insertion  # noqa: E402
from stitchplan.needle.saddle_point import SaddlePointSolver  # noqa: E402

RUNS = (("sh12_100x100", "h", 1.0, 1), ("soft_t2.5", "h/4", 0.25, 14))  # scene, level, factor, exact from step
PROBE_STEP = 16  # soft_t2.5's step at h/4 whose last load carried is Taylor-tested
STEPS = (1.0, 0.1, 0.01, 1e-3, 1e-4)  # t of the Taylor test
NEWTON_LINE = (1.0, 0.5, 0.2, 0.1, 0.05, 0.02, 0.01)  # t along the Newton direction
FLOOR_LOADS = (0.875, 0.8875, 0.9, 0.9125, 0.925, 0.9375, 0.94375, 0.95, 0.9625, 0.975, 0.9875, 1.0)  # residual_floor
FLOOR_ITERATIONS = 40  # damped Newton's iterations at most per load
FLOOR_GAIN = 1e-3  # ... and FLOOR_STALL iterations in a row that lower its least merit by less than this share stop it
FLOOR_STALL = 3
FLANK_SEPARATION = 0.5  # mm along the entry's edge: points further apart count as its two sides (entry_flanks)
BALANCED = 0.01  # a least merit at most this: an equilibrium (the reading's; damped Newton goes on to a tenth of it)


def follower_stiffness(insertion: NeedleInsertion, free: np.ndarray, center: np.ndarray) -> sp.csr_matrix | None:
    """F = -d f_needle / dd (2 n_free, 2 n_free): each load point's force a_l turns with the
    point's polar angle about C, d a_l / dx_l = -d a_l / dC (NeedleCoupling._needle_force_turn),
    so F = S^T blockdiag(d a_l / dC) S over the load points' interleaved rows S; None
    without load points."""
    coupling = insertion.coupling
    rows, _, points = coupling._track()
    q = coupling.weights.shape[0]
    if len(points) == q:
        return None
    blocks = np.zeros((len(points), 2, 2))
    blocks[q:] = coupling._needle_force_turn(free, center)
    return point_blocks_on_dofs(rows, blocks)


def point_blocks_on_dofs(rows: sp.csr_matrix, blocks: np.ndarray) -> sp.csr_matrix:
    """S^T blockdiag(blocks) S (2 n_free, 2 n_free): a 2 x 2 block per point (blocks (P, 2, 2))
    carried to the dofs through the points' shape-function rows (P, n_free), interleaved."""
    interleaved = sp.kron(rows, sp.identity(2), format="csr")
    count = len(blocks)
    block_diagonal = sp.bsr_matrix((blocks, np.arange(count), np.arange(count + 1)),
                                   shape=(2 * count, 2 * count)).tocsr()
    return (interleaved.T @ block_diagonal @ interleaved).tocsr()


def jacobian(insertion: NeedleInsertion, free: np.ndarray, multipliers: np.ndarray, center: np.ndarray,
             with_follower: bool, state=None) -> tuple[sp.csc_matrix, np.ndarray]:
    """The saddle matrix [[K + H (+ F), G], [G^T, 0]] at the state, and R = [r_u; g] there;
    `state`: the residuals there where the caller has them (the assembler is then at the state)."""
    if state is None:
        state = insertion.residuals(free.reshape(-1, 2), multipliers, center)
    stiffness = insertion._stiffness(multipliers, state)()
    follower = follower_stiffness(insertion, free.reshape(-1, 2), center) if with_follower else None
    if follower is not None:
        stiffness = stiffness + follower
    constraints = insertion.coupling.constraint_matrix(state.normal)
    matrix = sp.bmat([[stiffness, constraints], [constraints.T, None]], format="csc")
    return matrix, np.concatenate([state.residual, state.violation])


@contextlib.contextmanager
def exact_newton(from_step: int, kept: dict):
    """Newton on the full Jacobian from `from_step` on (see the module's docstring); `kept`
    gets the insertion and, at PROBE_STEP, each load carried with its snapshot."""
    newton, solve, stiffness = NeedleInsertion._newton, SaddlePointSolver.solve_direct, NeedleInsertion._stiffness
    residuals, renew, depth = NeedleInsertion._timed_residuals, newton_module.renew_factor, \
        newton_module.FIXED_CENTER_ANDERSON_DEPTH
    exact = {"on": False}

    def newton_step(insertion, rotation, step, aim=None):
        exact["on"] = step >= from_step
        kept["insertion"] = insertion
        result = newton(insertion, rotation, step, aim)
        if step == PROBE_STEP:
            kept.setdefault("states", []).append((insertion.coupling.load_factor, insertion.snapshot()))
        return result

    def timed_residuals(insertion, free, multipliers, center, rotation, step):
        insertion.probe_point = (free, center)
        return residuals(insertion, free, multipliers, center, rotation, step)

    def full_stiffness(insertion, multipliers, state):
        symmetric = stiffness(insertion, multipliers, state)
        if not exact["on"]:
            return symmetric

        def assembled():
            follower = follower_stiffness(insertion, *insertion.probe_point)
            return symmetric() if follower is None else (symmetric() + follower).tocsr()
        return assembled

    def full_solve(solver, stiffness_of, rhs, refactor, rows, weights, on_rows=None):
        if not exact["on"] or on_rows is not None:
            return solve(solver, stiffness_of, rhs, refactor, rows, weights, on_rows)
        constraints = (sp.csr_matrix(rows).T @ sp.csr_matrix(weights)).tocsc()
        matrix = sp.bmat([[stiffness_of(), constraints], [constraints.T, None]], format="csc")
        solver.factorizations += 1
        return spla.splu(matrix).solve(rhs)

    NeedleInsertion._newton, NeedleInsertion._timed_residuals = newton_step, timed_residuals
    NeedleInsertion._stiffness, SaddlePointSolver.solve_direct = full_stiffness, full_solve
    newton_module.renew_factor = lambda *args: True if exact["on"] else renew(*args)
    newton_module.FIXED_CENTER_ANDERSON_DEPTH = 0 if from_step <= 1 else depth
    refuse = NeedleInsertion._refuse_unstable  # its eigensolver takes a symmetric tangent
    NeedleInsertion._refuse_unstable = lambda insertion, rotation, step: None if exact["on"] else \
        refuse(insertion, rotation, step)
    try:
        yield
    finally:
        NeedleInsertion._newton, NeedleInsertion._timed_residuals = newton, residuals
        NeedleInsertion._stiffness, SaddlePointSolver.solve_direct = stiffness, solve
        newton_module.renew_factor, newton_module.FIXED_CENTER_ANDERSON_DEPTH = renew, depth
        NeedleInsertion._refuse_unstable = refuse


def run(scene: str, level: str, factor: float, method: str, from_step: int, kept: dict) -> dict:
    scenario = needle_coupling.refined(scene, factor)
    start = time.perf_counter()
    context = exact_newton(from_step, kept) if method == "exact" else contextlib.nullcontext()
    with context:
        try:
            result = run_insertion(scenario)
            outcome = {"exit_error_mm": f"{result.exit_error_mm:.6f}", "failure": "",
                       "newton_iterations": sum(step.newton_iterations for step in result.steps)}
        except InsertionFailure as failure:
            outcome = {"exit_error_mm": "", "failure": " ".join(str(failure).split())[:150].replace(",", ";"),
                       "newton_iterations": ""}
    row = {"table": "run", "scene": scene, "level": level, "newton": method,
           "exact_from_step": from_step if method == "exact" else "", **outcome,
           "seconds": f"{time.perf_counter() - start:.1f}"}
    print(row, flush=True)
    return row


def taylor(kept: dict) -> list[dict]:
    """The Taylor test and the residual along the Newton direction at the last load carried at
    PROBE_STEP, under the step's full load (module docstring)."""
    insertion = kept["insertion"]
    carried, snapshot = max(kept["states"], key=lambda state: state[0])
    insertion.restore(snapshot)
    insertion.coupling.load_factor = 1.0
    free, multipliers, center = insertion.free.ravel().copy(), insertion.multipliers.copy(), insertion.center.copy()
    n = len(free)

    def residual(direction: np.ndarray, t: float) -> np.ndarray:
        state = insertion.residuals((free + t * direction[:n]).reshape(-1, 2), multipliers + t * direction[n:], center)
        return np.concatenate([state.residual, state.violation])

    rows = []
    full, start = jacobian(insertion, free, multipliers, center, with_follower=True)
    newton_direction = spla.splu(full).solve(-start)
    moves = np.linalg.norm(insertion.model.boundary.free_map @ newton_direction[:n].reshape(-1, 2), axis=1)
    where = insertion.model.particles[int(np.argmax(moves))]  # the particle the step moves most
    random = np.random.default_rng(0).standard_normal(len(start)) * 1e-2 * moves.max()  # |d| ~ 1 % of Newton's
    for with_follower in (True, False):
        matrix = full if with_follower else jacobian(insertion, free, multipliers, center, False)[0]
        tangent = "K + H + F" if with_follower else "K + H"
        for name, direction in (("Newton", newton_direction), ("random", random)):
            change = matrix @ direction
            for t in STEPS:
                remainder = float(np.linalg.norm(residual(direction, t) - start - t * change))
                rows.append({"table": "taylor", "tangent": tangent, "direction": name, "t": t,
                             "remainder": f"{remainder:.4e}", "remainder_over_t": f"{remainder / t:.4e}",
                             "remainder_over_t2": f"{remainder / t ** 2:.4e}"})
    for t in NEWTON_LINE:
        rows.append({"table": "line", "t": t, "residual_N": f"{np.linalg.norm(residual(newton_direction, t)[:n]):.4e}",
                     "load_carried": carried, "start_residual_N": f"{np.linalg.norm(start[:n]):.4e}",
                     "largest_move_mm": f"{moves.max():.4f}",
                     "largest_move_at": f"({where[0]:.3f}; {where[1]:.3f})"})
    return rows


def damped_newton(insertion: NeedleInsertion) -> tuple[float, float, float, int, bool]:
    """Newton on the full Jacobian with Armijo backtracking on the scaled merit
    |(r_u / tol_r, g / tol_g)| (tol_r, tol_g the needle step's tolerances, so that converged
    is a merit of about one or less) from the insertion's state under its current load, on past
    the tolerance until the merit is BALANCED / 10 (Newton converges quadratically to an
    equilibrium), FLOOR_STALL iterations in a row gain less than FLOOR_GAIN of it, or no step
    along the Newton direction lowers it. Returns the least merit, |r_u| (N) and max |g| (mm)
    there, the iterations and whether that iterate meets the step's tolerances; the insertion
    is left at it."""
    free, multipliers, center = insertion.free.ravel().copy(), insertion.multipliers.copy(), insertion.center.copy()
    n = len(free)

    def scaled(state) -> float:
        return math.hypot(float(np.linalg.norm(state.residual)) / (insertion.residual_tolerance * state.needle_force),
                          float(np.linalg.norm(state.violation)) / insertion.constraint_tolerance)

    best = (math.inf, math.inf, math.inf, math.inf, free, multipliers)  # merit, |r_u|, max |g|, |f_needle|, state
    stalled, iteration = 0, 0
    for iteration in range(FLOOR_ITERATIONS):
        state = insertion.residuals(free.reshape(-1, 2), multipliers, center)
        merit = scaled(state)
        if merit < best[0]:
            stalled = stalled + 1 if merit > (1.0 - FLOOR_GAIN) * best[0] else 0
            best = (merit, float(np.linalg.norm(state.residual)), state.worst_violation, state.needle_force,
                    free, multipliers)
        else:
            stalled += 1
        if merit <= BALANCED / 10.0 or stalled >= FLOOR_STALL:  # far inside the tolerance, or no further
            break
        matrix, residual = jacobian(insertion, free, multipliers, center, with_follower=True, state=state)
        direction = spla.splu(matrix).solve(-residual)
        t = 1.0
        while t >= 1e-4:
            try:
                trial = insertion.residuals((free + t * direction[:n]).reshape(-1, 2), multipliers + t * direction[n:],
                                            center)
                if scaled(trial) <= (1.0 - 1e-4 * t) * merit:
                    break
            except InvertedMaterial:
                pass
            t *= 0.5
        if t < 1e-4:
            break
        free, multipliers = free + t * direction[:n], multipliers + t * direction[n:]
    merit, residual_norm, violation, needle_force, free, multipliers = best
    insertion.free, insertion.multipliers = free.reshape(-1, 2), multipliers
    converged = residual_norm <= insertion.residual_tolerance * needle_force and violation <= insertion.constraint_tolerance
    return merit, residual_norm, violation, iteration, converged


def entry_flanks(insertion: NeedleInsertion) -> tuple[float, float, float]:
    """The free edge within exit_components.EDGE_SPAN of the needle's entry at the insertion's
    state: its least stretch and how far its tangent turns (exit_components.entry_edge), and
    the least distance between two of its points more than FLANK_SEPARATION mm apart along it
    (the two sides of the entry drawn along the needle: how near they come to each other)."""
    state = SimpleNamespace(scenario=insertion.scenario, geometry=insertion.geometry, model=insertion.model,
                            coefficients=[insertion.coefficients()])
    points, deformed = exit_components.edge_polyline(state)
    stretch, turn = exit_components.entry_edge((points, deformed))
    along = np.linalg.norm(points - points[0], axis=1)
    apart = np.abs(along[:, None] - along[None, :]) > FLANK_SEPARATION
    distance = np.linalg.norm(deformed[:, None, :] - deformed[None, :, :], axis=2)
    return stretch, turn, float(distance[apart].min())


def residual_floor(kept: dict) -> list[dict]:
    """The least scaled merit damped_newton reaches at PROBE_STEP under each of FLOOR_LOADS,
    each from the last load it converged under, starting at the largest load below 90 % exact
    Newton carried: where the equilibrium path ends at a limit point, the least residual beyond
    it is not zero."""
    insertion = kept["insertion"]
    start, snapshot = max((state for state in kept["states"] if state[0] < 0.9), key=lambda state: state[0])
    rows = []
    for load in (load for load in FLOOR_LOADS if load >= start):
        insertion.restore(snapshot)
        insertion.coupling.load_factor = load
        merit, residual_norm, violation, iterations, converged = damped_newton(insertion)
        if converged:
            snapshot = insertion.snapshot()
        stretch, turn, gap = entry_flanks(insertion)
        rows.append({"table": "floor", "load": load, "least_merit": f"{merit:.4g}",
                     "least_residual_N": f"{residual_norm:.4e}", "violation_mm": f"{violation:.3e}",
                     "iterations": iterations, "converged": "yes" if converged else "no",
                     "edge_least_stretch": f"{stretch:.4f}", "edge_turn_deg": f"{turn:.2f}", "flank_gap_mm": f"{gap:.4f}"})
        print(rows[-1], flush=True)
    return rows


def report(rows: list[dict]) -> str:
    runs = [row for row in rows if row["table"] == "run"]
    taylor_rows = [row for row in rows if row["table"] == "taylor"]
    line = [row for row in rows if row["table"] == "line"]
    text = ["# Newton at the 2.5 mm soft slab's stop: the tangent or the tissue", "",
            f"Generated by `python benchmarks/entry_newton.py` ({common.machine_note()}). Newton as shipped "
            "(K + H, the follower loads' stiffness F left out; Cholesky and modified Newton with Anderson mixing) "
            "beside `exact` Newton (K + H + F, the saddle matrix LU-factored at every iteration, patched in for "
            "the runs) from the step given; soft_t2.5: configs/sh12_100x100.yaml as a neo-Hookean slab 2.5 mm "
            "thick, h the file's spacing.", "",
            common.markdown_table(["scene", "level", "Newton", "exact from step", "exit error (mm)",
                                   "Newton iterations", "seconds"],
                                  [[row["scene"], row["level"], row["newton"], row["exact_from_step"] or "—",
                                    row["exit_error_mm"] or f"stops: {row['failure'].split('; the next')[0]}",
                                    row["newton_iterations"] or "—", row["seconds"]] for row in runs]), ""]
    if line:
        first = line[0]
        text += [f"At soft_t2.5's last load carried at step {PROBE_STEP} by exact Newton "
                 f"({100 * float(first['load_carried']):.2f} % of the step's), under the step's full load: "
                 f"|r_u| = {first['start_residual_N']} N; the Newton step moves a particle by up to "
                 f"{first['largest_move_mm']} mm (at {first['largest_move_at']} mm). The Taylor remainder "
                 "|R(x + t d) - R(x) - t J d| (N and mm together):", "",
                 common.markdown_table(["tangent", "direction", "t", "remainder", "remainder / t", "remainder / t^2"],
                                       [[row["tangent"], row["direction"], f"{float(row['t']):g}", row["remainder"],
                                         row["remainder_over_t"], row["remainder_over_t2"]] for row in taylor_rows]),
                 "", "|r_u| along the Newton direction (t = 1 is the full Newton step):", "",
                 common.markdown_table(["t", "‖r_u(x + t d)‖ (N)"], [[f"{float(row['t']):g}", row["residual_N"]] for row in line]),
                 "", *reading(taylor_rows, line), ""]
    floor = [row for row in rows if row["table"] == "floor"]
    if floor:
        text += ["Damped Newton (full Jacobian, Armijo backtracking on the merit |(r_u / tol_r, g / tol_g)|, the "
                 "needle step's tolerances: converged is a merit of about one or less) at step 16 under rising loads, "
                 "each from the last load it converged under, from the largest load below 90 % exact Newton carried: "
                 "the least "
                 f"merit it reaches (on past the tolerance to {BALANCED / 10:g}; it stops after {FLOOR_STALL} "
                 f"iterations in a row gaining less than {100 * FLOOR_GAIN:g} %, or where no step along the Newton "
                 "direction lowers the merit); converged: within the step's tolerances there:", "",
                 common.markdown_table(["load (share of the step's)", "least merit", "‖r_u‖ there (N)",
                                        "max abs(g) there (mm)", "iterations", "converged", "edge least stretch",
                                        "edge turn (deg)", "gap between the entry's sides (mm)"],
                                       [[f"{float(row['load']):g}", row["least_merit"], row["least_residual_N"],
                                         row["violation_mm"], row["iterations"], row["converged"],
                                         row.get("edge_least_stretch", ""), row.get("edge_turn_deg", ""),
                                         row.get("flank_gap_mm", "")] for row in floor]),
                 "", *floor_reading(floor), ""]
    return "\n".join(text) + "\n"


def floor_reading(floor: list[dict]) -> list[str]:
    """Where damped Newton still finds an equilibrium (quadratic convergence far inside the
    tolerance) and where it stalls."""
    balanced = [float(row["load"]) for row in floor if float(row["least_merit"]) <= BALANCED]
    beyond = [row for row in floor if float(row["least_merit"]) > BALANCED]
    if not balanced:
        return ["Reading: no load balanced far inside the tolerance."]
    text = (f"Reading: damped Newton balances the loads up to {100 * max(balanced):g} % of the step's far inside the "
            f"tolerance (least merit <= {BALANCED:g}, Newton converging quadratically)")
    if beyond:
        merits = [float(row["least_merit"]) for row in beyond]
        accepted = [f"{100 * float(row['load']):g}" for row in beyond if row["converged"] == "yes"]
        text += (f"; from {100 * min(float(row['load']) for row in beyond):g} % on it stalls at a least merit of "
                 f"{min(merits):.2g} to {max(merits):.2g} (the full Jacobian's steps no longer lowering it, or no step "
                 "along the Newton direction doing so, as near a singular J): no equilibrium is found past "
                 f"{100 * max(balanced):g} %, the step's path ends, as at a limit point, before "
                 f"{100 * min(float(row['load']) for row in beyond):g} %")
        if accepted:
            text += (f". Within the step's tolerances all the same at {', '.join(accepted)} %: states the ramp "
                     "may accept there are the tolerance's margin, not an equilibrium near")
    text += "."
    gaps = [row for row in floor if row.get("flank_gap_mm")]
    if gaps:
        last = max((row for row in gaps if float(row["least_merit"]) <= BALANCED), key=lambda row: float(row["load"]),
                   default=gaps[0])
        text += (f" At the last load balanced ({100 * float(last['load']):g} %) the free edge at the entry is folded back "
                 f"on itself (its tangent turns by {float(last['edge_turn_deg']):.0f} deg, its least stretch "
                 f"{float(last['edge_least_stretch']):.3f}) and its two sides, drawn along the needle, lie "
                 f"{1000 * float(last['flank_gap_mm']):.0f} um apart (points more than {FLANK_SEPARATION:g} mm apart "
                 "along the edge); the needle, a line here, would hold them a wire's diameter apart.")
    return [text]


def reading(taylor_rows: list[dict], line: list[dict]) -> list[str]:
    """What the Taylor test and the line say, from their numbers."""
    def ratio_spread(tangent: str, direction: str, key: str) -> float:
        values = [float(row[key]) for row in taylor_rows if row["tangent"] == tangent and row["direction"] == direction
                  and float(row["t"]) <= 0.01]
        return max(values) / min(values)

    at_full_step = [float(row["remainder"]) for row in taylor_rows if row["direction"] == "Newton"
                    and float(row["t"]) == 1.0]
    full_step_difference = abs(at_full_step[0] - at_full_step[1]) / max(at_full_step)
    best = min(line, key=lambda row: float(row["residual_N"]))
    start = float(line[0]["start_residual_N"])
    return [f"Reading: with F, remainder / t^2 stays within a factor {ratio_spread('K + H + F', 'Newton', 'remainder_over_t2'):.3f} "
            f"(Newton direction) and {ratio_spread('K + H + F', 'random', 'remainder_over_t2'):.3f} (random) for t <= 0.01: "
            "the full Jacobian is the residual's derivative. Without F the remainder falls like t (remainder / t within "
            f"{ratio_spread('K + H', 'random', 'remainder_over_t'):.3f} on the random direction at small t): the omitted "
            f"follower stiffness, but at the full Newton step the two remainders differ by {full_step_difference:.1e} of "
            f"theirs: the residual's curvature dwarfs it. Along the Newton direction |r_u| is least at t = {float(best['t']):g} ({float(best['residual_N']):.4e} N, "
            f"{100 * (1 - float(best['residual_N']) / start):.1f} % below the start) and {float(line[0]['residual_N']) / start:.0f} "
            f"times the start at the full step: Newton's linear model holds for about {100 * float(best['t']):.0f} % of its "
            "step. The state sits near a fold of the tissue at the entry, where the rest of the load needs a large, "
            "strongly nonlinear move."]


def chart(rows: list[dict], path) -> None:
    """Left: the Taylor remainders against t (slope 2: the tangent is exact). Right: |r_u|
    along the Newton direction."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    floor = [row for row in rows if row["table"] == "floor"]
    figure, axes = plt.subplots(1, 3 if floor else 2, figsize=(16 if floor else 11, 4.2))
    left, right = axes[0], axes[1]
    for (tangent, direction), style in ((("K + H + F", "Newton"), "o-"), (("K + H + F", "random"), "s-"),
                                        (("K + H", "Newton"), "o--"), (("K + H", "random"), "s--")):
        own = [row for row in rows if row["table"] == "taylor" and row["tangent"] == tangent
               and row["direction"] == direction]
        if own:
            left.loglog([float(row["t"]) for row in own], [float(row["remainder"]) for row in own], style,
                        label=f"{tangent}, {direction} direction")
    left.set_xlabel("t")
    left.set_ylabel("|R(x + t d) - R(x) - t J d|")
    left.set_title("Taylor remainder (slope 2: J is R's derivative)", fontsize=10)
    left.legend(fontsize=8)
    line = [row for row in rows if row["table"] == "line"]
    if line:
        right.loglog([float(row["t"]) for row in line], [float(row["residual_N"]) for row in line], "o-",
                     label="|r_u(x + t d)|")
        right.axhline(float(line[0]["start_residual_N"]), color="grey", ls=":", label="|r_u(x)| (t = 0)")
        right.set_xlabel("t (1: the full Newton step)")
        right.set_ylabel("|r_u| (N)")
        right.set_title("Along the Newton direction at step 16's last load carried", fontsize=10)
        right.legend(fontsize=8)
    if floor:
        panel = axes[2]
        loads = np.array([float(row["load"]) for row in floor])
        least = np.array([float(row["least_merit"]) for row in floor])
        converged = np.array([row["converged"] == "yes" for row in floor])
        panel.semilogy(100 * loads[converged], least[converged], "o", color="tab:green",
                       label="least merit, within the tolerances")
        panel.semilogy(100 * loads[~converged], least[~converged], "x", color="tab:red", ms=8,
                       label="least merit, outside them")
        panel.axhline(1.0, ls=":", color="grey", label="tolerance (merit 1)")
        panel.axhline(BALANCED, ls="--", color="grey", lw=0.8, label=f"balanced ({BALANCED:g})")
        panel.set_xlabel("load (% of step 16's)")
        panel.set_ylabel("least merit |(r_u / tol_r, g / tol_g)| reached")
        panel.set_title("Damped Newton on the full Jacobian", fontsize=10)
        panel.legend(fontsize=8)
    figure.suptitle("soft_t2.5 at h/4: Newton's model at the stop (exact tangent K + H + F)")
    common.save_figure(figure, path, (0, 0, 1, 0.93))
    plt.close(figure)


def main() -> None:
    if "--report" in common.command_line(__doc__, ("--report",)):  # the table and chart again from the CSV
        rows = common.csv_rows(common.results_path("entry_newton.csv"))
        common.publish("entry_newton", report(rows), chart, rows)
        return
    rows = []
    for scene, level, factor, from_step in RUNS:
        kept: dict = {}
        rows.append(run(scene, level, factor, "shipped", from_step, {}))
        rows.append(run(scene, level, factor, "exact", from_step, kept))
        if scene == "soft_t2.5" and kept.get("states"):
            rows += taylor(kept)
            rows += residual_floor(kept)
    header = sorted({key for row in rows for key in row})
    common.write_csv(common.results_path("entry_newton.csv"), header, [[row.get(key, "") for key in header]
                                                                        for row in rows])
    common.publish("entry_newton", report(rows), chart, rows)


if __name__ == "__main__":
    main()
