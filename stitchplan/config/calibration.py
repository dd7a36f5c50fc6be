"""The input file of `stitchplan calibrate material` (thesis appendix A.2; README,
"Calibration: from measurements to a scenario"): the tissue without its moduli, the experiments (loads and a marker
CSV each) and the search ranges of the fit. Validated like a scenario: every problem of the
file at once. Reading the marker CSVs is stitchplan.calibration.inputs' part."""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import (
    AfterValidator,
    Field,
    Strict,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from .blocks import (
    MODULUS_RANGE_MPA,
    THICKNESS_LIMITS,
    THICKNESS_RANGE_MM,
    Clamps,
    Discretization,
    Hole,
    Load,
    Material,
    PolygonPoints,
    Region,
    Size,
    Solver,
    Tissue,
    block,
    default_spacing_of,
    shape_domain,
    within_limits,
)
from .boundary_points import log_moves, segment_ends
from .fields import (
    MATERIAL_MODELS,
    Name,
    PositiveMM,
    choice,
    described,
    expecting,
    integer,
    number,
    problem,
    sequence,
)
from .load_checks import load_problems
from .messages import Shown, combined, valid_or_none, validate
from .tissue_shape import regions_covered_before, tissue_outside_regions

GRID_SCALES = ("log", "linear")
MarkerFile = Annotated[str, Strict(), Field(min_length=1),
                       expecting("a CSV file name (relative to the YAML file)")]
NO_MATERIAL = ("no material in a calibration file (the moduli are what is fitted; choose the "
               "model with fit.model)")


def _increasing(expected: str):
    def check(pair: tuple[float, float]) -> tuple[float, float]:
        if not pair[0] < pair[1]:
            raise problem(expected)
        return pair

    return AfterValidator(check)


# The moduli a search range may reach, MPa. 1e-6 MPa is 1 Pa, a thousand times softer than
# the softest soft tissues (brain, fat: about 1 kPa); 1e6 MPa is 1 TPa, stiffer than diamond
# (shear modulus about 0.5 TPa). Outside them the moduli are no material the fit can resolve:
# bounds such as [1e-200, 1e-199] underflow (their geometric middle is 0.0), a range over
# hundreds of decades overflows the least squares' trust region and leaves the grid a point
# per fifty decades. Within them a range spans at most 12 decades. lame_lambda may still
# start at exactly 0 (a linear grid).
MIN_SEARCH_MODULUS, MAX_SEARCH_MODULUS = MODULUS_RANGE_MPA  # a scenario's moduli have the same bounds


def _at_least_softest_or_zero(value: float) -> float:
    if 0 < value < MIN_SEARCH_MODULUS:
        raise problem(f"0 or a number of at least {MIN_SEARCH_MODULUS:g} (MPa; 1 Pa, softer than any tissue)")
    return value


def _search_range(low: Any, zero_allowed: bool) -> Any:
    # the pair's message keeps its 0.1.x text; a low bound below MIN_SEARCH_MODULUS is
    # reported on the item, fit.lame_mu[0], with the bound
    expected = f"[low, high] with {'0 <=' if zero_allowed else '0 <'} low < high (MPa)"
    high = number(f"a positive number of at most {MAX_SEARCH_MODULUS:g} (MPa; 1 TPa, stiffer than diamond)",
                  gt=0, le=MAX_SEARCH_MODULUS)
    return Annotated[tuple[low, high], expecting(expected, items=True, length=2), _increasing(expected)]


LambdaLow = Annotated[number("a non-negative number (MPa)", ge=0), AfterValidator(_at_least_softest_or_zero)]
MuLow = number(f"a number of at least {MIN_SEARCH_MODULUS:g} (MPa; 1 Pa, softer than any tissue)",
               ge=MIN_SEARCH_MODULUS)


@block(title="tissue", file_required=("thickness",), one_of=("size", "outline"))
class CalibrationTissue:
    """The tissue of a calibration: a scenario's tissue without its material. Its regions
    keep the materials they give (those fit.regions names only their law, their moduli being
    fitted from the ones given); the tissue's own moduli hold everywhere else."""

    size: described(Size | None, "[W, H] mm: the rectangle [0, W] x [0, H]; or give outline") = None
    thickness: described(PositiveMM, f"out-of-plane thickness t, mm; {THICKNESS_RANGE_MM[0]:g} to "
                                      f"{THICKNESS_RANGE_MM[1]:g}", maximum=THICKNESS_RANGE_MM[1]) = 1.0
    clamped: described(Clamps, "edges held fixed (names, or {segment: ...} pieces)") = ()
    outline: described(PolygonPoints | None, "a simple polygon [[x, y], ...] (mm), instead of size") = None
    holes: described(sequence(Hole, "a list of holes ({polygon: ...} or {circle: ...})"),
                     "cut-outs with free edges; one reaching the outline is cut out of it") = ()
    regions: described(sequence(Region, "a list of regions ({polygon: ...} or {circle: ...}, and material: ...)"),
                       "areas of another material, kept as given unless fit.regions fits their "
                       "moduli too: the fit finds the rest of the tissue's moduli") = ()

    _thickness_within_limits = within_limits(THICKNESS_LIMITS)

    @model_validator(mode="wrap")
    @classmethod
    def _no_material(cls, data: Any, handler):
        if not (isinstance(data, dict) and "material" in data):
            return handler(data)
        material = data["material"]
        try:
            handler({key: value for key, value in data.items() if key != "material"})
            errors = []
        except ValidationError as error:
            errors = error.errors()
        raise combined([*errors, problem(NO_MATERIAL, field="material", value=material)])

    @model_validator(mode="after")
    def _shape(self) -> CalibrationTissue:
        try:
            tissue = self.tissue(Material())
        except ValidationError as error:
            raise combined(error.errors()) from None
        # a calibration's region that holds no tissue fits nothing, or when fitted has no
        # marker to see it: a user's mistake (a scenario keeps its regions as they come)
        covered = [problem("a region overlapping the tissue (this one holds no tissue: "
                           + " and ".join(f"tissue.regions[{j}]" for j in before)
                           + f", listed before it, cover{'s' * (len(before) == 1)} its part of the tissue, and the region "
                           "listed first wins where regions overlap)",
                           field=f"regions[{i}].{self.regions[i].shown()[0]}", value=self.regions[i].shown()[1])
                   for i, before in regions_covered_before(tissue).items()]
        if covered:
            raise combined(covered)
        if self.regions and not tissue_outside_regions(tissue):
            raise problem("regions that leave some of the tissue to its own material (the moduli the fit "
                          "finds; the regions keep theirs)", field="regions",
                          value=Shown(f"{len(self.regions)} region{'s' if len(self.regions) > 1 else ''} "
                                      "covering the whole tissue"))
        return self

    def tissue(self, material: Material) -> Tissue:
        return Tissue(self.size, self.thickness, material, self.clamped, self.outline, self.holes, self.regions)


@block(kw_only=True, title="experiment")
class ExperimentBlock:
    name: described(Name, "optional label") = ""
    loads: described(sequence(Load, "a non-empty list of loads (force or displacement)", min_length=1),
                     "the loads of this experiment, as in a scenario")
    markers: described(MarkerFile, "CSV file x,y,x_def,y_def (mm), relative to the YAML file")
    load_steps: described(integer(1, 10000), "load increments") = 10

    @field_validator("loads")
    @classmethod
    def _held_in_place(cls, loads: tuple[Load, ...], info: ValidationInfo):
        clamped = (info.context or {}).get("clamped", True)
        if not clamped and all(load.displacement is None for load in loads):
            raise problem("tissue.clamped or a displacement load to hold the slab in place",
                          value=Shown("only forces on a tissue with no clamped edge"))
        if all(not any(load.force or ()) and not any(load.displacement or ()) for load in loads):
            # the markers then stay where they are whatever the moduli: nothing to fit
            raise problem("a non-zero force or displacement (the markers must move for the moduli to show)",
                          value=Shown("only zero loads"))
        return loads

    @model_validator(mode="after")
    def _loads_and_clamps_agree(self, info: ValidationInfo) -> ExperimentBlock:
        context = info.context or {}
        problems = load_problems(self.loads, context.get("clamped_edges") or (), context.get("domain"))
        if problems:
            raise combined(problems)
        return self


@block(title="fit")
class FitBlock:
    lame_lambda: described(_search_range(LambdaLow, zero_allowed=True),
                           f"search range [low, high] of lame_lambda, MPa (low 0 or at least "
                           f"{MIN_SEARCH_MODULUS:g}, high at most {MAX_SEARCH_MODULUS:g})")
    lame_mu: described(_search_range(MuLow, zero_allowed=False),
                       f"search range [low, high] of lame_mu, MPa (from {MIN_SEARCH_MODULUS:g} to "
                       f"{MAX_SEARCH_MODULUS:g})")
    model: described(choice(MATERIAL_MODELS), "constitutive law fitted") = "saint-venant-kirchhoff"
    grid: described(integer(2, 50), "grid points per axis of the initial search") = 6
    grid_scale: described(choice(GRID_SCALES) | None,
                          "log or linear grid; default log unless the lame_lambda range starts at 0") = None
    max_evaluations: described(integer(2, 1000), "forward evaluations of the least-squares refinement") = 40
    regions: described(sequence(integer(0, 999), "a list of indices into tissue.regions"),
                       "tissue.regions whose moduli are fitted too, within the same search ranges, "
                       "starting from the moduli their material gives") = ()

    @field_validator("regions")
    @classmethod
    def _each_once(cls, regions: tuple[int, ...]) -> tuple[int, ...]:
        if len(set(regions)) != len(regions):
            raise problem("each region at most once")
        return regions

    @model_validator(mode="after")
    def _scale(self) -> FitBlock:
        if self.grid_scale is None:
            object.__setattr__(self, "grid_scale", "log" if self.lame_lambda[0] > 0 else "linear")
        elif self.grid_scale == "log" and self.lame_lambda[0] <= 0:
            raise problem("linear when the lame_lambda range starts at 0 (a log grid needs positive bounds)",
                          field="grid_scale", value=self.grid_scale)
        return self


@block(kw_only=True, title="stitchplan material calibration")
class CalibrationFile:
    """A `calibrate material` input file as written."""

    name: described(Name, "optional label") = ""
    tissue: described(CalibrationTissue, "the slab: size, thickness, clamped edges (no material)")
    experiments: described(sequence(ExperimentBlock, "a non-empty list of experiments", min_length=1),
                           "loadings of the slab and their marker files")
    fit: described(FitBlock, "search ranges and settings of the fit")
    discretization: described(Discretization | None, "optional; default spacing min(W, H)/20") = None
    solver: described(Solver | None, "Newton settings") = None

    @model_validator(mode="after")
    def _names_once(self) -> CalibrationFile:
        """Each experiment's name once: fitted.yaml's per-experiment results and the residual
        plot tell the experiments apart by it (unnamed ones by their index)."""
        first: dict[str, int] = {}
        problems = []
        # an unnamed one is called by its index: a name that is another's index is taken too
        unnamed = {f"experiments[{i}]": i for i, experiment in enumerate(self.experiments) if not experiment.name}
        for i, experiment in enumerate(self.experiments):
            if not experiment.name:
                continue
            j = first.setdefault(experiment.name, i)
            if j != i:
                problems.append(problem(f"a name of its own (experiments[{j}] has it too; fitted.yaml's results per "
                                        "experiment are told apart by it)",
                                        field=f"experiments.{i}.name", value=experiment.name))
            elif experiment.name in unnamed:
                problems.append(problem(f"a name of its own (experiments[{unnamed[experiment.name]}], unnamed, is "
                                        "called so; fitted.yaml's results per experiment are told apart by it)",
                                        field=f"experiments.{i}.name", value=experiment.name))
        if problems:
            raise combined(problems)
        return self

    @model_validator(mode="after")
    def _fitted_regions(self) -> CalibrationFile:
        """fit.regions name regions of the tissue whose given moduli lie within the search
        ranges (they start the least squares)."""
        regions, problems = self.tissue.regions, []
        for k, index in enumerate(self.fit.regions):
            if index >= len(regions):
                problems.append(problem(f"an index of tissue.regions (it has {len(regions)} "
                                        f"region{'s' * (len(regions) != 1)}: 0 to {len(regions) - 1})"
                                        if regions else "none (tissue.regions is empty)",
                                        field=f"fit.regions.{k}", value=index))
                continue
            material = regions[index].material
            for name in ("lame_lambda", "lame_mu"):
                low, high = getattr(self.fit, name)
                value = getattr(material, name)
                if not low <= value <= high:
                    problems.append(problem(f"a start within fit.{name} [{low:g}, {high:g}] MPa (fit.regions "
                                            f"fits tissue.regions[{index}]'s moduli from its material's)",
                                            field=f"tissue.regions.{index}.material.{name}", value=value))
        if problems:
            raise combined(problems)
        return self


def parse_calibration(raw: Any, source: str = "") -> CalibrationFile:
    """The validated calibration file; an InputError lists every problem of it. Without a
    spacing the discretization gets a twentieth of the smaller side. `source`: its path, for
    its warnings."""
    context: dict[str, Any] = {"domain": None}
    if isinstance(raw, dict):
        tissue = raw.get("tissue")
        domain = shape_domain(tissue)
        size = None if domain is None else domain.size
        context["domain"] = domain
        context["clamped"] = not isinstance(tissue, dict) or bool(tissue.get("clamped"))
        if isinstance(tissue, dict):
            context["clamped_edges"] = valid_or_none(Clamps, tissue.get("clamped", ()))
        given = raw.get("discretization")
        given = {} if given is None else given
        if isinstance(given, dict):  # the keys the file gives (the default spacing is filled in below)
            context["discretization_given"] = {k for k, v in given.items() if v is not None}
        if isinstance(given, dict) and "spacing" not in given:
            if size is None:
                context["default_spacing_unknown"] = True
            else:
                raw = {**raw, "discretization": {**given, "spacing": default_spacing_of(size, None)}}
    calibration = validate(CalibrationFile, raw, "", root="calibration", context=context)
    moves = segment_ends(raw, ("tissue", "clamped"), calibration.tissue.tissue(Material()).clamped)
    for j, experiment in enumerate(calibration.experiments):
        moves += segment_ends(raw, ("experiments", j, "loads"), experiment.loads)
    if context["domain"] is not None:
        log_moves(context["domain"], moves, source)
    return calibration
