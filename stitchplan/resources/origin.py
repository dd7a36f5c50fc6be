"""What set a run's discretization (a file's field, an option, a replay's rescaling), for a refusal to name."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

from ..config import Scenario
from ..config.blocks import default_spacing_of


@dataclass(frozen=True)
class Origin:
    """What set a run's discretization, so that a refusal names what the user can change.

    A discretization field is named as the scenario file's `discretization.<field>` unless
    `names` maps it to what else set it: an option ({"spacing": "--spacing"}) or another
    block ({"spacing": "study.spacing"}); `given` holds the value as set there where the
    run's differs. A run derived from the given model (a plan's verification) says so in
    `derived` and how to leave it out in `skip`."""

    names: Mapping[str, str] = field(default_factory=dict)
    given: Mapping[str, float] = field(default_factory=dict)
    derived: str = ""  # follows what was expected, e.g. " in the plan's verification at half the spacing"
    skip: str = ""  # advice, e.g. "pass --no-verify to skip the verification"

    def name(self, key: str, default: str | None = None) -> str:
        return self.names.get(key, default or f"discretization.{key}")

    def value(self, key: str, run_value: float) -> float:
        return self.given.get(key, run_value)


def replay_origin(scenario: Scenario, names: Mapping[str, str] | None, derived: str, skip: str) -> Origin:
    """The origin of a model rescaled from the scenario's (a replay at another spacing): a
    refusal names the scenario's own spacings (`names` as for the scenario's model), says
    which replay in `derived` and how to leave it out in `skip`."""
    d = scenario.discretization
    given = {"spacing": d.spacing}
    if d.needle_spacing is not None:
        given["needle_spacing"] = d.needle_spacing
    return Origin(dict(names or {}), given, derived=derived, skip=skip)


def verification_origin(scenario: Scenario, names: Mapping[str, str] | None = None) -> Origin:
    """The origin of a plan's verification model (planning.replay_models.replay_scenario):
    replay_origin offering --no-verify."""
    return replay_origin(scenario, names, " in the plan's verification at half the spacing",
                         "pass --no-verify to skip the verification")


def radius_default_of(scenario: Scenario, origin: Origin) -> float | None:
    """The needle radius when the run's spacing is the default that follows it (a scenario
    giving no spacing: config.blocks.default_spacing_of), else None."""
    if scenario.needle is None or "spacing" in origin.names:
        return None
    size, radius = scenario.tissue.bounding_size, scenario.needle.radius
    default = default_spacing_of(size, radius)
    follows_radius = default < default_spacing_of(size, math.inf)  # not held by the tissue's size
    spacing = origin.value("spacing", scenario.discretization.spacing)
    return radius if follows_radius and math.isclose(spacing, default, rel_tol=1e-9) else None


def size_default_of(scenario: Scenario, origin: Origin) -> str | None:
    """The tissue's field setting the run's spacing ("tissue.size", or "tissue.outline" for a
    polygon) when the spacing is the default of a scenario giving none that the tissue's size
    sets (config.blocks.default_spacing_of: a twentieth of the smaller side without a needle,
    a share of a side where that is below 2/5 of the needle's radius), else None."""
    if "spacing" in origin.names:
        return None
    radius = None if scenario.needle is None else scenario.needle.radius
    default = default_spacing_of(scenario.tissue.bounding_size, radius)
    if not math.isclose(origin.value("spacing", scenario.discretization.spacing), default, rel_tol=1e-9):
        return None
    return "tissue.outline" if scenario.tissue.size is None else "tissue.size"
