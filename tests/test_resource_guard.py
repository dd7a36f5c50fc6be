"""The resource guard at the extremes, and what its refusals name.

Any finite positive discretization input ends in one refusal line naming the field or option
that drives the estimate past the limit (never an overflow); the advice matches the limit
that was hit (--max-particles only for the particle limit); ordinary inputs keep their
estimates; a shaped tissue is counted as the model places it; a needle run's estimate counts
what it keeps of its steps, against peaks measured at steps of 0.08-0.0025 rad. Also here: the needle
calibration's radius bounds and its numerical failures. Nothing is solved, and only the
shaped-tissue tests build models: the module runs in a few seconds.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from stitchplan.cli import app
from stitchplan.config import load_scenario, parse_scenario, with_discretization
from stitchplan.errors import InputError, NumericalFailure
from stitchplan.resources.costs import BASE_MEMORY, HELPER_BASE_MEMORY, PLAN_RUNS, VERIFICATION_RUNS, estimate
from stitchplan.resources.guard import check_resources
from stitchplan.resources.limits import Limits
from stitchplan.resources.model_size import COUNT_CAP, model_size
from stitchplan.resources.origin import Origin, verification_origin
from stitchplan.planning.replay_models import rescaled

REPOSITORY = Path(__file__).resolve().parents[1]
PHANTOM = {"model": "saint-venant-kirchhoff", "lame_lambda": 0.189151, "lame_mu": 0.147688}
# 40 x 20 mm block clamped on the right, SH needle (r 8.88 mm) entering (0, 12) cw; no
# spacing given, so the default one (graded toward the needle by the default refinement)
NEEDLE_SCENE = {
    "tissue": {"size": [40.0, 20.0], "thickness": 10.0, "material": dict(PHANTOM), "clamped": ["right"]},
    "needle": {"radius": 8.88, "entry": [0.0, 12.0], "turn": "cw", "step": 0.2, "friction": 0.0602,
               "cutting_force": 0.7},
}
LARGE_MEMORY = 64e9  # bytes: a machine where only the particle limit can refuse
SMALL_MEMORY = 4e9  # bytes: 2 GB allowed, less than a 10 000-particle model with dilation 10 needs


def scene(**changes) -> dict:
    """NEEDLE_SCENE with top-level blocks replaced, `needle__radius=...` for one needle key."""
    raw = {key: dict(value) for key, value in NEEDLE_SCENE.items()}
    for key, value in changes.items():
        if "__" in key:
            block, field = key.split("__")
            raw[block][field] = value
        else:
            raw[key] = value
    return raw


def refusal(estimates, memory: float = LARGE_MEMORY, limits: Limits | None = None) -> str:
    """The guard's one refusal line for these estimates (default limits)."""
    with pytest.raises(InputError) as error:
        check_resources(estimates, limits or Limits(), memory=memory)
    assert len(error.value.lines) == 1, error.value.lines
    return error.value.lines[0]


# --- extreme inputs: a refusal, never an overflow -------------------------------------------


@pytest.mark.parametrize("raw, name", [
    (scene(discretization={"spacing": 1e-300}), "discretization.spacing: got 1e-300 mm"),
    (scene(discretization={"spacing": 5e-324}), "discretization.spacing: got 4.94066e-324 mm"),
    (scene(discretization={"needle_refinement": 1e200}), "discretization.needle_refinement: got 1e+200"),
    (scene(discretization={"spacing": 1e-300, "needle_refinement": 1e300}),
     "discretization.spacing: got 1e-300 mm"),  # a needle spacing that underflows to 0
])
def test_extreme_spacings_are_refused_at_the_capped_count(raw, name):
    """Counts past any machine are held at COUNT_CAP, with finite costs, and the refusal
    names the field and says the count is a lower bound."""
    item = estimate(parse_scenario(raw), "insertion", "simulate")
    assert item.size.particles == COUNT_CAP
    assert math.isfinite(item.memory_bytes) and math.isfinite(item.seconds)
    line = refusal([item])
    assert line.startswith(name), line
    assert f"at most {Limits().max_particles} particles" in line and "over 1e+15 particles" in line


def test_an_extreme_dilation_and_needle_step_are_refused():
    scenario = parse_scenario(scene())
    wide = with_discretization(scenario, dilation=1e300)
    assert model_size(wide).neighbours == math.inf
    line = refusal([estimate(wide, "insertion")])
    assert line.startswith("discretization.dilation: got 1e+300, expected at most 10")
    tiny_step = parse_scenario(scene(needle__step=5e-324))
    item = estimate(tiny_step, "insertion")
    assert item.steps == COUNT_CAP
    assert refusal([item]).startswith("needle.step: got 4.94066e-324 rad, expected a step giving at most 2000")


@pytest.mark.parametrize("discretization, fragment", [
    ({"spacing": 11.0}, "discretization.spacing: got 11 mm, expected at most half the tissue's smaller side "
                        "(40 x 20 mm)"),
    ({"spacing": 9.0, "needle_spacing": None}, "discretization.spacing: got 9 mm, expected a spacing at the "
                                               "needle of at most its radius, 8.88 mm"),
    ({"spacing": 9.5, "needle_spacing": 9.0}, "discretization.needle_spacing: got 9 mm, expected a spacing at "
                                              "the needle of at most its radius"),
    ({"spacing": 10.0, "needle_refinement": 1.1}, "discretization.spacing: got 10 mm (a needle spacing of "
                                                  "9.09 mm), expected"),
])
def test_a_model_too_coarse_for_its_tissue_or_needle_is_refused(discretization, fragment):
    """A spacing typed wrong the other way: fewer than three particles across the tissue,
    or a needle spacing past the needle's radius, runs to numbers that mean nothing."""
    raw = scene(discretization={k: v for k, v in discretization.items() if v is not None})
    line = refusal([estimate(parse_scenario(raw), "insertion", "simulate")])
    assert line.startswith(fragment), line
    assert line.endswith("refine it, or pass --no-resource-check to run it anyway")
    # at the bounds it runs
    fine = scene(discretization={"spacing": 8.88, "needle_refinement": 1.0})
    check_resources([estimate(parse_scenario(fine), "insertion")], memory=LARGE_MEMORY)
    check_resources([estimate(parse_scenario({**NEEDLE_SCENE, "needle": None,
                                              "discretization": {"spacing": 10.0}}), "deform")],
                    memory=LARGE_MEMORY)


def test_a_study_family_too_coarse_names_the_coarse_spacing_its_grading_makes():
    """A study's spacing is the one at the needle: a graded family's coarse spacing is a
    multiple of it, and the refusal says which number broke the bound."""
    raw = scene(tissue={**NEEDLE_SCENE["tissue"], "size": [100.0, 30.0]},
                discretization={"spacing": 24.0, "needle_spacing": 6.0})
    study = Origin({"spacing": "study.spacing", "needle_spacing": "study.spacing"},
                   {"spacing": 6.0, "needle_spacing": 6.0})
    line = refusal([estimate(parse_scenario(raw), "insertion", "study run 'graded x4 h=6 mm'", origin=study)])
    assert line.startswith("study.spacing: got 6 mm (a coarse spacing of 24 mm), expected at most half the "
                           "tissue's smaller side (100 x 30 mm)"), line


def test_the_cli_refuses_a_spacing_too_coarse_for_the_needle(tmp_path):
    path = write(tmp_path, scene(tissue={**NEEDLE_SCENE["tissue"], "size": [60.0, 40.0]}))
    result = CliRunner().invoke(app, ["simulate", str(path), "--spacing", "19", "--summary",
                                      str(tmp_path / "summary.json")])
    assert result.exit_code == 2, result.output
    assert result.stderr.strip() == ("error: --spacing: got 19 mm (a needle spacing of 9.5 mm), expected a spacing "
                                     "at the needle of at most its radius, 8.88 mm, so that the particles follow "
                                     "the needle's curve; refine it, or pass --no-resource-check to run it anyway")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.yaml"]


def with_step(scenario, step: float, **needle):
    """The scenario with another needle step (rad), and other needle keys if given."""
    return replace(scenario, needle=replace(scenario.needle, step=step, **needle))


def write(folder: Path, raw: dict, name: str = "scene.yaml") -> Path:
    path = folder / name
    path.write_text(yaml.safe_dump(raw))
    return path


