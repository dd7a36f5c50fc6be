"""Features at or below what the particles resolve: circular holes, thin strips of tissue,
sharp corners, and the singular matrices they used to end a run with.

A circular hole's wall carries particles one local spacing apart (not one per vertex of its
96-gon), and no edge doubles the lattice's own particles on it: configs/hole_near_stitch.yaml
factors at a quarter of its spacing, and a 1 um hole changes nothing the model resolves.
Tissue thinner than half the local particle spacing, and corners sharper than the model
resolves, are refused by every command that builds a model, in one line naming the hole
(stitchplan/tissue/thin_features.py, where the limits are measured). What still slips
through ends in one line, never a traceback. Small models: the module runs in a few seconds
(a quarter of hole_near_stitch's spacing, ~5000 particles, is the largest).
"""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
import scipy.sparse as sp
import yaml
from conftest import CONFIGS, SLAB_EDGE_LOAD
from test_bad_inputs import OUTPUTS, assert_refused, invoke, write_scene

from stitchplan.config import Discretization
from stitchplan.config.scenario import load_scenario, parse_scenario
from stitchplan.errors import InputError, NumericalFailure

PHANTOM = {"model": "neo-hookean", "lame_lambda": 0.189151, "lame_mu": 0.147688}


def strip(thickness: float, needle: bool = True, left: float = 40.0, width: float = 10.0) -> dict:
    """The 60 x 30 mm block of hole_near_stitch with a rectangular hole from x = `left` to
    `left` + `width` leaving a strip `thickness` mm thick under its top edge (without
    `needle`: no needle, the spacing deform's default, 1.5 mm); every command accepts its
    keys."""
    raw = {
        "name": "thin strip",
        "tissue": {"size": [60.0, 30.0], "thickness": 10.0, "material": dict(PHANTOM),
                   "holes": [{"polygon": [[left, 20.0], [left + width, 20.0], [left + width, 30.0 - thickness],
                                          [left, 30.0 - thickness]]}],
                   "clamped": ["bottom"]},
        "needle": {"radius": 8.88, "entry": [30.0, 30.0], "turn": "cw", "step": 0.08, "friction": 0.0602,
                   "cutting_force": 0.7},
        "loads": [{"segment": [[60.0, 0.0], [60.0, 30.0]], "force": [2.0, 0.0]}],
        "probes": [[30.0, 30.0]],
    }
    if not needle:
        del raw["needle"]
    return raw


# --- circular holes at the local spacing -------------------------------------------------------


def test_hole_near_stitch_factors_at_a_quarter_of_its_spacing():
    """At 0.75 mm the particles added along the top edge between the lattice's own (which
    the edge, a lattice line, already carries one spacing apart) made K0 nearly singular
    (condition ~3e13, the run refused); now ~1.3e4, as the block's own at that spacing."""
    from stitchplan.needle.prepared_tissue import PreparedTissue
    from stitchplan.planning.replay_models import rescaled
    from stitchplan.tissue.factorization import condition_estimate

    scenario = rescaled(load_scenario(CONFIGS / "hole_near_stitch.yaml"), 0.25)
    assert scenario.discretization.spacing == 0.75
    tissue = PreparedTissue(scenario)
    factor = tissue.factor_at_rest()  # refuses a condition number above 1e12
    stiffness = tissue.stiffness_at_rest()
    assert condition_estimate(stiffness, factor) < 1e5


def test_no_particle_is_added_between_the_lattice_s_own_on_an_edge():
    """Along hole_near_stitch's top edge (a lattice line) at its default spacing the
    particles stand no closer than half the local spacing (they stood 0.72 mm apart at 1.5)."""
    from stitchplan.needle.geometry import needle_zone
    from stitchplan.tissue.model import model_for_scenario

    scenario = load_scenario(CONFIGS / "hole_near_stitch.yaml")
    model = model_for_scenario(scenario, needle_zone(scenario))
    local = model.support / scenario.discretization.dilation
    top = np.flatnonzero(np.abs(model.particles[:, 1] - 30.0) < 1e-9)
    order = top[np.argsort(model.particles[top, 0])]
    gaps = np.diff(model.particles[order, 0])
    assert np.all(gaps >= 0.5 * np.minimum(local[order[1:]], local[order[:-1]])), gaps.min()


