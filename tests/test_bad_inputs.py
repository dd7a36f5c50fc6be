"""Every bad input refused up front: exit code 2, one `error:` line per problem naming the file
and the field (or the option), the value received and what was expected, and no output file.

Each case runs the real command (typer's CliRunner) on small files in tmp_path and is refused
before any model is built: the whole module runs in a few seconds. Also here: the resource
guard's estimates against what the model builds, the exported trajectories of the shipped
scenes replaying through the centre-path checks, and the auto discretization refusing an
accuracy its particle limit cannot reach.
"""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from stitchplan.cli import app

REPOSITORY = Path(__file__).resolve().parents[1]
PHANTOM = {"model": "saint-venant-kirchhoff", "lame_lambda": 0.189151, "lame_mu": 0.147688}
# 40 x 20 mm block clamped on the right, SH needle (r 8.88 mm) entering (0, 12) cw in 0.2 rad
# steps (10 until the tip exits), a force on the left edge: every command accepts it as it stands
BASE = {
    "name": "small",
    "tissue": {"size": [40.0, 20.0], "thickness": 10.0, "material": dict(PHANTOM), "clamped": ["right"]},
    "discretization": {"spacing": 5.0},
    "needle": {"radius": 8.88, "entry": [0.0, 12.0], "turn": "cw", "step": 0.2, "friction": 0.0602,
               "cutting_force": 0.7},
    "loads": [{"segment": [[0.0, 5.0], [0.0, 15.0]], "force": [-1.0, 0.5]}],
    "probes": [[10.0, 10.0]],
}
OUTPUTS = {  # output options of each command, all in tmp_path
    "deform": ["--probes-out", "probes.csv", "--reactions-out", "reactions.csv", "--summary", "summary.json"],
    "simulate": ["--summary", "summary.json", "--out", "run.h5"],
    "plan": ["--export", "trajectory.csv", "--summary", "summary.json"],
    "study": [],
}


def invoke(folder: Path, *args: str):
    """Run `stitchplan ARGS` with paths relative to `folder` (outputs land there)."""
    return CliRunner().invoke(app, [str(folder / a) if _is_file(a) else a for a in args])


def _is_file(arg: str) -> bool:
    return arg.endswith((".yaml", ".csv", ".json", ".h5", ".png"))


def error_lines(result) -> list[str]:
    """The error lines of a refused command: exit 2, nothing on stdout, only `error:` lines."""
    assert result.exit_code == 2, result.output
    assert result.stdout == ""
    assert "Traceback" not in result.output
    lines = result.stderr.splitlines()
    assert lines and all(line.startswith("error: ") for line in lines), result.stderr
    return lines


def assert_refused(result, folder: Path, inputs: set[str], expected: list[list[str]]) -> None:
    """One line per problem, each with its fragments (file, field, value, expectation), and
    no file besides the inputs."""
    lines = error_lines(result)
    assert len(lines) == len(expected), lines
    for line, fragments in zip(lines, expected):
        for fragment in fragments:
            assert fragment in line, (fragment, line)
    assert {p.name for p in folder.iterdir()} == inputs


def scene(**changes) -> dict:
    """BASE with nested keys replaced: scene(needle__radius=-1); a value None deletes the key."""
    raw = copy.deepcopy(BASE)
    for path, value in changes.items():
        *parents, key = path.split("__")
        block = raw
        for parent in parents:
            block = block[parent]
        if value is None:
            del block[key]
        else:
            block[key] = value
    return raw


def write_scene(folder: Path, raw: dict | str | bytes, name: str = "scene.yaml") -> Path:
    path = folder / name
    if isinstance(raw, bytes):
        path.write_bytes(raw)
    else:
        path.write_text(raw if isinstance(raw, str) else yaml.safe_dump(raw, sort_keys=False))
    return path


# --- the scenario file ----------------------------------------------------------------------------

CLAMPED_ALL = ["left", "right", "bottom", "top"]
RIGHT_SEGMENT = [[40.0, 5.0], [40.0, 15.0]]
TEXT = yaml.safe_dump(BASE, sort_keys=False)

