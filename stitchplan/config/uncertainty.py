"""The `--uncertainty` file of `stitchplan plan` (README, "Planning under
uncertainty"): how many parameter sets to draw, the seed, and a normal distribution around
the scenario's value for each uncertain parameter, with correlations.

    samples: 32
    seed: 7
    from_calibration: fitted.yaml     # lame_lambda, lame_mu std and their correlation
    parameters:
      thickness: {std: 0.5}           # mm
    correlation:
      - {between: [lame_lambda, lame_mu], value: -0.9}

`from_calibration` reads a `stitchplan calibrate material` output (path relative to this
file): its `fit.standard_uncertainty` gives the std of lame_lambda and lame_mu and its
`fit.correlation` their correlation (where it fitted regions' moduli too, those are sampled
as well: `tissue.regions[k].lame_*`, their stds from `fit.fitted_regions`, every pair's
correlation from `fit.correlations`); entries of `parameters` and `correlation` given in
this file override them. `resolve_uncertainty` gives the resolved `Uncertainty` (names,
stds, correlation matrix), refusing a matrix that is not positive definite;
`check_against_scenario` refuses a parameter the scenario does not have, a std above the
scenario's value, and uncertain moduli on a scenario with material regions unless they are a
calibration's fitted around the same regions.
"""

from __future__ import annotations

import difflib
import math
import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import Field, Strict, ValidationInfo, field_validator, model_validator

from ..errors import InputError
from .blocks import Region, block
from .fields import choice, described, expecting, integer, number, pair, problem, sequence
from .messages import input_error, short, validate
from .yaml_files import read_yaml_file, with_key_problems

# the uncertain parameters and their units (the scenario's fields they replace: UNITS order)
UNITS = {"lame_lambda": "MPa", "lame_mu": "MPa", "friction": "N/mm", "cutting_force": "N",
         "thickness": "mm"}
PARAMETERS = tuple(UNITS)
# a region's moduli, sampled when a calibration fitted them (its fit.fitted_regions)
REGION_MODULUS = re.compile(r"tissue\.regions\[(\d+)\]\.(lame_lambda|lame_mu)")


def unit_of(name: str) -> str:
    """The units of parameter `name`, a region's moduli's too."""
    region = REGION_MODULUS.fullmatch(name)
    return UNITS[region.group(2) if region else name]
MAX_SAMPLES = 10_000
# the robust plan re-aims only when the training runs' mean exit shift stands out of their
# noise, by Hotelling's T^2, which needs 3 deviations (uncertainty.robust.shift_significance):
# with 2 the robust plan could only ever be the nominal one
MIN_SAMPLES = 3

Parameter = choice(PARAMETERS, "one of " + ", ".join(PARAMETERS))
CalibrationFile = Annotated[str, Strict(), Field(min_length=1),
                            expecting("a `calibrate material` output file (relative to this file)")]


@block(title="parameter")
class Spread:
    """A normal distribution around the scenario's value, truncated to positive values."""

    std: described(number("a positive number (the parameter's units)", gt=0), "standard deviation")

    @model_validator(mode="before")
    @classmethod
    def _a_normal_distribution(cls, data: Any) -> Any:
        """Another distribution ({low, high}, {mean, sigma}) is one problem, told as such, not a
        missing std and an unknown key each (a misspelt std keeps its own line)."""
        if (isinstance(data, dict) and data and "std" not in data
                and not any(difflib.get_close_matches(str(key), ["std"]) for key in data)):
            raise problem("{std: s}: a normal distribution around the scenario's value with standard deviation s "
                          "(the parameter's units), truncated to positive values; no other distribution is sampled")
        return data


@block(title="parameters")
class Spreads:
    lame_lambda: described(Spread | None, "MPa") = None
    lame_mu: described(Spread | None, "MPa") = None
    friction: described(Spread | None, "N/mm") = None
    cutting_force: described(Spread | None, "N") = None
    thickness: described(Spread | None, "mm") = None

    @field_validator("*", mode="before")
    @classmethod
    def _not_blank(cls, value: Any) -> Any:
        """A parameter given without a value (`friction:`) is refused, not dropped: the file
        says it is uncertain but not by how much."""
        if value is None:
            raise problem("a mapping {std: ...} giving the parameter's standard deviation (to keep the "
                          "parameter fixed, remove it)")
        return value


