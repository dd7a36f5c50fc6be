"""`stitchplan plan --uncertainty`: the uncertainty file and every refusal of it (one line,
exit 2, no file written), the seeded design (reproducible, correlated and spread as asked,
positive), sampled runs on a two-worker Dask cluster identical to in-process ones, a failing
sample recorded rather than lost, and the command end to end with the summary's
`uncertainty` block, the run log and uncertainty.png.

The scene is test_plan_cli's smallest (20 x 20 mm, 25 particles, 0.3 rad steps, one planner
pass): a run takes ~0.1 s, a whole `plan --uncertainty` with 4 samples a few seconds.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from conftest import TIGHT_NEEDLE_NEWTON
from test_plan_cli import invoke, one_error_line, small_raw, write

from stitchplan.config import parse_scenario
from stitchplan.config.uncertainty import load_uncertainty, parse_uncertainty, resolve_uncertainty
from stitchplan.errors import InputError, SolverDivergence
from stitchplan.parallel.executor import Executor
from stitchplan.uncertainty import evaluation
from stitchplan.uncertainty.evaluation import run_sample
from stitchplan.uncertainty.robust import LABELS, exit_statistics, plan_under_uncertainty
from stitchplan.uncertainty.sampling import draw, with_parameters

CALIBRATION = Path(__file__).resolve().parents[1] / "sample_runs" / "calibration"
STATISTICS = {"mean_mm", "p50_mm", "p95_mm", "max_mm"}


def uncertainty(raw: dict, path: str = "uncertainty.yaml"):
    return resolve_uncertainty(parse_uncertainty(raw), path)


def small_uncertainty(samples: int = 4, seed: int = 5) -> dict:
    return {"samples": samples, "seed": seed,
            "parameters": {"lame_mu": {"std": 0.01}, "thickness": {"std": 1.0}, "cutting_force": {"std": 0.1}},
            "correlation": [{"between": ["lame_mu", "thickness"], "value": 0.3}]}


# --- the file --------------------------------------------------------------------------------


def test_from_calibration_gives_the_moduli_spread_and_the_file_overrides_it(tmp_path):
    shutil.copy(CALIBRATION / "fitted.yaml", tmp_path / "fitted.yaml")
    path = write(tmp_path, {"samples": 8, "seed": 7, "from_calibration": "fitted.yaml",
                            "parameters": {"lame_mu": {"std": 0.002}, "thickness": {"std": 0.5}}}, "u.yaml")
    resolved = load_uncertainty(path)
    assert resolved.names == ("lame_lambda", "lame_mu", "thickness")
    np.testing.assert_allclose(resolved.std, [0.0129, 0.002, 0.5])  # lame_mu: the file's own
    assert resolved.sources == {"lame_lambda": "calibration", "lame_mu": "file", "thickness": "file"}
    np.testing.assert_allclose(resolved.correlation, [[1, -0.9903, 0], [-0.9903, 1, 0], [0, 0, 1]])
    assert resolved.as_record()["correlation"] == [{"between": ["lame_lambda", "lame_mu"], "value": -0.9903,
                                                    "source": "calibration"}]
    # an explicit correlation replaces the calibration's, and the record says so
    again = write(tmp_path, {"samples": 8, "from_calibration": "fitted.yaml",
                             "correlation": [{"between": ["lame_mu", "lame_lambda"], "value": -0.5}]}, "v.yaml")
    assert load_uncertainty(again).correlation[0, 1] == -0.5
    assert load_uncertainty(again).as_record()["correlation"] == [
        {"between": ["lame_lambda", "lame_mu"], "value": -0.5, "source": "file"}]


BAD_FILES = [
    ({"samples": 1}, "u.yaml: samples: got 1, expected an integer between 3 and 10000"),
    # accepted before, while the robust plan it asked for could only ever be the nominal one
    ({"samples": 2}, ("u.yaml: samples: got 2, expected an integer between 3 and 10000 (training runs, and as many "
                      "held out; the robust plan's test of the mean exit shift needs at least 3)")),
    ({"parameters": {"thicknes": {"std": 1.0}}}, "unknown key 'thicknes'"),
    ({"parameters": {"thickness": {"std": 0.0}}}, "parameters.thickness.std: got 0.0, expected a positive number"),
    ({"correlation": [{"between": ["lame_mu", "thickness"], "value": 1.0}]},
     "correlation[0].value: got 1.0, expected a number between -1 and 1"),
    ({"correlation": [{"between": ["lame_mu", "lame_mu"], "value": 0.5}]},
     "correlation[0].between: got ['lame_mu', 'lame_mu'], expected two different parameter names"),
    ({"correlation": [{"between": ["lame_mu", "friction"], "value": 0.5}]},
     "correlation[0].between: got ['lame_mu', 'friction'], expected parameters with a std (friction has none"),
    ({"parameters": {"lame_mu": {"std": 0.01}, "thickness": {"std": 1.0}, "cutting_force": {"std": 0.1}},
      "correlation": [{"between": ["lame_mu", "thickness"], "value": 0.9},
                      {"between": ["thickness", "cutting_force"], "value": 0.9},
                      {"between": ["lame_mu", "cutting_force"], "value": -0.9}]},
     "expected a positive definite correlation matrix"),
    ({"parameters": {"friction": {"std": 0.01}}},
     "parameters.friction: got {std: 0.01}, expected a parameter the scenario has"),
    # another distribution: one line, not a missing std and an unknown key each (three lines)
    ({"parameters": {"lame_mu": {"low": 0.2, "high": 0.1}}},
     "parameters.lame_mu: got {'low': 0.2, 'high': 0.1}, expected {std: s}: a normal distribution around the "
     "scenario's value with standard deviation s (the parameter's units), truncated to positive values; no other "
     "distribution is sampled"),
    ({"parameters": {"thickness": {"mean": 10.0, "sigma": 0.5}}}, "parameters.thickness: got {'mean': 10.0, "),
    ({"parameters": {"thickness": {"sd": 0.5}}},  # a misspelt std keeps its line
     "parameters.thickness: unknown key 'sd', expected one of: std (did you mean 'std'? parameters.thickness.std "
     "is missing)"),
    ({"parameters": {"friction": None, "thickness": {"std": 1.0}}},  # `friction:` left blank
     "parameters.friction: got null, expected a mapping {std: ...} giving the parameter's standard deviation"),
    # `from_calibration:` left blank: it ran without the calibration's moduli, saying nothing
    ({"from_calibration": None}, ("u.yaml: from_calibration: got null, expected a `stitchplan calibrate material` "
                                  "output file (fitted.yaml), relative to this file (or remove the key)")),
    ({"parameters": None, "from_calibration": "fitted_displacement_only.yaml"},
     "u.yaml: parameters: got null, expected a mapping of parameters to {std: ...} (or remove the key)"),
    ({"from_calibration": "missing.yaml"}, "from_calibration: "),
    ({"from_calibration": "."}, ": cannot be read (Is a directory), expected a `stitchplan calibrate material` output"),
    ({"from_calibration": "fitted_displacement_only.yaml"},
     "fit.standard_uncertainty: got {'lame_lambda': null, 'lame_mu': null}, expected positive standard "
     "uncertainties of lame_lambda and lame_mu (MPa); the calibration did not identify the moduli"),
]


@pytest.mark.parametrize("changes, fragment", BAD_FILES)
def test_bad_uncertainty_files_are_one_line_exit_2_and_no_output(tmp_path, changes, fragment):
    shutil.copy(CALIBRATION / "fitted_displacement_only.yaml", tmp_path)
    raw = {**small_uncertainty(), "correlation": [], **changes}
    scenario = write(tmp_path, _frictionless())
    path = write(tmp_path, raw, "u.yaml")
    out = tmp_path / "out"
    result = invoke("plan", scenario, "--uncertainty", path, "--export", out / "t.csv", "--summary",
                    out / "s.json", "--workers", "0")
    line = one_error_line(result)
    assert fragment in line and str(path) in line, line
    assert not out.exists()


def _frictionless() -> dict:
    raw = small_raw()
    raw["needle"]["friction"] = 0.0  # the scenario has no friction to be uncertain about
    return raw


def test_options_of_uncertainty_without_it_and_bad_pairs_are_refused(tmp_path):
    scenario = write(tmp_path, small_raw())
    line = one_error_line(invoke("plan", scenario, "--export", tmp_path / "t.csv", "--workers", "2"))
    assert line == "error: --workers: got 2, expected it only with --uncertainty FILE"
    path = write(tmp_path, small_uncertainty(), "u.yaml")
    line = one_error_line(invoke("plan", scenario, "--export", tmp_path / "t.csv", "--uncertainty", path,
                                 "--scheduler", "localhost"))
    assert "--scheduler: got 'localhost', expected a Dask scheduler address" in line
    line = one_error_line(invoke("plan", scenario, "--export", tmp_path / "t.csv", "--uncertainty", path,
                                 "--scheduler", "tcp://127.0.0.1:8786", "--workers", "2"))
    assert "--workers: got 2 with --scheduler tcp://127.0.0.1:8786, expected one of the two" in line
    line = one_error_line(invoke("plan", scenario, "--export", path, "--uncertainty", path, "--workers", "0"))
    assert "expected a file other than the input --uncertainty" in line
    shutil.copy(CALIBRATION / "fitted.yaml", tmp_path / "fitted.yaml")
    calibrated = write(tmp_path, {"samples": 3, "from_calibration": "fitted.yaml"}, "c.yaml")
    before = (tmp_path / "fitted.yaml").read_bytes()
    line = one_error_line(invoke("plan", scenario, "--export", tmp_path / "t.csv", "--summary", tmp_path / "fitted.yaml",
                                 "--uncertainty", calibrated, "--workers", "0"))
    assert "--summary" in line and "expected a file other than the input from_calibration" in line
    assert (tmp_path / "fitted.yaml").read_bytes() == before
    assert not (tmp_path / "t.csv").exists()
    line = one_error_line(invoke("plan", scenario, "--export", tmp_path / "t.csv", "--uncertainty", path,
                                 "--no-compare", "--workers", "0"))
    assert line.startswith("error: --no-compare: got it with --uncertainty FILE, whose report compares the "
                           "unplanned, nominal and robust exits"), line
    assert not (tmp_path / "t.csv").exists()


# --- the design ------------------------------------------------------------------------------


def test_the_design_is_reproducible_correlated_and_spread_as_asked():
    scenario = parse_scenario(small_raw())
    spec = uncertainty({"samples": 512, "seed": 11,
                        "parameters": {"lame_lambda": {"std": 0.01}, "lame_mu": {"std": 0.005},
                                       "thickness": {"std": 0.5}},
                        "correlation": [{"between": ["lame_lambda", "lame_mu"], "value": -0.9}]})
    design = draw(spec, scenario)
    again = draw(spec, scenario)
    np.testing.assert_array_equal(design.train, again.train)  # the seed fixes every point
    np.testing.assert_array_equal(design.held_out, again.held_out)
    other = draw(uncertainty({**small_uncertainty(512, seed=12), "parameters": {
        "lame_lambda": {"std": 0.01}, "lame_mu": {"std": 0.005}, "thickness": {"std": 0.5}},
        "correlation": [{"between": ["lame_lambda", "lame_mu"], "value": -0.9}]}), scenario)
    assert not np.allclose(other.train, design.train)
    assert design.train.shape == design.held_out.shape == (512, 3)
    assert not np.isin(design.train, design.held_out).any()  # training and held-out points differ
    points = np.vstack([design.train, design.held_out])
    nominal = np.array([0.189151, 0.147688, 10.0])
    np.testing.assert_allclose(points.mean(axis=0), nominal, atol=0.02 * spec.std.max())
    np.testing.assert_allclose(points.std(axis=0, ddof=1), spec.std, rtol=0.03)
    correlation = np.corrcoef(points.T)
    assert correlation[0, 1] == pytest.approx(-0.9, abs=0.01)
    assert abs(correlation[0, 2]) < 0.05 and abs(correlation[1, 2]) < 0.05


def test_values_at_or_below_zero_are_rejected_and_the_stream_continues():
    scenario = parse_scenario(small_raw())  # cutting force 0.7 N
    design = draw(uncertainty({"samples": 64, "parameters": {"cutting_force": {"std": 0.7}}}), scenario)
    points = np.vstack([design.train, design.held_out])
    assert (points > 0).all() and len(points) == 128
    assert design.rejected > 10  # about 16 % of a normal lies one std below its mean
    assert points.mean() > 0.7  # truncation shifts the mean up


def test_a_point_with_any_value_at_or_below_zero_is_rejected():
    """With two parameters each often drawn below zero, a point is kept only where both are
    positive, and `rejected` counts, among the points drawn up to the last one kept, those
    with either at or below zero (by brute force over the same seeded points)."""
    from stitchplan.uncertainty.sampling import normal_points, scenario_values

    scenario = parse_scenario(small_raw())
    spec = uncertainty({"samples": 64, "seed": 3, "parameters": {"cutting_force": {"std": 0.7},
                                                                 "friction": {"std": scenario.needle.friction}}})
    design = draw(spec, scenario)
    points = np.vstack([design.train, design.held_out])
    assert (points > 0).all() and len(points) == 128
    drawn = normal_points(spec, scenario_values(scenario, spec.names), design.drawn)
    kept = np.flatnonzero((drawn > 0).all(axis=1))[:128]
    np.testing.assert_array_equal(points, drawn[kept])
    one_only = ((drawn[: kept[-1] + 1] <= 0).sum(axis=1) == 1).sum()
    assert one_only > 10  # points refused for one value alone: `any`, not `all`
    assert design.rejected == int((drawn[: kept[-1] + 1] <= 0).any(axis=1).sum())


def test_a_sample_is_the_scenario_with_its_values():
    scenario = parse_scenario(small_raw())
    sample = with_parameters(scenario, ("lame_lambda", "thickness", "friction"), np.array([0.2, 9.0, 0.05]))
    assert sample.tissue.material.lame_lambda == 0.2 and sample.tissue.thickness == 9.0
    assert sample.needle.friction == 0.05
    assert sample.tissue.material.lame_mu == scenario.tissue.material.lame_mu
    assert sample.needle.cutting_force == scenario.needle.cutting_force


def test_exit_statistics_of_known_distances():
    errors = np.column_stack([np.arange(1.0, 21.0), np.zeros(20)])  # distances 1 .. 20
    stats = exit_statistics(errors)
    assert stats == {"mean_mm": 10.5, "p50_mm": 10.5, "p95_mm": pytest.approx(19.05), "max_mm": 20.0}


def test_the_95_percent_ellipse_holds_95_percent_of_a_normal_sample():
    """uncertainty.png's ellipse: on a large correlated normal sample it holds 95 % of the
    points (the chi^2 quantile of two degrees of freedom), and its axes are the covariance's
    principal standard deviations times sqrt(chi^2_0.95)."""
    from scipy.stats import chi2

    from stitchplan.uncertainty.robust import ellipse_95

    rng = np.random.default_rng(11)
    covariance = np.array([[0.04, 0.03], [0.03, 0.09]])
    points = rng.multivariate_normal([0.1, -0.2], covariance, size=20000)
    center, axes = ellipse_95(points)
    inside = np.linalg.norm(np.linalg.solve(axes, (points - center).T), axis=0) <= 1.0
    assert inside.mean() == pytest.approx(0.95, abs=0.005)
    lengths = np.sort(np.linalg.norm(axes, axis=0))
    np.testing.assert_allclose(lengths, np.sqrt(np.linalg.eigvalsh(np.cov(points.T)) * chi2.ppf(0.95, 2)))


# --- runs: on a cluster as in-process, failures recorded -------------------------------------


@pytest.fixture(scope="module")
def cluster():
    """A running two-worker Dask cluster, reached through its address (--scheduler)."""
    from dask.distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                      silence_logs=50) as running:
        yield running.scheduler_address


def test_a_two_worker_cluster_gives_the_in_process_results(cluster):
    scenario = parse_scenario(small_raw())
    spec = uncertainty(small_uncertainty(samples=3))
    local = plan_under_uncertainty(scenario, spec, Executor(workers=0))
    with Executor(scheduler=cluster) as executor:
        remote = plan_under_uncertainty(scenario, spec, executor)
        assert len(executor.client.scheduler_info()["workers"]) == 2
    assert remote.where.startswith("Dask scheduler tcp://")
    for label in LABELS:
        np.testing.assert_array_equal(remote.errors(label, evaluated_only=False), local.errors(label, False))
    np.testing.assert_array_equal([s.exit_error for s in remote.sensitivities],
                                  [s.exit_error for s in local.sensitivities])
    assert remote.statistics == local.statistics and remote.exported == local.exported


def test_the_tasks_of_a_lost_worker_run_again(cluster, tmp_path):
    def dies_once(index: int, marker: str) -> int:  # pickled by value: the workers need no test module
        import os

        if index == 1 and not os.path.exists(marker):
            open(marker, "w").close()
            os._exit(1)  # the worker process dies with the task
        return index * index

    with Executor(scheduler=cluster) as executor:
        results = executor.map(dies_once, range(4), [str(tmp_path / "died")] * 4)
    assert (tmp_path / "died").exists() and results == [0, 1, 4, 9]


def test_the_study_sweep_on_a_cluster_gives_the_in_process_runs(cluster):
    from test_study import tiny_raw

    from stitchplan.study.sweep import run_study

    scenario = parse_scenario(tiny_raw())
    local = run_study(scenario, quick=True)
    seen = []
    with Executor(scheduler=cluster) as executor:
        remote = run_study(scenario, quick=True, executor=executor, on_run=lambda run: seen.append(run.label))
    assert sorted(seen) == sorted(run.label for run in local.runs)  # each reported once, as it completes
    assert [run.label for run in remote.runs] == [run.label for run in local.runs]  # submission order
    for a, b in zip(remote.runs, local.runs):
        assert a.ok and b.ok and a.particles == b.particles
        np.testing.assert_array_equal(a.result.achieved_exit_def, b.result.achieved_exit_def)
        assert a.deviations == b.deviations


def test_a_failing_sample_is_recorded_with_its_reason(tmp_path, monkeypatch):
    scenario_path = write(tmp_path, small_raw())
    path = write(tmp_path, small_uncertainty(), "u.yaml")
    design = draw(load_uncertainty(path), parse_scenario(small_raw()))
    doomed = design.held_out[1, design.names.index("thickness")]
    real = evaluation.run_insertion

    def failing(scenario, **options):
        if scenario.tissue.thickness == doomed:
            raise SolverDivergence("Newton diverged at needle step 3 (needle rotation 0.900 rad)")
        return real(scenario, **options)

    monkeypatch.setattr(evaluation, "run_insertion", failing)
    result = invoke("plan", scenario_path, "--uncertainty", path, "--export", tmp_path / "t.csv",
                    "--summary", tmp_path / "s.json", "--out", tmp_path / "run.h5", "--workers", "0")
    assert result.exit_code == 0, result.output
    block = json.loads((tmp_path / "s.json").read_text())["uncertainty"]
    assert block["failed_samples"] == 1 and block["evaluated_samples"] == 3
    failures = block["failures"]
    assert {f["path"] for f in failures} == set(LABELS) and {f["sample"] for f in failures} == {1}
    assert all(f["reason"].startswith("SolverDivergence: Newton diverged at needle step 3") for f in failures)
    with h5py.File(tmp_path / "run.h5") as log:
        for label in LABELS:
            group = log[f"uncertainty/held_out/{label}"]
            np.testing.assert_array_equal(group["failed"][()], [0, 1, 0, 0])
            assert "SolverDivergence" in group["reason"][()].decode().splitlines()[1]
            assert np.isnan(group["exit_error"][1]).all() and np.isfinite(group["exit_error"][0]).all()


def test_run_sample_records_a_replay_that_ends_before_the_exit():
    scenario = parse_scenario(small_raw())
    centers = np.repeat([[0.0, 18.0 - 8.88]], 3, axis=0)  # three rows: the tip has not left yet
    run = run_sample(scenario, centers)
    assert not run.ok and run.reason.startswith("InputError: centre path: rows: got 3, expected one per step until the tip exits")
    assert np.isnan(run.exit_error).all()


# --- the command -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def planned(tmp_path_factory):
    folder = tmp_path_factory.mktemp("uncertainty")
    shutil.copy(CALIBRATION / "fitted.yaml", folder / "fitted.yaml")
    # tight needle tolerances: the verification's replay (a second round's starts from the first's)
    # is compared with a cold `simulate --center-path` replay
    scenario = write(folder, {**small_raw(), "solver": TIGHT_NEEDLE_NEWTON})
    path = write(folder, {"samples": 4, "seed": 7, "from_calibration": "fitted.yaml",
                          "parameters": {"thickness": {"std": 1.0}, "cutting_force": {"std": 0.1}}}, "u.yaml")
    result = invoke("plan", scenario, "--uncertainty", path, "--export", folder / "t.csv", "--summary",
                    folder / "s.json", "--out", folder / "run.h5", "--uncertainty-plot", folder / "u.png",
                    "--workers", "0")
    return folder, result


def test_the_summary_has_the_uncertainty_block_of_the_format(planned):
    folder, result = planned
    assert result.exit_code == 0, result.output
    summary = json.loads((folder / "s.json").read_text())
    block = summary["uncertainty"]
    assert block["samples"] == 4 and block["failed_samples"] == 0
    for label in LABELS:
        assert set(block[label]) >= STATISTICS and all(block[label][k] >= 0 for k in STATISTICS)
        assert block[label]["p50_mm"] <= block[label]["p95_mm"] <= block[label]["max_mm"]
    assert set(block["sensitivity"]) == {"lame_lambda", "lame_mu", "cutting_force", "thickness"}
    assert all(len(value) == 2 for value in block["sensitivity"].values())
    assert summary["sensitivity"] == block["sensitivity"]  # the format read either way
    # the plans land far closer than the fixed centre on every held-out sample
    assert block["nominal"]["max_mm"] < 0.5 * block["unplanned"]["mean_mm"]
    # the exported plan is never worse than the nominal one on the held-out samples
    assert block["robust"]["mean_mm"] <= block["nominal"]["mean_mm"]
    assert block["robust"]["p95_mm"] <= block["nominal"]["p95_mm"]
    assert block["exported"] in ("robust", "nominal")
    # verified (the default): the plans aim for the refined model, by its offset of the nominal path
    offset = np.asarray(block["refined_offset_mm"])
    if block["mean_shift_t2"] >= block["mean_shift_t2_threshold"]:  # a shift beyond noise: aimed at its opposite
        np.testing.assert_allclose(block["robust_aim_mm"], -np.asarray(block["mean_shift_mm"]) - offset)
    else:  # noise: the robust plan is the nominal one, its aim where it exits on the planning model
        own = np.subtract(summary["achieved_exit_def"], summary["desired_exit_def"])
        np.testing.assert_allclose(block["robust_aim_mm"], own, atol=2e-12)  # the summary's points to 1e-12 mm
        assert block["robust"] == block["nominal"]
        assert block["training_prediction"]["robust"] == block["training_prediction"]["nominal"]
    assert block["distributions"]["parameters"]["lame_lambda"] == {"std": 0.0129, "units": "MPa",
                                                                    "source": "calibration"}
    # the files the distributions came from, recorded as the scenario is (path and sha256)
    digest = {name: hashlib.sha256((folder / name).read_bytes()).hexdigest() for name in ("u.yaml", "fitted.yaml")}
    assert summary["uncertainty_file"] == str(folder / "u.yaml")
    assert summary["uncertainty_file_sha256"] == digest["u.yaml"]
    assert summary["calibration_file"] == str(folder / "fitted.yaml")
    assert summary["calibration_file_sha256"] == digest["fitted.yaml"]
    with h5py.File(folder / "run.h5") as log:
        assert log.attrs["uncertainty_file_sha256"] == digest["u.yaml"]
    # more thickness, less force per unit of it: the sensitivity has the sign of the forces' opposite
    assert np.dot(block["sensitivity"]["thickness"], block["sensitivity"]["cutting_force"]) < 0
    assert "exit spread dominated by" in result.stdout
    assert f"exit spread dominated by {block['dominant_parameter']}" in result.stdout



def test_an_uncertainty_file_from_a_pipe_records_the_checksum_of_what_was_parsed(tmp_path):
    """`--uncertainty <(cat u.yaml)`: the pipe gives its bytes once, so uncertainty_file_sha256
    is theirs, not that of a second, empty read (a named pipe's second open waited for ever)."""
    import os

    scenario = write(tmp_path, small_raw())
    content = yaml.safe_dump(small_uncertainty(samples=3)).encode()
    read_end, write_end = os.pipe()
    os.write(write_end, content)  # a few lines: within the pipe's buffer
    os.close(write_end)
    try:
        result = invoke("plan", scenario, "--uncertainty", f"/dev/fd/{read_end}", "--export", tmp_path / "t.csv",
                        "--summary", tmp_path / "s.json", "--no-verify", "--workers", "0")
    finally:
        os.close(read_end)
    assert result.exit_code == 0, result.output
    summary = json.loads((tmp_path / "s.json").read_text())
    assert summary["uncertainty_file_sha256"] == hashlib.sha256(content).hexdigest()

def test_the_exported_plan_under_uncertainty_is_verified_by_default(planned):
    """As any plan: the exported trajectory replayed on the refined model (at the scenario's
    values), which `simulate --center-path ... --spacing` reproduces, and an estimate from it."""
    folder, result = planned
    assert result.exit_code == 0, result.output
    summary = json.loads((folder / "s.json").read_text())
    assert summary["verification"]["rounds"][0]["aimed_by"] in ("none", "predicted offset")
    assert summary["exit_error_estimate"]["basis"] == "refined"
    replay = invoke("simulate", folder / "scene.yaml", "--center-path", folder / "t.csv", "--spacing",
                    str(summary["verification_spacing_mm"]), "--summary", folder / "replay.json")
    assert replay.exit_code == 0, replay.output
    replayed = json.loads((folder / "replay.json").read_text())
    assert replayed["exit_error_mm"] == pytest.approx(summary["verified_exit_error_mm"], abs=1e-6)
    assert summary["exit_error_estimate_mm"] > 0.0
    assert "verified" in result.stdout


def test_the_plans_statistics_are_on_the_refined_model_by_its_offset_of_the_nominal_path(planned):
    """The sampled runs replay on the planning model (the run log keeps their exit errors as
    they are); the summary's nominal and robust statistics add the refined model's offset of
    the nominal path, measured by its verification replay, and the unplanned path's do not."""
    folder, result = planned
    assert result.exit_code == 0, result.output
    summary = json.loads((folder / "s.json").read_text())
    block = summary["uncertainty"]
    offset = np.asarray(block["refined_offset_mm"])
    if block["exported"] == "robust" and block["mean_shift_t2"] < block["mean_shift_t2_threshold"]:
        verification = summary["verification"]  # the nominal plan's own replay
        refined = np.subtract(verification["achieved_exit_def"], verification["desired_exit_def"])
        planned_error = np.subtract(summary["achieved_exit_def"], summary["desired_exit_def"])
        np.testing.assert_allclose(offset, refined - planned_error, atol=1e-12)
    assert "refined_offset_mm" in block["statistics_model"]
    with h5py.File(folder / "run.h5") as log:
        group = log["uncertainty"]
        np.testing.assert_array_equal(group["refined_offset"][()], offset)
        on_planning = {label: group[f"held_out/{label}/exit_error"][()] for label in LABELS}
    assert block["unplanned"] == pytest.approx(exit_statistics(on_planning["unplanned"]), rel=1e-12)
    assert block["nominal"] == pytest.approx(exit_statistics(on_planning["nominal"] + offset), rel=1e-12)
    assert block["nominal"] != pytest.approx(exit_statistics(on_planning["nominal"]), rel=1e-6)
    assert "on the refined model" in result.stdout


def plan_re_aimed(folder):
    """`plan --uncertainty` on the small scene (4 samples of thickness and cutting force, in
    this process), with every mean shift taken as significant by the caller: (scenario file,
    uncertainty file, the command's result), its outputs t.csv, s.json and run.h5 in `folder`."""
    scenario_path = write(folder, {**small_raw(), "solver": TIGHT_NEEDLE_NEWTON})
    path = write(folder, {"samples": 4, "seed": 7, "parameters": {"thickness": {"std": 1.0},
                                                                  "cutting_force": {"std": 0.1}}}, "u.yaml")
    result = invoke("plan", scenario_path, "--uncertainty", path, "--export", folder / "t.csv", "--summary",
                    folder / "s.json", "--out", folder / "run.h5", "--workers", "0")
    assert result.exit_code == 0, result.output
    return scenario_path, path, result


def test_a_re_aimed_robust_plan_aims_by_the_shift_and_the_refined_offset_and_is_verified(tmp_path, monkeypatch):
    """Every shift taken as significant (a zero threshold): the robust plan is planned again,
    aimed at -s - delta on the planning model, and replayed on the refined model itself; its
    statistics there are its held-out exits + delta, as the nominal plan's are."""
    from stitchplan.uncertainty import robust

    monkeypatch.setattr(robust, "shift_threshold", lambda n: 0.0)
    scenario_path, path, result = plan_re_aimed(tmp_path)
    summary = json.loads((tmp_path / "s.json").read_text())
    block = summary["uncertainty"]
    offset = np.asarray(block["refined_offset_mm"])
    assert np.linalg.norm(offset) > 0.0
    np.testing.assert_allclose(block["robust_aim_mm"], -np.asarray(block["mean_shift_mm"]) - offset)
    with h5py.File(tmp_path / "run.h5") as log:
        robust_exits = log["uncertainty/held_out/robust/exit_error"][()]
    candidate = block["robust"] if block["exported"] == "robust" else block["robust_candidate"]
    assert candidate == pytest.approx(exit_statistics(robust_exits + offset), rel=1e-12)
    # the exported plan's own replay on the refined model, as `simulate --center-path --spacing` gives it
    replay = invoke("simulate", scenario_path, "--center-path", tmp_path / "t.csv", "--spacing",
                    str(summary["verification_spacing_mm"]), "--summary", tmp_path / "replay.json")
    assert replay.exit_code == 0, replay.output
    replayed = json.loads((tmp_path / "replay.json").read_text())
    assert replayed["exit_error_mm"] == pytest.approx(summary["verified_exit_error_mm"], abs=1e-6)


def test_where_the_nominal_plan_is_exported_robust_names_it_everywhere(tmp_path, monkeypatch):
    """A re-aimed robust plan judged worse than the nominal one: the summary's `robust`
    statistics and held-out mean are the exported (nominal) plan's, the candidate's stand
    beside them as `robust_candidate`, the printed lines say which is which, and the run log
    says which plan trajectory.csv holds and how the samples were drawn."""
    from stitchplan.uncertainty import robust

    monkeypatch.setattr(robust, "shift_threshold", lambda n: 0.0)  # a robust plan of its own

    def prefer_nominal(result) -> None:
        result.exported = "nominal"
        result.notes.append("the nominal plan is exported")

    monkeypatch.setattr(robust, "_choose", prefer_nominal)
    scenario_path, path, result = plan_re_aimed(tmp_path)
    block = json.loads((tmp_path / "s.json").read_text())["uncertainty"]
    assert block["exported"] == "nominal"
    assert block["robust"] == block["nominal"] and block["robust_candidate"] != block["nominal"]
    means = block["held_out_mean_exit_error_mm"]
    assert means["robust"] == means["nominal"] and means["robust_candidate"] != means["nominal"]
    lines = {line.split()[0]: line for line in result.stdout.splitlines() if line.startswith("  ")}
    assert lines["nominal"].endswith("(exported)")
    assert lines["robust"].endswith("(the robust candidate, not exported)")
    assert f"{block['robust_candidate']['p95_mm']:.4f} mm" in lines["robust"]
    with h5py.File(tmp_path / "run.h5") as log:
        group = log["uncertainty"]
        assert group["exported"][()].decode() == "nominal" and group["exported"].attrs["units"] == "text"
        assert group["seed"][()] == 7 and group["samples"][()] == 4
        assert group["uncertainty_file"][()].decode() == str(path)
        distributions = json.loads(group["distributions"][()].decode())
        assert distributions["seed"] == 7 and set(distributions["parameters"]) == {"cutting_force", "thickness"}
        assert group["mean_shift_t2_threshold"][()] == 0.0


def test_the_run_log_and_the_png(planned):
    folder, result = planned
    assert result.exit_code == 0, result.output
    with h5py.File(folder / "run.h5") as log:
        group = log["uncertainty"]
        assert group["parameter_names"][()].decode().split() == ["lame_lambda", "lame_mu", "cutting_force",
                                                                 "thickness"]
        assert group["held_out_parameters"].shape == (4, 4) and group["training_parameters"].shape == (4, 4)
        assert group["held_out_parameters"].attrs["units"] == "MPa,MPa,N,mm"
        assert group["held_out/robust/exit_error"].attrs["units"] == "mm"
        assert (group["held_out/unplanned/failed"][()] == 0).all()
    image = plt_image(folder / "u.png")
    assert image.shape[1] > 1200 and image.std() > 0.05  # a drawn figure, not a blank one


def test_the_plot_draws_a_robust_plan_that_is_the_nominal_one_once():
    """Where the robust plan is the nominal one (none made, or the same object), uncertainty.png
    draws its held-out exits once, named for both, instead of a cloud hidden under another."""
    from types import SimpleNamespace

    from stitchplan.io.uncertainty_reports import plotted_paths
    from stitchplan.uncertainty.robust import UncertaintyResult

    nominal = object()
    same = UncertaintyResult.robust_is_nominal.fget
    assert same(SimpleNamespace(robust=None, nominal=nominal))
    assert same(SimpleNamespace(robust=nominal, nominal=nominal))
    assert not same(SimpleNamespace(robust=object(), nominal=nominal))
    for exported in ("robust", "nominal"):
        paths = plotted_paths(SimpleNamespace(robust_is_nominal=True, exported=exported))
        assert paths == [("unplanned", "unplanned"), (exported, "robust = nominal plan (exported)")]
    paths = plotted_paths(SimpleNamespace(robust_is_nominal=False, exported="robust"))
    assert paths == [("unplanned", "unplanned"), ("nominal", "nominal"), ("robust", "robust (exported)")]


def plt_image(path: Path) -> np.ndarray:
    import matplotlib.image

    return matplotlib.image.imread(path)


def test_the_executor_and_the_uncertainty_layer_import_nothing_above_them():
    """stitchplan.parallel stands on errors alone; stitchplan.uncertainty on the layers up to
    planning (no study, io or cli), and neither imports dask before an executor starts."""
    import subprocess
    import sys

    executor_modules = ", ".join(f"stitchplan.parallel.{name}"
                                 for name in ("executor", "dask_logs", "signals", "scheduler", "workers", "failures"))
    for module, allowed in ((executor_modules, ("stitchplan.errors", "stitchplan.parallel")),
                            ("stitchplan.uncertainty.robust", ("stitchplan.errors", "stitchplan.geometry",
                                                               "stitchplan.config", "stitchplan.tissue",
                                                               "stitchplan.needle", "stitchplan.resources",
                                                               "stitchplan.parallel", "stitchplan.planning",
                                                               "stitchplan.uncertainty", "stitchplan.events",
                                                               "stitchplan.early_helper"))):
        code = (f"import sys, {module}\n"
                "print(sorted(m for m in sys.modules if m.startswith(('stitchplan', 'dask', 'distributed'))))")
        loaded = eval(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                     check=True).stdout)
        outside = [m for m in loaded if m != "stitchplan" and not m.startswith(allowed)]
        assert outside == [], (module, outside)


