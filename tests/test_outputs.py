"""All-or-nothing outputs and their provenance.

Every command checks its outputs before computing (writable, not a folder or a device, no two
the same file, none an input), writes them to temporaries and renames them only when all
succeeded, so a failed run creates, replaces or deletes none of the user's files. The suite
runs as root, where a folder's permissions do not stop writes: unwritable outputs here are
paths under an existing *file*, /proc, or an `os.replace` made to fail mid-way.

Summaries carry the version, the command line, the scenario and its SHA-256 and the time;
every HDF5 dataset says its units; the trajectory a robot reads has no round-off noise.
"""

from __future__ import annotations

import csv
import errno
import hashlib
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

import stitchplan
from stitchplan.cli import app
from stitchplan.errors import InputError
from stitchplan.io import files
from stitchplan.io.files import OutputSet

RADIUS = 8.0


def block_raw(**extra) -> dict:
    """20 x 20 mm block, 5 mm spacing, an 8 mm needle in 0.3 rad steps (a run of ~1 s), with a
    load and a probe for deform."""
    return {"name": "outputs",
            "tissue": {"size": [20.0, 20.0], "thickness": 10.0, "clamped": ["right"],
                       "material": {"lame_lambda": 0.189151, "lame_mu": 0.147688}},
            "discretization": {"spacing": 5.0},
            "needle": {"radius": RADIUS, "entry": [0.0, 18.0], "turn": "cw", "step": 0.3,
                       "friction": 0.0602, "cutting_force": 0.7},
            "loads": [{"segment": [[0.0, 5.0], [0.0, 15.0]], "force": [1.0, 0.5]}],
            "load_steps": 2,
            "probes": [[0.0, 10.0], [10.0, 10.0]],
            "planner": {"max_passes": 1},
            **extra}


@pytest.fixture
def scene(tmp_path) -> Path:
    path = tmp_path / "scene.yaml"
    path.write_text("# outputs test\n" + yaml.safe_dump(block_raw(), sort_keys=False))
    return path


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def one_error_line(result, code: int = 2) -> str:
    assert result.exit_code == code, result.output
    assert "Traceback" not in result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.output
    return lines[0]


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under `folder` (hidden temporaries included) with its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def existing_outputs(folder: Path, *names: str) -> dict[str, bytes]:
    """Pre-existing outputs of an earlier run, each with distinct content."""
    for name in names:
        (folder / name).write_bytes(f"earlier {name}\n".encode())
    return snapshot(folder)


# --- the transaction itself --------------------------------------------------------------


@pytest.mark.parametrize("name", ["/dev/stdout", "/dev/stderr", "/dev/fd/1", "/proc/self/fd/1", "//dev/stdout"])
def test_a_process_stream_is_refused_as_an_output(tmp_path, name):
    """Redirected to a file, /dev/stdout resolves to that file, which the output's rename
    would replace (losing the command's own lines); to a pipe, to nothing writable."""
    if not os.path.exists(name):
        pytest.skip(f"no {name} here")
    with pytest.raises(InputError) as caught:
        OutputSet({"--summary": name}).check()
    assert caught.value.lines == [f"--summary: got {name}, a process's stream; expected a file name"]


def test_check_lists_every_problem_and_creates_nothing(tmp_path):
    blocker = tmp_path / "blocker"
    blocker.write_text("a file, not a folder")
    before = snapshot(tmp_path)
    with pytest.raises(InputError) as caught:
        OutputSet({"--out": blocker / "run.h5", "--plot": tmp_path, "--summary": "/dev/null",
                   "--export": tmp_path / "new" / "t.csv", "--probes-out": tmp_path / "new" / "t.csv"},
                  {"SCENARIO": blocker}).check()
    lines = caught.value.lines
    assert lines[0] == f"--out: cannot write {blocker / 'run.h5'}: {blocker} is not a folder"
    assert lines[1] == f"--plot: got {tmp_path}, a folder; expected a file name"
    assert lines[2] == "--summary: got /dev/null, not a regular file; expected a file name"
    assert lines[3] == (f"--probes-out: got {tmp_path / 'new' / 't.csv'}, expected a file other than "
                        f"--export ({tmp_path / 'new' / 't.csv'})")
    assert len(lines) == 4
    assert snapshot(tmp_path) == before and not (tmp_path / "new").exists()


def test_a_read_only_file_is_refused_and_kept_even_for_root(tmp_path, scene):
    """A file with no write permission for anyone (chmod a-w) is refused as read-only, also
    when the command runs as root, whose access test passes: kept as it was, nothing written."""
    before = existing_outputs(tmp_path, "t.csv")
    os.chmod(tmp_path / "t.csv", 0o444)
    with pytest.raises(InputError) as caught:
        OutputSet({"--export": tmp_path / "t.csv"}).check()
    assert caught.value.lines == [f"--export: cannot write {tmp_path / 't.csv'}: the file is read-only"]
    line = one_error_line(invoke("simulate", scene, "--no-estimate", "--summary", tmp_path / "t.csv"))
    assert line.endswith(f"--summary: cannot write {tmp_path / 't.csv'}: the file is read-only"), line
    assert snapshot(tmp_path) == before
    assert (tmp_path / "t.csv").stat().st_mode & 0o777 == 0o444


