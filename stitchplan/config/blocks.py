"""The blocks of a scenario file (tissue, material, discretization, needle, loads, solver;
the planner and robot blocks are plan_blocks') as validated, frozen dataclasses.

They are pydantic dataclasses: constructing one validates it, `dataclasses.replace` gives a
validated copy, `asdict` and hashing work as for plain dataclasses. Units as in
README, "Units and frames": mm, N, MPa, rad. The checks of a tissue's shape are tissue_shape's; those of the
loads against the clamped edges, load_checks'.
"""

from __future__ import annotations

import functools
import math
from dataclasses import asdict
from dataclasses import field as dataclasses_field
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    WrapValidator,
    field_validator,
    model_validator,
)
from pydantic.dataclasses import dataclass

from ..geometry.polygon_domain import PolygonDomain
from ..geometry.polygons import circle_polygon
from ..geometry.rectangle import Rectangle
from .boundary_points import entry_on_boundary, placed, segment_on_boundary
from .fields import (
    BLOCK,
    EDGES,
    INTEGRATIONS,
    MATERIAL_MODELS,
    TURNS,
    BasisOrder,
    CellsPerSpacing,
    Dilation,
    Flag,
    LinearSolver,
    NeedleStep,
    Number,
    Positive,
    PositiveMM,
    QuadratureOrder,
    TipTracking,
    choice,
    described,
    integer,
    number,
    pair,
    problem,
    sequence,
    within,
)
from .messages import Shown, adapter, combined, short, valid_or_none, validate
from .tissue_shape import clamps_on_boundary, counter_clockwise, shape_loops, shape_problems


def _file_schema(required: tuple[str, ...], one_of: tuple[str, ...], schema: dict) -> None:
    """Fields a file must give although Python callers may leave them to their defaults, and
    the fields of which a file gives exactly one (not null)."""
    if one_of:
        schema["oneOf"] = [{"required": [name], "properties": {name: {"not": {"type": "null"}}}} for name in one_of]
    if required:
        schema["required"] = sorted(set(schema.get("required", [])) | set(required))
        for name in required:
            schema["properties"][name].pop("default", None)


def _field_errors(handler, data: Any) -> list:
    """The field-level errors of `data` (none when its fields validate), so that a block-level
    problem is reported together with them rather than instead of them."""
    try:
        handler(data)
    except ValidationError as error:
        return error.errors()
    return []


def _required_in_files(names: tuple[str, ...]):
    def check(cls, data: Any, handler):
        missing = [name for name in names if isinstance(data, dict) and name not in data]
        if not missing:
            return handler(data)
        raise combined(_field_errors(handler, data)
                       + [{"type": "missing", "loc": (name,), "msg": "Field required", "input": data}
                          for name in missing])

    return model_validator(mode="wrap")(check)


def block(*, file_required: tuple[str, ...] = (), one_of: tuple[str, ...] = (), title: str | None = None,
          **options):
    """A frozen pydantic dataclass refusing unknown keys and non-finite numbers.
    `file_required`: keys a file must give although the class has defaults for them;
    `one_of`: keys of which a file gives exactly one (checked by the class, told to the JSON
    Schema)."""

    def make(cls):
        if file_required:
            cls._file_required = _required_in_files(file_required)
        config = ConfigDict(**BLOCK, json_schema_extra=functools.partial(_file_schema, file_required, one_of))
        if title:
            config["title"] = title
        return dataclass(frozen=True, config=config, **options)(cls)

    return make


def within_limits(limits: dict) -> Any:
    """A wrap validator refusing a file's numbers (data a mapping) outside `limits` (key:
    ((low, high), expected)), reported with every other problem of the block. A value the
    field's own type refuses (a negative thickness, a string) is left to that type."""

    def check(cls, data: Any, handler):
        problems = []
        for key, ((low, high), expected) in limits.items():
            value = data.get(key) if isinstance(data, dict) else None
            if (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
                    and value > 0 and not low <= value <= high):
                problems.append(problem(expected, field=key, value=value))
        if not problems:
            return handler(data)
        raise combined([*_field_errors(handler, data), *problems])

    return model_validator(mode="wrap")(check)


# A file's moduli, MPa, as a calibration's search ranges (config.calibration): 1e-6 MPa is 1 Pa,
# softer than any tissue, 1e6 MPa is 1 TPa, stiffer than diamond; beyond them a modulus is a
# unit mistake. At 1e300 MPa (or lame_lambda 1e7 with the phantom's lame_mu) Newton failed in
# the first load step, and at a lame_mu of 1e-300 the slab inverted there, naming no field.
MODULUS_RANGE_MPA = (1e-6, 1e6)
_MODULUS_WHY = (f"(MPa; below {MODULUS_RANGE_MPA[0]:g}, 1 Pa, softer than any tissue, or beyond "
                f"{MODULUS_RANGE_MPA[1]:g}, 1 TPa, stiffer than diamond, is a unit mistake)")
