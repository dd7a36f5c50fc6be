"""A plan's accuracy one refinement beyond its verification: the shipped plans' trajectories
replayed at the verification spacing (h/2) and at half of it (h/4).

`stitchplan plan` verifies its trajectory on a model with half the planning spacing h and
aims so that the verified exit error stays within the target. Whether that holds on a finer
model still is what a user relies on: this script replays each shipped trajectory
(sample_runs/SCENE/trajectory.csv, written by sample_runs/regenerate.sh) with
`stitchplan simulate CONFIG --center-path trajectory.csv --spacing S` at S = the plan's
verification spacing (which must give its verified exit error again) and S / 2. The
simulate summaries' own exit-error estimate (from a run at 2S) is listed too, and for a
stitch across a wound the difference of its two bites.

Where the exit point's discretization error comes from: the same trajectories replayed with
only the graded zone around the needle refined (its spacing that of h/2 and of h/4, the
planning spacing h elsewhere; the scene's file with `discretization.needle_spacing` set),
beside the replays refined throughout.

Writes benchmarks/results/plan_replay.{csv,md} and prints the tables. About 8 minutes.
Run from the repository root, after sample_runs/regenerate.sh:  python benchmarks/plan_replay.py
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import csv  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import yaml  # noqa: E402

import _common as common  # noqa: E402

SAMPLES = common.REPO_ROOT / "sample_runs"
FIELDS = ("scene", "planned_exit_error_mm", "verified_exit_error_mm", "verification_spacing_mm",
          "refined", "replay_spacing_mm", "replay_needle_spacing_mm", "particles", "exit_error_mm",
          "exit_error_estimate_mm", "seconds", "planned_bite_difference_mm", "bite_difference_mm", "target")
TARGET_MM = 0.01  # the verified exit error the shipped plans are held to (README)


def planned_scenes() -> list[str]:
    """The sample runs with a plan: a summary with a verification and its trajectory."""
    scenes = []
    for summary in sorted(SAMPLES.glob("*/plan_summary.json")):
        record = json.loads(summary.read_text())
        if record.get("verification_spacing_mm") and (summary.parent / "trajectory.csv").exists():
            scenes.append(summary.parent.name)
    return scenes


def scene_settings(scene: str) -> tuple[str, float]:
    """The scene's planner.target (`exit`, or `symmetric`: a wound stitch aimed at equal bites)
    and its nominal needle spacing / spacing, as the file asks for it."""
    from stitchplan.config.scenario import load_scenario

    scenario = load_scenario(common.REPO_ROOT / "configs" / f"{scene}.yaml")
    discretization = scenario.discretization
    return scenario.planner.target, (discretization.needle_spacing or discretization.spacing) / discretization.spacing


def replay(scene: str, spacing: float, folder: Path, needle_spacing: float | None = None) -> dict:
    """`stitchplan simulate` of the scene's shipped trajectory at `spacing`, the graded arrangement
    scaled with it; with `needle_spacing`, the particles at `spacing` and `needle_spacing` near
    the needle (the scene's file with those keys, written to `folder`). Its summary."""
    config = common.REPO_ROOT / "configs" / f"{scene}.yaml"
    options = ["--spacing", f"{spacing!r}"]
    name = f"{scene}_{spacing:.4f}"
    if needle_spacing is not None:
        raw = yaml.safe_load(config.read_text())
        discretization = raw.setdefault("discretization", {})
        discretization.pop("needle_refinement", None)
        discretization.update(spacing=spacing, needle_spacing=needle_spacing)
        name += f"_needle_{needle_spacing:.4f}"
        config = folder / f"{name}.yaml"
        config.write_text(yaml.safe_dump(raw))
        options = []
    summary = folder / f"{name}.json"
    subprocess.run([*common.STITCHPLAN, "simulate", str(config), "--center-path", str(SAMPLES / scene / "trajectory.csv"),
                    *options, "--summary", str(summary), "--quiet"], check=True, capture_output=True)
    return json.loads(summary.read_text())


def main() -> None:
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for scene in planned_scenes():
            plan = json.loads((SAMPLES / scene / "plan_summary.json").read_text())
            verification = float(plan["verification_spacing_mm"])
            target, grading = scene_settings(scene)
            levels = (verification, verification / 2.0)
            replays = ([("throughout", spacing, None) for spacing in levels]
                       + [("needle zone", 2.0 * verification, grading * spacing) for spacing in levels])
            for refined, spacing, needle_spacing in replays:
                result = replay(scene, spacing, Path(folder), needle_spacing)
                row = {"scene": scene, "planned_exit_error_mm": plan["exit_error_mm"],
                       "verified_exit_error_mm": plan["verified_exit_error_mm"],
                       "verification_spacing_mm": verification, "refined": refined, "replay_spacing_mm": spacing,
                       "replay_needle_spacing_mm": result["discretization"].get("needle_spacing_mm"),
                       "particles": result["particles"], "exit_error_mm": result["exit_error_mm"],
                       "exit_error_estimate_mm": result.get("exit_error_estimate_mm"),
                       "seconds": result["wall_seconds"],
                       # a stitch across a wound: the bites' difference, what a symmetric plan aims at
                       "planned_bite_difference_mm": (plan.get("bites") or {}).get("difference_mm"),
                       "bite_difference_mm": (result.get("bites") or {}).get("difference_mm"),
                       "target": target}
                print(row, flush=True)
                rows.append(row)
    with common.results_path("plan_replay.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=FIELDS)
        writer.writeheader()
        writer.writerows(rows)
    text = markdown(rows)
    common.results_path("plan_replay.md").write_text(text)
    print(text)


def markdown(rows: list[dict]) -> str:
    def mm(value) -> str:
        return "—" if value is None else f"{value:.4f}"

    by_scene: dict[str, dict[str, list[dict]]] = {}  # scene -> refined -> rows, coarser first
    for row in rows:
        by_scene.setdefault(row["scene"], {}).setdefault(row["refined"], []).append(row)
    for replays in by_scene.values():
        for same in replays.values():
            same.sort(key=lambda x: (-x["replay_spacing_mm"], -(x["replay_needle_spacing_mm"] or 0.0)))
    lines = ["# The shipped plans replayed one refinement beyond their verification", "",
             f"Generated by `python benchmarks/plan_replay.py` ({common.machine_note()}).", "",
             "Each shipped trajectory (sample_runs/SCENE/trajectory.csv) replayed by `stitchplan simulate "
             "--center-path` at the plan's verification spacing h/2 (which gives its verified exit error "
             "again) and at h/4; the estimate is simulate's own (Richardson from a run at twice the replay's "
             "spacing). Exit errors in mm.", "",
             "| scene | planned (h) | verified (h/2, summary) | replay h/2 | replay h/4 | estimate at h/4 | "
             "particles h/4 | h/4 replay s |",
             "|---|---|---|---|---|---|---|---|"]
    worst = 0.0
    for scene, replays in by_scene.items():
        half, quarter = replays["throughout"]
        if half["target"] != "symmetric":  # a symmetric plan aims its bites (below), not the exit
            worst = max(worst, quarter["exit_error_mm"])
        lines.append(f"| {scene} | {mm(half['planned_exit_error_mm'])} | {mm(half['verified_exit_error_mm'])} | "
                     f"{mm(half['exit_error_mm'])} | {mm(quarter['exit_error_mm'])} | "
                     f"{mm(quarter['exit_error_estimate_mm'])} | {quarter['particles']} | {quarter['seconds']:.1f} |")
    lines += ["", f"Largest exit error at h/4 of the plans aimed at the exit: {worst:.4f} mm "
                  f"({'within' if worst <= TARGET_MM else 'above'} the {TARGET_MM} mm target)."]
    lines += ["", "Where the exit point's discretization error comes from: the same replays with only the "
                  "graded zone around the needle refined (its spacing as at h/2 and h/4, the planning "
                  "spacing h elsewhere) beside those refined throughout; exit errors in mm, particles in "
                  "brackets, the largest difference between the two at the same needle spacing, and the "
                  "replays' runs at h/2 (simulate's `wall_seconds`).", "",
              "| scene | throughout h/2 | needle zone h/2 | throughout h/4 | needle zone h/4 | difference (mm) | "
              "h/2 replay s, throughout / needle zone |",
              "|---|---|---|---|---|---|---|"]
    largest = 0.0
    for scene, replays in by_scene.items():
        pairs = list(zip(replays["throughout"], replays["needle zone"]))
        difference = max(abs(whole["exit_error_mm"] - zone["exit_error_mm"]) for whole, zone in pairs)
        largest = max(largest, difference)
        cells = [f"{mm(row['exit_error_mm'])} ({row['particles']})" for pair in pairs for row in pair]
        seconds = " / ".join(f"{row['seconds']:.2f}" for row in pairs[0])
        lines.append(f"| {scene} | {' | '.join(cells)} | {difference:.4f} | {seconds} |")
    lines += ["", f"Largest difference: {largest:.4f} mm."]
    wounds = [(scene, replays["throughout"]) for scene, replays in by_scene.items()
              if replays["throughout"][0]["bite_difference_mm"] is not None]
    if wounds:
        lines += ["", "A stitch across a wound: the difference of the exit-side and entry-side bites (mm), "
                      "on the planning model (the plan's summary) and in the replays; with `planner.target: "
                      "symmetric` it is what the plan aims at.", "",
                  "| scene | bite difference planned (h) | replay h/2 | replay h/4 |", "|---|---|---|---|"]
        lines += [f"| {scene} | {half['planned_bite_difference_mm']:+.4f} | {half['bite_difference_mm']:+.4f} | "
                  f"{quarter['bite_difference_mm']:+.4f} |" for scene, (half, quarter) in wounds]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    common.command_line(__doc__)
    main()
