"""Centre-path files (`simulate --center-path trajectory.csv`) and the trajectory a robot gets.

The reader takes what `plan --export` writes and refuses, with one line naming the file, the
row and the column, anything else: angles off the scenario's rotation schedule (row k at
k x needle.step), steps out of order, NaN, inf or text that is not a plain number, rows of
another length than the header. Comment and blank lines are skipped, as in the calibration
recordings. The trajectory itself never holds inf or nan, and the robot options that would
make it do so are refused with their accepted range. Most checks call the readers directly
on tiny files; the CLI runs use configs/needle20_entry30.yaml (0.1 rad steps, 22 rows).
"""

from __future__ import annotations

import math
import re
import warnings
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from typer.testing import CliRunner

from stitchplan.cli import app
from stitchplan.cli.options import check_angular_speed, parse_base_transform
from stitchplan.config import Robot, load_scenario
from stitchplan.config.plan_blocks import MAX_BASE_OFFSET_MM, MIN_ANGULAR_SPEED
from stitchplan.decimals import last_digit, parse_number
from stitchplan.errors import InputError
from stitchplan.io.readers import ANGLE_TOLERANCE, read_center_path
from stitchplan.needle.geometry import scenario_needle
from stitchplan.planning.trajectory import exported_centers, to_base_frame, trajectory_table

REPOSITORY = Path(__file__).resolve().parents[1]
SCENE = REPOSITORY / "configs" / "needle20_entry30.yaml"
HEADER = "step,angle_rad,center_x_mm,center_y_mm,tip_x_mm,tip_y_mm"


@pytest.fixture(scope="module")
def geometry():
    """The 20 mm needle of needle20_entry30: centre (0, 10), 0.1 rad steps, 21 expected steps."""
    return scenario_needle(load_scenario(SCENE))


def trajectory_rows(geometry, drift=(0.01, -0.02)) -> list[list[str]]:
    """The cells of the rows `plan --export` writes for this needle (steps 0 .. N+1, angles
    k * step, printed with 9 significant digits), the centre drifting by `drift` mm per step."""
    rows = []
    for k in range(geometry.expected_steps + 1):
        center = geometry.center + k * np.asarray(drift)
        tip = geometry.tip(k * geometry.step, center)
        rows.append([str(k)] + [f"{value:.9g}" for value in (k * geometry.step, *center, *tip)])
    return rows


def write_rows(folder: Path, rows: list[list[str]], header: str = HEADER, name: str = "path.csv") -> Path:
    path = folder / name
    path.write_text("\n".join([header] + [",".join(row) for row in rows]) + "\n")
    return path


def refusal(path: Path, geometry) -> str:
    with pytest.raises(InputError) as caught:
        read_center_path(path, geometry)
    return str(caught.value)


# --- what plan writes is read back --------------------------------------------------------------


def test_an_exported_trajectory_is_read_back(tmp_path, geometry):
    rows = trajectory_rows(geometry)
    centers = read_center_path(write_rows(tmp_path, rows), geometry)
    expected = np.array([[float(row[2]), float(row[3])] for row in rows])
    np.testing.assert_array_equal(centers, expected)


def test_comment_and_blank_lines_are_skipped_and_rows_keep_their_line_numbers(tmp_path, geometry):
    """As in the calibration recordings: '#' lines and blank lines (also ',,,' rows, a
    spreadsheet's blank row) are not data; a bad value is named by its line in the file."""
    rows = trajectory_rows(geometry)
    lines = ["# planned for needle20_entry30", HEADER, ",".join(rows[0]), "", "  # a note", ",,,,,"]
    lines += [",".join(row) for row in rows[1:]]
    path = tmp_path / "path.csv"
    path.write_text("\n".join(lines) + "\n")
    np.testing.assert_array_equal(read_center_path(path, geometry)[1], [float(rows[1][2]), float(rows[1][3])])
    lines[7] = ",".join([rows[2][0], "nan", *rows[2][2:]])  # step 2's angle, on line 8 of the file
    path.write_text("\n".join(lines) + "\n")
    assert refusal(path, geometry) == f"{path}: line 8, angle_rad: got 'nan', expected a finite number"