# lame_lambda has no lower bound besides 0: a calibration's linear grid from 0 may fit any
# value above it (a Poisson's ratio near 0), and a tiny one runs as 0 does
MODULUS_LIMITS = {
    "lame_lambda": ((0.0, MODULUS_RANGE_MPA[1]), f"a non-negative number of at most {MODULUS_RANGE_MPA[1]:g} "
                                                 f"(MPa; beyond it, 1 TPa, stiffer than diamond, is a unit mistake)"),
    "lame_mu": (MODULUS_RANGE_MPA, f"a number between {MODULUS_RANGE_MPA[0]:g} and "
                                   f"{MODULUS_RANGE_MPA[1]:g} {_MODULUS_WHY}"),
}


@block(file_required=("lame_lambda", "lame_mu"))
class Material:
    """Defaults (the thesis's phantom) for Python callers; a file must give both moduli."""

    model: described(choice(MATERIAL_MODELS), "constitutive law") = "saint-venant-kirchhoff"
    lame_lambda: described(number("a non-negative number (MPa)", ge=0), "Lamé lambda, MPa",
                           maximum=MODULUS_RANGE_MPA[1]) = 0.189151
    lame_mu: described(number("a positive number (MPa)", gt=0), "Lamé mu (shear modulus), MPa",
                       minimum=MODULUS_RANGE_MPA[0], maximum=MODULUS_RANGE_MPA[1]) = 0.147688

    _moduli_within_limits = within_limits(MODULUS_LIMITS)


# Lengths and points of a scene beyond 10 m (the robot's frame ends there too, MAX_BASE_OFFSET_MM)
# are a unit mistake, not a tissue, and so are a circular hole below a nanometre (a hole of
# 0.1 um still runs: tests/test_thin_features.py) and a needle of a radius beyond a metre or
# below 0.05 mm (a suture needle's is 5-40 mm, a microsurgical one's about 1 mm; 0.05 mm
# catches every one of them written in metres); at 1e300 mm the geometry overflows and at
# 1e-20 mm a hole's vertices coincide, failing later without naming the field, and a needle
# of 1e-300 mm ran 0 steps.
MAX_SCENE_MM = 10_000.0
# the smallest tissue, its larger side: below it every tissue is one written in m (a 6 x 3 cm
# block as [0.06, 0.03]); a real patch a needle passes through is millimetres at the least
MIN_TISSUE_MM = 0.5
MIN_HOLE_RADIUS_MM = 1e-6
NEEDLE_RADIUS_RANGE_MM = (0.05, 1_000.0)
MIN_NEEDLE_RADIUS_MM, MAX_NEEDLE_RADIUS_MM = NEEDLE_RADIUS_RANGE_MM
_BEYOND = f"(mm; a tissue reaching beyond {MAX_SCENE_MM:g} mm is a unit mistake)"
SceneLength = within(PositiveMM, MAX_SCENE_MM, f"a positive number of at most {MAX_SCENE_MM:g} {_BEYOND}")
SceneCoordinate = within(Number, MAX_SCENE_MM, f"a number between {-MAX_SCENE_MM:g} and {MAX_SCENE_MM:g} {_BEYOND}",
                         low=-MAX_SCENE_MM)
ScenePoint = pair("a pair [x, y] of numbers (mm)", SceneCoordinate)
Size = pair("a pair [W, H] of positive numbers (mm)", SceneLength)
Edges = sequence(choice(EDGES), "a list of edges among " + ", ".join(EDGES))
PolygonPoints = sequence(ScenePoint, "a list of at least three points [[x, y], ...] (mm)", min_length=3)
SegmentPoints = pair("two points [[x0, y0], [x1, y1]] (mm)", ScenePoint)
HoleRadius = within(PositiveMM, MAX_SCENE_MM,
                    f"a number between {MIN_HOLE_RADIUS_MM:g} and {MAX_SCENE_MM:g} (mm; a hole below a nanometre "
                    f"or a tissue reaching beyond {MAX_SCENE_MM:g} mm is a unit mistake)", low=MIN_HOLE_RADIUS_MM)
# a particle spacing a file or an option gives: beyond the scene's bound it is a unit mistake too
# (1e308 mm passed the file's checks, and its replay at twice the spacing, inf, was refused
# naming no file); a spacing derived from one (a replay's, a study run's) is not bounded here
SPACING_EXPECTED = (f"a positive number of at most {MAX_SCENE_MM:g} (mm; a spacing beyond {MAX_SCENE_MM:g} mm, "
                    "the bound of every length of a scene, is a unit mistake)")