SCENARIO_CASES = {
    # what the config refused already
    "missing key": ("deform", scene(tissue__thickness=None), [["scene.yaml: tissue.thickness: missing"]]),
    "unknown key": ("deform", scene(tissue__colour="red"), [["scene.yaml: tissue: unknown key 'colour'"]]),
    "negative radius": ("simulate", scene(needle__radius=-1.0),
                        [["scene.yaml: needle.radius: got -1.0, expected a positive number (mm)"]]),
    "two problems, two lines": ("simulate", scene(needle__radius=-1.0, tissue__colour="red"),
                                [["tissue: unknown key 'colour'"], ["needle.radius: got -1.0"]]),
    # one misspelt key, one line (it said too that the key it is close to was missing, or that
    # the load gave neither force nor displacement)
    "a misspelt load key": ("deform", scene(loads=[{"segment": [[0.0, 5.0], [0.0, 15.0]], "forces": [-1.0, 0.5]}]),
                            [[("scene.yaml: loads[0]: unknown key 'forces', expected one of: segment, force, "
                               "displacement (did you mean 'force'? loads[0] gives neither 'force' nor "
                               "'displacement')")]]),
    "a misspelt block": ("deform", {"tissue2" if k == "tissue" else k: v for k, v in scene().items()},
                         [["scene.yaml: scenario: unknown key 'tissue2', expected one of: name, tissue,",
                           "(did you mean 'tissue'? tissue is missing)"]]),
    "a misspelt key of a block": ("simulate", scene(needle__radius=None, needle__radis=8.88),
                                  [["scene.yaml: needle: unknown key 'radis'",
                                    "(did you mean 'radius'? needle.radius is missing)"]]),
    "a misspelt size": ("deform", scene(tissue__size=None, tissue__sise=[40.0, 20.0]),
                        [["scene.yaml: tissue: unknown key 'sise'",
                          "(did you mean 'size'? tissue gives neither 'size' nor 'outline')"]]),
    # a block given a wrong value beside a stray key close to its name: each needs mending
    "a bad block beside a stray key": ("simulate", {**scene(needle=5), "needleX": BASE["needle"]},
                                       [["scene.yaml: needle: got 5, expected a mapping"],
                                        ["scene.yaml: scenario: unknown key 'needleX'", "(did you mean 'needle'?)"]]),
    "two misspelt keys, two lines": ("simulate", scene(needle__radius=None, needle__radis=8.88,
                                                       loads=[{"segment": [[0.0, 5.0], [0.0, 15.0]],
                                                               "displacment": [1.0, 0.0]}]),
                                     [["needle: unknown key 'radis'", "needle.radius is missing)"],
                                      ["loads[0]: unknown key 'displacment'",
                                       "(did you mean 'displacement'? loads[0] gives neither 'force' nor"]]),
    "entry off the boundary": ("simulate", scene(needle__entry=[5.0, 12.0]),
                               [["scene.yaml: needle.entry: got [5.0, 12.0]", "on the boundary"]]),
    "needle never leaves": ("plan", scene(needle__arc=0.5),
                            [["scene.yaml: needle: the 8.88 mm needle", "expected an exit within its arc"]]),
    "duplicate YAML key": ("deform", TEXT + "name: again\n", [["scene.yaml: line", "duplicate key 'name'"]]),
    "a YAML merge key": ("deform", TEXT.replace("  thickness: 10.0\n", "  <<: {thickness: 0.01}\n  thickness: 10.0\n"),
                         [["scene.yaml: line 6: merge key '<<' in tissue (YAML 1.1; files are read as YAML 1.2",
                           "expected the keys written out in this mapping"]]),
    "entry 0.01 mm off the boundary": ("deform", scene(needle__entry=[0.01, 12.0]),
                                       [["scene.yaml: needle.entry: got [0.01, 12.0], expected a point on the boundary "
                                         "of the 40 x 20 mm tissue or within 0.001 mm of it; the nearest is [0, 12], "
                                         "0.01 mm away"]]),
    "entry typed next to a corner": ("simulate", scene(needle__entry=[0.0004, 19.9996]),
                                     [["scene.yaml: needle.entry: got [0.0004, 19.9996], 0.000566 mm from the corner "
                                       "[0, 20], expected a point inside one edge"]]),
    "alias bomb": ("deform", "a: &a [x, x, x, x, x, x, x, x, x, x]\n"
                   + "".join(f"{c}: &{c} [*{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}]\n"
                             for p, c in zip("abcde", "bcdef")), [["scene.yaml: line", "YAML alias"]]),
    "binary file": ("simulate", b"\x89PNG\r\n\x1a\n\x00\xff\xfe", [["scene.yaml: not UTF-8 text"]]),
    "lists nested 500 deep": ("deform", "name: " + "[" * 500 + "]" * 500 + "\n",
                              [["scene.yaml: line 1: nesting too deep (more than 100 levels"]]),
    "a key true": ("deform", TEXT + "true: x\n", [["scene.yaml: scenario: unknown key true, expected one of: name"]]),
    "control characters in the name": ("simulate", scene(name="\x00\u202e \u00e9vil\nline"),
                                       [["scene.yaml: name: got '\\x00\\u202e \u00e9vil\\nline', expected a "
                                         "one-line string without control characters (U+0000 at character 1)"]]),
    "a tab in the name": ("simulate", scene(name="a\tb"),
                          [["scene.yaml: name: got 'a\\tb'", "(U+0009 at character 2)"]]),
    # the robot block within the bounds of --base-transform and --angular-speed
    "a robot base 10^9 mm away": ("plan", scene(robot={"base_transform": {"rotation_deg": 10,
                                                                          "translation": [1e9, 0]}}),
                                  [["scene.yaml: robot.base_transform.translation[0]: got 1000000000.0, expected a "
                                    "number between -10000 and 10000 (mm; a base more than 10 m"]]),
    "a robot base turned 1000 deg": ("plan", scene(robot={"base_transform": {"rotation_deg": 1000,
                                                                             "translation": [0, 0]}}),
                                     [["scene.yaml: robot.base_transform.rotation_deg: got 1000, expected a number "
                                       "between -360 and 360 (deg)"]]),
    **{f"angular speed {speed:g}": ("plan", scene(robot={"angular_speed": speed}),
                                    [[f"scene.yaml: robot.angular_speed: got {speed!r}, expected a positive number of "
                                      "at least 1e-06 (rad/s"]])
       for speed in (1e-9, 1e-300)},
    # its step in under a nanosecond: every time_s after row 0 was written 0, refused on replay
    "angular speed 1e12": ("plan", scene(robot={"angular_speed": 1e12}),
                           [["scene.yaml: robot.angular_speed: got 1000000000000.0, expected a speed of at most "
                             "2e+08 rad/s (the needle's step of 0.2 rad in at least 1e-09 s"]]),
    # magnitudes that are unit mistakes
    "a force of 1e300 N": ("deform", scene(loads=[{"segment": [[0.0, 5.0], [0.0, 15.0]], "force": [-1e300, 0.5]}]),
                           [["scene.yaml: loads[0].force[0]: got -1e+300, expected a number between -1e+06 and "
                             "1e+06 (N"]]),
    # ran into the first load step (det F = -6e296) and failed there naming no field, exit 1
    "a displacement of 1e300 mm": ("deform", scene(loads=[{"segment": [[0.0, 5.0], [0.0, 15.0]],
                                                           "displacement": [1e300, 0.0]}]),
                                   [[("scene.yaml: loads[0].displacement[0]: got 1e+300, expected a number between "
                                      "-10000 and 10000 (mm; a larger displacement is a unit mistake)")]]),
    **{f"a slab {thickness:g} mm thick": ("deform", scene(tissue__thickness=thickness),
                                          [[f"scene.yaml: tissue.thickness: got {thickness!r}, expected a number "
                                            "between 0.001 and 10000 (mm; a thinner or thicker slab is a unit "
                                            "mistake)"]])
       for thickness in (1e300, 1e-300)},
    "a cutting force of 1e7 N": ("simulate", scene(needle__cutting_force=1e7),
                                 [["scene.yaml: needle.cutting_force: got 10000000.0, expected a number between 0 and "
                                   "1e+06 (N; a larger force at the needle's tip is a unit mistake)"]]),
    "a friction of 1e7 N/mm": ("plan", scene(needle__friction=1e7),
                               [["scene.yaml: needle.friction: got 10000000.0, expected a number between 0 and 1e+06 "
                                 "(N/mm; a larger force on each millimetre of needle is a unit mistake)"]]),
    # lengths and points of a scene: the geometry overflowed at 1e300 mm (a traceback), coincided
    # at 1e-20 mm (NaN in the message of another field) and moved points 40 mm "onto" a 1e8 mm edge
    "a needle radius of 1e300 mm": ("simulate", scene(needle__radius=1e300),
                                    [[("scene.yaml: needle.radius: got 1e+300, expected a number between 0.05 and "
                                       "1000 (mm; a suture needle's radius is about 1-40 mm")]]),
    # refused before only by the spacing check ("refine it"), and run to 0 steps without it
    **{f"a needle radius of {radius:g} mm": ("simulate", scene(needle__radius=radius),
                                             [[(f"scene.yaml: needle.radius: got {radius!r}, expected a number "
                                                "between 0.05 and 1000 (mm; a suture needle's radius is about 1-40 "
                                                "mm: a smaller or larger one is a unit mistake, such as metres "
                                                "written for mm)")]])
       for radius in (1e-300, 0.00888)},
    **{f"a tissue {width:g} mm wide": ("deform", scene(tissue__size=[width, 20.0]),
                                       [[f"scene.yaml: tissue.size[0]: got {width!r}, expected a positive number of "
                                         "at most 10000 (mm; a tissue reaching beyond 10000 mm is a unit mistake)"]])
       for width in (1e300, 1e8)},
    "an outline vertex at 1e300 mm": ("deform", scene(tissue__size=None, tissue__outline=[[0.0, 0.0], [1e300, 0.0],
                                                                                         [40.0, 20.0], [0.0, 20.0]]),
                                      [["scene.yaml: tissue.outline[1][0]: got 1e+300, expected a number between "
                                        "-10000 and 10000 (mm; a tissue reaching beyond 10000 mm is a unit mistake)"]]),
    "a hole of radius 1e-20 mm": ("deform", scene(tissue__holes=[{"circle": {"center": [20.0, 10.0], "radius": 1e-20}}]),
                                  [["scene.yaml: tissue.holes[0].circle.radius: got 1e-20, expected a number between "
                                    "1e-06 and 10000 (mm; a hole below a nanometre"]]),
    "a cutting edge longer than the needle": ("simulate", scene(needle__cutting_length=1000),
                                              [["scene.yaml: needle.cutting_length: got 1000 mm, expected at most "
                                                "the needle's length 27.9 mm (radius 8.88 mm x arc 3.142 rad)"]]),
    # loads against clamps and each other
    "force on a clamped edge": ("deform", scene(loads=BASE["loads"] + [{"segment": RIGHT_SEGMENT, "force": [1.0, 0.0]}]),
                                [["scene.yaml: loads[1].segment: got [[40.0, 5.0], [40.0, 15.0]]",
                                  "expected a segment off the clamped edges (the right edge is clamped"]]),
    "displacement on a clamped edge": ("deform", scene(loads=BASE["loads"] + [{"segment": RIGHT_SEGMENT,
                                                                               "displacement": [1.0, 0.0]}]),
                                       [["scene.yaml: loads[1].segment", "off the clamped edges"]]),
    "every edge clamped, force load": ("deform", scene(tissue__clamped=CLAMPED_ALL),
                                       [["scene.yaml: loads[0].segment", "the left edge is clamped"]]),
    "overlapping segments": ("deform", scene(loads=BASE["loads"] + [{"segment": [[0.0, 12.0], [0.0, 18.0]],
                                                                     "displacement": [1.0, 0.0]}]),
                             [["scene.yaml: loads[1].segment: got [[0.0, 12.0], [0.0, 18.0]]",
                               "sharing at most an end point with loads[0].segment", "share 3 mm"]]),
    # a slab nothing holds, for every command that solves
    **{f"nothing holds the slab ({command})": (command, scene(tissue__clamped=[]),
                                               [["scene.yaml: tissue.clamped: got [], expected at least one",
                                                 "clamped edge or a displacement load"]])
       for command in ("deform", "simulate", "plan")},
    "deform without loads": ("deform", scene(loads=None),
                             [["scene.yaml: loads: got none, expected at least one load"]]),
    # a needle without friction and cutting force (both default to 0) left the tissue at rest
    # and reported a 0.0000 mm exit error, planned and unplanned
    **{f"a needle without loads ({command})": (command, scene(needle__friction=None, needle__cutting_force=None,
                                                                     loads=None),
                                               [["scene.yaml: needle: got friction 0 N/mm and cutting_force 0 N",
                                                 f"expected a positive friction or cutting_force for {command}"]])
       for command in ("simulate", "plan")},
    # resources
    "accuracy no model reaches": ("simulate", scene(discretization={"accuracy": 1e-9}),
                                  [["scene.yaml: discretization.accuracy: got 1e-09, expected a number >= 0.001"]]),
    "three million needle steps": ("simulate", scene(needle__step=1e-6),
                                   [["scene.yaml: needle.step: got 1e-06 rad", "at most 2000 needle steps",
                                     "--no-resource-check"]]),
}