def test_centres_off_the_needle_are_named_by_their_line(tmp_path, geometry):
    """Row 0 away from the entry centre, or a centre 3 radii away, below a comment line."""
    rows = trajectory_rows(geometry)
    rows[0][2] = "1"
    path = write_rows(tmp_path, rows, "# off the entry\n" + HEADER)
    assert refusal(path, geometry).startswith(f"{path}: line 3, center_x_mm, center_y_mm: got [1, 10], "
                                              "expected the needle centre at entry [0, 10]")
    rows = trajectory_rows(geometry)
    rows[4][2] = "500"
    path = write_rows(tmp_path, rows, "# far away\n" + HEADER)
    assert refusal(path, geometry).startswith(f"{path}: line 7, center_x_mm, center_y_mm: got [500, ")


def test_a_path_of_centres_only_follows_the_scenarios_schedule(tmp_path, geometry):
    """Without angle_rad the replay turns the needle by the scenario's steps (hand-made paths)."""
    rows = [[row[0], row[2], row[3]] for row in trajectory_rows(geometry)]
    centers = read_center_path(write_rows(tmp_path, rows, "step,center_x_mm,center_y_mm"), geometry)
    assert centers.shape == (geometry.expected_steps + 1, 2)


# --- the rotation schedule ------------------------------------------------------------------------


def test_a_path_for_another_needle_step_is_refused(tmp_path, geometry):
    """Rows written for 0.1 rad steps replayed with 0.12 rad steps: the first row differs."""
    path = write_rows(tmp_path, trajectory_rows(geometry))
    line = refusal(path, replace(geometry, step=0.12))
    assert line == f"{path}: line 3, angle_rad: got 0.1, expected 0.12 (step 1 of the needle's 0.12 rad steps)"


def test_tips_that_disagree_with_their_centres_are_refused(tmp_path, geometry):
    """A centre edited without its tip (or the other way round): the row says two things, a
    robot may follow either, so the replay refuses the first such row; the tips as written
    (9 significant digits) pass, and a file without tip columns is not checked for them."""
    rows = trajectory_rows(geometry)
    assert read_center_path(write_rows(tmp_path, rows), geometry).shape == (geometry.expected_steps + 1, 2)
    rows[6][2] = f"{float(rows[6][2]) + 0.05:.9g}"  # the centre moved, its tip not
    line = refusal(write_rows(tmp_path, rows), geometry)
    assert line.startswith(f"{tmp_path / 'path.csv'}: line 8, tip_x_mm, tip_y_mm: got [") and "0.05 mm off" in line
    rows = trajectory_rows(geometry)
    rows[9][4] = "0"
    assert "line 11, tip_x_mm, tip_y_mm: got [0, " in refusal(write_rows(tmp_path, rows), geometry)


def test_tips_printed_with_9_significant_digits_pass_far_from_the_origin(tmp_path, geometry):
    """Beyond 100 mm 9 significant digits keep 6 decimals or fewer: each coordinate is then up to
    5e-7 mm (at 1000 mm, 5e-6 mm) from the value plan computed, and a row's centre and tip
    together up to ~1.4 times that apart from the needle's tip, which is rounding, not an edit;
    a centre moved by 0.01 mm is still refused."""
    far = replace(geometry, center=geometry.center + 1000.0, entry=geometry.entry + 1000.0)
    rows = trajectory_rows(far)
    centers = read_center_path(write_rows(tmp_path, rows), far)
    assert centers.shape == (far.expected_steps + 1, 2)
    rows[6][2] = f"{float(rows[6][2]) + 0.01:.9g}"
    assert "line 8, tip_x_mm, tip_y_mm" in refusal(write_rows(tmp_path, rows), far)


