"""Needle friction and cutting force from force recordings (thesis section 5.2).

The force needed to turn the needle in air is fitted by a line in the angle (bearing
friction, cable drag: the background); subtracted from the recording in tissue it leaves
the tissue's share, fitted by a line in the inserted length radius x angle:
slope = friction (N/mm), intercept = cutting force (N).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..config.blocks import NEEDLE_RADIUS_RANGE_MM
from ..csv_tables import read_numeric_table
from ..errors import InputError, NumericalFailure

log = logging.getLogger(__name__)

FORCE_COLUMNS = ("angle_rad", "force_N")
MIN_FORCE_SAMPLES = 5
MIN_ANGLE_SPAN = 0.1  # rad: less than ~6 degrees of rotation cannot separate slope and offset
MAX_ANGLE_SPAN = 2.0 * math.pi  # rad: a needle turns less than once (a span beyond: degrees?)
MIN_R_SQUARED = 0.9  # below this the corrected force is not a line in the inserted length
# |force| bound of a recording (N). The forces that turn a suture needle are a few N (the
# thesis's SH 1/2 needle: 0.7 N cutting + 0.06 N/mm friction over a 28 mm arc, ~2.4 N; the
# shipped recordings stay below 2 N); 100 N (~10 kg weight) is 40 times that, far beyond what
# a surgeon's hand or a needle driver applies to a needle of under a millimetre's wire. A
# larger value is a unit slip (mN recorded as N) or a corrupt file, and a fit to it would
# only overflow.
MAX_FORCE_N = 100.0
# needle radius bounds (mm): a scenario's (config.blocks, NEEDLE_RADIUS_RANGE_MM), outside which
# a value is a unit slip (m or micrometres given as mm). Within them the inserted lengths
# radius x angle stay within a few decades of 1 mm, so the line's least-squares system
# [1, length] is far from singular in double precision.
MIN_RADIUS_MM, MAX_RADIUS_MM = NEEDLE_RADIUS_RANGE_MM


@dataclass
class LineFit:
    """y = intercept + slope x by least squares, with standard errors from the residuals."""

    intercept: float
    slope: float
    covariance: np.ndarray  # (2, 2) of (intercept, slope)
    residual_std: float  # sqrt(SSR / (n - 2))
    r_squared: float

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return self.intercept + self.slope * np.asarray(x)


def fit_line(x: np.ndarray, y: np.ndarray, what: str = "the line fit") -> LineFit:
    """Least squares y = intercept + slope x; NumericalFailure (naming `what`) when the
    system is singular or the result is not finite."""
    design = np.stack([np.ones_like(x), x], axis=1)  # (n, 2)
    coefficients, _, rank, _ = np.linalg.lstsq(design, y, rcond=None)
    if rank < 2:  # x spans too little beside its size for a slope and an offset apart
        raise NumericalFailure(f"{what}: singular least-squares system (x from {np.min(x):.4g} to "
                               f"{np.max(x):.4g}): no slope and offset can be told apart")
    residual = y - design @ coefficients
    ssr = float(residual @ residual)
    sigma2 = ssr / max(len(x) - 2, 1)
    sst = float(np.sum((y - y.mean()) ** 2))
    try:
        covariance = sigma2 * np.linalg.inv(design.T @ design)
    except np.linalg.LinAlgError:
        raise NumericalFailure(f"{what}: singular normal matrix (x from {np.min(x):.4g} to "
                               f"{np.max(x):.4g})") from None
    fit = LineFit(float(coefficients[0]), float(coefficients[1]), covariance, math.sqrt(sigma2),
                  1.0 - ssr / sst if sst > 0 else 1.0)
    values = [fit.intercept, fit.slope, fit.residual_std, fit.r_squared, *covariance.ravel()]
    if not all(math.isfinite(value) for value in values):
        raise NumericalFailure(f"{what}: non-finite result (intercept {fit.intercept:.4g}, slope "
                               f"{fit.slope:.4g}, residual {fit.residual_std:.4g}; x from {np.min(x):.4g} "
                               f"to {np.max(x):.4g})")
    return fit


@dataclass
class NeedleFit:
    radius: float  # mm
    friction: float  # N/mm
    cutting_force: float  # N
    standard_uncertainty: tuple[float, float]  # (friction, cutting_force)
    tissue_fit: LineFit  # corrected force (N) against inserted length (mm)
    background: LineFit  # air force (N) against angle (rad)
    air: np.ndarray  # (n, 2) angle, force
    tissue: np.ndarray  # (n, 2) angle, force
    corrected: np.ndarray  # (n,) tissue force minus background, N
    inserted_length: np.ndarray  # (n,) radius x angle, mm
    warnings: list[str] = field(default_factory=list)
    sources: tuple[str, str] = ("", "")
    source_sha256: tuple[str | None, str | None] = (None, None)  # of the recordings' bytes as read


def fit_needle(air_angle: np.ndarray, air_force: np.ndarray, tissue_angle: np.ndarray,
               tissue_force: np.ndarray, radius: float) -> NeedleFit:
    """Background line in air, subtracted at the tissue angles; line against radius x angle.

    The uncertainties combine the scatter of both recordings: the background's coefficient
    covariance is carried through the linear map from background line to (cutting, friction).
    """
    background = fit_line(air_angle, air_force, "needle fit: the background line (air force against angle)")
    corrected = tissue_force - background(tissue_angle)
    length = radius * tissue_angle
    tissue_line = ("needle fit: the tissue line (corrected force against inserted length, "
                   f"radius {radius:g} mm x angle)")
    tissue_fit = fit_line(length, corrected, tissue_line)
    design = np.stack([np.ones_like(length), length], axis=1)
    try:
        projector = np.linalg.solve(design.T @ design, design.T)  # (2, n): data -> (intercept, slope)
    except np.linalg.LinAlgError:
        raise NumericalFailure(f"{tissue_line}: singular normal matrix") from None
    carried = projector @ np.stack([np.ones_like(tissue_angle), tissue_angle], axis=1)  # (2, 2)
    covariance = tissue_fit.covariance + carried @ background.covariance @ carried.T
    variances = covariance[1, 1], covariance[0, 0]  # friction, cutting force
    if not all(math.isfinite(value) and value >= 0 for value in variances):
        raise NumericalFailure(f"{tissue_line}: the uncertainties came out as variances {variances[0]:.4g} "
                               f"(friction) and {variances[1]:.4g} (cutting force), expected finite "
                               "non-negative values")
    refuse_negative(tissue_fit, math.sqrt(variances[0]), math.sqrt(variances[1]))
    warnings = needle_warnings(air_angle, tissue_angle, tissue_fit, radius)
    for message in warnings:
        log.warning(message)
    return NeedleFit(
        radius=radius, friction=tissue_fit.slope, cutting_force=tissue_fit.intercept,
        standard_uncertainty=(math.sqrt(variances[0]), math.sqrt(variances[1])),
        tissue_fit=tissue_fit, background=background,
        air=np.stack([air_angle, air_force], axis=1),
        tissue=np.stack([tissue_angle, tissue_force], axis=1),
        corrected=corrected, inserted_length=length, warnings=warnings,
    )


def refuse_negative(tissue_fit: LineFit, friction_sigma: float, cutting_sigma: float) -> None:
    """NumericalFailure when the tissue line gives a negative friction (slope) or cutting force
    (intercept): no needle has them (a scenario's needle block refuses them), so the recordings
    do not show what the fit assumes, a tissue force growing from the cutting force at the
    entry by the friction along the inserted length."""
    friction, cutting = tissue_fit.slope, tissue_fit.intercept
    found = []  # (what the fit gave, why the recordings give it)
    if friction < 0:
        found.append((f"friction {friction:.4g} +- {friction_sigma:.2g} N/mm",
                      "the tissue recording's force less the air background does not grow with the "
                      "inserted length (radius x angle)"))
    if cutting < 0:
        found.append((f"cutting force {cutting:.4g} +- {cutting_sigma:.2g} N",
                      "the tissue recording starts below the air background where the tip enters"))
    if found:
        # only a negative value beyond its noise says the recordings are the wrong way round
        significant = friction < -2.0 * friction_sigma or cutting < -2.0 * cutting_sigma
        gave = " and ".join(gave for gave, _ in found)
        if significant:
            raise NumericalFailure(f"needle fit: the fit gave {gave}, expected >= 0: "
                                   f"{', and '.join(why for _, why in found)}; is --tissue the recording in tissue "
                                   "and --air the one in air?")
        raise NumericalFailure(f"needle fit: the fit gave {gave}, expected >= 0: zero within twice "
                               f"{'its' if len(found) == 1 else 'their'} standard uncertainty, the tissue recording "
                               "shows no force above the air's (record more of the insertion, or a tissue that "
                               "grips the needle)")


LATE_START = 0.1  # the tissue recording's first angle over its span beyond which the touch was missed


def needle_warnings(air_angle: np.ndarray, tissue_angle: np.ndarray, tissue_fit: LineFit,
                    radius: float) -> list[str]:
    """A tissue recording that starts well after the touch, extrapolated background, a poor
    line (negative values are refused: refuse_negative)."""
    warnings = []
    tissue_span = tissue_angle[-1] - tissue_angle[0]
    if tissue_angle[0] > LATE_START * tissue_span:
        warnings.append(
            f"the tissue recording starts at {tissue_angle[0]:.3g} rad, not at the touch (0 rad): the "
            f"cutting force is the line extrapolated back over {radius * tissue_angle[0]:.3g} mm of "
            "inserted length; record from the moment the tip touches the tissue")
    span = air_angle[-1] - air_angle[0]
    if tissue_angle[0] < air_angle[0] - 0.01 * span or tissue_angle[-1] > air_angle[-1] + 0.01 * span:
        warnings.append(
            f"the tissue recording ({tissue_angle[0]:.3g} to {tissue_angle[-1]:.3g} rad) reaches outside "
            f"the air recording ({air_angle[0]:.3g} to {air_angle[-1]:.3g} rad): the background is "
            "extrapolated there")
    if tissue_fit.r_squared < MIN_R_SQUARED:
        warnings.append(f"the corrected force is far from linear in the inserted length "
                        f"(R^2 = {tissue_fit.r_squared:.3f}); check the recordings")
    return warnings


def read_force_recording(path: str | Path, label: str, max_rows: int | None = None,
                         rows_note: str = "") -> tuple[np.ndarray, np.ndarray, str]:
    """angle_rad, force_N of a recording and the SHA-256 of the bytes read; at least
    MIN_FORCE_SAMPLES rows, angles strictly increasing over at least MIN_ANGLE_SPAN rad, at
    most `max_rows` (read_numeric_table's)."""
    data, lines, digest = read_numeric_table(path, FORCE_COLUMNS, "a force recording over the needle angle",
                                             exact=True, label=label, max_rows=max_rows, rows_note=rows_note)
    angle, force = data["angle_rad"], data["force_N"]
    beyond = np.flatnonzero(np.abs(force) > MAX_FORCE_N)
    if len(beyond):
        k = beyond[0]
        raise InputError(f"{label}: {path}: line {lines[k]}, force_N: got {force[k]:g}, expected "
                         f"|force| <= {MAX_FORCE_N:g} N (a suture needle is turned by a few N; "
                         "is the recording in mN?)")
    if len(angle) < MIN_FORCE_SAMPLES:
        raise InputError(f"{label}: {path}: rows: got {len(angle)} samples, expected at least "
                         f"{MIN_FORCE_SAMPLES}")
    steps = np.diff(angle)
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0)) + 1
        raise InputError(f"{label}: {path}: line {lines[k]}, angle_rad: got {angle[k]:g} after "
                         f"{angle[k - 1]:g}, expected strictly increasing angles")
    span = float(angle[-1] - angle[0])
    if span < MIN_ANGLE_SPAN:
        raise InputError(f"{label}: {path}: angle_rad: got a span of {span:.3g} rad, expected at "
                         f"least {MIN_ANGLE_SPAN:g} rad")
    if span > MAX_ANGLE_SPAN:
        raise InputError(f"{label}: {path}: angle_rad: got a span of {span:.4g} rad, expected at most "
                         f"{MAX_ANGLE_SPAN:.4g} rad (one turn of the needle; are the angles in degrees?)")
    return angle, force, digest


