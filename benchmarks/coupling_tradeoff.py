"""Speed against coupling convergence on the shipped needle scenes: the shipped
discretization beside the one whose unplanned exit error converges monotonically.

The converged configuration (README, "The model"; benchmarks/results/needle_coupling.md,
rows `fixed`) sets four scenario keys: the cutting force ramped in with the cutting edge
inside (`needle.cutting_ramp: true`), the kernel support 3 spacings (`discretization.dilation:
3`), the multiplier elements' least length fixed in mm (`needle.multiplier_length`, the
default level's needle spacing) and, on the SH 1/2 blocks, a quarter of the spacing at the
needle (`discretization.needle_refinement: 4`, a needle spacing of 1.25 needle steps; the 20
mm needle scenes' default already is). Per scene and configuration:

- accuracy: the unplanned exit error's change from the default spacing to half of it, whether
  the three levels h, h/sqrt(2), h/2 are monotone, and their observed rate, read from
  results/needle_coupling.csv (rows `mortar` and RECIPES'; run benchmarks/needle_coupling.py
  with those couplings where rows are missing);
- speed: the planned run (the summary's `wall_seconds` of `stitchplan plan CONFIG --no-compare
  --no-verify`, the converged configuration's CONFIG a copy of the shipped file with the four
  keys) and its speed-up over the planned run at BASELINE (`plan CONFIG --no-compare`, the code
  before the speed work, extracted with `git archive`, as benchmarks/plan_speed.py times it),
  REPEATS runs each, alternating the three;
- the same speed-up like for like: BASELINE's planned run on the converged configuration's
  particles (a copy of the converged file without `needle.cutting_ramp` and
  `needle.multiplier_length`, which BASELINE does not have: it runs the same discretization
  with the whole cutting force from the first step and multiplier elements refined with the
  particles), SAME_REPEATS runs, checked to have the converged run's particle count. It
  separates what the code gained from what the converged discretization costs.

Writes benchmarks/results/coupling_tradeoff.{csv,md,png}; about 15 minutes (`--report` only
rewrites the CSV, the table and the chart: the timings as they are, the accuracy columns
again from results/needle_coupling.csv). Run from the repository root:
    python benchmarks/coupling_tradeoff.py
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import _common as common  # noqa: E402
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.ticker import FixedLocator, FuncFormatter, NullFormatter  # noqa: E402
import needle_coupling  # noqa: E402
import plan_speed  # noqa: E402
import yaml  # noqa: E402

from stitchplan.config.scenario import load_scenario  # noqa: E402
from stitchplan.config.yaml_files import read_yaml  # noqa: E402

BASELINE = plan_speed.BASELINE
SHIPPED = "mortar"
RECIPES = {"sh12": "mortar ramp r=4 fixed d=3", "needle20": "mortar ramp fixed d=3"}
REPEATS = 5
SAME_REPEATS = 3  # BASELINE on the converged particles: 1-30 s a run
BASELINE_LACKS = ("cutting_ramp", "multiplier_length")  # needle keys BASELINE's scenarios do not have
SPEEDUP_TARGET = 4.0  # the planned run's goal against BASELINE (README, Planner speed)
CHANGE_TARGET = 0.02  # the coupling's goal: the change from the default to half the spacing
FIELDS = ("scene", "configuration", "coupling", "particles", "passes", "baseline_planned_s", "planned_s", "speedup",
          "cost", "change", "monotone", "rate", "planned_exit_error_mm", "baseline_same_s", "speedup_same")


def recipe(scene: str) -> str:
    return RECIPES[scene.split("_")[0]]


def converged_config(scene: str, folder: Path) -> Path:
    """configs/SCENE.yaml as it was until 2026-12-05 with the converged configuration's four
    keys, written into `folder`; checked to load as the scenario needle_coupling.scene runs."""
    expected = needle_coupling.scene(scene, recipe(scene))
    data = common.previous_data(common.REPO_ROOT / "configs" / f"{scene}.yaml")
    discretization = data.setdefault("discretization", {})
    discretization["dilation"] = expected.discretization.dilation
    discretization["needle_refinement"] = expected.discretization.needle_refinement
    data["needle"].update(cutting_ramp=True, multiplier_length=expected.needle.multiplier_length)
    path = folder / f"{scene}_converged.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    loaded = load_scenario(path)
    if (loaded.discretization, loaded.needle) != (expected.discretization, expected.needle):
        raise SystemExit(f"{path}: does not load as needle_coupling.scene({scene!r}, {recipe(scene)!r})")
    return path


def baseline_config(converged: Path) -> Path:
    """The converged configuration as BASELINE can read it: the same discretization, without
    the needle keys it does not have (BASELINE_LACKS)."""
    data, _ = read_yaml(converged)
    for key in BASELINE_LACKS:
        data["needle"].pop(key, None)
    path = converged.with_name(converged.stem + "_baseline.yaml")
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def planned_run(config: Path, options: list[str], folder: Path, source: Path) -> dict:
    """The summary of one `stitchplan plan CONFIG OPTIONS` process of the code in `source`."""
    return common.config_command("plan", config, options, folder, source, PYTHONPATH=str(source))[1]


def convergence_of(scene: str, coupling: str, table: dict) -> dict:
    """change, monotone and rate of the unplanned exit error over h, h/sqrt(2), h/2 (`table`:
    convergence_table)."""
    entry = table.get((scene, coupling))
    if entry is None or entry["change"] is None:
        raise SystemExit(f"results/needle_coupling.csv has no three levels of {scene} with "
                         f"'{coupling}': python benchmarks/needle_coupling.py --scenes {scene} "
                         f"--couplings '{coupling}'")
    return {"change": entry["change"], "monotone": bool(entry["monotone"]), "rate": entry["rate"]}


def convergence_table() -> dict:
    """results/needle_coupling.csv summarised by (scene, coupling)."""
    return {(entry["scene"], entry["coupling"]): entry
            for entry in needle_coupling.summarise(needle_coupling.read_rows(
                common.results_path("needle_coupling.csv")))}


def measure(scenes: tuple[str, ...]) -> list[dict]:
    convergence = convergence_table()
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch)
        (folder / "baseline").mkdir()
        baseline = common.extract_revision(BASELINE, folder / "baseline", "stitchplan")
        for scene in scenes:
            shipped = common.previous_config(scene, folder)  # the file as shipped until 2026-12-05
            configurations = {"shipped": (shipped, SHIPPED),
                              "converged": (converged_config(scene, folder), recipe(scene))}
            before, after = [], {name: [] for name in configurations}
            for _ in range(REPEATS):
                before.append(planned_run(shipped, ["--no-compare"], folder, baseline)["wall_seconds"])
                for name, (config, _) in configurations.items():
                    after[name].append(planned_run(config, ["--no-compare", "--no-verify", "-q"], folder,
                                                   common.REPO_ROOT))
            same_config = baseline_config(configurations["converged"][0])
            same = [planned_run(same_config, ["--no-compare"], folder, baseline) for _ in range(SAME_REPEATS)]
            if same[-1]["particles"] != after["converged"][-1]["particles"]:
                raise SystemExit(f"{scene}: {BASELINE} built {same[-1]['particles']} particles from "
                                 f"{same_config.name}, the converged run {after['converged'][-1]['particles']}")
            baseline_s = statistics.median(before)
            baseline_same = {"shipped": baseline_s,
                             "converged": statistics.median(record["wall_seconds"] for record in same)}
            planned = {name: statistics.median(record["wall_seconds"] for record in records)
                       for name, records in after.items()}
            for name, (_, coupling) in configurations.items():
                accuracy = convergence_of(scene, coupling, convergence)
                last = after[name][-1]
                row = {"scene": scene, "configuration": name, "coupling": coupling,
                       "particles": last["particles"], "passes": len(last["planner_passes"]),
                       "baseline_planned_s": baseline_s, "planned_s": planned[name],
                       "speedup": baseline_s / planned[name], "cost": planned[name] / planned["shipped"],
                       **accuracy,
                       "planned_exit_error_mm": last["exit_error_mm"], "baseline_same_s": baseline_same[name],
                       "speedup_same": baseline_same[name] / planned[name]}
                rows.append(row)
                print(f"{scene} {name}: {row['particles']} particles, {row['passes']} pass(es), planned run "
                      f"{planned[name]:.3f} s ({row['speedup']:.1f}x {BASELINE}'s {baseline_s:.3f} s, "
                      f"{row['speedup_same']:.1f}x on the same particles), change "
                      f"{100 * row['change']:+.2f} %{', monotone' if row['monotone'] else ''}", flush=True)
    return rows


def chart(rows: list[dict], path: Path) -> None:
    figure, axes = plt.subplots(figsize=(8.5, 5.5))
    styles = {"shipped": ("tab:blue", "o"), "converged": ("tab:red", "s")}
    for name, (colour, marker) in styles.items():
        chosen = [row for row in rows if row["configuration"] == name]
        for monotone in (True, False):
            part = [row for row in chosen if row["monotone"] == monotone]
            axes.scatter([row["speedup"] for row in part], [100 * abs(row["change"]) for row in part],
                         marker=marker, s=55, color=colour if monotone else "white", edgecolors=colour,
                         label=f"{name} discretization, {'monotone' if monotone else 'not monotone'}")
        for number, row in enumerate(chosen):  # labels above and below in turn: neighbours overlap less
            axes.annotate(row["scene"].replace("needle20_", "n20_"), (row["speedup"], 100 * abs(row["change"])),
                          fontsize=7, xytext=(4, 3 if number % 2 == 0 else -10), textcoords="offset points",
                          color=colour)
    converged = [row for row in rows if row["configuration"] == "converged"]
    for row in converged:  # the same rows against BASELINE on their own particles
        axes.plot([row["speedup"], row["speedup_same"]], [100 * abs(row["change"])] * 2, color="tab:red",
                  linewidth=0.6, alpha=0.5)
    axes.scatter([row["speedup_same"] for row in converged], [100 * abs(row["change"]) for row in converged],
                 marker=">", s=40, color="tab:red", alpha=0.6,
                 label=f"converged discretization against {BASELINE} on the same particles")
    axes.axvline(SPEEDUP_TARGET, color="grey", linestyle="--", linewidth=1)
    axes.axhline(100 * CHANGE_TARGET, color="grey", linestyle=":", linewidth=1)
    axes.set_xscale("log")
    axes.xaxis.set_major_locator(FixedLocator([1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 24.0, 32.0]))
    axes.xaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}x"))
    axes.xaxis.set_minor_formatter(NullFormatter())
    axes.set_xlabel(f"planned run: speed-up over {BASELINE} (plan --no-compare --no-verify)")
    axes.set_ylabel("|exit error change| from h to h/2 (%), unplanned")
    axes.set_title("Shipped needle scenes: speed against coupling convergence\n"
                   f"targets: >= {SPEEDUP_TARGET:g}x (dashed) and < {100 * CHANGE_TARGET:g} %, monotone (dotted)",
                   fontsize=10)
    axes.grid(True, which="both", alpha=0.3)
    axes.legend(fontsize=8, loc="upper left")
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def report(rows: list[dict], redrawn: bool = False) -> list[str]:
    both = [row for row in rows if row["speedup"] >= SPEEDUP_TARGET and abs(row["change"]) < CHANGE_TARGET
            and row["monotone"]]
    alike = [row for row in rows if row["speedup_same"] >= SPEEDUP_TARGET and abs(row["change"]) < CHANGE_TARGET
             and row["monotone"]]
    table = [(row["scene"], row["configuration"], row["particles"], row["passes"], row["baseline_planned_s"],
              row["planned_s"], f"{row['speedup']:.2f}x", f"{row['cost']:.2f}", f"{100 * row['change']:+.2f} %",
              "yes" if row["monotone"] else "no", "—" if row["rate"] is None else f"{row['rate']:.1f}",
              row["planned_exit_error_mm"], row["baseline_same_s"], f"{row['speedup_same']:.2f}x") for row in rows]
    return [
        "# Speed against coupling convergence on the shipped needle scenes", "",
        (f"Redrawn by `python benchmarks/coupling_tradeoff.py --report` from results/coupling_tradeoff.csv "
         f"({time.strftime('%Y-%m-%d %H:%M')}); the timings are the CSV's, change, monotone and rate "
         "results/needle_coupling.csv's now." if redrawn else
         f"Generated by `python benchmarks/coupling_tradeoff.py` ({common.machine_note()})."), "",
        "shipped: the scene's file as shipped until 2026-12-05 (coupling `mortar`; since then the SH 1/2 "
        "and 20 mm needle files carry a discretization of their own: needle_coupling.md, coupling `shipped`, "
        "and plan_speed.md); converged: the same file with "
        "`needle.cutting_ramp: true`, `needle.multiplier_length` (the default level's needle spacing, mm), "
        "`discretization.dilation: 3` and, on the SH 1/2 blocks, `discretization.needle_refinement: 4` "
        f"(needle_coupling.py couplings {', '.join(repr(value) for value in RECIPES.values())}). "
        f"Planned run: the summary's `wall_seconds` of `plan CONFIG --no-compare --no-verify`, median of "
        f"{REPEATS}, alternating with {BASELINE}'s `plan CONFIG --no-compare` of the shipped file; cost: the "
        "planned run against the shipped discretization's in the same run. Change, "
        "monotone and rate: the unplanned exit error at h, h/sqrt(2), h/2, from results/needle_coupling.csv. "
        f"On these particles: {BASELINE}'s `plan CONFIG --no-compare` of the converged file without "
        f"{' and '.join(f'`needle.{key}`' for key in BASELINE_LACKS)} (keys it does not have), median of "
        f"{SAME_REPEATS}, the same particles (checked): the speed-up of the code on the same discretization.", "",
        common.markdown_table(("scene", "discretization", "particles", "planner passes",
                               f"planned run {BASELINE} (s)", "planned run now (s)", "speed-up", "cost (x shipped)",
                               "change h to h/2", "monotone", "rate", "planned exit error (mm)",
                               f"{BASELINE} on these particles (s)", "speed-up on these particles"), table), "",
        f"Both targets (>= {SPEEDUP_TARGET:g}x, < {100 * CHANGE_TARGET:g} % and monotone) on "
        f"{len(both)} of {len(rows)} rows"
        + (": " + ", ".join(f"{row['scene']} ({row['configuration']})" for row in both) if both else "") + ".",
        "", f"With the speed-up on the same particles instead (the code's gain, the discretization's cost "
        f"set aside): {len(alike)} of {len(rows)} rows"
        + (": " + ", ".join(f"{row['scene']} ({row['configuration']})" for row in alike) if alike else "") + ".",
        "", "![speed against convergence](coupling_tradeoff.png)", ""]


def read_rows() -> list[dict]:
    """The rows of results/coupling_tradeoff.csv, typed as measure returns them."""
    rows = []
    for row in needle_coupling.read_rows(common.results_path("coupling_tradeoff.csv")):
        typed = dict(row)
        for field in ("baseline_planned_s", "planned_s", "speedup", "cost", "change", "planned_exit_error_mm",
                      "baseline_same_s", "speedup_same"):
            typed[field] = float(row[field])
        typed["particles"], typed["passes"] = int(row["particles"]), int(row["passes"])
        typed["monotone"] = row["monotone"] == "True"
        typed["rate"] = float(row["rate"]) if row["rate"] else None
        rows.append(typed)
    return rows


def main() -> None:
    if "--report" in common.command_line(__doc__, ("--report",)):  # the table and the chart again from the CSV, the accuracy
        convergence = convergence_table()  # columns from results/needle_coupling.csv as it is now
        rows = [{**row, **convergence_of(row["scene"], row["coupling"], convergence)} for row in read_rows()]
        common.write_csv(common.results_path("coupling_tradeoff.csv"), FIELDS,
                         [[row[field] for field in FIELDS] for row in rows])
        chart(rows, common.results_path("coupling_tradeoff.png"))
        common.write_report("coupling_tradeoff.md", report(rows, redrawn=True))
        return
    rows = measure(needle_coupling.SHIPPED)
    common.write_csv(common.results_path("coupling_tradeoff.csv"), FIELDS,
                     [[row[field] for field in FIELDS] for row in rows])
    chart(rows, common.results_path("coupling_tradeoff.png"))
    common.write_report("coupling_tradeoff.md", report(rows))


if __name__ == "__main__":
    main()
