"""MINRES with the block preconditioner diag(K0^-1, S^-1) (eq. 3.71-3.74) as needle points
accumulate: iterations per Newton solve and the condition numbers of the saddle matrix and
of the preconditioned one, at every needle step.

The scene is the 40 x 30 mm phantom block of tests/test_stability.py (clamped on the right,
99 particles at 4 mm, an 8 mm needle entering (0, 22) clockwise in 0.1 rad steps, the
thesis's point coupling, Levenberg-Marquardt tip tracking), run once with dense condition
numbers recorded at every step. The README's Stability limits (the MINRES row) quotes it.

Writes benchmarks/results/minres_growth.md and .csv. About 10 seconds.
Run from the repository root:  python benchmarks/minres_growth.py
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

import _common as common  # noqa: E402
from stitchplan.config.scenario import parse_scenario  # noqa: E402
from stitchplan.needle.insertion import run_insertion  # noqa: E402

PHANTOM = {"lame_lambda": 0.189151, "lame_mu": 0.147688}  # MPa, thesis appendix A.2


def block_scene():
    return parse_scenario({
        "tissue": {"size": [40.0, 30.0], "thickness": 10.0, "clamped": ["right"], "material": dict(PHANTOM)},
        "discretization": {"spacing": 4.0},
        "needle": {"radius": 8.0, "entry": [0.0, 22.0], "turn": "cw", "step": 0.1, "friction": 0.0602,
                   "cutting_force": 0.7, "coupling": "points"}})


def main() -> None:
    common.command_line(__doc__)
    result = run_insertion(block_scene(), linear_solver="minres", tip_tracking="levenberg-marquardt",
                           condition_numbers=True)
    header = ["step", "needle_points", "newton_iterations", "minres_iterations", "minres_per_solve",
              "condition_saddle", "condition_preconditioned"]
    rows = [[k + 1, s.needle_points, s.newton_iterations, s.minres_iterations,
             s.minres_iterations / s.newton_iterations, s.condition_saddle, s.condition_preconditioned]
            for k, s in enumerate(result.steps)]
    per_solve = np.array([row[4] for row in rows])
    preconditioned = np.array([row[6] for row in rows])
    saddle = np.array([row[5] for row in rows])
    first, last = slice(0, 5), slice(-5, None)
    lines = [
        "# MINRES as needle points accumulate",
        "",
        "`python benchmarks/minres_growth.py` (results/minres_growth.csv). " + __doc__.split("\n\n")[1].replace("\n", " "),
        "",
        f"Iterations per Newton solve: {per_solve[first].mean():.1f} over the first five steps "
        f"({rows[0][1]} to {rows[4][1]} needle points), {per_solve[last].mean():.1f} over the last five "
        f"({rows[-5][1]} to {rows[-1][1]}; {per_solve.min():.1f} to {per_solve.max():.1f} in all). Preconditioned "
        f"condition number {preconditioned[0]:.3g} at the first step, {preconditioned[-1]:.3g} at the last, "
        f"{preconditioned.max():.3g} at most; the saddle matrix's own {saddle[0]:.3g} to {saddle[-1]:.3g}.",
        "",
        common.markdown_table(header, [[common.fmt(v) for v in row] for row in rows]),
        "",
        common.machine_note(),
        "",
    ]
    common.write_csv(common.results_path("minres_growth.csv"), header, rows)
    common.write_report("minres_growth.md", lines)


if __name__ == "__main__":
    main()
