"""Whether the needle runs' equilibria stay stable as the spacing is refined.

On tissue soft against the SH 1/2 needle's loads the exit error does not settle and the
2.5 mm slab's quarter-spacing run stops (benchmarks/results/needle_coupling.md,
exit_components.md). Here the same unplanned runs (needle_coupling.scene, each file as
shipped) record, after every load they carry (each step's end and each increment of
Algorithm 1's ramp), the tangent's least stiffness on the needle's constraints
(NeedleInsertion.softest_mode, needle/stability.py: the smallest eigenvalue of K + H on
null(G^T), relative to K's mean diagonal) and where its mode moves the tissue most. A
negative value is an unstable state: Newton converged to an equilibrium the tissue would
leave (it buckles or creases there); within a cut ramp the package refuses such a state and
takes a smaller increment (NeedleInsertion._refuse_unstable; the table counts them). The
recording is patched into NeedleInsertion for the runs: a probe, not an option of the package.

Per scene and level (h, h/2, h/4, h the file's spacing): the exit error or the failure, the
least stiffness over the run relative to its first step's (states kept), the first unstable
state (step, load) and its mode's place. Writes benchmarks/results/entry_stability.{csv,md,png}. About 15
minutes. Run from the repository root:  python benchmarks/entry_stability.py [--chart]
"""

from __future__ import annotations

import os

# single-threaded BLAS, as the `stitchplan` command sets it
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import contextlib  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

import _common as common  # noqa: E402
import needle_coupling  # noqa: E402
from stitchplan.errors import InsertionFailure  # noqa: E402
from stitchplan.needle.equilibrium import NeedleInsertion  # noqa: E402
from stitchplan.needle.insertion import run_insertion  # noqa: E402
from stitchplan.needle.stability import mode_peak  # noqa: E402

SCENES = ("soft_t2.5", "soft_t3", "sh12_100x100")
LEVELS = (("h", 1.0), ("h/2", 0.5), ("h/4", 0.25))
FIELDS = ("scene", "level", "spacing_mm", "particles", "step", "load", "least_stiffness", "mode_x_mm", "mode_y_mm",
          "mode_to_entry_mm", "refused", "exit_error_mm", "failure")


@contextlib.contextmanager
def recording(records: list[dict]):
    """NeedleInsertion records its least stiffness after every load it carries, and which of
    those states the ramp refused as unstable (NeedleInsertion._refuse_unstable)."""
    equilibrate, accept, refuse = NeedleInsertion.equilibrate, NeedleInsertion._accept, NeedleInsertion._refuse_unstable

    def equilibrate_step(insertion, rotation, step, *arguments, **keywords):
        insertion.probe_step = step
        return equilibrate(insertion, rotation, step, *arguments, **keywords)

    def accept_recorded(insertion, free, multipliers, center, worst, iterations):
        accept(insertion, free, multipliers, center, worst, iterations)
        mode = insertion.softest_mode()
        if mode is None:
            return
        peak = insertion.model.particles[mode_peak(mode, insertion.model.boundary.free_map)]
        records.append({"step": insertion.probe_step, "load": insertion.coupling.load_factor,
                        "least_stiffness": mode.stiffness, "mode_x_mm": float(peak[0]), "mode_y_mm": float(peak[1]),
                        "mode_to_entry_mm": float(np.linalg.norm(peak - insertion.geometry.entry)),
                        "refused": ""})

    def refuse_recorded(insertion, rotation, step):
        try:
            refuse(insertion, rotation, step)
        except InsertionFailure:
            records[-1]["refused"] = "yes"
            raise

    NeedleInsertion.equilibrate, NeedleInsertion._accept = equilibrate_step, accept_recorded
    NeedleInsertion._refuse_unstable = refuse_recorded
    try:
        yield
    finally:
        NeedleInsertion.equilibrate, NeedleInsertion._accept = equilibrate, accept
        NeedleInsertion._refuse_unstable = refuse


def run(scene: str, level: str, factor: float) -> list[dict]:
    """One unplanned run with its least stiffness after every load carried, as CSV rows."""
    scenario = needle_coupling.refined(scene, factor)
    records: list[dict] = []
    start = time.perf_counter()
    with recording(records):
        try:
            result = run_insertion(scenario)
            outcome = {"exit_error_mm": f"{result.exit_error_mm:.6f}", "failure": "",
                       "particles": result.model.n_particles}
        except InsertionFailure as failure:
            outcome = {"exit_error_mm": "", "failure": " ".join(str(failure).split())[:160].replace(",", ";"),
                       "particles": ""}
    print(f"{scene} at {level}: {outcome['exit_error_mm'] or outcome['failure'][:90]}, {len(records)} states, "
          f"least stiffness {min(r['least_stiffness'] for r in records):.3e}, {time.perf_counter() - start:.0f} s",
          flush=True)
    fixed = {"scene": scene, "level": level, "spacing_mm": scenario.discretization.spacing, **outcome}
    return [{**fixed, **record} for record in records]