@pytest.mark.parametrize("raw, options, fragments", [
    (scene(), ["--spacing", "1e-300"], ["got 1e-300 mm", "over 1e+15 particles"]),
    (scene(needle__radius=1e-200), [], ["scene.yaml: needle.radius: got 1e-200, expected a number between 0.05"]),
    (scene(discretization={"needle_refinement": 1e200}), [],
     ["scene.yaml: discretization.needle_refinement: got 1e+200", "2 mm / 1e+200"]),
    (scene(discretization={"needle_refinement": 1000}), [],
     ["scene.yaml: discretization.needle_refinement: got 1000", "lower it", "--max-particles"]),
    (scene(), ["--dilation", "1e300"], ["--dilation: got 1e+300"]),
])
def test_the_cli_refuses_extreme_inputs_in_one_line(tmp_path, raw, options, fragments):
    path = write(tmp_path, raw)
    result = CliRunner().invoke(app, ["simulate", str(path), "--no-estimate", "--summary",
                                      str(tmp_path / "summary.json"), *options])
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output and result.stdout == ""
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.yaml"]


# --- what a refusal names -------------------------------------------------------------------


def test_a_refusal_names_the_option_or_block_its_origin_gives():
    scenario = with_discretization(parse_scenario(scene()), spacing=0.01)
    line = refusal([estimate(scenario, "insertion", "simulate", origin=Origin({"spacing": "--spacing"}))])
    assert line.startswith("--spacing: got 0.01 mm, expected a spacing giving at most 50000 particles")
    study = Origin({"spacing": "study.spacing", "needle_spacing": "study.spacing"})
    uniform = scenario.discretization.replaced(spacing=0.02, needle_spacing=None, needle_refinement=None)
    line = refusal([estimate(replace(scenario, discretization=uniform), "insertion", "study run", origin=study)])
    assert line.startswith("study.spacing: got 0.02 mm")


def test_the_verification_refusal_names_the_given_spacing_and_how_to_skip_it():
    """The plan's model fits and its verification at half the spacing does not: the refusal
    names the spacing as given (not halved) and offers --no-verify."""
    scenario = with_discretization(parse_scenario(scene()), spacing=0.2)
    limit = Limits(max_particles=estimate(scenario, "insertion").size.particles)  # the plan's model just fits
    plan = estimate(scenario, "insertion", "plan", 4)
    verification = estimate(rescaled(scenario, 0.5), "insertion", "plan verification", 2,
                            origin=verification_origin(scenario, {"spacing": "--spacing"}))
    line = refusal([plan, verification], limits=limit)
    assert line.startswith("--spacing: got 0.2 mm, expected a spacing giving at most")
    assert "in the plan's verification at half the spacing" in line
    assert "pass --no-verify to skip the verification" in line and "raise --max-particles" in line


def test_a_refinement_names_the_refinement_not_the_spacing():
    """The coarse spacing alone would fit: the needle zone's refinement (or its own spacing)
    makes the particles too many; the default refinement of 2 follows the spacing, which is
    then named."""
    refined = estimate(parse_scenario(scene(discretization={"spacing": 2.0, "needle_refinement": 1000})), "insertion")
    line = refusal([refined])
    assert line.startswith("discretization.needle_refinement: got 1000, expected a refinement giving at most")
    assert "a needle spacing of 2 mm / 1000 = 0.002 mm" in line
    fine_zone = estimate(parse_scenario(scene(discretization={"spacing": 2.0, "needle_spacing": 0.005})), "insertion")
    assert refusal([fine_zone]).startswith("discretization.needle_spacing: got 0.005 mm")
    default = estimate(parse_scenario(scene(discretization={"spacing": 0.02, "needle_refinement": 2})), "insertion")
    assert refusal([default]).startswith("discretization.spacing: got 0.02 mm")
    # a plan's verification: the file's refinement at half its spacing, both needle spacings said
    scenario = parse_scenario(scene(discretization={"spacing": 2.0, "needle_refinement": 500}))
    verification = estimate(rescaled(scenario, 0.5), "insertion", "plan verification", 2,
                            origin=verification_origin(scenario))
    line = refusal([verification])
    assert line.startswith("discretization.needle_refinement: got 500, expected a refinement giving at most"), line
    assert "a needle spacing of 2 mm / 500 = 0.004 mm, the replay's 1 mm / 500 = 0.002 mm;" in line
    assert "; lower it, pass --no-verify" in line
    # the spacing given by --spacing: coarsening it is offered beside lowering the refinement
    by_option = estimate(rescaled(scenario, 0.5), "insertion", "plan verification", 2,
                         origin=verification_origin(scenario, {"spacing": "--spacing"}))
    assert "; lower it or coarsen --spacing, pass --no-verify" in refusal([by_option])


def test_a_needle_radius_that_sets_the_default_spacing_is_named():
    """A file giving no spacing gets one from the needle radius: a tiny radius is named,
    and with --spacing given the spacing is."""
    scenario = parse_scenario(scene(needle__radius=0.05))
    line = refusal([estimate(scenario, "insertion")])
    assert line.startswith("needle.radius: got 0.05 mm, expected a radius whose default particle spacing")
    given = with_discretization(scenario, spacing=0.004)
    line = refusal([estimate(given, "insertion", origin=Origin({"spacing": "--spacing"}))])
    assert line.startswith("--spacing: got 0.004 mm")


def long_slab(**tissue) -> dict:
    """A 4000 x 10 mm slab under an edge load, giving no spacing: the default, a twentieth of
    the smaller side (0.5 mm), puts ~170 000 particles in it."""
    return {"tissue": {"size": [4000.0, 10.0], "thickness": 10.0, "material": dict(PHANTOM), "clamped": ["right"],
                       **tissue},
            "loads": [{"segment": [[0.0, 4.0], [0.0, 6.0]], "force": [-3.0, 1.0]}], "load_steps": 10}


def test_a_default_spacing_set_by_the_tissue_size_names_the_size():
    """A file giving no spacing gets one from the tissue's size (without a needle, or where
    a needle's radius does not set it): the refusal names the size, as a default that
    follows the needle radius names the radius, and a spacing given in the file or by an
    option is named as given."""
    scenario = parse_scenario(long_slab())
    line = refusal([estimate(scenario, "deform")])
    assert line.startswith("tissue.size: got [4000, 10] mm, expected a size whose default particle spacing "
                           "(here 0.5 mm) gives at most 50000 particles"), line
    assert line.endswith("check that it is in mm, or give discretization.spacing, or raise --max-particles or "
                         "pass --no-resource-check to run it anyway")
    line = refusal([estimate(scenario, "deform")], memory=SMALL_MEMORY, limits=Limits(max_particles=10**9))
    assert line.startswith("tissue.size: got [4000, 10] mm, expected a model within 50% of the 4 GB"), line
    given = with_discretization(scenario, spacing=0.4)
    assert refusal([estimate(given, "deform")]).startswith("discretization.spacing: got 0.4 mm")
    option = estimate(given, "deform", origin=Origin({"spacing": "--spacing"}))
    assert refusal([option]).startswith("--spacing: got 0.4 mm")
    # a needle scene whose default is held by the tissue's size (an eighth of the smaller
    # side, 2.5 mm, below 2/5 of the 8.88 mm radius)
    wide = parse_scenario(scene(tissue={**NEEDLE_SCENE["tissue"], "size": [4000.0, 20.0]}))
    line = refusal([estimate(wide, "insertion", "simulate")], limits=Limits(max_particles=5000))
    assert line.startswith("tissue.size: got [4000, 20] mm, expected a size whose default particle spacing "
                           "(here 2.5 mm) gives at most 5000 particles"), line


def test_the_cli_names_the_tissue_size_that_sets_a_default_spacing(tmp_path):
    path = write(tmp_path, long_slab())
    result = CliRunner().invoke(app, ["deform", str(path), "--probes-out", str(tmp_path / "probes.csv")])
    assert result.exit_code == 2, result.output
    (line,) = result.stderr.splitlines()
    assert line.startswith(f"error: {path}: tissue.size: got [4000, 10] mm, expected a size whose default "
                           "particle spacing (here 0.5 mm) gives at most 50000 particles"), line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.yaml"]


# --- the memory limit: what governs it -------------------------------------------------------


@pytest.mark.parametrize("changes, name", [
    ({"dilation": 10.0}, "discretization.dilation: got 10"),
    ({"cells_per_spacing": 4, "dilation": 2.0}, "discretization.cells_per_spacing: got 4"),
    ({"quadrature_order": 8, "dilation": 2.0}, "discretization.quadrature_order: got 8"),
])
def test_a_kernel_past_the_memory_share_names_the_kernel_not_the_particle_limit(changes, name):
    """10 000 particles fit the memory with a standard kernel, not with a wide support or
    many quadrature points: the refusal names that setting, and --max-particles (which does
    not lift the memory limit) is not offered."""
    scenario = parse_scenario(scene(discretization={"spacing": 0.2, **changes}))
    item = estimate(scenario, "insertion", "simulate")
    assert item.size.particles < Limits().max_particles
    line = refusal([item], memory=SMALL_MEMORY)
    assert line.startswith(f"{name}, expected a model within 50% of the 4 GB of memory available"), line
    assert "lower it" in line and "--no-resource-check" in line and "--max-particles" not in line


