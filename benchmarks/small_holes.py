"""Round holes no wider than the kernel's reach: `stitchplan deform` on a 40 x 20 mm plate
pushed down and sideways on its top edge, clamped at its bottom, with one round hole of
radius 0.5, 1, 1.5 or 2.5 mm at its centre, at spacings 3, 2, 1.5, 1 and 0.5 mm (supports
6 to 1 mm: pairs of particles and points reach across the smaller holes), against scikit-fem
(P2 triangles of side 0.125 mm following the hole's 96-gon, solve_skfem_curved in
benchmarks/skfem_reference.py; its change from side 0.25 mm in the table). Probes: eight
0.002 mm outside the hole's wall, the top edge's middle, two points beside the hole and two
1 mm from it. Error = max over the probes of |u - u_ref| / max |u_ref|, and over the wall's
eight alone.

The visibility criterion weighs a pair whose segment crosses a round hole by the way round it
(tissue.shape_functions.Visibility); BASELINE blocked such pairs when at least as long as the
hole is wide and kept the shorter ones whole. The particles are graded toward a round hole the
default spacing (1 mm here) does not resolve, to leaves of at most inradius / 2 at its wall
(tissue.shapes.hole_zones, discretization.hole_resolution 2); "way round, ungraded" is the
same code with hole_resolution 0, as the code was before the grading. All three are run
(BASELINE's code extracted with git archive, each level in a fresh process of its own code),
and charted against the spacing and against the particles they cost.

A second table asks which holes to weigh so: the same plate with a 4 x 4 mm square hole (not
round: corners) and with a 10 x 1.5 mm elliptic one (200 vertices; round), each with the pairs
through it blocked (every convex hole taken as not round by the visibility criterion, in the
worker) and weighed by the way round it (every convex hole taken as round); "(as shipped)"
marks what the code does. Both are graded as shipped (the ellipse toward its wall, the square
toward its corners).

`--holes H ...` runs only those holes (0.5 1.0 1.5 2.5 square ellipse), replacing their rows in
results/small_holes.csv; `--report` only rewrites the tables and chart from the CSV.

Writes benchmarks/results/small_holes.{csv,md,png} and prints the tables. About 50 minutes
(the references). Run from the repository root:  python benchmarks/small_holes.py
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import json  # noqa: E402
import sys  # noqa: E402

import _common as common  # noqa: E402
import numpy as np  # noqa: E402

BASELINE = "144b415"  # round holes blocking the pairs at least as long as their width
RADII = (0.5, 1.0, 1.5, 2.5)  # mm
CONVEX = {  # holes that are not round: (name, vertices)
    "square": ("4 x 4 mm square", [[18.0, 8.0], [22.0, 8.0], [22.0, 12.0], [18.0, 12.0]]),
    "ellipse": ("10 x 1.5 mm ellipse",
                np.column_stack([20.0 + 5.0 * np.cos(2.0 * np.pi * np.arange(200) / 200),
                                 10.0 + 0.75 * np.sin(2.0 * np.pi * np.arange(200) / 200)]).round(6).tolist()),
}
SPACINGS = (3.0, 2.0, 1.5, 1.0, 0.5)  # mm
REFERENCE_H = 0.125  # mm, P2 triangle side
SOFT = {"model": "saint-venant-kirchhoff", "lame_lambda": 0.189151, "lame_mu": 0.147688}
CENTER = (20.0, 10.0)
WALL_PROBES = 8


def scene(hole: str, spacing: float) -> dict:
    """The plate's scenario (raw) at `spacing` with a round hole of radius `hole` (mm) or one
    of CONVEX; its first WALL_PROBES probes 0.002 mm outside the hole's wall (radially from its
    centre)."""
    if hole in CONVEX:
        loop = np.array(CONVEX[hole][1])
        # the square's probes off its corners, the ellipse's on its tips among them
        angle = 2.0 * np.pi * np.arange(WALL_PROBES) / WALL_PROBES + (np.pi / WALL_PROBES if hole == "square" else 0.0)
        direction = np.column_stack([np.cos(angle), np.sin(angle)])
        # the wall where each direction leaves the hole: the largest t with CENTER + t d inside every edge
        along = np.roll(loop, -1, axis=0) - loop
        outward = np.column_stack([along[:, 1], -along[:, 0]])
        limit = np.einsum("kd,kd->k", outward, loop - np.array(CENTER))
        rate = direction @ outward.T
        reach = np.min(np.where(rate > 0, limit / np.maximum(rate, 1e-300), np.inf), axis=1)
        wall = np.array(CENTER) + (reach + 0.002)[:, None] * direction
        holes = [{"polygon": loop.tolist()}]
        size = float(np.ptp(loop[:, 1])) / 2.0
    else:
        radius = float(hole)
        angle = 2.0 * np.pi * np.arange(WALL_PROBES) / WALL_PROBES
        wall = np.array(CENTER) + (radius + 0.002) * np.column_stack([np.cos(angle), np.sin(angle)])
        holes = [{"circle": {"center": list(CENTER), "radius": radius}}]
        size = radius
    others = [[20.0, 20.0], [10.0, 10.0], [30.0, 10.0], [20.0, 11.0 + size], [20.0, 9.0 - size]]
    return {"tissue": {"size": [40.0, 20.0], "thickness": 10.0, "material": SOFT, "clamped": ["bottom"],
                       "holes": holes},
            "discretization": {"spacing": spacing},
            "loads": [{"segment": [[0.0, 20.0], [40.0, 20.0]], "force": [0.3, -1.5]}],
            "probes": [*wall.round(6).tolist(), *others]}


def worker(hole: str, spacing: str, option: str = "") -> dict:
    """The model's probe displacements on one plate (`--worker`), with the code on sys.path;
    `option`: "weighed" or "blocked" through every convex hole (take_convex_holes), or
    "ungraded" (hole_resolution 0)."""
    from stitchplan.config.scenario import parse_scenario
    from stitchplan.tissue.deform import run_deform

    raw = scene(hole, float(spacing))
    if option in ("weighed", "blocked"):
        take_convex_holes(as_round=option == "weighed")
    elif option == "ungraded":
        raw["discretization"]["hole_resolution"] = 0
    try:
        result = run_deform(parse_scenario(raw))
    except Exception as failure:  # noqa: BLE001 - a level the code refuses is a row of the table
        return {"failure": str(failure).splitlines()[0][:120]}
    return {"particles": result.model.n_particles, "probes": result.probe_displacements.tolist()}


def take_convex_holes(as_round: bool) -> None:
    """Make the visibility criterion take every convex hole as round (the pairs through it
    weighed by the way round it) or none (the pairs blocked): is_round, as
    tissue.shape_functions calls it, replaced (a worker's code only)."""
    from stitchplan.geometry.polygons import turns
    from stitchplan.tissue import shape_functions

    shape_functions.is_round = lambda loop: as_round and bool(np.all(turns(loop) >= -1e-9))


def errors(probes: np.ndarray, reference: np.ndarray) -> tuple[float, float]:
    """The max probe error over all probes and over the wall's, relative to the largest reference displacement."""
    error = np.linalg.norm(probes - reference, axis=1) / np.linalg.norm(reference, axis=1).max()
    return float(error.max()), float(error[:WALL_PROBES].max())


STYLES = {"before": ("--", "x"), "ungraded": (":", "s"), "now": ("-", "o")}


def chart(rows: list[dict], path) -> None:
    """Max probe error against the spacing (left) and against the particles (right): each
    circle's three codes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    figure, panels = plt.subplots(1, 2, figsize=(11.0, 4.8))
    for index, radius in enumerate(RADII):
        for code, (style, marker) in STYLES.items():
            chosen = [row for row in rows if row["hole"] == str(radius) and row["code"] == code and row["error"] != ""]
            for axes, key in zip(panels, ("spacing_mm", "particles")):
                if chosen:
                    axes.loglog([float(row[key]) for row in chosen], [100 * float(row["error"]) for row in chosen],
                                style, marker=marker, color=f"C{index}", markersize=4)
    panels[0].set_xticks(SPACINGS, [f"{spacing:g}" for spacing in SPACINGS])
    panels[0].minorticks_off()
    panels[0].set_xlabel("particle spacing (mm)")
    panels[1].set_xlabel("particles")
    for axes in panels:
        axes.set_ylabel("max probe error vs scikit-fem (% of largest displacement)")
        axes.grid(True, which="both", alpha=0.3)
    holes = [Line2D([], [], color=f"C{index}", label=f"{2 * radius:g} mm circle") for index, radius in enumerate(RADII)]
    codes = [Line2D([], [], color="0.3", linestyle=style, marker=marker, label=CODES[code])
             for code, (style, marker) in STYLES.items()]
    panels[0].legend(handles=holes, fontsize=8)
    panels[1].legend(handles=codes, fontsize=8)
    figure.suptitle("Plate with a small round hole: deform against scikit-fem, by spacing and by cost")
    common.save_figure(figure, path, (0, 0, 1, 0.95))


def reference(hole: str) -> tuple[np.ndarray, float]:
    """scikit-fem's probe displacements on the plate with `hole`, and their change from side
    2 x REFERENCE_H (relative to the largest)."""
    from skfem_reference import solve_skfem_curved
    from stitchplan.config.scenario import parse_scenario

    scenario = parse_scenario(scene(hole, 1.0))
    print(f"hole {hole}: scikit-fem reference, side {REFERENCE_H:g} mm ...", flush=True)
    fine = solve_skfem_curved(scenario, REFERENCE_H, grading=0).probe_displacements
    coarser = solve_skfem_curved(scenario, 2 * REFERENCE_H, grading=0).probe_displacements
    return fine, errors(coarser, fine)[0]


HOLES = (*(str(radius) for radius in RADII), *CONVEX)
# the codes run on each hole: round ones before (BASELINE) and now, the others both ways
CODES = {"before": "blocked past its width", "ungraded": "way round, ungraded", "now": "way round, graded",
         "blocked": "blocked", "weighed": "way round"}


def run(hole: str, baseline) -> list[dict]:
    """Every level of `hole`'s codes: rows of the CSV."""
    fine, change = reference(hole)
    rows = []
    codes = (("blocked", common.REPO_ROOT, ("blocked",)), ("weighed", common.REPO_ROOT, ("weighed",))) \
        if hole in CONVEX else (("before", baseline, ()), ("ungraded", common.REPO_ROOT, ("ungraded",)),
                                ("now", common.REPO_ROOT, ()))
    for code, source, options in codes:
        for spacing in SPACINGS:
            record = common.worker_record(__file__, source, hole, str(spacing), *options)
            error, wall = errors(np.array(record["probes"]), fine) if "probes" in record else ("", "")
            rows.append({"hole": hole, "spacing_mm": spacing, "code": code, "particles": record.get("particles", ""),
                         "error": error, "wall_error": wall, "failure": record.get("failure", ""),
                         "reference_change": change})
            print(f"  {code} spacing {spacing:g} mm: {cell(rows[-1])}", flush=True)
    return rows


def cell(row: dict) -> str:
    if row["failure"]:
        return row["failure"]
    return f"{100 * float(row['error']):.2f} % ({100 * float(row['wall_error']):.2f} %), {row['particles']}"


def report(rows: list[dict]) -> None:
    from stitchplan.geometry.polygons import is_round

    header = ["hole", "pairs through it", *(f"spacing {spacing:g} mm" for spacing in SPACINGS),
              f"reference change (side {2 * REFERENCE_H:g} to {REFERENCE_H:g} mm)"]
    tables = []
    for holes in ([str(radius) for radius in RADII], list(CONVEX)):
        table = []
        for hole in holes:
            shipped = "weighed" if hole in CONVEX and is_round(np.array(CONVEX[hole][1])) else "blocked"
            for code in ("before", "ungraded", "now") if hole not in CONVEX else ("blocked", "weighed"):
                cells = {float(row["spacing_mm"]): row for row in rows if row["hole"] == hole and row["code"] == code}
                if not cells:
                    continue
                name = CONVEX[hole][0] if hole in CONVEX else f"{2 * float(hole):g} mm circle"
                label = CODES[code] + (" (as shipped)" if hole in CONVEX and code == shipped else "")
                table.append([name, label, *(cell(cells[spacing]) if spacing in cells else "not run"
                                             for spacing in SPACINGS),
                              f"{100 * float(next(iter(cells.values()))['reference_change']):.3f} %"])
        tables.append(common.markdown_table(header, table))
    common.results_path("small_holes.md").write_text("\n".join([
        "# Small holes against scikit-fem",
        "",
        "`stitchplan deform` on a 40 x 20 mm plate with a hole at its centre (clamped bottom, "
        "force (0.3, -1.5) N/mm on the top edge, St. Venant-Kirchhoff), against scikit-fem P2 triangles "
        f"of side {REFERENCE_H:g} mm following the hole's edges (a circle's 96-gon). Each cell: max probe "
        "error over all probes (over the eight 0.002 mm outside the hole's wall), % of the largest "
        "displacement, and the model's particles. Scenes in benchmarks/small_holes.py.",
        "",
        f"Round holes: 'blocked past its width' is {BASELINE}, a pair through the hole blocked when at "
        "least as long as the hole is wide and kept whole when shorter; 'way round', the pair's kernel "
        "taken at its offset stretched by the way round the hole over the straight length "
        "(tissue.shape_functions.Visibility); 'ungraded', the particles at the spacing round the hole "
        "(hole_resolution 0); 'graded', toward the hole to leaves of at most inradius / 2 at its wall at the "
        "default spacing (1 mm), as many levels below any other (tissue.shapes.hole_zones; as shipped).",
        "",
        tables[0],
        "",
        "A hole with corners and a thin round one, the pairs through them blocked and weighed by the way "
        "round them (in the worker, every convex hole taken as not round or as round by the visibility "
        "criterion; both graded as shipped: the ellipse toward its wall, the square toward its corners):",
        "",
        tables[1],
        "",
        f"Machine: {common.machine_note()}.",
        "",
    ]))
    chart(rows, common.results_path("small_holes.png"))
    print("\n\n".join(tables))


def main() -> None:
    flags = sys.argv[1:]
    path = common.results_path("small_holes.csv")
    rows = common.csv_rows(path) if path.exists() else []
    if "--report" not in flags:
        chosen = flags[flags.index("--holes") + 1:] if "--holes" in flags else list(HOLES)
        unknown = [hole for hole in chosen if hole not in HOLES]
        if unknown:
            raise SystemExit(f"small_holes.py: --holes got {' '.join(unknown)}, expected some of {' '.join(HOLES)}")
        rows = [row for row in rows if row["hole"] not in chosen]
        with common.against(BASELINE) as (baseline, _):
            for hole in chosen:
                rows.extend(run(hole, baseline))
        rows.sort(key=lambda row: HOLES.index(row["hole"]))
        common.write_csv(path, list(rows[0]), [list(row.values()) for row in rows])
    report(rows)


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        print(json.dumps(worker(*sys.argv[2:])))
    else:
        if "-h" in sys.argv or "--help" in sys.argv:
            common.command_line(__doc__)
        main()
