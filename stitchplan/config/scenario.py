"""Scenario files: YAML in, validated typed configuration out.

Every error names the field, the value received and what was expected; unknown keys are
refused so a misspelt option never silently falls back to a default.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from ..errors import ScenarioError
from ..geometry import EDGE_NAMES, Rectangle

EDGES = EDGE_NAMES
MATERIAL_MODELS = ("saint-venant-kirchhoff", "neo-hookean")
TIP_TRACKING = ("auto", "inverse-gradient", "levenberg-marquardt")
LINEAR_SOLVERS = ("direct", "minres")
INTEGRATIONS = ("gauss", "vci")


@dataclass(frozen=True)
class Material:
    model: str = "saint-venant-kirchhoff"
    lame_lambda: float = 0.189151
    lame_mu: float = 0.147688


@dataclass(frozen=True)
class Tissue:
    size: tuple[float, float]
    thickness: float
    material: Material
    clamped: tuple[str, ...]

    @property
    def domain(self) -> Rectangle:
        return Rectangle.of_size(self.size)


@dataclass(frozen=True)
class Discretization:
    spacing: float = 5.0
    dilation: float = 2.0
    quadrature_order: int = 2
    basis_order: int = 1
    cells_per_spacing: int = 1
    # graded particles (see discretization.graded_particles): `needle_spacing` within
    # `needle_zone` needle radii of the needle centre, growing to `spacing` away from it
    needle_spacing: float | None = None
    needle_zone: float = 1.5
    # needle_spacing = spacing / needle_refinement when no needle_spacing is given, so that
    # `--spacing` refines the graded arrangement as a whole (the default for needle scenes)
    needle_refinement: float | None = None
    # "gauss": Galerkin with background-cell Gauss quadrature; "vci": the test-function
    # gradients corrected so that the quadrature satisfies the divergence theorem
    # (variationally consistent integration; passes the linear patch test; deform only)
    integration: str = "gauss"
    # exit-point accuracy (mm): the auto discretization (stitchplan.auto) picks the rest
    accuracy: float | None = None

    def as_input(self) -> dict:
        """The block as a scenario file would give it: parse_discretization(d.as_input())
        returns d, and a needle spacing derived from needle_refinement stays derived, so it
        follows a changed spacing."""
        from dataclasses import asdict

        values = asdict(self)
        if self.needle_refinement is not None:
            values["needle_spacing"] = None
        return values

    def replaced(self, path: str = "discretization", **changes) -> Discretization:
        """A validated copy with `changes` applied (None is a value here: needle_spacing=None
        makes the particles uniform). A needle spacing derived from needle_refinement follows
        a changed spacing unless needle_spacing is given; `path` names the block in errors."""
        values = self.as_input()
        values.update(changes)
        return parse_discretization(values, path)


@dataclass(frozen=True)
class Needle:
    radius: float
    arc: float
    entry: tuple[float, float]
    turn: str
    step: float
    friction: float
    cutting_force: float
    tip_tracking: str = "levenberg-marquardt"
    linear_solver: str = "direct"


@dataclass(frozen=True)
class Load:
    segment: tuple[tuple[float, float], tuple[float, float]]
    force: tuple[float, float] | None = None
    displacement: tuple[float, float] | None = None


@dataclass(frozen=True)
class Solver:
    residual_tolerance: float = 1e-8
    increment_tolerance: float = 1e-8
    max_iterations: int = 25
    max_step_cuts: int = 6


@dataclass(frozen=True)
class Planner:
    tolerance: float = 1e-3  # mm
    max_iterations: int = 10
    strict: bool = False
    exit_tolerance: float = 0.005  # mm
    max_passes: int = 4


@dataclass(frozen=True)
class Robot:
    """Tissue frame -> robot base frame: p_base = R(rotation) p_tissue + translation."""

    rotation_deg: float = 0.0
    translation: tuple[float, float] = (0.0, 0.0)
    angular_speed: float | None = None  # rad/s of needle rotation; adds time_s to trajectories
    given: bool = False


@dataclass(frozen=True)
class Scenario:
    tissue: Tissue
    discretization: Discretization = field(default_factory=Discretization)
    needle: Needle | None = None
    loads: tuple[Load, ...] = ()
    load_steps: int = 10
    probes: tuple[tuple[float, float], ...] = ()
    solver: Solver = field(default_factory=Solver)
    planner: Planner = field(default_factory=Planner)
    robot: Robot = field(default_factory=Robot)
    name: str = ""
    source_text: str = ""
    study: Any = None  # stitchplan.study.StudySpec from the optional `study:` block


# --- field readers -------------------------------------------------------------------


def _fail(path: str, value: Any, expected: str) -> ScenarioError:
    return ScenarioError(f"{path}: got {value!r}, expected {expected}")


def _mapping(value: Any, path: str, allowed: tuple[str, ...]) -> dict:
    if not isinstance(value, dict):
        raise _fail(path, value, "a mapping")
    unknown = [k for k in value if k not in allowed]
    if unknown:
        raise ScenarioError(
            f"{path}: unknown key {unknown[0]!r}, expected one of: {', '.join(allowed)}"
        )
    return value


def _required(block: dict, key: str, path: str) -> Any:
    if key not in block:
        raise ScenarioError(f"{path}.{key}: missing, required")
    return block[key]


def _number(value: Any, path: str, *, positive: bool = False, nonnegative: bool = False,
            unit: str = "") -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    kind = "a positive number" if positive else "a non-negative number" if nonnegative else "a number"
    kind += f" ({unit})" if unit else ""
    if not ok or (positive and value <= 0) or (nonnegative and value < 0):
        raise _fail(path, value, kind)
    return float(value)


def _integer(value: Any, path: str, minimum: int = 1, maximum: int | None = None) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or value < minimum or (
        maximum is not None and value > maximum
    ):
        bound = f"between {minimum} and {maximum}" if maximum is not None else f">= {minimum}"
        raise _fail(path, value, f"an integer {bound}")
    return value


def _point(value: Any, path: str) -> tuple[float, float]:
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise _fail(path, value, "a pair [x, y] of numbers (mm)")
    return (_number(value[0], f"{path}[0]"), _number(value[1], f"{path}[1]"))


def _choice(value: Any, path: str, choices: tuple[str, ...]) -> str:
    if value not in choices:
        raise _fail(path, value, "one of " + ", ".join(choices))
    return value


# --- blocks --------------------------------------------------------------------------


def parse_material(raw: Any, path: str = "tissue.material") -> Material:
    block = _mapping(raw, path, ("model", "lame_lambda", "lame_mu"))
    return Material(
        model=_choice(block.get("model", "saint-venant-kirchhoff"), f"{path}.model", MATERIAL_MODELS),
        lame_lambda=_number(_required(block, "lame_lambda", path), f"{path}.lame_lambda",
                            nonnegative=True, unit="MPa"),
        lame_mu=_number(_required(block, "lame_mu", path), f"{path}.lame_mu", positive=True,
                        unit="MPa"),
    )


def parse_tissue(raw: Any, path: str = "tissue", need_material: bool = True) -> Tissue:
    block = _mapping(raw, path, ("size", "thickness", "material", "clamped"))
    size = _required(block, "size", path)
    if not isinstance(size, (list, tuple)) or len(size) != 2:
        raise _fail(f"{path}.size", size, "a pair [W, H] of positive numbers (mm)")
    width = _number(size[0], f"{path}.size[0]", positive=True, unit="mm")
    height = _number(size[1], f"{path}.size[1]", positive=True, unit="mm")
    thickness = _number(_required(block, "thickness", path), f"{path}.thickness", positive=True,
                        unit="mm")
    material = (parse_material(_required(block, "material", path), f"{path}.material")
                if need_material or "material" in block else Material())
    clamped = block.get("clamped", [])
    if not isinstance(clamped, (list, tuple)):
        raise _fail(f"{path}.clamped", clamped, "a list of edges among " + ", ".join(EDGES))
    edges = tuple(_choice(edge, f"{path}.clamped[{i}]", EDGES) for i, edge in enumerate(clamped))
    if len(set(edges)) != len(edges):
        raise _fail(f"{path}.clamped", list(clamped), "each edge at most once")
    return Tissue((width, height), thickness, material, edges)


def parse_discretization(raw: Any, path: str = "discretization") -> Discretization:
    if raw is None:
        return Discretization()
    block = _mapping(raw, path, ("spacing", "dilation", "quadrature_order", "basis_order",
                                 "cells_per_spacing", "needle_spacing", "needle_zone", "needle_refinement",
                                 "integration", "accuracy"))
    default = Discretization()
    dilation = _number(block.get("dilation", default.dilation), f"{path}.dilation", positive=True)
    if dilation <= 1.0:
        raise _fail(f"{path}.dilation", dilation,
                    "a number > 1 (kernel support / spacing; at least ~1.5 for a linear basis)")
    spacing = _number(block.get("spacing", default.spacing), f"{path}.spacing", positive=True, unit="mm")
    needle_spacing = block.get("needle_spacing")
    refinement = block.get("needle_refinement")
    if refinement is not None:
        refinement = _number(refinement, f"{path}.needle_refinement", positive=True)
        if refinement < 1.0:
            raise _fail(f"{path}.needle_refinement", refinement,
                        "a number >= 1 (spacing / spacing at the needle)")
        if needle_spacing is None and refinement > 1.0:
            needle_spacing = spacing / refinement
    if needle_spacing is not None:
        needle_spacing = _number(needle_spacing, f"{path}.needle_spacing", positive=True, unit="mm")
        if needle_spacing > spacing:
            raise _fail(f"{path}.needle_spacing", needle_spacing,
                        f"a spacing (mm) no larger than spacing = {spacing:g} mm")
    accuracy = block.get("accuracy")
    if accuracy is not None:
        accuracy = _number(accuracy, f"{path}.accuracy", positive=True, unit="mm, exit point")
    return Discretization(
        spacing=spacing,
        dilation=dilation,
        quadrature_order=_integer(block.get("quadrature_order", default.quadrature_order),
                                  f"{path}.quadrature_order", 1, 10),
        basis_order=_integer(block.get("basis_order", default.basis_order), f"{path}.basis_order",
                             1, 2),
        cells_per_spacing=_integer(block.get("cells_per_spacing", default.cells_per_spacing),
                                   f"{path}.cells_per_spacing", 1, 4),
        needle_spacing=needle_spacing,
        needle_zone=_number(block.get("needle_zone", default.needle_zone), f"{path}.needle_zone",
                            positive=True, unit="needle radii"),
        needle_refinement=refinement,
        integration=_choice(block.get("integration", default.integration), f"{path}.integration", INTEGRATIONS),
        accuracy=accuracy,
    )


def parse_needle(raw: Any, path: str = "needle") -> Needle:
    block = _mapping(raw, path, ("radius", "arc", "entry", "turn", "step", "friction",
                                 "cutting_force", "tip_tracking", "linear_solver"))
    arc = _number(block.get("arc", math.pi), f"{path}.arc", positive=True, unit="rad")
    if arc > 2 * math.pi:
        raise _fail(f"{path}.arc", arc, "a positive angle of at most 2*pi rad")
    step = _number(_required(block, "step", path), f"{path}.step", positive=True, unit="rad")
    if step > 0.5:
        raise _fail(f"{path}.step", step, "a positive angle of at most 0.5 rad per step")
    return Needle(
        radius=_number(_required(block, "radius", path), f"{path}.radius", positive=True, unit="mm"),
        arc=arc,
        entry=_point(_required(block, "entry", path), f"{path}.entry"),
        turn=_choice(_required(block, "turn", path), f"{path}.turn", ("cw", "ccw")),
        step=step,
        friction=_number(block.get("friction", 0.0), f"{path}.friction", nonnegative=True,
                         unit="N/mm"),
        cutting_force=_number(block.get("cutting_force", 0.0), f"{path}.cutting_force",
                              nonnegative=True, unit="N"),
        tip_tracking=_choice(block.get("tip_tracking", "levenberg-marquardt"), f"{path}.tip_tracking",
                             TIP_TRACKING),
        linear_solver=_choice(block.get("linear_solver", "direct"), f"{path}.linear_solver",
                              LINEAR_SOLVERS),
    )


def parse_loads(raw: Any, size: tuple[float, float], path: str = "loads") -> tuple[Load, ...]:
    if raw is None:
        return ()
    if not isinstance(raw, (list, tuple)):
        raise _fail(path, raw, "a list of loads")
    loads = []
    for i, item in enumerate(raw):
        item_path = f"{path}[{i}]"
        block = _mapping(item, item_path, ("segment", "force", "displacement"))
        segment = _required(block, "segment", item_path)
        if not isinstance(segment, (list, tuple)) or len(segment) != 2:
            raise _fail(f"{item_path}.segment", segment, "two points [[x0, y0], [x1, y1]] (mm)")
        p0 = _point(segment[0], f"{item_path}.segment[0]")
        p1 = _point(segment[1], f"{item_path}.segment[1]")
        if Rectangle.of_size(size).segment_edge(p0, p1) is None:
            raise _fail(f"{item_path}.segment", [list(p0), list(p1)],
                        f"a non-empty straight piece of one edge of the {size[0]:g} x {size[1]:g} mm tissue")
        has_force, has_disp = "force" in block, "displacement" in block
        if has_force == has_disp:
            raise ScenarioError(f"{item_path}: expected exactly one of 'force' (N) or "
                                f"'displacement' (mm), got {sorted(k for k in block if k != 'segment') or 'neither'}")
        force = _point(block["force"], f"{item_path}.force") if has_force else None
        displacement = _point(block["displacement"], f"{item_path}.displacement") if has_disp else None
        loads.append(Load((p0, p1), force, displacement))
    return tuple(loads)


def parse_solver(raw: Any, path: str = "solver") -> Solver:
    if raw is None:
        return Solver()
    block = _mapping(raw, path, ("residual_tolerance", "increment_tolerance", "max_iterations",
                                 "max_step_cuts"))
    d = Solver()
    return Solver(
        residual_tolerance=_number(block.get("residual_tolerance", d.residual_tolerance),
                                   f"{path}.residual_tolerance", positive=True),
        increment_tolerance=_number(block.get("increment_tolerance", d.increment_tolerance),
                                    f"{path}.increment_tolerance", positive=True),
        max_iterations=_integer(block.get("max_iterations", d.max_iterations),
                                f"{path}.max_iterations", 1, 500),
        max_step_cuts=_integer(block.get("max_step_cuts", d.max_step_cuts),
                               f"{path}.max_step_cuts", 0, 30),
    )


# graded needle scenes: spacing at the needle = spacing / DEFAULT_NEEDLE_REFINEMENT
DEFAULT_NEEDLE_REFINEMENT = 2.0


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
    if needle is None:
        return min(tissue.size) / 20.0
    return min(0.4 * needle.radius, max(tissue.size) / 20.0, min(tissue.size) / 8.0)


def parse_planner(raw: Any, path: str = "planner") -> Planner:
    if raw is None:
        return Planner()
    block = _mapping(raw, path, ("tolerance", "max_iterations", "strict", "exit_tolerance", "max_passes"))
    d = Planner()
    strict = block.get("strict", d.strict)
    if not isinstance(strict, bool):
        raise _fail(f"{path}.strict", strict, "true or false")
    return Planner(
        tolerance=_number(block.get("tolerance", d.tolerance), f"{path}.tolerance", positive=True, unit="mm"),
        max_iterations=_integer(block.get("max_iterations", d.max_iterations), f"{path}.max_iterations", 1, 1000),
        strict=strict,
        exit_tolerance=_number(block.get("exit_tolerance", d.exit_tolerance), f"{path}.exit_tolerance",
                               positive=True, unit="mm"),
        max_passes=_integer(block.get("max_passes", d.max_passes), f"{path}.max_passes", 1, 20),
    )


def parse_robot(raw: Any, path: str = "robot") -> Robot:
    if raw is None:
        return Robot()
    block = _mapping(raw, path, ("base_transform", "angular_speed"))
    rotation, translation = 0.0, (0.0, 0.0)
    given = "base_transform" in block
    if given:
        transform = _mapping(block["base_transform"], f"{path}.base_transform", ("rotation_deg", "translation"))
        rotation = _number(transform.get("rotation_deg", 0.0), f"{path}.base_transform.rotation_deg", unit="deg")
        translation = _point(transform.get("translation", [0.0, 0.0]), f"{path}.base_transform.translation")
    speed = block.get("angular_speed")
    speed = None if speed is None else _number(speed, f"{path}.angular_speed", positive=True, unit="rad/s")
    return Robot(rotation, translation, speed, given)


SCENARIO_KEYS = ("name", "tissue", "discretization", "needle", "loads", "load_steps", "probes",
                 "solver", "planner", "robot", "study")


def parse_scenario(raw: Any, source_text: str = "") -> Scenario:
    block = _mapping(raw, "scenario", SCENARIO_KEYS)
    tissue = parse_tissue(_required(block, "tissue", "scenario"))
    probes_raw = block.get("probes", [])
    if not isinstance(probes_raw, (list, tuple)):
        raise _fail("probes", probes_raw, "a list of reference points [[x, y], ...] (mm)")
    probes = tuple(_point(p, f"probes[{i}]") for i, p in enumerate(probes_raw))
    w, h = tissue.size
    for i, (x, y) in enumerate(probes):
        if not (0 <= x <= w and 0 <= y <= h):
            raise _fail(f"probes[{i}]", [x, y], f"a point inside [0, {w:g}] x [0, {h:g}] mm")
    discretization = parse_discretization(block.get("discretization"))
    needle = parse_needle(block["needle"]) if block.get("needle") is not None else None
    given = block.get("discretization") if isinstance(block.get("discretization"), dict) else {}
    if "spacing" not in given:
        spacing = default_spacing(tissue, needle)
        refinement = discretization.needle_refinement
        if needle is not None and refinement is None and discretization.needle_spacing is None:
            refinement = DEFAULT_NEEDLE_REFINEMENT
        discretization = parse_discretization({**given, "spacing": spacing, "needle_refinement": refinement})
    name = block.get("name", "")
    if not isinstance(name, str):
        raise _fail("name", name, "a string")
    return Scenario(
        tissue=tissue,
        discretization=discretization,
        needle=needle,
        loads=parse_loads(block.get("loads"), tissue.size),
        load_steps=_integer(block.get("load_steps", 10), "load_steps", 1, 10000),
        probes=probes,
        solver=parse_solver(block.get("solver")),
        planner=parse_planner(block.get("planner")),
        robot=parse_robot(block.get("robot")),
        name=name,
        source_text=source_text,
        study=_parse_study(block.get("study")),
    )


def _parse_study(raw: Any):
    if raw is None:
        return None
    from .study import parse_study

    return parse_study(raw)


def read_yaml(path: str | Path) -> tuple[Any, str]:
    """Read a YAML file, turning I/O and syntax problems into ScenarioError."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as error:
        raise ScenarioError(f"{path}: cannot be read ({error.strerror or error})") from None
    try:
        return yaml.safe_load(text), text
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise ScenarioError(f"{path}: not valid YAML{where}") from None


def load_scenario(path: str | Path) -> Scenario:
    raw, text = read_yaml(path)
    return parse_scenario(raw, text)


def with_discretization(scenario: Scenario, **overrides: float | int | None) -> Scenario:
    """Copy of the scenario with discretization fields replaced (None values ignored)."""
    from dataclasses import replace

    changes = {k: v for k, v in overrides.items() if v is not None}
    if "spacing" in changes and "accuracy" not in overrides:
        changes["accuracy"] = None  # an explicit spacing replaces the auto discretization
    return replace(scenario, discretization=scenario.discretization.replaced(**changes))
