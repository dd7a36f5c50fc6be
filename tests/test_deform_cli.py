"""`stitchplan deform`: equilibrium and reactions of the static solve, and the command
itself on real files in tmp_path (outputs, and bad inputs ending in one error line,
exit code 2 and no output left behind)."""

from __future__ import annotations

import csv
import json

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from stitchplan.tissue.assembly import Assembler
from stitchplan.tissue.boundary_conditions import CLAMPED
from stitchplan.cli import app
from stitchplan.config.scenario import load_scenario, parse_scenario
from stitchplan.tissue.deform import external_forces, run_deform, to_free
from stitchplan.tissue.material import first_piola_and_tangent

PROBE_COUNT = 6  # probes in configs/slab_edge_load.yaml


# --- equilibrium and reactions -----------------------------------------------------------


def particle_internal_force(model, coefficients) -> np.ndarray:
    """f_int on every particle coefficient (NP, 2), before the boundary transformation."""
    first_piola, _ = first_piola_and_tangent(model.material, model.deformation_gradient(coefficients))
    weighted = first_piola * model.quadrature_weights[:, None, None]  # (nq, i, J)
    return model.shape.grad_x.T @ weighted[:, :, 0] + model.shape.grad_y.T @ weighted[:, :, 1]


def clamped_reaction(result) -> np.ndarray:
    """Total force the tissue exerts on its clamped edges (N), as deform.reactions does for a
    prescribed segment: minus the boundary multipliers T_g^T (f_int - f_ext) summed over the clamp."""
    model = result.model
    unbalanced = model.boundary.prescribed_map.T @ (
        particle_internal_force(model, result.coefficients) - external_forces(model, result.scenario))
    return -unbalanced[model.boundary.group == CLAMPED].sum(axis=0)


def test_shipped_slab_is_in_equilibrium(slab_path):
    """configs/slab_edge_load.yaml: the free-coefficient residual at the converged state is
    below the solver tolerance (1e-8) relative to the applied load, as reported and recomputed."""
    result = run_deform(load_scenario(slab_path))
    model = result.model
    external = to_free(model, external_forces(model, result.scenario))
    applied = np.linalg.norm(external)
    assert applied > 0.1  # N: the 3.16 N load reaches the free coefficients
    assert len(result.report.steps) == 10
    assert result.report.steps[-1].residual <= 1e-8 * applied
    assert result.report.steps[-1].load_fraction == 1.0
    internal = Assembler(model).update(model.deformation_gradient(result.coefficients))
    assert np.linalg.norm(internal - external) <= 1e-8 * applied


def test_shipped_slab_clamp_carries_the_applied_load(slab_path):
    """Global equilibrium: the clamp receives the whole 3 N / 1 N load, the loaded segment's
    reaction is minus its load, and the slab moves the way it is pulled."""
    result = run_deform(load_scenario(slab_path))
    np.testing.assert_allclose(clamped_reaction(result), [-3.0, 1.0], rtol=0, atol=1e-6)
    np.testing.assert_allclose(result.reactions, [[3.0, -1.0]], rtol=0, atol=1e-12)
    ux, uy = result.probe_displacements[0]  # (0, 50), middle of the loaded segment
    assert ux < -0.5 and uy > 0.5
    # the probe displacement is the RK interpolant, not the coefficient of the particle at
    # (0, 50): RK functions lack the Kronecker-delta property
    at_probe = int(np.flatnonzero(np.all(result.model.particles == [0.0, 50.0], axis=1))[0])
    assert np.abs(result.probe_displacements[0] - result.coefficients[at_probe]).max() > 1e-6


@pytest.fixture
def displaced_slab(slab_raw) -> dict:
    """The shipped slab with its left-edge segment moved by [-2, 1] mm instead of pulled."""
    slab_raw["loads"] = [{"segment": [[0.0, 40.0], [0.0, 60.0]], "displacement": [-2.0, 1.0]}]
    slab_raw["probes"] = [[0.0, 50.0], [0.0, 40.0], [25.0, 50.0]]
    return slab_raw


def test_displacement_segment_reaction_balances_the_clamp(displaced_slab):
    result = run_deform(parse_scenario(displaced_slab))
    segment = result.reactions[0]
    assert np.linalg.norm(segment) > 0.1  # N, a real reaction
    np.testing.assert_allclose(segment, -clamped_reaction(result), rtol=0, atol=1e-6 * np.linalg.norm(segment))
    # the tissue resists the imposed motion
    assert segment @ np.array([-2.0, 1.0]) < 0
    # the transformation method imposes the displacement exactly at the segment's particles
    np.testing.assert_allclose(result.probe_displacements[:2], [[-2.0, 1.0], [-2.0, 1.0]], rtol=0, atol=1e-9)