def test_the_shipped_uncertainty_file_reads_the_sample_calibration():
    root = Path(__file__).resolve().parents[1]
    resolved = load_uncertainty(root / "configs" / "uncertainty" / "uncertainty_sample.yaml")
    assert resolved.names == ("lame_lambda", "lame_mu", "friction", "cutting_force", "thickness")
    assert resolved.sources["lame_lambda"] == resolved.sources["lame_mu"] == "calibration"
    assert resolved.correlation[0, 1] == pytest.approx(-0.9903)
    scenario = parse_scenario(yaml.safe_load((root / "configs" / "sh12_100x100.yaml").read_text()))
    design = draw(resolved, scenario)
    assert design.train.shape == (16, 5) and design.rejected == 0


def test_mean_shift_significance_is_hotellings_t2():
    """T^2 = n s^T W^-1 s: a shift of one standard error per axis on 16 samples gives about
    n (1/4)^2 x 2 = 2 (noise, below 5.99); a shift of two standard deviations is significant."""
    from stitchplan.uncertainty.robust import CHI2_95_2D, shift_significance

    rng = np.random.default_rng(5)
    noise = rng.standard_normal((16, 2))
    noise = (noise - noise.mean(axis=0)) / noise.std(axis=0, ddof=1)  # mean 0, unit sample spread
    assert shift_significance(noise) == pytest.approx(0.0, abs=1e-12)
    assert shift_significance(noise + 0.25) < CHI2_95_2D
    assert shift_significance(noise + 2.0) > CHI2_95_2D
    expected = 16 * np.array([2.0, 2.0]) @ np.linalg.inv(np.cov((noise + 2.0).T)) @ np.array([2.0, 2.0])
    assert shift_significance(noise + 2.0) == pytest.approx(expected)