@block(title="correlation")
class Correlation:
    between: described(pair("two different parameter names [a, b]", Parameter), "the two parameters")
    value: described(number("a number between -1 and 1 (exclusive)", gt=-1, lt=1), "correlation coefficient")

    @model_validator(mode="after")
    def _two_different(self) -> Correlation:
        if self.between[0] == self.between[1]:
            raise problem("two different parameter names [a, b]", field="between", value=list(self.between))
        return self


@block(kw_only=True, title="stitchplan uncertainty")
class UncertaintyFile:
    """An uncertainty file as written."""

    samples: described(integer(MIN_SAMPLES, MAX_SAMPLES,
                               f"training runs, and as many held out; the robust plan's test of the mean exit shift "
                               f"needs at least {MIN_SAMPLES}"),
                       "parameter sets that train the robust plan (and as many held out)")
    seed: described(integer(0, 2 ** 32 - 1), "seed of the low-discrepancy design") = 0
    from_calibration: described(CalibrationFile | None, "`calibrate material` output: lame_lambda and "
                                                        "lame_mu std and correlation") = None
    parameters: described(Spreads | None, "normal distributions around the scenario's values") = None
    correlation: described(sequence(Correlation, "a list of {between: [a, b], value: r}"),
                           "correlations between parameters") = ()

    @field_validator("from_calibration", "parameters", mode="before")
    @classmethod
    def _not_blank(cls, value: Any, info: ValidationInfo) -> Any:
        """A key given without a value (`from_calibration:`) is refused, not dropped: the run
        would sample without what the file names (the calibration's moduli)."""
        if value is None:
            what = ("a `stitchplan calibrate material` output file (fitted.yaml), relative to this file"
                    if info.field_name == "from_calibration" else "a mapping of parameters to {std: ...}")
            raise problem(f"{what} (or remove the key)")
        return value

    @model_validator(mode="after")
    def _pairs_once(self) -> UncertaintyFile:
        seen: dict[frozenset, int] = {}
        for k, entry in enumerate(self.correlation):
            key = frozenset(entry.between)
            if key in seen:
                raise problem(f"each pair once (given at correlation[{seen[key]}] already)",
                              field=f"correlation[{k}].between", value=list(entry.between))
            seen[key] = k
        return self


@dataclass(frozen=True)
class Uncertainty:
    """The resolved distributions: `names` (PARAMETERS order) with their `std` and the
    correlation matrix (len(names) square, positive definite); where each came from."""

    samples: int
    seed: int
    names: tuple[str, ...]
    std: np.ndarray  # (k,)
    correlation: np.ndarray  # (k, k)
    sources: dict[str, str]  # name -> "file" or "calibration"
    path: str  # the uncertainty file
    calibration: str | None  # the calibrate material output read, if any
    correlation_sources: dict[frozenset, str] = field(default_factory=dict)  # pair -> "file" | "calibration"
    calibration_regions: tuple = ()  # Region: those the calibration's moduli were fitted around
    sha256: str | None = None  # of the file's bytes as parsed (a pipe gives them once)
    calibration_sha256: str | None = None  # of the calibration's bytes as parsed

    @property
    def covariance(self) -> np.ndarray:
        return self.correlation * np.outer(self.std, self.std)

    def as_record(self) -> dict:
        return {"samples": self.samples, "seed": self.seed,
                "parameters": {name: {"std": float(s), "units": unit_of(name), "source": self.sources[name]}
                               for name, s in zip(self.names, self.std)},
                "correlation": [{"between": [a, b], "value": float(self.correlation[i, j]),
                                 "source": self.correlation_sources.get(frozenset((a, b)), "file")}
                                for i, a in enumerate(self.names) for j, b in enumerate(self.names)
                                if i < j and self.correlation[i, j] != 0.0],
                "from_calibration": self.calibration}


def parse_uncertainty(raw: Any) -> UncertaintyFile:
    """The validated file; an InputError lists every problem of it."""
    return validate(UncertaintyFile, raw, "", root="uncertainty")


