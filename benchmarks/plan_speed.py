"""Speed of the planner (`stitchplan plan`) on every shipped needle scene, before and after.

1. Side by side in one run: the planned run of `plan CONFIG --no-compare` at BASELINE (the
   code before the speed work, extracted with `git archive` into a temporary folder) and of
   `plan CONFIG --no-compare --no-verify` now (the same planned run: BASELINE had no
   verification), REPEATS times each, alternating so both see the same machine load. The
   planned run's time is the summary's `wall_seconds` (from the loaded scenario to the
   result, every pass); the whole command's process wall time is reported too. Now also with
   scipy alone (no CHOLMOD) and with the estimate's replay in the command's process
   (STITCHPLAN_REPLAY_HELPER=0: no forked helper alongside, as at BASELINE), and
   the distribution of the needle steps' wall times, every Newton iteration, equilibrium
   solves, factorizations and linear solves (from the summary).
2. Where it comes from, in process on configs/sh12_100x100.yaml (and sh12_100x30, which
   takes two planner passes): the planned run with each lever switched back off in turn
   (Anderson mixing, SuperLU's symmetric mode, the stale centre columns, the centre columns
   from the kept K^-1 E^T, CHOLMOD's L D L^T for an indefinite K + H, Newton's method
   before Levenberg-Marquardt in the tip tracking, the residual tolerance, K0 from the
   direction gradients, one model shared by the passes, a later pass taking over the first
   pass's early steps with their tip points and equilibria, the internal force kept where a
   step starts; on needle20_entry25 also the kernel's truncated powers and one point's
   gradient directions in one product),
   median of LEVER_REPEATS rounds, each round running every variant once;
   and the verified plan with the second round's replay started cold and with its passes
   solving every step.
3. The whole command with the default verification on sh12_100x100, median of REPEATS.
4. Replays of the shipped trajectories at half the spacing with the factor renewed as now
   and as a planner's step renews it (needle/newton.py renew_factor).
5. The allocator: the planned run, the whole command, the process's page faults and its
   peak memory with glibc malloc's thresholds set as the command sets them
   (stitchplan/allocator.py) and with glibc's default.
6. Start-up: `stitchplan --help` and `stitchplan --version`, median of STARTUP_REPEATS; and
   the end: a `simulate` ended by the console entry point (no module teardown) and by the
   interpreter's ordinary exit.

Writes benchmarks/results/plan_speed.{csv,md} and prints the tables. 9-15 minutes.
Run from the repository root:  python benchmarks/plan_speed.py
"""

from __future__ import annotations

import os

# single-threaded BLAS, as the `stitchplan` command sets it
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import contextlib  # noqa: E402
import gc  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import _common as common  # noqa: E402

BASELINE = "19ff45d"
SCENES = ("sh12_100x100", "sh12_100x100_mid", "sh12_100x50", "sh12_100x40", "sh12_100x30",
          "needle20_entry30", "needle20_entry25", "needle20_entry20", "needle20_entry18")
REPEATS = 5
LEVER_REPEATS = 9  # rounds of the in-process levers table
STARTUP_REPEATS = 7


def run_plan_command(source: Path, scene: str, options: list[str], folder: Path, config: Path | None = None,
                     **environment) -> dict:
    """One `stitchplan plan` process of the code in `source` (with `environment` added to
    the process's) on configs/SCENE.yaml or `config`; its summary and wall time."""
    config = config or common.REPO_ROOT / "configs" / f"{scene}.yaml"
    seconds, record = common.config_command("plan", config, options, folder, source, PYTHONPATH=str(source),
                                            **environment)
    record["command_seconds"] = seconds
    return record


