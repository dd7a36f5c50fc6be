"""Print the planned-vs-unplanned table of the shipped SH 1/2 scenes (markdown), with the
largest distance of the planned centre from its start and its largest move between two
steps (read from trajectory.csv)."""

import csv
import json
import math
from pathlib import Path

THESIS = {"sh12_100x100": (1.89, 0.01), "sh12_100x100_mid": (1.89, 0.01), "sh12_100x50": (3.0, 0.05),
          "sh12_100x40": (3.58, 0.02), "sh12_100x30": (4.35, 0.01),
          "skin_layered": ("-", "-"), "hole_near_stitch": ("-", "-"),
          "wound_closure": ("-", "-"), "wound_closure_symmetric": ("-", "-")}  # shapes: no thesis figures


def centre_moves(trajectory: Path) -> tuple[float, float]:
    """Largest distance of the centre from its start, and largest move between two steps."""
    with trajectory.open(newline="") as handle:
        rows = [(float(r["center_x_mm"]), float(r["center_y_mm"])) for r in csv.DictReader(handle)]
    x0, y0 = rows[0]
    excursion = max(math.hypot(x - x0, y - y0) for x, y in rows)
    jump = max(math.hypot(b[0] - a[0], b[1] - a[1]) for a, b in zip(rows, rows[1:]))
    return excursion, jump


here = Path(__file__).parent
print("| scene | particles | unplanned exit error (mm) | planned exit error (mm) | verified exit error (mm) | "
      "verification spacing (mm) | exit-error estimate (mm) | thesis unplanned / planned (mm) | "
      "planned centre excursion (mm) | largest centre move per step (mm) | largest second difference (mm) | "
      "planned run s |")
print("|---|---|---|---|---|---|---|---|---|---|---|---|")
for scene, (thesis_unplanned, thesis_planned) in THESIS.items():
    summary = here / scene / "plan_summary.json"
    if not summary.exists():
        continue
    data = json.loads(summary.read_text())
    planned, unplanned = data["exit_error_mm"], data["unplanned_exit_error_mm"]
    excursion, jump = centre_moves(here / scene / "trajectory.csv")
    print(f"| {scene} | {data['particles']} | {unplanned:.4f} | {planned:.4f} | "
          f"{data['verified_exit_error_mm']:.4f} | {data['verification_spacing_mm']:.3g} | "
          f"{data['exit_error_estimate_mm']:.3f} | {thesis_unplanned} / {thesis_planned} | {excursion:.1f} | "
          f"{jump:.2f} | {data['max_center_second_difference_mm']:.2f} | {data['wall_seconds']:.1f} |")
