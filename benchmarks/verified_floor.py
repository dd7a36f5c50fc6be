"""How fast a verified plan can be: the default `plan CONFIG --no-compare` beside the replay of
its exported trajectory on the refined model alone.

The default `plan` replays its trajectory on a model of half the particle spacing
(planning/verification.py); a helper process makes that replay while the planning goes on,
each step once the planner has fixed its centre (planning/replays.py). Every step of the first
round's trajectory is replayed on the refined model that way, from the model's start, so no
verified plan can end much sooner than `simulate CONFIG --center-path trajectory.csv --spacing
VERIFICATION_SPACING --no-estimate`, the same replay made alone: start-up, the refined model
and all its steps. That command is the floor a faster planner cannot lower.

For each scene, REPEATS times (median): the plan's whole command, its planned runs (every
round's, the summary's `wall_seconds`), its verification rounds and their verified exit errors;
the same with `planner.predicted_aim: false` (the scene's file with that key changed), which
re-aims only after the refined replay, and the same command with the code at BASELINE (before
the helper's replay took over the steps of a replay it dropped, and before a replay's entry
centre was the one its path gave: a trajectory's rounded entry centre took over no step),
alternating with it (on the scene's file as it was then, _common.previous_config); then the kept trajectory replayed alone (its whole command and its run,
the summary's `wall_seconds`), with its particle count checked against the verification's.

Writes benchmarks/results/verified_floor.{csv,md} and prints the table. About 6 minutes.
Run from the repository root:  python benchmarks/verified_floor.py
"""

from __future__ import annotations

import os

# single-threaded BLAS, as the `stitchplan` command sets it
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import statistics  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import yaml  # noqa: E402

import _common as common  # noqa: E402

from stitchplan.config.scenario import load_scenario  # noqa: E402

SCENES = ("sh12_100x100", "sh12_100x30", "hole_near_stitch", "needle20_entry30", "needle20_entry18")
REPEATS = 5
BASELINE = "685727f"
GOAL_SECONDS = 1.5  # the whole `plan --no-compare` command the speed work aims at


def measure(scene: str, folder: Path, baseline: Path) -> dict:
    """The scene's verified plan, with and without the predicted aim and at BASELINE (its
    code extracted into `baseline`), and its trajectory's replay alone, REPEATS times each."""
    raw = yaml.safe_load((common.REPO_ROOT / "configs" / f"{scene}.yaml").read_text())
    raw.setdefault("planner", {})["predicted_aim"] = False
    unpredicted = folder / f"{scene}_without_predicted_aim.yaml"
    unpredicted.write_text(yaml.safe_dump(raw))
    plans, befores, baselines = [], [], []
    previous = common.previous_config(scene, folder)  # the file as BASELINE's code reads it
    for _ in range(REPEATS):  # alternating, so that a slower spell of the machine hits each
        baselines.append(common.config_command("plan", previous, ["--no-compare", "-q"], folder, baseline,
                                               PYTHONPATH=str(baseline)))
        befores.append(common.config_command("plan", unpredicted, ["--no-compare", "-q"], folder, folder))
        plans.append(common.scene_command("plan", scene, ["--no-compare", "-q"], folder, folder))
    # BASELINE solved a needle step to 5e-6 of the needle force and 1e-9 R, the code now to 1e-3
    # and 1e-7 R (benchmarks/results/solver_tolerance.md): the plans then agree within the
    # planner's tolerance, not to the bit
    tolerance = load_scenario(common.REPO_ROOT / "configs" / f"{scene}.yaml").planner.tolerance
    # a shape scene whose particles BASELINE placed otherwise (hole_near_stitch: 514 then, 417 since
    # its boundary particles stopped doubling the lattice's, tissue/shapes.py) plans on another model
    same_model = baselines[-1][1]["particles"] == plans[-1][1]["particles"]
    if same_model and abs(baselines[-1][1]["verified_exit_error_mm"] - plans[-1][1]["verified_exit_error_mm"]) > tolerance:
        raise RuntimeError(f"{scene}: verified exit error {plans[-1][1]['verified_exit_error_mm']} mm, at "
                           f"{BASELINE} {baselines[-1][1]['verified_exit_error_mm']} mm")
    plan, before = plans[-1][1], befores[-1][1]
    trajectory = folder / f"{scene}_trajectory.csv"
    (folder / "trajectory.csv").replace(trajectory)
    verification = plan["verification"]
    replays = [common.scene_command("simulate", scene, ["--center-path", str(trajectory), "--spacing",
                                                        repr(plan["verification_spacing_mm"]), "--no-estimate", "-q"],
                                    folder, folder) for _ in range(REPEATS)]
    replay = replays[-1][1]
    particles = verification["discretization"]["particles"]
    if replay["particles"] != particles:
        raise RuntimeError(f"{scene}: the replay alone has {replay['particles']} particles, the verification "
                           f"{particles}")
    rounds = verification["rounds"]
    return {
        "scene": scene,
        "plan_command_s": statistics.median(seconds for seconds, _ in plans),
        "planned_s": statistics.median(summary["wall_seconds"] for _, summary in plans),
        "rounds": len(rounds),
        "first_round_verified_mm": rounds[0]["verified_exit_error_mm"],
        "verified_mm": plan["verified_exit_error_mm"],
        "particles": plan["particles"], "refined_particles": particles,
        "replay_command_s": statistics.median(seconds for seconds, _ in replays),
        "replay_s": statistics.median(summary["wall_seconds"] for _, summary in replays),
        "replay_exit_mm": replay["exit_error_mm"],
        "unpredicted_command_s": statistics.median(seconds for seconds, _ in befores),
        "unpredicted_rounds": len(before["verification"]["rounds"]),
        "unpredicted_verified_mm": before["verified_exit_error_mm"],
        "baseline_command_s": statistics.median(seconds for seconds, _ in baselines),
        "baseline_particles": baselines[-1][1]["particles"],
    }