def compare_revisions(baseline: Path) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch)
        for scene in SCENES:
            before, after, scipy_only, inline = [], [], [], []  # scipy_only: the path without the `fast` extra
            # BASELINE runs the file as it was before it was discretized for the needle, the
            # scene it was timed on (and keys it does not have left out)
            previous = common.previous_config(scene, folder)
            for _ in range(REPEATS):
                before.append(run_plan_command(baseline, scene, ["--no-compare"], folder, config=previous))
                after.append(run_plan_command(common.REPO_ROOT, scene, ["--no-compare", "--no-verify", "-q"], folder))
                scipy_only.append(run_plan_command(common.REPO_ROOT, scene, ["--no-compare", "--no-verify", "-q"],
                                                   folder, STITCHPLAN_LINEAR_BACKEND="scipy"))
                inline.append(run_plan_command(common.REPO_ROOT, scene, ["--no-compare", "--no-verify", "-q"],
                                               folder, STITCHPLAN_REPLAY_HELPER="0"))
            last = after[-1]
            steps = last["timings_seconds"]["steps"]
            row = {
                "scene": scene, "particles": last["particles"], "steps": last["steps"],
                "baseline_planned_s": statistics.median(r["wall_seconds"] for r in before),
                "planned_s": statistics.median(r["wall_seconds"] for r in after),
                "scipy_planned_s": statistics.median(r["wall_seconds"] for r in scipy_only),
                "inline_planned_s": statistics.median(r["wall_seconds"] for r in inline),
                "inline_command_s": statistics.median(r["command_seconds"] for r in inline),
                "baseline_least_s": min(r["wall_seconds"] for r in before),
                "least_s": min(r["wall_seconds"] for r in after),
                "baseline_command_s": statistics.median(r["command_seconds"] for r in before),
                "command_s": statistics.median(r["command_seconds"] for r in after),
                "step_median_ms": 1e3 * steps["median"], "step_p90_ms": 1e3 * steps["p90"],
                "step_max_ms": 1e3 * steps["max"],
                "passes": len(last["planner_passes"]), "baseline_passes": len(before[-1]["planner_passes"]),
                "newton": last["newton_iterations"], "solves": last["equilibrium_solves"],
                "factorizations": last["solver"]["factorizations"], "linear_solves": last["solver"]["linear_solves"],
                "baseline_exit_mm": before[-1]["exit_error_mm"], "exit_mm": last["exit_error_mm"],
                "backend": last["solver"]["linear_solver_backend"],
            }
            row["speedup"] = row["baseline_planned_s"] / row["planned_s"]
            row["scipy_speedup"] = row["baseline_planned_s"] / row["scipy_planned_s"]
            row["inline_speedup"] = row["baseline_planned_s"] / row["inline_planned_s"]
            row["least_speedup"] = row["baseline_least_s"] / row["least_s"]
            rows.append(row)
            print(f"{scene}: planned run {row['baseline_planned_s']:.2f} s at {BASELINE} -> {row['planned_s']:.2f} s "
                  f"({row['speedup']:.1f}x; scipy only {row['scipy_planned_s']:.2f} s, {row['scipy_speedup']:.1f}x; "
                  f"replays in the process {row['inline_planned_s']:.2f} s, {row['inline_speedup']:.1f}x), "
                  f"steps median {row['step_median_ms']:.1f} ms, p90 "
                  f"{row['step_p90_ms']:.1f} ms; whole command {row['command_s']:.2f} s", flush=True)
    return rows


def verified_command(scene: str = "sh12_100x100") -> dict:
    """`plan CONFIG --no-compare` with the default verification, now: median process wall time
    of REPEATS, and the verification's share (the summary's replay times)."""
    with tempfile.TemporaryDirectory() as folder:
        records = [run_plan_command(common.REPO_ROOT, scene, ["--no-compare"], Path(folder)) for _ in range(REPEATS)]
    record = records[-1]
    return {"scene": scene, "command_s": statistics.median(r["command_seconds"] for r in records),
            "planned_s": record["wall_seconds"], "verified_mm": record["verified_exit_error_mm"],
            "rounds": len(record["verification"]["rounds"])}


@contextlib.contextmanager
def switched(changes: dict):
    """Module attributes set to other values ({(module, name): value}) while it is open."""
    saved = {key: getattr(*key) for key in changes}
    for (module, name), value in changes.items():
        setattr(module, name, value)
    try:
        yield
    finally:
        for (module, name), value in saved.items():
            setattr(module, name, value)


