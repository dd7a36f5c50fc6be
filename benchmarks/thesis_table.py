"""The thesis's simulation results beside ours: table 5.1 and figures 5.9-5.10.

For each scene of configs/thesis/ that the thesis gives numbers for, runs the command a user
runs, once, in sequence:

    stitchplan plan CONFIG --export t.csv --summary s.json --no-verify [--spacing H]

at the default discretization and at half its spacing (H = the file's
`discretization.spacing` / 2, as benchmarks/needle_coupling.py halves it; the spacing at the
needle is halved with it). The plan summary carries both the unplanned exit error
(`unplanned_exit_error_mm`, the same scene with the needle centre fixed) and the planned one
(`exit_error_mm`). At a quarter of the spacing only the unplanned exit error is run,
`stitchplan simulate CONFIG --spacing H/2 --no-estimate --summary s.json`: the value the
thesis's numbers are compared with, and a third level for the convergence. A run
that fails is recorded with its message.

Then the thickness sweep: the table 5.1 files with only their thickness changed
(SWEEP_THICKNESSES), each block's unplanned exit error at its spacing h, h/2 and h/4: which
readings of the one parameter the thesis leaves open converge, and how near each comes to
table 5.1.

The thesis's numbers: table 5.1 (exit error before / after planning for the four SH 1/2
blocks) and, for figures 5.9 and 5.10, the distance between the deformed desired exit and
the reported unplanned / planned exits (section 5.1.1, cm converted to mm).

Writes benchmarks/results/thesis_table.{csv,md} and thesis_table_thickness.{csv,png} and prints
the tables (`--chart`: only redraws the png from the csv). About 12 minutes on a shared 2-core
machine. Run from the repository root:  python benchmarks/thesis_table.py
"""

from __future__ import annotations

import os

# single-threaded BLAS, as the `stitchplan` command sets it
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import json  # noqa: E402
import math  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import _common as common  # noqa: E402
import numpy as np  # noqa: E402
from softness_sweep import change as relative_change  # noqa: E402
from softness_sweep import load_ratio  # noqa: E402
from stitchplan.config import Planner  # noqa: E402
from stitchplan.config.scenario import load_scenario  # noqa: E402

THESIS_DIR = common.REPO_ROOT / "configs" / "thesis"


def _distance(a: tuple[float, float], b: tuple[float, float]) -> float:
    return math.hypot(a[0] - b[0], a[1] - b[1])


# section 5.1.1, in mm: desired exit (deformed), unplanned exit, planned exit
_FIG59 = ((17.85, -2.13), (14.37, -3.56), (17.60, -2.15))
_FIG510 = ((-1.70, 80.93), (-3.52, 85.09), (-1.94, 81.22))

# (config, what the thesis reports it as, thesis unplanned mm, thesis planned mm)
SCENES = (
    ("table51_100x100", "table 5.1, 10cm x 10cm", 1.89, 0.01),
    ("table51_100x50", "table 5.1, 5cm x 10cm", 3.0, 0.05),
    ("table51_100x40", "table 5.1, 4cm x 10cm", 3.58, 0.02),
    ("table51_100x30", "table 5.1, 3cm x 10cm", 4.35, 0.01),
    ("needle20_entry30", "figure 5.9", _distance(_FIG59[0], _FIG59[1]), _distance(_FIG59[0], _FIG59[2])),
    ("needle20_fig510", "figure 5.10", _distance(_FIG510[0], _FIG510[1]),
     _distance(_FIG510[0], _FIG510[2])),
)


def run_scene(config: Path, workdir: Path, spacing: float | None, simulate: bool = False) -> dict:
    """One `stitchplan plan --no-verify` run (with `simulate`: `stitchplan simulate
    --no-estimate`, the unplanned run only); its summary, or {"error": message}."""
    summary = workdir / "summary.json"
    summary.unlink(missing_ok=True)
    command = [sys.executable, "-m", "stitchplan", "plan", str(config), "--export",
               str(workdir / "trajectory.csv"), "--summary", str(summary), "--no-verify"]
    if simulate:
        command = [sys.executable, "-m", "stitchplan", "simulate", str(config), "--summary", str(summary),
                   "--no-estimate"]
    if spacing is not None:
        command += ["--spacing", repr(spacing)]
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0 or not summary.exists():
        lines = (done.stderr or done.stdout).strip().splitlines()
        return {"error": lines[-1] if lines else f"exit code {done.returncode}"}
    return json.loads(summary.read_text())