def test_an_output_cannot_be_the_folder_of_another(tmp_path):
    folder = tmp_path / "run"
    with pytest.raises(InputError) as caught:
        OutputSet({"--export": folder / "t.csv", "--out": folder}).check()
    assert caught.value.lines == [f"--out: got {folder}, the folder of --export ({folder / 't.csv'}); "
                                  "expected a file name"]
    assert not folder.exists()


def test_coinciding_files_are_found_through_links_and_spellings(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "a.csv").write_text("x\n")
    os.link(tmp_path / "a.csv", tmp_path / "hard.csv")
    (tmp_path / "soft.csv").symlink_to(tmp_path / "a.csv")
    for other in ("./a.csv", tmp_path / "sub" / ".." / "a.csv", "hard.csv", "soft.csv"):
        with pytest.raises(InputError, match="expected a file other than the input SCENARIO"):
            OutputSet({"--out": other}, {"SCENARIO": "a.csv"}).check()
    OutputSet({"--out": "b.csv"}, {"SCENARIO": "a.csv"}).check()  # a different file is fine


def test_a_failing_writer_leaves_every_file_as_it_was(tmp_path):
    before = existing_outputs(tmp_path, "t.csv", "summary.json")
    outputs = OutputSet({"--export": tmp_path / "t.csv", "--summary": tmp_path / "summary.json",
                         "--out": tmp_path / "logs" / "deep" / "run.h5"})
    with pytest.raises(RuntimeError, match="writer failed"), outputs.staged() as staged:
        staged["--export"].write_text("new trajectory\n")
        raise RuntimeError("writer failed")
    assert snapshot(tmp_path) == before  # no temporaries left, nothing replaced
    assert not (tmp_path / "logs").exists()  # the folders made for the outputs are gone too


def test_an_os_error_while_writing_is_one_line_naming_the_output(tmp_path):
    before = existing_outputs(tmp_path, "t.csv")
    outputs = OutputSet({"--export": tmp_path / "t.csv", "--summary": tmp_path / "s.json"})
    with pytest.raises(InputError) as caught, outputs.staged() as staged:
        raise OSError(28, "No space left on device", str(staged["--summary"]))
    assert str(caught.value) == f"--summary: cannot write {tmp_path / 's.json'}: No space left on device"
    assert snapshot(tmp_path) == before


def test_a_failed_rename_puts_back_the_files_already_replaced(tmp_path, monkeypatch):
    """The second of three renames fails: the first target gets its old content back, the
    third is never touched, a new file the first rename created is removed."""
    before = existing_outputs(tmp_path, "t.csv", "summary.json", "run.h5")
    replace = os.replace
    for new_first in (False, True):
        first = tmp_path / ("fresh.csv" if new_first else "t.csv")
        outputs = OutputSet({"--export": first, "--summary": tmp_path / "summary.json",
                             "--out": tmp_path / "run.h5"})
        calls = []

        def failing_replace(source, target, calls=calls):
            calls.append(target)
            if len(calls) == 2:
                raise OSError(5, "Input/output error", str(target))
            return replace(source, target)

        monkeypatch.setattr(os, "replace", failing_replace)
        with (pytest.raises(InputError, match="--summary: cannot write .*Input/output error"),
              outputs.staged() as staged):
            for temporary in staged.values():
                temporary.write_text("new\n")
        monkeypatch.setattr(os, "replace", replace)
        assert snapshot(tmp_path) == before


def test_success_renames_all_and_keeps_an_existing_files_mode(tmp_path):
    existing_outputs(tmp_path, "t.csv")
    os.chmod(tmp_path / "t.csv", 0o640)
    outputs = OutputSet({"--export": tmp_path / "t.csv", "--out": tmp_path / "new" / "run.h5"})
    with outputs.staged() as staged:
        for label, temporary in staged.items():
            assert temporary.parent == outputs.outputs[label].parent  # beside the target
            temporary.write_text(label)
    assert snapshot(tmp_path) == {"t.csv": b"--export", "new/run.h5": b"--out"}
    assert (tmp_path / "t.csv").stat().st_mode & 0o777 == 0o640


# --- every command: unwritable outputs and coincidences are refused before any work -------


def _commands(folder: Path, scene: Path) -> dict[str, list]:
    """Each command with its usual outputs in `folder` (all pre-existing in the tests)."""
    air, tissue = folder / "air.csv", folder / "tissue.csv"
    for path, force in ((air, "0.1"), (tissue, "0.9")):
        path.write_text("angle_rad,force_N\n" + "".join(f"{a / 10},{force}\n" for a in range(10)))
    (folder / "markers.csv").write_text("x,y,x_def,y_def\n10,10,10.1,10\n15,5,15.1,5\n")
    calibration = folder / "calib.yaml"
    calibration.write_text(yaml.safe_dump({
        "tissue": {"size": [20.0, 20.0], "thickness": 10.0, "clamped": ["right"]},
        "experiments": [{"loads": [{"segment": [[0.0, 5.0], [0.0, 15.0]], "force": [1.0, 0.5]}],
                         "markers": "markers.csv"}],
        "fit": {"lame_lambda": [0.05, 1.0], "lame_mu": [0.05, 1.0], "grid": 3, "max_evaluations": 10},
        "discretization": {"spacing": 5.0}}))  # a fit of ~0.5 s
    return {
        "deform": ["deform", scene, "--probes-out", folder / "probes.csv", "--reactions-out",
                   folder / "reactions.csv", "--summary", folder / "summary.json"],
        "simulate": ["simulate", scene, "--out", folder / "run.h5", "--summary", folder / "summary.json"],
        "plan": ["plan", scene, "--export", folder / "trajectory.csv", "--summary", folder / "summary.json"],
        "calibrate material": ["calibrate", "material", calibration, "--out", folder / "fitted.yaml"],
        "calibrate needle": ["calibrate", "needle", "--air", air, "--tissue", tissue, "--radius", 8.88,
                             "--out", folder / "needle.yaml"],
        "study": ["study", scene, "--quick", "--out", folder],
    }


