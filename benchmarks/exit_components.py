"""Which part of the unplanned exit error moves under refinement: the needle's track in the
tissue, where the tip comes out, or where the desired exit point has been pushed to.

The exit error is |achieved_exit_def - desired_exit_def|: the tip's spatial position as it
leaves the tissue minus the spatial position of the desired exit's material point at that
moment. benchmarks/needle_coupling.py measures how it changes with the particle spacing; here
the same `simulate` runs (needle_coupling.scene, each scene's file as shipped) at nested
spacings 2h, h, h/2, h/4, h/8 (h the file's spacing) are split into what the exit error is the
difference of. For each pair of consecutive levels: the change of the exit error, of the
achieved exit (spatial), of the desired exit's spatial position, and the largest change of
the track's material tip point over steps TRACK_STEPS (where the needle has cut the tissue),
and of the displacement of the entry point (the free edge's material point where the needle
went in) after the exit.
A change that halves with each halving of the spacing converges at rate 1; the rate here is
log2 of the ratio of consecutive changes.

Writes benchmarks/results/exit_components.{csv,md} and prints the table. About 7 minutes (the
h/8 runs and soft_t2.5's failing h/4 take most of it).
Run from the repository root:  python benchmarks/exit_components.py
"""

from __future__ import annotations

import os

# single-threaded BLAS, as the `stitchplan` command sets it
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import math  # noqa: E402

import numpy as np  # noqa: E402

import _common as common  # noqa: E402
import needle_coupling  # noqa: E402
from stitchplan.config import with_discretization  # noqa: E402
from stitchplan.errors import InsertionFailure  # noqa: E402
from stitchplan.needle.insertion import run_insertion  # noqa: E402

SCENES = ("sh12_100x100", "sh12_100x100_mid", "soft_t3", "soft_t2.5")
FACTORS = (2.0, 1.0, 0.5, 0.25, 0.125)
LEVELS = ("2h", "h", "h/2", "h/4", "h/8")
TRACK_STEPS = (10, 20, 30)
COUPLING = needle_coupling.SHIPPED_COUPLING  # the scene's file as it is


def runs(scene: str) -> list:
    """The scene's unplanned insertion at each of FACTORS x its spacing, up to the first
    level that fails (its failure returned)."""
    base = needle_coupling.scene(scene, COUPLING)
    results = []
    for factor in FACTORS:
        try:
            result = run_insertion(with_discretization(base, spacing=base.discretization.spacing * factor))
        except InsertionFailure as failure:
            print(f"{scene} at {factor:g} h: {failure}", flush=True)
            return results, " ".join(str(failure).split())[:120]
        print(f"{scene} at {factor:g} h: {result.model.n_particles} particles, exit error "
              f"{result.exit_error_mm:.4f} mm", flush=True)
        results.append(result)
    return results, ""


def changes(coarse, fine) -> dict[str, float]:
    """How far each part moved from the `coarse` run to the `fine` one (mm)."""
    steps = [k for k in TRACK_STEPS if k <= min(len(coarse.steps), len(fine.steps))]
    return {
        "exit_error": fine.exit_error_mm - coarse.exit_error_mm,
        "achieved_exit_def": float(np.linalg.norm(fine.achieved_exit_def - coarse.achieved_exit_def)),
        "desired_exit_def": float(np.linalg.norm(fine.desired_exit_def - coarse.desired_exit_def)),
        "achieved_exit": float(np.linalg.norm(fine.achieved_exit - coarse.achieved_exit)),
        "track": max(float(np.linalg.norm(fine.steps[k - 1].tip_reference - coarse.steps[k - 1].tip_reference))
                     for k in steps),
        "entry": float(np.linalg.norm(entry_displacement(fine) - entry_displacement(coarse))),
    }


def entry_displacement(result) -> np.ndarray:
    """The displacement of the needle's entry point (a material point of the free edge) once
    the tip has left the tissue, mm (2,)."""
    return result.model.shape_functions_at(result.geometry.entry[None]).values @ result.coefficients[-1]


PARTS = (("exit_error", "exit error"), ("achieved_exit_def", "achieved exit (spatial)"),
         ("desired_exit_def", "desired exit's spatial position"), ("achieved_exit", "achieved exit (material)"),
         ("track", f"track's tip point, steps {', '.join(map(str, TRACK_STEPS))} (material, largest)"),
         ("entry", "entry point's displacement at the exit"))


def rate(first: float | None, second: float | None) -> float | str:
    """log2 of the ratio of two consecutive changes (nested levels, ratio 2)."""
    if not first or not second:
        return "—"
    return math.log2(abs(first) / abs(second))


def main() -> None:
    rows = []
    pairs = len(FACTORS) - 1
    for scene in SCENES:
        results, failure = runs(scene)
        moved = [changes(a, b) for a, b in zip(results, results[1:])]
        for key, label in PARTS:
            values = [m[key] for m in moved] + [None] * (pairs - len(moved))
            rates = [rate(a, b) for a, b in zip(values, values[1:])]
            rows.append([scene, label, *("—" if v is None else v for v in values), *rates])
        levels = " / ".join(f"{r.exit_error_mm:.4f}" for r in results)
        if failure:
            levels += f" / {LEVELS[len(results)]}: {failure}"
        rows.append([scene, f"exit error (mm) at {', '.join(LEVELS)}", levels, *[""] * (2 * pairs - 2)])
    header = ["scene", "part", *(f"{a} -> {b} (mm)" for a, b in zip(LEVELS, LEVELS[1:])),
              *(f"rate ({a}, {b}, {c})" for a, b, c in zip(LEVELS, LEVELS[1:], LEVELS[2:]))]
    common.write_csv(common.results_path("exit_components.csv"), header, rows)
    lines = [
        "# Which part of the exit error moves under refinement\n",
        f"Generated by `python benchmarks/exit_components.py` ({common.machine_note()}). `simulate` "
        "(each scene's file as shipped) at nested spacings 2h, h, h/2, h/4 and h/8, h the file's "
        "spacing; soft_t3 and soft_t2.5 are configs/sh12_100x100.yaml as neo-Hookean slabs 3 and 2.5 mm "
        "thick (benchmarks/needle_coupling.py). Exit error: its signed change between levels; the other "
        "parts: how far they moved (mm). Rate: log2 of the ratio of consecutive changes (1: the change "
        "halves with the spacing).\n",
        common.markdown_table(header, rows),
        "",
    ]
    common.write_report("exit_components.md", lines)


if __name__ == "__main__":
    main()
