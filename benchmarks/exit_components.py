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
went in) after the exit; and at each level the free edge around the entry: its least stretch
and how far its tangent turns (edge_polyline, entry_edge), on sh12_100x100 and the 3 mm slab also with the
tissue as linear triangles on the same particles (benchmarks/needle_fem_reference.py), and
drawn for four scenes (edge_chart).
A change that halves with each halving of the spacing converges at rate 1; the rate here is
log2 of the ratio of consecutive changes.

Writes benchmarks/results/exit_components.{csv,md,png} and prints the table. About 13 minutes (the
h/8 runs and soft_t2.5's failing h/4 take most of it).
Run from the repository root:  python benchmarks/exit_components.py
"""

from __future__ import annotations

import os

# single-threaded BLAS, as the `stitchplan` command sets it
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import contextlib  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

import _common as common  # noqa: E402
import needle_coupling  # noqa: E402
from needle_fem_reference import finite_element_model  # noqa: E402
from stitchplan.config import with_discretization  # noqa: E402
from stitchplan.errors import InsertionFailure  # noqa: E402
from stitchplan.needle.prepared_tissue import PreparedTissue  # noqa: E402
from stitchplan.needle.insertion import run_insertion  # noqa: E402

SCENES = ("sh12_100x100", "sh12_100x100_mid", "soft_t3", "soft_t2.5", needle_coupling.THESIS_FIT[3],
          "thesis/table51_100x30")
FACTORS = (2.0, 1.0, 0.5, 0.25, 0.125)
LEVELS = ("2h", "h", "h/2", "h/4", "h/8")
TRACK_STEPS = (10, 20, 30)
EDGE_SPAN = 3.0  # mm of the entry's edge on each side of the entry whose deformed shape is read
EDGE_POINTS = 601
TRIANGLE_SCENES = ("sh12_100x100", "soft_t3")  # the free edge also with the tissue as linear triangles
# the edge drawn (exit_components.png)
CHART_SCENES = ("sh12_100x100", "soft_t3", needle_coupling.THESIS_FIT[3], "thesis/table51_100x30")
COUPLING = needle_coupling.SHIPPED_COUPLING  # the scene's file as it is


def runs(scene: str, triangles: bool = False) -> tuple[list, str]:
    """The scene's unplanned insertion at each of FACTORS x its spacing, up to the first
    level that fails (its failure returned); `triangles`: the tissue as linear triangles on the
    same particles (needle_fem_reference.finite_element_model)."""
    base = needle_coupling.scene(scene, COUPLING)
    name = f"{scene} (triangles)" if triangles else scene
    results = []
    for factor in FACTORS:
        scenario = with_discretization(base, spacing=base.discretization.spacing * factor)
        try:
            tissue = PreparedTissue(scenario, finite_element_model(scenario)) if triangles else None
            result = run_insertion(scenario, tissue=tissue)
        except InsertionFailure as failure:
            print(f"{name} at {factor:g} h: {failure}", flush=True)
            return results, " ".join(str(failure).split())[:120]
        print(f"{name} at {factor:g} h: {result.model.n_particles} particles, exit error "
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
    return result.model.field_at(result.geometry.entry[None], result.coefficients[-1])[0][0]


PARTS = (("exit_error", "exit error"), ("achieved_exit_def", "achieved exit (spatial)"),
         ("desired_exit_def", "desired exit's spatial position"), ("achieved_exit", "achieved exit (material)"),
         ("track", f"track's tip point, steps {', '.join(map(str, TRACK_STEPS))} (material, largest)"),
         ("entry", "entry point's displacement at the exit"))


def rate(first: float | None, second: float | None) -> float | str:
    """log2 of the ratio of two consecutive changes (nested levels, ratio 2)."""
    if not first or not second:
        return "—"
    return math.log2(abs(first) / abs(second))


def edge_polyline(result) -> tuple[np.ndarray, np.ndarray] | None:
    """The free edge through the entry, EDGE_SPAN mm on each side of it (clipped to the
    rectangle): its reference points and where they are once the tip has left the tissue,
    (EDGE_POINTS, 2) each. None where the entry is not on a side of the rectangle."""
    width, height = result.scenario.tissue.bounding_size
    entry = np.asarray(result.geometry.entry, dtype=float)
    along = np.linspace(-EDGE_SPAN, EDGE_SPAN, EDGE_POINTS)
    if min(abs(entry[0]), abs(entry[0] - width)) < 1e-9 * width:
        points = np.column_stack([np.full_like(along, entry[0]), np.clip(entry[1] + along, 0.0, height)])
    elif min(abs(entry[1]), abs(entry[1] - height)) < 1e-9 * height:
        points = np.column_stack([np.clip(entry[0] + along, 0.0, width), np.full_like(along, entry[1])])
    else:
        return None
    return points, points + result.model.field_at(points, result.coefficients[-1])[0]


def entry_edge(edge: tuple[np.ndarray, np.ndarray]) -> tuple[float, float]:
    """An edge_polyline's least stretch (deformed over reference length) and how far its
    tangent turns (degrees: 0 straight, 180 folded back on itself)."""
    points, deformed = edge
    pieces, lengths = np.diff(deformed, axis=0), np.linalg.norm(np.diff(points, axis=0), axis=1)
    kept = lengths > 0.0  # the clipped ends repeat a point
    stretch = np.linalg.norm(pieces[kept], axis=1) / lengths[kept]
    angle = np.degrees(np.unwrap(np.arctan2(pieces[kept, 1], pieces[kept, 0])))
    return float(stretch.min()), float(angle.max() - angle.min())


def edge_run(scenario, context=None) -> dict:
    """One unplanned insertion of `scenario` (inside `context`, e.g. a patch of the model): its
    particles, exit error and the entry's free edge after the exit (least stretch, turn of the
    tangent), or the InsertionFailure, and the seconds it took, as CSV strings."""
    start = time.perf_counter()
    try:
        with context or contextlib.nullcontext():
            result = run_insertion(scenario)
        stretch, turn = entry_edge(edge_polyline(result))
        fields = {"particles": result.model.n_particles, "exit_error_mm": f"{result.exit_error_mm:.6f}",
                  "edge_least_stretch": f"{stretch:.4f}", "edge_turn_deg": f"{turn:.2f}", "failure": ""}
    except InsertionFailure as failure:
        fields = {"particles": "", "exit_error_mm": "", "edge_least_stretch": "", "edge_turn_deg": "",
                  "failure": str(failure)[:120].replace(",", ";")}
    fields["seconds"] = f"{time.perf_counter() - start:.1f}"
    return fields


def edge_chart(edges: dict, path) -> None:
    """One panel per scene: the free edge around the entry after the exit at each level (the
    track's material pulled along the needle draws it into a cusp), the needle's circle about
    the last centre dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, len(edges), figsize=(4.6 * len(edges), 4.8), squeeze=False)
    for axis, (scene, levels) in zip(axes.ravel(), edges.items()):
        near = []
        for index, (level, deformed, center, radius) in enumerate(levels):
            color = plt.cm.viridis(index / max(len(LEVELS) - 1, 1))
            axis.plot(deformed[:, 0], deformed[:, 1], color=color, lw=1.2, label=level)
            near.append(deformed)
        level, deformed, center, radius = levels[-1]
        angles = np.linspace(0.0, 2.0 * np.pi, 4000)
        axis.plot(center[0] + radius * np.cos(angles), center[1] + radius * np.sin(angles), "k--", lw=0.7,
                  label="needle (last centre)")
        stacked = np.vstack(near)
        low, high = stacked.min(axis=0), stacked.max(axis=0)
        middle, half = 0.5 * (low + high), 0.55 * max(high - low)
        axis.set_xlim(middle[0] - half, middle[0] + half)
        axis.set_ylim(middle[1] - half, middle[1] + half)
        axis.set_aspect("equal")
        axis.set_title(f"{scene}: the entry's edge after the exit", fontsize=9)
        axis.set_xlabel("x (mm)", fontsize=8)
        axis.set_ylabel("y (mm)", fontsize=8)
    common.panels_legend(figure, axes, ncol=len(LEVELS) + 1)
    figure.suptitle(f"The free edge within {EDGE_SPAN:g} mm of the needle's entry once the tip has left, at particle "
                    "spacings 2h to h/8 (h: the scene file's spacing; RK model)")
    common.save_figure(figure, path, (0, 0.1, 1, 0.95))