OUTPUT_NAMES = ("probes.csv", "reactions.csv", "summary.json", "run.h5", "trajectory.csv",
                "fitted.yaml", "needle.yaml", "study.csv", "speed_accuracy.png", "study.json")


@pytest.mark.parametrize("command", ["deform", "simulate", "plan", "calibrate material",
                                     "calibrate needle", "study"])
@pytest.mark.parametrize("where", ["under a file", "/proc"])
def test_an_unwritable_output_leaves_every_earlier_output_byte_identical(tmp_path, scene, command, where):
    args = _commands(tmp_path, scene)[command]
    before = existing_outputs(tmp_path, *OUTPUT_NAMES)
    blocker = tmp_path / "blocker"
    blocker.write_text("a file\n")
    before[blocker.name] = blocker.read_bytes()
    bad = blocker / "plot.png" if where == "under a file" else Path("/proc/stitchplan-test.png")
    if command == "study":  # its folder holds every output
        args[args.index("--out") + 1] = bad.parent / "study"
    else:
        args += ["--plot", bad] if command != "calibrate material" else ["--plot-dir", bad.parent / "plots"]
    line = one_error_line(invoke(*args))
    assert "cannot write" in line and str(bad.parent) in line
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("command, first, second", [
    ("deform", "--probes-out", "--reactions-out"),
    ("deform", "--summary", "--probes-out"),
    ("simulate", "--out", "--summary"),
    ("plan", "--export", "--summary"),
])
def test_two_outputs_on_one_file_are_refused_naming_both(tmp_path, scene, command, first, second):
    args = _commands(tmp_path, scene)[command]
    args = [a for a in args[:2]] + [first, tmp_path / "same.csv", second, tmp_path / "same.csv"]
    before = snapshot(tmp_path)
    line = one_error_line(invoke(*args))
    same = tmp_path / "same.csv"
    assert line in (f"error: {second}: got {same}, expected a file other than {first} ({same})",
                    f"error: {first}: got {same}, expected a file other than {second} ({same})")
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("command, option, input_label, input_name", [
    ("deform", "--summary", "SCENARIO", "scene.yaml"),
    ("simulate", "--out", "SCENARIO", "scene.yaml"),
    ("plan", "--export", "SCENARIO", "scene.yaml"),
    ("calibrate material", "--out", "CALIBRATION", "calib.yaml"),
    ("calibrate material", "--out", "markers of experiments[0]", "markers.csv"),
    ("calibrate needle", "--out", "--tissue", "tissue.csv"),
])
def test_an_output_on_an_input_is_refused_naming_both(tmp_path, scene, command, option, input_label,
                                                      input_name):
    args = _commands(tmp_path, scene)[command]
    args[args.index(option) + 1] = tmp_path / input_name
    before = snapshot(tmp_path)
    line = one_error_line(invoke(*args))
    assert line.startswith(f"error: {option}: got {tmp_path / input_name}, expected a file other than "
                           f"the input {input_label} (")
    assert snapshot(tmp_path) == before


def test_simulate_refuses_to_overwrite_its_center_path(tmp_path, scene):
    path = tmp_path / "trajectory.csv"
    path.write_text("step,angle_rad,center_x_mm,center_y_mm\n0,0,0,10\n")
    line = one_error_line(invoke("simulate", scene, "--center-path", path, "--summary", path))
    assert "the input --center-path" in line
    assert path.read_text().startswith("step,")


def test_study_refuses_a_folder_whose_study_csv_is_the_scenario(tmp_path):
    scenario = tmp_path / "study.csv"
    scenario.write_text(yaml.safe_dump(block_raw()))
    line = one_error_line(invoke("study", scenario, "--quick", "--out", tmp_path))
    assert "expected a file other than the input SCENARIO" in line


# --- a failure after the computation: nothing of the run lands -----------------------------


def test_deform_failing_at_its_last_rename_replaces_nothing(tmp_path, scene, monkeypatch):
    before = existing_outputs(tmp_path, "probes.csv", "summary.json")
    replace, calls = os.replace, []

    def failing_replace(source, target):
        calls.append(target)
        if Path(target).name == "run.h5":
            raise OSError(30, "Read-only file system", str(target))
        return replace(source, target)

    monkeypatch.setattr(os, "replace", failing_replace)
    result = invoke("deform", scene, "--probes-out", tmp_path / "probes.csv", "--summary",
                    tmp_path / "summary.json", "--reactions-out", tmp_path / "reactions.csv",
                    "--out", tmp_path / "run.h5")
    monkeypatch.setattr(os, "replace", replace)
    line = one_error_line(result)
    assert line == f"error: --out: cannot write {tmp_path / 'run.h5'}: Read-only file system"
    assert len(calls) >= 4  # the earlier three were renamed, then undone
    assert snapshot(tmp_path) == before