def test_particles_past_the_memory_share_name_the_spacing():
    scenario = with_discretization(parse_scenario(scene(discretization={"spacing": 1.0})), spacing=0.15)
    line = refusal([estimate(scenario, "insertion", origin=Origin({"spacing": "--spacing"}))], memory=SMALL_MEMORY,
                   limits=Limits(max_particles=10**9))
    assert line.startswith("--spacing: got 0.15 mm, expected a model within 50% of the 4 GB")
    assert "coarsen it" in line and "--max-particles" not in line


def test_the_memory_refusal_of_the_cli_does_not_offer_max_particles(tmp_path, monkeypatch):
    """The reproducer: dilation 10 with --max-particles raised is still refused, and the
    line says what governs the memory (on a machine with SMALL_MEMORY available)."""
    monkeypatch.setattr("stitchplan.resources.guard.available_memory", lambda: SMALL_MEMORY)
    path = write(tmp_path, scene(discretization={"spacing": 0.2}))
    result = CliRunner().invoke(app, ["simulate", str(path), "--no-estimate", "--dilation", "10",
                                      "--max-particles", "1000000"])
    assert result.exit_code == 2, result.output
    (line,) = result.stderr.splitlines()
    assert "dilation: got 10, expected a model within 50% of the 4 GB of memory available" in line
    assert "--max-particles" not in line and "Traceback" not in result.output


# --- what a needle run keeps of its steps ------------------------------------------------------


def sh12(step: float, name: str = "sh12_100x100", **needle):
    return with_step(load_scenario(REPOSITORY / "configs" / f"{name}.yaml"), step, **needle)


def test_a_needle_run_is_estimated_to_keep_its_dense_blocks():
    """Every step's state keeps the saddle-point solver's E K^-1, (2Q, n) after the last step
    with 2Q = 4 x the steps (the mortar coupling's two Gauss points per segment, two
    directions each), and its E K^-1 E^T, (2Q, 2Q), while 2Q <= n: at 0.0025 rad on SH 1/2, 2Q
    passes n = 2 x 642 at step ~321 of 1257; the last E K^-1 alone is ~52 MB, the last
    E K^-1 E^T kept at least (2Q)^2 = n^2 floats (a (2Q)^2 block to the end would be ~200 MB,
    whose doubling buffers put the estimate past 2.1x the measured peak,
    test_the_memory_estimate_bounds_the_measured_peaks). The point coupling's states also keep
    their own identity weights, sparse (k + 1 entries after step k), the last one dense."""
    item = estimate(sh12(0.0025), "insertion", "simulate")
    unknowns, rows = 2.0 * item.size.particles, 4.0 * item.steps
    assert item.steps > 1200 and rows > unknowns
    assert item.memory_bytes >= BASE_MEMORY + 8.0 * rows * unknowns + 8.0 * unknowns ** 2
    points = estimate(sh12(0.0025, coupling="points"), "insertion", "simulate")
    kept_weights = 16.0 * sum(k + 1 for k in range(1, points.steps + 1))  # sparse, 12 + 4 bytes a row
    assert points.memory_bytes >= BASE_MEMORY + kept_weights + 8.0 * (points.steps + 1) ** 2
    # a plan holds two runs' steps at once (resources.costs.HELD_RUNS), a simulate one
    plan = estimate(sh12(0.0025), "insertion", "plan", PLAN_RUNS)
    assert plan.step_memory == pytest.approx(2.0 * item.step_memory)


# peak resident memory (MiB) measured with `/usr/bin/time -f %M python -m stitchplan simulate
# CFG --no-estimate --no-resource-check` (plan: `plan CFG --no-compare --no-verify --export x.csv`,
# `compare` without --no-compare) on copies of the configs at these needle steps, remeasured when
# the SH 1/2 files were discretized for the needle (7.104 mm graded to 0.888 mm); the plans at
# 0.005 rad hold two passes' steps
MEASURED_PEAKS = [
    ("sh12_100x100", 0.08, "simulate", 89.6), ("sh12_100x100", 0.02, "simulate", 116.3),
    ("sh12_100x100", 0.01, "simulate", 168.4), ("sh12_100x100", 0.005, "simulate", 237.2),
    ("sh12_100x100", 0.0025, "simulate", 427.1), ("sh12_100x30", 0.08, "simulate", 85.9),
    ("sh12_100x30", 0.02, "simulate", 106.7), ("sh12_100x30", 0.01, "simulate", 131.8),
    ("sh12_100x30", 0.005, "simulate", 190.6), ("sh12_100x30", 0.0025, "simulate", 346.0),
    ("sh12_100x100", 0.01, "plan", 173.9), ("sh12_100x100", 0.005, "plan", 322.7),
    ("sh12_100x100", 0.005, "compare", 471.8), ("sh12_100x30", 0.005, "plan", 362.6),
]


@pytest.mark.parametrize("name, step, command, peak", MEASURED_PEAKS)
def test_the_memory_estimate_bounds_the_measured_peaks(name, step, command, peak):
    """From steps of 0.08 to 0.0025 rad (37 to 1257 taken) the measured peaks grow 4-5-fold
    (16-fold while every step's state kept E K^-1 E^T and a dense W, remeasured when they
    stopped); the estimate stays above 0.85 of each (the 100 x 30 block's plan of two passes
    at 0.005 rad 0.93 the lowest) and within 2.1 times it (a one-pass plan at 0.01 rad 1.80 the
    highest: a plan may hold two runs' steps, one pass holds one); it bounds the simulate peaks
    by 1.13-1.30x. With the SH 1/2 files at the default spacing (979 particles, before they
    were discretized for the needle) the same measurements gave 1.14-2.07."""
    runs = {"simulate": 1, "plan": PLAN_RUNS, "compare": PLAN_RUNS + 1}[command]
    item = estimate(sh12(step, name), "insertion", command, runs)
    assert 0.85 <= item.memory_bytes / (peak * 2**20) <= 2.1, item.describe()


# unplanned runs of sh12_100x100 (benchmarks/results/resource_costs.md): in steps of 0.08, 0.01
# and 0.0025 rad they took 0.24, 2.42 and 17.8 s, each step longer than the one before (each
# solve reads E K^-1, a row pair per needle point)
MEASURED_RUN_SECONDS = [(0.08, 0.2357), (0.01, 2.415), (0.0025, 17.82)]


@pytest.mark.parametrize("step, seconds", MEASURED_RUN_SECONDS)
def test_the_time_estimate_bounds_runs_in_small_steps(step, seconds):
    """The estimate stays above each measured time and within 2.5 times it (1.7-1.9x, the
    deform runs' 1.6-3.2x): with the time of a run linear in its steps it fell to 0.66 of the
    measured time at 0.0025 rad (1 257 steps estimated, 1 202 taken)."""
    item = estimate(sh12(step), "insertion", "simulate")
    assert 1.0 <= item.seconds / seconds <= 2.5, item.describe()


def test_steps_too_many_for_the_memory_are_refused_naming_the_needle_step():
    """SH 1/2 at 0.0025 rad: the tissue's model (~115 MB) fits half of 800 MB, with what its
    1257 steps keep (~390 MB estimated; a run peaked at 427 MiB) it does not: the refusal names
    the needle step, not the spacing; at the shipped 0.08 rad it runs."""
    line = refusal([estimate(sh12(0.0025), "insertion", "simulate")], memory=8e8)
    assert line.startswith("needle.step: got 0.0025 rad, expected a model within 50% of the 800 MB of memory "
                           "available (1257 needle steps keep ~392 MB of states and solver blocks until the run "
                           "ends; estimated simulate: 642 particles, 1257 needle steps"), line
    assert line.endswith("take a larger step, or pass --no-resource-check to run it anyway")
    plan = refusal([estimate(sh12(0.0025), "insertion", "plan", PLAN_RUNS)], memory=8e8)
    assert "~392 MB of states and solver blocks until the run ends, 785 MB for the 2 runs held at once" in plan
    check_resources([estimate(sh12(0.08), "insertion", "simulate")], memory=8e8)
    # past the step limit too: one line, the step limit's
    line = refusal([estimate(sh12(0.0012), "insertion", "simulate")], memory=2e9)
    assert line.startswith("needle.step: got 0.0012 rad, expected a step giving at most 2000 needle steps"), line


