"""Memory of a command's runs that go on at once, against the resource guard's sum.

`plan` replays its trajectory on the verification model and the predicted aim's model at
twice the spacing in helper processes while it plans (planning/replays.py); `simulate`
replays the exit error estimate's run at twice the spacing beside its own; `plan
--uncertainty` runs its sampled plans on the workers of a local Dask cluster while it holds
its own. The guard (resources.guard.check_resources `alongside`) holds their memory together within
its share: the interpreter counted once and HELPER_BASE_MEMORY for each forked helper, the
whole estimate for each Dask worker (a process started afresh). Here
each command runs on configs/sh12_100x100.yaml at its needle step and at 0.005 rad (what the
runs keep of their steps then dominates; plan --uncertainty at 0.02 rad), and its process
tree's proportional set size (PSS: pages shared by forked processes counted once between
them) is sampled every 20 ms; the peak of the sum is set beside the guard's estimates as the
command logs them with -v.

Writes benchmarks/results/memory_at_once.{md,csv} and prints them. About 4 minutes.
Run from the repository root:  python benchmarks/memory_at_once.py
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import re  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import yaml  # noqa: E402

import _common as common  # noqa: E402

SCENE = common.REPO_ROOT / "configs" / "sh12_100x100.yaml"
UNCERTAINTY = common.REPO_ROOT / "configs" / "uncertainty" / "uncertainty_sample.yaml"
# (name, arguments, needle steps (None: the scenario's))
COMMANDS = (
    ("plan", ["plan", "{config}", "--no-compare", "--export", "{folder}/trajectory.csv"], (None, 0.005)),
    ("plan --no-verify", ["plan", "{config}", "--no-compare", "--no-verify", "--export", "{folder}/trajectory.csv"],
     (None, 0.005)),
    ("simulate", ["simulate", "{config}", "--summary", "{folder}/summary.json"], (None, 0.005)),
    # 58 sampled plans on two local Dask workers (0.005 rad would take ~8 minutes)
    ("plan --uncertainty --workers 2 --no-verify",
     ["plan", "{config}", "--uncertainty", str(UNCERTAINTY), "--workers", "2", "--no-verify", "--export",
      "{folder}/trajectory.csv"], (None, 0.02)),
)
ESTIMATE_LINE = re.compile(r"stitchplan\.resources: resources: (?P<label>[^:]+): "
                           r".*?~(?P<amount>[\d.]+) (?P<unit>GB|MB|kB) memory")
UNITS = {"GB": 1e9, "MB": 1e6, "kB": 1e3}
OWN_RUNS = ("plan", "simulate", "plan --uncertainty")  # the label a command's first estimate has


def process_tree(root: int) -> list[int]:
    found = [root]
    try:
        for task in os.listdir(f"/proc/{root}/task"):
            with open(f"/proc/{root}/task/{task}/children") as handle:
                for child in handle.read().split():
                    found += process_tree(int(child))
    except OSError:
        pass
    return found


def proportional_set_size(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/smaps_rollup") as handle:
            for line in handle:
                if line.startswith("Pss:"):
                    return float(line.split()[1]) * 1024.0
    except OSError:
        pass
    return 0.0


def run(arguments: list[str], log: Path) -> tuple[float, dict[int, float], float, int]:
    """Peak PSS of the process tree (bytes), each process's peak, wall seconds, exit code."""
    start = time.perf_counter()
    with open(log, "w") as output:
        process = subprocess.Popen(common.STITCHPLAN + arguments, stdout=output, stderr=subprocess.STDOUT,
                                   cwd=common.REPO_ROOT, env=common.command_environment())
        peak, each = 0.0, {}
        while process.poll() is None:
            sizes = {pid: proportional_set_size(pid) for pid in process_tree(process.pid)}
            peak = max(peak, sum(sizes.values()))
            for pid, size in sizes.items():
                each[pid] = max(each.get(pid, 0.0), size)
            time.sleep(0.02)
    return peak, each, time.perf_counter() - start, process.returncode


def main() -> None:
    from stitchplan.resources.costs import held_at_once

    header = ["command", "needle step (rad)", "exit code", "wall (s)", "processes", "peak of each (MB)",
              "peak together (MB)", "guard's runs (MB)", "guard together (MB)", "measured / guard"]
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch)
        for name, template, steps in COMMANDS:
            for step in steps:
                raw = yaml.safe_load(SCENE.read_text())
                if step is not None:
                    raw["needle"]["step"] = step
                config = folder / f"scene_{step}.yaml"
                config.write_text(yaml.safe_dump(raw))
                arguments = [part.format(config=config, folder=folder) for part in template] + ["-v"]
                log = folder / "log.txt"
                peak, each, wall, code = run(arguments, log)
                estimates = [(match["label"], float(match["amount"]) * UNITS[match["unit"]])
                             for match in map(ESTIMATE_LINE.search, log.read_text().splitlines()) if match]
                # the last check's: plan --uncertainty checks the plan's runs, then its own with the workers'
                first = max(k for k, (label, _) in enumerate(estimates) if label in OWN_RUNS)
                estimates = estimates[first:]
                # as the guard sums them; Dask workers are processes of their own
                together = held_at_once([amount for _, amount in estimates],
                                        forked=not name.startswith("plan --uncertainty"))
                rows.append([name, step or raw["needle"]["step"], code, wall, len(each),
                             " / ".join(f"{size / 1e6:.0f}" for size in sorted(each.values(), reverse=True)),
                             peak / 1e6, "; ".join(f"{label} {amount / 1e6:.0f}" for label, amount in estimates),
                             together / 1e6, peak / together])
                print(rows[-1], flush=True)
    common.write_csv(common.results_path("memory_at_once.csv"), header, rows)
    lines = [
        "# Memory of a command's runs that go on at once",
        "",
        f"Generated by `python benchmarks/memory_at_once.py` ({common.machine_note()}). configs/sh12_100x100.yaml "
        "at its needle step and at 0.005 rad (plan --uncertainty with configs/uncertainty/uncertainty_sample.yaml "
        "on a local cluster of two Dask worker processes, at 0.02 rad); the PSS (proportional set size: pages the "
        "forked helper processes share with the command counted once between them) of the command's process tree, "
        "sampled every 20 ms. "
        "Guard's runs: the estimates the command logs with -v; together: their sum with the interpreter's "
        "BASE_MEMORY counted once and HELPER_BASE_MEMORY for each forked helper (a Dask worker's estimate whole), "
        "what resources.guard.check_resources holds within half the memory available.",
        "",
        common.markdown_table(header, rows),
    ]
    common.write_report("memory_at_once.md", lines)


if __name__ == "__main__":
    common.command_line(__doc__)
    main()