# --- provenance --------------------------------------------------------------------------


def _check_provenance(record: dict, args: list, scene: Path) -> None:
    assert record["stitchplan_version"] == stitchplan.__version__
    assert record["stitchplan_source_sha256"] == stitchplan.source_sha256()  # the code, which the version is not
    assert record["command"][1:] == list(map(str, args))  # [0]: the program as invoked
    assert record["scenario"] == str(scene)
    assert record["scenario_sha256"] == hashlib.sha256(scene.read_bytes()).hexdigest()
    assert record["created_utc"].endswith("+00:00")
    # what the relative paths of the command line are relative to
    assert record["working_directory"] == os.getcwd()



def test_the_source_digest_tells_apart_code_of_one_version(tmp_path):
    """The version stays the same over many changes of the numerics between releases (plan's
    exit error on sh12_100x100 went from 0.021 to 0.00023 mm at 0.2.0): the records' source
    digest changes with any byte of the package's code, and only with its code."""
    import shutil

    copy = tmp_path / "stitchplan"
    shutil.copytree(Path(stitchplan.__file__).parent, copy, ignore=shutil.ignore_patterns("__pycache__"))
    assert stitchplan.sources_digest(copy) == stitchplan.source_sha256()
    (copy / "notes.txt").write_text("not code")
    assert stitchplan.sources_digest(copy) == stitchplan.source_sha256()
    module = copy / "tissue" / "material.py"
    module.write_bytes(module.read_bytes() + b"\n")
    assert stitchplan.sources_digest(copy) != stitchplan.source_sha256()


def test_deform_summary_and_run_log_carry_provenance_and_units(tmp_path, scene):
    args = ["deform", scene, "--summary", tmp_path / "summary.json", "--out", tmp_path / "run.h5"]
    result = invoke(*args)
    assert result.exit_code == 0, result.output
    _check_provenance(json.loads((tmp_path / "summary.json").read_text()), args, scene)
    _check_run_log(tmp_path / "run.h5", scene, "deform")


def test_a_scenario_with_a_bom_is_stored_as_the_bytes_it_hashes(tmp_path, scene):
    """A spreadsheet's byte-order mark: the run log's scenario text, encoded, is the file,
    whose SHA-256 it records (the text left the mark out)."""
    marked = tmp_path / "marked.yaml"
    marked.write_bytes(b"\xef\xbb\xbf" + scene.read_bytes())
    result = invoke("deform", marked, "--out", tmp_path / "run.h5")
    assert result.exit_code == 0, result.output
    with h5py.File(tmp_path / "run.h5") as log:
        text = log["scenario/text"][()]
        text = text if isinstance(text, bytes) else text.encode()
        assert hashlib.sha256(text).hexdigest() == log.attrs["scenario_sha256"]
        assert text == marked.read_bytes()


def test_python_m_stitchplan_records_its_command_as_arguments(tmp_path, scene):
    """Under `python -m stitchplan` the program's name is three arguments of the recorded
    command line, which subprocess can run again as it stands."""
    result = CliRunner().invoke(app, ["deform", str(scene), "--summary", str(tmp_path / "s.json")],
                                prog_name="python -m stitchplan")
    assert result.exit_code == 0, result.output
    command = json.loads((tmp_path / "s.json").read_text())["command"]
    assert command[:4] == ["python", "-m", "stitchplan", "deform"], command


def test_a_replay_records_its_centre_path_and_its_sha256(tmp_path, scene):
    """simulate --center-path: the summary and the run log name the path's file and its
    SHA-256, as they do the scenario's."""
    planned = invoke("plan", scene, "--export", tmp_path / "t.csv", "--no-compare", "--no-verify")
    assert planned.exit_code == 0, planned.output
    path = tmp_path / "t.csv"
    result = invoke("simulate", scene, "--center-path", path, "--summary", tmp_path / "s.json", "--out",
                    tmp_path / "run.h5", "--no-estimate")
    assert result.exit_code == 0, result.output
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    record = json.loads((tmp_path / "s.json").read_text())
    assert record["center_path"] == str(path) and record["center_path_sha256"] == digest
    with h5py.File(tmp_path / "run.h5") as log:
        assert log.attrs["center_path"] == str(path) and log.attrs["center_path_sha256"] == digest