def edge_rows(scene: str, polylines: list, kind: str) -> list[list]:
    """entry_edge of each level's edge_polyline as two rows of the table."""
    if not polylines or any(polyline is None for polyline in polylines):
        return []
    edges = [entry_edge(polyline) for polyline in polylines]
    blank = [""] * (2 * (len(FACTORS) - 1) - 2)
    return [[scene, f"free edge within {EDGE_SPAN:g} mm of the entry{kind}, {label}, at "
             f"{', '.join(LEVELS[:len(edges)])}", " / ".join(f"{edge[index]:.3g}" for edge in edges), *blank]
            for index, label in ((0, "least stretch"), (1, "turn of the tangent (deg)"))]


def main() -> None:
    rows, edges = [], {}
    pairs = len(FACTORS) - 1
    for scene in SCENES:
        results, failure = runs(scene)
        polylines = [edge_polyline(result) for result in results]
        if scene in CHART_SCENES:
            edges[scene] = [(level, polyline[1], result.steps[-1].center, result.geometry.radius)
                            for level, polyline, result in zip(LEVELS, polylines, results)]
        moved = [changes(a, b) for a, b in zip(results, results[1:])]
        for key, label in PARTS:
            values = [m[key] for m in moved] + [None] * (pairs - len(moved))
            rates = [rate(a, b) for a, b in zip(values, values[1:])]
            rows.append([scene, label, *("—" if v is None else v for v in values), *rates])
        levels = " / ".join(f"{r.exit_error_mm:.4f}" for r in results)
        if failure:
            levels += f" / {LEVELS[len(results)]}: {failure}"
        rows.append([scene, f"exit error (mm) at {', '.join(LEVELS)}", levels, *[""] * (2 * pairs - 2)])
        rows += edge_rows(scene, polylines, "")
        if scene in TRIANGLE_SCENES:
            rows += edge_rows(scene, [edge_polyline(result) for result in runs(scene, triangles=True)[0]],
                              ", linear triangles")
    header = ["scene", "part", *(f"{a} -> {b} (mm)" for a, b in zip(LEVELS, LEVELS[1:])),
              *(f"rate ({a}, {b}, {c})" for a, b, c in zip(LEVELS, LEVELS[1:], LEVELS[2:]))]
    common.write_csv(common.results_path("exit_components.csv"), header, rows)
    lines = [
        "# Which part of the exit error moves under refinement\n",
        f"Generated by `python benchmarks/exit_components.py` ({common.machine_note()}). `simulate` "
        "(each scene's file as shipped) at nested spacings 2h, h, h/2, h/4 and h/8, h the file's "
        "spacing; soft_t3 and soft_t2.5 are configs/sh12_100x100.yaml as neo-Hookean slabs 3 and 2.5 mm "
        "thick (benchmarks/needle_coupling.py), thesis/table51_100x30@f28e417 the thesis's softest block "
        "as configs/thesis read it until it was read for a converged model (2.76 mm thick), "
        "thesis/table51_100x30 that block as read since (5 mm thick). Exit error: its signed change between levels; the other "
        "parts: how far they moved (mm). Rate: log2 of the ratio of consecutive changes (1: the change "
        "halves with the spacing). The free edge through the needle's entry, once the tip has left: its "
        "least stretch within 3 mm of the entry and how far its tangent turns there (0 degrees: straight, "
        "180: folded back on itself): the track's material slides along the needle and draws the edge into "
        "a cusp at the entry, which the model (the needle a line the tissue is held to, no contact) "
        "sharpens at every level (exit_components.png); on "
        "sh12_100x100 and soft_t3 also with the tissue as linear triangles on the same particles "
        "(benchmarks/needle_fem_reference.py).\n",
        common.markdown_table(header, rows),
        "",
    ]
    common.write_report("exit_components.md", lines)
    edge_chart(edges, common.results_path("exit_components.png"))


if __name__ == "__main__":
    common.command_line(__doc__)
    main()