def levers() -> list[tuple]:
    """The planned run with each lever off in turn: (scene, label, median s, least s, median s of
    tip tracking, Newton iterations, linear solves, right-hand-side columns they took,
    factorizations, planned exit error mm); the counts are every planner pass's, as the plan
    summary's (planning.planner.planning_work)."""
    from dataclasses import replace

    import numpy as np

    import stitchplan.needle.equilibrium as equilibrium
    import stitchplan.needle.insertion as insertion
    import stitchplan.needle.newton as newton
    import stitchplan.needle.prepared_tissue as prepared_tissue
    import stitchplan.needle.saddle_point as saddle_point
    import stitchplan.needle.tip_tracking as tip_tracking
    from stitchplan.tissue.assembly import Assembler
    import stitchplan.planning.pass_offsets as pass_offsets
    import stitchplan.planning.planner as planner
    import stitchplan.tissue.factorization as factorization
    import stitchplan.tissue.kernel as kernel
    import stitchplan.tissue.shape_functions as shape_functions
    from stitchplan.config.scenario import load_scenario

    logging.getLogger("stitchplan").setLevel(logging.ERROR)
    chosen, shared_run = saddle_point.factorize, planner.run_insertion

    class GeneralLU(factorization.SuperLUFactor):
        backend = "scipy SuperLU, default options"

        def __init__(self, matrix):
            import scipy.sparse as sp
            import scipy.sparse.linalg as spla
            self._lu = spla.splu(sp.csc_matrix(matrix), permc_spec="MMD_AT_PLUS_A")

    def own_model(scenario, **options):  # each pass builds its model and factors K0 again
        options.pop("tissue", None)
        return shared_run(scenario, **options)


    def general_stiffness_at_rest(model):
        assembler = Assembler(model)
        assembler.update(np.broadcast_to(np.eye(2), (len(model.quadrature_weights), 2, 2)).copy())
        return assembler.tangent_matrix()

    def tracked_again(_earlier, step, state):  # as a step of its own run tracks its tip
        return insertion.track_step(state, step, step * state.geometry.step)

    needle_step = insertion._needle_step

    def solved_again(*args, taken=None, **kwargs):  # a taken-over step added and solved from the earlier state
        return needle_step(*args, **kwargs)

    residuals = equilibrium.NeedleInsertion.residuals

    def stress_every_time(self, *args):  # no internal force kept from the step before
        self._last_internal = None
        return residuals(self, *args)

    class NoLDL:  # an indefinite K + H factored by SuperLU, as before CHOLMOD's L D L^T
        def __init__(self, *args):
            raise ValueError("off")

    def tolerance(residual, constraint=1e-9):  # a needle step's Newton (|r| / |f_needle|, |g| / R)
        return lambda scenario: replace(scenario, solver=replace(scenario.solver, needle_residual_tolerance=residual,
                                                                 needle_constraint_tolerance=constraint))

    def spline_by_branches(z, derivative=True):  # eq. 3.23's two pieces, both computed everywhere
        r = np.abs(z)
        inner = r <= 0.5
        rest = np.maximum(1.0 - r, 0.0)
        r2, rest2 = r * r, rest * rest
        phi = np.where(inner, 2.0 / 3.0 - 4.0 * r2 + 4.0 * r2 * r, 4.0 / 3.0 * rest2 * rest)
        if not derivative:
            return phi, None
        return phi, np.where(inner, -8.0 * r + 12.0 * r2, -4.0 * rest2) * np.sign(z)

    def one_point_by_direction(h, phi, dphi, maps, point):  # each gradient direction's sums on their own
        moment = ((h.T * phi) @ h)[None]
        inverse = shape_functions._checked_inverse(moment, point)
        b = inverse[:, :, 0]
        corrected = h @ b[0]
        if dphi is None:
            return corrected * phi, None
        grad = np.empty((len(h), 2))
        for k in range(2):
            dmoment = ((h.T * dphi[:, k]) @ h)[None]
            spread = maps[k] @ moment
            dmoment += spread + spread.transpose(0, 2, 1)
            weights = -(inverse @ (dmoment @ b[:, :, None]))[:, :, 0] + b @ maps[k]
            grad[:, k] = (h @ weights[0]) * phi + corrected * dphi[:, k]
        return corrected * phi, grad

    backend = factorization.factorize(_spd_probe(), symmetric_positive=True).backend
    settings = [  # (scene, label, module attributes, scenario change)
        ("sh12_100x100", f"all levers (now; {backend})", {}, None),
        ("sh12_100x100", "without Anderson mixing", {(newton, "ANDERSON_DEPTH"): 0}, None),
        ("sh12_100x100", "centre columns re-solved every iteration", {(newton, "STALE_CENTER_MOVES"): 0.0}, None),
        ("sh12_100x100", "centre columns solved with the factor (not from the kept K^-1 E^T)",
         {(equilibrium, "CENTER_COLUMNS_ON_ROWS"): False}, None),
        ("sh12_100x100", "SuperLU in symmetric mode (without the `fast` extra, where the band is wide)",
         {(saddle_point, "factorize"): lambda m, **_: factorization.SuperLUFactor(m),
          (prepared_tissue, "factorize"): lambda m, **_: factorization.SuperLUFactor(m)}, None),
        ("sh12_100x100", "SuperLU without symmetric mode",
         {(saddle_point, "factorize"): lambda m, **_: GeneralLU(m),
          (prepared_tissue, "factorize"): lambda m, **_: GeneralLU(m)}, None),
        ("sh12_100x100", "tip tracking by scipy's Levenberg-Marquardt only (no Newton first)",
         {(tip_tracking, "NEWTON_TIP_ITERATIONS"): 0}, None),
        ("sh12_100x100", "needle tolerances 5e-6 and 1e-9 R (the defaults before 1e-3 and 1e-7 R)", {},
         tolerance(5e-6)),
        ("sh12_100x100", "residual tolerance 1e-6 (the default before 5e-6)", {}, tolerance(1e-6)),
        ("sh12_100x100", "residual tolerance 1e-8 (the default before 1e-6)", {}, tolerance(1e-8)),
        ("sh12_100x100", "K0 as B^T diag(w A) B over the 4 nq rows of B (not from the direction gradients)",
         {(prepared_tissue, "stiffness_at_rest"): general_stiffness_at_rest}, None),
        ("needle20_entry25", "all levers (now)", {}, None),
        ("needle20_entry25", "needle tolerances 5e-6 and 1e-9 R (the defaults before 1e-3 and 1e-7 R)", {},
         tolerance(5e-6)),
        ("needle20_entry25", "residual tolerance 1e-6 (the default before 5e-6)", {}, tolerance(1e-6)),
        ("needle20_entry25", "tip Newton stopped at a step below 1e-8 R (not 1e-6 R)",
         {(tip_tracking, "NEWTON_TIP_STOP"): 1e-8}, None),
        ("needle20_entry25", "centre columns solved with the factor (not from the kept K^-1 E^T)",
         {(equilibrium, "CENTER_COLUMNS_ON_ROWS"): False}, None),
        ("needle20_entry25", "the cubic spline by its two branches (not its truncated powers)",
         {(kernel, "cubic_spline"): spline_by_branches}, None),
        ("needle20_entry25", "one point's shape-function gradients a direction at a time (tip tracking)",
         {(shape_functions, "_one_point"): one_point_by_direction}, None),
        ("sh12_100x30", "all levers (now; 2 planner passes)", {}, None),
        ("sh12_100x30", "its indefinite K + H factored by SuperLU (not CHOLMOD's L D L^T)",
         {(factorization, "LDLFactor"): NoLDL}, None),
        ("sh12_100x30", "the taken-over steps' tip points tracked again", {(insertion, "_tracked_before"): tracked_again}, None),
        ("sh12_100x30", "the taken-over steps solved again from the first pass's states (no take-over)",
         {(insertion, "_needle_step"): solved_again}, None),
        ("sh12_100x30", "every residual evaluates the stress (none kept where the step before ended)",
         {(equilibrium.NeedleInsertion, "residuals"): stress_every_time}, None),
        ("sh12_100x30", "each pass builds its own model and factors K0", {(planner, "run_insertion"): own_model}, None),
        ("sh12_100x30", "the second pass solves every step (its offset from step 1, no PassPrefix)",
         {(pass_offsets, "REAIM_FRACTION"): 0.0}, None),
    ]
    # every variant once per round, REPEATS rounds: the machine's speed drifts over minutes,
    # so each variant's runs are spread over the same span
    scenarios, warmed = [], set()
    for scene, _, _, change_scenario in settings:
        scenario = load_scenario(common.REPO_ROOT / "configs" / f"{scene}.yaml")
        scenarios.append(change_scenario(scenario) if change_scenario else scenario)
        if scene not in warmed:
            planner.run_plan(scenarios[-1], compare=False)
            warmed.add(scene)
    results: list[list] = [[] for _ in settings]
    for round_number in range(LEVER_REPEATS):
        # each round starts at another variant (in a fixed order K0 by the general product ran
        # 20 % faster than `now` in two tables, and as fast when the two alternate), and the
        # garbage of the runs before is collected before each run, not within it
        start = round_number * len(settings) // LEVER_REPEATS
        for index in [*range(start, len(settings)), *range(start)]:
            (scene, label, changes, _), scenario, runs = settings[index], scenarios[index], results[index]
            gc.collect()
            with switched(changes):
                runs.append(planner.run_plan(scenario, compare=False))
    rows = []
    for (scene, label, _, _), runs in zip(settings, results):
        work = planner.planning_work(runs[-1])  # every pass's, as the summary counts them
        counts = work["solver"]
        rows.append((scene, label, statistics.median(r.planned.wall_seconds for r in runs),
                     min(r.planned.wall_seconds for r in runs),
                     statistics.median(r.planned.timings["tip_tracking"] for r in runs),
                     work["newton_iterations"], counts["linear_solves"],
                     counts["solved_columns"], counts["factorizations"], runs[-1].planned.exit_error_mm))
        print(f"{scene} {label}: {rows[-1][2]:.2f} s (least {rows[-1][3]:.2f} s), {rows[-1][5]} Newton iterations",
              flush=True)
    assert saddle_point.factorize is chosen and planner.run_insertion is shared_run
    return rows


