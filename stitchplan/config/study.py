"""The optional `study:` block of a scenario: families of discretization and method choices
swept by `stitchplan study` (see stitchplan.study.sweep)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from .scenario import (LINEAR_SOLVERS, TIP_TRACKING, _choice, _fail, _integer, _mapping, _number,
                       parse_discretization)

FAMILY_KEYS = ("name", "spacing", "grading", "dilation", "quadrature_order", "basis_order",
               "cells_per_spacing", "step", "tip_tracking", "linear_solver")
STUDY_KEYS = ("spacing", "families", "reference", "repeats")
GRADINGS = (2, 4, 8, 16)


@dataclass(frozen=True)
class StudyFamily:
    """Method choices held fixed along a family; None keeps the scenario's choice."""

    name: str
    spacing: tuple[float, ...] | None = None  # mm at the needle; None: the study's list
    grading: int | None = None  # coarse / needle spacing (graded particles); None: uniform
    dilation: float | None = None
    quadrature_order: int | None = None
    basis_order: int | None = None
    cells_per_spacing: int | None = None
    step: float | None = None  # rad per needle step
    tip_tracking: str | None = None
    linear_solver: str | None = None


@dataclass(frozen=True)
class StudySpec:
    spacing: tuple[float, ...] | None = None  # None: default_spacings(scenario)
    families: tuple[StudyFamily, ...] | None = None  # None: default_families()
    reference: StudyFamily | None = None  # None: default_reference(...)
    repeats: int = 1


def _spacings(value: Any, path: str) -> tuple[float, ...]:
    if not isinstance(value, (list, tuple)) or not value:
        raise _fail(path, value, "a non-empty list of spacings (mm)")
    return tuple(_number(v, f"{path}[{i}]", positive=True, unit="mm") for i, v in enumerate(value))


def parse_family(raw: Any, path: str, default_name: str = "") -> StudyFamily:
    block = _mapping(raw, path, FAMILY_KEYS)
    name = block.get("name", default_name)
    if not isinstance(name, str) or not name:
        raise _fail(f"{path}.name", name, "a non-empty string")
    spacing = block.get("spacing")
    if spacing is not None:
        spacing = _spacings(spacing if isinstance(spacing, (list, tuple)) else [spacing], f"{path}.spacing")
    grading = block.get("grading")
    if grading is not None and grading not in GRADINGS:
        raise _fail(f"{path}.grading", grading, "one of " + ", ".join(map(str, GRADINGS))
                    + " (coarse spacing / needle spacing)")
    step = block.get("step")
    if step is not None:
        step = _number(step, f"{path}.step", positive=True, unit="rad")
        if step > 0.5:
            raise _fail(f"{path}.step", step, "a positive angle of at most 0.5 rad per step")
    family = StudyFamily(
        name=name, spacing=spacing, grading=grading,
        dilation=None if "dilation" not in block else _number(block["dilation"], f"{path}.dilation", positive=True),
        quadrature_order=None if "quadrature_order" not in block else _integer(
            block["quadrature_order"], f"{path}.quadrature_order", 1, 10),
        basis_order=None if "basis_order" not in block else _integer(block["basis_order"], f"{path}.basis_order", 1, 2),
        cells_per_spacing=None if "cells_per_spacing" not in block else _integer(
            block["cells_per_spacing"], f"{path}.cells_per_spacing", 1, 4),
        step=step,
        tip_tracking=None if "tip_tracking" not in block else _choice(
            block["tip_tracking"], f"{path}.tip_tracking", TIP_TRACKING),
        linear_solver=None if "linear_solver" not in block else _choice(
            block["linear_solver"], f"{path}.linear_solver", LINEAR_SOLVERS),
    )
    if family.dilation is not None:  # the same checks as the discretization block
        parse_discretization({"dilation": family.dilation}, path)
    return family


def parse_study(raw: Any, path: str = "study") -> StudySpec:
    """The optional `study:` block of a scenario (see the module docstring)."""
    if raw is None:
        return StudySpec()
    block = _mapping(raw, path, STUDY_KEYS)
    spacing = _spacings(block["spacing"], f"{path}.spacing") if "spacing" in block else None
    families = None
    if "families" in block:
        items = block["families"]
        if not isinstance(items, (list, tuple)) or not items:
            raise _fail(f"{path}.families", items, "a non-empty list of families")
        families = tuple(parse_family(item, f"{path}.families[{i}]", f"family {i + 1}")
                         for i, item in enumerate(items))
        names = [f.name for f in families]
        if len(set(names)) != len(names):
            raise _fail(f"{path}.families", names, "families with distinct names")
    reference = None
    if "reference" in block:
        reference = parse_family(block["reference"], f"{path}.reference", "reference")
        if reference.spacing is None or len(reference.spacing) != 1:
            raise _fail(f"{path}.reference.spacing", block["reference"].get("spacing"),
                        "one spacing (mm): the reference is a single, finest run")
        reference = replace(reference, name="reference")
    repeats = _integer(block.get("repeats", 1), f"{path}.repeats", 1, 20)
    return StudySpec(spacing, families, reference, repeats)