def slab_with_hole(radius: float | None) -> dict:
    """configs/slab_edge_load.yaml (100 x 100 mm, clamped right, pulled on 20 mm of its left
    edge) with a circular hole of `radius` at (80, 80), 60 mm from the probes."""
    raw = yaml.safe_load(SLAB_EDGE_LOAD.read_text())
    raw["probes"] = [[0.0, 50.0], [25.0, 50.0]]
    if radius is not None:
        raw["tissue"]["holes"] = [{"circle": {"center": [80.0, 80.0], "radius": radius}}]
    return raw


@pytest.mark.parametrize("radius", [1e-3, 1e-4])
def test_a_hole_far_below_the_spacing_changes_nothing_the_model_resolves(radius):
    """A 1 um hole moved the probe at (25, 50) by 1.25 % (its 96 vertices were particles a few
    nanometres apart), one of 0.1 um stopped Newton at the first load step. Such a hole keeps
    one boundary particle, and the quadrature still cuts it out: the probes move by less
    than 0.01 % of the largest displacement (the limit asserted: 0.1 %)."""
    from stitchplan.tissue.deform import run_deform

    plain = run_deform(parse_scenario(slab_with_hole(None))).probe_displacements
    result = run_deform(parse_scenario(slab_with_hole(radius)))
    on_hole = np.abs(np.hypot(*(result.model.particles - [80.0, 80.0]).T) - radius) <= 1e-6
    assert on_hole.sum() == 1
    assert np.abs(result.probe_displacements - plain).max() < 1e-3 * np.abs(plain).max()


# --- thin tissue refused up front ------------------------------------------------------------------


@pytest.mark.parametrize("command", ["simulate", "deform", "plan"])
@pytest.mark.parametrize("thickness", [0.01, 0.1])
def test_a_strip_thinner_than_the_spacing_is_refused_by_every_command(tmp_path, command, thickness):
    """Before: simulate ended in a traceback (SuperLU's 'Factor is exactly singular') or an
    exit-1 line blaming the dilation, deform refused blaming the dilation even at
    --dilation 4 --spacing 0.5, and the 0.1 mm strip ran under simulate. Now each command
    refuses it before any model is built, naming the hole, the thickness, where, the spacing
    there and what to do, and writes nothing."""
    path = write_scene(tmp_path, strip(thickness))
    result = invoke(tmp_path, command, "scene.yaml", *OUTPUTS[command])
    assert_refused(result, tmp_path, {"scene.yaml"}, [[
        f"{path}: tissue.holes[0]: the hole leaves tissue {thickness:g} mm thin at (", "between it and the outline",
        "below what the particle spacing there (", "expected tissue at least 0.5 x the local spacing thick",
        f"refine the spacing there to {2 * thickness:g} mm or less", "or move or shrink the hole"]])


def test_a_strip_only_the_estimate_s_coarser_model_cannot_resolve_leaves_the_run_without_estimate(tmp_path):
    """A 1 mm strip over a circular hole at 1.5 mm spacing (0.67 of it) runs; at twice the
    spacing, the exit error estimate's model, it is too thin. The resource guard, which places
    that model's particles, refused the whole simulate (exit 2, 'refine the spacing there to
    2.01 mm or less' where the file's was 1.5 mm); the estimate's failure is now the run's
    accuracy-check event, as when that model fails otherwise."""
    raw = strip(1.0)
    raw["tissue"]["holes"] = [{"circle": {"center": [45.0, 24.0], "radius": 5.0}}]
    raw["discretization"] = {"spacing": 1.5}
    write_scene(tmp_path, raw)
    result = invoke(tmp_path, "simulate", "scene.yaml", "--summary", "summary.json")
    assert result.exit_code == 0, result.output
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["exit_error_estimate_mm"] is None
    assert [event["kind"] for event in summary["events"]] == ["accuracy-check"]
    assert "the model at twice the spacing failed (tissue.holes[0]: the hole leaves tissue 1.01 mm thin" in (
        summary["events"][0]["message"])