# --- failed runs, small samples, absurd stds, material regions ----------------------------------


def _failing_on(monkeypatch, thicknesses) -> None:
    """run_insertion raising SolverDivergence on the scenarios whose thickness is one of
    `thicknesses` (the sampled parameter sets: the nominal plan and the probes stay)."""
    real = evaluation.run_insertion
    doomed = {float(t) for t in np.ravel(thicknesses)}

    def failing(scenario, **options):
        if scenario.tissue.thickness in doomed:
            raise SolverDivergence("Newton diverged at needle step 2 (needle rotation 0.600 rad)")
        return real(scenario, **options)

    monkeypatch.setattr(evaluation, "run_insertion", failing)


def _thickness_only(samples: int = 3) -> dict:
    return {"samples": samples, "seed": 3, "parameters": {"thickness": {"std": 1.0}}}


def _strict_json(path: Path) -> dict:
    """The file as JSON that has no Infinity or NaN (json.loads accepts them by default)."""
    def refuse(constant):
        raise AssertionError(f"{path} holds {constant}: not JSON")

    return json.loads(path.read_text(), parse_constant=refuse)


def test_the_uncertainty_plot_without_an_evaluated_held_out_sample(tmp_path, monkeypatch):
    """Every held-out run fails, the training runs succeed: the command ends normally, the
    held-out statistics are null, and uncertainty.png says that no held-out sample ran."""
    from stitchplan.io.uncertainty_reports import plot_title

    scenario_path = write(tmp_path, small_raw())
    path = write(tmp_path, _thickness_only(), "u.yaml")
    design = draw(load_uncertainty(path), parse_scenario(small_raw()))
    _failing_on(monkeypatch, design.held_out)
    result = invoke("plan", scenario_path, "--uncertainty", path, "--export", tmp_path / "t.csv", "--summary",
                    tmp_path / "s.json", "--uncertainty-plot", tmp_path / "u.png", "--workers", "0")
    assert result.exit_code == 0, result.output
    assert "Traceback" not in result.output
    block = _strict_json(tmp_path / "s.json")["uncertainty"]
    assert block["evaluated_samples"] == 0 and block["failed_samples"] == 3
    assert block["training"]["failed"] == 0
    assert all(block[label]["p95_mm"] is None for label in LABELS)
    assert plt_image(tmp_path / "u.png").std() > 0.05
    local = plan_under_uncertainty(parse_scenario(small_raw()), load_uncertainty(path), Executor(workers=0))
    assert "no held-out sample ran every path (3 samples with a failed run)" in plot_title(local, "s")


