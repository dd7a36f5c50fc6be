"""Scenario files: YAML in, validated typed configuration out.

Every problem of a file is reported at once, one line each naming the field, the value
received and what was expected; unknown keys are refused so a misspelt option never
silently falls back to a default.
"""

from __future__ import annotations

from dataclasses import field, replace
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import AfterValidator, ValidationInfo, model_validator

from ..errors import InputError, ScenarioError
from ..geometry.polygon_domain import PolygonDomain
from ..geometry.rectangle import Rectangle
from .blocks import (
    Discretization,
    Load,
    Material,
    Needle,
    NeedleRadius,
    ScenePoint,
    Solver,
    Tissue,
    block,
    default_spacing_of,
    parse_discretization,
    shape_domain,
)
from .boundary_points import (inside_expectation, log_moves, placed, probe_in_tissue, segment_ends,
                              segment_expectation)
from .fields import (
    EDGES,
    INTEGRATIONS,
    LINEAR_SOLVERS,
    MATERIAL_MODELS,
    TIP_TRACKING,
    Name,
    Point,
    described,
    integer,
    problem,
    sequence,
)
from .load_checks import HELD, load_problems
from .messages import combined, input_error, merged_typos, valid_or_none, validate, value_at
from .plan_blocks import Planner, Robot, RobotBlock, speed_problem
from .study import StudySpec
from .yaml_files import read_yaml, read_yaml_file, with_key_problems

__all__ = [
    "DEFAULT_NEEDLE_REFINEMENT", "EDGES", "INTEGRATIONS", "LINEAR_SOLVERS", "MATERIAL_MODELS",
    "TIP_TRACKING", "Discretization", "Load", "Material", "Needle", "Planner", "Robot", "Scenario",
    "ScenarioError", "ScenarioFile", "Solver", "Tissue", "default_spacing", "load_scenario",
    "parse_discretization", "parse_material", "parse_needle", "parse_scenario", "read_yaml",
    "with_discretization",
]

# graded needle scenes: spacing at the needle = spacing / DEFAULT_NEEDLE_REFINEMENT
DEFAULT_NEEDLE_REFINEMENT = 2.0


def _inside(point: tuple[float, float], domain: Rectangle | PolygonDomain) -> str | None:
    """What a probe must be when it is not inside the domain."""
    return None if domain.contains(np.asarray(point, dtype=float)) else inside_expectation(domain)


def _probe_inside(point: tuple[float, float], info: ValidationInfo) -> tuple[float, float]:
    """A file's probe inside the tissue, or moved onto its boundary from just outside (within
    the input tolerance: boundary_points); further out, refused naming the nearest point."""
    return placed(point, info.context, probe_in_tissue)


Probes = sequence(Annotated[ScenePoint, AfterValidator(_probe_inside)],
                  "a list of reference points [[x, y], ...] (mm)")
LoadSteps = integer(1, 10000)


@block()
class Scenario:
    """What the numerics receive: the validated blocks of a scenario file (robot in the form
    the writers use), its text, and the resolved default discretization."""

    tissue: Tissue
    discretization: Discretization = field(default_factory=Discretization)
    needle: Needle | None = None
    loads: tuple[Load, ...] = ()
    load_steps: LoadSteps = 10
    probes: tuple[Point, ...] = ()
    solver: Solver = field(default_factory=Solver)
    planner: Planner = field(default_factory=Planner)
    robot: Robot = field(default_factory=Robot)
    name: str = ""
    source_text: str = ""  # the file as read, kept in run logs
    source_sha256: str | None = None  # of the bytes parsed: a piped file cannot be read again
    study: StudySpec | None = None  # the optional `study:` block

    @model_validator(mode="after")
    def _within_the_tissue(self) -> Scenario:
        domain = self.tissue.domain
        for i, load in enumerate(self.loads):
            if domain.segment_edge(*load.segment) is None:
                raise problem(segment_expectation(domain), field=f"loads[{i}].segment", value=load.segment)
        for i, point in enumerate(self.probes):
            expected = _inside(point, domain)
            if expected:
                raise problem(expected, field=f"probes[{i}]", value=point)
        return self