def guarded(monkeypatch, memory: float, run: str):
    """The CLI on a machine with `memory` bytes available, where reaching `run` (the
    attribute that starts the command's runs) fails the test: returns a function invoking
    the CLI, which gives (exit code, stderr lines, the invocation's exception)."""
    monkeypatch.setattr("stitchplan.resources.guard.available_memory", lambda: memory)

    def not_reached(*args, **kwargs):
        raise AssertionError("the run started past the guard")

    monkeypatch.setattr(run, not_reached)

    def invoke(*arguments) -> tuple[int, list[str], BaseException | None]:
        result = CliRunner().invoke(app, [str(argument) for argument in arguments])
        return result.exit_code, result.stderr.splitlines(), result.exception

    return invoke


def past_the_guard(invoked) -> bool:
    """Whether an invocation of `guarded` passed the guard (and stopped at the run)."""
    return "the run started past the guard" in repr(invoked[2])


def test_the_cli_refuses_steps_too_many_for_the_memory(tmp_path, monkeypatch):
    """772 steps of 0.0025 rad on the 40 x 20 mm block keep ~140 MB: refused in one line on a
    machine with 400 MB available, before the run (which would take seconds) starts."""
    invoke = guarded(monkeypatch, 4e8, "stitchplan.planning.verification.simulate_with_estimate")
    path = write(tmp_path, scene(needle__step=0.0025))
    code, (line,), _ = invoke("simulate", path, "--no-estimate", "--summary", tmp_path / "summary.json")
    assert code == 2
    assert line.startswith(f"error: {path}: needle.step: got 0.0025 rad, expected a model within 50% of the "
                           "400 MB of memory available (772 needle steps keep ~"), line
    assert line.endswith("take a larger step, or pass --no-resource-check to run it anyway")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.yaml"]


def runs_at_once(step: float) -> tuple[list, list]:
    """The 40 x 20 mm block's plan at `step`: its passes and its verification (the command's
    own estimates), and the predicted aim's replay at twice the spacing (alongside)."""
    scenario = parse_scenario(scene(needle__step=step))
    own = [estimate(scenario, "insertion", "plan", PLAN_RUNS),
           estimate(rescaled(scenario, 0.5), "insertion", "plan verification", VERIFICATION_RUNS,
                    origin=verification_origin(scenario))]
    return own, [estimate(rescaled(scenario, 2.0), "insertion", "plan's replay at twice the spacing")]


def test_runs_that_go_on_at_once_are_refused_by_the_memory_they_hold_together():
    """At 0.005 rad the plan (~230 MB), its verification (~540 MB) and the replay at twice the
    spacing (~120 MB) each fit 700 MB, but not together (~800 MB: the interpreter counted once, and a
    forked helper's own share of it for each helper): one line naming the needle step (what they keep
    of their steps drives all three) with every run's estimate. Runs not said to go on at
    once (no `alongside`) are checked one at a time, as before; at 0.01 rad they fit together."""
    own, alongside = runs_at_once(0.005)
    assert all(item.memory_bytes < 7e8 for item in own + alongside)
    together = sum(item.memory_bytes for item in own + alongside) - 2 * (BASE_MEMORY - HELPER_BASE_MEMORY)
    assert 7e8 < together < 1.4e9
    check_resources(own, memory=1.4e9)  # one at a time: each fits
    with pytest.raises(InputError) as error:
        check_resources(own, memory=1.4e9, alongside=alongside)
    (line,) = error.value.lines
    assert line.startswith("needle.step: got 0.005 rad, expected runs within 50% of the 1.4 GB of memory available "
                           "when they run at once ("), line
    assert f"estimated ~{together / 1e6:.3g} MB together: plan: " in line
    assert "; plan verification: " in line and "; plan's replay at twice the spacing: " in line
    assert line.endswith("take a larger step, pass --no-verify to skip the verification, or pass "
                         "--no-resource-check to run it anyway"), line
    check_resources(*runs_at_once(0.01)[:1], memory=1.4e9, alongside=runs_at_once(0.01)[1])


def test_the_cli_refuses_a_plan_whose_runs_do_not_fit_at_once(tmp_path, monkeypatch):
    """The same plan through the CLI: refused in one line before any run, no file written;
    with --no-verify (its passes and the estimate's replay at 2h, ~310 MB) it passes the guard."""
    invoke = guarded(monkeypatch, 1.4e9, "stitchplan.planning.verification.plan_verified")
    path = write(tmp_path, scene(needle__step=0.005))
    arguments = ["plan", path, "--export", tmp_path / "trajectory.csv", "--no-compare"]
    code, (line,), _ = invoke(*arguments)
    assert code == 2
    assert line.startswith(f"error: {path}: needle.step: got 0.005 rad, expected runs within 50% of the 1.4 GB "
                           "of memory available when they run at once"), line
    assert "set planner.predicted_aim: false to skip the predicted aim" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.yaml"]
    assert past_the_guard(invoke(*arguments, "--no-verify"))


def test_the_cli_counts_the_estimate_replay_of_a_simulate(tmp_path, monkeypatch):
    """simulate at 0.0025 rad on the 40 x 20 mm block (~240 MB) fits 300 MB alone, not with
    its exit error estimate's replay at twice the spacing (~170 MB) beside it: refused naming
    --no-estimate too; with --no-estimate it passes the guard."""
    invoke = guarded(monkeypatch, 6e8, "stitchplan.planning.verification.simulate_with_estimate")
    path = write(tmp_path, scene(needle__step=0.0025))
    arguments = ["simulate", path, "--summary", tmp_path / "summary.json"]
    code, (line,), _ = invoke(*arguments)
    assert code == 2
    assert line.startswith(f"error: {path}: needle.step: got 0.0025 rad, expected runs within 50% of the 600 MB "
                           "of memory available when they run at once"), line
    assert "; exit error estimate: " in line and "pass --no-estimate to skip the estimate" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.yaml"]
    assert past_the_guard(invoke(*arguments, "--no-estimate"))


def test_the_cli_counts_the_workers_of_a_plan_under_uncertainty(tmp_path, monkeypatch):
    """plan --uncertainty at 0.005 rad on the 40 x 20 mm block: this process's runs and each
    local worker's sampled plans (~230 MB each) fit 600 MB one at a time, not with two workers
    beside this process (~690 MB): refused naming the needle step and --workers; with one worker it
    passes the guard. (The cluster is not started: a Dask cluster sets malloc variables in the
    process's environment, which later tests' processes would inherit.)"""
    invoke = guarded(monkeypatch, 1.2e9, "stitchplan.parallel.executor.Executor.__enter__")
    path = write(tmp_path, scene(needle__step=0.005))
    spread = write(tmp_path, {"samples": 4, "seed": 1, "parameters": {"friction": {"std": 0.001}}}, "spread.yaml")
    arguments = ["plan", path, "--uncertainty", spread, "--export", tmp_path / "trajectory.csv", "--no-verify"]
    code, (line,), _ = invoke(*arguments, "--workers", 2)
    assert code == 2
    assert line.startswith(f"error: {path}: needle.step: got 0.005 rad, expected runs within 50% of the 1.2 GB "
                           "of memory available when they run at once"), line
    assert "; worker 1 of 2: sampled plans: " in line and "; worker 2 of 2: sampled plans: " in line
    assert "pass --workers with fewer workers" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.yaml", "spread.yaml"]
    assert past_the_guard(invoke(*arguments, "--workers", 1))


def test_the_cli_counts_the_largest_study_runs_its_workers_hold_at_once(tmp_path, monkeypatch):
    """A quick study at 0.005 rad on the 40 x 20 mm block: each run fits 500 MB (its largest
    ~290 MB), its two largest on two local workers do not (~640 MB with this process, each
    worker a process of its own): refused naming the needle step; on one worker the runs go one at a time and it
    passes the guard."""
    invoke = guarded(monkeypatch, 1e9, "stitchplan.parallel.executor.Executor.__enter__")
    path = write(tmp_path, scene(needle__step=0.005))
    arguments = ["study", path, "--quick", "--out", tmp_path / "study"]
    code, (line,), _ = invoke(*arguments, "--workers", 2)
    assert code == 2
    assert line.startswith(f"error: {path}: needle.step: got 0.005 rad, expected runs within 50% of the 1 GB "
                           "of memory available when they run at once"), line
    assert line.count("; study run ") == 1 and "together: study run " in line  # the two largest
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.yaml"]
    assert past_the_guard(invoke(*arguments, "--workers", 1))


