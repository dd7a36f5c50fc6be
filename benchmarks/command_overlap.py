"""What `plan` does while its replay helper works: before (BASELINE) and now.

A verified plan's longest path is its helper's: the helper builds the refined model, then
replays the trajectory on it while the command plans, and the command waits for the end of
that replay before it writes. Three changes move work off that path:

1. The helper is handed its model as soon as the command has checked its inputs and passed
   the resource guard, before the command imports the numerics (stitchplan/early_helper.py
   `hand`; planning/replay_models.py and needle/track_layout.py hold what the guard needs
   without them). BASELINE handed it over when the replays started, after those imports.
2. While the command waits for the replay, it imports what writing its outputs needs (h5py
   for --out, matplotlib for --plot: io.reports.prepare_plan_outputs); BASELINE imported
   them after the replay.
3. plan.png is laid out from the axes' tight boxes without first drawing the whole figure
   twice (io.plot_elements title_above and legend_below), and cropped to its tight box
   measured without savefig's own layout draw (io.plots.save); the PNG is the same byte for
   byte.

Part 1: whole `stitchplan plan` processes, the code of BASELINE and this code alternating,
REPEATS times each: medians, ratio (now over before), pairs won, and whether every pair's
trajectory, summary (planned, verified and estimated exit errors) and PNG agree byte for byte.
Part 2: plan.png of three verified plans drawn in this process the BASELINE way (a full draw
before the title and before the legend, savefig's bbox_inches="tight") and now, alternating,
median of DRAWS, and whether the PNGs agree byte for byte.

Writes benchmarks/results/command_overlap.{csv,md} and prints the tables. About 6 minutes.
Run from the repository root:  python benchmarks/command_overlap.py
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import _common as common  # noqa: E402

BASELINE = "014623d"  # the helper handed its model when the replays start; outputs' imports after the replay
REPEATS = int(os.environ.get("OVERLAP_REPEATS", 7))
DRAWS = 5
COMPARED = ("exit_error_mm", "verified_exit_error_mm", "exit_error_estimate_mm")
COMMANDS = (  # (scene, label, options besides --export and --summary)
    ("sh12_100x100", "plan --no-compare", ["--no-compare"]),
    ("sh12_100x100", "plan --no-compare --out run.h5", ["--no-compare", "--out", "{folder}/run.h5"]),
    ("sh12_100x100", "plan --no-compare --plot plan.png", ["--no-compare", "--plot", "{folder}/plan.png"]),
    ("sh12_100x100", "plan --plot plan.png (README's first command)", ["--plot", "{folder}/plan.png"]),
    ("needle20_entry30", "plan --no-compare", ["--no-compare"]),
)
DRAWN = (("sh12_100x100", False), ("sh12_100x30", True), ("wound_closure", True))


def whole_commands() -> list[list]:
    rows = []
    with common.against(BASELINE) as (baseline, folders):
        for scene, label, options in COMMANDS:
            seconds = {"before": [], "now": []}
            same = True
            for _ in range(REPEATS):
                outputs = {}
                for key, source, folder in (("before", baseline, folders[0]), ("now", common.REPO_ROOT, folders[1])):
                    given = [option.format(folder=folder) for option in options]
                    wall, summary = common.scene_command("plan", scene, given, folder, source)
                    seconds[key].append(wall)
                    outputs[key] = ([summary.get(name) for name in COMPARED], (folder / "trajectory.csv").read_bytes(),
                                    (folder / "plan.png").read_bytes() if "--plot" in options else b"")
                same &= outputs["before"] == outputs["now"]
            before, now = statistics.median(seconds["before"]), statistics.median(seconds["now"])
            won = sum(b > n for b, n in zip(seconds["before"], seconds["now"]))
            rows.append([scene, label, before, now, now / before, f"{won} of {REPEATS}", "yes" if same else "no"])
            print(rows[-1], flush=True)
    return rows


def drawn_plots() -> list[list]:
    """plan.png of verified plans drawn the BASELINE way and now, in this process."""
    import io

    import matplotlib.pyplot as plt

    from stitchplan.config.scenario import load_scenario
    from stitchplan.io import needle_plots, plot_elements, plots
    from stitchplan.io.files import write_bytes
    from stitchplan.planning.verification import plan_verified

    def drawn_first(place):  # BASELINE: the whole figure drawn before the boxes are measured
        def placed(fig, *args, **kwargs):
            fig.canvas.draw()
            return place(fig, *args, **kwargs)
        return placed

    def saved_tight(fig, path):  # BASELINE: savefig measures the tight box after a layout draw of its own
        buffer = io.BytesIO()
        try:
            fig.savefig(buffer, dpi=plots.SAVED_DPI, bbox_inches="tight", format="png")
        finally:
            plt.close(fig)
        write_bytes(path, buffer.getbuffer())

    ways = {"before": (drawn_first(plot_elements.title_above), drawn_first(plot_elements.legend_below), saved_tight),
            "now": (plot_elements.title_above, plot_elements.legend_below, plots.save)}
    rows = []
    try:
        with tempfile.TemporaryDirectory() as scratch:
            for scene, compare in DRAWN:
                plan = plan_verified(load_scenario(common.REPO_ROOT / "configs" / f"{scene}.yaml"), compare=compare)
                seconds, images = {"before": [], "now": []}, {}
                for round_ in range(DRAWS):
                    for way in (("before", "now") if round_ % 2 == 0 else ("now", "before")):
                        needle_plots.title_above, needle_plots.legend_below, needle_plots.save = ways[way]
                        path = Path(scratch) / f"{way}.png"
                        start = time.perf_counter()
                        needle_plots.plot_plan(path, plan)
                        seconds[way].append(time.perf_counter() - start)
                        images[way] = path.read_bytes()
                before, now = statistics.median(seconds["before"]), statistics.median(seconds["now"])
                rows.append([scene, "yes" if compare else "no", before, now, now / before,
                             "yes" if images["before"] == images["now"] else "no"])
                print(rows[-1], flush=True)
    finally:
        needle_plots.title_above, needle_plots.legend_below, needle_plots.save = ways["now"]
    return rows


def main() -> None:
    commands = whole_commands()
    plots = drawn_plots()
    common.write_csv(common.results_path("command_overlap.csv"),
                     common.ALTERNATED_COLUMNS,
                     [["command", scene, label, *rest] for scene, label, *rest in commands]
                     + [["plan.png", scene, f"unplanned run drawn: {compare}", before, now, ratio, "", same]
                        for scene, compare, before, now, ratio, same in plots])
    common.write_report("command_overlap.md", [
        "# What `plan` does while its replay helper works",
        "",
        f"Generated by `python benchmarks/command_overlap.py` ({common.machine_note()}). Before: the code of "
        f"{BASELINE} (the helper handed its model when the replays start, after the command's imports of the "
        "numerics; the outputs' libraries imported after the replay; plan.png laid out after two full draws "
        "and cropped by savefig's bbox_inches=\"tight\"). "
        "Now: the helper handed its model once the inputs are checked and the resource guard has passed; h5py "
        "and matplotlib imported while the command waits for the replay; plan.png laid out from the axes' tight "
        "boxes and cropped to its own measured without savefig's layout draw (benchmarks/command_overlap.py says "
        "where each lives).",
        "",
        f"## Whole commands (process wall time, median of {REPEATS}, the two codes alternating)",
        "",
        "Every command with `--export trajectory.csv --summary summary.json`. Same: every pair's trajectory, "
        f"summary ({', '.join(COMPARED)}) and plan.png byte for byte.",
        "",
        common.markdown_table(["scene", "command", f"{BASELINE} (s)", "now (s)", "ratio", "pairs won now", "same"],
                              commands),
        "",
        f"## plan.png drawn in process (median of {DRAWS}, alternating)",
        "",
        common.markdown_table(["scene", "unplanned run drawn", f"{BASELINE} way (s)", "now (s)", "ratio",
                               "same PNG"], plots),
    ])


if __name__ == "__main__":
    common.command_line(__doc__)
    main()
