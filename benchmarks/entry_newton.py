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
mixing, from step FROM on (the steps before as shipped, for time).

Runs: sh12_100x100 at h (exact from step 1: where Newton converges, what F changes) and
soft_t2.5 at h/4 (exact from step 14). Then, at the last load exact Newton carried at step 16
(the state restored after the stop), a Taylor test of the residual R = [r_u; g] of eq. 3.62
under the step's full load: |R(x + t d) - R(x) - t J d| for t = 1 .. 1e-4 along the Newton
direction d = -J^-1 R(x) and along a random direction, for J with and without F. A remainder
falling like t^2 says J is R's exact derivative; like t, that a term is missing. Along the
Newton direction, |R(x + t d)| against t says how far Newton's linear model holds.

Writes benchmarks/results/entry_newton.{csv,md,png}. About 8 minutes; `--report` redraws the
table and chart from the CSV.
Run from the repository root:  python benchmarks/entry_newton.py
"""

from __future__ import annotations

import os

# single-threaded BLAS, as the `stitchplan` command sets it
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import contextlib  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402
import scipy.sparse.linalg as spla  # noqa: E402

import _common as common  # noqa: E402
import needle_coupling  # noqa: E402
from stitchplan.config import with_discretization  # noqa: E402
from stitchplan.errors import InsertionFailure  # noqa: E402
from stitchplan.needle import equilibrium as equilibrium_module  # noqa: E402
from stitchplan.needle.equilibrium import NeedleInsertion  # noqa: E402
from stitchplan.needle.insertion import run_insertion  # noqa: E402
from stitchplan.needle.saddle_point import SaddlePointSolver  # noqa: E402

RUNS = (("sh12_100x100", "h", 1.0, 1), ("soft_t2.5", "h/4", 0.25, 14))  # scene, level, factor, exact from step
PROBE_STEP = 16  # soft_t2.5's step at h/4 whose last load carried is Taylor-tested
STEPS = (1.0, 0.1, 0.01, 1e-3, 1e-4)  # t of the Taylor test
NEWTON_LINE = (1.0, 0.5, 0.2, 0.1, 0.05, 0.02, 0.01)  # t along the Newton direction


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
    interleaved = sp.kron(rows, sp.identity(2), format="csr")
    turn = sp.bsr_matrix((blocks, np.arange(len(points)), np.arange(len(points) + 1)),
                         shape=(2 * len(points), 2 * len(points))).tocsr()
    return (interleaved.T @ turn @ interleaved).tocsr()


def jacobian(insertion: NeedleInsertion, free: np.ndarray, multipliers: np.ndarray, center: np.ndarray,
             with_follower: bool) -> tuple[sp.csc_matrix, np.ndarray]:
    """The saddle matrix [[K + H (+ F), G], [G^T, 0]] at the state, and R = [r_u; g] there."""
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
    gets the insertion and, at PROBE_STEP, the snapshot of each load carried from 90 % on."""
    newton, solve, stiffness = NeedleInsertion._newton, SaddlePointSolver.solve_direct, NeedleInsertion._stiffness
    residuals, renew, depth = NeedleInsertion._timed_residuals, equilibrium_module.renew_factor, \
        equilibrium_module.FIXED_CENTER_ANDERSON_DEPTH
    exact = {"on": False}

    def newton_step(insertion, rotation, step, aim=None):
        exact["on"] = step >= from_step
        kept["insertion"] = insertion
        result = newton(insertion, rotation, step, aim)
        if step == PROBE_STEP and insertion.coupling.load_factor >= 0.9:
            kept["carried"] = (insertion.snapshot(), insertion.coupling.load_factor)
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
    equilibrium_module.renew_factor = lambda *args: True if exact["on"] else renew(*args)
    equilibrium_module.FIXED_CENTER_ANDERSON_DEPTH = 0 if from_step <= 1 else depth
    refuse = NeedleInsertion._refuse_unstable  # its eigensolver takes a symmetric tangent
    NeedleInsertion._refuse_unstable = lambda insertion, rotation, step: None if exact["on"] else \
        refuse(insertion, rotation, step)
    try:
        yield
    finally:
        NeedleInsertion._newton, NeedleInsertion._timed_residuals = newton, residuals
        NeedleInsertion._stiffness, SaddlePointSolver.solve_direct = stiffness, solve
        equilibrium_module.renew_factor, equilibrium_module.FIXED_CENTER_ANDERSON_DEPTH = renew, depth
        NeedleInsertion._refuse_unstable = refuse


def run(scene: str, level: str, factor: float, method: str, from_step: int, kept: dict) -> dict:
    base = needle_coupling.scene(scene, needle_coupling.SHIPPED_COUPLING)
    scenario = with_discretization(base, spacing=base.discretization.spacing * factor)
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
    snapshot, carried = kept["carried"]
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
                 common.markdown_table(["t", "|r_u(x + t d)| (N)"], [[f"{float(row['t']):g}", row["residual_N"]] for row in line]),
                 "", *reading(taylor_rows, line), ""]
    return "\n".join(text) + "\n"


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

    figure, (left, right) = plt.subplots(1, 2, figsize=(11, 4.2))
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
    figure.suptitle("soft_t2.5 at h/4: Newton's model at the stop (exact tangent K + H + F)")
    common.save_figure(figure, path, (0, 0, 1, 0.93))
    plt.close(figure)


def main() -> None:
    if "--report" in sys.argv[1:]:  # the table and chart again from the CSV
        rows = common.csv_rows(common.results_path("entry_newton.csv"))
        common.publish("entry_newton", report(rows), chart, rows)
        return
    rows = []
    for scene, level, factor, from_step in RUNS:
        kept: dict = {}
        rows.append(run(scene, level, factor, "shipped", from_step, {}))
        rows.append(run(scene, level, factor, "exact", from_step, kept))
        if scene == "soft_t2.5" and "carried" in kept:
            rows += taylor(kept)
    header = sorted({key for row in rows for key in row})
    common.write_csv(common.results_path("entry_newton.csv"), header, [[row.get(key, "") for key in header]
                                                                        for row in rows])
    common.publish("entry_newton", report(rows), chart, rows)


if __name__ == "__main__":
    main()
