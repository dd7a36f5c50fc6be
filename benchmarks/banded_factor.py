"""The banded Cholesky of the path without CHOLMOD (stitchplan/tissue/factorization.py):
where it beats SuperLU, and what it does to a planned run.

1. Matrices: K0 of every shipped needle scene at its spacing, at twice it (the exit error
   estimate's replay model) and at half of it (the verification's), in reverse Cuthill-McKee
   order: the band's width, its size against K's stored entries (the rule's ratio; the band is
   used at most BANDED_STORAGE), and the factor and one solve by LAPACK's banded Cholesky,
   SuperLU and, with the `fast` extra, CHOLMOD (median of 5 factors, of 11 solves).
2. Planned runs: `plan CONFIG --no-compare --no-verify` with STITCHPLAN_LINEAR_BACKEND=scipy
   (the path without the `fast` extra: the band where the rule allows it, SuperLU elsewhere),
   with =superlu (SuperLU alone, as before the band) and with the band wherever the matrix is
   positive definite (the rule's limit lifted: what the rule decides between), in turn,
   REPEATS each: the median of the summary's `wall_seconds` (the planned run), the ratios, the
   backends that ran and the largest difference between the planned exit errors.

Writes benchmarks/results/banded_factor.{csv,md} and banded_factor_runs.csv and prints the tables. About 6 minutes.
Run from the repository root:  python benchmarks/banded_factor.py
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import contextlib  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402

import _common as common  # noqa: E402

SCENES = ("sh12_100x100", "sh12_100x100_mid", "sh12_100x50", "sh12_100x40", "sh12_100x30",
          "needle20_entry30", "needle20_entry25", "needle20_entry20", "needle20_entry18",
          "skin_layered", "hole_near_stitch", "wound_closure")
FACTORS = (1.0, 2.0, 0.5)  # spacing / the scene's: the planning model, the estimate's, the verification's
REPEATS = int(os.environ.get("BANDED_REPEATS", 5))
PATHS = {"scipy": {"STITCHPLAN_LINEAR_BACKEND": "scipy"}, "SuperLU": {"STITCHPLAN_LINEAR_BACKEND": "superlu"},
         "band": {"STITCHPLAN_LINEAR_BACKEND": "scipy"}}
# the `stitchplan` command with the band's limit lifted (the "band" path)
UNLIMITED_BAND = [common.STITCHPLAN[0], "-c", "import sys; import stitchplan.tissue.factorization as factorization; "
                  "factorization.BANDED_STORAGE = float('inf'); from stitchplan.cli import main; "
                  "sys.argv[0] = 'stitchplan'; main()"]


@contextlib.contextmanager
def command_prefix(prefix: list[str]):
    """common.scene_command's processes started with `prefix` instead of the `stitchplan` command's."""
    saved, common.STITCHPLAN = common.STITCHPLAN, prefix
    try:
        yield
    finally:
        common.STITCHPLAN = saved


def matrices_table() -> list[list]:
    from stitchplan.config import load_scenario
    from stitchplan.needle.prepared_tissue import PreparedTissue
    from stitchplan.planning.replay_models import rescaled
    from stitchplan.tissue import factorization

    rows = []
    probe = None
    for scene in SCENES:
        for factor in FACTORS:
            scenario = rescaled(load_scenario(common.REPO_ROOT / "configs" / f"{scene}.yaml"), factor)
            stiffness = sp.csr_matrix(PreparedTissue(scenario).stiffness_at_rest())
            n = stiffness.shape[0]
            probe = np.cos(np.arange(n))
            saved, factorization.BANDED_STORAGE = factorization.BANDED_STORAGE, np.inf
            try:
                band_factor_s, banded = common.median_time(
                    lambda: factorization.BandedCholeskyFactor(factorization.narrow_band(stiffness)), 5, 1)
                bandwidth = factorization.narrow_band(stiffness)[0].shape[0] - 1
            finally:
                factorization.BANDED_STORAGE = saved
            band_solve_s, solution = common.median_time(lambda: banded.solve(probe), 11)
            residual = np.linalg.norm(stiffness @ solution - probe) / np.linalg.norm(probe)
            lu_factor_s, lu = common.median_time(lambda: factorization.SuperLUFactor(stiffness), 5, 1)
            lu_solve_s, _ = common.median_time(lambda: lu.solve(probe), 11)
            cholmod = ["", ""]
            if factorization.cholmod is not None:
                ch_factor_s, cholesky = common.median_time(lambda: factorization.CholeskyFactor(stiffness), 5, 1)
                ch_solve_s, _ = common.median_time(lambda: cholesky.solve(probe), 11)
                cholmod = [1e3 * ch_factor_s, 1e3 * ch_solve_s]
            ratio = n * (bandwidth + 1) / stiffness.nnz
            rows.append([scene, factor, n, stiffness.nnz, bandwidth, ratio,
                         "band" if ratio <= factorization.BANDED_STORAGE else "SuperLU",
                         1e3 * band_factor_s, 1e3 * band_solve_s, 1e3 * lu_factor_s, 1e3 * lu_solve_s, *cholmod,
                         residual])
            print(rows[-1], flush=True)
    return rows


def planned_runs_table() -> list[list]:
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        for scene in SCENES:
            seconds = {name: [] for name in PATHS}
            errors, backends = {}, {}
            for round_ in range(REPEATS):
                for name in (list(PATHS) if round_ % 2 == 0 else list(PATHS)[::-1]):  # alternating
                    folder = Path(scratch) / name
                    folder.mkdir(exist_ok=True)
                    with command_prefix(UNLIMITED_BAND if name == "band" else common.STITCHPLAN):
                        _, summary = common.scene_command("plan", scene, ["--no-compare", "--no-verify", "-q"],
                                                          folder, common.REPO_ROOT, **PATHS[name])
                    seconds[name].append(summary["wall_seconds"])
                    errors[name] = summary["exit_error_mm"]
                    backends[name] = ", ".join(summary["solver"]["linear_solver_backends"])
            scipy, superlu, band = (statistics.median(seconds[name]) for name in PATHS)
            won = sum(a < b for a, b in zip(seconds["scipy"], seconds["SuperLU"]))
            spread = max(errors.values()) - min(errors.values())
            rows.append([scene, scipy, superlu, band, scipy / superlu, band / superlu, f"{won} of {REPEATS}",
                         spread, backends["scipy"]])
            print(rows[-1], flush=True)
    return rows


def main() -> None:
    from stitchplan.tissue.factorization import BANDED_STORAGE

    matrices = matrices_table()
    runs = planned_runs_table()
    matrix_header = ["scene", "spacing factor", "dofs", "stored entries", "bandwidth", "band / stored",
                     "rule's choice", "band factor (ms)", "band solve (ms)", "SuperLU factor (ms)",
                     "SuperLU solve (ms)", "CHOLMOD factor (ms)", "CHOLMOD solve (ms)", "band solve residual"]
    run_header = ["scene", "planned run, scipy path (s)", "SuperLU alone (s)", "band wherever it factors (s)",
                  "scipy path / SuperLU", "band / SuperLU", "pairs won by the scipy path over SuperLU",
                  "exit error spread (mm)", "backends (scipy path)"]
    common.write_csv(common.results_path("banded_factor.csv"), matrix_header, matrices)
    common.write_csv(common.results_path("banded_factor_runs.csv"), run_header, runs)
    common.write_report("banded_factor.md", [
        "# The banded Cholesky of the path without CHOLMOD",
        "",
        f"Generated by `python benchmarks/banded_factor.py` ({common.machine_note()}).",
        "",
        "## K0 of the shipped needle scenes",
        "",
        "At the scene's spacing (factor 1), the estimate's (2) and the verification's (0.5); the band "
        "in reverse Cuthill-McKee order, n x (bandwidth + 1) numbers; the band is used where that is at "
        f"most {BANDED_STORAGE:g} times K's stored entries. Factor: median of 5; one solve of one "
        "right-hand side: median of 11.",
        "",
        common.markdown_table(matrix_header, matrices),
        "",
        "## Planned runs",
        "",
        f"`plan CONFIG --no-compare --no-verify`, the summary's `wall_seconds`, median of {REPEATS} each, "
        "STITCHPLAN_LINEAR_BACKEND=scipy (the band where the rule allows, SuperLU elsewhere: the path "
        "without the `fast` extra), =superlu (SuperLU alone) and the band wherever the matrix is positive "
        "definite (the rule's limit lifted), in turn; exit error spread: the largest difference between the "
        "three's planned exit errors.",
        "",
        common.markdown_table(run_header, runs),
    ])


if __name__ == "__main__":
    common.command_line(__doc__)
    main()
