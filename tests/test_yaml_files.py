"""Reading YAML inputs: YAML 1.2 core scalars, every duplicate key reported at once, and
the scenario's checksum taken from the bytes that were parsed.

YAML 1.1 (what a plain YAML loader implements) reads `1e-6` as a string, `010` as eight,
`5:00` as 300 and `no` as False; the JSON Schema of the scenario files and editors follow
YAML 1.2, so a value could be accepted by the editor and refused, or silently changed, by
the tool. Each case loads a small file from tmp_path through the package's loaders.
"""

from __future__ import annotations

import hashlib
import math
import os
import threading

import pytest
import yaml
from typer.testing import CliRunner

from stitchplan.calibration import load_material_calibration
from stitchplan.cli import app
from stitchplan.config import ScenarioError, load_scenario, read_yaml
from stitchplan.config.uncertainty import load_uncertainty

# a 40 x 20 mm slab with a needle and a force on the left edge: every field below is valid
SCENE = """\
name: small
tissue:
  size: [40.0, 20.0]
  thickness: 10.0
  material: {model: saint-venant-kirchhoff, lame_lambda: 0.189151, lame_mu: 0.147688}
  clamped: [right]
discretization: {spacing: 5.0}
needle:
  radius: 8.88
  entry: [0.0, 12.0]
  turn: cw
  step: 0.2
  friction: 0.0602
  cutting_force: 0.7
loads:
  - segment: [[0.0, 5.0], [0.0, 15.0]]
    force: [-1.0, 0.5]
"""


