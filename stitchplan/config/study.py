"""The optional `study:` block of a scenario: families of discretization and method choices
swept by `stitchplan study` (see stitchplan.study.sweep)."""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import AfterValidator, WithJsonSchema, field_validator, model_validator

from .blocks import SceneSpacing, block
from .fields import (
    BasisOrder,
    CellsPerSpacing,
    Dilation,
    LinearSolver,
    NeedleStep,
    NonEmptyName,
    PositiveMM,
    QuadratureOrder,
    TipTracking,
    choice,
    described,
    integer,
    problem,
    sequence,
)
from .messages import valid_or_none, validate

GRADINGS = (2, 4, 8, 16)
STUDY_RUN_NAMES = ("reference", "auto")  # the families of the reference run and the auto discretization


def _no_repeats(spacings: tuple[float, ...]) -> tuple[float, ...]:
    """A spacing list without repeats: a repeated spacing would run twice under one label."""
    if len(set(spacings)) != len(spacings):
        raise problem("spacings each given once (a repeat runs the same model twice under one label)",
                      value=list(spacings))
    return spacings


Spacings = Annotated[sequence(SceneSpacing, "a non-empty list of spacings (mm)", min_length=1),
                     AfterValidator(_no_repeats)]
# a family's spacing: one number or a list in a file (so the schema says), held as a list (a
# number is read as a list of one, StudyFamily._one_or_more), so that a bad value is one line
# naming its item rather than one line per member of a union
OneOrMoreSpacings = Annotated[Spacings | None, WithJsonSchema({"anyOf": [
    {"type": "array", "items": {"type": "number", "exclusiveMinimum": 0}, "minItems": 1},
    {"type": "number", "exclusiveMinimum": 0},
    {"type": "null"}]})]


def _as_list(value: Any) -> Any:
    """A spacing given as one number, as a list of one; a bad one reported as given."""
    if isinstance(value, (list, tuple)) or value is None:
        return value
    if valid_or_none(PositiveMM, value) is None:
        raise problem("a positive number (mm) or a non-empty list of them")
    return [value]


@block()
class StudyFamily:
    """Method choices held fixed along a family; None keeps the scenario's choice."""

    # optional in a file: the study block names a family 'family N' and the reference 'reference'
    name: described(NonEmptyName | None, "label of the family in study.csv; default 'family N'") = None
    spacing: described(OneOrMoreSpacings, "mm at the needle (one number or a list); default: the "
                                           "study's list") = None
    grading: described(choice(GRADINGS, "one of 2, 4, 8, 16 (coarse spacing / needle spacing)") | None,
                       "coarse spacing / needle spacing (graded particles); default uniform") = None
    dilation: described(Dilation | None, "kernel support / spacing") = None
    quadrature_order: described(QuadratureOrder | None, "Gauss points per direction per cell") = None
    basis_order: described(BasisOrder | None, "1 linear, 2 quadratic RK basis") = None
    cells_per_spacing: described(CellsPerSpacing | None, "background cells per particle spacing") = None
    step: described(NeedleStep | None, "rad per needle step") = None
    tip_tracking: described(TipTracking | None, "tip tracking of the needle") = None
    linear_solver: described(LinearSolver | None, "linear solver of the needle steps") = None

    @field_validator("spacing", mode="before")
    @classmethod
    def _one_or_more(cls, value: Any) -> Any:
        return _as_list(value)



@block(title="study")
class StudySpec:
    spacing: described(Spacings | None, "mm at the needle, swept in every family; default: around "
                                 "the scenario's spacing") = None
    families: described(sequence(StudyFamily, "a non-empty list of families", min_length=1) | None,
                        "default: eight families, each changing one choice") = None
    reference: described(StudyFamily | None, "the finest run: one spacing") = None
    repeats: described(integer(1, 20), "timing: median of this many runs of each family run "
                                        "(the reference runs once)") = 1

    @model_validator(mode="before")
    @classmethod
    def _names(cls, data: Any) -> Any:
        """Families without a name are 'family 1', 'family 2', ...; the reference is 'reference'."""
        if not isinstance(data, dict):
            return data
        data = dict(data)
        if isinstance(data.get("families"), list):
            data["families"] = [{"name": f"family {i + 1}", **item} if isinstance(item, dict) else item
                                for i, item in enumerate(data["families"])]
        if isinstance(data.get("reference"), dict):
            given = data["reference"].get("name", "reference")
            if given != "reference":  # it was taken and dropped: the reference is study.csv's `reference`
                raise problem("no name: the reference's runs are named 'reference' in study.csv and study.json",
                              field="reference.name", value=given)
            data["reference"] = {**data["reference"], "name": "reference"}
        return data

    @field_validator("families")
    @classmethod
    def _distinct(cls, families: tuple[StudyFamily, ...] | None):
        names = [family.name for family in families or ()]
        for k, name in enumerate(names):
            if name in STUDY_RUN_NAMES:  # study.csv's family column would mix them with the study's own runs
                raise problem("a name other than 'reference' and 'auto', the study's own runs' families",
                              field=f"{k}.name", value=name)
        if len(set(names)) != len(names):
            raise problem("families with distinct names (a family without a name is 'family k', k its place in "
                          "the list)", value=names)
        return families

    @field_validator("reference")
    @classmethod
    def _one_spacing(cls, reference: StudyFamily | None):
        if reference is not None and (reference.spacing is None or len(reference.spacing) != 1):
            raise problem("one spacing (mm): the reference is a single, finest run", field="spacing",
                          value=reference.spacing)
        return reference


def parse_study(raw: Any, path: str = "study") -> StudySpec:
    """The optional `study:` block of a scenario (see the module docstring)."""
    return StudySpec() if raw is None else validate(StudySpec, raw, path)