def test_a_strip_half_the_spacing_thick_runs():
    """The limit's other side: a 1 mm strip at the 1.5 mm spacing deform gives it
    (0.6 x the local spacing) builds, solves and reproduces nothing singular."""
    from stitchplan.tissue.deform import run_deform

    result = run_deform(parse_scenario(strip(1.0, needle=False)))
    assert np.all(np.isfinite(result.probe_displacements))


def test_a_strip_between_two_holes_names_both():
    from stitchplan.tissue.model import model_for_scenario

    raw = strip(0.05, needle=False)
    raw["tissue"]["holes"] = [{"polygon": [[40.0, 15.0], [50.0, 15.0], [50.0, 20.0], [40.0, 20.0]]},
                              {"circle": {"center": [45.0, 22.55], "radius": 2.5}}]
    with pytest.raises(InputError, match=r"^tissue\.holes\[\d\]: the hole leaves tissue 0\.05 mm thin at .* "
                                         r"between it and holes\[\d\], .*move or shrink either hole$"):
        model_for_scenario(parse_scenario(raw))


@pytest.mark.parametrize("neck", [0.05, 0.01, 0.001])
def test_a_neck_between_two_tips_is_refused_with_its_width(neck):
    """Two pointed notches whose tips face each other across `neck` mm, and two diamond holes
    whose corners do: no edge's normal crosses the neck, which the check measured from the
    edges alone, so the tissue ran through a 1 um neck (exit 0, the far half carried by it);
    the vertices' gaps find it and say its width."""
    from stitchplan.tissue.model import model_for_scenario

    raw = strip(0.05, needle=False)
    low, high = 15.0 - neck / 2, 15.0 + neck / 2
    raw["tissue"].pop("holes")
    raw["tissue"].pop("size")
    raw["tissue"]["outline"] = [[0, 0], [25, 0], [30, low], [35, 0], [60, 0], [60, 30], [35, 30], [30, high],
                                [25, 30], [0, 30]]
    raw["tissue"]["clamped"], raw["probes"] = ["left"], [[60.0, 15.0]]
    with pytest.raises(InputError, match=rf"^tissue\.outline: the outline leaves tissue {neck:g} mm thin at \(30, "
                                         r"15\) mm between two of its edges"):
        model_for_scenario(parse_scenario(raw))
    raw = strip(0.05, needle=False)
    raw["tissue"]["holes"] = [{"polygon": [[30, 5], [35, 10], [30, low], [25, 10]]},
                              {"polygon": [[30, high], [35, 20], [30, 25], [25, 20]]}]
    with pytest.raises(InputError, match=rf"^tissue\.holes\[0\]: the hole leaves tissue {neck:g} mm thin at "
                                         r"\(30, 15\) mm between it and holes\[1\]"):
        model_for_scenario(parse_scenario(raw))


def test_a_gap_narrower_than_the_spacing_is_no_thin_tissue():
    """A wound 2 mm wide and 10 mm deep at 5 mm spacing: the lips of its walls lie 2 mm apart
    across the gap, outside the tissue, which the vertices' gaps measured as tissue 2 mm thin
    at the gap's middle and refused (so did a needle run's estimate at twice its spacing);
    the tissue either side is 29 mm wide, and the run's two sides move apart as at 1 mm."""
    from stitchplan.tissue.deform import run_deform

    raw = strip(0.05, needle=False)
    raw["tissue"].pop("holes")
    raw["tissue"].pop("size")
    raw["tissue"]["outline"] = [[0, 0], [60, 0], [60, 30], [31, 30], [31, 20], [29, 20], [29, 30], [0, 30]]
    raw["loads"] = [{"segment": [[0.0, 10.0], [0.0, 30.0]], "force": [-1.0, 0.0]}]
    raw["probes"] = [[29.0, 25.0], [31.0, 25.0]]
    raw["discretization"] = {"spacing": 5.0}
    coarse = run_deform(parse_scenario(raw)).probe_displacements
    raw["discretization"] = {"spacing": 1.0}
    fine = run_deform(parse_scenario(raw)).probe_displacements
    np.testing.assert_allclose(coarse[:, 0], fine[:, 0], rtol=0.1)  # x: -0.43 mm left of it, -0.15 right