SceneSpacing = within(PositiveMM, MAX_SCENE_MM, SPACING_EXPECTED)
NeedleRadius = within(PositiveMM, MAX_NEEDLE_RADIUS_MM,
                      f"a number between {MIN_NEEDLE_RADIUS_MM:g} and {MAX_NEEDLE_RADIUS_MM:g} (mm; a suture "
                      "needle's radius is about 1-40 mm: a smaller or larger one is a unit mistake, such as "
                      "metres written for mm)", low=MIN_NEEDLE_RADIUS_MM)


@block()
class Circle:
    center: described(ScenePoint, "centre, mm")
    radius: described(HoleRadius, f"radius, mm; {MIN_HOLE_RADIUS_MM:g} to {MAX_SCENE_MM:g}")


def _polygon_or_circle(shape):
    """A Hole or a Region, refused unless it gives exactly one of its polygon and circle."""
    if (shape.polygon is None) == (shape.circle is None):
        both = shape.polygon is not None
        raise problem("exactly one of 'polygon' or 'circle'", value=Shown("both" if both else "neither"),
                      absent=() if both else ("polygon", "circle"))
    return shape


@block(one_of=("polygon", "circle"))
class Hole:
    """A cut-out with free edges: a polygon or a circle (held as a polygon of
    geometry.polygons.CIRCLE_SEGMENTS edges with its vertices on the circle)."""

    polygon: described(PolygonPoints | None, "vertices, mm") = None
    circle: described(Circle | None, "{center: [x, y], radius: r}, mm") = None

    @model_validator(mode="after")
    def _one_shape(self) -> Hole:
        return _polygon_or_circle(self)

    def vertices(self) -> np.ndarray:
        """Counter-clockwise vertices (k, 2)."""
        if self.circle is not None:
            return circle_polygon(self.circle.center, self.circle.radius)
        return counter_clockwise(np.asarray(self.polygon, dtype=float))


@block(one_of=("polygon", "circle"))
class Region:
    """An area of another material: a polygon or a circle (held as a polygon, as a hole's
    circle is); the first region holding a point gives its material."""

    material: described(Material, "the region's hyperelastic material")
    polygon: described(PolygonPoints | None, "vertices, mm; the first region holding a point gives its material") = None
    circle: described(Circle | None, "{center: [x, y], radius: r}, mm") = None

    @model_validator(mode="after")
    def _one_shape(self) -> Region:
        return _polygon_or_circle(self)

    def vertices(self) -> np.ndarray:
        """The region's vertices (k, 2): a polygon's as the file gives them, a circle's
        counter-clockwise."""
        if self.circle is not None:
            return circle_polygon(self.circle.center, self.circle.radius)
        return np.asarray(self.polygon, dtype=float)

    def shown(self) -> tuple[str, Any]:
        """The field that gives the region's shape and its value, for a message."""
        return ("polygon", self.polygon) if self.polygon is not None else ("circle", asdict(self.circle))

    def as_block(self) -> dict:
        """The region as a scenario file gives it (plain lists and numbers): its shape and material."""
        if self.circle is not None:
            shape = {"circle": {"center": [float(v) for v in self.circle.center], "radius": float(self.circle.radius)}}
        else:
            shape = {"polygon": [[float(x), float(y)] for x, y in self.polygon]}
        return {**shape, "material": asdict(self.material)}


@block()
class ClampedSegment:
    segment: described(SegmentPoints, "straight piece of the boundary held fixed, mm")


CLAMP_EXPECTED = "an edge among " + ", ".join(EDGES) + " or {segment: [[x0, y0], [x1, y1]]}"


def _clamp_item(value: Any, handler) -> Any:
    """A clamped item: a mapping is a {segment: ...} piece, its own errors kept (an unknown or
    missing key named); anything else an edge's name."""
    if isinstance(value, dict):
        try:
            return adapter(ClampedSegment).validate_python(value)
        except ValidationError as error:
            raise combined(error.errors()) from None
    try:
        return handler(value)
    except ValidationError:
        raise problem(CLAMP_EXPECTED) from None


_clamp_item.expected = CLAMP_EXPECTED  # read by the message of a missing field
Clamp = Annotated[Literal[EDGES] | ClampedSegment, Field(union_mode="left_to_right"), WrapValidator(_clamp_item)]
Clamps = Annotated[sequence(Clamp, "a list of edges or {segment: ...} pieces of the boundary"),
                   Field(json_schema_extra={"uniqueItems": True})]  # each edge at most once (Tissue)