def test_a_trajectory_rounded_to_fewer_decimals_keeps_its_tips(tmp_path, geometry):
    """A file whose centres and tips were all rounded to 6 or 3 decimals (as a robot's toolchain
    may write them) was refused for tips 1.06e-6 mm off their centres' needle: the rounding of
    its finest cell, half a unit in each coordinate of a centre and a tip, is allowed, and a
    centre moved by 0.01 mm is still refused in the 3-decimal file; a file whose cells keep 9
    digits but for a few (zeros dropped, '30' for 30.000000000) stays as strict."""
    for decimals in (6, 3):
        rows = [row[:2] + [f"{float(cell):.{decimals}f}" for cell in row[2:6]] for row in trajectory_rows(geometry)]
        assert read_center_path(write_rows(tmp_path, rows), geometry).shape == (geometry.expected_steps + 1, 2)
    rows[6][2] = f"{float(rows[6][2]) + 0.01:.3f}"
    assert "line 8, tip_x_mm, tip_y_mm" in refusal(write_rows(tmp_path, rows), geometry)
    rows = trajectory_rows(geometry)
    rows[6][4] = f"{float(rows[6][4]):.3f}"  # one tip rounded among 9-digit cells: an edit, not the file's rounding
    assert "line 8, tip_x_mm, tip_y_mm" in refusal(write_rows(tmp_path, rows), geometry)


def test_a_zero_written_with_a_huge_exponent_is_read_as_zero(tmp_path, geometry):
    """'0e400' and '0e' followed by thousands of digits spell 0 (parse_number takes them): the
    unit of their last digit, for the tips' rounding tolerance, is inf rather than an
    OverflowError or int()'s digit limit escaping as a traceback, and the path is read."""
    assert last_digit("0e400") == math.inf and last_digit("0e-" + "9" * 5000) == 0.0
    assert (last_digit("1."), last_digit("-0"), last_digit("+.5e+3"), last_digit(" 1.50 ")) == (1.0, 1.0, 100.0, 0.01)
    for zero in ("0e400", "0e" + "9" * 5000):
        rows = trajectory_rows(geometry)
        assert rows[0][2] == "0"  # the needle's centre at x = 0
        rows[0][2] = zero
        assert read_center_path(write_rows(tmp_path, rows), geometry)[0, 0] == 0.0


def base_rows(geometry, rotation_deg=30.0, translation=(400.0, 120.0), digits=None) -> list[list[str]]:
    """trajectory_rows with the four base-frame columns plan writes with a base transform."""
    robot = Robot(rotation_deg, translation, None, given=True)
    rows = []
    for row in trajectory_rows(geometry):
        points = np.array([[float(row[2]), float(row[3])], [float(row[4]), float(row[5])]])
        base = to_base_frame(points, robot)
        cells = [f"{value:.{digits}g}" if digits else repr(float(np.round(value, 9)))
                 for value in base.ravel()]
        rows.append(row + cells)
    return rows


BASE_HEADER = HEADER + ",base_center_x_mm,base_center_y_mm,base_tip_x_mm,base_tip_y_mm"


def test_base_frame_points_that_disagree_with_the_tissue_frame_are_refused(tmp_path, geometry):
    """With a base transform the robot follows the base-frame columns: a row whose base-frame
    centre or tip is not the same rigid motion of its tissue-frame points as the other rows'
    says two things, and the replay would check a path the robot does not follow. Any
    rotation and offset pass (the transform may be the file's robot block or the options),
    also written with 9 significant digits."""
    for rotation, translation, digits in ((30.0, (400.0, 120.0), None), (-90.0, (-2500.0, 7.5), 9)):
        rows = base_rows(geometry, rotation, translation, digits)
        centers = read_center_path(write_rows(tmp_path, rows, BASE_HEADER), geometry)
        assert centers.shape == (geometry.expected_steps + 1, 2)
    rows = base_rows(geometry)
    rows[6][6] = f"{float(rows[6][6]) + 0.05:.12g}"  # base_center_x_mm of step 6 edited, not its tissue centre
    line = refusal(write_rows(tmp_path, rows, BASE_HEADER), geometry)
    assert line.startswith(f"{tmp_path / 'path.csv'}: line 8, base_center_x_mm, base_center_y_mm: got [")
    assert "0.05 mm off" in line and "rotation 30 deg" in line
    rows = base_rows(geometry)
    rows[10][9] = "0"  # base_tip_y_mm
    assert "line 12, base_tip_x_mm, base_tip_y_mm: got [" in refusal(write_rows(tmp_path, rows, BASE_HEADER), geometry)


