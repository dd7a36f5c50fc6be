"""Model parameters fitted to measurements: Lame moduli from marker displacements (thesis
appendix A.2), needle friction and cutting force from force recordings (section 5.2).

Modules, in the order data flows through them:

- inputs: the calibration YAML and its experiments as typed inputs;
- forward: the static forward model of one experiment and its exact sensitivities;
- material_fit: grid search, least squares and the discretization estimate for the moduli;
- fit_statistics: their standard uncertainties, correlations, identifiability and warnings;
- needle_fit: background and tissue lines for friction and cutting force.

Reports and plots of the results are written by stitchplan.io.calibration_reports.
"""

from .forward import ExperimentModel, simulate_markers
from .inputs import (
    Experiment,
    FitSettings,
    MaterialCalibration,
    load_material_calibration,
    parse_material_calibration,
)
from .fit_statistics import CORRELATION_LIMIT, POORLY_DETERMINED
from .material_fit import (
    GridSearch,
    MarkerMisfit,
    MaterialFit,
    Progress,
    calibrate_material,
    fit_material,
    no_progress,
)
from .needle_fit import (
    LineFit,
    NeedleFit,
    calibrate_needle,
    fit_line,
    fit_needle,
    read_force_recording,
)

__all__ = [
    "CORRELATION_LIMIT", "POORLY_DETERMINED", "Experiment", "ExperimentModel", "FitSettings",
    "GridSearch", "LineFit", "MarkerMisfit", "MaterialCalibration", "MaterialFit", "NeedleFit",
    "Progress", "calibrate_material", "calibrate_needle", "fit_line", "fit_material", "fit_needle",
    "load_material_calibration", "no_progress", "parse_material_calibration",
    "read_force_recording", "simulate_markers",
]
