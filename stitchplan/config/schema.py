"""The JSON Schema of scenario files, for editors and validators (`stitchplan schema`)."""

from __future__ import annotations

from .messages import adapter
from .scenario import ScenarioFile

DIALECT = "https://json-schema.org/draft/2020-12/schema"


def scenario_schema() -> dict:
    """JSON Schema (2020-12) of a scenario file: every block refuses unknown keys, choices
    are enums, and each field says its unit. Cross-field rules (a load segment on an edge,
    probes inside the tissue, needle_spacing <= spacing, ...) are checked by the tool itself."""
    schema = adapter(ScenarioFile).json_schema()
    schema.update(title="stitchplan scenario",
                  description="A stitchplan scenario file (YAML). Lengths in mm, forces in N, "
                              "Lamé moduli in MPa, angles in rad.")
    return {"$schema": DIALECT, **schema}
