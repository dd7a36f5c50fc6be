"""The shipped needle scenes on shaped tissue against linear finite elements.

benchmarks/needle_fem_reference.py checks the rectangle scenes' exit errors on an
independent tissue discretization: linear triangles (P1) on the same particles, everything
else the package's (needle coupling, ramp, tip tracking, Newton). Here the same for the
scenes whose tissue is not a plain rectangle: a stitch across a wound (wound_closure), a
stitch next to a circular hole (hole_near_stitch) and a layered skin (skin_layered). The
triangles are the Delaunay triangulation of the particles the RK model places for the shape
(boundary particles on every edge and corner, on both walls of the wound), without the
triangles whose centre lies outside the tissue (in the wound's gap, in the hole): so no
triangle couples the two walls of the wound, as the RK model's visibility criterion keeps
its shape functions from reaching across; each triangle's material that of the region
holding its centre. A point in no kept triangle (past an edge: the exit's bracket, a tip
crossing the gap) takes its nearest kept triangle, extended. Where the tissue's edge is
curved (the hole) the triangles' chords between boundary particles cut it off, by less at
every refinement.

Per scene: the unplanned exit error at the file's spacing h and at h/2 and h/4 (nested
levels), RK and FE (the chart: both against the spacing at the needle), and rk / fe - 1 at
each level.

Writes benchmarks/results/needle_fem_shapes.{csv,md,png}. About a minute on 2 cores.
Run from the repository root:  python benchmarks/needle_fem_shapes.py  (--report: only the
tables from the CSV)
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import logging  # noqa: E402
import time  # noqa: E402

import _common as common  # noqa: E402
import numpy as np  # noqa: E402
from needle_fem_reference import (LinearTriangles, chart, compression, finite_element_model,  # noqa: E402
                                  closing_lines, ladder_figures, ladders, rk_over_fe, run_ladders)
from scipy.spatial import cKDTree  # noqa: E402

from stitchplan.config.scenario import load_scenario, with_discretization  # noqa: E402
from stitchplan.errors import InsertionFailure  # noqa: E402
from stitchplan.geometry.polygons import signed_area  # noqa: E402
from stitchplan.needle.insertion import run_insertion  # noqa: E402
from stitchplan.needle.prepared_tissue import PreparedTissue  # noqa: E402

SCENES = ("wound_closure", "hole_near_stitch", "skin_layered")
FACTORS = (1.0, 0.5, 0.25)
FIELDS = ("scene", "model", "factor", "needle_spacing_mm", "particles", "exit_error_mm", "min_det_f",
          "min_det_f_from_entry_mm", "fe_area_rel", "seconds", "failure")


class ShapedTriangles(LinearTriangles):
    """LinearTriangles on a shaped tissue: only the `kept` triangles (their centre inside the
    tissue) carry the tissue."""

    def located(self, points: np.ndarray) -> np.ndarray:
        simplex = self.triangulation.find_simplex(points)
        off = (simplex < 0) | ~self.kept[np.maximum(simplex, 0)]
        if off.any():  # past an edge or in the gap: the nearest kept triangle, extended
            kept = np.flatnonzero(self.kept)
            if getattr(self, "_kept_centres", None) is None:
                self._kept_centres = cKDTree(self.triangulation.points[self.triangulation.simplices[kept]].mean(axis=1))
            simplex[off] = kept[self._kept_centres.query(points[off])[1]]
        return simplex


def shaped_model(scenario) -> tuple[ShapedTriangles, float]:
    """P1 triangles on the particles stitchplan places for `scenario`'s shape (the
    triangulation of needle_fem_reference.finite_element_model, which checks that it tiles the
    bounding box: a tissue whose corners are its box's, as the three scenes', without the
    triangles whose centre lies outside the tissue), and their area over the tissue's, less 1."""
    model = finite_element_model(scenario, ShapedTriangles, scenario.tissue.domain.contains)
    area = float(np.sum(model.quadrature_weights)) / scenario.tissue.thickness
    return model, area / domain_area(scenario.tissue.domain) - 1.0