def _planner_note(summary: dict) -> str:
    """Where the move limits held the centre back, where the thesis's plain centre update
    would stall (eq. 4.2 fails: moving the centre moves the desired exit point about as
    much) and where the centre was held, from the summary."""
    passes = summary.get("planner_passes") or []
    best = min(passes, key=lambda p: p["exit_error_mm"]) if passes else {}
    limited = best.get("limited_steps", [])
    failed = summary.get("planner_eq42_failed_steps", [])
    held = [e for e in summary.get("events", []) if e.get("kind") == "planner-not-converged"]
    lean = summary.get("needle_entry_tilt_rad") or 0.0
    notes = ([f"needle leaning {lean:.3g} rad at entry"] if lean else []) + (
        [f"move limits held {len(limited)} of {summary['steps']} steps"] if limited else []) + (
        [f"eq. 4.2 fails at {len(failed)} steps"] if failed else []) + (
        [f"centre held at {len(held)} steps"] if held else [])
    return "; ".join(notes)


def _result_row(scene: tuple, level: str, spacing: float | None, summary: dict, simulate: bool = False) -> list:
    """A thesis_table.csv row: `scene` (name, label, thesis unplanned, thesis planned) run at
    `level` (`spacing` asked for), from its summary (with `simulate`: the unplanned run alone)."""
    name, label, thesis_unplanned, thesis_planned = scene
    if "error" in summary:
        print(f"{name} {level}: FAILED {summary['error']}", flush=True)
        return [name, label, level, spacing, None, thesis_unplanned, None, None, thesis_planned, None, None, None,
                summary["error"]]
    disc = summary["discretization"]
    unplanned = summary["exit_error_mm" if simulate else "unplanned_exit_error_mm"]
    planned = None if simulate else summary["exit_error_mm"]
    print(f"{name} {level}: unplanned {unplanned} mm, planned {planned} mm, {summary['wall_seconds']:.1f} s",
          flush=True)
    return [name, label, level, disc["spacing_mm"], disc["particles"], thesis_unplanned, unplanned,
            relative_change(thesis_unplanned, unplanned), thesis_planned, planned,
            summary.get("exit_error_estimate_mm"), summary["wall_seconds"],
            "unplanned only (simulate)" if simulate else _planner_note(summary)]


LEVELS = (("default", 1.0), ("half", 0.5), ("quarter", 0.25))  # x the file's spacing
LOOSE_LIMITS = (1.5, 2.0, 2.5, 3.0, 10.0)  # the move limits x these, for the trade-off table
HELD_BACK = 0.01  # mm: a default-level plan further off than this, its move limits held, is rerun loosened
# files whose planner leans the needle at entry (planner.aim_entry_tilt): planned upright too,
# at the default spacing, where the move limits' price shows
LEANING = ("needle20_fig510",)


# the table 5.1 files with their one unstated parameter changed: which thicknesses converge
SWEEP_THICKNESSES = (2.76, 3.0, 3.5, 4.0, 4.5, 5.0)  # mm; 2.76 the files' reading until f28e417
SVK_THICKNESSES = (4.5, 5.0)  # the thesis's Saint Venant-Kirchhoff law besides, where it nearly converges
SWEEP_LEVELS = (1.0, 0.5, 0.25)  # x the file's spacing (both spacings: needle_refinement)
CONVERGED_CHANGE = 2.0  # %, default to half the spacing (and the three levels in one direction)


def changed_copy(config: Path, workdir: Path, suffix: str, change) -> Path:
    """A copy of `config` in `workdir` with `change(raw data)` applied."""
    import yaml

    raw = yaml.safe_load(config.read_text())
    change(raw)
    path = workdir / f"{config.stem}_{suffix}.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


def loosened(config: Path, workdir: Path, factor: float) -> Path:
    """A copy of `config` with the planner's move limits `factor` times the defaults (config Planner)."""
    defaults = Planner()

    def loosen(raw: dict) -> None:
        planner = raw.setdefault("planner", {})
        planner["center_step_limit"] = defaults.center_step_limit * factor
        planner["center_second_difference_limit"] = defaults.center_second_difference_limit * factor
    return changed_copy(config, workdir, f"loose{factor:g}", loosen)


