"""Typed inputs of the material calibration and their readers (thesis appendix A.2): the
calibration YAML, its experiments and their marker CSV files."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..config import (
    Discretization,
    Load,
    Material,
    Solver,
    Tissue,
    input_error,
)
from ..config.calibration import (
    GRID_SCALES,
    CalibrationFile,
    ExperimentBlock,
    FitBlock,
    parse_calibration,
)
from ..config.scenario import default_spacing
from ..config.yaml_files import read_yaml_file, with_key_problems
from ..csv_tables import read_numeric_table
from ..errors import InputError
from ..geometry.segments import on_segment

log = logging.getLogger(__name__)

MARKER_COLUMNS = ("x", "y", "x_def", "y_def")
# A marker moves by less than the tissue's size (the longer side of its bounding box): more
# would stretch the slab to over twice its length, far beyond the strains a calibration
# photographs and the quasi-static model fits (the shipped example's markers move under
# 6 mm in a 100 mm slab). A deformed position beyond is a typo, a unit slip (micrometres
# as mm) or a coordinate of another frame, and would only make the misfit overflow.
MAX_DISPLACEMENT_OVER_SIZE = 1.0
# Markers all displaced by less than this fraction of the tissue's size (0.1 micrometre in a
# 100 mm slab, far below what a photograph resolves) did not move: the deformed columns
# repeat the rest ones. The fit would read them as an infinitely stiff material.
NO_MOTION_OVER_SIZE = 1e-6
# Markers whose rest positions span less than this fraction of the tissue's bounding box in
# both directions sit in a speck of it: 1 mm of a 100 mm slab, where a calibration spreads its
# markers over the slab (the shipped examples' span 90 % and more of each side). Positions
# in metres read as mm put every marker within 0.1 mm of the origin: a 1000-fold shrink, which
# this catches whatever the markers' spread, while a real cluster of markers this tight
# would see almost none of the tissue's deformation. A warning, not a refusal: the data can
# be right.
CLUSTERED_SPAN_OVER_SIZE = 1e-2
__all__ = ["GRID_SCALES", "MARKER_COLUMNS", "Experiment", "FitSettings", "MaterialCalibration",
           "load_material_calibration", "parse_material_calibration"]


@dataclass(frozen=True)
class Experiment:
    """One loading of the slab and the markers measured under it."""

    name: str
    loads: tuple[Load, ...]
    load_steps: int
    markers: np.ndarray  # (n, 2) rest positions X_i, mm
    measured: np.ndarray  # (n, 2) measured deformed positions p_i, mm
    source: str = ""
    warnings: tuple[str, ...] = ()  # what its markers suggest checking (read_experiment)
    source_sha256: str | None = None  # of the marker file's bytes as read


@dataclass(frozen=True)
class FitSettings:
    model: str
    lame_lambda: tuple[float, float]  # search range, MPa
    lame_mu: tuple[float, float]
    grid_points: int = 6  # per axis
    grid_scale: str = "log"
    max_evaluations: int = 40  # forward evaluations allowed to the least-squares refinement
    regions: tuple[int, ...] = ()  # indices of tissue.regions whose moduli are fitted too

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """The fitted moduli in the order of the parameter vector: the tissue's own pair,
        then each fitted region's."""
        return ("lame_lambda", "lame_mu", *(f"tissue.regions[{k}].{name}" for k in self.regions
                                            for name in ("lame_lambda", "lame_mu")))

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Each parameter's search range (every pair shares the fit's)."""
        pairs = 1 + len(self.regions)
        return (np.tile([self.lame_lambda[0], self.lame_mu[0]], pairs),
                np.tile([self.lame_lambda[1], self.lame_mu[1]], pairs))


@dataclass(frozen=True)
class MaterialCalibration:
    tissue: Tissue
    experiments: tuple[Experiment, ...]
    fit: FitSettings
    discretization: Discretization
    solver: Solver = field(default_factory=Solver)
    name: str = ""
    source: str = ""
    source_sha256: str | None = None  # of the calibration file's bytes as parsed

    @property
    def warnings(self) -> list[str]:
        """What the inputs suggest checking (each experiment's markers'): the fit's warnings
        start with them."""
        return [warning for experiment in self.experiments for warning in experiment.warnings]

    @property
    def estimate_spacing(self) -> float:
        """The discretization estimate's spacing, mm: twice the fit's (its default where the
        file gives none)."""
        return 2.0 * (self.discretization.spacing or default_spacing(self.tissue, None))

    @property
    def region_start(self) -> np.ndarray:
        """The fitted regions' moduli as the file gives them, (lambda, mu) per region in
        fit.regions' order: where the least squares starts them (and the grid holds them)."""
        return np.array([(self.tissue.regions[k].material.lame_lambda, self.tissue.regions[k].material.lame_mu)
                         for k in self.fit.regions], dtype=float).reshape(-1)