def domain_area(domain) -> float:
    """The tissue's area: its outline's less its holes', a rectangle's sides' product."""
    if not hasattr(domain, "outline"):
        return float(np.prod(domain.size))
    return abs(signed_area(domain.outline)) - sum(abs(signed_area(hole)) for hole in domain.holes)


def run(job: tuple[str, str, float]) -> dict:
    scene, model, factor = job
    base = load_scenario(common.REPO_ROOT / "configs" / f"{scene}.yaml")
    scenario = with_discretization(base, spacing=base.discretization.spacing * factor)
    start = time.perf_counter()
    row = {"scene": scene, "model": model, "factor": factor, "needle_spacing_mm": scenario.discretization.needle_spacing,
           "particles": 0, "exit_error_mm": float("nan"), "min_det_f": float("nan"),
           "min_det_f_from_entry_mm": float("nan"), "fe_area_rel": float("nan"), "failure": ""}
    try:
        triangles = None
        if model == "fe":
            triangles, row["fe_area_rel"] = shaped_model(scenario)
        result = run_insertion(scenario, tissue=PreparedTissue(scenario, triangles))
        figures = compression(result)
        row.update(particles=result.model.n_particles, exit_error_mm=result.exit_error_mm,
                   min_det_f=figures["min_det_f"], min_det_f_from_entry_mm=figures["min_det_f_from_entry_mm"])
    except InsertionFailure as failure:
        row["failure"] = " ".join(str(failure).split())
    row["seconds"] = time.perf_counter() - start
    print(scene, model, f"h x {factor:g}", f"{row['exit_error_mm']:.6f}", row["failure"], flush=True)
    return row


def markdown(rows: list[dict]) -> str:
    groups = ladders(rows)
    lines = ["# Shaped tissue's needle scenes on linear finite elements", "",
             "`python benchmarks/needle_fem_shapes.py` (results/needle_fem_shapes.csv holds every run).",
             "Unplanned exit error (mm) at the scene file's spacing h, h/2 and h/4 (nested levels), with the",
             "tissue as stitchplan's RK particles (`rk`) or as linear triangles on the same particles, those",
             "whose centre lies outside the tissue left out (`fe`); the needle coupling, ramp, tip tracking",
             "and Newton solver the package's in both. Differences d between successive levels; rate",
             "log2(d_1 / d_2); FE area: the kept triangles' area over the tissue's, less 1.", "",
             "| scene | model | particles at h | h | h/2 | h/4 | h to h/2 | d (mm) | rate | FE area at h |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for (scene, model), group in groups.items():
        figures = ladder_figures(group)
        cells = [("stops" if row["failure"] else f"{float(row['exit_error_mm']):.4f}") for row in group]
        area = float(group[0]["fe_area_rel"])
        lines.append(f"| {scene} | {model} | {group[0]['particles']} | " + " | ".join(cells)
                     + f" | {figures['change']:+.2f} % | " + " ".join(f"{d:+.4f}" for d in figures["differences"])
                     + " | " + (" ".join("-" if np.isnan(r) else f"{r:.2f}" for r in figures["rates"]) or "-")
                     + f" | {'-' if np.isnan(area) else f'{100 * area:+.3f} %'} |")
    lines += ["", "RK against FE at each level (rk / fe - 1):", "", "| scene | h | h/2 | h/4 |", "|---|---|---|---|"]
    for scene in dict.fromkeys(row["scene"] for row in rows):
        rk, fe = groups.get((scene, "rk")), groups.get((scene, "fe"))
        if rk is None or fe is None:
            continue
        lines.append(f"| {scene} | " + " | ".join(rk_over_fe(rk, fe, FACTORS)) + " |")
    return "\n".join(lines + closing_lines(rows))


def main() -> None:
    logging.disable(logging.WARNING)
    csv_path = common.results_path("needle_fem_shapes.csv")
    if "--report" in common.command_line(__doc__, ("--report",)):
        rows = common.csv_rows(csv_path)
    else:
        rows = run_ladders([(scene, model, factor) for scene in SCENES for model in ("rk", "fe") for factor in FACTORS],
                           run, csv_path, FIELDS)
    common.publish("needle_fem_shapes", markdown(rows), chart, rows)


if __name__ == "__main__":
    main()