def test_a_study_on_workers_counts_this_process_beside_them(tmp_path, monkeypatch):
    """The study's own process runs none of the runs but holds its interpreter while a local
    worker holds the largest: where the share fits that run alone but not with the
    interpreter beside it, one worker is refused too, the line listing this process."""
    from stitchplan.study.sweep import plan_runs

    raw = scene(needle__step=0.005)
    runs, reference, repeats = plan_runs(parse_scenario(raw), True)
    largest = max(estimate(run.scenario, "insertion", "study run", repeats).memory_bytes for run in [*runs, reference])
    memory = 2.0 * (largest + 0.5 * BASE_MEMORY)  # a share between the run alone and the run with this process
    invoke = guarded(monkeypatch, memory, "stitchplan.parallel.executor.Executor.__enter__")
    path = write(tmp_path, raw)
    code, (line,), _ = invoke("study", path, "--quick", "--out", tmp_path / "study", "--workers", 1)
    assert code == 2
    assert "expected runs within 50% of the " in line and "when they run at once" in line, line
    assert line.count("; study run ") == 0 and "together: study run " in line
    assert f"; this process: {BASE_MEMORY / 1e6:.3g} MB)" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.yaml"]


# --- ordinary inputs: unchanged ---------------------------------------------------------------


@pytest.mark.parametrize("name", ["needle20_entry30", "sh12_100x100", "slab_edge_load", "wound_closure"])
def test_the_shipped_scenes_pass_the_guard(name):
    scenario = load_scenario(REPOSITORY / "configs" / f"{name}.yaml")
    kinds = (["deform"] if scenario.loads else []) + (["insertion"] if scenario.needle else [])
    check_resources([estimate(scenario, kind) for kind in kinds], Limits(), memory=8e9)


def test_the_verification_origin_changes_no_estimate():
    """An origin only changes what a refusal names, never the estimate."""
    scenario = load_scenario(REPOSITORY / "configs" / "sh12_100x100.yaml")
    verification = rescaled(scenario, 0.5)
    plain, named = (estimate(verification, "insertion", "plan verification", 2, origin=origin)
                    for origin in (None, verification_origin(scenario)))
    assert (plain.size, plain.memory_bytes, plain.seconds) == (named.size, named.memory_bytes, named.seconds)
    assert plain.describe() == named.describe()


# --- the needle calibration's radius and numerical failures -----------------------------------


def recordings(folder: Path, touch: float = 0.0) -> tuple[Path, Path]:
    """air.csv and tissue.csv: background 0.12 N + 0.035 N/rad, cutting 0.7 N, friction
    0.06 N/mm at 8.88 mm and a small ripple; the tissue's angles start at `touch` rad, its
    forces as if they started at 0."""
    air_angle = np.linspace(0.0, math.pi, 20)
    angle = np.linspace(0.0, 2.8, 15)
    tables = {"air.csv": (air_angle, 0.12 + 0.035 * air_angle),
              "tissue.csv": (touch + angle,
                             0.12 + 0.035 * angle + 0.7 + 0.06 * 8.88 * angle + 0.01 * np.sin(7 * angle))}
    for name, (x, y) in tables.items():
        (folder / name).write_text("angle_rad,force_N\n" + "".join(f"{float(a)!r},{float(f)!r}\n" for a, f in zip(x, y)))
    return folder / "air.csv", folder / "tissue.csv"


def calibrate(folder: Path, radius: str):
    air, tissue = folder / "air.csv", folder / "tissue.csv"
    return CliRunner().invoke(app, ["calibrate", "needle", "--air", str(air), "--tissue", str(tissue),
                                    "--radius", radius, "--out", str(folder / "needle.yaml")])


@pytest.mark.parametrize("radius", ["1e-300", "0.049", "1001", "1e160"])
def test_a_needle_radius_outside_the_bounds_is_refused(tmp_path, radius):
    recordings(tmp_path)
    result = calibrate(tmp_path, radius)
    assert result.exit_code == 2, result.output
    (line,) = result.stderr.splitlines()
    assert line.startswith(f"error: --radius: got {float(radius)!r}, expected a positive number (mm) from 0.05 to 1000")
    assert not (tmp_path / "needle.yaml").exists()


@pytest.mark.parametrize("radius", ["0.05", "8.88", "1000"])
def test_a_needle_radius_at_the_bounds_fits_finite_values(tmp_path, radius):
    recordings(tmp_path)
    result = calibrate(tmp_path, radius)
    assert result.exit_code == 0, result.output
    fitted = yaml.safe_load((tmp_path / "needle.yaml").read_text())
    assert fitted["cutting_force"] == pytest.approx(0.7, abs=0.02)
    assert fitted["friction"] * float(radius) == pytest.approx(0.06 * 8.88, rel=0.05)
    assert all(math.isfinite(value) for value in fitted["diagnostics"]["standard_uncertainty"].values())


def test_a_line_that_cannot_be_fitted_is_a_numerical_failure(tmp_path):
    """Tissue angles from 1e9 rad on, over 2.8 rad: the accepted recording gives a singular
    least-squares system, reported in one line (exit 1) with no output."""
    from stitchplan.calibration import fit_line

    with pytest.raises(NumericalFailure, match="singular"):
        fit_line(np.full(6, 3.0), np.arange(6.0))
    recordings(tmp_path, touch=1e9)
    result = calibrate(tmp_path, "8.88")
    assert result.exit_code == 1, result.output
    (line,) = result.stderr.splitlines()
    assert line.startswith(f"error: --tissue {tmp_path / 'tissue.csv'} and --air {tmp_path / 'air.csv'}: needle fit: "
                           "the tissue line") and "singular" in line
    assert "Traceback" not in result.output and not (tmp_path / "needle.yaml").exists()


def test_a_run_estimated_long_is_announced_before_it_starts(caplog):
    """Within the limits, a run estimated past LONG_RUN_SECONDS starts with a warning line
    (shown by default, unlike the estimates of -v); a short one starts without, and so do the
    replays alongside a command's runs (they follow those runs)."""
    from stitchplan.resources.guard import LONG_RUN_SECONDS

    scenario = load_scenario(REPOSITORY / "configs" / "needle20_entry30.yaml")
    long_run = estimate(with_discretization(scenario, spacing=1.5, dilation=10.0), "insertion", "simulate")
    short_run = estimate(scenario, "insertion", "simulate")
    assert long_run.seconds > LONG_RUN_SECONDS > short_run.seconds
    with caplog.at_level("WARNING", logger="stitchplan"):
        check_resources([short_run], memory=math.inf)
        assert not caplog.records
        check_resources([long_run], memory=math.inf)
    assert [record.levelname for record in caplog.records] == ["WARNING"]
    assert caplog.records[0].getMessage().startswith("a long run: estimated simulate: ")
    caplog.clear()
    with caplog.at_level("WARNING", logger="stitchplan"):  # a long replay alongside: no warning of its own
        check_resources([short_run], memory=math.inf, alongside=[replace(long_run, label="exit error estimate")])
    assert not caplog.records


def test_minres_needle_steps_are_estimated_at_their_measured_cost():
    """MINRES runs take 3.5-7.4x the direct solve's time on SH 1/2 (simulate_speed.md): the
    estimate follows the scenario's solver or the option's, and leaves deform alone."""
    from stitchplan.resources.costs import MINRES_TIME_FACTOR

    scenario = load_scenario(REPOSITORY / "configs" / "sh12_100x100.yaml")
    direct = estimate(scenario, "insertion", "simulate").seconds
    assert estimate(scenario, "insertion", "simulate", linear_solver="minres").seconds == \
        pytest.approx(MINRES_TIME_FACTOR * direct)
    in_file = replace(scenario, needle=replace(scenario.needle, linear_solver="minres"))
    assert estimate(in_file, "insertion", "simulate").seconds == pytest.approx(MINRES_TIME_FACTOR * direct)
    assert estimate(in_file, "insertion", "simulate", linear_solver="direct").seconds == pytest.approx(direct)
    slab = load_scenario(REPOSITORY / "configs" / "slab_edge_load.yaml")
    assert estimate(slab, "deform", linear_solver="minres").seconds == estimate(slab, "deform").seconds


def test_condition_numbers_are_estimated_at_their_measured_cost():
    """simulate --condition-numbers takes each step's dense eigenvalues: 0.59 s a step on the
    642 particles of SH 1/2 and 6.1 s on 1379, 115 and 437 MB more at the peak
    (benchmarks/results/condition_costs.md), where the guard estimated the run without them at
    0.37 s in all. Its estimate now adds 0.7-1.3x the measured time and bounds the memory from
    above; the estimate replay (no condition numbers) and deform are left alone."""
    scenario = load_scenario(REPOSITORY / "configs" / "sh12_100x100.yaml")
    for spacing, per_step, added in ((7.104, 0.589, 115e6), (4.5, 6.15, 437e6)):
        model = with_discretization(scenario, spacing=spacing)
        plain = estimate(model, "insertion", "simulate")
        dense = estimate(model, "insertion", "simulate", condition_numbers=True)
        assert 0.7 < (dense.seconds - plain.seconds) / (per_step * dense.steps) < 1.3
        assert added < dense.memory_bytes - plain.memory_bytes < 1.5 * added
    slab = load_scenario(REPOSITORY / "configs" / "slab_edge_load.yaml")
    assert estimate(slab, "deform", condition_numbers=True) == estimate(slab, "deform")