def test_every_planned_task_is_reported_where_the_robust_plan_is_the_nominal_one():
    """The progress bar counts planned_tasks + 2 runs; where the robust plan is the nominal
    one (the mean shift within the noise) its plan and held-out runs are not run, and are
    reported as done, so the bar ends full (before, it stopped at 4 of 6 samples' worth)."""
    from stitchplan.uncertainty.robust import planned_tasks

    spec = uncertainty(_thickness_only())
    seen = []
    result = plan_under_uncertainty(parse_scenario(small_raw()), spec, Executor(workers=0), on_run=seen.append)
    assert result.robust is result.nominal or result.robust is None  # the case at hand
    assert len(seen) == planned_tasks(spec) + 2


def test_every_sampled_run_failing_is_a_numerical_failure_and_writes_nothing(tmp_path, monkeypatch):
    scenario_path = write(tmp_path, small_raw())
    path = write(tmp_path, _thickness_only(), "u.yaml")
    design = draw(load_uncertainty(path), parse_scenario(small_raw()))
    _failing_on(monkeypatch, np.vstack([design.train, design.held_out]))
    out = tmp_path / "out"
    result = invoke("plan", scenario_path, "--uncertainty", path, "--export", out / "t.csv", "--summary",
                    out / "s.json", "--uncertainty-plot", out / "u.png", "--workers", "0")
    line = one_error_line(result, code=1)
    assert "all 9 sampled runs failed (3 training, 6 held-out)" in line, line
    assert "training sample 0 (nominal path): SolverDivergence: Newton diverged at needle step 2" in line, line
    assert not out.exists() or not any(out.iterdir())