def test_a_circle_cutting_the_edge_at_a_shallow_angle_is_refused_at_every_spacing():
    """A 5 mm hole poking 0.15 or 0.33 mm through the top edge meets it at 20 or 32 degrees
    (at a point on one of its 96-gon's edges): with the check off the sliver beyond it gives a
    singular moment matrix at 3 and 1.5 mm, at 20 degrees at 0.75 mm too. Refining does not
    resolve it, so the line says to move the hole; at 45 degrees it runs."""
    from stitchplan.tissue.model import model_for_scenario

    def crossing(degrees: float, spacing: float) -> dict:
        raw = strip(1.0, needle=False)
        drop = 2.5 * (1.0 - math.cos(math.radians(degrees)))
        raw["tissue"]["holes"] = [{"circle": {"center": [45.37, 27.5 + drop], "radius": 2.5}}]
        raw["discretization"] = {"spacing": spacing}
        return raw

    for degrees, spacing in ((20.0, 3.0), (30.0, 0.75)):
        with pytest.raises(InputError) as refused:
            model_for_scenario(parse_scenario(crossing(degrees, spacing)))
        message = str(refused.value)
        assert re.match(r"tissue\.holes\[0\]: the hole meets the tissue's edge at a corner of (2\d|3[0-5])(\.\d)? "
                        r"degrees at \(4\d\.\d+, 30\) mm, a sliver of tissue that no particle spacing resolves",
                        message), message
        assert message.endswith("expected a corner of at least 40 degrees: move or shrink the hole so that it "
                                "crosses the edge more steeply or stays clear of it")
        assert "refine" not in message
    model_for_scenario(parse_scenario(crossing(45.0, 1.5)))


def test_an_acute_outline_corner_the_model_resolves_is_not_refused():
    """A triangle's 20 degree corner: near its tip the tissue is thinner than any spacing, yet
    the corner's particle and its edges' resolve it (15 degrees ran at 3 and 1.5 mm, 10 did
    not); it is a wedge, not a strip, and only a corner below 12.5 degrees is refused."""
    from stitchplan.tissue.model import model_for_scenario

    def triangle(degrees: float) -> dict:
        top = 60.0 * math.tan(math.radians(degrees))
        return {"tissue": {"outline": [[0.0, 0.0], [60.0, 0.0], [60.0, top]], "thickness": 10.0,
                           "material": dict(PHANTOM), "clamped": [{"segment": [[60.0, 0.0], [60.0, top]]}]},
                "loads": [{"segment": [[0.0, 0.0], [60.0, top]], "force": [0.0, 0.5]}]}

    model_for_scenario(parse_scenario(triangle(20.0)))
    with pytest.raises(InputError, match=r"^tissue\.outline: the outline has a corner of 10 degrees at \(0, 0\) mm"):
        model_for_scenario(parse_scenario(triangle(10.0)))


@pytest.mark.parametrize("scene", ["hole_near_stitch", "wound_closure", "wound_closure_symmetric"])
def test_no_shipped_shape_is_refused_at_its_spacing_half_or_a_quarter(scene):
    """The check on the lattice each model would build (the other shipped scenes are
    rectangles, which have no thin tissue): nothing under three local spacings thick."""
    from stitchplan.needle.geometry import needle_zone
    from stitchplan.planning.replay_models import rescaled
    from stitchplan.tissue.model import load_segments, shaped_lattice
    from stitchplan.tissue.shapes import lattice_spacing
    from stitchplan.tissue.thin_features import thinnest_spot

    for factor in (1.0, 0.5, 0.25):
        scenario = rescaled(load_scenario(CONFIGS / f"{scene}.yaml"), factor)
        held, pulled = load_segments(scenario)
        lattice = shaped_lattice(scenario.tissue, scenario.discretization, held + pulled, needle_zone(scenario))
        assert thinnest_spot(scenario.tissue, lattice_spacing(lattice), limit=3.0) is None


# --- what slips through: one line, never a traceback ----------------------------------------------


def test_a_singular_matrix_is_the_project_s_error_not_scipy_s():
    from stitchplan.tissue.factorization import SuperLUFactor

    with pytest.raises(NumericalFailure, match=r"^the 2 x 2 stiffness matrix is singular: SuperLU met a zero pivot"):
        SuperLUFactor(sp.csr_matrix(np.ones((2, 2))))