@pytest.mark.parametrize("case", list(SCENARIO_CASES))
def test_a_bad_scenario_is_refused_up_front(tmp_path, case):
    command, raw, expected = SCENARIO_CASES[case]
    write_scene(tmp_path, raw)
    result = invoke(tmp_path, command, "scene.yaml", *OUTPUTS[command])
    assert_refused(result, tmp_path, {"scene.yaml"}, expected)


# --- points typed by hand on a slanted edge ----------------------------------------------------------

# a block whose top edge slants from (40, 20) to (0, 30), on the line x + 4 y = 120: points typed
# on it to four decimals lie 2.4e-5 mm off it, and were refused
SLANT = {"tissue": {"outline": [[0, 0], [40, 0], [40, 20], [0, 30]], "thickness": 10.0, "material": dict(PHANTOM),
                    "clamped": [{"segment": [[0, 0], [40, 0]]}]},
         "needle": {"radius": 5.0, "entry": [13.3333, 26.6667], "turn": "cw", "step": 0.1, "friction": 0.0602,
                    "cutting_force": 0.7},
         "loads": [{"segment": [[33.3333, 21.6667], [26.6667, 23.3333]], "force": [0.0, -1.0]}],
         "probes": [[40.0004, 10.0], [20.0, 10.0]]}