def test_a_replay_from_a_pipe_records_the_path_it_read_and_reruns_from_its_run_log_alone(tmp_path, scene):
    """A pipe gives the centre path once (`--center-path <(ssh robot cat t.csv)`): its SHA-256
    is of the bytes replayed, not of a second, empty read (a named pipe's second open waited
    for a writer for ever), and the run log keeps their text beside the scenario's, so that a
    folder holding only run.h5 replays the same steps again."""
    planned = invoke("plan", scene, "--export", tmp_path / "t.csv", "--no-compare", "--no-verify")
    assert planned.exit_code == 0, planned.output
    content = (tmp_path / "t.csv").read_bytes()
    read_end, write_end = os.pipe()
    os.write(write_end, content)  # a few rows: within the pipe's buffer
    os.close(write_end)
    try:
        result = invoke("simulate", scene, "--center-path", f"/dev/fd/{read_end}", "--summary", tmp_path / "s.json",
                        "--out", tmp_path / "run.h5", "--no-estimate")
    finally:
        os.close(read_end)
    assert result.exit_code == 0, result.output
    digest = hashlib.sha256(content).hexdigest()
    assert json.loads((tmp_path / "s.json").read_text())["center_path_sha256"] == digest
    again = tmp_path / "again"
    again.mkdir()
    with h5py.File(tmp_path / "run.h5") as log:
        assert log.attrs["center_path_sha256"] == digest and log["center_path/text"][()] == content
        (again / "scene.yaml").write_bytes(log["scenario/text"][()])
        (again / "path.csv").write_bytes(log["center_path/text"][()])
        first = log["steps/tip_spatial"][()]
    rerun = invoke("simulate", again / "scene.yaml", "--center-path", again / "path.csv", "--out",
                   again / "run.h5", "--no-estimate")
    assert rerun.exit_code == 0, rerun.output
    with h5py.File(again / "run.h5") as log:
        np.testing.assert_array_equal(log["steps/tip_spatial"][()], first)

def _check_run_log(path: Path, scene: Path, command: str) -> dict[str, str]:
    units = {}
    with h5py.File(path) as log:
        assert log.attrs["schema_version"] == files.HDF5_SCHEMA_VERSION
        assert log.attrs["command"] == command
        assert log.attrs["stitchplan_source_sha256"] == stitchplan.source_sha256()
        assert log.attrs["scenario_sha256"] == hashlib.sha256(scene.read_bytes()).hexdigest()
        for name in ("python_version", "numpy_version", "scipy_version", "h5py_version"):
            assert log.attrs[name]
        assert log.attrs["numpy_version"] == np.__version__
        assert log.attrs["working_directory"] == os.getcwd()
        log.visititems(lambda name, item: units.update({name: item.attrs.get("units")})
                       if isinstance(item, h5py.Dataset) else None)
    assert units and all(isinstance(u, str) and u for u in units.values()), units
    return units


def test_plan_summary_run_log_and_a_trajectory_without_round_off(tmp_path, scene):
    args = ["plan", scene, "--export", tmp_path / "trajectory.csv", "--summary", tmp_path / "summary.json",
            "--out", tmp_path / "run.h5", "--no-compare", "--angular-speed", "0.5"]
    result = invoke(*args)
    assert result.exit_code == 0, result.output
    _check_provenance(json.loads((tmp_path / "summary.json").read_text()), args, scene)
    units = _check_run_log(tmp_path / "run.h5", scene, "plan")
    assert units["steps/center"] == "mm" and units["steps/rotation"] == "rad"
    assert units["planner/trajectory"] == "1,rad,mm,mm,mm,mm,s"
    with (tmp_path / "trajectory.csv").open(newline="") as handle:
        rows = list(csv.reader(handle))
    assert rows[1][:2] == ["0", "0"]
    # the tip at entry is the entry point, (0, 18) exactly; no 5e-16 or -0 in any cell
    assert [float(v) for v in rows[1][4:6]] == [0.0, 18.0]
    cells = [cell for row in rows[1:] for cell in row[2:6]]
    assert not any(cell.startswith("-0") and float(cell) == 0 for cell in cells)
    values = np.asarray(cells, dtype=float)
    assert np.all((values == 0) | (np.abs(values) >= 1e-9))
    # the file holds the run log's table to the last bit: coordinates to 1e-9 mm, angles and
    # times to 1e-12 (2.8, not 35 x 0.08 = 2.8000000000000003)
    table = np.asarray(rows[1:], dtype=float)
    with h5py.File(tmp_path / "run.h5") as log:
        np.testing.assert_array_equal(table, log["planner/trajectory"][()])
    np.testing.assert_array_equal(table[:, 2:6], np.round(table[:, 2:6], 9))
    np.testing.assert_array_equal(table[:, [1, 6]], np.round(table[:, [1, 6]], 12))
    assert max(len(row[1]) for row in rows[1:]) < 16  # no round-off tail on an angle


def test_simulate_run_log_has_units_on_every_dataset(tmp_path, scene):
    args = ["simulate", scene, "--out", tmp_path / "run.h5", "--summary", tmp_path / "summary.json"]
    assert invoke(*args).exit_code == 0
    _check_provenance(json.loads((tmp_path / "summary.json").read_text()), args, scene)
    units = _check_run_log(tmp_path / "run.h5", scene, "simulate")
    assert units["steps/friction_force"] == "N" and units["needle/arc"] == "rad"
    assert units["scenario/text"] == "text" and units["steps/newton_iterations"] == "1"


def test_calibrate_needle_records_command_and_input_digests(tmp_path, scene):
    args = _commands(tmp_path, scene)["calibrate needle"]
    result = invoke(*args)
    assert result.exit_code == 0, result.output
    diagnostics = yaml.safe_load((tmp_path / "needle.yaml").read_text())["diagnostics"]
    assert diagnostics["command"][1:] == list(map(str, args))
    assert diagnostics["stitchplan_version"] == stitchplan.__version__
    assert diagnostics["stitchplan_source_sha256"] == stitchplan.source_sha256()
    assert diagnostics["working_directory"] == os.getcwd()
    for name in ("air.csv", "tissue.csv"):
        path = tmp_path / name
        assert diagnostics["input_sha256"][str(path)] == hashlib.sha256(path.read_bytes()).hexdigest()