def load_uncertainty(path: str | Path) -> Uncertainty:
    """The resolved uncertainty of a file; every error line starts with the file's path."""
    file = read_yaml_file(path, keys_later=True)
    spec = with_key_problems(file, path, parse_uncertainty)
    return replace(resolve_uncertainty(spec, path), sha256=file.sha256)


def resolve_uncertainty(spec: UncertaintyFile, path: str | Path) -> Uncertainty:
    """Stds and correlations from the file and its `from_calibration` output (the file's own
    entries win); the correlation matrix must be positive definite."""
    path = Path(path)
    std: dict[str, float] = {}
    sources: dict[str, str] = {}
    pairs: dict[frozenset, float] = {}
    pair_sources: dict[frozenset, str] = {}
    calibration, calibration_regions, calibration_sha256 = None, (), None
    if spec.from_calibration is not None:
        calibration = path.parent / spec.from_calibration
        std, pairs, calibration_regions, calibration_sha256 = calibration_spread(calibration, path)
        sources = {name: "calibration" for name in std}
        pair_sources = {pair: "calibration" for pair in pairs}
    given = spec.parameters or Spreads()
    for name in PARAMETERS:
        spread = getattr(given, name)
        if spread is not None:
            std[name], sources[name] = spread.std, "file"
    for entry in spec.correlation:
        pairs[frozenset(entry.between)] = entry.value
        pair_sources[frozenset(entry.between)] = "file"
    # the scenario's parameters, then the calibration's fitted regions' moduli in its order
    names = tuple(name for name in PARAMETERS if name in std) + tuple(name for name in std if name not in PARAMETERS)
    lines = []
    if not names:
        lines.append(f"{path}: parameters: got none, expected at least one uncertain parameter among "
                     f"{', '.join(PARAMETERS)} (or from_calibration)")
    for k, entry in enumerate(spec.correlation):
        missing = [name for name in entry.between if name not in std]
        if missing:
            lines.append(f"{path}: correlation[{k}].between: got {list(entry.between)}, expected parameters "
                         f"with a std ({missing[0]} has none in parameters" +
                         (" or from_calibration)" if spec.from_calibration is None or missing[0] not in
                          ("lame_lambda", "lame_mu") else ")"))
    if lines:
        raise input_error(lines)
    matrix = np.eye(len(names))
    for i, a in enumerate(names):
        for j, b in enumerate(names):
            if i != j:
                matrix[i, j] = pairs.get(frozenset((a, b)), 0.0)
    try:
        np.linalg.cholesky(matrix)
    except np.linalg.LinAlgError:
        smallest = float(np.linalg.eigvalsh(matrix).min())
        given_pairs = [f"{'-'.join(sorted(pair_names))} {value:g}" for pair_names, value in pairs.items()]
        raise input_error([f"{path}: correlation: got {short('; '.join(given_pairs))}, expected a positive "
                           f"definite correlation matrix (its smallest eigenvalue is {smallest:.3g})"]) from None
    return Uncertainty(spec.samples, spec.seed, names, np.array([std[name] for name in names]), matrix,
                       {name: sources[name] for name in names}, str(path),
                       None if calibration is None else str(calibration), pair_sources, calibration_regions,
                       calibration_sha256=calibration_sha256)