def verified_warm_starts(scene: str = "sh12_100x100") -> list[tuple]:
    """plan_verified (the default `plan`'s runs: planned passes, replays on the refined model,
    a second round) in process, with the second round's replay started from the first's
    (now) and started cold: (scene, label, median s, rounds, replay seconds, verified exit
    error mm)."""
    import stitchplan.planning.pass_offsets as pass_offsets
    import stitchplan.planning.replays as replays
    import stitchplan.planning.verification as verification
    from stitchplan.config.scenario import load_scenario

    logging.getLogger("stitchplan").setLevel(logging.ERROR)
    scenario = load_scenario(common.REPO_ROOT / "configs" / f"{scene}.yaml")
    shared = replays.run_insertion  # the replays' (in this process: plan_verified's default)

    def cold_run(scenario, **options):
        options.pop("start_from", None)
        return shared(scenario, **options)

    variants = (("second replay started from the first (now)", {}),
                ("second replay started cold", {(replays, "run_insertion"): cold_run}),
                ("second round's passes solve every step (no PassPrefix)", {(pass_offsets, "REAIM_FRACTION"): 0.0}))
    seconds: dict[str, list] = {label: [] for label, _ in variants}
    results: dict[str, list] = {label: [] for label, _ in variants}
    for _ in range(REPEATS):  # every variant once per round, as in levers()
        for label, changes in variants:
            with switched(changes):
                start = time.perf_counter()
                results[label].append(verification.plan_verified(scenario, compare=False))
                seconds[label].append(time.perf_counter() - start)
    rows = []
    for label, _ in variants:
        result = results[label][-1]
        rounds = result.verification.rounds
        rows.append((scene, label, statistics.median(seconds[label]), len(rounds),
                     " / ".join(f"{r['replay_wall_seconds']:.2f}" for r in rounds),
                     result.verification.exit_error_mm))
        print(f"verified {scene} {label}: {rows[-1][2]:.2f} s", flush=True)
    assert replays.run_insertion is shared
    return rows