@block(kw_only=True, title="stitchplan scenario")
class ScenarioFile:
    """A scenario file as written (see docs: Scenario format)."""

    name: described(Name, "optional label") = ""
    tissue: described(Tissue, "the slab: size, thickness, material, clamped edges")
    discretization: described(Discretization | None, "optional; the tool chooses sound defaults") = None
    needle: described(Needle | None, "needed by simulate and plan") = None
    loads: described(sequence(Load, "a list of loads"), "static loads, used by deform") = ()
    load_steps: described(LoadSteps, "load increments of deform") = 10
    probes: described(Probes, "reference points to report displacement at, mm") = ()
    solver: described(Solver | None, "Newton settings") = None
    planner: described(Planner | None, "planner settings") = None
    robot: described(RobotBlock | None, "robot base frame and needle speed for trajectory.csv") = None
    study: described(StudySpec | None, "sweep of discretizations and methods for `stitchplan study`") = None

    @model_validator(mode="after")
    def _loads_and_clamps_agree(self) -> ScenarioFile:
        """Loads off the clamped edges and apart from each other; a slab held in place."""
        problems = load_problems(self.loads, self.tissue.clamped, self.tissue.domain)
        if not self.tissue.clamped and all(load.displacement is None for load in self.loads):
            problems.append(problem(HELD, field="tissue.clamped", value=list(self.tissue.clamped)))
        if problems:
            raise combined(problems)
        return self

    @model_validator(mode="after")
    def _lean_within_the_search(self) -> ScenarioFile:
        """With planner.aim_entry_tilt the lean search starts from the needle's own lean, and
        keeps within planner.max_entry_tilt: a lean given beyond it would be the plan's."""
        planner, needle = self.planner, self.needle
        if planner is not None and needle is not None and planner.aim_entry_tilt \
                and abs(needle.entry_tilt) > planner.max_entry_tilt:
            raise problem(f"a lean of at most planner.max_entry_tilt ({planner.max_entry_tilt:g} rad) either way with "
                          "planner.aim_entry_tilt (the lean search starts from it)", field="needle.entry_tilt",
                          value=needle.entry_tilt)
        return self

    @model_validator(mode="after")
    def _speed_within_the_steps(self) -> ScenarioFile:
        speed = self.robot.angular_speed if self.robot is not None else None
        expected = speed_problem(speed, self.needle.step) if speed is not None and self.needle is not None else None
        if expected is not None:
            raise problem(expected, field="robot.angular_speed", value=speed)
        return self

    def scenario(self, source_text: str = "", source_sha256: str | None = None) -> Scenario:
        return Scenario(
            tissue=self.tissue,
            discretization=self.discretization or Discretization(),
            needle=self.needle,
            loads=self.loads,
            load_steps=self.load_steps,
            probes=self.probes,
            solver=self.solver or Solver(),
            planner=self.planner or Planner(),
            robot=self.robot.robot() if self.robot else Robot(),
            name=self.name,
            source_text=source_text,
            source_sha256=source_sha256,
            study=self.study,
        )


def default_spacing(tissue: Tissue, needle: Needle | None) -> float:
    """Spacing used when the scenario gives none.

    Static loads: a twentieth of the smaller side (within 1 % of the converged probe
    displacements on the shipped slab, see benchmarks/). Needle scenes: 2/5 of the needle
    radius, at most a twentieth of the larger side and an eighth of the smaller one, graded
    to half that around the needle (DEFAULT_NEEDLE_REFINEMENT: r/5 for the SH 1/2 needle);
    halving both changes the SH 1/2 exit errors by at most ~7 %
    (benchmarks/results/simulate_convergence.md), where a uniform r/3 grid changed by 13 %
    with three times the particles.
    """
    return default_spacing_of(tissue.bounding_size, None if needle is None else needle.radius)


def _with_default_spacing(raw: dict, size: tuple[float, float] | None) -> dict | None:
    """The file with the default spacing (and needle refinement) filled in when it gives no
    spacing: default_spacing's, graded by DEFAULT_NEEDLE_REFINEMENT in needle scenes. None
    when that default cannot be known (an invalid size or radius, reported by their fields)."""
    given = raw.get("discretization")
    given = {} if given is None else given
    if not isinstance(given, dict) or "spacing" in given:
        return raw
    needle = raw.get("needle")
    radius = valid_or_none(NeedleRadius, needle.get("radius")) if isinstance(needle, dict) else None
    if size is None or (needle is not None and radius is None):
        return None
    values = {**given, "spacing": default_spacing_of(size, radius)}
    if needle is not None and given.get("needle_refinement") is None and given.get("needle_spacing") is None:
        values["needle_refinement"] = DEFAULT_NEEDLE_REFINEMENT
    return {**raw, "discretization": values}