def fit_settings(fit: FitBlock) -> FitSettings:
    return FitSettings(fit.model, fit.lame_lambda, fit.lame_mu, fit.grid, fit.grid_scale, fit.max_evaluations,
                       fit.regions)


def read_experiment(block: ExperimentBlock, tissue: Tissue, folder: Path, path: str) -> Experiment:
    """The experiment with its marker file (relative to `folder`) read and checked."""
    markers_path = folder / block.markers
    data, lines, digest = read_numeric_table(markers_path, MARKER_COLUMNS, "marker positions at rest and deformed, mm",
                                             exact=True, label=f"{path}.markers")
    rest = np.stack([data["x"], data["y"]], axis=1)
    outside = np.flatnonzero(~tissue.domain.contains(rest))
    if len(outside):
        k = outside[0]
        raise InputError(
            f"{path}.markers: {markers_path}: line {lines[k]}, x, y: got the rest position "
            f"[{rest[k, 0]:g}, {rest[k, 1]:g}] mm, expected a point inside "
            + (f"[0, {tissue.size[0]:g}] x [0, {tissue.size[1]:g}] mm" if tissue.outline is None and not tissue.holes
               else f"the {tissue.domain.describe()}"))
    # a marker given twice would weigh twice in the least squares
    _, first, inverse = np.unique(rest, axis=0, return_index=True, return_inverse=True)
    again = np.flatnonzero(first[inverse.ravel()] != np.arange(len(rest)))
    if len(again):
        k = again[0]
        raise InputError(
            f"{path}.markers: {markers_path}: line {lines[k]}, x, y: got the rest position [{rest[k, 0]:g}, "
            f"{rest[k, 1]:g}] mm again (first at line {lines[first[inverse.ravel()[k]]]}), expected each marker once")
    deformed = np.stack([data["x_def"], data["y_def"]], axis=1)
    where = f"{path}.markers: {markers_path}"
    check_displacements(rest, deformed, lines, max(tissue.bounding_size), where)
    return Experiment(
        name=block.name,
        loads=block.loads,
        load_steps=block.load_steps,
        markers=rest,
        measured=deformed,
        source=str(markers_path),
        source_sha256=digest,
        warnings=tuple(filter(None, [clustered_markers(rest, tissue, where),
                                     moved_on_a_clamp(rest, deformed, lines, tissue, where)])),
    )


def clustered_markers(rest: np.ndarray, tissue: Tissue, where: str) -> str | None:
    """The warning for markers whose rest positions span less than CLUSTERED_SPAN_OVER_SIZE of
    the tissue's bounding box in both x and y (positions in m read as mm), or None; a single
    marker spans nothing and says nothing."""
    if len(rest) < 2:
        return None
    span, size = np.ptp(rest, axis=0), np.asarray(tissue.bounding_size, dtype=float)
    if np.any(span >= CLUSTERED_SPAN_OVER_SIZE * size):
        return None
    return (f"{where}: x, y: the {len(rest)} markers' rest positions span only {span[0]:.3g} x {span[1]:.3g} mm, "
            f"less than 1/{1 / CLUSTERED_SPAN_OVER_SIZE:.0f} of the tissue's {size[0]:g} x {size[1]:g} mm in both "
            "directions: are they in m rather than mm? (marker files are read in mm)")


