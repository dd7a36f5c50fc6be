"""Print the planned-vs-unplanned table of the shipped SH 1/2 scenes (markdown)."""

import json
from pathlib import Path

THESIS = {"sh12_100x100": (1.89, 0.01), "sh12_100x100_mid": (1.89, 0.01), "sh12_100x50": (3.0, 0.05),
          "sh12_100x40": (3.58, 0.02), "sh12_100x30": (4.35, 0.01)}

here = Path(__file__).parent
print("| scene | unplanned exit error (mm) | planned exit error (mm) | planned / unplanned | "
      "thesis unplanned / planned (mm) | planned wall s |")
print("|---|---|---|---|---|---|")
for scene, (thesis_unplanned, thesis_planned) in THESIS.items():
    summary = here / scene / "plan_summary.json"
    if not summary.exists():
        continue
    data = json.loads(summary.read_text())
    planned, unplanned = data["exit_error_mm"], data["unplanned_exit_error_mm"]
    print(f"| {scene} | {unplanned:.4f} | {planned:.4f} | {planned / unplanned:.1%} | "
          f"{thesis_unplanned} / {thesis_planned} | {data['wall_seconds']:.1f} |")