def calibration_spread(calibration: Path, source: Path) -> tuple[dict[str, float], dict[frozenset, float], tuple, str]:
    """The standard uncertainties of the moduli a `calibrate material` output fitted (the
    tissue's lame_lambda and lame_mu, and `tissue.regions[k].lame_*` of each region in its
    fit.fitted_regions), the correlations of their pairs, the regions (Region) it was
    fitted around (none in outputs without `regions`) and the SHA-256 of the bytes parsed."""
    where = f"{source}: from_calibration: {calibration}"
    if not calibration.is_file():
        what = "Is a directory" if calibration.is_dir() else "No such file or directory"  # as the OS says it
        raise input_error([f"{where}: cannot be read ({what}), expected a `stitchplan calibrate "
                           "material` output (path relative to the uncertainty file)"])
    try:
        file = read_yaml_file(calibration)
        raw = file.data
    except Exception as error:
        raise input_error([f"{source}: from_calibration: {line}" for line in getattr(error, "lines", [str(error)])]) from None
    fit = raw.get("fit") if isinstance(raw, dict) else None
    if not isinstance(fit, dict) or not isinstance(fit.get("standard_uncertainty"), dict):
        raise input_error([f"{where}: fit.standard_uncertainty: missing, expected a `stitchplan calibrate "
                           "material` output (fitted.yaml)"])
    given = {name: fit["standard_uncertainty"].get(name) for name in ("lame_lambda", "lame_mu")}
    if not all(_finite(value) and value > 0 for value in given.values()):
        why = ("; the calibration did not identify the moduli (fit.identifiable: false: they could not be "
               "separated, or one ended on a bound of its search range)" if fit.get("identifiable") is False else "")
        raise input_error([f"{where}: fit.standard_uncertainty: got {short(given)}, expected positive standard "
                           f"uncertainties of lame_lambda and lame_mu (MPa){why}"])
    if not isinstance(fit.get("identifiable", True), bool):  # a quoted "no" is a string, not false
        raise input_error([f"{where}: fit.identifiable: got {short(fit['identifiable'])}, expected true or "
                           "false, as `calibrate material` writes it"])
    if fit.get("identifiable") is False:
        raise input_error([f"{where}: fit.identifiable: got false, expected a calibration that identifies "
                           "the moduli (its standard uncertainties and correlation are not usable: add a "
                           "force-controlled experiment or markers that move more, or widen a search range "
                           "the fit ended on; its warnings say which)"])
    value = fit.get("correlation")
    if not (_finite(value) and -1 < value < 1):
        raise input_error([f"{where}: fit.correlation: got {short(value)}, expected a number between -1 and 1 "
                           "(exclusive)"])
    std = {name: float(v) for name, v in given.items()}
    pairs = {frozenset(("lame_lambda", "lame_mu")): float(value)}
    regions = _calibration_regions(raw.get("regions"), where)
    if fit.get("fitted_regions"):
        region_std, pairs = _fitted_regions_spread(fit, len(regions), where)
        std.update(region_std)
    return std, pairs, regions, file.sha256


def _fitted_regions_spread(fit: dict, regions: int, where: str) -> tuple[dict[str, float], dict[frozenset, float]]:
    """The fitted regions' moduli' stds (fit.fitted_regions) and the correlations of every pair
    of fitted moduli (fit.correlations), as `calibrate material` writes them."""
    entries, std = fit["fitted_regions"], {}
    if not isinstance(entries, list):
        raise input_error([f"{where}: fit.fitted_regions: got {short(entries)}, expected a list of "
                           "{region: k, standard_uncertainty: {lame_lambda, lame_mu}}, as `calibrate material` "
                           "writes it"])
    lines = []
    for i, entry in enumerate(entries):
        index = entry.get("region") if isinstance(entry, dict) else None
        spread = entry.get("standard_uncertainty") if isinstance(entry, dict) else None
        if not (isinstance(index, int) and not isinstance(index, bool) and 0 <= index < regions):
            lines.append(f"{where}: fit.fitted_regions[{i}].region: got {short(index)}, expected an index of its "
                         f"regions: (0 to {regions - 1})" if regions else
                         f"{where}: fit.fitted_regions[{i}].region: got {short(index)}, expected none: its "
                         "regions: is empty")
            continue
        for name in ("lame_lambda", "lame_mu"):
            value = spread.get(name) if isinstance(spread, dict) else None
            if not (_finite(value) and value > 0):
                lines.append(f"{where}: fit.fitted_regions[{i}].standard_uncertainty.{name}: got {short(value)}, "
                             "expected a positive standard uncertainty (MPa)")
            else:
                std[f"tissue.regions[{index}].{name}"] = float(value)
    correlations = fit.get("correlations")
    names = correlations.get("parameters") if isinstance(correlations, dict) else None
    matrix = correlations.get("matrix") if isinstance(correlations, dict) else None
    expected = ["lame_lambda", "lame_mu", *std]
    if not lines and (names != expected or not _correlation_matrix(matrix, len(expected))):
        lines.append(f"{where}: fit.correlations: got {short(correlations)}, expected the parameters {expected} "
                     "and their correlation matrix, as `calibrate material` writes them")
    if lines:
        raise input_error(lines)
    pairs = {frozenset((a, b)): float(matrix[i][j]) for i, a in enumerate(names) for j, b in enumerate(names) if i < j}
    return std, pairs