def thickness_sweep(workdir: Path) -> list[list]:
    """The table 5.1 blocks' unplanned exit error at SWEEP_LEVELS for each of
    SWEEP_THICKNESSES, neo-Hookean as the files, and of SVK_THICKNESSES with the thesis's Saint
    Venant-Kirchhoff law (`stitchplan simulate --no-estimate`): per block and thickness the
    errors, the change from the default to half the spacing, whether the three levels change it
    in one direction, the observed rate and the quarter-spacing error against the thesis's."""
    rows = []
    cases = [("neo-hookean", t) for t in SWEEP_THICKNESSES] + [("saint-venant-kirchhoff", t) for t in SVK_THICKNESSES]
    for law, thickness in cases:
        for name, _, thesis_unplanned, _ in SCENES[:4]:
            def read_as(raw: dict) -> None:  # the case's thickness and law in the file's data
                raw["tissue"]["thickness"] = thickness
                raw["tissue"]["material"]["model"] = law
            config = changed_copy(THESIS_DIR / f"{name}.yaml", workdir, f"{law}_t{thickness:g}", read_as)
            scenario = load_scenario(config)
            spacing = scenario.discretization.spacing
            errors, failure = [], ""
            for factor in SWEEP_LEVELS:
                summary = run_scene(config, workdir, None if factor == 1.0 else spacing * factor, simulate=True)
                if "error" in summary:
                    failure = f"{factor:g} h: {summary['error']}"[:110]
                    break
                errors.append(summary["exit_error_mm"])
            errors += [None] * (len(SWEEP_LEVELS) - len(errors))
            e0, e1, e2 = errors
            change = relative_change(e0, e1)
            one_way = e2 is not None and (e1 - e0) * (e2 - e1) > 0
            rate = math.log(abs(e1 - e0) / abs(e2 - e1), 2.0) if one_way else None
            converged = one_way and abs(change) < CONVERGED_CHANGE
            rows.append([law, thickness, load_ratio(scenario), name, *errors, change, "yes" if one_way else "no", rate,
                         "yes" if converged else "no", thesis_unplanned,
                         relative_change(thesis_unplanned, e2), failure])
            print(f"{name} at {thickness:g} mm, {law}: {errors} {failure}", flush=True)
    return rows