@pytest.mark.parametrize("command", ["simulate", "deform"])
@pytest.mark.parametrize("left, width", [(40.0, 10.0), (22.0, 6.0)])
def test_without_the_check_a_thin_strip_ends_in_one_line(tmp_path, monkeypatch, command, left, width):
    """With the up-front check switched off, a 0.01 mm strip reaches the model: its build
    meets a singular moment matrix and names the hole and the thickness through the failing
    point (the dilation does not help there), or the factorization of K0 (the strip over the
    needle's entry, simulate) fails in one line, where it was SuperLU's traceback."""
    import stitchplan.tissue.model as model

    monkeypatch.setattr(model, "refuse_thin_tissue", lambda tissue, spacing_at: None)
    write_scene(tmp_path, strip(0.01, left=left, width=width))
    result = invoke(tmp_path, command, "scene.yaml", *OUTPUTS[command])
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)
    assert "Traceback" not in result.output
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    assert result.exit_code in (1, 2)
    if "moment matrix" in lines[0]:
        assert result.exit_code == 2 and "tissue.holes[0]: the hole leaves tissue 0.01 mm thin" in lines[0]
    else:
        assert result.exit_code == 1 and "stiffness matrix is singular: SuperLU met a zero pivot" in lines[0]


def test_a_nearly_singular_stiffness_at_dilation_2_does_not_advise_the_dilation():
    """K0 nearly singular at a dilation of 3 or less is not the kernels' doing: the line
    names crowded particles instead of advising a dilation the run already uses."""
    from stitchplan.needle.prepared_tissue import refuse_singular_stiffness

    with pytest.raises(InputError) as narrow:
        refuse_singular_stiffness(3e13, Discretization(spacing=0.75, dilation=2.0))
    assert "use a dilation of 3 or less" not in str(narrow.value)
    assert "particles closer together than the spacing" in str(narrow.value)
    with pytest.raises(InputError, match="use a dilation of 3 or less"):
        refuse_singular_stiffness(3e13, Discretization(spacing=0.75, dilation=4.0))
    refuse_singular_stiffness(1e4, Discretization(spacing=0.75, dilation=2.0))  # well conditioned: passes


def test_a_nearly_singular_stiffness_names_the_particles_closest_for_their_spacing():
    """Given the particles, the line says where to look: the pair closest for their local
    spacing (here two particles 0.1 mm apart in a 1 mm lattice, at (2.05, 2))."""
    from stitchplan.needle.prepared_tissue import refuse_singular_stiffness

    lattice = np.stack(np.meshgrid(np.arange(5.0), np.arange(5.0)), axis=-1).reshape(-1, 2)
    particles = np.vstack([lattice, [[2.1, 2.0]]])
    with pytest.raises(InputError) as refused:
        refuse_singular_stiffness(3e13, Discretization(spacing=1.0, dilation=2.0), particles, np.ones(len(particles)))
    assert ("the particles closest for their spacing are 0.1 mm apart at [2.05, 2] (0.1 of the local spacing, "
            "1 mm)") in str(refused.value)