def off_slant(point) -> float:
    return float((point[0] + 4.0 * point[1] - 120.0) / math.sqrt(17.0))


def test_points_typed_on_a_slanted_edge_run_from_the_boundary(tmp_path):
    """deform and simulate run with the typed points moved onto the edge: the needle's centre
    lies on the edge's tangent line through the entry, the edge itself (2.4e-5 mm off it from
    the entry as typed). The probe typed 0.4 um outside moved more than the digits' rounding:
    a warning says so; the others moved within it (shown with -v only)."""
    write_scene(tmp_path, SLANT)
    result = invoke(tmp_path, "deform", "scene.yaml", *OUTPUTS["deform"])
    assert result.exit_code == 0, result.output
    assert [line for line in result.stderr.splitlines() if "off the boundary" in line] == [
        f"warning: {tmp_path / 'scene.yaml'}: probes[0]: [40.0004, 10.0] lies 0.0004 mm off the boundary of "
        "the polygon tissue (4 vertices); the run uses [40, 10] on it (more than the rounding of the digits given)"]
    probes = np.loadtxt(tmp_path / "probes.csv", delimiter=",", skiprows=1)
    assert probes[0, :2].tolist() == [40.0, 10.0]
    result = invoke(tmp_path, "simulate", "scene.yaml", "--summary", "summary.json", "--no-estimate", "-v")
    assert result.exit_code == 0, result.output
    assert "needle.entry: [13.3333, 26.6667] lies 2.43e-05 mm off the boundary" in result.stderr
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert abs(off_slant(summary["needle_center_at_entry"])) < 1e-9