def test_times_that_go_back_are_refused(tmp_path, geometry):
    rows = [row + [f"{k * 0.2:.9g}"] for k, row in enumerate(trajectory_rows(geometry))]
    header = HEADER + ",time_s"
    assert read_center_path(write_rows(tmp_path, rows, header), geometry).shape == (geometry.expected_steps + 1, 2)
    rows[7][-1] = "0.2"
    line = refusal(write_rows(tmp_path, rows, header), geometry)
    assert line == (f"{tmp_path / 'path.csv'}: line 9, time_s: got 0.2, expected more than the row before's 1.2 "
                    "(the needle turns forward in time, one step per row)")


def test_doubled_angles_are_refused(tmp_path, geometry):
    rows = [[row[0], f"{2 * float(row[1]):.9g}", *row[2:]] for row in trajectory_rows(geometry)]
    line = refusal(write_rows(tmp_path, rows), geometry)
    assert "line 3, angle_rad: got 0.2, expected 0.1" in line


def test_the_exit_row_carries_the_full_step(tmp_path, geometry):
    """Row N+1 is the step during which the tip leaves; the trajectory gives it (N+1) x step,
    not the rotation at which the tip left, and the reader expects exactly that."""
    rows = trajectory_rows(geometry)
    last = len(rows) - 1
    rows[-1][1] = f"{geometry.exit_rotation:.9g}"  # within the last step: not what plan writes
    line = refusal(write_rows(tmp_path, rows), geometry)
    assert f"line {last + 2}, angle_rad: got {geometry.exit_rotation:.9g}, expected {last * geometry.step:.9g}" in line


def test_the_angle_tolerance_covers_the_printed_digits_and_nothing_more(tmp_path, geometry):
    """An irrational step printed with 9 significant digits is accepted; an angle off by 10
    times the tolerance is not."""
    needle = replace(geometry, step=math.pi / 31)
    rows = trajectory_rows(needle)
    assert read_center_path(write_rows(tmp_path, rows), needle).shape == (needle.expected_steps + 1, 2)
    rows[5][1] = f"{5 * needle.step + 10 * ANGLE_TOLERANCE:.12g}"
    assert "line 7, angle_rad" in refusal(write_rows(tmp_path, rows), needle)


# --- steps, numbers, row lengths ------------------------------------------------------------------


@pytest.mark.parametrize("edit,message", [
    (lambda rows: rows[:5] + rows[6:], "line 7, step: got 6, expected 5 (one row per needle step"),  # a gap
    (lambda rows: rows[:6] + rows[5:], "line 8, step: got 5, expected 6"),  # a repeated row
    (lambda rows: [["1.5", *rows[1][1:]] if k == 1 else row for k, row in enumerate(rows)],
     "line 3, step: got 1.5, expected 1"),
])
def test_a_bad_step_sequence_names_its_first_row(tmp_path, geometry, edit, message):
    line = refusal(write_rows(tmp_path, edit(trajectory_rows(geometry))), geometry)
    assert line.startswith(f"{tmp_path / 'path.csv'}: {message}"), line


@pytest.mark.parametrize("column,text,expected", [
    (1, "nan", "angle_rad: got 'nan', expected a finite number"),
    (4, "NaN", "tip_x_mm: got 'NaN', expected a finite number"),
    (5, "-inf", "tip_y_mm: got '-inf', expected a finite number"),
    (2, "1e999", "center_x_mm: got '1e999', expected a finite number"),
    (0, "1_0", "step: got '1_0', expected a finite number in plain decimals (digits 0-9, like -1.5e-3)"),  # float() would read 10
    (3, "0x10", "center_y_mm: got '0x10', expected a finite number in plain decimals (digits 0-9, like -1.5e-3)"),
    (3, "\u0661\u0660", "center_y_mm: got '\u0661\u0660', expected a finite number in plain decimals (digits 0-9, like -1.5e-3)"),  # Arabic-Indic digits
    (2, "", "center_x_mm: missing; expected a finite number"),
])
def test_every_cell_is_a_plain_finite_number(tmp_path, geometry, column, text, expected):
    rows = trajectory_rows(geometry)
    rows[3][column] = text
    assert refusal(write_rows(tmp_path, rows), geometry) == f"{tmp_path / 'path.csv'}: line 5, {expected}"


