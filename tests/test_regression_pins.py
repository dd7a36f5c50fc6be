"""Pinned results of every shipped scenario, driven through the commands themselves.

The first values were produced at 19ff45d (before the package was split into layers) by
`stitchplan plan CONFIG --export ... --summary ...`, `stitchplan deform` and
`stitchplan calibrate material` on the shipped files, so any restructuring that changes a
result fails here. They pin behaviour, not accuracy: a change that makes the model more
accurate (a new needle coupling, a new load treatment) updates them with its reason.

Tolerances:
- unplanned runs are deterministic sequences of Newton solves to a relative residual of
  1e-3 of the needle force and a track within 1e-7 R of the needle (their exit points lie
  within 6e-5 mm of the converged ones: benchmarks/results/solver_tolerance.md);
  re-ordered floating-point sums (another BLAS, another sparse product order) move the exit
  by far less than 1e-6 mm, so exit errors and exit points are pinned to 1e-6 mm;
- the planner stops its centre iterations at 1e-3 mm and its passes at 0.005 mm, and
  which late step fails eq. 4.2 can flip on round-off, so planned exit errors are pinned
  to 2e-4 mm (a tenth of the smallest plan's error scale) and must stay below the
  planner's 0.005 mm exit tolerance;
- static probes: Newton to 1e-8 relative, pinned to 1e-7 mm;
- the material fit is written to 6 significant digits; pinned to 2e-6 MPa.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from stitchplan.cli import app

from conftest import CONFIGS, REPOSITORY

# scene: (steps, particles, unplanned exit error mm, planned exit error mm with --no-verify)
# Re-pinned when the needle coupling became a mortar multiplier field with the cutting force
# over the last 3 mm of needle (needle.coupling: mortar; benchmarks/results/needle_coupling.md)
# and the planner limited each step's centre move (0.28 mm) and second difference (0.14 mm):
# unplanned errors moved by +3.5 to +8.5 % on the SH 1/2 blocks and +32 to +51 % (0.005 mm)
# on the 20 mm needle, planned ones stay below 0.0025 mm. Step and particle counts unchanged.
# Planned values re-pinned when the needle centre became an unknown of each step's Newton
# solve (needle/steering.py; the unplanned values did not move): the planner now settles
# the fixed point of Algorithm 2's update also where eq. 4.2 fails, and all stay below 0.0025 mm.
# sh12_100x100's planned value re-pinned when the Newton residual tolerance became 1e-6 of
# the needle force (config Solver): its passes take another path to the exit (0.00034 ->
# 0.00067 mm, within the 0.001 mm planner tolerance); every unplanned value moved < 1e-7 mm.
# The 20 mm needle scenes re-pinned when they changed from `auto` tip tracking (the inverse
# gradient first) to Levenberg-Marquardt, whose exit error converges under refinement
# (configs/needle20_entry*.yaml): unplanned -0.9 to +4.8 %, planned now below 1e-10 mm.
# sh12_100x30 (two passes) re-pinned when a later pass's offset began acting a few steps
# before the first pass's late limited steps instead of at step 1 (planning/planner.py
# PassPrefix): 0.00033 -> 0.00047 mm; the scenes planned in one pass did not move.
# sh12_100x100's planned value re-pinned when the residual tolerance became 5e-6 of the
# needle force and the centre's mixed Newton update was projected into its move limits
# (needle/newton.py; before, the mixing could carry a centre up to 5e-6 mm past a
# limit): 0.00067 -> 0.00032 mm; every unplanned value moved < 2.5e-7 mm, every other
# planned value < 2e-4 mm.
# Re-pinned when a needle step's Newton stopped at 1e-3 of the needle force and a track within
# 1e-7 R instead of 5e-6 and 1e-9 R (config Solver, benchmarks/results/solver_tolerance.md:
# 0.6x the Newton iterations): unplanned values moved by at most 4.2e-5 mm, planned ones by
# at most 1.7e-4 mm (hole_near_stitch: another path to the exit within the planner's
# tolerance), the wound's bite differences by 4.3e-6 mm.
# Re-pinned when the shipped needle files were discretized for the needle (configs/sh12_*.yaml:
# 7.104 mm particles graded to 0.888 mm within 1.25 r of the needle's centre, coarsening by
# 1 mm per mm beyond, multiplier elements fixed at 0.888 mm and the cutting force ramped in;
# configs/needle20_entry*.yaml: elements fixed at 2.5 mm and the ramp;
# benchmarks/results/needle_coupling.md, coupling `shipped`): the SH 1/2 blocks' unplanned
# errors moved by +2.9 to +4.5 % (from the default to half the spacing they now
# change by < 2 %, before by up to -3.3 %), the 20 mm needle's by -0.02 to +0.04 %; planned
# errors stay below 0.005 mm.
NEEDLE_SCENES = {
    "sh12_100x100": (39, 642, 0.48466736366427354, 0.00023455978123494172),
    "sh12_100x100_mid": (38, 639, 0.36045628384276673, 0.0027533584381251755),
    "sh12_100x50": (39, 530, 0.490860759025577, 0.0002963912940865466),
    "sh12_100x40": (39, 545, 0.5659626304060602, 3.30304712729892e-05),
    "sh12_100x30": (39, 469, 0.7113931446050438, 0.0011475968458436448),
    "needle20_entry30": (20, 622, 0.021324303754943215, 7.633254099123549e-10),
    "needle20_entry25": (18, 600, 0.01873986773242118, 2.160050122851766e-12),
    "needle20_entry20": (15, 578, 0.01698622889401663, 4.337863923513087e-11),
    "needle20_entry18": (14, 569, 0.016300630248204096, 5.1652912845991376e-11),
}

# the tissue-shape scenes (an outline, holes, layers, a wound): (steps, particles, unplanned
# exit error mm, planned exit error mm with --no-verify, the wound stitch's bite difference mm
# or None), pinned from `stitchplan plan CONFIG --no-verify` when the wound scenes moved to a
# 1.5 mm spacing (their verified plans did not hold at a quarter of the default spacing:
# benchmarks/results/plan_replay.md). wound_closure_symmetric aims equal bites, not the exit
# (planner.target: symmetric), so its exit error is pinned but not held to the exit tolerance.
# wound_closure_symmetric's passes run every step (no PassPrefix, above): with the later
# passes moving only the steps after the wound, equal bites took 7 passes over the two
# verification rounds instead of 3 and held 0.0032 mm instead of 0.0002 mm on the refined model.
SHAPE_SCENES = {
    # re-pinned when its cutting force was ramped in with the cutting edge (needle.cutting_ramp,
    # as the other needle files): unplanned 0.1705 -> 0.1800 mm, against 0.1802, 0.1803 and
    # 0.1805 mm at h/2, h/4 and h/8 (0.1721, 0.1685 mm at h/2, h/4 before)
    "skin_layered": (39, 417, 0.18002983073319243, 5.86119543278905e-05, None),
    # re-pinned when boundary particles stopped doubling the lattice's own along its top edge
    # (tissue/shapes.py fit_particles; K0's condition number 1.6e9 -> 1.6e3, and 3e13 at a
    # quarter of the spacing, refused, -> 1.3e4) and its circle's 96 vertices stopped being
    # particles: unplanned 0.3292 -> 0.3232 mm against 0.3210, 0.3220 and 0.3236 mm at h/2, h/4
    # and h/8 (0.3215 mm at h/2 before, h/4 refused); verified plan 0.0045 -> 0.0002 mm.
    # Re-pinned when a boundary particle stopped giving way to a lattice particle just inside
    # the boundary (fit_particles: the lattice's gives way instead, so the hole's wall carries a
    # particle at every local spacing): unplanned 0.32322 -> 0.32318 mm, the same 417 particles.
    # Re-pinned when the visibility criterion stopped testing a round hole for pairs shorter
    # than its width (tissue.shape_functions.Visibility): unplanned 0.3232 -> 0.3185 mm, with
    # 0.3196, 0.3215 and 0.3224 mm at h/2, h/4 and h/8 (0.3216, 0.3221 at h/2, h/4 before),
    # the linear triangles on the same particles 0.2951, 0.3085, 0.3137 mm at h, h/2, h/4.
    # Re-pinned when a pair through a round hole was weighed by the way round it instead of
    # kept whole (tissue.shape_functions.Visibility): unplanned 0.318523 -> 0.318540 mm.
    # Re-pinned when the particles were graded toward a round hole to leaves of at most half its
    # inradius at the default spacing (tissue.shapes.hole_zones; here 1.5 mm, the needle's spacing,
    # now along the hole's whole wall): 417 -> 424 particles, unplanned 0.318540 -> 0.318531 mm,
    # with 0.3190, 0.3198 and 0.3216 mm at h/sqrt2, h/2 and h/4 (0.3188, 0.3196, 0.3215 before)
    "hole_near_stitch": (39, 424, 0.31853135385161496, 0.0001500468466868511, None),
    # re-pinned with hole_near_stitch (no boundary particles between the lattice's own on an
    # edge along a lattice line): 1474 -> 1457 particles, unplanned 0.7260 -> 0.7244 mm, with
    # 0.7246 and 0.7280 mm at h/2 and h/4 (0.7254 and 0.7281 before)
    "wound_closure": (39, 1457, 0.724379471620868, 0.0008295656681164761, 0.013907748836645695),
    "wound_closure_symmetric": (39, 1457, 0.724379471620868, 0.015145124419607792, -0.0010171507772573918),
}

# static scenes re-pinned when load segments got a particle on each end and particles graded
# toward the segment ends (tests/test_segments.py, benchmarks/results/deform_segments.md): the
# slab's probes moved by at most 0.009 mm, the fitted moduli by 1.7e-4 and 4e-6 MPa; needle
# scenes (no load segments) are unchanged
SLAB_PROBES = np.array([
    [0, 50, -1.36386595, 1.79477693],
    [0, 20, -0.872886815, 1.46409331],
    [25, 50, -0.763060905, 1.10446388],
    [50, 50, -0.415764045, 0.623465084],
    [50, 90, 0.101934359, 0.49680446],
    [75, 25, -0.280734118, 0.329852297],
])

CALIBRATION = {"lame_lambda": 0.187484, "lame_mu": 0.147878}

runner = CliRunner()


def invoke(*args: str):
    result = runner.invoke(app, [str(a) for a in args])
    assert result.exit_code == 0, result.output
    return result


def pinned_plan(scene: str, tmp_path, steps: int, particles: int, unplanned: float, planned: float) -> dict:
    """`plan CONFIG --no-verify` on a shipped scene, checked against its pins and the move
    limits; its summary."""
    config = yaml.safe_load((CONFIGS / f"{scene}.yaml").read_text())
    summary = tmp_path / "summary.json"
    invoke("plan", CONFIGS / f"{scene}.yaml", "--export", tmp_path / "t.csv", "--summary", summary,
           "--no-verify")
    record = json.loads(summary.read_text())
    assert (record["steps"], record["particles"]) == (steps, particles)
    graded = record["discretization"]["needle_spacing_mm"] is not None  # the file's grading, as run
    grading = (config.get("discretization") or {}).get("needle_grading", 0.5)
    assert record["discretization"]["needle_grading"] == (grading if graded else None)
    assert record["unplanned_exit_error_mm"] == pytest.approx(unplanned, abs=1e-6)
    assert record["exit_error_mm"] == pytest.approx(planned, abs=2e-4)
    if (config.get("planner") or {}).get("target") != "symmetric":  # symmetric aims the bites
        assert record["exit_error_mm"] <= 0.005
    # a path a robot can follow: per 0.08 rad, centre moves <= 0.3 mm, second differences <= 0.15 mm
    scale = config["needle"]["step"] / 0.08
    assert record["max_center_step_mm"] <= 0.3 * scale
    assert record["max_center_second_difference_mm"] <= 0.15 * scale
    return record


@pytest.mark.parametrize("scene", sorted(NEEDLE_SCENES))
def test_planned_and_unplanned_exit_of_each_shipped_scene(scene, tmp_path):
    pinned_plan(scene, tmp_path, *NEEDLE_SCENES[scene])


@pytest.mark.parametrize("scene", sorted(SHAPE_SCENES))
def test_planned_and_unplanned_exit_of_each_shipped_shape_scene(scene, tmp_path):
    *pins, bite_difference = SHAPE_SCENES[scene]
    record = pinned_plan(scene, tmp_path, *pins)
    if bite_difference is None:
        assert not record.get("bites")
    else:
        assert record["bites"]["difference_mm"] == pytest.approx(bite_difference, abs=2e-4)


def test_slab_probes_pinned(tmp_path):
    probes = tmp_path / "probes.csv"
    invoke("deform", CONFIGS / "slab_edge_load.yaml", "--probes-out", probes)
    values = np.loadtxt(probes, delimiter=",", skiprows=1)
    np.testing.assert_allclose(values[:, :2], SLAB_PROBES[:, :2])
    np.testing.assert_allclose(values[:, 2:], SLAB_PROBES[:, 2:], atol=1e-7)


def test_sample_calibration_pinned(tmp_path):
    fitted = tmp_path / "fitted.yaml"
    invoke("calibrate", "material", REPOSITORY / "sample_runs" / "calibration" / "calibration.yaml",
           "--out", fitted, "--no-estimate")  # the moduli are pinned, not their estimate
    material = yaml.safe_load(fitted.read_text())["material"]
    assert "NOT IDENTIFIED" not in fitted.read_text()  # identified: no header against pasting it
    for key, value in CALIBRATION.items():
        assert material[key] == pytest.approx(value, abs=2e-6)
