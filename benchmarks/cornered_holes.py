"""Holes with corners on the verification scenes: blocked (as shipped) or weighed by the way
round them, as round holes are.

`stitchplan deform` on the plate with an 8 x 8 mm hole of benchmarks/deform_shapes.py
(clamped left, pulled on the right edge) at its default spacing, half and a quarter of it,
against that benchmark's scikit-fem reference (the probe displacements in
results/deform_shapes.csv, rows of spacing 0): the pairs through the hole blocked (the
visibility criterion as shipped) and weighed by the way round it (every convex hole taken as
round, in the worker, as benchmarks/small_holes.py does on a squeezed plate with a 4 x 4 mm
square hole). Max probe error relative to the largest reference displacement.

Writes benchmarks/results/cornered_holes.{csv,md} and prints the table. Under a minute.
Run from the repository root:  python benchmarks/cornered_holes.py
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import csv  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402

import _common as common  # noqa: E402
import numpy as np  # noqa: E402

SCENE = "plate_with_hole"  # deform_shapes.SCENES
REFINEMENTS = (1, 2, 4)


def worker(factor: str, weighed: str = "") -> dict:
    """The probe displacements of the plate at its default spacing / `factor` (`--worker`)."""
    from deform_shapes import SCENES
    from small_holes import take_convex_holes
    from stitchplan.config.scenario import parse_scenario, with_discretization
    from stitchplan.tissue.deform import run_deform

    if weighed:
        take_convex_holes(as_round=True)
    scenario = parse_scenario(SCENES[SCENE])
    result = run_deform(with_discretization(scenario, spacing=scenario.discretization.spacing / float(factor)))
    return {"particles": result.model.n_particles, "probes": result.probe_displacements.tolist()}


def main() -> None:
    with common.results_path("deform_shapes.csv").open() as handle:  # its probes fill the columns from the 7th on
        reference = next(np.array([float(value) for value in row[6:]]).reshape(-1, 2) for row in csv.reader(handle)
                         if row[0] == SCENE and row[1] != "spacing_mm" and float(row[1]) == 0.0)
    rows, cells = [], {}
    for label, options in (("blocked (as shipped)", ()), ("way round", ("weighed",))):
        for factor in REFINEMENTS:
            record = common.worker_record(__file__, common.REPO_ROOT, str(factor), *options)
            error = common.max_probe_error(np.array(record["probes"]), reference)
            rows.append([label, factor, record["particles"], error])
            cells[label, factor] = f"{100 * error:.3f} %"
            print(f"{label}, default/{factor}: {cells[label, factor]}", flush=True)
    header = ["pairs through the hole", *(f"default/{factor}" for factor in REFINEMENTS)]
    table = [[label, *(cells[label, factor] for factor in REFINEMENTS)]
             for label in ("blocked (as shipped)", "way round")]
    common.write_csv(common.results_path("cornered_holes.csv"), ["pairs", "refinement", "particles", "max_probe_error_rel"],
                     rows)
    common.write_report("cornered_holes.md", [
        "# A hole with corners: blocked or weighed by the way round",
        "",
        "`stitchplan deform` on benchmarks/deform_shapes.py's plate with an 8 x 8 mm hole (default "
        "spacing 1 mm) against its scikit-fem reference (results/deform_shapes.csv); max probe error, "
        "% of the largest displacement. Script: benchmarks/cornered_holes.py.",
        "",
        common.markdown_table(header, table),
        "",
        f"Machine: {common.machine_note()}.",
        "",
    ])


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        print(json.dumps(worker(*sys.argv[2:])))
    else:
        common.command_line(__doc__)
        main()