def test_a_std_above_the_scenarios_value_is_refused_up_front(tmp_path):
    """std 1e300 on a 0.7 N cutting force: most of the normal lies below 0 and the rest
    overflows the model; refused before any run, naming the file, the field and the bound."""
    scenario_path = write(tmp_path, small_raw())  # cutting force 0.7 N
    path = write(tmp_path, {"samples": 3, "parameters": {"cutting_force": {"std": 1e300}}}, "u.yaml")
    out = tmp_path / "out"
    line = one_error_line(invoke("plan", scenario_path, "--uncertainty", path, "--export", out / "t.csv",
                                 "--workers", "0"))
    assert line.startswith(f"error: --uncertainty: {path}: parameters.cutting_force.std: got 1e+300, expected at "
                           f"most the scenario's value 0.7 N ({scenario_path}: needle.cutting_force)"), line
    assert not out.exists()


def test_a_std_too_small_to_move_the_value_is_refused_up_front(tmp_path):
    """std 1e-300 on a 10 mm thickness: every sample and the sensitivity's step are 10 mm in
    double precision, and the sensitivity read 0; refused before any run, with the bound."""
    scenario_path = write(tmp_path, small_raw())  # thickness 10 mm
    path = write(tmp_path, {"samples": 3, "parameters": {"thickness": {"std": 1e-300}}}, "u.yaml")
    out = tmp_path / "out"
    line = one_error_line(invoke("plan", scenario_path, "--uncertainty", path, "--export", out / "t.csv",
                                 "--workers", "0"))
    assert line.startswith(f"error: --uncertainty: {path}: parameters.thickness.std: got 1e-300, expected at "
                           f"least {2 * np.spacing(10.0):.3g} mm"), line
    assert not out.exists()


