"""Whole commands with the replays on the second model in a helper process (now), in a
helper forked later (LATE_FORK) and in the command's own process (STITCHPLAN_REPLAY_HELPER=0,
as before the helper), side by side.

`simulate` runs its exit error estimate at 2h; `plan` replays its trajectory at 2h
(`--no-verify`, the estimate) or on the refined model (the default verification, every
round). With the helper (planning/replays.py) those replays run on the machine's second core
while the command's own run goes on: the estimate run from the start, a plan's replay as
each planner pass's centres arrive. Now the command forks the helper as it starts, before
its imports (stitchplan/early_helper.py); at LATE_FORK (the code extracted with `git
archive`) it forked it once it had imported everything and loaded the scenario, sharing
those memory pages with it. For each scene and command: the process wall time and the
command's own run (the summary's `wall_seconds`), the three ways in turn REPEATS times
(median, each round from another way on), and whether the summaries agree (exit error,
estimate and verified exit error, to the last bit).

Writes benchmarks/results/replay_helper.{csv,md} and prints the table. About 5 minutes.
Run from the repository root:  python benchmarks/replay_helper.py
"""

from __future__ import annotations

import os

# single-threaded BLAS, as the `stitchplan` command sets it
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import resource  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import _common as common  # noqa: E402

SCENES = ("sh12_100x100", "sh12_100x30", "needle20_entry30", "needle20_entry18", "hole_near_stitch",
          "wound_closure")
COMMANDS = (("simulate", []), ("plan --no-compare --no-verify", ["--no-compare", "--no-verify"]),
            ("plan (default: compare, verify)", []))
REPEATS = int(os.environ.get("REPLAY_HELPER_REPEATS", 3))
COMPARED = ("exit_error_mm", "exit_error_estimate_mm", "verified_exit_error_mm", "unplanned_exit_error_mm")
LATE_FORK = "b1fc7f2"  # the last commit whose helper was forked once the command had imported everything
WAYS = ("here", "late", "now")


def run(command: str, options: list[str], scene: str, folder: Path, way: str, late: Path) -> tuple[float, dict, float]:
    """One process the `way` given: its wall time, summary and CPU time (its own and its
    helper's, which it waits for)."""
    source = late if way == "late" else common.REPO_ROOT
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    seconds, summary = common.scene_command(command.split()[0], scene, [*options, "-q"], folder, source,
                                            PYTHONPATH=str(source),
                                            STITCHPLAN_REPLAY_HELPER="0" if way == "here" else "1")
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return seconds, summary, (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)


def main() -> None:
    rows = []
    with tempfile.TemporaryDirectory() as scratch, tempfile.TemporaryDirectory() as extracted:
        folder, late = Path(scratch), common.extract_revision(LATE_FORK, Path(extracted))
        for way in WAYS:  # each way's modules compiled once (Python's bytecode cache), not in a timed run
            run(*COMMANDS[0], SCENES[0], folder, way, late)
        for scene in SCENES:
            for label, options in COMMANDS:
                times, own, cpu = {way: [] for way in WAYS}, {way: [] for way in WAYS}, {way: [] for way in WAYS}
                summaries = {}
                for repeat in range(REPEATS):
                    for way in WAYS[repeat % 3:] + WAYS[:repeat % 3]:
                        seconds, summaries[way], cpu_seconds = run(label, options, scene, folder, way, late)
                        times[way].append(seconds)
                        cpu[way].append(cpu_seconds)
                        own[way].append(summaries[way]["wall_seconds"])
                same = all(summaries[way].get(key) == summaries["here"].get(key) for key in COMPARED for way in WAYS)
                wall = {way: statistics.median(times[way]) for way in WAYS}
                run_seconds = {way: statistics.median(own[way]) for way in WAYS}
                rows.append((scene, label, wall["here"], wall["late"], wall["now"], wall["here"] / wall["now"],
                             run_seconds["here"], run_seconds["late"], run_seconds["now"],
                             run_seconds["late"] / run_seconds["now"], statistics.median(cpu["late"]),
                             statistics.median(cpu["now"]), "yes" if same else "NO",
                             summaries["now"].get("exit_error_estimate_mm"),
                             summaries["now"].get("verified_exit_error_mm")))
                print(f"{scene} {label}: {wall['here']:.3f} s here, {wall['late']:.3f} s with the helper forked late, "
                      f"{wall['now']:.3f} s now; own run {run_seconds['here']:.4f} / {run_seconds['late']:.4f} / "
                      f"{run_seconds['now']:.4f} s", flush=True)
    header = ["scene", "command", "replays here (s)", f"helper forked late, {LATE_FORK} (s)",
              "helper forked at the start, now (s)", "speed-up now against here",
              "own run, replays here (s)", "own run, helper forked late (s)", "own run, now (s)",
              "own run: late / now", "CPU, helper forked late (s)", "CPU, now (s)", "same summary", "exit error estimate (mm)", "verified exit error (mm)"]
    common.write_csv(common.results_path("replay_helper.csv"), header, rows)
    common.write_report("replay_helper.md", [
        "# Whole commands with the replays in a helper process, forked early and late",
        "",
        f"Generated by `python benchmarks/replay_helper.py` ({common.machine_note()}).",
        "",
        f"Process wall time, median of {REPEATS}, the three ways in turn. *Replays here*: "
        "STITCHPLAN_REPLAY_HELPER=0, the estimate's run and the verification's replays after the "
        "command's own run, in its process (as before the helper). *Helper forked late*: the code at "
        f"{LATE_FORK}, whose helper was forked once the command had imported everything and loaded the "
        "scenario: it shared those memory pages with the command's process, which paid a copy-on-write "
        "page fault for each of them it then wrote (CPython's reference counts and bytecode caches "
        "write to most objects a run touches). *Now*: the helper forked as the command starts, before "
        "its imports (stitchplan/early_helper.py); each process imports its own. *Same summary*: "
        f"{', '.join(COMPARED)} equal to the last bit across the three. *Own run*: the summary's "
        "`wall_seconds` (simulate: its run; plan: the planned runs of every pass and round, the replays "
        "not included), median of the same processes; what the helper still costs it now is the two "
        "processes running at once. *CPU*: user and system time of the command and its helper, median "
        "of the same processes.",
        "",
        common.markdown_table(header, [[common.fmt(value) for value in row] for row in rows]),
    ])


if __name__ == "__main__":
    common.command_line(__doc__)
    main()