def test_an_entry_typed_on_a_clamped_slanted_edge_is_refused_as_on_the_clamp(tmp_path):
    """The entry moved onto the edge meets the clamp typed on the same edge: refused as before
    for points exactly on a clamp, not left 2.4e-5 mm beside it."""
    raw = copy.deepcopy(SLANT)
    raw["tissue"]["clamped"].append({"segment": [[40.0, 20.0], [6.6667, 28.3333]]})
    del raw["loads"], raw["probes"]
    write_scene(tmp_path, raw)
    result = invoke(tmp_path, "simulate", "scene.yaml", *OUTPUTS["simulate"])
    [line] = error_lines(result)
    assert "scene.yaml: needle.entry: got [13.3332" in line and "on a clamped segment of the boundary" in line
    assert {p.name for p in tmp_path.iterdir()} == {"scene.yaml"}


OPTION_CASES = {
    "spacing 0.1": ("deform", ["--spacing", "0.1"],
                                          [["--spacing: got 0.1 mm",
                                            "at most 50000 particles", "deform: 80721 particles", "--max-particles"]]),
    "spacing 0.01": ("deform", ["--spacing", "0.01"], [["--spacing: got 0.01 mm", "about 8006001 particles"]]),
    "dilation 1e6": ("deform", ["--dilation", "1e6"],
                     [["--dilation: got 1e+06, expected at most 10"]]),
    "max particles below the model": ("simulate", ["--max-particles", "20"],
                                      [["discretization.spacing: got 5 mm", "at most 20 particles"]]),
    "max particles not positive": ("deform", ["--max-particles", "0"], [["--max-particles: got 0"]]),
    "plot step beyond the run": ("simulate", ["--plot", "run.png", "--plot-steps", "3,99"],
                                 [["--plot-steps: got 99, expected steps between 0 (the entry) and 9"]]),
    "negative plot step": ("simulate", ["--plot", "run.png", "--plot-steps", "-1"],
                           [["--plot-steps: got -1", "expected steps between"]]),
    "an empty plot step": ("simulate", ["--plot", "run.png", "--plot-steps", "3,,5"],
                           [["--plot-steps: got '3,,5', expected comma-separated step numbers"]]),
    "plot steps without a plot": ("simulate", ["--plot-steps", "3"],
                                  [["--plot-steps: got 3, expected it only with --plot PNG"]]),
    "a plot not named .png": ("plan", ["--plot", "plan.pdf"],
                              [["--plot: got plan.pdf, expected a file name ending in .png"]]),
    # every output named for another format, each on its line (given after OUTPUTS: the last counts)
    "outputs named for other formats": ("deform", ["--summary", "s.h5", "--probes-out", "p.yaml", "--plot", "x.svg"],
                                        [["--probes-out: got", "p.yaml, a YAML file name; expected a CSV file name"],
                                         ["--summary: got", "s.h5, an HDF5 file name; expected a JSON file name"],
                                         ["--plot: got", "x.svg, expected a file name ending in .png"]]),
    "an empty plot name": ("deform", ["--plot", ""], [["--plot: got an empty path, expected a file name"]]),
    "an empty centre path": ("simulate", ["--center-path", ""],
                             [["--center-path: got an empty path, expected a file name"]]),
    "an empty uncertainty file": ("plan", ["--uncertainty", ""],
                                  [["--uncertainty: got an empty path, expected a file name"]]),
    "a missing uncertainty file": ("plan", ["--uncertainty", "absent.yaml"],
                                   [["--uncertainty: ", "absent.yaml: cannot be read (No such file or directory)"]]),
    "an empty study folder": ("study", ["--out", ""], [["--out: got an empty path, expected a folder name"]]),
    "a needle turning 1e12 rad/s": ("plan", ["--angular-speed", "1e12"],
                                    [["--angular-speed: got 1000000000000.0, expected a speed of at most 2e+08 rad/s "
                                      "(the needle's step of 0.2 rad in at least 1e-09 s"]]),
}


@pytest.mark.parametrize("case", list(OPTION_CASES))
def test_a_bad_option_is_refused_up_front(tmp_path, case):
    command, options, expected = OPTION_CASES[case]
    write_scene(tmp_path, BASE)
    result = invoke(tmp_path, command, "scene.yaml", *OUTPUTS[command], *options)
    assert_refused(result, tmp_path, {"scene.yaml"}, expected)


def test_a_study_too_large_for_the_machine_is_refused_before_its_first_run(tmp_path):
    """Each run of the sweep past the limits is one line naming the study field that set its
    spacing (here the 0.05 mm run and the reference at 0.04 mm), before any run starts and
    before the output folder exists."""
    raw = scene(loads=None, probes=None)
    raw["study"] = {"spacing": [4.0, 0.05], "families": [{"name": "uniform"}], "reference": {"spacing": [0.04]}}
    write_scene(tmp_path, raw)
    result = CliRunner().invoke(app, ["study", str(tmp_path / "scene.yaml"), "--out", str(tmp_path / "out")])
    assert_refused(result, tmp_path, {"scene.yaml"},
                   [["scene.yaml: study.spacing: got 0.05 mm", "study run 'uniform h=0.05 mm'"],
                    ["scene.yaml: study.reference.spacing: got 0.04 mm", "study run 'reference h=0.04 mm'"]])


# --- centre paths (simulate --center-path) ------------------------------------------------------