def _correlation_matrix(matrix: Any, size: int) -> bool:
    """A symmetric size x size matrix of numbers in (-1, 1) with a unit diagonal."""
    if not (isinstance(matrix, list) and len(matrix) == size
            and all(isinstance(row, list) and len(row) == size and all(_finite(v) for v in row) for row in matrix)):
        return False
    values = np.array(matrix, dtype=float)
    return bool(np.allclose(values, values.T) and np.all(np.diag(values) == 1.0)
                and np.all(np.abs(values[~np.eye(size, dtype=bool)]) < 1.0))


def _calibration_regions(raw: Any, where: str) -> tuple:
    """The `regions` of a calibration output as Regions; an InputError naming them if they are
    not a list of regions."""
    if raw is None:
        return ()
    if not isinstance(raw, list):
        raise input_error([f"{where}: regions: got {short(raw)}, expected a list of regions ({{polygon: ...}} or "
                           "{circle: ...}, and material: ...), as `calibrate material` writes them"])
    regions, lines = [], []
    for i, given in enumerate(raw):
        try:
            regions.append(validate(Region, given, f"regions[{i}]"))
        except InputError as error:
            lines += [f"{where}: {line}" for line in getattr(error, "lines", [str(error)])]
    if lines:
        raise input_error(lines)
    return tuple(regions)