def test_condition_numbers_taking_too_long_are_refused_naming_the_option(tmp_path, monkeypatch):
    """The reproducer: --spacing 3.55 on SH 1/2 (2104 particles) was estimated at ~1.3 s and
    took ~25 s a needle step with --condition-numbers; refused in one line naming the option,
    what a step takes and the particles that fit, no file written. Without the option, or at
    the file's own spacing (~25 s in all), it passes the guard."""
    invoke = guarded(monkeypatch, LARGE_MEMORY, "stitchplan.planning.verification.simulate_with_estimate")
    config = REPOSITORY / "configs" / "sh12_100x100.yaml"
    summary = tmp_path / "summary.json"
    code, (line,), _ = invoke("simulate", config, "--no-estimate", "--condition-numbers", "--spacing", "3.55",
                              "--summary", summary)
    assert code == 2
    assert line.startswith("error: --condition-numbers: got a dense saddle system of 4208 unknowns (2 x 2104 "
                           "particles) in each of 40 needle steps, expected condition numbers within 10 min (~22 s "
                           "a step, ~14.9 min in all; estimated simulate: 2104 particles, 40 needle steps, "), line
    assert line.endswith("leave it out or coarsen --spacing to at most ~1842 particles, or pass "
                         "--no-resource-check to run it anyway"), line
    assert not summary.exists()
    assert past_the_guard(invoke("simulate", config, "--no-estimate", "--spacing", "3.55"))
    assert past_the_guard(invoke("simulate", config, "--no-estimate", "--condition-numbers"))


def test_condition_numbers_past_the_memory_share_name_the_option():
    """At 5.5 mm on SH 1/2 (972 particles, ~1.5 min of condition numbers) the run fits 500 MB
    without its dense matrices (~270 MB), not with them: the memory refusal names the option."""
    model = with_discretization(load_scenario(REPOSITORY / "configs" / "sh12_100x100.yaml"), spacing=5.5)
    check_resources([estimate(model, "insertion", "simulate")], memory=5e8)
    line = refusal([estimate(model, "insertion", "simulate", condition_numbers=True)], memory=5e8)
    assert line.startswith("--condition-numbers: got a dense saddle system of 1944 unknowns, expected a model "
                           "within 50% of the 500 MB of memory available (~272 MB of dense matrices for the "
                           "condition numbers of 972 particles; "), line
    assert line.endswith("leave it out or coarsen the spacing, or pass --no-resource-check to run it anyway"), line


# --- shaped tissues: the guard counts the particles the model places --------------------------


def eight_holes() -> dict:
    """The traced ellipse of test_shapes with eight small circular holes instead of one, whose
    walls carry particles at the local spacing (tissue/shapes.py: not at each of a circle's
    CIRCLE_SEGMENTS vertices, which made about three times the particles the spacing gives)."""
    from test_shapes import traced

    raw = traced(40)
    raw["tissue"]["holes"] = [{"circle": {"center": [12.0 + 6.0 * k, 12.0 + 6.0 * (k % 2)], "radius": 1.5}}
                              for k in range(6)] + [{"circle": {"center": [30.0, 4.5], "radius": 1.5}},
                                                    {"circle": {"center": [30.0, 25.0], "radius": 1.5}}]
    return raw


@pytest.mark.parametrize("name", ["traced 200-gon", "eight holes"])
def test_a_shaped_tissue_is_counted_as_the_model_places_it(name):
    """The guard places a shaped tissue's particles and quadrature points as the model does
    (the bounding box's area over the spacing squared said 231 for both; the 200-gon once
    built 5159): its count is the built model's, and its crowding (particles seen per
    quadrature point, squared, over a regular lattice's) raises the cost estimates where the
    holes' boundary particles crowd the supports (they no longer do: the count stays near what
    the spacing gives, with the particles left ungraded toward the holes)."""
    from test_shapes import traced

    from stitchplan.tissue.model import model_for_scenario

    scenario = parse_scenario(traced(200) if name == "traced 200-gon" else eight_holes())
    size = model_size(scenario)
    model = model_for_scenario(scenario)
    assert size.exact and size.particles == len(model.particles)
    assert size.points_per_particle == pytest.approx(len(model.quadrature_points) / len(model.particles))
    nominal = replace(size, crowding=1.0)
    item, plain = estimate(scenario, "deform"), replace(estimate(scenario, "deform"), size=nominal)
    assert size.crowding >= 1.0 and item.memory_bytes >= plain.memory_bytes
    if name == "eight holes":  # the holes' walls at the spacing: 2.5x and 3x with a particle a vertex
        raw = eight_holes()
        raw["discretization"]["hole_resolution"] = 0
        unrefined = model_size(parse_scenario(raw))
        assert unrefined.particles < 1.5 * 231 and unrefined.crowding < 1.5


def test_the_cli_refuses_a_traced_contour_past_max_particles(tmp_path):
    """--max-particles just below the 200-gon's real count refuses it up front, in the usual
    line, with the count the run would have."""
    from test_shapes import traced

    raw = traced(200)
    count = model_size(parse_scenario(raw)).particles
    path = write(tmp_path, raw)
    result = CliRunner().invoke(app, ["deform", str(path), "--probes-out", str(tmp_path / "probes.csv"),
                                      "--max-particles", str(count - 1)])
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output and result.stdout == ""
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {path}: discretization.spacing: got 3 mm"), lines
    assert f"at most {count - 1} particles" in lines[0] and f"estimated deform: {count} particles" in lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.yaml"]


# --- an address-space limit (ulimit -v) ------------------------------------------------------


def under_address_limit(kilobytes: int, *arguments, cwd: Path = REPOSITORY):
    """`python -m stitchplan ARGUMENTS` in a process whose address space is limited to
    `kilobytes` (ulimit -v), as the tester's shell ran it."""
    import os
    import resource
    import subprocess
    import sys

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (kilobytes * 1024, kilobytes * 1024))

    return subprocess.run([sys.executable, "-m", "stitchplan", *map(str, arguments)], capture_output=True, text=True,
                          cwd=cwd, preexec_fn=limit, timeout=120, check=False,
                          env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="Linux: the loader's mmap of the libraries")
@pytest.mark.parametrize("command", [["simulate", "configs/sh12_100x100.yaml", "--no-estimate"],
                                     ["study", "configs/sh12_100x100.yaml"]])
def test_libraries_that_do_not_fit_the_address_space_limit_are_one_error_line(tmp_path, command):
    """The reproducer: under `ulimit -v 150000` simulate printed a 59-line traceback (an
    ImportError as scipy's OpenBLAS failed to map) before its guard ran; now one `error:` line
    names the limit, exit code 2, and no output is written."""
    summary = tmp_path / "summary.json"
    options = ["--out", tmp_path / "study"] if command[0] == "study" else ["--summary", summary]
    done = under_address_limit(150000, *command, *options)
    assert done.returncode == 2, done.stderr
    (line,) = done.stderr.splitlines()
    assert line.startswith("error: the numerical libraries could not be loaded within the process's address-space "
                           "limit (ulimit -v 150000) of 154 MB ("), line
    assert line.endswith("raise the limit: their imports alone map ~300 MB of address space")
    assert sorted(tmp_path.iterdir()) == []


def test_a_failed_library_load_without_a_limit_stays_a_bug(monkeypatch):
    """Without an address-space limit (or for an ImportError of another cause) the error is
    not the limit's: address_space_failure gives no line, and the traceback stays."""
    import resource

    from stitchplan.cli.group import address_space_failure
    from stitchplan.resources import machine

    mapped = ImportError("libscipy_openblas.so: failed to map segment from shared object")
    monkeypatch.setattr(machine, "mapped_peak", lambda: 250e6)  # as at the imports (this process maps more)
    monkeypatch.setattr(resource, "getrlimit", lambda which: (resource.RLIM_INFINITY, resource.RLIM_INFINITY))
    assert address_space_failure(mapped) is None
    monkeypatch.setattr(resource, "getrlimit", lambda which: (400000 * 1024, resource.RLIM_INFINITY))
    assert address_space_failure(ImportError("No module named 'scipy'")) is None
    assert address_space_failure(mapped).startswith("the numerical libraries could not be loaded within the "
                                                    "process's address-space limit (ulimit -v 400000) of 410 MB")
    assert address_space_failure(MemoryError()).startswith("out of memory within the process's address-space limit")