def center_rows(count: int, shift=(0.0, 0.0), first=(0.0, 3.12)) -> str:
    """A centre path of `count` rows: row 0 at `first` (the small scene's entry centre by
    default), the others at the entry centre plus `shift`."""
    rows = ["step,center_x_mm,center_y_mm", f"0,{first[0]:g},{first[1]:g}"]
    rows += [f"{step},{shift[0]:g},{3.12 + shift[1]:g}" for step in range(1, count)]
    return "\n".join(rows) + "\n"


PATH_CASES = {
    "nan": ("step,center_x_mm,center_y_mm\n0,0,3.12\n1,nan,3.12\n",
            [["path.csv: line 3, center_x_mm: got 'nan', expected a finite number"]]),
    "wrong columns": ("step,x,y\n0,0,3.12\n", [["path.csv: columns ['step', 'x', 'y'] lack"]]),
    "steps not 0, 1, 2": ("step,center_x_mm,center_y_mm\n1,0,3.12\n2,0,3.12\n",
                          [["path.csv: line 2, step: got 1, expected 0"]]),
    "200 rows for a 10-step run": (center_rows(200), [["path.csv: rows: got 200, expected 8 to 14"]]),
    "too few rows": (center_rows(3), [["path.csv: rows: got 3, expected 8 to 14"]]),
    "centres 500 mm away": (center_rows(11, shift=(500.0, 0.0)),
                            [["path.csv: line 3, center_x_mm, center_y_mm: got [500, 3.12]",
                              "from the entry centre [0, 3.12]; expected at most 3 needle radii"]]),
    "row 0 not at the entry centre": (center_rows(11, first=(1.0, 3.12)),
                                      [["path.csv: line 2, center_x_mm, center_y_mm: got [1, 3.12]",
                                        "expected the needle centre at entry [0, 3.12]"]]),
    "binary": (b"\x00\xff\xfe\x89", [["path.csv: not a text file"]]),
    # a norm's squares overflowed: "inf mm", and numpy's overflow warning on stderr besides
    "a centre at 1e300 mm": (center_rows(11, shift=(1e300, 0.0)),
                             [["path.csv: line 3, center_x_mm, center_y_mm: got [1e+300, 3.12], 1e+300 mm from the "
                               "entry centre [0, 3.12]"]]),
    "row 0 at 1e300 mm": (center_rows(11, first=(1e300, 3.12)),
                          [["path.csv: line 2, center_x_mm, center_y_mm: got [1e+300, 3.12], expected the needle "
                            "centre at entry"]]),
    "a tip at 1e300 mm": ("step,center_x_mm,center_y_mm,tip_x_mm,tip_y_mm\n0,0,3.12,0,12\n"
                          + "".join(f"{step},0,3.12,1e300,12\n" for step in range(1, 11)),
                          [["path.csv: line 3, tip_x_mm, tip_y_mm: got [1e+300, 12]", "(1e+300 mm off"]]),
}


@pytest.mark.filterwarnings("error")  # a warning of the numerics is a line on stderr besides the error's
@pytest.mark.parametrize("case", list(PATH_CASES))
def test_a_bad_center_path_is_refused_up_front(tmp_path, case):
    text, expected = PATH_CASES[case]
    write_scene(tmp_path, BASE)
    write_scene(tmp_path, text, "path.csv")
    result = invoke(tmp_path, "simulate", "scene.yaml", "--center-path", "path.csv", *OUTPUTS["simulate"])
    assert_refused(result, tmp_path, {"scene.yaml", "path.csv"}, expected)


def test_the_shipped_trajectories_fit_their_needles():
    """Every trajectory `plan` exported for a shipped scene (N + 2 rows) passes the checks a
    replay makes, and sits inside the row range with room on both sides."""
    from stitchplan.config import load_scenario
    from stitchplan.io.readers import expected_rows, read_center_path
    from stitchplan.needle.geometry import scenario_needle

    paths = sorted((REPOSITORY / "sample_runs").glob("*/trajectory.csv"))
    assert paths
    for path in paths:
        geometry = scenario_needle(load_scenario(REPOSITORY / "configs" / f"{path.parent.name}.yaml"))
        centers = read_center_path(path, geometry)
        _, fewest, most = expected_rows(geometry)
        assert fewest < len(centers) < most
        np.testing.assert_allclose(centers[0], geometry.center, atol=1e-6)


# --- calibration inputs ---------------------------------------------------------------------------


def recording(angles: np.ndarray, forces: np.ndarray) -> str:
    return "angle_rad,force_N\n" + "".join(f"{a:.6g},{f!s}\n" for a, f in zip(angles, forces))


ANGLES = np.linspace(0.0, 2.0, 12)
AIR = recording(ANGLES, 0.12 + 0.035 * ANGLES)
RECORDING_CASES = {
    "forces of 1e308 N": (recording(ANGLES, np.full(12, 1e308)),
                          [["--tissue: ", "tissue.csv: line 2, force_N: got 1e+308, expected |force| <= 100 N"]]),
    "a force of a kN": (recording(ANGLES, np.r_[np.full(11, 1.0), 1500.0]),
                        [["tissue.csv: line 13, force_N: got 1500"]]),
    "nan": (recording(ANGLES, ["0.8", "0.9", "nan", *["1.0"] * 9]),
            [["tissue.csv: line 4, force_N: got 'nan', expected a finite number"]]),
    "wrong columns": ("angle,force\n0,1\n", [["tissue.csv: columns: got 'angle,force', expected the columns "
                                             "'angle_rad,force_N' (in any order, no others)"]]),
    "binary": (b"\xff\xfe\x00\x01", [["--tissue: ", "tissue.csv: not a text file; expected a CSV table"]]),
}