def test_an_unverified_plan_under_uncertainty_estimates_its_error_as_plan_does(tmp_path):
    """--no-verify skips the refined replays, not the estimate: the exported plan's
    exit_error_estimate_mm comes from its path replayed at twice the spacing, as `plan
    --no-verify` gives it (the nominal plan's, the same path here)."""
    scenario_path = write(tmp_path, small_raw())
    path = write(tmp_path, _thickness_only(), "u.yaml")
    result = invoke("plan", scenario_path, "--uncertainty", path, "--export", tmp_path / "t.csv", "--summary",
                    tmp_path / "s.json", "--no-verify", "--workers", "0")
    assert result.exit_code == 0, result.output
    summary = _strict_json(tmp_path / "s.json")
    assert summary["verified_exit_error_mm"] is None
    plain = invoke("plan", scenario_path, "--export", tmp_path / "p.csv", "--summary", tmp_path / "p.json",
                   "--no-verify")
    assert plain.exit_code == 0, plain.output
    expected = _strict_json(tmp_path / "p.json")["exit_error_estimate_mm"]
    assert expected is not None and expected > 0.0
    assert summary["exit_error_estimate_mm"] == pytest.approx(expected, rel=1e-9)
    assert "discretization error estimate" in result.output


def test_a_plan_under_uncertainty_chosen_for_an_accuracy_says_when_its_estimate_is_above_it(tmp_path, monkeypatch):
    """With discretization.accuracy, plan --uncertainty puts the auto discretization's note
    first and, where the exported plan's own estimate comes out above the accuracy asked, the
    accuracy check after it, as plan does (cli/runs.py put_accuracy_notes_first). The choice
    itself is stood in for by the 5 mm scene (its search is study/auto.py's, tested there)."""
    from stitchplan.config.scenario import parse_scenario
    from stitchplan.events import Event, EventKind

    chosen = parse_scenario(small_raw())

    def choose(scenario, tip_tracking=None, linear_solver=None, max_particles=None):
        return chosen, Event(EventKind.AUTO_DISCRETIZATION, "auto discretization: the 5 mm scene")

    monkeypatch.setattr("stitchplan.study.auto.resolve_accuracy", choose)
    scenario_path = write(tmp_path, {**small_raw(), "discretization": {"accuracy": 0.001}})
    path = write(tmp_path, _thickness_only(), "u.yaml")
    result = invoke("plan", scenario_path, "--uncertainty", path, "--export", tmp_path / "t.csv", "--summary",
                    tmp_path / "s.json", "--no-verify", "--workers", "0")
    assert result.exit_code == 0, result.output
    summary = _strict_json(tmp_path / "s.json")
    assert summary["exit_error_estimate_mm"] > 0.001
    kinds = [(event["kind"], event["message"]) for event in summary["events"]]
    assert kinds[0] == ("auto-discretization", "auto discretization: the 5 mm scene")
    assert kinds[1][0] == "accuracy-check" and kinds[1][1].startswith("accuracy: the run's own exit error estimate")


def test_two_successful_training_runs_do_not_test_the_mean_shift(tmp_path, monkeypatch):
    """With 2 training runs that succeed (of the 3 a file asks for at least) the deviations'
    covariance is singular: T^2 is not defined, the summary says null (valid JSON, no
    Infinity) with a note, and the nominal plan is not re-aimed."""
    scenario_path = write(tmp_path, small_raw())
    path = write(tmp_path, {**_thickness_only(), "parameters": {"thickness": {"std": 1.0},
                                                                "cutting_force": {"std": 0.1}}}, "u.yaml")
    design = draw(load_uncertainty(path), parse_scenario(small_raw()))
    _failing_on(monkeypatch, design.train[:1, list(design.names).index("thickness")])
    result = invoke("plan", scenario_path, "--uncertainty", path, "--export", tmp_path / "t.csv", "--summary",
                    tmp_path / "s.json", "--workers", "0")
    assert result.exit_code == 0, result.output
    block = _strict_json(tmp_path / "s.json")["uncertainty"]
    assert block["mean_shift_t2"] is None and block["mean_shift_t2_threshold"] is None
    # not re-aimed by a mean shift: the nominal plan, aimed where it exits on the planning model
    summary = _strict_json(tmp_path / "s.json")
    own = np.subtract(summary["achieved_exit_def"], summary["desired_exit_def"])
    np.testing.assert_allclose(block["robust_aim_mm"], own, atol=1e-12)
    assert block["robust"] == block["nominal"]
    assert any("Hotelling's T^2 needs at least 3" in note for note in block["notes"])
    # its notes go to stderr with the plan's, and -q leaves them out
    assert "note: the mean exit shift" in result.stderr and "Hotelling's T^2 needs at least 3" in result.stderr
    assert "note:" not in result.stdout
    quiet = invoke("plan", scenario_path, "--uncertainty", path, "--export", tmp_path / "q.csv", "--workers", "0",
                   "-q")
    assert quiet.exit_code == 0, quiet.output
    assert "note:" not in quiet.output


def test_the_mean_shift_test_uses_the_small_sample_quantile_and_refuses_a_singular_covariance():
    """The 95 % quantile of T^2 for n samples is 2 (n-1)/(n-2) F(2, n-2): 798 for 3 (the chi^2
    value 5.99 made noise significant at a few samples), tending to 5.99; a covariance
    without spread in a direction has no T^2."""
    from scipy.stats import chi2

    from stitchplan.uncertainty.robust import shift_significance, shift_threshold

    assert shift_threshold(2) is None and shift_threshold(3) == pytest.approx(798.0)
    assert shift_threshold(4) == pytest.approx(57.0) and shift_threshold(16) == pytest.approx(8.0119, abs=1e-4)
    assert shift_threshold(10_000) == pytest.approx(chi2.ppf(0.95, 2), rel=1e-3)
    # the quantile holds: about 5 % of normal samples of 4 exceed it
    rng = np.random.default_rng(1)
    t2 = np.array([shift_significance(rng.standard_normal((4, 2))) for _ in range(2000)])
    assert np.mean(t2 > shift_threshold(4)) == pytest.approx(0.05, abs=0.015)
    assert np.mean(t2 > chi2.ppf(0.95, 2)) == pytest.approx(1 / 3, abs=0.04)  # chi^2: 1 in 3 noise draws a "shift"
    assert shift_significance(np.array([[1.0, 0.0], [2.0, 0.0]])) is None  # 2 samples
    collinear = np.column_stack([np.arange(1.0, 6.0), 2.0 * np.arange(1.0, 6.0)])
    assert shift_significance(collinear) is None  # no spread across the line
    assert shift_significance(np.zeros((5, 2))) == 0.0


def test_no_non_finite_number_reaches_the_summary_block():
    from stitchplan.io.uncertainty_reports import finite_only

    block = finite_only({"a": np.float64(np.inf), "b": [1.0, float("nan")], "c": {"d": 2}, "notes": []})
    assert block["a"] is None and block["b"] == [1.0, None] and block["c"] == {"d": 2}
    assert block["notes"] == ["not finite, written as null: a (inf), b[1] (nan)"]
    json.dumps(block, allow_nan=False)