def _finite(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def scenario_values(scenario, names: tuple[str, ...]) -> np.ndarray:
    """The scenario's values of the parameters `names` (PARAMETERS' units; a region's moduli
    `tissue.regions[k].lame_*` its material's)."""
    tissue, needle = scenario.tissue, scenario.needle
    values = {"lame_lambda": tissue.material.lame_lambda, "lame_mu": tissue.material.lame_mu,
              "thickness": tissue.thickness,
              "friction": needle.friction if needle is not None else 0.0,
              "cutting_force": needle.cutting_force if needle is not None else 0.0}
    for k, region in enumerate(getattr(tissue, "regions", ()) or ()):
        for modulus in ("lame_lambda", "lame_mu"):
            values[f"tissue.regions[{k}].{modulus}"] = getattr(region.material, modulus)
    return np.array([values[name] for name in names], dtype=float)


def check_against_scenario(uncertainty: Uncertainty, scenario, scenario_path: str | Path) -> None:
    """Refuse what the sampled scenarios could not honour, one line each:

    - a parameter the scenario does not have (a zero friction or cutting force, no needle): a
      normal distribution truncated to positive values around 0 is not centred on the scenario;
    - a std above the scenario's value: more than 16 % of the normal would lie at or below 0,
      and the distribution truncated to positive values would no longer be around the
      scenario's value (its mean moves up by more than 0.29 std; a std of 1e300 samples only
      values that overflow the model);
    - lame_lambda or lame_mu on a scenario with material `regions`, unless they come from a
      calibration fitted around the same regions: a sample replaces tissue.material only, so
      the regions' moduli stay fixed, which is the calibration's model (the tissue's own
      moduli around regions of given material) and no other file's;
    - moduli from a calibration fitted around regions the scenario does not hold as given
      (a calibration that fitted regions' moduli too samples them as `tissue.regions[k].lame_*`,
      around the scenario's values);
    - a std that does not move the value in double precision: the sensitivity's step, half a
      std (uncertainty.robust), must change it, else the samples and the step are the value
      itself and the sensitivity reads 0 (a std of 1e-300 on a 10 mm thickness)."""
    scenario_regions = tuple(getattr(scenario.tissue, "regions", ()) or ())
    regions = len(scenario_regions)
    lines = _region_problems(uncertainty, scenario_regions, scenario_path)
    if lines:  # a fitted region's modulus may name a region the scenario lacks
        raise input_error(lines)
    values = scenario_values(scenario, uncertainty.names)
    for name, value, std in zip(uncertainty.names, values, uncertainty.std):
        where = {"friction": "needle", "cutting_force": "needle", "thickness": "tissue"}.get(name, "tissue.material")
        name_in_scenario = name
        region = REGION_MODULUS.fullmatch(name)
        if region:
            where, name_in_scenario = f"tissue.regions[{region.group(1)}].material", region.group(2)
        field = parameter_field(uncertainty, name)
        if value <= 0:
            lines.append(f"{uncertainty.path}: {field}: got {{std: {std:g}}}, expected a parameter the "
                         f"scenario has ({scenario_path} has {where}.{name_in_scenario} = {value:g}; remove it or "
                         "give the scenario a positive value)")
        elif std > value:
            std_field = field if uncertainty.sources.get(name) == "calibration" else f"{field}.std"
            lines.append(f"{uncertainty.path}: {std_field}: got {std:g}, expected at most the scenario's value "
                         f"{value:g} {unit_of(name)} ({scenario_path}: {where}.{name_in_scenario}): a larger std "
                         "puts more than 16 % of the normal at or below 0, and truncated to positive values it is "
                         "no longer centred on the scenario's value")
        elif std < 2.0 * np.spacing(value):
            std_field = field if uncertainty.sources.get(name) == "calibration" else f"{field}.std"
            lines.append(f"{uncertainty.path}: {std_field}: got {std:g}, expected at least "
                         f"{2.0 * np.spacing(value):.3g} {unit_of(name)}, a std that moves the scenario's value "
                         f"{value:g} ({scenario_path}: {where}.{name_in_scenario}) in double precision: half a "
                         "std, the sensitivity's step, would leave it as it is")
        if name in ("lame_lambda", "lame_mu") and regions and uncertainty.sources[name] != "calibration":
            lines.append(f"{uncertainty.path}: {field}: got {{std: {std:g}}}, expected no uncertain moduli for a "
                         f"scenario with material regions ({scenario_path} has {_counted(regions)} in tissue.regions, "
                         f"whose moduli the uncertainty would not reach: only tissue.material.{name} would vary; "
                         f"remove {name} from the uncertainty or the regions from the scenario, or take both moduli "
                         "from a `calibrate material` fitted around the scenario's regions: from_calibration)")
    if lines:
        raise input_error(lines)


def _counted(regions: int) -> str:
    return f"{regions} region{'s' * (regions != 1)}"


def _region_problems(uncertainty: Uncertainty, scenario_regions: tuple, scenario_path: str | Path) -> list[str]:
    """Moduli from a calibration whose regions are not the scenario's (shapes and materials as
    given): its moduli are the tissue's own around its regions, so they hold only there."""
    from_calibration = [name for name in ("lame_lambda", "lame_mu") if uncertainty.sources.get(name) == "calibration"]
    if not from_calibration or uncertainty.calibration_regions == scenario_regions:
        return []
    return [f"{uncertainty.path}: from_calibration: {uncertainty.calibration}: regions: got "
            f"{_counted(len(uncertainty.calibration_regions))}, expected the scenario's regions as given "
            f"({scenario_path} has {_counted(len(scenario_regions))} in tissue.regions"
            + (", with other shapes or materials" if len(scenario_regions) == len(uncertainty.calibration_regions)
               else "")
            + f"): the calibration's {' and '.join(from_calibration)} are the tissue's own around the regions it kept "
            "at their materials, and vary so only on the same regions"]


def parameter_field(uncertainty: Uncertainty, name: str) -> str:
    """Where the uncertainty file gives parameter `name`: `parameters.<name>`, or
    `from_calibration: <file>: fit.standard_uncertainty.<name>` for the calibration's."""
    region = REGION_MODULUS.fullmatch(name)
    if region:
        return (f"from_calibration: {uncertainty.calibration}: fit.fitted_regions (region {region.group(1)}): "
                f"standard_uncertainty.{region.group(2)}")
    if uncertainty.sources.get(name) == "calibration":
        return f"from_calibration: {uncertainty.calibration}: fit.standard_uncertainty.{name}"
    return f"parameters.{name}"