@pytest.mark.parametrize("case", list(RECORDING_CASES))
def test_a_bad_force_recording_is_refused(tmp_path, case):
    text, expected = RECORDING_CASES[case]
    write_scene(tmp_path, AIR, "air.csv")
    write_scene(tmp_path, text, "tissue.csv")
    result = invoke(tmp_path, "calibrate", "needle", "--air", "air.csv", "--tissue", "tissue.csv",
                    "--radius", "8.88", "--out", "needle.yaml", "--plot", "forces.png")
    assert_refused(result, tmp_path, {"air.csv", "tissue.csv"}, expected)


LEFT_FORCE = {"segment": [[0.0, 5.0], [0.0, 15.0]], "force": [1.0, 0.0]}


def write_calibration(tmp_path, markers: str, loads=(LEFT_FORCE,), **fit) -> None:
    """calibration.yaml on a 40 x 20 mm slab clamped on the right, one experiment with `loads`
    and the marker table `markers` (markers.csv), lame_lambda and lame_mu searched in
    [0.05, 1] MPa (`fit` adds to the fit block)."""
    calibration = {"tissue": {"size": [40.0, 20.0], "thickness": 10.0, "clamped": ["right"]},
                   "experiments": [{"loads": list(loads), "markers": "markers.csv"}],
                   "fit": {"lame_lambda": [0.05, 1.0], "lame_mu": [0.05, 1.0], **fit}}
    write_scene(tmp_path, calibration, "calibration.yaml")
    write_scene(tmp_path, markers, "markers.csv")


def test_a_marker_file_with_nan_is_refused(tmp_path):
    write_calibration(tmp_path, "x,y,x_def,y_def\n10,10,10.5,10\n20,10,nan,10\n")
    result = invoke(tmp_path, "calibrate", "material", "calibration.yaml", "--out", "fitted.yaml")
    assert_refused(result, tmp_path, {"calibration.yaml", "markers.csv"},
                   [["calibration.yaml: experiments[0].markers: ", "markers.csv: line 3, x_def: got 'nan'"]])


def test_a_calibration_too_fine_for_the_machine_is_refused(tmp_path):
    write_calibration(tmp_path, "x,y,x_def,y_def\n10,10,10.5,10\n20,10,20.2,10\n", grid=3, max_evaluations=4)
    result = invoke(tmp_path, "calibrate", "material", "calibration.yaml", "--out", "fitted.yaml", "--spacing", "0.1")
    assert_refused(result, tmp_path, {"calibration.yaml", "markers.csv"},
                   [["--spacing: got 0.1 mm", "experiments[0]: 80721 particles",
                     "in each of 13 runs"]])


@pytest.mark.parametrize("options, named", [
    ((), "calibration.yaml: discretization: dilation 1 with spacing 5 mm"),
    (("--dilation", "1.0000001"), "--dilation 1.0000001 over {folder}/calibration.yaml: discretization: dilation 1"),
])
def test_a_calibration_whose_model_cannot_be_built_names_the_file_or_the_option(tmp_path, options, named):
    """A dilation that leaves a point covered by too few particles was found as the fit built its
    first model, and its line named neither the calibration file nor the option that set it."""
    write_calibration(tmp_path, "x,y,x_def,y_def\n10,10,10.5,10\n20,10,20.2,10\n", grid=3, max_evaluations=4)
    if not options:
        raw = yaml.safe_load((tmp_path / "calibration.yaml").read_text())
        write_scene(tmp_path, {**raw, "discretization": {"spacing": 5.0, "dilation": 1.0000001}}, "calibration.yaml")
    else:
        options = (*options, "--spacing", "5")
        named = named.replace("--dilation", "--spacing 5 and --dilation")
    result = invoke(tmp_path, "calibrate", "material", "calibration.yaml", "--out", "fitted.yaml", *options)
    assert_refused(result, tmp_path, {"calibration.yaml", "markers.csv"},
                   [[named.format(folder=tmp_path), "gives a singular RK moment matrix"]])


@pytest.mark.parametrize("command", ["deform", "simulate"])
def test_a_discretization_an_option_changed_is_named_with_the_option(tmp_path, command):
    """The model's build refused a dilation given by --dilation as the file's own
    (`scene.yaml: discretization: dilation 1 ...`), naming a field the file may not even hold."""
    write_scene(tmp_path, BASE)
    result = invoke(tmp_path, command, "scene.yaml", *OUTPUTS[command], "--dilation", "1.0000001")
    assert_refused(result, tmp_path, {"scene.yaml"},
                   [[f"--dilation 1.0000001 over {tmp_path}/scene.yaml: discretization: dilation 1 with spacing 5 mm",
                     "gives a singular RK moment matrix"]])