def test_a_nearly_incompressible_material_is_named_not_the_particles(tmp_path):
    """lame_lambda 1e10 MPa over lame_mu 1 MPa made K0's condition number ~9e12 on a lattice
    that gives ~1e3 with the shipped moduli, and the line blamed particles closer together than
    the spacing; the material is named instead, a region's by its index. Crowded particles
    under a compressible material are still told as before."""
    from typer.testing import CliRunner

    from stitchplan.cli import app
    from stitchplan.config import Material, Tissue
    from stitchplan.config.blocks import Region
    from stitchplan.needle.prepared_tissue import refuse_singular_stiffness

    raw = {"tissue": {"size": [40.0, 30.0], "thickness": 10.0, "clamped": ["right"],
                      "material": {"lame_lambda": 1e6, "lame_mu": 1e-4}},  # within a file's bounds
           "discretization": {"spacing": 5.0},
           "needle": {"radius": 8.0, "entry": [0.0, 22.0], "turn": "cw", "step": 0.2, "friction": 0.0602,
                      "cutting_force": 0.7}}
    scenario = tmp_path / "stiff.yaml"
    scenario.write_text(yaml.safe_dump(raw, sort_keys=False))
    summary = tmp_path / "summary.json"
    result = CliRunner().invoke(app, ["simulate", str(scenario), "--summary", str(summary), "--no-estimate"])
    lines = result.output.strip().splitlines()
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert lines[0].startswith(f"error: {scenario}: tissue.material: got lame_lambda 1e+06 MPa with lame_mu 0.0001 MPa, "
                               "(lambda + 2 mu) / mu = 1e+10, a material so nearly incompressible"), lines[0]
    assert "particles closer together" not in lines[0] and not summary.exists()

    soft, stiff = Material(lame_lambda=0.189151, lame_mu=0.147688), Material(lame_lambda=1e12, lame_mu=0.5)
    layered = Tissue((40.0, 30.0), 10.0, soft, ("right",),
                     regions=(Region(material=stiff, polygon=((0.0, 28.0), (40.0, 28.0), (40.0, 30.0), (0.0, 30.0))),))
    with pytest.raises(InputError, match=r"^tissue\.regions\[0\]\.material: got lame_lambda 1e\+12 MPa"):
        refuse_singular_stiffness(3e15, Discretization(spacing=1.0, dilation=2.0), tissue=layered)
    with pytest.raises(InputError, match="particles closer together than the spacing"):
        refuse_singular_stiffness(3e13, Discretization(spacing=1.0, dilation=2.0),
                                  tissue=Tissue((40.0, 30.0), 10.0, soft, ("right",)))


def test_a_singular_moment_matrix_keeps_its_point_across_processes():
    """Replays run in helper processes and send their failures back pickled: the point the
    build's line is made from survives the trip."""
    import pickle

    from stitchplan.tissue.shape_functions import SingularMomentAt

    made = SingularMomentAt("moment matrix M(X) is singular at (1, 2) mm", np.array([1.0, 2.0]))
    error = pickle.loads(pickle.dumps(made))
    assert isinstance(error, NumericalFailure) and str(error).startswith("moment matrix")
    assert error.point.tolist() == [1.0, 2.0]


def test_the_thinnest_spot_is_thinnest_for_its_spacing_not_in_millimetres():
    """Two strips under the top edge: 0.6 mm where the particles are 2 mm apart (0.3 of the
    spacing), 0.4 mm where they are 1 mm apart (0.4): the spot named is the first, the one
    the particles resolve worst, though the second is thinner."""
    from stitchplan.tissue.thin_features import thinnest_spot

    raw = strip(0.6, needle=False, left=10.0)
    raw["tissue"]["holes"].append({"polygon": [[40.0, 20.0], [50.0, 20.0], [50.0, 29.6], [40.0, 29.6]]})
    tissue = parse_scenario(raw).tissue
    spot = thinnest_spot(tissue, lambda points: np.where(points[:, 0] < 30.0, 2.0, 1.0), limit=0.5)
    assert 10.0 <= spot.start[0] <= 20.0 and spot.thickness == pytest.approx(0.6, abs=1e-9)
    assert spot.thickness / spot.spacing == pytest.approx(0.3, abs=1e-9)


def test_a_plate_with_a_round_hole_runs_at_every_spacing_near_the_one_it_was_refused_at(tmp_path):
    """The plate with a circular hole (benchmarks/deform_shapes.py) at 0.45 and 0.55 mm: a
    quadrature point 0.00085 mm from the hole's 96-gon saw the wall's particles only through
    the hole, the four left lay on one line and the build was refused (0.44 and 0.46 mm ran).
    The hole, wider than any pair reaching it, is left out of the visibility criterion now."""
    raw = {"tissue": {"size": [40.0, 20.0], "thickness": 10.0, "material": dict(PHANTOM), "clamped": ["left"],
                      "holes": [{"circle": {"center": [20.0, 10.0], "radius": 5.0}}]},
           "discretization": {"spacing": 0.45},
           "loads": [{"segment": [[40.0, 0.0], [40.0, 20.0]], "force": [1.0, 0.3]}], "load_steps": 2}
    for spacing in (0.45, 0.55):
        raw["discretization"]["spacing"] = spacing
        write_scene(tmp_path, raw)
        result = invoke(tmp_path, "deform", "scene.yaml", *OUTPUTS["deform"])
        assert result.exit_code == 0, result.output