def test_a_library_that_fails_to_load_within_a_run_is_not_blamed_on_the_imports(monkeypatch):
    """Under `ulimit -v 700000` a calibration's late import of its optimizer failed to map once
    the experiments' factors held the rest of the limit, and the line said the libraries' imports
    alone map ~300 MB (of a 717 MB limit); a failure after the process mapped more than its
    imports now says that the run's arrays and factors held the rest."""
    import resource

    from stitchplan.cli import group
    from stitchplan.resources import machine

    failed = ImportError("_highspy/_core.cpython-311-x86_64-linux-gnu.so: failed to map segment from shared object")
    monkeypatch.setattr(resource, "getrlimit", lambda which: (700000 * 1024, resource.RLIM_INFINITY))
    monkeypatch.setattr(machine, "mapped_peak", lambda: 716e6)
    line = group.address_space_failure(failed)
    assert line.startswith("a library loaded within the run could not be mapped within the process's address-space "
                           "limit (ulimit -v 700000) of 717 MB, its arrays and factors holding the rest ("), line
    assert line.endswith("); raise the limit, or make the run smaller")
    monkeypatch.setattr(machine, "mapped_peak", lambda: 150e6)
    assert group.address_space_failure(failed).endswith("their imports alone map ~300 MB of address space")


def test_an_address_space_limit_too_small_for_any_model_names_the_limit():
    """Under `ulimit -v 400000` simulate said `discretization.spacing: got 7.104 mm, expected a
    model within 50% of the 0 kB of memory available`: the limit less what the process mapped
    and a 320 MB reserve, halved, had nothing left, and a field was blamed. The address space a
    run needs is now estimated apart from the machine's memory (machine.address_space_needed:
    simulate on SH 1/2 ran under 409 MB at the least, deform on the slab under 448 MB), and where
    no model would fit the line names the limit and what the run needs; a limit with room for
    the run passes; one with room for a smaller model names the spacing."""
    from stitchplan.resources.machine import address_space_needed

    scenario = load_scenario(REPOSITORY / "configs" / "sh12_100x100.yaml")
    item = estimate(scenario, "insertion", "simulate")
    needed = address_space_needed(226e6, item.memory_bytes, BASE_MEMORY)
    assert 409e6 < needed < 1.3 * 409e6  # bounds the least limit it ran under, within 30 %
    with pytest.raises(InputError) as error:
        check_resources([item], memory=LARGE_MEMORY, space=(400000 * 1024.0, 226e6))
    (line,) = error.value.lines
    assert line.startswith("ulimit -v: got 400000 (the process's address-space limit of 410 MB; 226 MB mapped now), "
                           f"expected at least ~{needed / 1e6:.3g} MB for this run ("), line
    assert " 0 kB" not in line and "spacing" not in line
    check_resources([item], memory=LARGE_MEMORY, space=(needed + 1e6, 226e6))
    fine = estimate(with_discretization(scenario, spacing=1.0), "insertion", "simulate")
    with pytest.raises(InputError) as error:
        check_resources([fine], memory=LARGE_MEMORY, space=(700000 * 1024.0, 226e6))
    (line,) = error.value.lines
    assert line.startswith("discretization.spacing: got 1 mm, expected a model within the ~"), line
    assert "memory the process's address-space limit of 717 MB (ulimit -v 700000) leaves it" in line


def test_a_calibrations_experiments_are_held_at_once_in_its_process(monkeypatch):
    """calibrate material keeps every experiment's model and tangent factor between the fit's
    evaluations, and factors one more for an experiment's sensitivity: under `ulimit -v` the
    guard let the sample calibration (two experiments) through at 489 MB, each experiment
    alone fitting, while it needed 614-742 MB (by the hash seed) and failed within the fit.
    The experiments are now counted together, with the sensitivity's factor: ~711 MB, where
    the sample ran under 614 MB for eight hash seeds (its optimizer imported before the guard)."""
    from stitchplan.calibration import load_material_calibration
    from stitchplan.cli.options import guard_calibration
    from stitchplan.resources import guard
    from stitchplan.resources.costs import held_in_one_process
    from stitchplan.resources.machine import address_space_needed

    path = REPOSITORY / "sample_runs" / "calibration" / "calibration.yaml"
    problem = load_material_calibration(path, None, None)
    original, seen = guard.check_resources, {}

    def recorded(estimates, limits, **options):
        seen.update(options, estimates=[*estimates, *options.get("beside", ())])  # the estimate's held beside
        return original(estimates, limits, **options)

    mapped = 332e6  # after the calibration's imports, its optimizer's included
    monkeypatch.setattr(guard, "check_resources", recorded)
    monkeypatch.setattr(guard, "address_space", lambda: (680000 * 1024.0, mapped))
    monkeypatch.setattr(guard, "available_memory", lambda: LARGE_MEMORY)
    with pytest.raises(InputError) as error:
        guard_calibration(path, problem, Limits(), estimate=False)  # as measured: the fit alone
    memories = [item.memory_bytes for item in seen["estimates"]]
    assert len(memories) == 2 and seen["in_one_process"] is True
    together = held_in_one_process(memories)
    assert together == pytest.approx(BASE_MEMORY + 3 * (max(memories) - BASE_MEMORY), rel=0.01)
    assert all(address_space_needed(mapped, amount, BASE_MEMORY) < 680000 * 1024.0 for amount in memories)
    (line,) = error.value.lines
    assert "the process's address-space limit of 696 MB (ulimit -v 680000) leaves it beside the ~" in line, line
    assert "of the runs held with it (estimated experiments[" in line
    needed = address_space_needed(mapped, together, BASE_MEMORY)
    assert 614e6 < needed < 1.3 * 614e6
    monkeypatch.setattr(guard, "address_space", lambda: (needed + 1e6, mapped))
    guard_calibration(path, problem, Limits(), estimate=False)  # room for all of them: no refusal
    # the discretization estimate's models at twice the spacing are held beside them, smaller
    with pytest.raises(InputError):
        guard_calibration(path, problem, Limits())
    coarse = [item for item in seen["estimates"] if "at twice the spacing" in item.label]
    assert len(coarse) == 2 and max(item.memory_bytes for item in coarse) < min(memories)
    # the limits the README quotes (MB of 1e6 bytes): ~711 without the estimate, ~740 with it
    with_estimate = address_space_needed(
        mapped, held_in_one_process([item.memory_bytes for item in seen["estimates"]]), BASE_MEMORY)
    assert round(needed / 1e6) == 711 and round(with_estimate / 1e6) == 740, (needed, with_estimate)


def test_the_memory_that_fits_an_address_space_limit_is_the_need_inverted():
    """machine.memory_within_address_space is address_space_needed solved for the run's
    memory: a run estimated at that memory needs exactly the limit, whatever the process maps
    now (below and above what the numerical libraries map)."""
    from stitchplan.resources.machine import NUMERICS_MAPPED, address_space_needed, memory_within_address_space

    checked = 0
    for mapped in (0.5 * NUMERICS_MAPPED, NUMERICS_MAPPED, 1.7 * NUMERICS_MAPPED):
        for limit in (4e8, 1.3e9, 8e9):
            memory = memory_within_address_space(limit, mapped, BASE_MEMORY)
            if memory > BASE_MEMORY:  # a run beyond the interpreter fits
                assert address_space_needed(mapped, memory, BASE_MEMORY) == pytest.approx(limit, rel=1e-12)
                checked += 1
    assert checked >= 6


def test_a_setting_refused_for_several_runs_is_said_once():
    """A study whose spacing is too coarse for the tissue: its families' runs were each refused
    by the same field (three lines for one problem); now the field's first line alone."""
    from stitchplan.resources.guard import _one_per_field

    lines = ["study.spacing: got 500 mm, expected at most half ...",
             "study.spacing: got 500 mm (a coarse spacing of 2e+03 mm), expected at most half ...",
             "the study's default reference spacing: got 250 mm, expected ...",
             "needle.step: got 1e-05 rad, expected a step giving at most 2000 needle steps"]
    assert _one_per_field(lines) == [lines[0], lines[2], lines[3]]


# --- the calibrations' measured data: markers and recording rows ------------------------------

# peak RSS of `calibrate material` (/usr/bin/time -f %M, MiB; benchmarks/calibration_memory.py
# measures them again, in MB) on the sample calibration with its
# first experiment's markers sampled at 1e4 to 1e6 points of the same experiment (its second's 20
# kept), dilation 2; before, the fit
# kept every evaluation's residual, Jacobian and simulated markers, which the guard did not count
# (230, 521 and 1246 MiB; 3610 MiB at 1e6)
MEASURED_MARKER_PEAKS = [(10_000, 179.9), (100_000, 315.7), (300_000, 553.7), (1_000_000, 1329.4)]