def test_calibration_loads_meet_the_same_checks(tmp_path):
    """A calibration experiment's load on the clamped edge or over another load is refused
    like a scenario's."""
    write_calibration(tmp_path, "x,y,x_def,y_def\n10,10,10.5,10\n20,10,20.2,10\n",
                      loads=(LEFT_FORCE, {"segment": [[0.0, 10.0], [0.0, 20.0]], "force": [1.0, 0.0]},
                             {"segment": RIGHT_SEGMENT, "displacement": [1.0, 0.0]}))
    result = invoke(tmp_path, "calibrate", "material", "calibration.yaml", "--out", "fitted.yaml")
    assert_refused(result, tmp_path, {"calibration.yaml", "markers.csv"},
                   [["experiments[0].loads[1].segment", "share 5 mm"],
                    ["experiments[0].loads[2].segment", "the right edge is clamped"]])


# --- the resource guard ------------------------------------------------------------------------


def test_the_guard_counts_the_particles_the_needle_model_builds():
    """The guard's count (before anything is built) is the model's own: uniform grids, the
    needle-graded arrangement of the tiny needle scene, at two spacings, and a deform scene's
    grid graded toward its load segment's ends; and the estimate used when the graded
    lattice is too large to count lies within 25 % of the count."""
    from dataclasses import replace

    from stitchplan.config import parse_scenario, with_discretization
    from stitchplan.needle.geometry import needle_zone
    from stitchplan.resources.model_size import _graded_estimate, model_size
    from stitchplan.tissue.model import model_for_scenario

    base = parse_scenario(scene(loads=None, probes=None, discretization=None))  # graded default
    for scenario in (base, with_discretization(base, spacing=2.0),
                     replace(base, discretization=base.discretization.replaced(needle_spacing=None))):
        size = model_size(scenario)
        model = model_for_scenario(scenario, needle_zone(scenario))
        assert size.exact and size.particles == model.n_particles
        d = scenario.discretization
        if d.needle_spacing is not None:
            approximate = _graded_estimate(scenario.tissue.size, d.spacing, d.needle_spacing, needle_zone(scenario))
            assert abs(approximate / size.particles - 1) < 0.25
    pulled = parse_scenario(scene(needle=None, discretization={"spacing": 2.0}))  # graded toward the ends
    size, model = model_size(pulled), model_for_scenario(pulled)
    assert size.exact and size.particles == model.n_particles > 21 * 11


def test_the_guard_scales_memory_and_time_with_particles_and_neighbours():
    """Halving the spacing about quadruples the particles and grows the estimated memory and
    time faster still (superlinear fits); dilation 3 costs (36/16)^2 the time of dilation 2
    and 36/16 the memory above the interpreter's; a small machine refuses what a large one
    runs."""
    from stitchplan.config import parse_scenario, with_discretization
    from stitchplan.errors import InputError
    from stitchplan.resources.costs import BASE_MEMORY, estimate
    from stitchplan.resources.guard import check_resources
    from stitchplan.resources.limits import Limits

    base = parse_scenario(scene(loads=None, discretization={"spacing": 2.0}))  # a uniform grid
    coarse, fine = estimate(base, "deform"), estimate(with_discretization(base, spacing=1.0), "deform")
    ratio = fine.size.particles / coarse.size.particles
    assert ratio > 3.5
    assert fine.memory_bytes - BASE_MEMORY > ratio * (coarse.memory_bytes - BASE_MEMORY)
    assert fine.seconds > ratio * coarse.seconds
    wide = estimate(with_discretization(base, dilation=3.0), "deform")
    assert math.isclose(wide.seconds / coarse.seconds, (36 / 16) ** 2)
    assert math.isclose((wide.memory_bytes - BASE_MEMORY) / (coarse.memory_bytes - BASE_MEMORY), 36 / 16)
    check_resources([fine], Limits(), memory=64e9)
    with pytest.raises(InputError, match=r"discretization.spacing: got 1 mm, expected a model within 50% "
                                         r"of the 100 MB of memory available"):
        check_resources([fine], Limits(), memory=100e6)


def test_an_accuracy_beyond_the_particle_limit_is_refused_after_the_first_pair():
    """The auto discretization stops as soon as its first two resolutions show that the finest
    model within the particle limit misses the accuracy, saying what that model reaches."""
    from stitchplan.config import parse_scenario
    from stitchplan.errors import InputError
    from stitchplan.study.auto import Trials, choose_discretization

    scenario = parse_scenario(scene(loads=None, probes=None, needle__step=0.4))
    first = round(scenario.needle.radius / 3.0, 4)
    limit = Trials(scenario).particles(round(first / 2, 4))  # the first pair fits, no finer model
    seen = []
    with pytest.raises(InputError) as error:
        choose_discretization(scenario, accuracy=0.001, max_particles=limit, on_trial=seen.append)
    message = str(error.value)
    assert message.startswith("discretization.accuracy: got 0.001 mm, expected at least ")
    assert f"within {limit} particles" in message and "raise --max-particles" in message
    assert max(run.particles for run in seen) <= limit
    assert {run.spacing for run in seen} <= {first, round(first / 2, 4)}
