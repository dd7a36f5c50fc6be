"""Plans under uncertainty on the refined model: the held-out samples replayed at half the
spacing, against the statistics `plan --uncertainty` reports.

On configs/sh12_100x100.yaml with the distributions of configs/uncertainty/uncertainty_sample.yaml:

1. plan_under_uncertainty as the command runs it, with verification (`verify`: the plans aim
   for the refined model; the nominal and robust statistics are the planning model's sampled
   exits plus the refined model's offset of the nominal path, measured at the scenario's
   values) and without it (`--no-verify`: the plans aim at the planning model, as before the
   verification aimed them);
2. each exported path replayed on every held-out sample at half the spacing (the refined
   model the verification uses, planning.replay_models.rescaled), the same sampled scenarios;
3. per plan: the exit error statistics on the refined model (measured), those the summary
   reports, and how far each sample's own refined offset (refined - planning exit error
   vector) is from the one offset the report adds; and the exported path replayed on the
   refined model at the scenario's values (with verification: the verified exit error).

The sampled runs go to a local Dask cluster of 2 workers (the command's default here).
Writes benchmarks/results/uncertainty_refined.md and .csv. About 3 minutes.
Run from the repository root:  python benchmarks/uncertainty_refined.py
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as the command and its Dask workers run

import csv  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

import _common as common  # noqa: E402
from stitchplan.config.scenario import load_scenario  # noqa: E402
from stitchplan.config.uncertainty import load_uncertainty  # noqa: E402
from stitchplan.parallel.executor import Executor  # noqa: E402
from stitchplan.planning.replay_models import VERIFICATION_FACTOR, rescaled  # noqa: E402
from stitchplan.uncertainty.evaluation import run_sample  # noqa: E402
from stitchplan.uncertainty.robust import exit_statistics, plan_under_uncertainty  # noqa: E402
from stitchplan.uncertainty.sampling import with_parameters  # noqa: E402

SCENE = "sh12_100x100"
WORKERS = 2
STATISTICS = ("mean_mm", "p50_mm", "p95_mm", "max_mm")


def main() -> None:
    scenario = load_scenario(common.REPO_ROOT / "configs" / f"{SCENE}.yaml")
    uncertainty = load_uncertainty(common.REPO_ROOT / "configs" / "uncertainty" / "uncertainty_sample.yaml")
    rows, lines = [], []
    with Executor(workers=WORKERS) as executor:
        for verify in (True, False):
            start = time.perf_counter()
            result = plan_under_uncertainty(scenario, uncertainty, executor, verify=verify)
            seconds = time.perf_counter() - start
            label = result.exported
            plan = result.exported_plan
            held = [with_parameters(scenario, result.design.names, values) for values in result.design.held_out]
            refined = [rescaled(sample, VERIFICATION_FACTOR) for sample in held]
            runs = executor.map(run_sample, refined, [plan.exported_centers] * len(refined), [{}] * len(refined))
            planning = np.array([run.exit_error for run in result.held_out[label]]).reshape(-1, 2)
            ok = np.array([run.ok for run in runs]) & np.array([run.ok for run in result.held_out[label]])
            measured = np.array([run.exit_error if run.ok else [np.nan, np.nan] for run in runs])
            offsets = measured[ok] - planning[ok]  # each sample's own refined offset
            added = result.refined_offset if result.refined_offset is not None else np.zeros(2)
            spread = np.linalg.norm(offsets - added, axis=1)
            reported = exit_statistics(planning[ok] + added)
            on_refined = exit_statistics(measured[ok])
            on_planning = exit_statistics(planning[ok])
            # the exported path at the scenario's values on the refined model (the verification's replay)
            at_nominal = run_sample(rescaled(scenario, VERIFICATION_FACTOR), plan.exported_centers)
            verified = float(np.linalg.norm(at_nominal.exit_error)) if at_nominal.ok else None
            rows.append({
                "verify": verify, "exported": label, "held_out": int(ok.sum()), "seconds": seconds,
                "refined_offset_x_mm": added[0], "refined_offset_y_mm": added[1],
                "verified_exit_error_mm": verified,
                "sample_offset_from_added_max_mm": float(spread.max()),
                "sample_offset_from_added_mean_mm": float(spread.mean()),
                "mean_on_refined_x_mm": float(measured[ok][:, 0].mean()),
                "mean_on_refined_y_mm": float(measured[ok][:, 1].mean()),
                **{f"reported_{key}": reported[key] for key in STATISTICS},
                **{f"refined_{key}": on_refined[key] for key in STATISTICS},
                **{f"planning_{key}": on_planning[key] for key in STATISTICS},
            })
            print(rows[-1], flush=True)
    path = common.results_path("uncertainty_refined.csv")
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)

    def number(value) -> str:
        return "—" if value is None else f"{value:.4f}"

    lines += [
        "# Plans under uncertainty on the refined model",
        "",
        f"Generated by `python benchmarks/uncertainty_refined.py` ({common.machine_note()}; {WORKERS} Dask "
        "workers).",
        "",
        f"configs/{SCENE}.yaml with configs/uncertainty/uncertainty_sample.yaml: plan_under_uncertainty with "
        "verification (the plans aim for the refined model; the summary's nominal and robust statistics are the "
        "planning model's held-out exits plus the refined model's offset of the nominal path at the scenario's "
        "values) and without (`--no-verify`: aimed at the planning model). The exported path is then replayed "
        "on every held-out sample at half the spacing. *Reported*: the summary's statistics of the exported "
        "plan; *on the refined model*: those of the refined replays; *on the planning model*: the sampled runs "
        "as they are. Offset spread: |a sample's own refined offset - the one added|. The exit error at the "
        "scenario's values is the exported path replayed on the refined model (with verification: the plan's "
        "verified exit error).",
        "",
        "| plan | exported | held-out samples | refined offset added (mm) | exit error on the refined model at the "
        "scenario's values (mm) | "
        "offset spread mean / max (mm) | mean exit error vector on the refined model (mm) | "
        "reported mean / p95 / max (mm) | on the refined model mean / p95 / max (mm) | "
        "on the planning model mean / p95 / max (mm) | command (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        triple = [" / ".join(number(row[f"{kind}_{key}"]) for key in ("mean_mm", "p95_mm", "max_mm"))
                  for kind in ("reported", "refined", "planning")]
        lines.append(
            f"| {'aimed for the refined model' if row['verify'] else '--no-verify'} | {row['exported']} | "
            f"{row['held_out']} | ({row['refined_offset_x_mm']:.4f}, {row['refined_offset_y_mm']:.4f}) | "
            f"{number(row['verified_exit_error_mm'])} | {row['sample_offset_from_added_mean_mm']:.4f} / "
            f"{row['sample_offset_from_added_max_mm']:.4f} | ({row['mean_on_refined_x_mm']:.4f}, "
            f"{row['mean_on_refined_y_mm']:.4f}) | {triple[0]} | {triple[1]} | {triple[2]} | {row['seconds']:.0f} |")
    common.write_report("uncertainty_refined.md", lines + [""])


if __name__ == "__main__":
    common.command_line(__doc__)
    main()