def parse_scenario(raw: Any, source_text: str = "", source_sha256: str | None = None,
                   source: str = "") -> Scenario:
    """A scenario from the data of a file (its text and the SHA-256 of its bytes kept for
    run logs; `source`, its path, for its warnings); an InputError lists every problem of it."""
    context: dict[str, Any] = {"domain": None}
    if isinstance(raw, dict):
        domain = shape_domain(raw.get("tissue"))
        size = None if domain is None else domain.size
        context["domain"] = domain
        given = raw.get("discretization")
        # the keys the file gives (the default spacing is filled in below)
        context["discretization_given"] = {k for k, v in given.items() if v is not None} if isinstance(given, dict) else set()
        resolved = _with_default_spacing(raw, size)
        context["default_spacing_unknown"] = resolved is None
        raw = raw if resolved is None else resolved
    try:
        scenario_file = validate(ScenarioFile, raw, "", root="scenario", context=context)
    except InputError as error:
        raise input_error(merged_typos(_with_shape_lines(error.lines, _shape_lines(raw)))) from None
    log_moves(scenario_file.tissue.domain, moved_points(raw, scenario_file), source)
    return scenario_file.scenario(source_text, source_sha256)


def _shape_lines(raw: Any) -> list[str]:
    """The problems of the tissue's shape (size or outline, holes, regions, clamped): a tissue
    whose other fields fail (a negative thickness, say) is not checked as a whole, so its
    shape is checked on its own, that every problem is said at once."""
    tissue = raw.get("tissue") if isinstance(raw, dict) else None
    if not isinstance(tissue, dict):
        return []
    shape = {key: tissue[key] for key in ("size", "outline", "holes", "regions", "clamped") if key in tissue}
    try:
        validate(Tissue, {**shape, "thickness": 1.0, "material": Material()}, "tissue")
    except InputError as error:
        return list(error.lines)
    return []


def _with_shape_lines(known: list[str], shape: list[str]) -> list[str]:
    """`known` with the shape's lines not among them; one that says the same with more (an
    unknown key's line with where the key belongs) takes the shorter one's place."""
    lines = list(known)
    for line in shape:
        fuller = next((k for k, said in enumerate(lines) if line.startswith(said)), None)
        if fuller is not None:
            lines[fuller] = line
        elif not any(said.startswith(line) for said in lines):
            lines.append(line)
    return lines


def moved_points(raw: Any, scenario_file: ScenarioFile) -> list[tuple[str, Any, Any]]:
    """(field, point as the file gives it, point as the run uses it) of every point a file
    places on the boundary or inside the tissue: the needle entry, segment ends, probes."""
    points = []
    if scenario_file.needle is not None:
        points.append(("needle.entry", value_at(raw, ("needle", "entry")), scenario_file.needle.entry))
    points += segment_ends(raw, ("tissue", "clamped"), scenario_file.tissue.clamped)
    points += segment_ends(raw, ("loads",), scenario_file.loads)
    for i, point in enumerate(scenario_file.probes):
        points.append((f"probes[{i}]", value_at(raw, ("probes", i)), point))
    return points


def load_scenario(path: str | Path) -> Scenario:
    """The scenario of a YAML file; every error line starts with the file's path."""
    file = read_yaml_file(path, keys_later=True)  # read once: the checksum is of the bytes parsed
    return with_key_problems(file, path, lambda data: parse_scenario(data, file.text, file.sha256, str(path)))


def require_loads(scenario: Scenario, source: str | Path) -> None:
    """deform needs loads: without any the slab stays at rest (one line naming the file)."""
    if not scenario.loads:
        raise input_error([(f"{source}: loads: got none, expected at least one load (force or "
                            "displacement) for deform; without loads the slab stays at rest")])


def require_needle_loads(scenario: Scenario, source: str | Path, command: str) -> None:
    """simulate, plan and study need something that deforms the tissue: with neither friction
    nor a cutting force (both 0 when not given) and no `loads`, the tissue stays at rest and
    every exit error is 0, which reads as a perfect stitch (one line naming the file). With
    loads, a needle without its own is a scene of the loads' deformation alone."""
    needle = scenario.needle
    if needle is not None and needle.friction == 0 and needle.cutting_force == 0 and not scenario.loads:
        raise input_error([(f"{source}: needle: got friction 0 N/mm and cutting_force 0 N (their defaults when "
                            f"not given) and no loads, expected a positive friction or cutting_force for {command}; "
                            "without them nothing loads the tissue, which stays at rest")])


def parse_material(raw: Any, path: str = "tissue.material") -> Material:
    return validate(Material, raw, path)


def parse_needle(raw: Any, path: str = "needle") -> Needle:
    return validate(Needle, raw, path)


def with_discretization(scenario: Scenario, **overrides: float | None) -> Scenario:
    """Copy of the scenario with discretization fields replaced (None values ignored)."""
    changes = {k: v for k, v in overrides.items() if v is not None}
    if "spacing" in changes and "accuracy" not in overrides:
        changes["accuracy"] = None  # an explicit spacing replaces the auto discretization
    return replace(scenario, discretization=scenario.discretization.replaced(**changes))