def _needle_radius(radius: object) -> float:
    """The radius in mm, within MIN_RADIUS_MM and MAX_RADIUS_MM."""
    number = isinstance(radius, (int, float)) and not isinstance(radius, bool)
    if not (number and math.isfinite(radius) and MIN_RADIUS_MM <= radius <= MAX_RADIUS_MM):
        unit_slip = number and math.isfinite(radius) and radius > 0
        raise InputError(f"--radius: got {radius!r}, expected a positive number (mm) from {MIN_RADIUS_MM:g} to "
                         f"{MAX_RADIUS_MM:g}" + ("; suture needles measure about 1 to 40 mm in radius: is it "
                                                 "in m or micrometres?" if unit_slip else ""))
    return float(radius)


def calibrate_needle(air: str | Path, tissue: str | Path, radius: float, max_rows: int | None = None,
                     rows_note: str = "") -> NeedleFit:
    """`stitchplan calibrate needle`: read both recordings, validate and fit; at most
    `max_rows` rows in both (the resource guard's; `rows_note`: why)."""
    radius = _needle_radius(radius)
    air_angle, air_force, air_digest = read_force_recording(air, "--air", max_rows, f" in both recordings{rows_note}")
    left = None if max_rows is None else max_rows - len(air_angle)
    tissue_angle, tissue_force, tissue_digest = read_force_recording(
        tissue, "--tissue", left, f" beside --air's {len(air_angle)} ({max_rows} in both recordings){rows_note}")
    # a copy of the air recording under another name (the same file is refused by name before):
    # the fit subtracts it from itself and wrote friction and cutting force of ~1e-17
    if np.array_equal(air_angle, tissue_angle) and np.array_equal(air_force, tissue_force):
        raise InputError(f"--tissue: {tissue}: got the same angles and forces as --air's {air}; expected the "
                         "recording in tissue, not a copy of the one in air")
    if tissue_angle[0] < 0:
        raise InputError(f"--tissue: {tissue}: angle_rad: got {tissue_angle[0]:g} first, expected "
                         "angles >= 0 rad (rotation since the tip touched the tissue)")
    try:
        result = fit_needle(air_angle, air_force, tissue_angle, tissue_force, radius)
    except NumericalFailure as failure:  # the recordings' doing: name them
        raise NumericalFailure(f"--tissue {tissue} and --air {air}: {failure}") from None
    result.sources = (str(air), str(tissue))
    result.source_sha256 = (air_digest, tissue_digest)
    return result