def sweep_chart(rows: list[dict], path: Path) -> None:
    """The thickness sweep (thesis_table_thickness.csv rows): left, each block's change from h
    to h/2 against the thickness (filled where h, h/2, h/4 go one way) with the 2 % line;
    right, its error at h/4 beside table 5.1's (dashed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (left, right) = plt.subplots(1, 2, figsize=(11, 4.2))
    for number, (name, label, thesis_unplanned, _) in enumerate(SCENES[:4]):
        colour = f"C{number}"
        block = [row for row in rows if row["scene"] == name and row["law"] == "neo-hookean"]
        thickness = [float(row["thickness_mm"]) for row in block]
        change = [float(row["change_h_h2_pct"]) if row["change_h_h2_pct"] else math.nan for row in block]
        left.plot(thickness, change, "-", color=colour, label=label)
        for t, c, row in zip(thickness, change, block):
            left.plot(t, c, "o", color=colour, markerfacecolor=colour if row["one_direction"] == "yes" else "white")
        quarter = [float(row["exit_error_h4_mm"]) if row["exit_error_h4_mm"] else math.nan for row in block]
        right.plot(thickness, quarter, "o-", color=colour, label=label)
        right.axhline(thesis_unplanned, color=colour, linestyle="--", linewidth=1)
    left.axhline(CONVERGED_CHANGE, color="black", linewidth=0.8)
    left.axhline(-CONVERGED_CHANGE, color="black", linewidth=0.8)
    left.set_xlabel("slab thickness (mm)")
    left.set_ylabel("unplanned exit error, change h -> h/2 (%)")
    left.set_title("convergence (open: h, h/2, h/4 not one way)", fontsize=10)
    right.set_xlabel("slab thickness (mm)")
    right.set_ylabel("unplanned exit error at h/4 (mm)")
    right.set_title("ours at h/4 (solid) and table 5.1 (dashed)", fontsize=10)
    reading = load_scenario(THESIS_DIR / "table51_100x30.yaml").tissue.thickness  # the files' thickness
    for axis in (left, right):
        axis.axvline(reading, color="gray", linestyle=":", linewidth=1)
    common.panels_legend(figure, np.array([left, right]), ncol=4, fontsize=9)
    figure.suptitle("Table 5.1's blocks against the thickness the thesis leaves open (dotted: the files' reading)",
                    fontsize=11)
    common.save_figure(figure, path, (0, 0.07, 1, 0.95))


def main() -> None:
    if "--chart" in common.command_line(__doc__, ("--chart",)):  # only redraw the sweep's chart from its CSV
        sweep_chart(common.csv_rows(common.results_path("thesis_table_thickness.csv")),
                    common.results_path("thesis_table_thickness.png"))
        return
    header = ["scene", "thesis", "discretization", "spacing_mm", "particles",
              "thesis_unplanned_mm", "unplanned_mm", "unplanned_vs_thesis_pct",
              "thesis_planned_mm", "planned_mm", "exit_error_estimate_mm", "plan_wall_s", "note"]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        workdir = Path(tmp)
        for name, label, thesis_unplanned, thesis_planned in SCENES:
            config = THESIS_DIR / f"{name}.yaml"
            default_spacing = None
            for level, factor in LEVELS:
                if level != "default" and default_spacing is None:
                    rows.append([name, label, level, None, None, thesis_unplanned, None, None,
                                 thesis_planned, None, None, None, "default run failed"])
                    continue
                spacing = None if level == "default" else default_spacing * factor
                simulate = level == "quarter"
                summary = run_scene(config, workdir, spacing, simulate)
                rows.append(_result_row((name, label, thesis_unplanned, thesis_planned), level, spacing, summary,
                                        simulate))
                if "error" not in summary and level == "default":
                    # the file's spacing, as benchmarks/needle_coupling.py halves it
                    default_spacing = load_scenario(config).discretization.spacing
        configs = {name: THESIS_DIR / f"{name}.yaml" for name, *_ in SCENES}
        for scene in (scene for scene in SCENES if scene[0] in LEANING):
            configs[scene[0]] = changed_copy(configs[scene[0]], workdir, "upright",
                                             lambda raw: raw["planner"].update(aim_entry_tilt=False))
            rows.append(_result_row(scene, "default, upright", None, run_scene(configs[scene[0]], workdir, None)))
        loose = []
        held_back = [row[0] for row in rows if row[2] in ("default", "default, upright") and row[9] is not None
                     and row[9] > HELD_BACK and "move limits held" in row[12]]
        for name in held_back:
            for factor in LOOSE_LIMITS:
                summary = run_scene(loosened(configs[name], workdir, factor), workdir, None)
                if "error" in summary:
                    loose.append([name, factor, None, None, None, summary["error"]])
                else:
                    loose.append([name, factor, summary["exit_error_mm"], summary["max_center_step_mm"],
                                  summary["max_center_second_difference_mm"], _planner_note(summary)])
                print(f"{name} with the limits x {factor:g}: {loose[-1][2:]}", flush=True)
        sweep = thickness_sweep(workdir)

    common.write_csv(common.results_path("thesis_table_thickness.csv"),
                     ["law", "thickness_mm", "load_ratio", "scene", "exit_error_h_mm", "exit_error_h2_mm",
                      "exit_error_h4_mm", "change_h_h2_pct", "one_direction", "rate", "converges",
                      "thesis_unplanned_mm", "h4_vs_thesis_pct", "stopped"],
                     [[("" if v is None else v) for v in row] for row in sweep])
    common.write_csv(common.results_path("thesis_table.csv"), header,
                     [[("" if v is None else v) for v in row] for row in rows])
    shown = ["scene", "thesis", "discretization", "spacing (mm)", "particles",
             "thesis unplanned (mm)", "ours unplanned (mm)", "vs thesis (%)",
             "thesis planned (mm)", "ours planned (mm)", "exit-error estimate (mm)",
             "plan wall (s)", "note"]
    lines = [
        "# The thesis's simulation results beside ours",
        "",
        f"Generated by `python benchmarks/thesis_table.py` ({common.machine_note()}).",
        "",
        "Each row is one `stitchplan plan configs/thesis/SCENE.yaml --export t.csv --summary s.json "
        "--no-verify` run, at the default discretization and with `--spacing` half the file's "
        "`discretization.spacing` (the spacing at the needle halves with it; the *spacing* column "
        "is the lattice's, fitted to the block). *Unplanned* is the summary's "
        "`unplanned_exit_error_mm` (needle centre fixed), *planned* its `exit_error_mm`. The "
        "*quarter* rows are `stitchplan simulate ... --spacing H/4 --no-estimate` runs (unplanned "
        "only; their wall time is the simulate run's), a third level for the convergence. The "
        "thesis's numbers are table 5.1 and, for figures 5.9 and 5.10, the distances between the "
        "deformed desired exit and the unplanned / planned exits that section 5.1.1 reports.",
        "",
        "Readings of what the thesis leaves unstated (each config's comment says why):",
        "",
        "- table 5.1: thickness 5 mm (forces as totals through it; the thinnest half-millimetre "
        "reading at which all four blocks converge with a margin: the thickness sweep below), "
        "neo-Hookean, Lame moduli in MPa, entry at mid-height + r on the left edge, the SH 1/2 "
        "files' discretization (configs/sh12_*.yaml);",
        "- section 5.1.1: the thesis's code in cm, so lambda = 9.263 and mu = 1.029 are N/cm^2 "
        "(0.01 MPa) and the model had unit thickness 1 cm = 10 mm; neo-Hookean, not the thesis's "
        "Saint Venant-Kirchhoff, which collapses in front of the tip when refined at this softness; "
        "the entry of figure 5.10 is not stated (ours: top edge at (20, 100)).",
        "",
        common.markdown_table(shown, [[("-" if v is None or v == "" else v) for v in row]
                                      for row in rows]),
        "",
        "## The move limits' price (default discretization, limits loosened)",
        "",
        f"The default-level plans above that end more than {HELD_BACK:g} mm off with the centre's "
        "move limits holding them back (0.28 mm per step and 0.14 mm second difference per 0.08 "
        "rad, scaled with the step): there the planner needs centre excursions the limits do not "
        "allow (on the 20 mm needle's figure 5.10 scene planned upright, the *default, upright* "
        f"row: its file leans the needle at entry instead, `planner.aim_entry_tilt`; the rows of "
        f"{', '.join(LEANING)} above lean it; and on the table 5.1 blocks as read until "
        "git f28e417, 2.76 mm thick, the three narrower ones). The same plans with the limits "
        f"{', '.join(f'{factor:g}' for factor in LOOSE_LIMITS)} times the defaults "
        "(`planner.center_step_limit` and `center_second_difference_limit` in the scenario): "
        "how far the limits must give for the plan to reach the exit:",
        "",
        common.markdown_table(["scene", "limits x", "planned (mm)", "largest centre move per step (mm)",
                               "largest second difference (mm)", "note"],
                              [[("-" if v is None or v == "" else v) for v in row] for row in loose]),
        "",
        "## Which thickness: where the table 5.1 blocks converge",
        "",
        "The one parameter the thesis leaves open for table 5.1 is the slab's thickness (its forces "
        "read as totals through it). Each block's file with only the thickness changed (and at 4.5 "
        "and 5 mm also the law, the thesis's Saint Venant-Kirchhoff), `stitchplan "
        "simulate --no-estimate` at the file's spacing h, h/2 and h/4 (both spacings: "
        "needle_refinement). *Load ratio*: (friction + cutting force / R) / (mu t), the needle's "
        "loads against the tissue's shear stiffness (benchmarks/softness_sweep.py). *Converges*: "
        f"the change from h to h/2 below {CONVERGED_CHANGE:g} % and the three levels changing it in one direction. "
        "*Rate*: log2 of the change from h to h/2 over the change from h/2 to h/4 (negative: the "
        "second change is the larger; benchmarks/results/needle_coupling.md adds 2h and h/8 for "
        "the files' reading). "
        "*vs thesis*: the error at h/4 against table 5.1's. Thinner slabs come nearer the "
        "thesis's magnitudes but the entry's free edge creases there and the narrow blocks' errors "
        "do not settle (2.76 mm: the files' reading until git f28e417). Drawn in "
        "thesis_table_thickness.png.",
        "",
        common.markdown_table(["law", "thickness (mm)", "load ratio", "scene", "h (mm)", "h/2 (mm)", "h/4 (mm)",
                               "h -> h/2 (%)", "one direction", "rate p (ratio 2)", "converges",
                               "thesis unplanned (mm)", "h/4 vs thesis (%)", "stopped"],
                              [[("-" if v is None or v == "" else v) for v in row] for row in sweep]),
        "",
        "Where the note says eq. 4.2 fails, the thesis's plain centre update would stall: in these "
        "soft blocks moving the needle centre moves the desired exit point (the material near the "
        "free edge) about as much. stitchplan's centre is a Newton unknown of each step's solve, "
        "which needs only I - du(X_exit)/dO invertible, so it settles those steps too unless the "
        "move limits hold it back (then the passes correct the exit through the early steps).",
        "",
    ]
    common.write_report("thesis_table.md", lines)
    sweep_chart(common.csv_rows(common.results_path("thesis_table_thickness.csv")),
                common.results_path("thesis_table_thickness.png"))


if __name__ == "__main__":
    main()