# Magnitudes beyond which a file's value is a unit mistake, not a tissue or a needle (as a
# load's force beyond MAX_LOAD_FORCE_N). A slab thinner than a micrometre is thinner than a cell
# (no needle passes through it), thicker than 10 m is no tissue (the robot's frame ends at
# 10 m too); a mega-newton at the needle's tip, or on each millimetre of needle inside the
# tissue, is 1e6 times a suture needle's cutting force and friction (0.7 N, 0.06 N/mm). At
# 1e300 mm, 1e-300 mm or 1e7 N the numerics fail in the first step instead, naming no field.
# Python callers may go beyond them (the numerics' overflow checks are tested that way).
THICKNESS_RANGE_MM = (1e-3, 1e4)
MAX_CUTTING_FORCE_N = 1e6
MAX_FRICTION_N_PER_MM = 1e6
THICKNESS_LIMITS = {"thickness": (THICKNESS_RANGE_MM, f"a number between {THICKNESS_RANGE_MM[0]:g} and "
                                  f"{THICKNESS_RANGE_MM[1]:g} (mm; a thinner or thicker slab is a unit mistake)")}
NEEDLE_LIMITS = {
    "friction": ((0.0, MAX_FRICTION_N_PER_MM), f"a number between 0 and {MAX_FRICTION_N_PER_MM:g} (N/mm; a "
                 "larger force on each millimetre of needle is a unit mistake)"),
    "cutting_force": ((0.0, MAX_CUTTING_FORCE_N), f"a number between 0 and {MAX_CUTTING_FORCE_N:g} (N; a "
                      "larger force at the needle's tip is a unit mistake)"),
}