def replay_renewals(scenes: tuple[str, ...] = ("sh12_100x30", "wound_closure")) -> list[tuple]:
    """The shipped trajectory (sample_runs/SCENE/trajectory.csv) replayed at half the spacing,
    as the verification does, with the factor of K + H renewed as now (a prescribed centre:
    only when the iteration's measure exceeds both of the last two) and as a planner's step renews it
    (contraction below REFACTOR_CONTRACTION), alternating, median of REPEATS: (scene,
    variant, s, factorizations, Newton iterations, exit error mm)."""
    import stitchplan.needle.newton as newton
    from stitchplan.config.scenario import load_scenario
    from stitchplan.io.readers import read_center_path
    from stitchplan.needle.geometry import scenario_needle
    from stitchplan.needle.insertion import run_insertion
    from stitchplan.planning.replay_models import rescaled

    logging.getLogger("stitchplan").setLevel(logging.ERROR)
    now = newton.renew_factor
    variants = (("now: renewed when the measure exceeds the last two", now),
                ("renewed as a planner's step renews it", lambda measure, previous, earlier, planned:
                 now(measure, previous, earlier, True)))
    rows = []
    for scene in scenes:
        scenario = load_scenario(common.REPO_ROOT / "configs" / f"{scene}.yaml")
        path = read_center_path(common.REPO_ROOT / "sample_runs" / scene / "trajectory.csv",
                                scenario_needle(scenario))
        fine = rescaled(scenario, 0.5)
        results: dict[str, list] = {label: [] for label, _ in variants}
        for _ in range(REPEATS):
            for label, rule in variants:
                with switched({(newton, "renew_factor"): rule}):
                    start = time.perf_counter()
                    replayed = run_insertion(fine, center_path=path)
                    results[label].append((time.perf_counter() - start, replayed))
        for label, _ in variants:
            replayed = results[label][-1][1]
            rows.append((scene, label, statistics.median(t for t, _ in results[label]),
                         replayed.solver_counts["factorizations"], sum(s.newton_iterations for s in replayed.steps),
                         replayed.exit_error_mm))
            print(f"replay {scene} {label}: {rows[-1][2]:.2f} s", flush=True)
    return rows


def _spd_probe():
    """A small symmetric positive definite matrix, to ask which backend factorize picks."""
    import scipy.sparse as sp
    return sp.diags([4.0, 4.0, 4.0]) + sp.eye(3, k=1) + sp.eye(3, k=-1)


def startup() -> dict[str, float]:
    """The installed `stitchplan` script beside this interpreter (as a virtual environment
    has it), else `python -m stitchplan`."""
    script = Path(sys.executable).parent / "stitchplan"
    command = [str(script)] if script.exists() else [sys.executable, "-m", "stitchplan"]
    seconds = {}
    for arguments in (["--help"], ["--version"]):
        samples = []
        for _ in range(STARTUP_REPEATS):
            start = time.perf_counter()
            subprocess.run([*command, *arguments], check=True, capture_output=True, cwd=common.REPO_ROOT,
                           env=common.command_environment())
            samples.append(time.perf_counter() - start)
        seconds[" ".join([Path(command[0]).name, *command[1:], *arguments])] = statistics.median(samples)
    return seconds