def write(tmp_path, text: str, name: str = "scene.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def refusal(path) -> list[str]:
    with pytest.raises(ScenarioError) as error:
        load_scenario(path)
    return error.value.lines


# --- YAML 1.2 core scalars -----------------------------------------------------------------


@pytest.mark.parametrize("text, value", [
    ("1e-6", 1e-6), ("1E+3", 1000.0), (".5", 0.5), ("-.5e-1", -0.05), ("1.", 1.0), ("+12", 12),
    ("010", 10), ("0o17", 15), ("0x1F", 31), ("!!int 010", 10),
    ("-.inf", -math.inf), (".Inf", math.inf),
    ("true", True), ("True", True), ("FALSE", False),
    ("null", None), ("~", None), ("", None),
    # YAML 1.1 would read these as 300, False, True, True, False, 1000 and a date
    ("5:00", "5:00"), ("no", "no"), ("yes", "yes"), ("on", "on"), ("off", "off"), ("1_000", "1_000"),
    ("2024-06-11", "2024-06-11"), ("'1e-6'", "1e-6"),
])
def test_plain_scalars_are_read_as_yaml_1_2_core(tmp_path, text, value):
    data, _ = read_yaml(write(tmp_path, f"value: {text}\n"))
    assert data["value"] == value and type(data["value"]) is type(value)


def test_nan_is_read_as_nan_and_the_global_loader_keeps_yaml_1_1(tmp_path):
    data, _ = read_yaml(write(tmp_path, "a: .nan\nb: .NaN\n"))
    assert math.isnan(data["a"]) and math.isnan(data["b"])
    # other readers of YAML in the same process are not changed behind their back
    assert yaml.safe_load("a: yes\nb: 010\nc: 1e-6\n") == {"a": True, "b": 8, "c": "1e-6"}


@pytest.mark.parametrize("text", ["!!bool yes", "!!int 1_000", "!!float 5:00"])
def test_explicit_tags_take_yaml_1_2_values_only(tmp_path, text):
    path = write(tmp_path, f"value: {text}\n")
    tag, value = text.split()
    with pytest.raises(ScenarioError) as error:
        read_yaml(path)
    assert str(error.value).startswith(f"{path}: not valid YAML at line 1 (got {tag} {value!r}, expected ")


@pytest.mark.parametrize("text, line", [("a: 1\n---\nb: 2\n", 2), ("a: 1\n---\n", 2), ("---\na: 1\n---\nb: 2\n", 3)])
def test_a_second_document_is_refused_saying_one_is_expected(tmp_path, text, line):
    """A `---` after the first document (two scenarios pasted into one file): the line says
    where the second starts and that one document is expected (it said only "but found
    another document"); a `---` before the only document is read."""
    path = write(tmp_path, text)
    with pytest.raises(ScenarioError) as error:
        read_yaml(path)
    assert str(error.value) == (f"{path}: a second YAML document at line {line} (after a `---` line), expected one "
                                "document a file; remove the `---` line and what follows it, or put that in a file "
                                "of its own")
    assert read_yaml(write(tmp_path, "---\na: 1\n", "one.yaml"))[0] == {"a": 1}


@pytest.mark.parametrize("text, line, character, code", [
    ("name: a\x1b[31mb\n", 1, 8, "001B"), ("name: ok\r\n\x00\n", 2, 1, "0000"),
    ("\ufeffa: [1]\nb: \x7f\n", 2, 4, "007F")])
def test_a_raw_control_character_is_placed_and_named(tmp_path, text, line, character, code):
    """PyYAML's reader refuses it with no mark: the line said only "not valid YAML"."""
    path = tmp_path / "scene.yaml"
    path.write_text(text, encoding="utf-8", newline="")
    with pytest.raises(ScenarioError) as error:
        read_yaml(path)
    assert str(error.value) == (f"{path}: line {line}, character {character}: got U+{code}, a character YAML text may "
                                "not hold, expected printable characters, tabs and line breaks (inside double quotes "
                                "a control character is written as an escape such as \\x1b)")


def test_scientific_notation_reaches_the_scenario(tmp_path):
    scenario = load_scenario(write(tmp_path, SCENE + "solver: {residual_tolerance: 1e-6}\n"
                                   + "planner: {strict: True}\n"))
    assert scenario.solver.residual_tolerance == 1e-6
    assert scenario.planner.strict is True


def test_a_leading_zero_is_decimal(tmp_path):
    scenario = load_scenario(write(tmp_path, SCENE.replace("spacing: 5.0", "spacing: 010")))
    assert scenario.discretization.spacing == 10


def test_yaml_1_1_spellings_are_refused_as_the_strings_they_are(tmp_path):
    text = (SCENE.replace("spacing: 5.0", "spacing: 5:00").replace("turn: cw", "turn: no")
            .replace("thickness: 10.0", "thickness: .inf") + "planner: {strict: on}\n")
    path = write(tmp_path, text)
    lines = refusal(path)
    assert len(lines) == 4, lines
    for field, shown in [("tissue.thickness", "inf"), ("discretization.spacing", "'5:00'"),
                         ("needle.turn", "'no'"), ("planner.strict", "'on'")]:
        assert any(line.startswith(f"{path}: {field}: got {shown}, expected ") for line in lines), (field, lines)


def test_other_input_files_read_yaml_1_2_too(tmp_path):
    path = write(tmp_path, "samples: 8\nseed: 010\nparameters:\n  friction: {std: 5e-4}\n", "uncertainty.yaml")
    uncertainty = load_uncertainty(path)
    assert uncertainty.seed == 10
    assert dict(zip(uncertainty.names, uncertainty.std)) == {"friction": 5e-4}


# --- duplicate keys -------------------------------------------------------------------------


def test_every_duplicate_key_is_reported_at_once(tmp_path):
    text = (SCENE.replace("  thickness: 10.0\n", "  thickness: 10.0\n  size: [40.0, 20.0]\n")
            .replace("  step: 0.2\n", "  step: 0.2\n  radius: 8.88\n  radius: 9.0\n")
            + "loads:\n  - {segment: [[0.0, 5.0], [0.0, 15.0]], force: [1.0, 0.0], force: [2.0, 0.0]}\n"
            + "name: again\n")
    path = write(tmp_path, text)
    assert refusal(path) == [
        f"{path}: line 5: duplicate key 'size' (first given at line 3) in tissue, expected each key once",
        (f"{path}: lines 14 and 15: duplicate key 'radius' (first given at line 10) in needle, "
         "expected each key once"),
        f"{path}: line 21: duplicate key 'loads' (first given at line 18), expected each key once",
        f"{path}: line 22: duplicate key 'force' (first given at line 22) in loads[0], expected each key once",
        f"{path}: line 23: duplicate key 'name' (first given at line 1), expected each key once",
    ]


def test_an_aliased_mapping_is_reported_once_where_it_is_anchored(tmp_path):
    path = write(tmp_path, "base: &m {k: 1, k: 2}\nfirst: *m\nsecond: [*m]\n")
    with pytest.raises(ScenarioError) as error:
        read_yaml(path)
    assert error.value.lines == [
        f"{path}: line 1: duplicate key 'k' (first given at line 1) in base, expected each key once"]


def test_the_command_lists_every_duplicate_key(tmp_path):
    path = write(tmp_path, "name: a\n" + SCENE.replace("  step: 0.2\n", "  step: 0.2\n  radius: 9.0\n"))
    result = CliRunner().invoke(app, ["deform", str(path), "--summary", str(tmp_path / "summary.json")])
    assert result.exit_code == 2, result.output
    assert result.stderr.splitlines() == [
        f"error: {path}: line 2: duplicate key 'name' (first given at line 1), expected each key once",
        (f"error: {path}: line 14: duplicate key 'radius' (first given at line 10) in needle, "
         "expected each key once"),
    ]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.yaml"]


# --- merge keys -------------------------------------------------------------------------------

MERGE = ("merge key '<<'{inside} (YAML 1.1; files are read as YAML 1.2, which has no merge keys), expected the "
         "keys written out in this mapping (an alias such as `material: *phantom` may still stand for a whole value)")


def test_a_merge_key_is_refused_not_overridden_silently(tmp_path):
    """`<<` merged thickness 0.01 and the mapping's own 10.0 silently won: the file ran as
    10 mm although it gives two thicknesses. YAML 1.2 has no merge keys; each is one line."""
    text = SCENE.replace("  thickness: 10.0\n", "  <<: {thickness: 0.01}\n  thickness: 10.0\n")
    path = write(tmp_path, text)
    assert refusal(path) == [f"{path}: line 4: " + MERGE.format(inside=" in tissue")]


def test_every_merge_key_is_reported_with_the_duplicate_keys(tmp_path):
    text = (SCENE + "probes: [[10.0, 10.0]]\n").replace(
        "loads:\n  - segment: [[0.0, 5.0], [0.0, 15.0]]\n    force: [-1.0, 0.5]\n",
        "loads:\n  - &pull {segment: [[0.0, 5.0], [0.0, 15.0]], force: [-1.0, 0.5]}\n"
        "  - {<<: *pull, segment: [[0.0, 15.0], [0.0, 18.0]]}\n  - <<: [*pull]\n    segment: [[0.0, 1.0], [0.0, 2.0]]\n"
        "    segment: [[0.0, 2.0], [0.0, 3.0]]\n")
    path = write(tmp_path, text)
    assert refusal(path) == [
        f"{path}: line 17: " + MERGE.format(inside=" in loads[1]"),
        f"{path}: line 18: " + MERGE.format(inside=" in loads[2]"),
        f"{path}: line 20: duplicate key 'segment' (first given at line 19) in loads[2], expected each key once",
    ]


def test_a_merge_key_does_not_hide_the_other_problems(tmp_path):
    """The merge key's line stopped the reading: an unknown key and a negative radius beside it
    went unsaid. The other problems follow it, found in the data with the merge followed (the
    thickness it merges is not also missing)."""
    text = "base: &slab {thickness: 10.0}\n" + SCENE.replace("  thickness: 10.0\n", "  <<: *slab\n").replace(
        "  radius: 8.88\n", "  radius: -8.88\n")
    path = write(tmp_path, text)
    assert refusal(path) == [
        f"{path}: line 5: " + MERGE.format(inside=" in tissue"),
        f"{path}: needle.radius: got -8.88, expected a positive number (mm)",
        (f"{path}: scenario: unknown key 'base', expected one of: name, tissue, discretization, needle, loads, "
         "load_steps, probes, solver, planner, robot, study"),
    ]


def test_a_duplicate_key_does_not_hide_the_other_problems(tmp_path):
    path = write(tmp_path, SCENE.replace("  step: 0.2\n", "  step: 0.2\n  step: -1\n"))
    assert refusal(path) == [
        f"{path}: line 13: duplicate key 'step' (first given at line 12) in needle, expected each key once",
        f"{path}: needle.step: got -1, expected a positive angle of at most 0.5 rad per step",
    ]


def test_a_merge_key_of_a_scalar_is_its_one_line(tmp_path):
    """`<<: 5` cannot be followed: its line alone, not also the YAML reader's complaint."""
    path = write(tmp_path, SCENE.replace("  thickness: 10.0\n", "  thickness: 10.0\n  <<: 5\n") + "colour: red\n")
    assert refusal(path) == [f"{path}: line 5: " + MERGE.format(inside=" in tissue")]


def test_the_uncertainty_and_calibration_files_list_a_merge_key_with_their_other_problems(tmp_path):
    path = write(tmp_path, "samples: 3\n<<: {seed: 1}\nparameters: {thicknes: {std: 1.0}}\n", "u.yaml")
    with pytest.raises(ScenarioError) as error:
        load_uncertainty(path)
    assert error.value.lines == [f"{path}: line 2: " + MERGE.format(inside=""),
                                 (f"{path}: parameters: unknown key 'thicknes', expected one of: lame_lambda, "
                                  "lame_mu, friction, cutting_force, thickness (did you mean 'thickness'?)")]
    calibration = write(tmp_path, "tissue: {<<: {thickness: 10.0}, size: [100.0, 60.0], clamped: [right]}\n"
                        "experiments: []\nfit: {lame_lambda: [0.01, 2.0], lame_mu: [0.01, 2.0]}\n", "c.yaml")
    with pytest.raises(ScenarioError) as error:
        load_material_calibration(calibration)
    assert error.value.lines[0] == f"{calibration}: line 1: " + MERGE.format(inside=" in tissue")
    assert len(error.value.lines) == 2 and error.value.lines[1].startswith(f"{calibration}: experiments: got []")


def test_the_command_refuses_a_merge_key_in_one_line(tmp_path):
    path = write(tmp_path, "<<: {name: merged}\n" + SCENE)
    result = CliRunner().invoke(app, ["deform", str(path), "--summary", str(tmp_path / "summary.json")])
    assert result.exit_code == 2, result.output
    assert result.stderr.splitlines() == [f"error: {path}: line 1: " + MERGE.format(inside="")]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.yaml"]


def test_a_quoted_key_and_aliases_of_whole_values_are_plain_data(tmp_path):
    """Only YAML 1.1's plain `<<` merges: a quoted '<<' is an unknown key, and an alias of a
    whole mapping stays what it is."""
    path = write(tmp_path, SCENE.replace("  material: {", "  material: &phantom {") + "'<<': 1\n")
    assert refusal(path) == [f"{path}: scenario: unknown key '<<', expected one of: name, tissue, discretization, "
                             "needle, loads, load_steps, probes, solver, planner, robot, study"]
    data, _ = read_yaml(write(tmp_path, "a: &m {k: 1}\nb: *m\n", "aliases.yaml"))
    assert data == {"a": {"k": 1}, "b": {"k": 1}}


# --- nesting ----------------------------------------------------------------------------------

TOO_DEEP = "line 1: nesting too deep (more than 100 levels of lists and mappings), expected plain data"


@pytest.mark.parametrize("depth", [100, 500, 100_000])
def test_nesting_beyond_a_hundred_levels_is_one_line(tmp_path, depth):
    """The loader recurses once per level: without a bound, 500 nested `[` end in a
    RecursionError traceback. The root mapping is the first level."""
    path = write(tmp_path, "name: " + "[" * depth + "]" * depth + "\n")
    assert refusal(path) == [f"{path}: {TOO_DEEP}"]
    with pytest.raises(ScenarioError) as error:  # any YAML input file
        load_uncertainty(path)
    assert error.value.lines == [f"{path}: {TOO_DEEP}"]


def test_nesting_within_the_bound_reaches_the_fields(tmp_path):
    path = write(tmp_path, SCENE.replace("name: small", "name: " + "[" * 99 + "]" * 99))
    [line] = refusal(path)
    assert line.startswith(f"{path}: name: got [[[[") and line.endswith("expected a string")


def test_nesting_built_from_aliases_is_bounded_too(tmp_path):
    """Each alias nests an anchored list 30 levels further: the fourth goes past 100."""
    lines = [f"a0: &a0 {'[' * 30}1{']' * 30}"]
    lines += [f"a{k}: &a{k} {'[' * 30}*a{k - 1}{']' * 30}" for k in range(1, 4)]
    path = write(tmp_path, "\n".join(lines) + "\n")
    [line] = refusal(path)
    assert line.startswith(f"{path}: line ") and "nesting too deep (more than 100 levels" in line


def test_a_recursion_error_while_reading_names_the_file(tmp_path, monkeypatch):
    """Should any recursion still run out of stack (here with the bound lifted), the file is
    named in one line."""
    from stitchplan.config import yaml_files

    monkeypatch.setattr(yaml_files, "MAX_DEPTH", 10 ** 9)
    path = write(tmp_path, "name: " + "[" * 5000 + "]" * 5000 + "\n")
    assert refusal(path) == [f"{path}: nesting too deep, expected plain data"]


# --- the checksum of what was parsed --------------------------------------------------------


def test_the_checksum_is_of_the_bytes_read(tmp_path):
    path = tmp_path / "scene.yaml"
    path.write_bytes(b"\xef\xbb\xbf" + SCENE.encode())  # a byte-order mark is part of the file
    scenario = load_scenario(path)
    assert scenario.source_sha256 == hashlib.sha256(path.read_bytes()).hexdigest()
    assert scenario.source_text.encode() == path.read_bytes()  # the text is the bytes hashed, its mark kept


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs named pipes")
def test_a_piped_scenario_is_read_once(tmp_path):
    """A pipe gives its bytes once: the checksum must come from the read that was parsed."""
    pipe = tmp_path / "scene.pipe"
    os.mkfifo(pipe)
    writer = threading.Thread(target=lambda: pipe.write_text(SCENE))
    writer.start()
    try:
        scenario = load_scenario(pipe)
    finally:
        writer.join(timeout=10)
    assert scenario.name == "small"
    assert scenario.source_sha256 == hashlib.sha256(SCENE.encode()).hexdigest()


@pytest.mark.parametrize("uses", [100, 101])
def test_a_file_may_use_a_hundred_aliases_and_no_more(tmp_path, uses):
    path = write(tmp_path, "b: &b [1]\nc: [" + ", ".join(["*b"] * uses) + "]\n", "aliases.yaml")
    if uses > 100:
        assert refusal(path) == [f"{path}: line 2: more than 100 YAML aliases, expected plain data"]
    else:
        data, _ = read_yaml(path)
        assert data["c"] == [[1]] * uses


@pytest.mark.parametrize("outer", [47, 48, 49])  # with the root, the anchored 50 and its 1: 99, 100, 101 levels
def test_nesting_through_an_alias_counts_as_written_out(tmp_path, outer):
    """An alias nests its anchored value where it is used: the document is read or refused
    at the depth bound exactly as the same document with the value written out."""
    inner = "[" * 50 + "1" + "]" * 50
    aliased = write(tmp_path, f"a: &a {inner}\nb: {'[' * outer}*a{']' * outer}\n", "aliased.yaml")
    written = write(tmp_path, f"a: {inner}\nb: {'[' * outer}{inner}{']' * outer}\n", "written.yaml")

    def refused(path) -> bool:
        try:
            read_yaml(path)
        except ScenarioError as error:
            assert "nesting too deep" in str(error)
            return True
        return False

    assert refused(aliased) == refused(written) == (outer > 48)


def test_an_endless_input_is_refused_at_the_size_cap_not_read_to_the_end(tmp_path, monkeypatch):
    """/dev/zero as a scenario or a CSV filled the machine's memory until the kernel killed the
    command without a word: inputs are read up to MAX_INPUT_BYTES, and one larger is refused
    by name (the cap lowered here to keep the file small)."""
    from stitchplan.config import load_scenario, yaml_files
    from stitchplan.errors import InputError
    from stitchplan.io.readers import read_center_path

    assert yaml_files.MAX_INPUT_BYTES >= 10 * 2**20  # a 10 MB scenario of comments still reads
    monkeypatch.setattr(yaml_files, "MAX_INPUT_BYTES", 1000)
    big = tmp_path / "big.yaml"
    big.write_text("# comment\n" * 200)
    with pytest.raises(InputError) as error:
        load_scenario(big)
    assert str(error.value) == f"{big}: got more than 1000 bytes, expected a YAML text file"
    table = tmp_path / "big.csv"
    table.write_text("step,center_x_mm,center_y_mm\n" + "0,0,0\n" * 400)
    with pytest.raises(InputError, match=r"big\.csv: got more than 1000 bytes, expected a CSV table \(a trajectory"):
        read_center_path(table)
    if os.path.exists("/dev/zero"):  # the endless file itself, at the real cap
        monkeypatch.setattr(yaml_files, "MAX_INPUT_BYTES", 2**20)
        with pytest.raises(InputError, match=r"^/dev/zero: got more than 1 MB"):
            load_scenario("/dev/zero")