def test_rows_of_another_length_than_the_header_are_refused(tmp_path, geometry):
    rows = trajectory_rows(geometry)
    path = write_rows(tmp_path, rows[:4] + [rows[4] + ["1"]] + rows[5:])
    assert refusal(path, geometry) == f"{path}: line 6: got 7 cells, expected 6 as in the header ({HEADER})"
    path = write_rows(tmp_path, rows[:4] + [rows[4][:-1]] + rows[5:])
    assert refusal(path, geometry) == (f"{path}: line 6, tip_y_mm: missing; got 5 cells, expected 6 as in "
                                       f"the header ({HEADER})")


def test_a_quote_left_open_in_a_long_file_is_refused_by_its_line(tmp_path, geometry):
    """A stray quote takes in the lines after it as one cell; past csv's field limit (128 KiB,
    a few thousand rows) that ended in a traceback instead of naming the line."""
    rows = trajectory_rows(geometry)
    rows += [[str(k)] + rows[-1][1:] for k in range(len(rows), 4000)]
    rows[3][2] = '"' + rows[3][2]
    path = write_rows(tmp_path, rows)
    assert refusal(path, geometry) == (f"{path}: line 5: got a cell longer than 131072 characters (a quote left "
                                       "open takes in the lines after it), expected a number in each cell")


def test_a_column_named_twice_is_refused(tmp_path, geometry):
    path = write_rows(tmp_path, [row + [row[2]] for row in trajectory_rows(geometry)], HEADER + ",center_x_mm")
    assert refusal(path, geometry) == f"{path}: line 1, column 7: got 'center_x_mm' again, expected each column once"


def test_a_column_named_twice_instead_of_a_required_one_is_refused_as_named_twice(tmp_path, geometry):
    """center_x_mm typed where center_y_mm belongs: said only that center_y_mm was missing."""
    path = write_rows(tmp_path, trajectory_rows(geometry), HEADER.replace("center_y_mm", "center_x_mm"))
    assert refusal(path, geometry) == (f"{path}: line 1, column 4: got 'center_x_mm' again, expected each column "
                                       "once (the header lacks center_y_mm)")


def test_parse_number_takes_plain_decimals_only():
    assert [parse_number(text) for text in ("0", " -1.5 ", "+.5", "2.", "1e-3", "3E+2")] == [0.0, -1.5, 0.5, 2.0,
                                                                                          1e-3, 300.0]
    for text in ("", "1_0", "nan", "inf", "Infinity", "1e999", "0x1", "1,5", "1 0", "--1", "e3", "\u0661"):
        assert parse_number(text) is None, text


# --- the trajectory a robot gets ------------------------------------------------------------------


def planned_result(geometry, steps: int = 4):
    """What trajectory_table reads of an insertion: the needle and each step's centre."""
    centers = [geometry.center + [0.01 * k, -0.02 * k] for k in range(1, steps + 1)]
    return SimpleNamespace(geometry=geometry, steps=[SimpleNamespace(center=c) for c in centers])


@pytest.mark.parametrize("robot,message", [
    (Robot(angular_speed=5e-324),
     "trajectory: step 1, time_s: got inf, expected a finite number; angle_rad 0.1 rad / angular speed "),
    (Robot(translation=(1e308, 1e308), given=True),
     ("trajectory: step 0, base_center_x_mm: got inf, expected a finite number; the base transform's offset "
      "[1e+308, 1e+308] mm overflows")),
])
def test_a_trajectory_with_inf_is_refused_by_its_column(geometry, robot, message):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the refusal is the only report: no numpy overflow warning
        with pytest.raises(InputError) as caught:
            trajectory_table(planned_result(geometry), robot)
    assert str(caught.value).startswith(message), str(caught.value)


def test_robot_options_at_their_bounds_give_a_finite_trajectory(geometry):
    result = planned_result(geometry)
    robot = Robot(rotation_deg=-360.0, translation=(MAX_BASE_OFFSET_MM, -MAX_BASE_OFFSET_MM),
                  angular_speed=MIN_ANGULAR_SPEED, given=True)
    columns, table = trajectory_table(result, robot)
    assert np.isfinite(table).all()
    assert len(columns) == 11 and table[-1, columns.index("time_s")] == pytest.approx(5 * 0.1 / MIN_ANGULAR_SPEED)
    np.testing.assert_array_equal(table[:, 2:4], exported_centers(result))


