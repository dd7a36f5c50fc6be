"""Python's cyclic garbage collector during a command's imports: before (BASELINE) and now.

A command imports numpy, scipy, pydantic with the scenario's classes, typer and the package
before its run, and its replay helper imports the numerics again; the objects those imports
make live as long as the process. With the collector on, it runs every few hundred
allocations and its older generations' passes visit everything made so far, again and again
as the imports go on. Now the collector is off from the command's start to the end of its
imports, which then freeze what exists (gc.freeze: left out of every later collection) and
turn it on again (stitchplan/allocator.py `pause_collection`, `resume_collection`); the
helper, forked while it is off, does the same after its own imports.

Part 1: whole `stitchplan` processes, the code of BASELINE and this code alternating,
REPEATS times each: medians, ratio (now over before), pairs won, and whether every pair's
summaries (and trajectories) agree. Part 2: what the `plan` command imports, in fresh
processes of this code (alternating, IMPORTS times each): with the collector on as Python
starts it, and paused as the command pauses it; with the collections the collector made and
the objects it tracks once they are done.

Writes benchmarks/results/import_collection.{csv,md} and prints the tables. About 5 minutes.
Run from the repository root:  python benchmarks/import_collection.py
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import json  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402

import _common as common  # noqa: E402

BASELINE = "00c3596"  # the collector on throughout
REPEATS = int(os.environ.get("COLLECTION_REPEATS", 9))
IMPORTS = 9
COMPARED = ("exit_error_mm", "verified_exit_error_mm", "exit_error_estimate_mm", "steps")
COMMANDS = (  # (command, scene, label, options besides --export and --summary)
    ("plan", "sh12_100x100", "plan --no-compare", ["--no-compare"]),
    ("plan", "sh12_100x100", "plan --no-compare --no-verify", ["--no-compare", "--no-verify"]),
    ("plan", "sh12_100x100", "plan --plot plan.png (README's first command)", ["--plot", "{folder}/plan.png"]),
    ("plan", "needle20_entry30", "plan --no-compare", ["--no-compare"]),
    ("simulate", "sh12_100x100", "simulate", []),
    ("simulate", "needle20_entry30", "simulate", []),
    ("deform", "slab_edge_load", "deform", []),
)
# what `plan` imports before its run (cli/commands.py), measured in a fresh process
IMPORT_SCRIPT = """
import gc, json, sys, time
paused = sys.argv[1] == "paused"
if paused:
    gc.disable()
start = time.perf_counter()
import stitchplan.cli.commands, stitchplan.config, stitchplan.io.reports, stitchplan.planning.verification
import stitchplan.study.auto
seconds = time.perf_counter() - start
print(json.dumps({"seconds": seconds, "collections": [generation["collections"] for generation in gc.get_stats()],
                  "tracked": len(gc.get_objects())}))
"""


def whole_commands() -> list[list]:
    rows = []
    with common.against(BASELINE) as (baseline, folders):
        for name, scene, label, options in COMMANDS:
            seconds = {"before": [], "now": []}
            same = True
            for _ in range(REPEATS):
                outputs = {}
                for key, source, folder in (("before", baseline, folders[0]), ("now", common.REPO_ROOT, folders[1])):
                    given = [option.format(folder=folder) for option in options]
                    wall, summary = common.scene_command(name, scene, given, folder, source)
                    seconds[key].append(wall)
                    trajectory = (folder / "trajectory.csv").read_bytes() if name == "plan" else b""
                    outputs[key] = ([summary.get(key) for key in COMPARED], trajectory)
                same &= outputs["before"] == outputs["now"]
            before, now = statistics.median(seconds["before"]), statistics.median(seconds["now"])
            won = sum(b > n for b, n in zip(seconds["before"], seconds["now"]))
            rows.append([scene, label, before, now, now / before, f"{won} of {REPEATS}", "yes" if same else "no"])
            print(rows[-1], flush=True)
    return rows


def imports() -> list[list]:
    records: dict[str, list[dict]] = {"on": [], "paused": []}
    environment = {**os.environ, "PYTHONPATH": str(common.REPO_ROOT)}
    for round_ in range(IMPORTS):
        for way in (("on", "paused") if round_ % 2 == 0 else ("paused", "on")):
            output = subprocess.run([sys.executable, "-c", IMPORT_SCRIPT, way], check=True, capture_output=True,
                                    text=True, env=environment, cwd=common.REPO_ROOT)
            records[way].append(json.loads(output.stdout.strip().splitlines()[-1]))
    rows = []
    for way, label in (("on", "collector on"), ("paused", "collector off (as the command pauses it)")):
        last = records[way][-1]
        rows.append([label, statistics.median(record["seconds"] for record in records[way]),
                     *last["collections"], last["tracked"]])
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    commands = whole_commands()
    imported = imports()
    common.write_csv(common.results_path("import_collection.csv"),
                     ["part", "scene", "what", "before (s)", "now (s)", "ratio", "pairs won now", "same"],
                     [["command", *row] for row in commands]
                     + [["plan's imports", "", label, "", seconds, "", "", ""]
                        for label, seconds, *_ in imported])
    common.write_report("import_collection.md", [
        "# The cyclic garbage collector during a command's imports",
        "",
        f"Generated by `python benchmarks/import_collection.py` ({common.machine_note()}). Before: the code of "
        f"{BASELINE} (the collector on throughout). Now: off from the command's start to the end of its imports, "
        "which freeze what exists and turn it on again; the replay helper likewise after its own imports "
        "(stitchplan/allocator.py).",
        "",
        f"## Whole commands (process wall time, median of {REPEATS}, the two codes alternating)",
        "",
        "Every command with `--summary summary.json` (plan with `--export trajectory.csv`). Same: every pair's "
        f"summary ({', '.join(COMPARED)}) and trajectory byte for byte.",
        "",
        common.markdown_table(["scene", "command", f"{BASELINE} (s)", "now (s)", "ratio", "pairs won now", "same"],
                              commands),
        "",
        f"## What `plan` imports before its run (fresh processes of this code, median of {IMPORTS}, alternating)",
        "",
        "Collections: how many times the collector ran on each generation during the imports; tracked: the "
        "objects it tracks once they are done.",
        "",
        common.markdown_table(["collector", "imports (s)", "generation 0 collections", "generation 1",
                               "generation 2", "tracked objects"], imported),
    ])


if __name__ == "__main__":
    main()