def test_mixed_loads_balance_globally(slab_raw):
    """Force and displacement segments together (the scenario format's example): the clamp and the
    displacement segment together take up the applied force."""
    slab_raw["loads"] = [
        {"segment": [[0.0, 40.0], [0.0, 60.0]], "force": [3.0, -2.0]},
        {"segment": [[0.0, 70.0], [0.0, 80.0]], "displacement": [-2.0, 1.0]},
    ]
    result = run_deform(parse_scenario(slab_raw))
    applied = np.array([3.0, -2.0])
    total = clamped_reaction(result) + result.reactions[1]
    np.testing.assert_allclose(total, applied, rtol=0, atol=1e-6)
    np.testing.assert_allclose(result.reactions[0], -applied, atol=1e-12)


# --- the command ---------------------------------------------------------------------------


def invoke(*args: str):
    return CliRunner().invoke(app, ["deform", *map(str, args)])


def read_csv(path):
    with open(path, newline="") as handle:
        rows = list(csv.reader(handle))
    return rows[0], rows[1:]


def test_deform_writes_probes_reactions_summary_and_run_log(slab_path, tmp_path):
    probes, reactions = tmp_path / "probes.csv", tmp_path / "reactions.csv"
    summary, run_log = tmp_path / "summary.json", tmp_path / "run.h5"
    result = invoke(slab_path, "--probes-out", probes, "--reactions-out", reactions,
                    "--summary", summary, "--out", run_log)
    assert result.exit_code == 0, result.output

    header, rows = read_csv(probes)
    assert header == ["x", "y", "ux", "uy"]
    values = np.array(rows, dtype=float)
    scenario = load_scenario(slab_path)
    assert values.shape == (PROBE_COUNT, 4)
    np.testing.assert_array_equal(values[:, :2], np.array(scenario.probes))  # file order
    assert np.all(np.isfinite(values)) and values[0, 2] < 0 < values[0, 3]

    header, rows = read_csv(reactions)
    assert header == ["segment", "fx", "fy"]
    assert len(rows) == 1 and int(rows[0][0]) == 0
    np.testing.assert_allclose(np.array(rows[0][1:], dtype=float), [3.0, -1.0], atol=1e-9)

    report = json.loads(summary.read_text())
    assert {"particles", "load_steps", "newton_iterations", "wall_seconds"} <= report.keys()
    # default spacing 100/20 = 5 mm, plus the particles graded toward the two segment ends
    assert 21 * 21 < report["particles"] < 2 * 21 * 21
    assert report["load_steps"] == 10
    assert report["newton_iterations"] >= report["load_steps"]
    assert report["wall_seconds"] > 0
    # the linear solver that ran, as in simulate's and plan's summaries
    solver = report["solver"]
    assert solver["factorizations"] >= 1 and solver["linear_solves"] == report["newton_iterations"]
    assert solver["linear_solver_backend"] == solver["linear_solver_backends"][-1]
    assert solver["linear_solver_backend"].startswith(("CHOLMOD", "scipy SuperLU"))

    with h5py.File(run_log, "r") as handle:
        text = handle["scenario/text"][()]
        text = text.decode() if isinstance(text, bytes) else text
        assert text == slab_path.read_text()
        assert json.loads(handle.attrs["solver_counts"]) == solver
        np.testing.assert_allclose(handle["probes/displacement"][()], values[:, 2:], rtol=1e-8, atol=1e-12)

    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["slab_edge_load.yaml", "probes.csv", "reactions.csv", "summary.json", "run.h5"])


def test_probes_out_without_probes_says_its_csv_holds_the_header_alone(tmp_path, slab_raw, write_scenario):
    scenario = write_scenario(with_changes(slab_raw, probes=[]))
    probes = tmp_path / "probes.csv"
    result = invoke(scenario, "--probes-out", probes)
    assert result.exit_code == 0, result.output
    assert read_csv(probes) == (["x", "y", "ux", "uy"], [])
    assert result.stderr.splitlines() == [f"note: --probes-out: {scenario} has no `probes` (reference points, mm); "
                                          f"{probes} holds the header alone"]


def test_spacing_option_overrides_the_scenario(slab_path, tmp_path):
    summary = tmp_path / "summary.json"
    result = invoke(slab_path, "--spacing", "10", "--summary", summary)
    assert result.exit_code == 0, result.output
    # the 10 mm grid (11 x 11) plus the particles graded toward the segment ends, fewer than
    # the default 5 mm grid alone
    assert 11 * 11 < json.loads(summary.read_text())["particles"] < 21 * 21