def moved_on_a_clamp(rest: np.ndarray, deformed: np.ndarray, lines: np.ndarray, tissue: Tissue,
                     where: str) -> str | None:
    """The warning for markers at rest on a clamped piece of the boundary whose measured
    position moved (by more than NO_MOTION_OVER_SIZE of the tissue's size), or None: the model
    holds them fixed whatever the moduli, so their move is misfit the fit cannot reduce (a
    slipping clamp, or a marker off the clamped edge)."""
    domain = tissue.domain
    held = np.zeros(len(rest), dtype=bool)
    piece = np.full(len(rest), -1)
    for k, (start, end) in enumerate(tissue.clamped_pieces()):
        on = on_segment(rest, start, end, domain.tolerance) & ~held
        piece[on], held = k, held | on
    move = np.linalg.norm(deformed - rest, axis=1)  # (n,)
    moved = np.flatnonzero(held & (move > NO_MOTION_OVER_SIZE * max(tissue.bounding_size)))
    if not len(moved):
        return None
    k = moved[np.argmax(move[moved])]
    item = tissue.clamped[piece[k]]
    clamp = f"the clamped edge {item!r}" if isinstance(item, str) else "a clamped segment"
    more = (f"; {len(moved) - 1} more marker{'s' * (len(moved) > 2)} on a clamped piece moved too"
            if len(moved) > 1 else "")
    return (f"{where}: line {lines[k]}, x_def, y_def: the marker at rest at [{rest[k, 0]:g}, {rest[k, 1]:g}] mm lies "
            f"on {clamp} (tissue.clamped[{piece[k]}]), which the model holds fixed, yet moved by {move[k]:.3g} mm to "
            f"[{deformed[k, 0]:g}, {deformed[k, 1]:g}]: its move is misfit whatever the moduli (does the clamp slip, "
            f"or does the marker lie off the clamped edge?){more}")


def check_displacements(rest: np.ndarray, deformed: np.ndarray, lines: np.ndarray, size: float,
                        where: str) -> None:
    """Each marker displaced by at most the tissue's `size` in x and in y, and the markers as a
    whole displaced at all (every experiment carries non-zero loads, so its markers move)."""
    displacement = deformed - rest  # (n, 2)
    reach = MAX_DISPLACEMENT_OVER_SIZE * size
    beyond = np.argwhere(np.abs(displacement) > reach)
    if len(beyond):
        k, axis = beyond[0]
        column, rest_column = ("x_def", "x") if axis == 0 else ("y_def", "y")
        raise InputError(
            f"{where}: line {lines[k]}, {column}: got {deformed[k, axis]:g}, expected a deformed position "
            f"within {reach:g} mm (the tissue's size) of the rest position {rest_column} = {rest[k, axis]:g} mm; "
            "is it in another unit or frame?")
    largest = float(np.linalg.norm(displacement, axis=1).max())
    if largest <= NO_MOTION_OVER_SIZE * size:
        raise InputError(
            f"{where}: x_def,y_def: got every marker at its rest position x,y (largest displacement "
            f"{largest:g} mm over {len(rest)} markers), expected markers the experiment's loads displace "
            "(are the deformed columns a copy of the rest ones?)")


