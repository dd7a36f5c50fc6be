"""How the kernel's width conditions the tissue's stiffness, and what a run then does.

1. K0 (the stiffness at rest) of configs/sh12_100x100.yaml at its default spacing and at
   5 mm, for dilations 2 to 6: its condition number (largest over smallest eigenvalue, by
   scipy's eigsh) and the relative residual |K0 x - p| / |p| a solve with its factor leaves
   (tissue.factorization.solve_residual), and the estimate `simulate` and `plan` check
   against STIFFNESS_CONDITION to refuse a nearly singular discretization.
2. `stitchplan simulate` of the same scene at dilations 2, 3, 3.5 and 4 at its default
   spacing: exit code, exit error, wall time (dilation 4 is refused).

The cubic-spline kernel of support a has the Fourier transform (sin(k a / 4) / (k a / 4))^4
per direction, which vanishes at the particles' alternating mode k = pi / spacing for
a = 4 spacings: there (and near it) coefficients that alternate from particle to particle
make no displacement.

Writes benchmarks/results/dilation_conditioning.md and .csv. About 3 minutes.
Run from the repository root:  python benchmarks/dilation_conditioning.py
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import json  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import scipy.sparse.linalg as spla  # noqa: E402

import _common as common  # noqa: E402
from stitchplan.config.scenario import load_scenario, with_discretization  # noqa: E402
from stitchplan.needle.prepared_tissue import STIFFNESS_CONDITION, PreparedTissue  # noqa: E402
from stitchplan.errors import InputError  # noqa: E402
from stitchplan.tissue.factorization import condition_estimate, factorize, solve_residual  # noqa: E402

SCENE = common.REPO_ROOT / "configs" / "sh12_100x100.yaml"
DILATIONS = (2.0, 2.5, 3.0, 3.25, 3.5, 3.75, 4.0, 4.5, 5.0, 6.0)
RUN_DILATIONS = (2.0, 3.0, 3.5, 4.0)


def stiffness_row(scene, spacing: float | None, dilation: float) -> list:
    scenario = with_discretization(scene, spacing=spacing, dilation=dilation)
    tissue = PreparedTissue(scenario)
    stiffness = tissue.stiffness_at_rest().tocsc()
    factor = factorize(stiffness, symmetric_positive=True)
    try:
        tissue.factor_at_rest()
        refused = False
    except InputError:
        refused = True
    largest = spla.eigsh(stiffness, 1, which="LA", return_eigenvectors=False)[0]
    smallest = spla.eigsh(stiffness, 1, sigma=0, which="LM", return_eigenvectors=False)[0]
    return [scenario.discretization.spacing, dilation, len(tissue.model.particles), stiffness.nnz,
            largest / abs(smallest), condition_estimate(stiffness, factor), solve_residual(stiffness, factor),
            refused]


def main() -> None:
    scene = load_scenario(SCENE)
    header = ["spacing_mm", "dilation", "particles", "nnz", "condition", "condition_estimate", "solve_residual",
              "refused"]
    rows = [stiffness_row(scene, spacing, dilation) for spacing in (None, 5.0) for dilation in DILATIONS]
    common.write_csv(common.results_path("dilation_conditioning.csv"), header, rows)

    run_rows = []
    with tempfile.TemporaryDirectory() as folder:
        for dilation in RUN_DILATIONS:
            summary_path = Path(folder) / f"d{dilation}.json"
            start = time.perf_counter()
            finished = subprocess.run([*common.STITCHPLAN, "simulate", str(SCENE), "--dilation", str(dilation),
                                       "--summary", str(summary_path)], capture_output=True, text=True,
                                      cwd=common.REPO_ROOT, env=common.command_environment())
            seconds = time.perf_counter() - start
            if finished.returncode == 0:
                summary = json.loads(summary_path.read_text())
                run_rows.append([dilation, 0, summary["exit_error_mm"], summary.get("exit_error_estimate_mm"),
                                 seconds, ""])
            else:
                run_rows.append([dilation, finished.returncode, "", "", seconds,
                                 finished.stderr.strip().splitlines()[-1].replace(f"{common.REPO_ROOT}/", "")[:150] + " …"])

    lines = [
        "# Kernel width against the stiffness's conditioning",
        "",
        "`python benchmarks/dilation_conditioning.py` (results/dilation_conditioning.csv).",
        "configs/sh12_100x100.yaml; K0 at rest. `condition`: eigsh's largest over smallest eigenvalue;",
        "`condition_estimate`: tissue.factorization.condition_estimate (Gershgorin over three inverse",
        "iterations), which `simulate` and `plan` compare with STIFFNESS_CONDITION",
        f"({STIFFNESS_CONDITION:.0e}): `refused`, they stop with an InputError (exit 2) before the first",
        "needle step; `solve_residual`: |K0 x - p| / |p| of one solve.",
        "",
        common.markdown_table(header, rows),
        "",
        "`stitchplan simulate` at the default spacing (wall time of the whole command):",
        "",
        common.markdown_table(["dilation", "exit_code", "exit_error_mm", "exit_error_estimate_mm", "seconds",
                               "error"], run_rows),
        "",
        common.machine_note(),
        "",
    ]
    common.write_report("dilation_conditioning.md", lines)


if __name__ == "__main__":
    common.command_line(__doc__)
    main()