def test_calibrate_material_records_command_and_input_digests(tmp_path, scene):
    args = _commands(tmp_path, scene)["calibrate material"] + ["--plot-dir", tmp_path / "plots"]
    result = invoke(*args)
    assert result.exit_code == 0, result.output
    diagnostics = yaml.safe_load((tmp_path / "fitted.yaml").read_text())["diagnostics"]
    assert diagnostics["command"][1:] == list(map(str, args))
    assert diagnostics["stitchplan_source_sha256"] == stitchplan.source_sha256()
    assert diagnostics["working_directory"] == os.getcwd()
    for name in ("calib.yaml", "markers.csv"):
        path = tmp_path / name
        assert diagnostics["input_sha256"][str(path)] == hashlib.sha256(path.read_bytes()).hexdigest()
    assert sorted(p.name for p in (tmp_path / "plots").iterdir()) == ["cost_surface.png", "marker_residuals.png"]


@pytest.mark.parametrize("command, inputs, module, fit_name, output", [
    ("calibrate material", ["calib.yaml", "markers.csv"], "stitchplan.calibration", "fit_material", "fitted.yaml"),
    ("calibrate needle", ["air.csv", "tissue.csv"], "stitchplan.calibration.needle_fit", "fit_needle", "needle.yaml"),
])
def test_calibration_records_the_digests_of_the_inputs_as_it_read_them(tmp_path, scene, monkeypatch, command, inputs,
                                                                       module, fit_name, output):
    """A calibration file, marker file or force recording edited while the fit runs (it takes
    seconds to minutes): the record gives the SHA-256 of the bytes the fit read, not of the
    edited files (before, it hashed the files as they were when the report was made)."""
    import importlib

    args = _commands(tmp_path, scene)[command]
    paths = [tmp_path / name for name in inputs]
    read = {str(path): hashlib.sha256(path.read_bytes()).hexdigest() for path in paths}
    fitting = importlib.import_module(module)
    fit = getattr(fitting, fit_name)

    def fit_while_the_inputs_change(*fit_args, **fit_kwargs):
        for path in paths:
            path.write_text(path.read_text() + "# edited during the fit\n")
        return fit(*fit_args, **fit_kwargs)

    monkeypatch.setattr(fitting, fit_name, fit_while_the_inputs_change)
    result = invoke(*args)
    assert result.exit_code == 0, result.output
    assert yaml.safe_load((tmp_path / output).read_text())["diagnostics"]["input_sha256"] == read


def test_calibrate_needle_failing_at_its_yaml_leaves_no_plot(tmp_path, scene, monkeypatch):
    """The old order wrote forces.png, then failed on needle.yaml and left the plot behind."""
    args = _commands(tmp_path, scene)["calibrate needle"] + ["--plot", tmp_path / "forces.png"]
    before = snapshot(tmp_path)
    replace = os.replace

    def failing_replace(source, target):
        if Path(target).name == "needle.yaml":
            raise OSError(13, "Permission denied", str(target))
        return replace(source, target)

    monkeypatch.setattr(os, "replace", failing_replace)
    line = one_error_line(invoke(*args))
    monkeypatch.setattr(os, "replace", replace)
    assert line == f"error: --out: cannot write {tmp_path / 'needle.yaml'}: Permission denied"
    assert snapshot(tmp_path) == before


# --- a full disk, impossible names, standard output -----------------------------------------