def check_marker_count(count: int, fit: FitSettings) -> None:
    """Enough markers for the P fitted moduli (the tissue's pair and each fitted region's) and
    their uncertainty: sigma^2 = |r|^2 / (m - P) needs m > P coordinates, and markers give
    them in pairs, so at least P / 2 + 1 markers."""
    parameters = len(fit.parameter_names)
    needed = parameters // 2 + 1
    if count >= needed:
        return
    regions = len(fit.regions)
    which = (f": the tissue's 2 moduli and 2 for each of the {regions} region{'s' * (regions != 1)} of fit.regions "
             f"{list(fit.regions)}" if regions else "")
    raise InputError(f"experiments: {count} marker{'s' * (count != 1)} in all, expected at least {needed} "
                     f"({2 * needed} coordinates for {parameters} parameters and their uncertainty{which})")


def parse_material_calibration(raw: Any, folder: Path, source: str = "") -> MaterialCalibration:
    """The calibration of a file's data (stitchplan.config.calibration validates it; every
    problem of the file and of its marker files is reported at once)."""
    spec: CalibrationFile = parse_calibration(raw, source)
    fit = fit_settings(spec.fit)
    tissue = spec.tissue.tissue(Material(fit.model, *_start_point(fit)))
    experiments, problems = [], []
    for i, block in enumerate(spec.experiments):
        try:
            experiments.append(read_experiment(block, tissue, folder, f"experiments[{i}]"))
        except InputError as error:
            problems += getattr(error, "lines", [str(error)])
    # one marker file in two experiments counts the same photographs twice, halving their
    # stated scatter: a copied block whose file was not changed
    first_of: dict[Path, int] = {}
    first_with: dict[bytes, int] = {}  # a copy of the file under another name says the same
    for i, experiment in enumerate(experiments):
        same = first_of.setdefault(Path(experiment.source).resolve(), i)
        copied = first_with.setdefault(experiment.markers.tobytes() + experiment.measured.tobytes(), i)
        if same != i:
            problems.append(f"experiments[{i}].markers: got {experiment.source}, the markers of experiments[{same}] "
                            "again; expected each experiment's own marker file (its loads move the markers "
                            "differently)")
        elif copied != i:
            problems.append(f"experiments[{i}].markers: got {experiment.source}, the same rest and measured "
                            f"positions as experiments[{copied}]'s {experiments[copied].source}; expected each "
                            "experiment's own markers (its loads move the markers differently)")
    if problems:
        raise input_error(problems)
    check_marker_count(sum(len(e.markers) for e in experiments), fit)
    calibration = MaterialCalibration(tissue, tuple(experiments), fit, spec.discretization or Discretization(),
                                      spec.solver or Solver(), spec.name, source)
    for warning in calibration.warnings:  # said now: a fit that fails on such data would not say them
        log.warning(warning)
    return calibration


def load_material_calibration(path: str | Path, spacing: float | None = None,
                              dilation: float | None = None) -> MaterialCalibration:
    """Read and validate a calibration YAML; marker files are relative to it. `spacing` and
    `dilation` override its discretization (the CLI options)."""
    path = Path(path)
    file = read_yaml_file(path, keys_later=True)
    problem = with_key_problems(file, path, lambda raw: parse_material_calibration(raw, path.parent, str(path)))
    problem = replace(problem, source_sha256=file.sha256)
    overrides = {k: v for k, v in {"spacing": spacing, "dilation": dilation}.items() if v is not None}
    if overrides:
        problem = replace(problem, discretization=problem.discretization.replaced(**overrides))
    return problem


def _start_point(fit: FitSettings) -> tuple[float, float]:
    """Geometric (or arithmetic) middle of the search ranges, written so that it neither
    underflows nor overflows (sqrt(low * high) of [1e-200, 1e-199] is 0.0, of [10, 1e308]
    inf) and kept within the range against rounding."""
    def mid(low: float, high: float) -> float:
        middle = math.sqrt(low) * math.sqrt(high) if fit.grid_scale == "log" else 0.5 * low + 0.5 * high
        return min(max(middle, low), high)

    return mid(*fit.lame_lambda), mid(*fit.lame_mu)