def summary(rows: list[dict]) -> list[list]:
    """Per scene and level: outcome, least stiffness over the run against its first step's,
    the first unstable state and its mode's place."""
    table = []
    for scene in SCENES:
        for level, _ in LEVELS:
            own = [row for row in rows if row["scene"] == scene and row["level"] == level]
            if not own:
                continue
            kept = [row for row in own if row["refused"] != "yes"]
            stiffness = np.array([float(row["least_stiffness"]) for row in kept])
            lowest = kept[int(np.argmin(stiffness))]
            unstable = [row for row in own if float(row["least_stiffness"]) < 0.0]
            first = unstable[0] if unstable else None
            refused = sum(row["refused"] == "yes" for row in unstable)
            table.append([
                scene, level, float(own[0]["spacing_mm"]),
                own[0]["exit_error_mm"] or f"stops: {own[0]['failure'][:70]}",
                f"{stiffness[0]:.3e}", f"{stiffness.min() / stiffness[0]:.3f}",
                f"{int(lowest['step'])} ({100 * float(lowest['load']):.0f} %)",
                f"({float(lowest['mode_x_mm']):.2f}, {float(lowest['mode_y_mm']):.2f}), "
                f"{float(lowest['mode_to_entry_mm']):.2f} mm from the entry",
                (f"step {int(first['step'])} at {100 * float(first['load']):.1f} % of its load; "
                 f"{len(unstable)} unstable, {refused} refused by the ramp" if first else "none")])
    return table


def chart(rows: list[dict], path) -> None:
    """One panel per scene: the least stiffness after each load carried over its first step's,
    against the needle step (a ramp's increments at fractions of the step), one curve per level."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, len(SCENES), figsize=(4.2 * len(SCENES), 3.8), squeeze=False)
    for axis, scene in zip(axes[0], SCENES):
        for level, _ in LEVELS:
            own = [row for row in rows if row["scene"] == scene and row["level"] == level]
            if not own:
                continue
            first = float(own[0]["least_stiffness"])
            kept = [row for row in own if row["refused"] != "yes"]
            line, = axis.plot([int(row["step"]) - 1 + float(row["load"]) for row in kept],
                              [float(row["least_stiffness"]) / first for row in kept], marker=".", markersize=3,
                              label=level)
            refused = [row for row in own if row["refused"] == "yes"]
            if refused:
                axis.plot([int(row["step"]) - 1 + float(row["load"]) for row in refused],
                          [float(row["least_stiffness"]) / first for row in refused], "x", color=line.get_color(),
                          markersize=8, label=f"{level}: unstable state refused")
            if not own[0]["exit_error_mm"]:
                axis.plot(int(kept[-1]["step"]) - 1 + float(kept[-1]["load"]), float(kept[-1]["least_stiffness"]) / first,
                          "s", color=line.get_color(), markerfacecolor="none", markersize=8,
                          label=f"{level}: last load carried (the run stops)")
        axis.axhline(0.0, color="0.5", linewidth=0.8)
        axis.set_title(scene, fontsize=10)
        axis.set_xlabel("needle step")
        axis.grid(alpha=0.3)
    axes[0][0].set_ylabel("least stiffness on the constraints\n(over its first step's)")
    common.panels_legend(figure, axes[0], ncol=len(LEVELS))
    common.save_figure(figure, path, (0.0, 0.08, 1.0, 1.0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--chart", action="store_true", help="redraw the chart and table from the CSV")
    arguments = parser.parse_args()
    csv_path = common.results_path("entry_stability.csv")
    if arguments.chart:
        rows = common.csv_rows(csv_path)
    else:
        rows = [row for scene in SCENES for level, factor in LEVELS for row in run(scene, level, factor)]
        common.write_csv(csv_path, FIELDS, [[row.get(key, "") for key in FIELDS] for row in rows])
        rows = common.csv_rows(csv_path)
    text = "\n".join([
        "# Do the needle runs' equilibria stay stable under refinement?",
        "",
        f"Generated by `python benchmarks/entry_stability.py` ({common.machine_note()}). Unplanned runs of each "
        "scene's file as shipped (soft_t3, soft_t2.5: configs/sh12_100x100.yaml as neo-Hookean slabs 3 and 2.5 "
        "mm thick, benchmarks/needle_coupling.py) at h, h/2 and h/4, h the file's spacing. After every load a run "
        "carries (each step's end, each increment of Algorithm 1's ramp): the tangent's least stiffness on the "
        "needle's constraints (the smallest eigenvalue of K + H on null(G^T), relative to K's mean diagonal; "
        "needle/stability.py) and the particle its mode moves most. Negative: the state is unstable (the tissue "
        "would buckle or crease there); within a cut ramp the package refuses such a state and takes a smaller "
        "increment. *Lowest / first*: the least stiffness over the states kept against its first step's. Drawn "
        "in entry_stability.png.",
        "",
        common.markdown_table(["scene", "level", "spacing (mm)", "exit error (mm)", "least stiffness, step 1",
                               "lowest / first", "lowest at step (load)", "its mode largest at",
                               "unstable states reached"],
                              summary(rows)),
        "",
    ])
    common.publish("entry_stability", text, chart, rows)


if __name__ == "__main__":
    main()