def _with_region() -> dict:
    raw = small_raw()
    material = raw["tissue"]["material"]
    raw["tissue"]["regions"] = [{"polygon": [[0.0, 0.0], [20.0, 0.0], [20.0, 20.0], [0.0, 20.0]],
                                 "material": {**material, "lame_mu": 2.0 * material["lame_mu"]}}]
    return raw


def test_uncertain_moduli_on_a_scenario_with_material_regions_are_refused(tmp_path):
    """A sample replaces tissue.material only: the regions' moduli would stay fixed, which
    moduli given in the uncertainty file do not say. Refused up front; thickness stays
    allowed."""
    scenario_path = write(tmp_path, _with_region())
    path = write(tmp_path, {"samples": 3, "parameters": {"lame_mu": {"std": 0.01}}}, "u.yaml")
    out = tmp_path / "out"
    line = one_error_line(invoke("plan", scenario_path, "--uncertainty", path, "--export", out / "t.csv",
                                 "--workers", "0"))
    expected = (f"error: --uncertainty: {path}: parameters.lame_mu: got {{std: 0.01}}, expected no uncertain "
                f"moduli for a scenario with material regions ({scenario_path} has 1 region in tissue.regions")
    assert line.startswith(expected), line
    assert line.endswith("or take both moduli from a `calibrate material` fitted around the scenario's regions: "
                         "from_calibration)"), line
    assert not out.exists()
    assert with_parameters(parse_scenario(_with_region()), ("thickness",), np.array([9.0])).tissue.thickness == 9.0


def _bottom_region(lame_mu: float = 0.3) -> dict:
    """A stiffer band along the bottom of small_raw's 20 x 20 mm block (the needle enters at the top)."""
    return {"polygon": [[0.0, 0.0], [20.0, 0.0], [20.0, 6.0], [0.0, 6.0]],
            "material": {"model": "saint-venant-kirchhoff", "lame_lambda": 0.4, "lame_mu": lame_mu}}


def _region_calibration(folder: Path, regions: list) -> Path:
    """A `calibrate material` output fitted around `regions` (as it writes them)."""
    fitted = folder / "fitted.yaml"
    fitted.write_text(yaml.safe_dump({"lame_lambda": 0.19, "lame_mu": 0.15, "regions": regions,
                                      "fit": {"standard_uncertainty": {"lame_lambda": 0.01, "lame_mu": 0.002},
                                              "correlation": -0.5, "identifiable": True}}))
    return fitted


def test_moduli_calibrated_around_the_scenarios_regions_vary_its_own_material(tmp_path):
    """A calibration fitted around regions of given material determines the tissue's own moduli
    there: on a scenario with the same regions its stds are taken, and a sample replaces
    tissue.material and keeps the regions'; other regions, other materials or none are refused,
    naming the calibration's regions and the scenario's."""
    from stitchplan.config.uncertainty import check_against_scenario

    _region_calibration(tmp_path, [_bottom_region()])
    resolved = uncertainty({"samples": 3, "from_calibration": "fitted.yaml"}, str(tmp_path / "u.yaml"))
    raw = small_raw()
    raw["tissue"]["regions"] = [_bottom_region()]
    scenario = parse_scenario(raw)
    check_against_scenario(resolved, scenario, "scene.yaml")  # the same regions: taken
    sample = with_parameters(scenario, ("lame_lambda", "lame_mu"), np.array([0.2, 0.16]))
    assert (sample.tissue.material.lame_lambda, sample.tissue.material.lame_mu) == (0.2, 0.16)
    assert sample.tissue.regions == scenario.tissue.regions
    raw["tissue"]["regions"] = [_bottom_region(lame_mu=0.31)]
    for regions, fragment in (([_bottom_region(lame_mu=0.31)], "has 1 region in tissue.regions, with other shapes "
                                                                  "or materials)"),
                              ((), "has 0 regions in tissue.regions)")):
        raw["tissue"]["regions"] = list(regions)
        with pytest.raises(InputError) as refused:
            check_against_scenario(resolved, parse_scenario(raw), "scene.yaml")
        message = str(refused.value)
        assert message.startswith(f"{tmp_path / 'u.yaml'}: from_calibration: {tmp_path / 'fitted.yaml'}: regions: "
                                  "got 1 region, expected the scenario's regions as given (scene.yaml " + fragment)
        assert message.count("\n") == 0


REGION_NAMES = ("tissue.regions[0].lame_lambda", "tissue.regions[0].lame_mu")


def _fitted_region_calibration(folder: Path, region_std: tuple = (0.04, 0.02), **changes) -> Path:
    """A `calibrate material` output that fitted the bottom band's moduli too (as it writes
    them: fit.fitted_regions and fit.correlations of all four); `changes` replace fit keys."""
    fitted = _region_calibration(folder, [_bottom_region()])
    raw = yaml.safe_load(fitted.read_text())
    raw["fit"]["fitted_regions"] = [{"region": 0, "lame_lambda": 0.4, "lame_mu": 0.3, "standard_uncertainty":
                                     dict(zip(("lame_lambda", "lame_mu"), region_std))}]
    raw["fit"]["correlations"] = {"parameters": ["lame_lambda", "lame_mu", *REGION_NAMES],
                                  "matrix": [[1.0, -0.5, 0.2, 0.1], [-0.5, 1.0, -0.3, 0.0],
                                             [0.2, -0.3, 1.0, -0.6], [0.1, 0.0, -0.6, 1.0]]}
    raw["fit"].update(changes)
    fitted.write_text(yaml.safe_dump(raw))
    return fitted


def test_a_calibrations_fitted_regions_moduli_vary_with_their_correlations(tmp_path):
    """A calibration that fitted a region's moduli too gives their stds and the correlations of
    all four: a sample varies the region's material as well as the tissue's, with the
    correlation matrix the calibration wrote; the run log's units name them."""
    from stitchplan.config.uncertainty import check_against_scenario, scenario_values

    _fitted_region_calibration(tmp_path)
    resolved = uncertainty({"samples": 3, "from_calibration": "fitted.yaml", "parameters": {"thickness": {"std": 1.0}}},
                           str(tmp_path / "u.yaml"))
    assert resolved.names == ("lame_lambda", "lame_mu", "thickness", *REGION_NAMES)
    np.testing.assert_array_equal(resolved.std, [0.01, 0.002, 1.0, 0.04, 0.02])
    assert resolved.correlation[3, 4] == -0.6 and resolved.correlation[0, 3] == 0.2 and resolved.correlation[2, 3] == 0
    record = resolved.as_record()
    assert record["parameters"][REGION_NAMES[1]] == {"std": 0.02, "units": "MPa", "source": "calibration"}
    raw = small_raw()
    raw["tissue"]["regions"] = [_bottom_region()]
    scenario = parse_scenario(raw)
    check_against_scenario(resolved, scenario, "scene.yaml")
    np.testing.assert_array_equal(scenario_values(scenario, REGION_NAMES), [0.4, 0.3])
    sample = with_parameters(scenario, ("lame_mu", *REGION_NAMES), np.array([0.16, 0.45, 0.35]))
    assert sample.tissue.material.lame_mu == 0.16
    assert (sample.tissue.regions[0].material.lame_lambda, sample.tissue.regions[0].material.lame_mu) == (0.45, 0.35)
    assert sample.tissue.regions[0].polygon == scenario.tissue.regions[0].polygon


def test_the_calibrations_checksum_is_of_the_bytes_its_spread_was_read_from(tmp_path):
    """The uncertainty resolved from a calibration carries the SHA-256 of the calibration's bytes
    as parsed, which the run records (calibration_file_sha256): before, the command hashed the
    file in a second read, which a file replaced between the two would have made another's."""
    fitted = _fitted_region_calibration(tmp_path)
    resolved = uncertainty({"samples": 3, "from_calibration": "fitted.yaml"}, str(tmp_path / "u.yaml"))
    assert resolved.calibration_sha256 == hashlib.sha256(fitted.read_bytes()).hexdigest()


