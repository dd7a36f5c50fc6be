"""Tissue shapes against an independent FEM: `stitchplan deform` on a plate with a
rectangular hole, a two-layer slab, an L-shaped outline, a plate with a circular inclusion,
one with a circular hole and the scenario format's notched outline (sloped walls, a hole cut
into the outline, a circular hole), each against a fine scikit-fem solution (Q2
quadrilaterals graded toward every corner, benchmarks/skfem_reference.py solve_skfem_shape;
where edges are sloped or curved P2 triangles that follow them, graded toward the re-entrant
corners, solve_skfem_curved), at the default spacing, half and a quarter of it: the max
probe error and the observed convergence rate. The reference's own probe displacements are
a row of the CSV each (spacing 0).

Writes benchmarks/results/deform_shapes.{csv,md} and prints the table.
Run from the repository root:  python benchmarks/deform_shapes.py
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import math  # noqa: E402
from functools import partial  # noqa: E402

import _common as common  # noqa: E402
import numpy as np  # noqa: E402
from skfem_reference import solve_skfem_curved, solve_skfem_shape  # noqa: E402
from stitchplan.config.scenario import parse_scenario, with_discretization  # noqa: E402
from stitchplan.tissue.deform import run_deform  # noqa: E402

SOFT = {"model": "saint-venant-kirchhoff", "lame_lambda": 0.189151, "lame_mu": 0.147688}
STIFF = {"model": "saint-venant-kirchhoff", "lame_lambda": 0.756604, "lame_mu": 0.590752}  # 4 x SOFT

SCENES = {
    # L: 40 x 40 mm with the 20 x 20 mm upper-right square cut away; clamped bottom, the top of
    # the upper arm sheared to the right (the re-entrant corner (20, 20) is singular)
    "l_shape": {
        "name": "L-shaped outline",
        "tissue": {"outline": [[0.0, 0.0], [40.0, 0.0], [40.0, 20.0], [20.0, 20.0], [20.0, 40.0],
                               [0.0, 40.0]],
                   "thickness": 10.0, "material": SOFT,
                   "clamped": [{"segment": [[0.0, 0.0], [40.0, 0.0]]}]},
        "loads": [{"segment": [[0.0, 40.0], [20.0, 40.0]], "force": [0.2, 0.0]},
                  {"segment": [[40.0, 0.0], [40.0, 20.0]], "force": [0.0, 0.15]}],
        "probes": [[0.0, 40.0], [20.0, 40.0], [40.0, 20.0], [20.0, 20.0], [10.0, 30.0], [30.0, 10.0]],
    },
    # 40 x 20 mm plate, an 8 x 8 mm hole in the middle, clamped left, pulled on the right edge
    "plate_with_hole": {
        "name": "plate with a rectangular hole",
        "tissue": {"size": [40.0, 20.0], "thickness": 10.0, "material": SOFT, "clamped": ["left"],
                   "holes": [{"polygon": [[16.0, 6.0], [24.0, 6.0], [24.0, 14.0], [16.0, 14.0]]}]},
        "loads": [{"segment": [[40.0, 0.0], [40.0, 20.0]], "force": [1.0, 0.3]}],
        "probes": [[40.0, 10.0], [40.0, 20.0], [20.0, 14.0], [20.0, 6.0], [24.0, 10.0], [30.0, 3.0]],
    },
    # 40 x 20 mm slab: soft below y = 12, a 4x stiffer layer above; clamped left, a force on the
    # right edge pulling and shearing both layers
    "two_layer_slab": {
        "name": "two-layer slab",
        "tissue": {"size": [40.0, 20.0], "thickness": 10.0, "material": SOFT, "clamped": ["left"],
                   "regions": [{"polygon": [[0.0, 12.0], [40.0, 12.0], [40.0, 20.0], [0.0, 20.0]],
                                "material": STIFF}]},
        "loads": [{"segment": [[40.0, 0.0], [40.0, 20.0]], "force": [1.0, -0.3]}],
        "probes": [[40.0, 0.0], [40.0, 12.0], [40.0, 20.0], [20.0, 12.0], [20.0, 4.0], [20.0, 18.0]],
    },
    # 40 x 20 mm plate, a 4x stiffer circular inclusion of radius 5 mm in the middle (the
    # model's 96-gon, its edges cutting the background cells at every slope), clamped left,
    # pulled and sheared on the right edge
    "circular_inclusion": {
        "name": "plate with a circular inclusion",
        "tissue": {"size": [40.0, 20.0], "thickness": 10.0, "material": SOFT, "clamped": ["left"],
                   "regions": [{"circle": {"center": [20.0, 10.0], "radius": 5.0}, "material": STIFF}]},
        "loads": [{"segment": [[40.0, 0.0], [40.0, 20.0]], "force": [1.0, 0.3]}],
        "probes": [[40.0, 10.0], [40.0, 20.0], [20.0, 10.0], [25.0, 10.0], [20.0, 15.0], [30.0, 3.0]],
    },
    # the same plate with a circular hole of radius 5 mm instead: free curved edges
    "circular_hole": {
        "name": "plate with a circular hole",
        "tissue": {"size": [40.0, 20.0], "thickness": 10.0, "material": SOFT, "clamped": ["left"],
                   "holes": [{"circle": {"center": [20.0, 10.0], "radius": 5.0}}]},
        "loads": [{"segment": [[40.0, 0.0], [40.0, 20.0]], "force": [1.0, 0.3]}],
        "probes": [[40.0, 10.0], [40.0, 20.0], [25.0, 10.0], [20.0, 15.0], [20.0, 5.0], [30.0, 3.0]],
    },
    # the scenario format's shape example (README, Tissue shapes) without its region, in St.
    # Venant-Kirchhoff: a notch with sloped walls in the top edge, a square hole cut into the
    # outline's top right, a circular hole; clamped right, pulled left on its left edge
    "notched_outline": {
        "name": "the scenario format's notched outline",
        "tissue": {"outline": [[0.0, 0.0], [60.0, 0.0], [60.0, 30.0], [34.0, 30.0], [32.0, 22.0], [28.0, 22.0],
                               [26.0, 30.0], [0.0, 30.0]],
                   "thickness": 10.0, "material": SOFT, "clamped": ["right"],
                   "holes": [{"polygon": [[40.0, 20.0], [60.0, 20.0], [60.0, 40.0], [40.0, 40.0]]},
                             {"circle": {"center": [20.0, 10.0], "radius": 3.0}}]},
        "loads": [{"segment": [[0.0, 5.0], [0.0, 25.0]], "force": [-1.0, 0.0]}],
        "probes": [[0.0, 15.0], [0.0, 25.0], [10.0, 10.0], [20.0, 13.0], [30.0, 15.0], [26.0, 30.0],
                   [34.0, 30.0], [40.0, 25.0]],
    },
}
# the scenes whose reference follows sloped or curved edges (solve_skfem_curved), with its
# levels of grading toward the re-entrant corners
CURVED = {"circular_inclusion": 0, "circular_hole": 0, "notched_outline": 4}
REFERENCE_H = 0.25  # mm, skfem element side (Q2 plus grading at the corners; P2 triangles where curved)
REFINEMENTS = (1, 2, 4)  # spacing = default / r
# one level further for these scenes (a note under the table, with the error of every probe at
# the last two levels): the notched outline, whose probes the reference's own change bounds there
FURTHER = {"notched_outline": 8}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference-h", type=float, default=REFERENCE_H)
    args = parser.parse_args()
    rows, csv_rows, notes = [], [], []
    for key, raw in SCENES.items():
        scenario = parse_scenario(raw)
        default = scenario.discretization.spacing
        print(f"{key}: skfem reference h = {args.reference_h:g} mm ...", flush=True)
        solve = partial(solve_skfem_curved, grading=CURVED[key]) if key in CURVED else solve_skfem_shape
        reference = solve(scenario, args.reference_h)
        check = solve(scenario, 2 * args.reference_h)
        reference_change = common.max_probe_error(check.probe_displacements, reference.probe_displacements)
        csv_rows.append([key, 0.0, "", "", "", reference.seconds, *reference.probe_displacements.ravel()])
        errors, spacings, per_probe = [], [], []
        scale = np.linalg.norm(reference.probe_displacements, axis=1).max()
        for r in (*REFINEMENTS, *([FURTHER[key]] if key in FURTHER else [])):
            spacing = default / r
            result = run_deform(with_discretization(scenario, spacing=spacing))
            per_probe.append(np.linalg.norm(result.probe_displacements - reference.probe_displacements, axis=1) / scale)
            error = float(per_probe[-1].max())  # common.max_probe_error
            if r in REFINEMENTS:
                errors.append(error)
                spacings.append(spacing)
            print(f"  spacing {spacing:g} mm: {result.model.n_particles} particles, error {100 * error:.3f} %, "
                  f"{result.wall_seconds:.2f} s", flush=True)
            csv_rows.append([key, spacing, result.model.n_particles, len(result.model.quadrature_weights),
                             error, result.wall_seconds, *result.probe_displacements.ravel()])
        if key in FURTHER:
            notes.append(f"{raw['name']}: every probe's error ({', '.join(f'({x:g}, {y:g})' for x, y in raw['probes'])}) "
                         f"at default/{REFINEMENTS[-1]}: "
                         + ", ".join(f"{100 * e:.4f}" for e in per_probe[-2]) + f" %; at default/{FURTHER[key]} "
                         f"({spacing:g} mm, {result.model.n_particles} particles): "
                         + ", ".join(f"{100 * e:.4f}" for e in per_probe[-1]) + " %.")
            print(f"  {notes[-1]}", flush=True)
        # the same default run without grading toward the corners (and load-segment ends)
        plain = run_deform(with_discretization(scenario, segment_end_levels=0))
        plain_error = common.max_probe_error(plain.probe_displacements, reference.probe_displacements)
        notes.append(f"{raw['name']}: at the default spacing without the grading toward re-entrant corners "
                     f"and segment ends (segment_end_levels 0): {plain.model.n_particles} particles, "
                     f"error {100 * plain_error:.3f} % (graded: {100 * errors[0]:.3f} %).")
        print(f"  {notes[-1]}", flush=True)
        rates = [math.log(errors[k] / errors[k + 1]) / math.log(spacings[k] / spacings[k + 1])
                 for k in range(len(errors) - 1)]
        rows.append([raw["name"], f"{default:g}", *(f"{100 * e:.3f} %" for e in errors),
                     *(f"{q:.2f}" for q in rates), f"{reference.dofs} dofs, change {100 * reference_change:.3f} %"])
    header = ["scene", "default spacing (mm)", *(f"error at default/{r}" for r in REFINEMENTS),
              *(f"rate {REFINEMENTS[k]}->{REFINEMENTS[k + 1]}" for k in range(len(REFINEMENTS) - 1)),
              f"skfem reference (Q2 graded or P2 where curved, h {args.reference_h:g} mm; change from h "
              f"{2 * args.reference_h:g})"]
    table = common.markdown_table(header, rows)
    common.write_csv(common.results_path("deform_shapes.csv"),
                     ["scene", "spacing_mm", "particles", "quadrature_points", "max_probe_error_rel",
                      "wall_seconds", "probe_displacements"], csv_rows)
    text = "\n".join([
        "# Tissue shapes against scikit-fem",
        "",
        "`stitchplan deform` (default discretization: gauss integration, dilation 2, particles "
        "fitted to the shape, cut cells split 3 times, visibility criterion) against a fine "
        "scikit-fem solution of the same plane-strain St. Venant-Kirchhoff problem (Q2 "
        "quadrilaterals, elements graded toward every corner; on the circle scenes and the "
        "notched outline P2 triangles whose edges follow the sloped and curved edges (the "
        "model's 96-gons), graded toward the re-entrant corners; each element's material that "
        "of its centre). "
        "The CSV's rows of spacing 0 hold the reference's probe displacements. Error = max over the probes of |u - u_ref| / max |u_ref|; rate = observed "
        "order log(e1/e2)/log(h1/h2). Scenes in benchmarks/deform_shapes.py (SCENES).",
        "",
        table,
        "",
        *(f"- {note}" for note in notes),
        "",
        f"Machine: {common.machine_note()}.",
        "",
    ])
    common.results_path("deform_shapes.md").write_text(text)
    print(table)


if __name__ == "__main__":
    main()
