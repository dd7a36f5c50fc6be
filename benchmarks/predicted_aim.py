"""The predicted aim of a verified plan: the refined model's exit offset predicted from a
replay at twice the spacing, and the verification rounds it saves.

`plan` replays its trajectory on a model of half the particle spacing h/2 and re-aims when
that replay misses by more than 1.5 x the exit tolerance (planning/verification.py). With
`planner.predicted_aim` (the default) it also replays its first planner pass at 2h, which
is cheap, predicts the refined model's offset of the exit-error vector e as
(e(h) - e(2h)) / PREDICTED_RATIO, and aims the later passes by it when the prediction says
the refined replay would miss; the refined replay then judges that plan, and a miss
re-aims again by the measured offset as before.

For each shipped needle scene aimed at its exit (wound_closure_symmetric aims at equal
bites and is not predicted), in this process:

1. The plan's first pass at h (`run_plan` with one pass, no aim) replayed at 2h and h/2: the ratio
   |e(h) - e(2h)| / |e(h/2) - e(h)| the prediction assumes to be PREDICTED_RATIO, the
   predicted and the measured offsets, and how far apart they are.
2. `plan_verified` with and without the predicted aim: its rounds, their aims and the
   verified exit error.

Writes benchmarks/results/predicted_aim.{csv,md} and prints the table. About 3 minutes.
Run from the repository root:  python benchmarks/predicted_aim.py
"""

from __future__ import annotations

import os
from dataclasses import replace

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import yaml  # noqa: E402

import _common as common  # noqa: E402
from stitchplan.config import load_scenario  # noqa: E402
from stitchplan.config.scenario import parse_scenario  # noqa: E402
from stitchplan.planning.planner import run_plan  # noqa: E402
from stitchplan.planning.replays import InlineReplays  # noqa: E402
from stitchplan.planning.replay_models import ESTIMATE_FACTOR, VERIFICATION_FACTOR, rescaled  # noqa: E402
from stitchplan.planning.verification import PREDICTED_RATIO, VERIFIED_FACTOR, plan_verified  # noqa: E402

SCENES = ("sh12_100x100", "sh12_100x100_mid", "sh12_100x30", "sh12_100x40", "sh12_100x50", "hole_near_stitch",
          "skin_layered", "wound_closure", "needle20_entry18", "needle20_entry20", "needle20_entry25",
          "needle20_entry30")


def without_prediction(scene: str):
    """configs/SCENE.yaml with planner.predicted_aim false."""
    raw = yaml.safe_load((common.REPO_ROOT / "configs" / f"{scene}.yaml").read_text())
    raw.setdefault("planner", {})["predicted_aim"] = False
    return parse_scenario(raw)


def measure(scene: str) -> dict:
    scenario = load_scenario(common.REPO_ROOT / "configs" / f"{scene}.yaml")
    threshold = VERIFIED_FACTOR * scenario.planner.exit_tolerance
    unaimed = run_plan(replace(scenario, planner=replace(scenario.planner, max_passes=1)), compare=False)
    centers = unaimed.exported_centers
    at = {factor: InlineReplays(rescaled(scenario, factor)).replay(centers).exit_error_vector_mm
          for factor in (ESTIMATE_FACTOR, VERIFICATION_FACTOR)}
    e_h = unaimed.planned.exit_error_vector_mm
    coarse_change, fine_change = e_h - at[ESTIMATE_FACTOR], at[VERIFICATION_FACTOR] - e_h
    predicted = coarse_change / PREDICTED_RATIO
    row = {"scene": scene, "planned_mm": float(np.linalg.norm(e_h)),
           "change_2h_h_mm": float(np.linalg.norm(coarse_change)),
           "change_h_h2_mm": float(np.linalg.norm(fine_change)),
           "ratio": float(np.linalg.norm(coarse_change) / max(np.linalg.norm(fine_change), 1e-300)),
           "predicted_offset_mm": float(np.linalg.norm(predicted)),
           "prediction_error_mm": float(np.linalg.norm(predicted - fine_change)),
           "unaimed_verified_mm": float(np.linalg.norm(at[VERIFICATION_FACTOR])),
           "predicted_verified_mm": float(np.linalg.norm(e_h + predicted)),
           "threshold_mm": threshold}
    for label, variant in (("with", scenario), ("without", without_prediction(scene))):
        plan = plan_verified(variant, compare=False)
        rounds = plan.verification.rounds
        row[f"{label}_rounds"] = len(rounds)
        row[f"{label}_aims"] = " / ".join(r["aimed_by"] for r in rounds)
        row[f"{label}_round_errors_mm"] = " / ".join(common.fmt(r["verified_exit_error_mm"]) for r in rounds)
        row[f"{label}_verified_mm"] = plan.verification.exit_error_mm
        row[f"{label}_planned_mm"] = plan.planned.exit_error_mm
    return row


