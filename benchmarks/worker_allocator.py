"""Runs in a local Dask worker against the same runs in the command's process: malloc's thresholds.

A local cluster's nanny starts each worker with MALLOC_TRIM_THRESHOLD_ set (64 KiB, Dask's
`distributed.nanny.pre-spawn-environ`), which also fixes glibc's mmap threshold at 128 KiB:
every array above it is mapped afresh and faulted in page by page when written. The command
sets both thresholds higher in its own process (stitchplan/allocator.py); the executor now
starts its workers with the same (`worker_environment`).

Each variant runs in a process of its own:

- `process`: RUNS unplanned runs of configs/sh12_100x100.yaml (`run_insertion`) in the
  process, after `reuse_freed_memory`, as the command makes them;
- `worker`: the same runs as one task on a 1-worker local cluster (the Executor, as the
  commands start it);
- `worker, Dask's malloc`: the same with MALLOC_TRIM_THRESHOLD_ set in the benchmark's
  environment, which the executor leaves to Dask (a user's own setting): the workers as
  they were started before.

Per run: wall time, the thread's CPU time and the process's minor page faults; medians over
the runs after the first (the first builds the model's caches). Then, as the commands run
now, `stitchplan study configs/needle20_entry30.yaml --quick` with `--workers 0` and
`--workers 1` (each run's wall time from study.csv, worker over process): its runs on the
20 mm needle's particles (900-1681) make arrays mostly below 128 KiB, where the thresholds
change nothing, so what a worker adds there is its own (its event loop and heartbeats beside
the task). (With MALLOC_TRIM_THRESHOLD_ set the command's own process keeps glibc's defaults
too, so that setting's ratio would compare two other processes.)

Writes benchmarks/results/worker_allocator.md and .csv and prints them. About 3 minutes.
Run from the repository root:  python benchmarks/worker_allocator.py
"""

from __future__ import annotations

import os

# single-threaded BLAS, as the `stitchplan` command sets it (and its Dask workers)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import csv  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import _common as common  # noqa: E402

SCENE = common.REPO_ROOT / "configs" / "sh12_100x100.yaml"
STUDY_SCENE = common.REPO_ROOT / "configs" / "needle20_entry30.yaml"
RUNS = 7
DASK_TRIM = "65536"  # Dask's MALLOC_TRIM_THRESHOLD_ for a nanny's workers
VARIANTS = (("process", "process", {}), ("worker", "worker", {}),
            ("worker, Dask's malloc", "worker", {"MALLOC_TRIM_THRESHOLD_": DASK_TRIM}))


def runs(count: int) -> list[tuple[float, float, int]]:
    """`count` unplanned runs of SCENE: (wall s, thread CPU s, minor page faults) each."""
    import resource
    import time

    from stitchplan.config.scenario import load_scenario
    from stitchplan.needle.insertion import run_insertion

    scenario = load_scenario(SCENE)
    measured = []
    for _ in range(count):
        faults, start, cpu = resource.getrusage(resource.RUSAGE_SELF).ru_minflt, time.perf_counter(), time.thread_time()
        run_insertion(scenario)
        measured.append((time.perf_counter() - start, time.thread_time() - cpu,
                         resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults))
    return measured


def child(where: str) -> None:
    """One variant's runs, printed as JSON (run as `--child WHERE`)."""
    if where == "process":
        from stitchplan.allocator import reuse_freed_memory

        reuse_freed_memory()
        measured = runs(RUNS)
    else:
        from stitchplan.parallel.executor import Executor

        with Executor(workers=1) as executor:
            (measured,) = executor.map(runs, [RUNS])
    print(json.dumps(measured))


def variant_environment(extra: dict) -> dict:
    """This environment without glibc's malloc variables, with `extra`."""
    environment = {key: value for key, value in os.environ.items() if not key.startswith("MALLOC_")}
    return {**environment, **extra}


def study_ratio(extra: dict, folder: Path) -> tuple[float, float]:
    """`study --quick` with --workers 0 and 1: the median and the largest of each run's wall
    time in the worker over its time in the process."""
    seconds = {}
    for workers in (0, 1):
        out = folder / f"study{workers}"
        done = subprocess.run([*common.STITCHPLAN, "study", str(STUDY_SCENE), "--quick", "--out", str(out),
                               "--workers", str(workers)], capture_output=True, text=True,
                              env=common.command_environment(**variant_environment(extra)), cwd=common.REPO_ROOT)
        if done.returncode != 0:
            raise SystemExit(common.failure_line("stitchplan study", common.REPO_ROOT, done))
        with (out / "study.csv").open() as handle:
            seconds[workers] = {(row["family"], row["label"]): float(row["wall_seconds"])
                                for row in csv.DictReader(handle) if row["status"] == "ok"}
    ratios = [seconds[1][run] / seconds[0][run] for run in seconds[0] if run in seconds[1]]
    return statistics.median(ratios), max(ratios)


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "--child":
        child(sys.argv[2])
        return
    common.command_line(__doc__)
    header = ["variant", "wall per run (s)", "thread CPU per run (s)", "page faults per run",
              "study --quick: worker / process, median", "largest"]
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        for name, where, extra in VARIANTS:
            done = subprocess.run([sys.executable, __file__, "--child", where], capture_output=True, text=True,
                                  env=variant_environment(extra), cwd=common.REPO_ROOT)
            if done.returncode != 0:
                raise SystemExit(common.failure_line(f"worker_allocator.py --child {where}", common.REPO_ROOT, done))
            measured = json.loads(done.stdout.strip().splitlines()[-1])[1:]
            ratio = study_ratio(extra, Path(scratch)) if name == "worker" else ("", "")
            rows.append([name, *(statistics.median(run[index] for run in measured) for index in range(3)), *ratio])
            print(*(common.fmt(value) for value in rows[-1]), flush=True)
    common.write_results("worker_allocator", header, rows, [
        "# Runs in a local Dask worker and in the command's process: malloc's thresholds",
        "",
        f"Generated by `python benchmarks/worker_allocator.py` ({common.machine_note()}). {RUNS} unplanned runs of "
        f"configs/{SCENE.name} in one process (`process`), as one task on a 1-worker local cluster started as the "
        "commands start it (`worker`: its workers get the command's malloc thresholds), and the same with "
        f"MALLOC_TRIM_THRESHOLD_={DASK_TRIM} in the environment, which the executor leaves to Dask (`worker, Dask's "
        "malloc`: how workers started before); medians over the runs after the first. The study columns: "
        f"`stitchplan study configs/{STUDY_SCENE.name} --quick` with --workers 1 against --workers 0, each run's wall "
        "time in study.csv (its arrays mostly below the 128 KiB the thresholds start from). The machine is shared: "
        "wall times vary by tens of percent."])


if __name__ == "__main__":
    main()