@block(file_required=("thickness", "material"), one_of=("size", "outline"))
class Tissue:
    """The tissue: the rectangle `size` or the polygon `outline` (clockwise accepted and walked
    counter-clockwise), optional holes and material regions (README, "Tissue shapes")."""

    size: described(Size | None, "[W, H] mm: the rectangle [0, W] x [0, H]; or give outline") = None
    thickness: described(PositiveMM, f"out-of-plane thickness t, mm (file forces are totals over t); "
                                      f"{THICKNESS_RANGE_MM[0]:g} to {THICKNESS_RANGE_MM[1]:g}",
                         minimum=THICKNESS_RANGE_MM[0], maximum=THICKNESS_RANGE_MM[1]) = 1.0
    material: described(Material, "hyperelastic material") = dataclasses_field(default_factory=Material)
    clamped: described(Clamps, "edges held fixed: any of " + ", ".join(EDGES)
                       + " (rectangles), or {segment: [[x0, y0], [x1, y1]]} pieces of the boundary") = ()
    outline: described(PolygonPoints | None, "a simple polygon [[x, y], ...] (mm), instead of size") = None
    holes: described(sequence(Hole, "a list of holes ({polygon: ...} or {circle: ...})"),
                     "cut-outs with free edges; one reaching the outline is cut out of it") = ()
    regions: described(sequence(Region, "a list of regions ({polygon: ...} or {circle: ...}, and material: ...)"),
                       "areas of other materials; the first region holding a point wins") = ()

    _thickness_within_limits = within_limits(THICKNESS_LIMITS)

    @field_validator("size", "outline")
    @classmethod
    def _not_in_metres(cls, value: Any, info: ValidationInfo) -> Any:
        """A tissue under MIN_TISSUE_MM across is a unit mistake (metres), refused rather
        than run on a speck (a 60 um block stretched to 16 times its size)."""
        if value is not None and float(np.ptp(np.asarray(value, dtype=float).reshape(-1, 2), axis=0).max()
                                       if info.field_name == "outline" else max(value)) < MIN_TISSUE_MM:
            raise problem(f"a tissue at least {MIN_TISSUE_MM:g} mm across (mm; a smaller one is a tissue written "
                          "in m)")
        return value

    @field_validator("clamped")
    @classmethod
    def _each_edge_once(cls, clamped: tuple) -> tuple:
        if len(set(clamped)) != len(clamped):
            raise problem("each edge at most once")
        return clamped

    @model_validator(mode="after")
    def _shape(self) -> Tissue:
        problems = shape_problems(self)
        if problems:
            raise combined(problems)
        # clamped segments as the run uses them: their ends moved onto the boundary
        object.__setattr__(self, "clamped", clamps_on_boundary(self.clamped, self.domain)[0])
        return self

    @functools.cached_property
    def loops(self) -> tuple:
        """shape_loops of this tissue, made once (its polygon difference is shapely's work)."""
        return shape_loops(self)

    @functools.cached_property
    def domain(self) -> Rectangle | PolygonDomain:
        outer, inside, cut, _ = self.loops
        holes = tuple(vertices for _, vertices in inside)
        if self.outline is None and not cut:
            return Rectangle.of_size(self.size) if not holes else PolygonDomain.rectangle(self.size, holes)
        return PolygonDomain(outer, holes)

    @property
    def bounding_size(self) -> tuple[float, float]:
        """Sides of the bounding box (mm): `size` for a rectangle."""
        return tuple(self.domain.size)

    def clamped_pieces(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """End points of every clamped piece of the boundary."""
        return [self.domain.edge(item) if isinstance(item, str) else
                (np.asarray(item.segment[0], float), np.asarray(item.segment[1], float))
                for item in self.clamped]


def shape_domain(tissue: Any) -> Rectangle | PolygonDomain | None:
    """The domain of a file's `tissue:` block from its shape keys alone (size or outline and
    holes), or None when they are not valid (their own errors are reported elsewhere)."""
    if not isinstance(tissue, dict):
        return None
    shape = {key: tissue[key] for key in ("size", "outline", "holes") if key in tissue}
    valid = valid_or_none(Tissue, {**shape, "thickness": 1.0, "material": Material()})
    return None if valid is None else valid.domain


@block(title="discretization")
class Discretization:
    # a file without a spacing gets default_spacing_of's, not the 5 mm of Python callers
    spacing: described(PositiveMM, "particle spacing, mm; default min(W, H)/20, with a needle 2r/5 "
                                   "(at most max(W, H)/20 and min(W, H)/8)", drop=("default",)) = 5.0
    dilation: described(Dilation, "kernel support a = dilation x spacing") = 2.0
    quadrature_order: described(QuadratureOrder, "Gauss points per direction per background cell") = 2
    basis_order: described(BasisOrder, "1 linear, 2 quadratic RK basis") = 1
    cells_per_spacing: described(CellsPerSpacing, "background cells per particle spacing") = 1
    # graded particles (see discretization.graded_particles): `needle_spacing` within
    # `needle_zone` needle radii of the needle centre, growing to `spacing` away from it
    needle_spacing: described(PositiveMM | None, "particle spacing near the needle, mm (graded "
                                          "particles); at most spacing") = None
    needle_zone: described(number("a positive number (needle radii)", gt=0),
                           "graded zone around the needle centre, needle radii") = 1.5
    # how fast the graded particles coarsen beyond the needle's zone: leaf side at most the
    # needle spacing + needle_grading x the distance to the zone (2:1 balanced)
    needle_grading: described(number("a positive number (mm per mm)", gt=0),
                              "growth of the particle spacing per mm of distance beyond the "
                              "needle zone") = 0.5
    # needle_spacing = spacing / needle_refinement when no needle_spacing is given, so that
    # `--spacing` refines the graded arrangement as a whole (the default for needle scenes)
    needle_refinement: described(number("a number >= 1 (spacing / spacing at the needle)", ge=1) | None,
                                 "needle_spacing = spacing / needle_refinement; default 2 with a "
                                 "needle and no spacing", drop=("default",)) = None
    # particles graded toward the ends of load segments inside an edge, where the solution
    # is singular (stitchplan.tissue.particles.end_spacing): leaf side there spacing / 2^levels,
    # levels = segment_end_levels at the default spacing, one more per halving; 0: none
    segment_end_levels: described(integer(0, 8), "particle refinement levels at load-segment "
                                                 "ends (at the default spacing; one more per "
                                                 "halving of the spacing); 0: none") = 3
    # particles graded toward the needle's entry and exit points, where the tip with its
    # cutting force meets the free boundary (stitchplan.needle.geometry.needle_end_zones):
    # leaf side there needle_spacing / 2^levels at the default spacing, one more per halving;
    # 0: none
    needle_end_levels: described(integer(0, 8), "particle refinement levels below the needle "
                                                "spacing at the needle's entry and exit (at the "
                                                "default spacing; one more per halving of the "
                                                "spacing); 0: none") = 0
    # particles graded toward the edges between regions of different materials, where the
    # strain jumps and the smooth RK functions smear its kink (stitchplan.tissue.shapes.
    # interface_zones): leaf side there spacing / 2^levels at the default spacing, one more per
    # halving; 0: none
    interface_levels: described(integer(0, 8), "particle refinement levels at the interfaces between "
                                               "material regions (at the default spacing; one more per "
                                               "halving of the spacing); 0: none") = 0
    # particles graded toward the round holes the default spacing does not resolve, whose wall
    # carries a stress concentration about an inradius long (stitchplan.tissue.shapes.hole_zones):
    # leaf side there at most inradius / hole_resolution at the default spacing, as many levels
    # below the spacing at any other; 0: none
    hole_resolution: described(number("a number between 0 and 16 (leaf sides per inradius)", ge=0, le=16),
                               "particle spacings across a round hole's inradius at its wall (at the "
                               "default spacing; finer and coarser with the spacing); 0: as the "
                               "spacing") = 2.0
    # "gauss": Galerkin with background-cell Gauss quadrature; "vci": the test-function
    # gradients corrected so that the quadrature satisfies the divergence theorem
    # (variationally consistent integration; passes the linear patch test; deform only)
    integration: described(choice(INTEGRATIONS), "gauss, or vci (variationally consistent; "
                                                 "deform and calibrate)") = "gauss"
    # exit-point accuracy (mm): the auto discretization (stitchplan.study.auto) picks the rest
    # at least a micrometre: the planner's own tolerance is 1e-3 mm and no robot places a
    # needle closer than that, so a finer target only runs the auto search to its limits
    accuracy: described(number("a number >= 0.001 (mm, exit point; a micrometre is the finest target)",
                               ge=1e-3) | None,
                        "exit-point accuracy, mm: simulate and plan choose the discretization") = None

    @model_validator(mode="after")
    def _graded(self, info: ValidationInfo) -> Discretization:
        given = (info.context or {}).get("discretization_given", ())  # the keys a scenario file gives
        for key in ("spacing", "needle_spacing"):  # a file's own spacings (SceneSpacing)
            value = getattr(self, key)
            if key in given and value is not None and value > MAX_SCENE_MM:
                raise problem(SPACING_EXPECTED, field=key, value=value)
        # two ways to the same value: the one not taken would be dropped without a word
        if "needle_spacing" in given and "needle_refinement" in given:
            raise problem(f"either needle_spacing or needle_refinement (needle_refinement {self.needle_refinement:g} "
                          f"sets needle_spacing = spacing / {self.needle_refinement:g} = "
                          f"{self.spacing / self.needle_refinement:g} mm)", field="needle_spacing",
                          value=self.needle_spacing)
        if self.accuracy is not None:  # the auto discretization chooses these
            for key in ("spacing", "needle_spacing", "needle_refinement"):
                if key in given:
                    raise problem(f"no {key} with accuracy {self.accuracy:g} mm (the auto discretization "
                                  f"chooses the spacings; give one or the other)", field=key,
                                  value=getattr(self, key))
        if self.needle_spacing is None and self.needle_refinement is not None and self.needle_refinement > 1:
            object.__setattr__(self, "needle_spacing", self.spacing / self.needle_refinement)
        spacing_known = not (info.context or {}).get("default_spacing_unknown")
        if spacing_known and self.needle_spacing is not None and self.needle_spacing > self.spacing:
            raise problem(f"a spacing (mm) no larger than spacing = {self.spacing:g} mm",
                          field="needle_spacing", value=self.needle_spacing)
        return self

    def as_input(self) -> dict:
        """The block as a scenario file would give it: parse_discretization(d.as_input())
        returns d, and a needle spacing derived from needle_refinement stays derived, so it
        follows a changed spacing."""
        values = asdict(self)
        if self.needle_refinement is not None:
            values["needle_spacing"] = None
        return values

    def replaced(self, path: str = "discretization", **changes) -> Discretization:
        """A validated copy with `changes` applied (None is a value here: needle_spacing=None
        makes the particles uniform). A needle spacing derived from needle_refinement follows
        a changed spacing unless needle_spacing is given; `path` names the block in errors."""
        return parse_discretization({**self.as_input(), **changes}, path)


def default_spacing_of(size: tuple[float, float], radius: float | None) -> float:
    """The spacing of a file that gives none (see scenario.default_spacing): a twentieth of
    the smaller side; with a needle of `radius` 2/5 of it, at most a twentieth of the larger
    side and an eighth of the smaller one."""
    if radius is None:
        return min(size) / 20.0
    return min(0.4 * radius, max(size) / 20.0, min(size) / 8.0)


def coarsest_spacing(size: tuple[float, float]) -> float:
    """The coarsest spacing a model of a tissue whose bounding box has `size` (mm) may have:
    half its smaller side, so that at least three particles span it (coarser, the model means
    nothing: resources.guard's `_coarse_refusal`, a calibration's discretization estimate)."""
    return min(size) / 2.0


def parse_discretization(raw: Any, path: str = "discretization") -> Discretization:
    """The `discretization:` block (None: the defaults); errors name fields below `path`."""
    return Discretization() if raw is None else validate(Discretization, raw, path)



# the needle's lean at entry (needle.entry_tilt, planner.max_entry_tilt): up to 1 rad (57 deg)
# from the orthogonal entry; nearer pi/2 the needle would run along the surface instead of in
MAX_ENTRY_TILT = 1.0
EntryTilt = number(f"an angle between {-MAX_ENTRY_TILT:g} and {MAX_ENTRY_TILT:g} rad", ge=-MAX_ENTRY_TILT,
                   le=MAX_ENTRY_TILT)


@block(kw_only=True)
class Needle:
    radius: described(NeedleRadius, f"needle radius, mm; {MIN_NEEDLE_RADIUS_MM:g} to {MAX_NEEDLE_RADIUS_MM:g}")
    arc: described(number("a positive angle of at most 2*pi rad", gt=0, le=2 * math.pi),
                   "rad swept by the needle body (1/2 circle = pi)") = math.pi
    entry: described(ScenePoint, "reference point on the boundary where the tip enters, mm")
    turn: described(choice(TURNS), "cw or ccw: the way the tip turns after entry")
    step: described(NeedleStep, "rad of needle rotation per step")
    friction: described(number("a non-negative number (N/mm)", ge=0),
                        f"N per mm of needle inside the tissue; at most {MAX_FRICTION_N_PER_MM:g}",
                        maximum=MAX_FRICTION_N_PER_MM) = 0.0
    cutting_force: described(number("a non-negative number (N)", ge=0),
                             f"N at the tip needed to cut; at most {MAX_CUTTING_FORCE_N:g}",
                             maximum=MAX_CUTTING_FORCE_N) = 0.0
    tip_tracking: described(TipTracking, "levenberg-marquardt, inverse-gradient (strict) or auto "
                                         "(inverse-gradient, LM fallback)") = "levenberg-marquardt"
    linear_solver: described(LinearSolver, "direct or minres") = "direct"
    coupling: described(choice(("mortar", "points")),
                        "mortar (multiplier field on the track, loads spread along it) or points "
                        "(the thesis's one constraint per needle point)") = "mortar"
    cutting_length: described(PositiveMM, "mm of needle behind the tip that carries the cutting "
                                          "force (mortar coupling)") = 3.0
    multiplier_ends: described(choice(("segments", "arc")),
                               "mortar coupling: multiplier elements of whole track segments "
                               "(segments) or cut at exact arc lengths one local spacing apart "
                               "(arc)") = "segments"
    # fixed in mm, the multiplier space stays the same when the particles are refined
    # (benchmarks/results/needle_coupling.md, rows `fixed`)
    multiplier_length: described(PositiveMM | None,
                                 "mortar coupling: least length of a multiplier element, mm (never "
                                 "less than one local particle spacing; default: that spacing)") = None
    cutting_ramp: described(Flag, "mortar coupling: the cutting force grows with the cutting edge "
                                  "inside (cutting_force / cutting_length per mm) instead of acting "
                                  "whole from the first step") = False
    # 0: the thesis's orthogonal entry, which also places the desired exit (needle/geometry.py)
    entry_tilt: described(EntryTilt, "rad the needle leans from the orthogonal entry, turned about the "
                                     "entry point; positive deepens the bite (a turn against the "
                                     "needle's); the desired exit stays the orthogonal needle's") = 0.0

    _magnitudes_within_limits = within_limits(NEEDLE_LIMITS)

    @field_validator("entry")
    @classmethod
    def _entry_on_the_boundary(cls, entry, info: ValidationInfo):
        """A file's entry moved onto the boundary when within its input tolerance
        (boundary_points); off it or at a corner, refused (the domain comes with a file)."""
        domain = (info.context or {}).get("domain")
        if domain is None:
            return entry
        snapped, got, why = entry_on_boundary(domain, entry)
        if snapped is None:
            raise problem(why, value=Shown(f"{short(list(entry))}, {got}") if got else list(entry))
        return snapped

    @model_validator(mode="wrap")
    @classmethod
    def _cutting_length_on_the_needle(cls, data: Any, handler) -> Needle:
        """A file's cutting_length no longer than the needle (radius x arc): a longer cutting
        edge than the needle has is a mistake (the default, 3 mm, is left to the coupling, which
        spreads the force over the needle inside when that is shorter)."""
        needle = handler(data)
        length = needle.radius * needle.arc
        if isinstance(data, dict) and "cutting_length" in data and needle.cutting_length > length:
            raise problem(f"at most the needle's length {length:.4g} mm (radius {needle.radius:g} mm x arc "
                          f"{needle.arc:.4g} rad)", field="cutting_length",
                          value=Shown(f"{needle.cutting_length:g} mm"))
        return needle


# a load's force components: a total of a mega-newton on a slab of tissue is a unit mistake
# (kN or mN read as N), and near 1e300 N the solver's norms overflow; a prescribed
# displacement moving the boundary beyond the scene's 10 m is one too (at 1e300 mm the first
# load step failed with det F = -6e296, naming no field)
MAX_LOAD_FORCE_N = 1e6
LoadForce = number(f"a number between {-MAX_LOAD_FORCE_N:g} and {MAX_LOAD_FORCE_N:g} (N; a larger total force "
                   "on tissue is a unit mistake)", ge=-MAX_LOAD_FORCE_N, le=MAX_LOAD_FORCE_N)
LoadDisplacement = number(f"a number between {-MAX_SCENE_MM:g} and {MAX_SCENE_MM:g} (mm; a larger displacement "
                          "is a unit mistake)", ge=-MAX_SCENE_MM, le=MAX_SCENE_MM)


@block(one_of=("force", "displacement"))
class Load:
    segment: described(SegmentPoints, "straight piece of one edge, mm")
    force: described(pair("a pair [fx, fy] of numbers (N)", LoadForce) | None,
                     "N total, spread uniformly over the segment") = None
    displacement: described(pair("a pair [ux, uy] of numbers (mm)", LoadDisplacement) | None,
                            "mm, prescribed on the segment") = None

    @field_validator("segment")
    @classmethod
    def _on_one_edge(cls, segment, info: ValidationInfo):
        """Both ends moved onto the boundary when within its input tolerance (boundary_points)."""
        return placed(segment, info.context, segment_on_boundary)

    @model_validator(mode="wrap")
    @classmethod
    def _force_or_displacement(cls, data: Any, handler):
        if not isinstance(data, dict):  # constructed in Python
            load = handler(data)
            if (load.force is None) == (load.displacement is None):
                raise problem(ONE_KIND, value=Shown("both" if load.force else "neither"))
            return load
        given = [key for key in ("displacement", "force") if data.get(key) is not None]
        if len(given) == 1:
            return handler(data)
        raise combined([*_field_errors(handler, data),
                        problem(ONE_KIND, value=given or Shown("neither"), absent=() if given else ("force",
                                                                                                  "displacement"))])


ONE_KIND = "exactly one of 'force' (N) or 'displacement' (mm)"


# the load steps' relative Newton tolerances stay below this: at 1e-2 a solve may stop with a
# hundredth of the load out of balance, and from a residual tolerance of 1 up a solve stops
# before its first iteration (the model never moves: `calibrate material` then ends every
# modulus on its bound). The defaults are 5e-6 and 1e-8.
MAX_RELATIVE_TOLERANCE = 1e-2
RelativeTolerance = number(f"a positive number below {MAX_RELATIVE_TOLERANCE:g} (a relative tolerance)",
                           gt=0, lt=MAX_RELATIVE_TOLERANCE)
# a needle step's, of the needle force: from 1 up the tissue at rest met it, so every step
# stopped before its first iteration and the run reported the undeformed circle's exit
# (an exit error of 5e-16 mm); the bound itself is one of benchmarks/solver_tolerance.py's pairs
NeedleResidualTolerance = number(f"a positive number of at most {MAX_RELATIVE_TOLERANCE:g} (a relative tolerance: "
                                 "a larger one leaves the tissue out of balance, from 1 up at rest)",
                                 gt=0, le=MAX_RELATIVE_TOLERANCE)


@block(title="solver")
class Solver:
    # static load steps (deform, calibration): full Newton, which the increment test ends
    residual_tolerance: described(RelativeTolerance, "load steps' Newton: force residual tolerance (relative, "
                                  f"below {MAX_RELATIVE_TOLERANCE:g})") = 5e-6
    increment_tolerance: described(RelativeTolerance, "load steps' Newton: increment tolerance (relative, "
                                   f"below {MAX_RELATIVE_TOLERANCE:g})") = 1e-8
    max_iterations: described(integer(1, 500), "Newton iterations per load or needle step") = 25
    max_step_cuts: described(integer(0, 30), "halvings of a load step that fails to converge") = 6
    # a needle step's modified Newton stops on both; unset, they follow the coupling
    # (needle/newton.py NEWTON_TOLERANCES)
    needle_residual_tolerance: described(NeedleResidualTolerance | None, "needle steps' Newton: force residual / "
                                         "needle force (default 1e-3; 5e-6 with needle.coupling points; at most "
                                         f"{MAX_RELATIVE_TOLERANCE:g})") = None
    needle_constraint_tolerance: described(Positive | None, "needle steps' Newton: largest distance of the "
                                           "track from the needle / needle radius (default 1e-7; 1e-9 with "
                                           "needle.coupling points)") = None