def main() -> None:
    with tempfile.TemporaryDirectory() as scratch, tempfile.TemporaryDirectory() as extracted:
        baseline = common.extract_revision(BASELINE, Path(extracted))
        rows = []
        for scene in SCENES:
            row = measure(scene, Path(scratch), baseline)
            rows.append(row)
            print(f"{scene}: plan --no-compare {row['plan_command_s']:.2f} s (at {BASELINE} "
                  f"{row['baseline_command_s']:.2f} s; {row['rounds']} round(s), verified "
                  f"{row['verified_mm']:.4f} mm; without the predicted aim {row['unpredicted_command_s']:.2f} s, "
                  f"{row['unpredicted_rounds']} round(s)); replay alone {row['replay_command_s']:.2f} s "
                  f"(run {row['replay_s']:.2f} s, {row['refined_particles']} particles)", flush=True)
    header = list(rows[0])
    common.write_csv(common.results_path("verified_floor.csv"), header, [[r[k] for k in header] for r in rows])
    above = [r["scene"] for r in rows if r["replay_command_s"] > GOAL_SECONDS]
    met = [r["scene"] for r in rows if r["plan_command_s"] <= GOAL_SECONDS]
    lines = [
        "# How fast a verified plan can be\n",
        f"Generated by `python benchmarks/verified_floor.py` ({common.machine_note()}; load average "
        f"{os.getloadavg()[0]:.1f} at the end). Median of {REPEATS}; every command with Python's bytecode "
        "cache on (_common.command_environment).\n",
        "*Plan*: `plan CONFIG --no-compare` with the default verification, its whole command and its "
        "planned runs (every round's, the summary's `wall_seconds`); a round whose verified exit error "
        "is above 1.5 x the planner's exit tolerance (0.0075 mm by default) re-aims and replays again "
        "(planning/verification.py); the plan's first pass is replayed at twice the spacing too, and "
        "where the refined model's offset predicted from it says the refined replay would miss, the later "
        "passes aim by it (`planner.predicted_aim`, benchmarks/results/predicted_aim.md). *Without the "
        "predicted aim*: "
        "the same command on the scene's file with `planner.predicted_aim: false`, run alternately with "
        "it (the plan before the predicted aim). "
        f"*At {BASELINE}*: the same command with the code of commit {BASELINE} on the scene's file as it "
        "was then (before the SH 1/2 and 20 mm needle files were discretized for the needle: "
        "_common.previous_config), run alternately with "
        "them, its verified exit error checked within the planner's 0.001 mm where it placed the same "
        "particles (a shape scene placed otherwise there plans on another model: its particles in "
        "brackets) (it solved a needle step to "
        "5e-6 of the needle force and 1e-9 R, the code now to 1e-3 and 1e-7 R): there the helper started a "
        "replay it had dropped "
        "(the planner's second pass leaving the first pass's centres at a step the replay had passed) "
        "again from the model's start, and a trajectory's entry centre as exported (rounded) took over "
        "no step of an earlier replay. "
        "*Replay alone*: the exported trajectory replayed on the refined model by itself, `simulate "
        "CONFIG --center-path trajectory.csv --spacing VERIFICATION_SPACING --no-estimate` (the same "
        "particles, checked): start-up, the refined model and every step. The plan's helper replays "
        "every step of the first round's trajectory on that model too, so the replay alone's whole "
        "command is about the least a verified plan can take, whatever the planning costs.\n",
        common.markdown_table(
            ["scene", "particles (planning / refined)", "plan --no-compare (s)", f"at {BASELINE} (s)",
             "planned runs (s)",
             "verification rounds", "verified exit error, round 1 (mm)", "verified exit error (mm)",
             "without the predicted aim: plan (s)", "rounds", "verified (mm)",
             "replay alone: whole command (s)", "replay alone: run (s)"],
            [[r["scene"], f"{r['particles']} / {r['refined_particles']}", r["plan_command_s"],
              r["baseline_command_s"] if r["baseline_particles"] == r["particles"]
              else f"{r['baseline_command_s']:.4g} (on {r['baseline_particles']} particles)", r["planned_s"],
              r["rounds"], r["first_round_verified_mm"], r["verified_mm"], r["unpredicted_command_s"],
              r["unpredicted_rounds"], r["unpredicted_verified_mm"], r["replay_command_s"], r["replay_s"]]
             for r in rows]),
        "",
        f"Whole `plan --no-compare` within {GOAL_SECONDS:g} s: {', '.join(met) or 'none'}. The replay alone "
        f"takes longer than {GOAL_SECONDS:g} s on: {', '.join(above) or 'none'}.\n",
    ]
    common.write_report("verified_floor.md", lines)


if __name__ == "__main__":
    common.command_line(__doc__)
    main()