def test_vci_integration_runs_deform_and_agrees_with_gauss(slab_path, tmp_path):
    """integration: vci from the file; the probes agree with the default Gauss run to well within
    the discretization error (both 0.4 % from the converged answer at 5 mm)."""
    import yaml

    raw = yaml.safe_load(slab_path.read_text())
    raw["discretization"] = {**(raw.get("discretization") or {}), "integration": "vci"}
    vci_path = tmp_path / "vci.yaml"
    vci_path.write_text(yaml.safe_dump(raw))
    probes = {}
    for name, path in (("gauss", slab_path), ("vci", vci_path)):
        out = tmp_path / f"probes_{name}.csv"
        result = invoke(path, "--probes-out", out)
        assert result.exit_code == 0, result.output
        probes[name] = np.loadtxt(out, delimiter=",", skiprows=1)[:, 2:]
    scale = np.abs(probes["gauss"]).max()
    assert np.abs(probes["vci"] - probes["gauss"]).max() < 5e-3 * scale
    assert np.abs(probes["vci"] - probes["gauss"]).max() > 1e-9 * scale  # a different discretization


def with_changes(raw: dict, **changes) -> dict:
    raw.update(changes)
    return raw


def with_value(raw: dict, path: tuple, value) -> dict:
    block = raw
    for key in path[:-1]:
        block = block[key]
    block[path[-1]] = value
    return raw


# (id, scenario dict builder or None for a missing file, extra options, fragments of the error)
BAD_INPUTS = [
    ("missing file", None, [], ["absent.yaml", "cannot be read"]),
    ("unknown key", lambda r: with_changes(r, solver_settings={"max_iterations": 3}), [],
     ["unknown key 'solver_settings'"]),
    ("negative thickness", lambda r: with_value(r, ("tissue", "thickness"), -10.0), [],
     ["tissue.thickness", "-10.0", "positive"]),
    ("negative lame_mu", lambda r: with_value(r, ("tissue", "material", "lame_mu"), -0.2), [],
     ["tissue.material.lame_mu", "-0.2", "positive"]),
    ("zero spacing option", lambda r: r, ["--spacing", "0"], ["--spacing", "0.0", "positive number"]),
    ("small dilation option", lambda r: r, ["--dilation", "0.5"], ["--dilation", "0.5", "> 1"]),
]

# the same, for a numerical method failing on an accepted input: exit code 1
NUMERICAL_FAILURES = [
    ("unconvergeable solve",
     lambda r: with_changes(r, loads=[{"segment": [[0.0, 40.0], [0.0, 60.0]], "force": [-300.0, 100.0]}],
                            load_steps=1, solver={"max_iterations": 1, "max_step_cuts": 0}),
     ["--spacing", "10"], ["Newton failed", "load step 1", "0 step cuts"]),
]


@pytest.mark.parametrize("build, options, fragments, code", [
    *(pytest.param(b, o, f, 2, id=i) for i, b, o, f in BAD_INPUTS),
    *(pytest.param(b, o, f, 1, id=i) for i, b, o, f in NUMERICAL_FAILURES),
])
def test_bad_input_exits_with_one_error_line_and_no_output(tmp_path, slab_raw, write_scenario, build,
                                                            options, fragments, code):
    scenario = tmp_path / "absent.yaml" if build is None else write_scenario(build(slab_raw))
    before = sorted(p.name for p in tmp_path.iterdir())
    result = invoke(scenario, *options, "--probes-out", tmp_path / "probes.csv", "--reactions-out",
                    tmp_path / "reactions.csv", "--summary", tmp_path / "summary.json",
                    "--out", tmp_path / "run.h5")
    assert result.exit_code == code
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ")
    assert "Traceback" not in result.output
    for fragment in fragments:
        assert fragment in lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no output, no temporary file


def test_spacing_option_is_named_once(slab_path):
    """--spacing 0 names the option, not `--spacing.spacing`; a value that is not a number too."""
    for value, expected in (("0", "error: --spacing: got 0.0, expected a positive number (mm)"),
                            ("abc", "error: --spacing: got 'abc', expected a number")):
        result = invoke(slab_path, "--spacing", value)
        assert result.exit_code == 2
        assert result.stderr.strip() == expected
        assert result.stdout == ""


def test_output_under_a_file_is_refused_before_solving(slab_path, tmp_path):
    blocker = tmp_path / "results"
    blocker.write_text("not a folder")
    result = invoke(slab_path, "--probes-out", blocker / "probes.csv")
    assert result.exit_code == 2
    assert result.stderr.startswith("error: ") and "is not a folder" in result.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results", "slab_edge_load.yaml"]