@pytest.mark.parametrize("text", ["0,1e308,1e308", "0,10000.1,0", "0,0,-2e4", "361,0,0", "0,1_0,0", "nan,1,2",
                                  "90,1", "90,1,2,3"])
def test_base_transforms_out_of_range_are_refused(text):
    with pytest.raises(InputError) as caught:
        parse_base_transform(text)
    assert str(caught.value) == (f"--base-transform: got {text!r}, expected ROTATION_DEG,TX_MM,TY_MM: three numbers "
                                 f"with |ROTATION_DEG| <= 360 and |TX_MM|, |TY_MM| <= 10000 (mm)")


def test_base_transforms_within_range_are_read():
    assert parse_base_transform("90,400,120") == (90.0, (400.0, 120.0))
    assert parse_base_transform(" -360 , 10000 , -1e4 ") == (-360.0, (10000.0, -10000.0))


def test_angular_speeds_too_slow_for_finite_times_are_refused():
    check_angular_speed(MIN_ANGULAR_SPEED)
    for speed in (5e-324, 9e-7, 0.0, -1.0, math.inf, math.nan):
        with pytest.raises(InputError, match=re.escape(f"--angular-speed: got {speed!r}, expected a positive "
                                                       f"speed in rad/s of at least 1e-06")):
            check_angular_speed(speed)


# --- the commands ---------------------------------------------------------------------------------


def one_error_line(result) -> str:
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.output
    return lines[0]


def test_plan_exports_what_simulate_replays_and_refuses_it_for_another_step(tmp_path, geometry):
    """The exported file passes the reader's checks as it is; replayed on a scenario of
    0.12 rad steps it is refused before any model is built, and nothing is written."""
    runner = CliRunner()
    trajectory = tmp_path / "trajectory.csv"
    result = runner.invoke(app, ["plan", str(SCENE), "--no-compare", "--no-verify", "--export", str(trajectory)])
    assert result.exit_code == 0, result.output
    assert read_center_path(trajectory, geometry).shape == (geometry.expected_steps + 1, 2)
    other = tmp_path / "step012.yaml"
    other.write_text(SCENE.read_text().replace("step: 0.1\n", "step: 0.12\n"))
    result = runner.invoke(app, ["simulate", str(other), "--no-estimate", "--center-path", str(trajectory),
                                 "--summary", str(tmp_path / "summary.json")])
    assert one_error_line(result) == (f"error: --center-path: {trajectory}: line 3, angle_rad: got 0.1, expected "
                                      f"0.12 (step 1 of the needle's 0.12 rad steps)")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["step012.yaml", "trajectory.csv"]


def test_plan_refuses_a_base_offset_beyond_range_before_running(tmp_path):
    result = CliRunner().invoke(app, ["plan", str(SCENE), "--no-compare", "--no-verify", "--export",
                                      str(tmp_path / "t.csv"), "--base-transform", "0,1e308,1e308"])
    assert "got '0,1e308,1e308', expected ROTATION_DEG,TX_MM,TY_MM" in one_error_line(result)
    assert list(tmp_path.iterdir()) == []


def test_simulate_records_the_entry_centre_of_the_path_it_followed(tmp_path, geometry):
    """Row 0 may lie off the scenario's centre (within ENTRY_TOLERANCE radii): the run enters
    about row 0, and the summary's `needle_center_at_entry` says so."""
    import json

    shift = np.array([0.004, -0.003]) * geometry.radius
    rows = trajectory_rows(geometry, drift=(0.0, 0.0))
    rows[0][2:6] = [f"{value:.9g}" for value in (*(geometry.center + shift), *geometry.tip(0.0, geometry.center + shift))]
    path = write_rows(tmp_path, rows)
    summary = tmp_path / "summary.json"
    result = CliRunner().invoke(app, ["simulate", str(SCENE), "--no-estimate", "--center-path", str(path),
                                      "--summary", str(summary), "-q"])
    assert result.exit_code == 0, result.output
    entry = json.loads(summary.read_text())["needle_center_at_entry"]
    np.testing.assert_allclose(entry, geometry.center + shift, rtol=0, atol=1e-9)