def sample_calibration(markers: int):
    """The sample calibration with `markers` markers in its first experiment (the guard reads
    only their count)."""
    from stitchplan.calibration import load_material_calibration

    problem = load_material_calibration(REPOSITORY / "sample_runs" / "calibration" / "calibration.yaml")
    first = replace(problem.experiments[0], markers=np.zeros((markers, 2)), measured=np.zeros((markers, 2)))
    return replace(problem, experiments=(first, *problem.experiments[1:]))


def guarded_calibration(monkeypatch, markers: int, memory: float = LARGE_MEMORY) -> dict:
    """What guard_calibration hands check_resources for the sample calibration with `markers`
    markers in its first experiment: the estimates, those held beside them and the markers."""
    from stitchplan.cli.options import guard_calibration
    from stitchplan.resources import guard

    original, seen = guard.check_resources, {}

    def recorded(estimates, limits, **options):
        seen.update(options, estimates=list(estimates))
        return original(estimates, limits, **options)

    monkeypatch.setattr(guard, "check_resources", recorded)
    monkeypatch.setattr(guard, "available_memory", lambda: memory)
    monkeypatch.setattr(guard, "address_space", lambda: None)
    path = REPOSITORY / "sample_runs" / "calibration" / "calibration.yaml"
    guard_calibration(path, sample_calibration(markers), Limits())
    return seen


@pytest.mark.parametrize("markers, peak", MEASURED_MARKER_PEAKS)
def test_a_calibrations_estimate_counts_its_markers(monkeypatch, markers, peak):
    """calibrate material with a million markers peaked at 3.8 GB (1.4 GB since the fit keeps
    only the evaluations it asks for again) where the guard estimated ~193 MB, its experiments'
    models alone: it now counts each marker (costs.marker_bytes), and the estimate bounds each
    measured peak by 1.11-1.35x, growing with the markers (twice the markers, twice their memory)."""
    from stitchplan.resources.costs import held_in_one_process, marker_bytes

    seen = guarded_calibration(monkeypatch, markers)
    data = seen["data"]
    assert (data.count, data.total, data.unit) == (markers, markers + 20, "markers")
    assert data.name.startswith("experiments[0].markers: ") and data.name.endswith("markers1.csv")
    assert data.memory_bytes == pytest.approx((markers + 20) * marker_bytes(16.0))
    models = held_in_one_process([item.memory_bytes for item in [*seen["estimates"], *seen["beside"]]])
    assert 1.0 <= (models + data.memory_bytes) / (peak * 2**20) <= 1.4, (models, data.describe())
    double = guarded_calibration(monkeypatch, 2 * markers)["data"]
    assert double.memory_bytes == pytest.approx(data.memory_bytes * (2 * markers + 20) / (markers + 20))


def test_markers_past_the_memory_are_refused_naming_the_marker_file(monkeypatch):
    """The sample calibration's models (~194 MB with its discretization estimate's) fit half of
    a memory leaving 5 MB beside them, its first experiment's 10 000 markers (~17 MB) do not: one
    line naming the marker file, the markers got and how many fit."""
    from stitchplan.resources.costs import held_in_one_process

    seen = guarded_calibration(monkeypatch, 20)
    memory = 2 * (held_in_one_process([item.memory_bytes for item in [*seen["estimates"], *seen["beside"]]]) + 5e6)
    with pytest.raises(InputError) as error:
        guarded_calibration(monkeypatch, 10_000, memory=memory)
    (line,) = error.value.lines
    calibration = REPOSITORY / "sample_runs" / "calibration"
    assert line.startswith(f"{calibration / 'calibration.yaml'}: experiments[0].markers: "
                           f"{calibration / 'markers1.csv'}: got 10000 markers (10020 in all experiments), expected "
                           "at most "), line
    fits = int(line.split("expected at most ")[1].split()[0])
    assert 0 < fits < 10_000
    assert f"markers in all experiments within 50% of the {memory / 1e6:.3g} MB of memory available" in line
    assert line.endswith("fit fewer markers (a subset of them), or pass --no-resource-check to run it anyway")
    guarded_calibration(monkeypatch, fits - 20, memory=memory)  # as many as it says fit: no refusal


def marker_calibration(folder: Path, markers: int) -> Path:
    """A calibration of the sample's tissue and loads in `folder`, its first experiment with
    `markers` markers (moved by 0.1 mm: the guard reads them before any fit)."""
    rng = np.random.default_rng(3)
    rest = np.column_stack([rng.uniform(2.0, 95.0, markers), rng.uniform(2.0, 58.0, markers)])
    rows = ["x,y,x_def,y_def", *(f"{x:.6f},{y:.6f},{x + 0.1:.6f},{y:.6f}" for x, y in rest)]
    (folder / "many.csv").write_text("\n".join(rows) + "\n")
    sample = REPOSITORY / "sample_runs" / "calibration"
    data = yaml.safe_load((sample / "calibration.yaml").read_text())
    data["experiments"][0]["markers"] = "many.csv"
    data["experiments"][1]["markers"] = str(sample / "markers2.csv")
    path = folder / "calibration.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_calibrate_material_with_too_many_markers_is_refused_before_the_fit(monkeypatch, tmp_path):
    """The command: one line, exit 2, and the existing --out file left as it was."""
    path = marker_calibration(tmp_path, 5000)
    out = tmp_path / "fitted.yaml"
    out.write_text("kept\n")
    invoke = guarded(monkeypatch, 2 * (BASE_MEMORY + 100e6 + 4e6), "stitchplan.calibration.fit_material")
    monkeypatch.setattr("stitchplan.resources.guard.address_space", lambda: None)
    code, lines, _ = invoke("calibrate", "material", path, "--out", out)
    assert code == 2, lines
    (line,) = lines
    assert line.startswith(f"error: {path}: experiments[0].markers: {tmp_path / 'many.csv'}: got 5000 markers "
                           "(5020 in all experiments), expected at most "), line
    assert out.read_text() == "kept\n"


def test_calibrate_needle_with_too_many_rows_is_refused_before_reading_them_all(monkeypatch, tmp_path):
    """A needle recording of a million rows peaked at 399 MB with no guard (and the reading
    alone held ~0.3 kB a row): the rows are now counted against the memory as they are read
    (costs.MEMORY_PER_RECORDING_ROW), refused in one line naming the recording, exit 2, the
    existing --out file left as it was; --no-resource-check reads them."""
    from stitchplan.resources.costs import MEMORY_PER_RECORDING_ROW

    sample = REPOSITORY / "sample_runs" / "calibration"
    angles = np.linspace(0.0, 2.5, 3000)
    tissue = tmp_path / "tissue.csv"
    tissue.write_text("angle_rad,force_N\n" + "".join(f"{a:.6f},{1.0 + 0.6 * a:.6f}\n" for a in angles))
    out = tmp_path / "needle.yaml"
    out.write_text("kept\n")
    monkeypatch.setattr("stitchplan.resources.guard.address_space", lambda: None)
    invoke = guarded(monkeypatch, 2 * (BASE_MEMORY + 1000 * MEMORY_PER_RECORDING_ROW),
                     "stitchplan.calibration.needle_fit.fit_needle")
    command = ["calibrate", "needle", "--air", sample / "air.csv", "--tissue", tissue, "--radius", "8.88",
               "--out", out]
    code, lines, _ = invoke(*command)
    assert code == 2, lines
    (line,) = lines
    assert line.startswith(f"error: --tissue: {tissue}: got 3000 rows, expected at most 842 beside --air's 158 "
                           "(1000 in both recordings) within 50% of the "), line
    assert line.endswith("record fewer rows (or average them), or pass --no-resource-check to run it anyway")
    assert out.read_text() == "kept\n"
    code, lines, error = invoke(*command, "--no-resource-check")
    assert isinstance(error, AssertionError) and "past the guard" in str(error)  # read, then fitted


def test_a_tables_rows_are_read_without_holding_their_lines(tmp_path):
    """A million-row force recording took ~0.3 kB a row to read (every line kept as a string
    until the last was parsed); a table now takes its text and its parsed columns (~0.07 kB a row
    for this one's 24-byte rows)."""
    import tracemalloc

    from stitchplan.csv_tables import read_numeric_table

    rows = 100_000
    path = tmp_path / "table.csv"
    path.write_text("angle_rad,force_N\n" + "".join(f"{k * 1e-5:.9f},{1.5:.9f}\n" for k in range(rows)))
    tracemalloc.start()
    try:
        data, lines, _ = read_numeric_table(path, ("angle_rad", "force_N"), "a table")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(lines) == rows and lines[-1] == rows + 1 and data["force_N"][-1] == 1.5
    assert peak / rows < 120, peak / rows