def test_plan_under_uncertainty_varies_a_fitted_regions_moduli(tmp_path):
    """End to end: the region's moduli are sampled and get their own sensitivities."""
    _fitted_region_calibration(tmp_path)
    raw = small_raw()
    raw["tissue"]["regions"] = [_bottom_region()]
    scenario = write(tmp_path, raw)
    path = write(tmp_path, {"samples": 3, "seed": 7, "from_calibration": "fitted.yaml"}, "u.yaml")
    result = invoke("plan", scenario, "--uncertainty", path, "--export", tmp_path / "t.csv", "--summary",
                    tmp_path / "s.json", "--no-verify", "--workers", "0")
    assert result.exit_code == 0, result.output
    block = _strict_json(tmp_path / "s.json")["uncertainty"]
    assert list(block["sensitivity"]) == ["lame_lambda", "lame_mu", *REGION_NAMES]
    assert all(abs(value) > 0 for name in REGION_NAMES for value in block["sensitivity"][name])
    assert block["sensitivity_units"][REGION_NAMES[0]] == "mm/MPa" and block["failed_samples"] == 0


def test_a_fitted_regions_spread_is_checked_as_the_tissues(tmp_path):
    """A region's std above its modulus is refused naming the calibration's entry and the
    scenario's field; a malformed fit.fitted_regions or fit.correlations is named."""
    from stitchplan.config.uncertainty import calibration_spread, check_against_scenario

    _fitted_region_calibration(tmp_path, region_std=(0.04, 0.5))
    resolved = uncertainty({"samples": 3, "from_calibration": "fitted.yaml"}, str(tmp_path / "u.yaml"))
    raw = small_raw()
    raw["tissue"]["regions"] = [_bottom_region()]
    with pytest.raises(InputError) as refused:
        check_against_scenario(resolved, parse_scenario(raw), "scene.yaml")
    assert str(refused.value) == (
        f"{tmp_path / 'u.yaml'}: from_calibration: {tmp_path / 'fitted.yaml'}: fit.fitted_regions (region 0): "
        "standard_uncertainty.lame_mu: got 0.5, expected at most the scenario's value 0.3 MPa (scene.yaml: "
        "tissue.regions[0].material.lame_mu): a larger std puts more than 16 % of the normal at or below 0, and "
        "truncated to positive values it is no longer centred on the scenario's value")
    for changes, fragment in (({"fitted_regions": [{"region": 3}]}, "fit.fitted_regions[0].region: got 3, "
                                                                     "expected an index of its regions: (0 to 0)"),
                              ({"fitted_regions": "region 0"}, "fit.fitted_regions: got 'region 0', expected a list"),
                              ({"correlations": {"parameters": ["lame_lambda"], "matrix": [[1.0]]}},
                               "'parameters': ['lame_lambda']}, expected the parameters ['lame_lambda', 'lame_mu', "
                               "'tissue.regions[0].lame_lambda'")):
        fitted = _fitted_region_calibration(tmp_path, **changes)
        with pytest.raises(InputError) as refused:
            calibration_spread(fitted, tmp_path / "u.yaml")
        assert fragment in str(refused.value) and str(refused.value).count("\n") == 0, str(refused.value)


def test_a_calibration_without_regions_is_refused_on_a_scenario_with_regions(tmp_path):
    """Moduli fitted to a tissue of one material are not the tissue's own around regions."""
    path = write(tmp_path, _with_region())
    (tmp_path / "u.yaml").write_text(f"samples: 3\nfrom_calibration: {CALIBRATION / 'fitted.yaml'}\n")
    out = tmp_path / "out"
    line = one_error_line(invoke("plan", path, "--uncertainty", tmp_path / "u.yaml", "--export", out / "t.csv",
                                 "--workers", "0"))
    assert "regions: got 0 regions, expected the scenario's regions as given" in line, line
    assert not out.exists()


def test_a_calibrations_regions_that_are_no_regions_are_named(tmp_path):
    from stitchplan.config.uncertainty import calibration_spread

    for regions, fragment in (("a disc", "regions: got 'a disc', expected a list of regions"),
                              ([{"circle": {"center": [5, 5], "radius": 2}}], "regions[0].material: missing")):
        fitted = _region_calibration(tmp_path, regions)
        with pytest.raises(InputError, match=fragment.replace("[", r"\[").replace("]", r"\]")):
            calibration_spread(fitted, tmp_path / "u.yaml")


def test_a_symmetric_target_across_a_wound_is_refused_with_uncertainty(tmp_path):
    """The plans under uncertainty aim at and report the exit; a symmetric plan aims at equal
    bites, whose passes would override the robust aim. Refused before any run, naming the
    scenario's file and field; the target alone (no wound crossed) means the exit, and passes."""
    from stitchplan.config import load_scenario
    from stitchplan.uncertainty.robust import check_target

    scenario_path = Path(__file__).resolve().parents[1] / "configs" / "wound_closure_symmetric.yaml"
    path = write(tmp_path, {"samples": 3, "parameters": {"thickness": {"std": 0.5}}}, "u.yaml")
    out = tmp_path / "out"
    line = one_error_line(invoke("plan", scenario_path, "--uncertainty", path, "--export", out / "t.csv",
                                 "--summary", out / "s.json", "--workers", "0"))
    assert line.startswith(f"error: {scenario_path}: planner.target: got 'symmetric', expected 'exit' with "
                           "--uncertainty"), line
    assert not out.exists()
    with pytest.raises(InputError, match="planner.target: got 'symmetric'"):
        plan_under_uncertainty(load_scenario(scenario_path), uncertainty({"samples": 3, "parameters":
                                                                          {"thickness": {"std": 0.5}}}))
    convex = small_raw()
    convex.setdefault("planner", {})["target"] = "symmetric"
    check_target(parse_scenario(convex))  # no wound crossed: nothing to refuse


def test_a_calibration_that_cannot_separate_the_moduli_is_refused_with_finite_stds(tmp_path):
    """A fit marked `identifiable: false` is refused even where it printed standard
    uncertainties (the estimates' correlation beyond the limit): they are not usable."""
    from stitchplan.config.uncertainty import calibration_spread
    from stitchplan.errors import InputError

    fitted = tmp_path / "fitted.yaml"
    fitted.write_text("fit:\n  standard_uncertainty: {lame_lambda: 0.02, lame_mu: 0.01}\n"
                      "  correlation: -0.9995\n  identifiable: false\n")
    with pytest.raises(InputError, match="fit.identifiable: got false, expected a calibration that identifies"):
        calibration_spread(fitted, tmp_path / "u.yaml")
    # quoted, "false" or "no" is a string: refused rather than read as true
    fitted.write_text("fit:\n  standard_uncertainty: {lame_lambda: 0.02, lame_mu: 0.01}\n"
                      "  correlation: -0.5\n  identifiable: 'no'\n")
    with pytest.raises(InputError, match="fit.identifiable: got 'no', expected true or false"):
        calibration_spread(fitted, tmp_path / "u.yaml")


def test_correlated_moduli_that_cancel_are_not_called_a_share_of_the_spread():
    """lame_lambda and lame_mu at -0.99: each alone moves the exit far more than both together
    (their effects cancel), so the line names the cancellation rather than '0.0088 mm of
    0.0014 mm'."""
    from types import SimpleNamespace

    from stitchplan.uncertainty.robust import Sensitivity, UncertaintyResult

    names = ("lame_lambda", "lame_mu")
    correlation = np.array([[1.0, -0.99], [-0.99, 1.0]])
    sensitivities = [Sensitivity("lame_lambda", 0.0129, 0.006, np.array([0.3, 0.1]), None),
                     Sensitivity("lame_mu", 0.0047, 0.002, np.array([0.8, 0.27]), None)]
    result = SimpleNamespace(uncertainty=SimpleNamespace(names=names, correlation=correlation),
                             sensitivities=sensitivities, statistics={"nominal": {"p95_mm": 0.002}},
                             exported="nominal")
    result.dominant = lambda: UncertaintyResult.dominant(result)
    result.linearised_spread_mm = lambda: UncertaintyResult.linearised_spread_mm(result)
    total, alone = result.linearised_spread_mm(), 1.959963984540054 * sensitivities[0].spread_mm
    assert total < alone
    line = UncertaintyResult.dominance_line(result)
    assert line.startswith(f"exit spread: lame_lambda alone would move the exit {alone:.3g} mm (p95, std "
                           f"0.0129 MPa), more than the {total:.3g} mm p95 of all parameters together "
                           "(linearised): its correlation with lame_mu (-0.99) cancels most of it")
    result.uncertainty.correlation = np.eye(2)  # independent: a share of the total again
    assert UncertaintyResult.dominance_line(result).startswith("exit spread dominated by")