class _FileOnAFullDisk:
    """An open file on a full disk: writing fails as the operating system's write does, with
    no file name in the error."""

    def __init__(self, handle):
        self.handle = handle

    def __enter__(self):
        return self

    def __exit__(self, *failure):
        self.handle.close()

    def write(self, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_a_full_disk_under_the_run_log_is_one_line_and_leaves_every_file_as_it_was(tmp_path, scene,
                                                                                  monkeypatch):
    """The HDF5 library used to crash the process (exit 139) when its file could not be
    written, leaving the temporaries behind; the log is built in memory and written like the
    other outputs, so the run ends with one line and nothing of it lands."""
    before = existing_outputs(tmp_path, "run.h5", "summary.json")
    real_open = open

    def open_on_a_full_disk(path, mode="r", *args, **kwargs):
        handle = real_open(path, mode, *args, **kwargs)
        return _FileOnAFullDisk(handle) if ".run.h5." in str(path) else handle

    monkeypatch.setattr(files, "open", open_on_a_full_disk, raising=False)
    line = one_error_line(invoke("simulate", scene, "--out", tmp_path / "run.h5",
                                 "--summary", tmp_path / "summary.json"))
    assert line == f"error: --out: cannot write {tmp_path / 'run.h5'}: No space left on device"
    assert snapshot(tmp_path) == before  # the summary written before it is gone too


def test_the_run_log_built_in_memory_holds_every_dataset_and_attribute(tmp_path):
    large = np.arange(3000.0).reshape(1500, 2)
    files.write_hdf5(tmp_path / "run.h5", {"steps": {"center": large, "step": [0, 1]},
                                           "scenario": {"text": "name: x\n"}},
                     {"command": "simulate", "solver_counts": {"newton": 3}, "note": None},
                     {"center": "mm", "step": "1", "text": "text"})
    with h5py.File(tmp_path / "run.h5") as log:
        np.testing.assert_array_equal(log["steps/center"][()], large)
        assert log["steps/center"].compression == "gzip"  # over 1000 values
        assert log["steps/step"].compression is None and list(log["steps/step"][()]) == [0, 1]
        assert log["scenario/text"].asstr()[()] == "name: x\n"
        assert log.attrs["command"] == "simulate" and log.attrs["note"] == "null"
        assert json.loads(log.attrs["solver_counts"]) == {"newton": 3}
        assert log.attrs["schema_version"] == files.HDF5_SCHEMA_VERSION
        assert {log[name].attrs["units"] for name in ("steps/center", "steps/step", "scenario/text")} == {
            "mm", "1", "text"}


def test_a_name_too_long_or_a_loop_of_links_is_refused_before_any_work(tmp_path, scene):
    (tmp_path / "loop_a").symlink_to("loop_b")
    (tmp_path / "loop_b").symlink_to("loop_a")
    long_name = tmp_path / ("a" * 300 + ".json")
    before = snapshot(tmp_path)
    line = one_error_line(invoke("simulate", scene, "--summary", long_name))
    assert line == (f"error: --summary: got {long_name}, a name of 305 bytes; expected at most 255 "
                    f"(File name too long)")
    line = one_error_line(invoke("simulate", scene, "--summary", tmp_path / "loop_a"))
    assert line == (f"error: --summary: got {tmp_path / 'loop_a'}, a loop of symbolic links; "
                    f"expected a file name (Too many levels of symbolic links)")
    with pytest.raises(InputError) as caught:  # each is named, the good output is not
        OutputSet({"--out": tmp_path / "loop_b" / "run.h5", "--summary": long_name,
                   "--plot": tmp_path / "p.png"}).check()
    assert [line.split(":")[0] for line in caught.value.lines] == ["--out", "--summary"]
    assert snapshot(tmp_path) == before


def test_a_name_near_the_limit_still_gets_its_temporary_beside_it(tmp_path):
    target = tmp_path / ("b" * 250 + ".csv")  # 254 bytes: its own temporary's name must be cut
    with OutputSet({"--export": target}).staged() as staged:
        assert len(staged["--export"].name) <= files.NAME_MAX
        staged["--export"].write_text("x\n")
    assert snapshot(tmp_path) == {target.name: b"x\n"}


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
@pytest.mark.parametrize("args", [["--version"], ["schema"]])
def test_standard_output_that_cannot_be_written_is_one_error_line(args):
    with open("/dev/full", "w") as full:
        run = subprocess.run([sys.executable, "-m", "stitchplan", *args], stdout=full, stderr=subprocess.PIPE,
                             text=True)
    assert run.returncode == 2
    assert run.stderr == "error: cannot write standard output: No space left on device\n"


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
def test_a_command_whose_standard_output_is_full_writes_no_file(tmp_path, scene):
    """The outputs land only once the command's line is out: with standard output full the
    command fails (exit 2) and neither creates nor replaces a file."""
    kept = tmp_path / "probes.csv"
    kept.write_text("earlier\n")
    before = snapshot(tmp_path)
    with open("/dev/full", "w") as full:
        run = subprocess.run([sys.executable, "-m", "stitchplan", "deform", str(scene), "--probes-out", str(kept),
                              "--summary", str(tmp_path / "summary.json")], stdout=full, stderr=subprocess.PIPE,
                             text=True, env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
    assert run.returncode == 2
    assert run.stderr == "error: cannot write standard output: No space left on device\n"
    assert snapshot(tmp_path) == before


def test_a_command_renaming_into_a_folder_another_is_renaming_into_waits_for_it(tmp_path, scene):
    """Two commands writing the same outputs rename, keep or undo them one after the other
    (files.FolderLocks on the outputs' folders), so each set lands whole: between one's renames
    the other's used to land, a mixed set, and one undoing its renames put the old files back
    over the other's. While another process holds the folder the command has its temporaries
    written and renames nothing; once it is released the whole set lands."""
    import time

    out = tmp_path / "out"
    out.mkdir()
    (out / "probes.csv").write_text("earlier\n")
    locks = files.FolderLocks.waiting([out])  # as another command renaming into `out` would hold it
    try:
        process = subprocess.Popen([sys.executable, "-m", "stitchplan", "deform", str(scene), "--probes-out",
                                    str(out / "probes.csv"), "--summary", str(out / "summary.json")],
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                   env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
        while len(list(out.glob(".*.tmp"))) < 2 and process.poll() is None:
            time.sleep(0.05)
        for _ in range(100):  # the command's remaining work is short: it would have renamed by now
            if process.poll() is not None:
                break
            time.sleep(0.05)
        assert process.poll() is None, process.stderr.read()
        assert (out / "probes.csv").read_text() == "earlier\n" and not (out / "summary.json").exists()
    finally:
        locks.release()
    stdout, stderr = process.communicate(timeout=600)
    assert process.returncode == 0, stderr
    assert sorted(p.name for p in out.iterdir()) == ["probes.csv", "summary.json"]
    assert (out / "probes.csv").read_text() != "earlier\n"


@pytest.mark.parametrize("how", ["the file itself", "a link to /dev/stdout"])
def test_the_file_standard_output_goes_to_is_refused_as_an_output(tmp_path, scene, how):
    """`--summary s.json > s.json`, or a link to /dev/stdout with standard output redirected to
    a file: the renamed summary would replace that file, and the command's own line with it."""
    captured = tmp_path / "captured.txt"
    named = captured if how == "the file itself" else tmp_path / "summary.json"
    if named != captured:
        named.symlink_to("/dev/stdout")
    with open(captured, "w") as redirected:
        run = subprocess.run([sys.executable, "-m", "stitchplan", "deform", str(scene), "--summary", str(named)],
                             stdout=redirected, stderr=subprocess.PIPE, text=True,
                             env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
    assert run.returncode == 2
    assert run.stderr == f"error: --summary: got {named}, a process's stream; expected a file name\n"
    assert captured.read_text() == ""


@pytest.mark.parametrize("form", ["separate", "joined"])
def test_an_output_given_as_a_folder_name_is_refused(tmp_path, scene, form):
    """`--export out/` names a folder, though a Path drops the slash: refused, not written as
    the file `out` (nor over an existing file of that name)."""
    (tmp_path / "trajectory.csv").write_text("earlier\n")
    before = snapshot(tmp_path)
    given = f"{tmp_path / 'trajectory.csv'}/"
    args = ["--export", given] if form == "separate" else [f"--export={given}"]
    result = invoke("plan", scene, *args, "--no-verify", "--no-compare")
    assert result.exit_code == 2
    assert result.stderr == f"error: --export: got {given}, a folder name (it ends in /); expected a file name\n"
    assert snapshot(tmp_path) == before


def test_a_reader_that_closes_the_pipe_ends_the_command_quietly():
    process = subprocess.Popen([sys.executable, "-m", "stitchplan", "schema"], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE)
    process.stdout.close()  # before the command has written anything
    _, stderr = process.communicate()
    assert process.returncode == 1 and stderr == b""


def test_an_os_error_of_a_bug_still_shows_its_traceback(monkeypatch):
    """Only a failed write to standard output is an `error:` line; another OSError is a bug."""
    from stitchplan.cli.group import exit_code

    class FullStream(io.StringIO):
        def write(self, text):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def bug():
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(sys, "stdout", FullStream())
    with pytest.raises(OSError):
        exit_code(bug)
    assert exit_code(lambda: print("lost")) == 2
    assert isinstance(sys.stdout, FullStream)  # put back after the run


def test_a_scenario_read_from_a_pipe_records_the_checksum_of_what_was_parsed(tmp_path, scene):
    """The pipe is read once: the summary's scenario_sha256 is that of the bytes parsed, not
    of a second, empty read."""
    import threading

    fifo = tmp_path / "scene.fifo"
    os.mkfifo(fifo)
    writer = threading.Thread(target=fifo.write_bytes, args=(scene.read_bytes(),))
    writer.start()
    summary = tmp_path / "summary.json"
    result = invoke("deform", fifo, "--summary", summary)
    writer.join()
    assert result.exit_code == 0, result.output
    record = json.loads(summary.read_text())
    assert record["scenario_sha256"] == hashlib.sha256(scene.read_bytes()).hexdigest()


def test_json_outputs_are_strict_json_with_null_for_numbers_that_are_not_finite(tmp_path):
    path = tmp_path / "summary.json"
    files.write_json(path, {"a": float("nan"), "b": [1.0, float("inf")], "c": np.array([np.nan, 2.0]),
                            "d": {"e": np.float64(-np.inf)}, "f": 3})

    def refuse(constant):
        raise ValueError(constant)

    assert json.loads(path.read_text(), parse_constant=refuse) == {"a": None, "b": [1.0, None], "c": [None, 2.0],
                                                                     "d": {"e": None}, "f": 3}


def test_a_csv_writes_a_negative_zero_as_zero(tmp_path):
    """A reaction of -0.0 N (a sign of rounding, not a direction) reads as 0 in the CSV;
    the full-precision path keeps every bit (a trajectory replays to the last bit)."""
    path = tmp_path / "reactions.csv"
    files.write_csv(path, ["segment", "fx", "fy"], [[0, -1.0, -0.0], [1, -0.0, 2.5]])
    assert path.read_text() == "segment,fx,fy\n0,-1,0\n1,0,2.5\n"
    files.write_csv(path, ["x"], [[-0.0]], precision=None)
    assert path.read_text() == "x\n-0\n"


def test_a_datasets_units_are_looked_up_by_its_group_first(tmp_path):
    """The run log's `step` datasets: the needle's step is an angle (rad), a step number
    under `steps/` or `events/` is a count ("1"); the group's own entry wins over the name's."""
    from stitchplan.io.reports import HDF5_UNITS

    groups = {"needle": {"step": 0.08}, "steps": {"step": [0, 1], "rotation": [0.0, 0.08]},
              "events": {"step": [1], "angle_rad": [0.08]}}
    files.write_hdf5(tmp_path / "run.h5", groups, {}, HDF5_UNITS)
    with h5py.File(tmp_path / "run.h5") as log:
        units = {f"{group}/{name}": log[group][name].attrs["units"] for group, data in groups.items() for name in data}
    assert units == {"needle/step": "rad", "steps/step": "1", "steps/rotation": "rad", "events/step": "1",
                     "events/angle_rad": "rad"}
