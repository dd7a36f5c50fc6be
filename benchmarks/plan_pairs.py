"""The default verified `plan` before (BASELINE) and now, side by side, with the resource guard alone.

1. Whole `stitchplan plan CONFIG` processes (comparison and verification, as a user runs it) of
   the code of BASELINE (extracted with `git archive`) and of this code, alternating, REPEATS
   times each on each scene: the medians of the wall time and of the CPU time (user + sys of
   the command and its replay helper, from wait4), their ratios (now over before), how many
   pairs this code won on wall time, and whether every pair's trajectories agree byte for
   byte and their summaries on the exit errors.
2. The resource guard of `plan` alone (cli.guards.guard_plan, what the command runs before it
   hands the replay helper its model and before its own planning), in a process of each
   code, after one call that imports what it needs: the median of GUARD_CALLS calls,
   alternating the two processes GUARD_ROUNDS times (median of the rounds' medians).

The machine is shared: compare within a run. Writes benchmarks/results/plan_pairs.{csv,md}
and prints the tables. 5-10 minutes.
Run from the repository root:  python benchmarks/plan_pairs.py   (PAIRS_BASELINE=REV to
choose the baseline, PAIRS_REPEATS=N the whole commands' repeats)
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import json  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import _common as common  # noqa: E402

BASELINE = os.environ.get("PAIRS_BASELINE", "577b0da")  # the code before the guard's shaped estimate bound
REPEATS = int(os.environ.get("PAIRS_REPEATS", 7))
GUARD_ROUNDS = 5
GUARD_CALLS = 5
SCENES = ("sh12_100x100", "wound_closure", "hole_near_stitch")
COMPARED = ("exit_error_mm", "verified_exit_error_mm", "exit_error_estimate_mm", "unplanned_exit_error_mm")

GUARD_SCRIPT = """
import json, statistics, sys, time
from pathlib import Path
from stitchplan.cli.guards import guard_plan
from stitchplan.cli.options import guard_limits, load_with_options, option_names
from stitchplan.planning.plan_options import with_plan_options
path = Path(sys.argv[1])
scenario = with_plan_options(load_with_options(path, None, None), None, None, False)
limits, names = guard_limits(None, False), option_names(None, None)
guard_plan(path, limits, names, scenario, verify=True, compare=True)  # its imports
times = []
for _ in range(int(sys.argv[2])):
    start = time.perf_counter()
    guard_plan(path, limits, names, scenario, verify=True, compare=True)
    times.append(time.perf_counter() - start)
print(json.dumps(statistics.median(times)))
"""


def timed_plan(source: Path, scene: str, folder: Path) -> tuple[float, float, dict]:
    """One `stitchplan plan configs/SCENE.yaml` process of the code in `source`: wall time,
    CPU time (user + sys of it and the children it waited for) and its summary."""
    summary = folder / "summary.json"
    arguments = ["plan", str(common.REPO_ROOT / "configs" / f"{scene}.yaml"), "--export",
                 str(folder / "trajectory.csv"), "--summary", str(summary), "-q"]
    start = time.perf_counter()
    process = subprocess.Popen([*common.STITCHPLAN, *arguments], cwd=source, stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE, env=common.command_environment(PYTHONPATH=str(source)))
    stderr = process.stderr.read()
    _, status, usage = os.wait4(process.pid, 0)
    wall = time.perf_counter() - start
    process.returncode = os.waitstatus_to_exitcode(status)
    if process.returncode != 0:
        raise SystemExit(common.failure_line(f"stitchplan plan {scene}", source,
                                             subprocess.CompletedProcess(arguments, process.returncode, b"", stderr)))
    return wall, usage.ru_utime + usage.ru_stime, json.loads(summary.read_text())


def whole_commands(baseline: Path, folders: tuple[Path, Path]) -> list[list]:
    rows = []
    for scene in SCENES:
        walls, cpus, same = ([], []), ([], []), True
        for _ in range(REPEATS):
            records = []
            for side, (source, folder) in enumerate(((baseline, folders[0]), (common.REPO_ROOT, folders[1]))):
                wall, cpu, record = timed_plan(source, scene, folder)
                walls[side].append(wall)
                cpus[side].append(cpu)
                records.append(record)
            same &= all(records[0].get(key) == records[1].get(key) for key in COMPARED)
            same &= (folders[0] / "trajectory.csv").read_bytes() == (folders[1] / "trajectory.csv").read_bytes()
        wall_before, wall_now = statistics.median(walls[0]), statistics.median(walls[1])
        cpu_before, cpu_now = statistics.median(cpus[0]), statistics.median(cpus[1])
        won = sum(b > n for b, n in zip(*walls))
        rows.append([scene, round(wall_before, 3), round(wall_now, 3), round(wall_now / wall_before, 3),
                     round(cpu_before, 3), round(cpu_now, 3), round(cpu_now / cpu_before, 3), f"{won} of {REPEATS}",
                     "yes" if same else "no"])
        print(rows[-1], flush=True)
    return rows


def guard_alone(baseline: Path) -> list[list]:
    rows = []
    for scene in SCENES:
        medians = ([], [])
        for _ in range(GUARD_ROUNDS):
            for side, source in enumerate((baseline, common.REPO_ROOT)):
                done = subprocess.run([common.STITCHPLAN[0], "-c", GUARD_SCRIPT,
                                       str(common.REPO_ROOT / "configs" / f"{scene}.yaml"), str(GUARD_CALLS)],
                                      cwd=source, capture_output=True, text=True,
                                      env=common.command_environment(PYTHONPATH=str(source)))
                if done.returncode != 0:
                    raise SystemExit(common.failure_line(f"guard_plan {scene}", source, done))
                medians[side].append(json.loads(done.stdout))
        before, now = statistics.median(medians[0]), statistics.median(medians[1])
        rows.append([scene, round(before, 4), round(now, 4), round(before - now, 4), round(now / before, 3)])
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    common.command_line(__doc__)
    with common.against(BASELINE) as (baseline, folders):
        guard = guard_alone(baseline)
        whole = whole_commands(baseline, folders)
    whole_columns = ["scene", "wall before (s)", "wall now (s)", "wall ratio", "CPU before (s)", "CPU now (s)",
                     "CPU ratio", "pairs won now (wall)", "same trajectories and exit errors"]
    guard_columns = ["scene", "guard before (s)", "guard now (s)", "saved (s)", "ratio"]
    common.RESULTS_DIR.mkdir(exist_ok=True)
    with open(common.RESULTS_DIR / "plan_pairs.csv", "w") as out:
        out.write("part," + ",".join(whole_columns) + "\n")
        out.writelines("whole," + ",".join(map(str, row)) + "\n" for row in whole)
        out.write("part," + ",".join(guard_columns) + "\n")
        out.writelines("guard," + ",".join(map(str, row)) + "\n" for row in guard)

    def table(columns, rows) -> str:
        lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
        return "\n".join(lines + ["| " + " | ".join(map(str, row)) + " |" for row in rows])

    text = (f"# plan before ({BASELINE}) and now\n\n`python benchmarks/plan_pairs.py`, "
            f"{time.strftime('%Y-%m-%d %H:%M')}; load average {os.getloadavg()[0]:.1f} at the end.\n\n"
            f"Whole `plan CONFIG` (comparison and verification), medians of {REPEATS}, alternating:\n\n"
            f"{table(whole_columns, whole)}\n\nThe resource guard alone (median of {GUARD_CALLS} calls, "
            f"median of {GUARD_ROUNDS} rounds alternating):\n\n{table(guard_columns, guard)}\n")
    (common.RESULTS_DIR / "plan_pairs.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
