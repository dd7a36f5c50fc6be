"""Regenerate the SYNTHETIC calibration data in this folder.

Nothing here was measured. The marker files are the deformed positions that stitchplan's
own forward model (the static solver behind `stitchplan deform`, via
stitchplan.calibration.simulate_markers) predicts for known Lamé moduli, plus Gaussian
noise; the force recordings are straight lines with known friction and cutting force plus
Gaussian noise. Fitting them back shows how well the calibration recovers known values.

    python sample_runs/calibration/generate.py        # rewrites the inputs (seeded)

then the commands in README.md rewrite the fitted outputs and plots. The skin-layered and
inclusion files come out identical; the 100 x 60 mm block's marker files were made with the forward model of
stitchplan 0.1.0 and are kept as shipped (the fits, the regression pins and the uncertainty
example are theirs): rewritten by today's model their deformed positions move by up to
0.0006 mm under the forces and 0.069 mm under the displacement, whose segment now acts on
exactly the segment given (README, Load segments).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
from pydantic import TypeAdapter

from stitchplan.calibration import simulate_markers
from stitchplan.config import load_scenario
from stitchplan.config.blocks import Region
from stitchplan.config.scenario import Discretization, Load, Material, Tissue
from stitchplan.io.files import write_text

HERE = Path(__file__).resolve().parent
SEED = 20240611

# --- material: two force experiments on a 100 x 60 mm block clamped on the right -------
TRUE_MATERIAL = Material("saint-venant-kirchhoff", lame_lambda=0.189151, lame_mu=0.147688)
TISSUE = Tissue((100.0, 60.0), 10.0, TRUE_MATERIAL, ("right",))
# generated at half the fit's default spacing (3 mm for this block), so the fit does not
# see its own discretization (about 0.5 % bias in lambda, 0.2 % in mu, noise-free)
GENERATION = Discretization(spacing=1.5)
MARKER_NOISE_MM = 0.05
MARKERS_PER_EXPERIMENT = 20
EXPERIMENTS = {
    "markers1.csv": (Load(((0.0, 24.0), (0.0, 36.0)), force=(2.0, 1.0)),),
    "markers2.csv": (Load(((20.0, 60.0), (60.0, 60.0)), force=(-1.0, -3.0)),),
}
# displacement-controlled counter-example: only lambda/mu can be identified from it
DISPLACEMENT_EXPERIMENT = {
    "markers_displacement.csv": (Load(((0.0, 20.0), (0.0, 40.0)), displacement=(-4.0, 2.0)),),
}

# --- material around a region of known material: configs/skin_layered.yaml's patch ------
# its subcutaneous tissue (the tissue's own material, the truth here) under the skin layer
# (its region, of known moduli), clamped along the bottom as the scene is
SKIN_SCENARIO = HERE.parents[1] / "configs" / "skin_layered.yaml"
SKIN_GENERATION = Discretization(spacing=0.75)  # half the fit's default 1.5 mm for 60 x 30 mm
SKIN_MARKERS = 40
SKIN_EXPERIMENTS = {
    "markers_skin1.csv": (Load(((60.0, 0.0), (60.0, 30.0)), force=(2.0, 0.0)),),
    "markers_skin2.csv": (Load(((20.0, 30.0), (40.0, 30.0)), force=(0.0, -2.0)),),
}

# --- a stiff inclusion whose moduli are fitted too: the block above around a lesion ---------
# (neo-Hookean, 4x the tissue's moduli), from three force experiments; inclusion.yaml starts
# the lesion's moduli at 0.3 MPa each
INCLUSION = {"circle": {"center": [45.0, 30.0], "radius": 14.0},
             "material": {"model": "neo-hookean", "lame_lambda": 0.756604, "lame_mu": 0.590752}}
INCLUSION_MARKERS = 40
INCLUSION_EXPERIMENTS = {
    "markers_inclusion1.csv": EXPERIMENTS["markers1.csv"],
    "markers_inclusion2.csv": EXPERIMENTS["markers2.csv"],
    "markers_inclusion3.csv": (Load(((0.0, 0.0), (0.0, 60.0)), force=(4.0, 0.0)),),
}

# --- needle: ETHICON SH radius, friction and cutting force of the thesis's phantom -------
RADIUS_MM = 8.88
FRICTION_N_PER_MM = 0.0602
CUTTING_FORCE_N = 0.7
BACKGROUND = (0.12, 0.035)  # N, N/rad: bearing and cable drag of the rotation stage
AIR_NOISE_N = 0.01
TISSUE_NOISE_N = 0.02


def _csv(path: Path, header: str, columns: list[str], rows: np.ndarray) -> None:
    lines = [f"# {line}" for line in header.strip().splitlines()]
    lines.append(",".join(columns))
    lines += [",".join(f"{v:.6f}" for v in row) for row in rows]
    write_text(path, "\n".join(lines) + "\n")


def markers(rng: np.random.Generator, count: int) -> np.ndarray:
    """Rest positions spread over the block, away from the clamped right edge."""
    width, height = TISSUE.size
    return np.column_stack([rng.uniform(2.0, width - 5.0, count), rng.uniform(2.0, height - 2.0, count)])


def material_data(rng: np.random.Generator) -> None:
    for name, loads in {**EXPERIMENTS, **DISPLACEMENT_EXPERIMENT}.items():
        rest = markers(rng, MARKERS_PER_EXPERIMENT)
        deformed = simulate_markers(TISSUE, GENERATION, loads, rest, TRUE_MATERIAL)
        deformed += MARKER_NOISE_MM * rng.standard_normal(deformed.shape)
        header = (f"SYNTHETIC markers, not measured: generate.py (seed {SEED}), stitchplan forward model\n"
                  f"lame_lambda {TRUE_MATERIAL.lame_lambda} MPa, lame_mu {TRUE_MATERIAL.lame_mu} MPa, "
                  f"spacing {GENERATION.spacing} mm, + Gaussian noise {MARKER_NOISE_MM} mm")
        _csv(HERE / name, header, ["x", "y", "x_def", "y_def"], np.hstack([rest, deformed]))


def skin_layered_data(rng: np.random.Generator) -> None:
    tissue = load_scenario(SKIN_SCENARIO).tissue
    truth = tissue.material
    width, height = tissue.size
    for name, loads in SKIN_EXPERIMENTS.items():
        rest = np.column_stack([rng.uniform(1.0, width - 1.0, SKIN_MARKERS), rng.uniform(2.0, height - 0.5, SKIN_MARKERS)])
        deformed = simulate_markers(tissue, SKIN_GENERATION, loads, rest, truth)
        deformed += MARKER_NOISE_MM * rng.standard_normal(deformed.shape)
        header = (f"SYNTHETIC markers, not measured: generate.py (seed {SEED + 1}), stitchplan forward model\n"
                  f"of configs/skin_layered.yaml's patch: {truth.model}, lame_lambda {truth.lame_lambda} MPa, "
                  f"lame_mu {truth.lame_mu} MPa\naround its skin layer (the region), spacing "
                  f"{SKIN_GENERATION.spacing} mm, + Gaussian noise {MARKER_NOISE_MM} mm")
        _csv(HERE / name, header, ["x", "y", "x_def", "y_def"], np.hstack([rest, deformed]))


def inclusion_data(rng: np.random.Generator) -> None:
    tissue = replace(TISSUE, regions=(TypeAdapter(Region).validate_python(INCLUSION),))
    lesion = INCLUSION["material"]
    for name, loads in INCLUSION_EXPERIMENTS.items():
        rest = markers(rng, INCLUSION_MARKERS)
        deformed = simulate_markers(tissue, GENERATION, loads, rest, TRUE_MATERIAL)
        deformed += MARKER_NOISE_MM * rng.standard_normal(deformed.shape)
        header = (f"SYNTHETIC markers, not measured: generate.py (seed {SEED + 2}), stitchplan forward model\n"
                  f"of the block: lame_lambda {TRUE_MATERIAL.lame_lambda} MPa, lame_mu {TRUE_MATERIAL.lame_mu} MPa "
                  f"around a stiff inclusion\n(circle centre {INCLUSION['circle']['center']} mm, radius "
                  f"{INCLUSION['circle']['radius']} mm, {lesion['model']}, lame_lambda {lesion['lame_lambda']} MPa, "
                  f"lame_mu {lesion['lame_mu']} MPa),\nspacing {GENERATION.spacing} mm, + Gaussian noise "
                  f"{MARKER_NOISE_MM} mm")
        _csv(HERE / name, header, ["x", "y", "x_def", "y_def"], np.hstack([rest, deformed]))


def needle_data(rng: np.random.Generator) -> None:
    offset, slope = BACKGROUND
    air_angle = np.arange(0.0, np.pi, 0.02)
    air_force = offset + slope * air_angle + AIR_NOISE_N * rng.standard_normal(len(air_angle))
    header = (f"SYNTHETIC recording, not measured: generate.py (seed {SEED}); needle turned in air:\n"
              f"background {offset} N + {slope} N/rad x angle + Gaussian noise {AIR_NOISE_N} N")
    _csv(HERE / "air.csv", header, ["angle_rad", "force_N"], np.column_stack([air_angle, air_force]))
    angle = np.arange(0.0, 2.8, 0.02)
    force = (offset + slope * angle + CUTTING_FORCE_N + FRICTION_N_PER_MM * RADIUS_MM * angle
             + TISSUE_NOISE_N * rng.standard_normal(len(angle)))
    header = (f"SYNTHETIC recording, not measured: generate.py (seed {SEED}); needle turned into tissue\n"
              f"from the moment the tip touches it: background + cutting {CUTTING_FORCE_N} N + friction "
              f"{FRICTION_N_PER_MM} N/mm x {RADIUS_MM} mm x angle + Gaussian noise {TISSUE_NOISE_N} N")
    _csv(HERE / "tissue.csv", header, ["angle_rad", "force_N"], np.column_stack([angle, force]))


def main() -> None:
    rng = np.random.default_rng(SEED)
    material_data(rng)
    needle_data(rng)
    skin_layered_data(np.random.default_rng(SEED + 1))  # its own stream: the files above stay as they were
    inclusion_data(np.random.default_rng(SEED + 2))


if __name__ == "__main__":
    main()