def main() -> None:
    rows = []
    for scene in SCENES:
        row = measure(scene)
        rows.append(row)
        print(f"{scene}: ratio {row['ratio']:.2f}, prediction off by {row['prediction_error_mm']:.4f} mm; rounds "
              f"{row['with_rounds']} ({row['with_verified_mm']:.4f} mm) with, {row['without_rounds']} "
              f"({row['without_verified_mm']:.4f} mm) without", flush=True)
    header = list(rows[0])
    common.write_csv(common.results_path("predicted_aim.csv"), header, [[r[k] for k in header] for r in rows])
    aimed = [r for r in rows if r["with_aims"].startswith("predicted")]
    ratios = [r["ratio"] for r in aimed]
    saved = [r["scene"] for r in rows if r["with_rounds"] < r["without_rounds"]]
    more = [r["scene"] for r in rows if r["with_rounds"] > r["without_rounds"]]
    lines = [
        "# The predicted aim: the refined model's offset predicted at twice the spacing\n",
        f"Generated by `python benchmarks/predicted_aim.py` ({common.machine_note()}).\n",
        "Exit-error vectors e (achieved minus desired exit, deformed) of each scene's first planner pass "
        "(no aim) at its spacing h and replayed at 2h and h/2, as the predicted aim replays it. "
        "*Ratio*: |e(h) - e(2h)| / |e(h/2) - e(h)|; "
        f"the predicted aim takes it to be {PREDICTED_RATIO:g} (planning/verification.py PREDICTED_RATIO) and "
        "aims the later passes at minus the predicted offset (e(h) - e(2h)) / ratio when |e(h) + predicted "
        f"offset| is above {VERIFIED_FACTOR:g} x the exit tolerance. "
        "*Prediction off by*: |predicted - measured offset|. "
        "*Verified*: the first pass's exit error on the refined model at h/2, predicted (|e(h) + predicted "
        "offset|) and measured. Distances in mm.\n",
        common.markdown_table(
            ["scene", "planned", "e(h) - e(2h)", "e(h/2) - e(h)", "ratio", "predicted offset",
             "prediction off by", "verified, not aimed", "verified, predicted"],
            [[r["scene"], r["planned_mm"], r["change_2h_h_mm"], r["change_h_h2_mm"], r["ratio"],
              r["predicted_offset_mm"], r["prediction_error_mm"], r["unaimed_verified_mm"],
              r["predicted_verified_mm"]] for r in rows]),
        "",
        "`plan_verified` (the default `plan`'s verification, in this process) with the predicted aim and "
        "without it (`planner.predicted_aim: false`): each round's aim (*none*: the plan as planned; "
        "*predicted offset*; *refined offset*: by the refined replay's measured offset) and verified exit "
        "error, and the exported plan's planned and verified exit errors (mm).\n",
        common.markdown_table(
            ["scene", "rounds with", "aims", "verified per round", "planned", "verified",
             "rounds without", "aims", "verified per round", "planned", "verified"],
            [[r["scene"], r["with_rounds"], r["with_aims"], r["with_round_errors_mm"], r["with_planned_mm"],
              r["with_verified_mm"], r["without_rounds"], r["without_aims"], r["without_round_errors_mm"],
              r["without_planned_mm"], r["without_verified_mm"]] for r in rows]),
        "",
        f"Re-aimed by the prediction: {len(aimed)} of {len(rows)} scenes (ratios "
        f"{common.fmt(min(ratios), 3) if ratios else '-'} to {common.fmt(max(ratios), 3) if ratios else '-'} "
        f"there). A round saved on: {', '.join(saved) or 'none'}; a round more on: {', '.join(more) or 'none'}.\n",
    ]
    common.write_report("predicted_aim.md", lines)


if __name__ == "__main__":
    common.command_line(__doc__)
    main()