def ending() -> dict[str, float]:
    """`simulate configs/sh12_100x100.yaml --no-estimate` ended by the console entry point
    (cli.main: exit functions, then no module teardown) and by the app itself (the
    interpreter's ordinary exit; the collector paused for the imports as cli.main pauses it,
    stitchplan/allocator.py, so that only the end differs), alternating, median of
    STARTUP_REPEATS."""
    scenario = str(common.REPO_ROOT / "configs" / "sh12_100x100.yaml")
    entries = {"console entry point (cli.main)": "from stitchplan.cli import main as run",
               "the app's ordinary exit (cli.app)": "from stitchplan.allocator import pause_collection; "
                                                    "pause_collection(command_start=True); "
                                                    "from stitchplan.cli import app as run"}
    samples: dict[str, list[float]] = {label: [] for label in entries}
    for _ in range(STARTUP_REPEATS):
        for label, entry in entries.items():
            script = f"import sys; {entry}; sys.argv = ['stitchplan', 'simulate', {scenario!r}, '--no-estimate']; run()"
            start = time.perf_counter()
            subprocess.run([sys.executable, "-c", script], check=True, capture_output=True, cwd=common.REPO_ROOT,
                           env=common.command_environment())
            samples[label].append(time.perf_counter() - start)
    return {f"simulate sh12_100x100 --no-estimate, {label}": statistics.median(values)
            for label, values in samples.items()}


def allocator_rows(scenes: tuple[str, ...] = ("needle20_entry30", "needle20_entry18", "sh12_100x100"),
                   verified: str = "sh12_100x100") -> list[tuple]:
    """`plan CONFIG --no-compare --no-verify` on `scenes` and the default verified `plan
    VERIFIED --no-compare`, with glibc malloc's thresholds set as the command sets them
    (stitchplan/allocator.py) and with glibc's default, alternating, REPEATS each: (command,
    variant, median planned run s, median whole command s, median page faults of the process
    and its helper, median peak memory of the command's process MiB)."""
    import resource

    variants = {"thresholds set (now)": "",
                "glibc's default": "import stitchplan.allocator as a; a.reuse_freed_memory = lambda: False; "}
    commands = [(scene, ["--no-verify"]) for scene in scenes] + [(verified, [])]
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch)
        summary, peak = folder / "summary.json", folder / "peak"
        for scene, options in commands:
            samples: dict[str, list[tuple[float, float, int, float]]] = {label: [] for label in variants}
            for repeat in range(REPEATS):
                for label in variants if repeat % 2 == 0 else reversed(variants):
                    arguments = ["stitchplan", "plan", str(common.REPO_ROOT / "configs" / f"{scene}.yaml"),
                                 "--no-compare", *options, "-q", "--export", str(folder / "trajectory.csv"),
                                 "--summary", str(summary)]
                    # VmHWM: the resident set's high-water mark of this process's own memory
                    # (ru_maxrss also counts the memory of the process it was forked from)
                    script = (f"import atexit, sys; {variants[label]}"
                              f"atexit.register(lambda: open({str(peak)!r}, 'w').write(next("
                              "line.split()[1] for line in open('/proc/self/status') if line.startswith('VmHWM')))); "
                              f"from stitchplan.cli import main; sys.argv = {arguments!r}; main()")
                    faults = resource.getrusage(resource.RUSAGE_CHILDREN).ru_minflt
                    start = time.perf_counter()
                    subprocess.run([sys.executable, "-c", script], check=True, capture_output=True,
                                   cwd=common.REPO_ROOT, env=common.command_environment())
                    seconds = time.perf_counter() - start
                    faults = resource.getrusage(resource.RUSAGE_CHILDREN).ru_minflt - faults
                    planned = json.loads(summary.read_text())["wall_seconds"]
                    samples[label].append((planned, seconds, faults, int(peak.read_text()) / 1024))
            command = f"plan {scene} --no-compare {' '.join(options)}".strip()
            for label, values in samples.items():
                rows.append((command, label, *(statistics.median(v[i] for v in values) for i in range(4))))
                print(f"allocator {command} {label}: planned {rows[-1][2]:.4f} s, whole {rows[-1][3]:.3f} s, "
                      f"{rows[-1][4]:.0f} page faults, peak {rows[-1][5]:.0f} MiB", flush=True)
    return rows


