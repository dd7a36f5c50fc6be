"""A small round hole by the needle's track: the particles graded toward it no finer than the
needle's spacing (as shipped, tissue.shapes.hole_zones) or to its own size. `stitchplan
simulate` on configs/hole_near_stitch.yaml's block (60 x 30 mm, the SH 1/2 needle entering at
(30, 30), clockwise; its default spacing 3 mm, 1.5 mm at the needle) with its 5 mm hole
replaced by one of HOLES, 0.3-2 mm from the track; unplanned exit error at spacings h, h/2, h/4
and h/8, each level's offset from its own h/8, and the particles.

"to its size" is the code as shipped with the needle's floor taken out of hole_zones in the
worker (discretization.needle_spacing hidden from it), as the grading was before the floor.

Writes benchmarks/results/hole_near_needle.{csv,md} and prints the table. About 15 minutes.
Run from the repository root:  python benchmarks/hole_near_needle.py  (--report: only the
tables, from the CSV)
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import json  # noqa: E402
import sys  # noqa: E402

import _common as common  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402

FACTORS = (1.0, 0.5, 0.25, 0.125)  # spacing / the file's
# (name, circle radius or ellipse semi-axes and angle in degrees, centre), mm
HOLES = {
    "circle r 0.23": ((0.2292,), (15.9956, 25.1966)),
    "circle r 0.53": ((0.5254,), (14.0576, 23.3041)),
    "circle r 0.22": ((0.2159,), (27.1373, 25.6817)),
    "circle r 0.17": ((0.1663,), (18.2738, 22.5477)),
    "circle r 0.16": ((0.1573,), (11.5782, 25.1151)),
    "circle r 0.3": ((0.3,), (30.0, 22.5)),
    "ellipse 0.27 x 0.11": ((0.265, 0.1102, 26.39), (26.9302, 25.6087)),
    "ellipse 0.86 x 0.28": ((0.8598, 0.2778, 43.11), (22.3275, 19.8978)),
}
CODES = ("shipped", "to its size")


def scene(hole: str) -> dict:
    """hole_near_stitch.yaml with its hole replaced by HOLES[hole] (an ellipse as a 200-gon)."""
    raw = yaml.safe_load((common.REPO_ROOT / "configs" / "hole_near_stitch.yaml").read_text())
    size, center = HOLES[hole]
    if len(size) == 1:
        raw["tissue"]["holes"] = [{"circle": {"center": list(center), "radius": size[0]}}]
    else:
        a, b, degrees = size
        t = 2.0 * np.pi * np.arange(200) / 200
        turn = np.radians(degrees)
        x, y = a * np.cos(t), b * np.sin(t)
        loop = np.column_stack([center[0] + x * np.cos(turn) - y * np.sin(turn),
                                center[1] + x * np.sin(turn) + y * np.cos(turn)])
        raw["tissue"]["holes"] = [{"polygon": loop.round(6).tolist()}]
    raw["name"] = f"hole by the needle: {hole}"
    raw.pop("probes", None)
    raw.pop("loads", None)
    return raw


def worker(hole: str, code: str, factor: str) -> dict:
    """The unplanned run of one scene at one level (`--worker`)."""
    from stitchplan.config.scenario import parse_scenario, with_discretization
    from stitchplan.needle.insertion import run_insertion
    from stitchplan.tissue import model, shapes

    if code == "to its size":  # hole_zones told of no needle: graded to the hole's size
        zones = shapes.hole_zones

        class WithoutNeedle:
            def __init__(self, discretization):
                self.discretization = discretization

            def __getattr__(self, name):
                return None if name == "needle_spacing" else getattr(self.discretization, name)

        model.shape_zones = lambda tissue, d: (*shapes.corner_zones(tissue, d), *shapes.interface_zones(tissue, d),
                                               *zones(tissue, WithoutNeedle(d)))
    scenario = parse_scenario(scene(hole))
    scenario = with_discretization(scenario, spacing=scenario.discretization.spacing * float(factor))
    result = run_insertion(scenario)
    return {"particles": result.model.n_particles, "exit_error_mm": float(result.exit_error_mm)}


def report(rows: list[dict]) -> None:
    header = ["hole", "grading", *(f"h/{round(1 / f):d}" if f < 1 else "h" for f in FACTORS), "offset at h from h/8 (mm)"]
    table = []
    for hole in HOLES:
        for code in CODES:
            cells = {float(row["factor"]): row for row in rows if row["hole"] == hole and row["code"] == code}
            if len(cells) < len(FACTORS):
                continue
            finest = float(cells[FACTORS[-1]]["exit_error_mm"])
            table.append([hole, code, *(f"{float(cells[f]['exit_error_mm']):.5f} ({cells[f]['particles']})" for f in FACTORS),
                          f"{float(cells[1.0]['exit_error_mm']) - finest:+.4f}"])
    text = common.markdown_table(header, table)
    common.results_path("hole_near_needle.md").write_text("\n".join([
        "# A small round hole by the needle's track",
        "",
        "`stitchplan simulate` on configs/hole_near_stitch.yaml's block with its hole replaced by a small one "
        "0.3-2 mm from the needle's track (benchmarks/hole_near_needle.py): the unplanned exit error (mm, "
        "particles in brackets) at the file's spacing h (3 mm, 1.5 mm at the needle) and finer, the particles "
        "graded toward the hole no finer than the needle's spacing (shipped) or to the hole's size.",
        "",
        text,
        "",
        f"Machine: {common.machine_note()}.",
        "",
    ]))
    print(text)


def main(flags: set[str]) -> None:
    path = common.results_path("hole_near_needle.csv")
    if "--report" not in flags:
        rows = []
        for hole in HOLES:
            for code in CODES:
                for factor in FACTORS:
                    record = common.worker_record(__file__, common.REPO_ROOT, hole, code, str(factor))
                    rows.append({"hole": hole, "code": code, "factor": factor, **record})
                    print(f"{hole}, {code}, h x {factor:g}: {record}", flush=True)
        common.write_csv(path, list(rows[0]), [list(row.values()) for row in rows])
    report(common.csv_rows(path))


if __name__ == "__main__":
    if sys.argv[1:2] == ["--worker"]:  # one level in a fresh process: the patched zones stay in it
        print(json.dumps(worker(*sys.argv[2:])))
    else:
        main(common.command_line(__doc__, ("--report",)))