def main() -> None:
    with tempfile.TemporaryDirectory() as extracted:
        rows = compare_revisions(common.extract_revision(BASELINE, Path(extracted)))
    lever_rows = levers()
    warm_rows = verified_warm_starts()
    verified = verified_command()
    renewal_rows = replay_renewals()
    allocator = allocator_rows()
    start_up = {**startup(), **ending()}
    for label, seconds in start_up.items():
        print(f"{label}: {seconds:.3f} s", flush=True)

    header = ["scene", "particles", "steps", "baseline_planned_s", "planned_s", "speedup", "scipy_planned_s",
              "scipy_speedup", "inline_planned_s", "inline_speedup", "baseline_least_s", "least_s",
              "least_speedup", "step_median_ms", "step_p90_ms", "step_max_ms", "newton", "solves", "factorizations",
              "linear_solves", "passes", "baseline_passes", "baseline_exit_mm", "exit_mm", "baseline_command_s",
              "command_s", "inline_command_s"]
    common.write_csv(common.results_path("plan_speed.csv"), header, [[r[k] for k in header] for r in rows])
    load = os.getloadavg()[0]
    lines = [
        "# Speed of `stitchplan plan`\n",
        f"Generated by `python benchmarks/plan_speed.py` ({common.machine_note()}; load average "
        f"{load:.1f} at the end). Linear solver: {rows[0]['backend']}.\n",
        f"## Planned run before ({BASELINE}) and now, side by side (median of {REPEATS})\n",
        "Now: with the installed backend (above); *scipy only*: the same code with "
        "STITCHPLAN_LINEAR_BACKEND=scipy, the path without the `fast` extra (LAPACK's banded Cholesky where "
        "the band is narrow, SuperLU elsewhere: stitchplan/tissue/factorization.py); *replays in the process*: "
        "STITCHPLAN_REPLAY_HELPER=0, the exit-error estimate's replay at 2h after the planned run in the "
        "command's process instead of in the helper alongside it (planning/replays.py; forked as the "
        "command starts, stitchplan/early_helper.py), which slows the planned run a little by running "
        f"at the same time (benchmarks/results/replay_helper.md), as no helper did at {BASELINE}. Steps: "
        "with the installed backend.\n",
        f"The planned run is the summary's `wall_seconds` of `plan CONFIG --no-compare` at {BASELINE} and of "
        "`plan CONFIG --no-compare --no-verify` now (the same run; verification did not exist then). "
        f"{BASELINE} runs each scene's file as it was shipped until 2026-12-05 (the default spacing, "
        "graded to half of it at the needle); now runs the file as shipped now, whose particles are graded "
        "from twice the default spacing to 1.25 needle steps at the needle on the SH 1/2 blocks "
        "(benchmarks/results/needle_coupling.md, coupling `shipped`): the same scene planned, before and after. "
        "Steps: wall time of each needle step (tip tracking, equilibrium and the planner's centre). "
        "Newton: every iteration of every solve, now one equilibrium solve per step (the centre is an "
        f"unknown of the step's Newton solve); {BASELINE}'s summary counted only the last solve of each "
        "step, so its counts are not comparable and are left out. Where a second pass ran, "
        "the counts are both passes' (the summary's totals), and the steps it takes over from the first "
        "pass (planning/planner.py PassPrefix) have the first pass's wall times.\n",
        common.markdown_table(
            ["scene", "particles", "steps", f"planned run {BASELINE} (s)", "planned run now (s)", "speed-up",
             "now with scipy only (s)", "speed-up with scipy only", "now, replays in the process (s)",
             "speed-up, replays in the process", f"least of the {REPEATS} runs {BASELINE} / now (s)",
             "speed-up of the least",
             "step median (ms)", "step p90 (ms)", "step max (ms)", "Newton iterations", "equilibrium solves",
             "factorizations", "linear solves", f"passes {BASELINE} / now", f"planned exit error {BASELINE} (mm)",
             "planned exit error now (mm)"],
            [[r["scene"], r["particles"], r["steps"], r["baseline_planned_s"], r["planned_s"],
              f"{r['speedup']:.2f}x", r["scipy_planned_s"], f"{r['scipy_speedup']:.2f}x",
              r["inline_planned_s"], f"{r['inline_speedup']:.2f}x",
              f"{r['baseline_least_s']:.4g} / {r['least_s']:.4g}", f"{r['least_speedup']:.2f}x", r["step_median_ms"], r["step_p90_ms"], r["step_max_ms"], r["newton"],
              r["solves"], r["factorizations"], r["linear_solves"], f"{r['baseline_passes']} / {r['passes']}",
              r["baseline_exit_mm"], r["exit_mm"]] for r in rows]),
        "",
        f"## Whole command (process wall time, median of {REPEATS})\n",
        "Every command here runs with Python's bytecode cache on (_common.command_environment), as an "
        "installed package has its modules compiled.\n",
        common.markdown_table(["scene", f"plan --no-compare at {BASELINE} (s)", "plan --no-compare --no-verify now (s)",
                               "now, replays in the process (s)"],
                              [[r["scene"], r["baseline_command_s"], r["command_s"], r["inline_command_s"]]
                               for r in rows]),
        "",
        f"With the default verification (`plan {verified['scene']}.yaml --no-compare`, median of {REPEATS}): "
        f"the whole command takes {verified['command_s']:.2f} s, of which the planned runs of its "
        f"{verified['rounds']} verification round(s) take {verified['planned_s']:.2f} s and the rest is the "
        f"replays on the refined model and start-up; verified exit error {verified['verified_mm']:.4f} mm.\n",
        "",
        f"## Where it comes from (planned run in process, median of {LEVER_REPEATS} rounds, each running every variant once, "
        "each round from another variant on)\n",
        "Each row switches one lever of the current code back off. The centre as a Newton unknown "
        "(needle/steering.py) is not switchable; it shows in the table above as one equilibrium solve per "
        "step instead of one per centre try. Factorizations: those the planned run made (K0's factor, "
        "shared by the passes, counts in the first). The planned exit error shows what a lever costs in "
        "accuracy: the residual tolerance moves the unplanned exit points by at most 2.5e-7 mm and the "
        "planned centres by up to 0.0023 mm (benchmarks/results/solver_tolerance.md). The least of the "
        "rounds is the run other work on this shared machine disturbed least; the medians of the same "
        "variant moved by up to 40 % between runs of this table, so only the iteration and solve counts "
        "are exact.\n",
        common.markdown_table(["scene", "variant", "planned run (s)", "least of the rounds (s)",
                               "of it tip tracking (s)", "Newton iterations",
                               "linear solves", "right-hand sides solved", "factorizations", "planned exit error (mm)"],
                              [list(row) for row in lever_rows]),
        "",
        f"The verified plan (the default `plan`'s runs, in process, median of {REPEATS}): the second "
        "round's replay on the refined model starts each step's Newton solve from the first round's replay "
        "(its change over the step added to this run's state; run_insertion `start_from`). Planner passes "
        "start cold: started from the pass before, a pass's exit error would depend on that pass (where the "
        "move limits hold the centre, it settles within the planner tolerance where the start leads it), "
        "and the thesis's table 5.1 100 x 100 block then missed the exit tolerance after four passes "
        "(benchmarks/results/thesis_table.md as generated at the commit that says so, git history). "
        "A later pass instead keeps the first pass's centres up to a few steps before its late limited "
        "steps and takes those steps over: their tip points, equilibria and needle coupling are the first "
        "pass's (planning/planner.py PassPrefix); its offset acts from there. The second round's passes "
        "are such passes, and the second replay takes over the first replay's steps while its centres are "
        "the first replay's.\n",
        common.markdown_table(["scene", "variant", "plan_verified (s)", "rounds", "replays (s)",
                               "verified exit error (mm)"], [list(row) for row in warm_rows]),
        "",
        "## Replays on the refined model: when the factor is renewed\n",
        f"The shipped trajectory replayed at half the spacing (as the verification does), median of {REPEATS}, "
        "with the factor of K + H renewed as now for a prescribed centre (only when the modified Newton "
        "iteration's convergence measure exceeds both of the last two; needle/newton.py renew_factor) and as a "
        "planner's step renews it (an iteration contracting by less than REFACTOR_CONTRACTION).\n",
        common.markdown_table(["scene", "variant", "replay (s)", "factorizations", "Newton iterations",
                               "exit error (mm)"], [list(row) for row in renewal_rows]),
        "",
        f"## The allocator (median of {REPEATS}, alternating)\n",
        "The command sets glibc malloc's mmap threshold to 32 MiB and its trim threshold to 64 MiB "
        "(stitchplan/allocator.py), where glibc's own adjustment of them ends; with glibc's default an "
        "array above the current mmap threshold (128 KiB at first) gets fresh pages from the system and "
        "gives them back when freed, and the heap's top is returned once 128 KiB is free there. Planned "
        "run: the summary's `wall_seconds` (with the default verification: its rounds' planned runs). "
        "Page faults: the command's process and its replay helper, start-up included. Peak memory: the "
        "command's process (the high-water mark of its resident set, VmHWM).\n",
        common.markdown_table(["command", "allocator", "planned run (s)", "whole command (s)", "page faults",
                               "peak memory (MiB)"], [list(row) for row in allocator]),
        "",
        f"## Start-up and end (median of {STARTUP_REPEATS})\n",
        common.markdown_table(["command", "wall (s)"], [[k, v] for k, v in start_up.items()]),
        "",
    ]
    common.write_report("plan_speed.md", lines)


if __name__ == "__main__":
    common.command_line(__doc__)
    main()
