"""Wall time and forward-solve count of `stitchplan calibrate material` on one experiment.

A 100 x 100 mm slab clamped on the right, pulled by 3 N over 20 mm of its left edge (the
shipped configs/slab_edge_load.yaml), 20 markers, at the default discretization (5 mm
spacing for this block). The markers are SYNTHETIC: the forward model's own prediction for
the thesis's phantom moduli plus 0.05 mm Gaussian noise (seeded). Target: < 30 s.

    python benchmarks/calibration_speed.py [--markers 20] [--noise 0.05] [--repeat 1]
"""

from __future__ import annotations

import os

# single-threaded BLAS, as the `stitchplan` command sets it (and for both codes compared):
# the numerics are sparse and small-dense, and BLAS threads only compete on 2 cores
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from stitchplan.calibration import calibrate_material, simulate_markers
from stitchplan.config.scenario import (
    Discretization,
    Load,
    Material,
    Tissue,
    default_spacing,
)
from stitchplan.io.files import write_csv, write_yaml

TRUE = Material("saint-venant-kirchhoff", 0.189151, 0.147688)
TISSUE = Tissue((100.0, 100.0), 10.0, TRUE, ("right",))
LOAD = Load(((0.0, 40.0), (0.0, 60.0)), force=(-3.0, 1.0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--markers", type=int, default=20)
    parser.add_argument("--noise", type=float, default=0.05, help="marker noise, mm")
    parser.add_argument("--repeat", type=int, default=1)
    args = parser.parse_args()

    spacing = default_spacing(TISSUE, None)
    rng = np.random.default_rng(7)
    rest = np.column_stack([rng.uniform(0.0, 95.0, args.markers), rng.uniform(0.0, 100.0, args.markers)])
    deformed = simulate_markers(TISSUE, Discretization(spacing=spacing), (LOAD,), rest, TRUE)
    deformed += args.noise * rng.standard_normal(deformed.shape)

    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        write_csv(folder / "markers.csv", ["x", "y", "x_def", "y_def"], np.hstack([rest, deformed]))
        write_yaml(folder / "calibration.yaml", {
            "tissue": {"size": list(TISSUE.size), "thickness": TISSUE.thickness, "clamped": ["right"]},
            "experiments": [{"loads": [{"segment": [list(p) for p in LOAD.segment],
                                        "force": list(LOAD.force)}],
                             "markers": "markers.csv"}],
            "fit": {"lame_lambda": [0.01, 2.0], "lame_mu": [0.01, 2.0]},
        })
        runs = []
        for _ in range(args.repeat):
            start = time.perf_counter()
            result = calibrate_material(folder / "calibration.yaml")
            runs.append((time.perf_counter() - start, result))
    wall, result = min(runs, key=lambda run: run[0])

    u = result.standard_uncertainty
    print(f"calibration speed: 100 x 100 mm, spacing {spacing:g} mm ({result.particles} particles), "
          f"1 experiment, {args.markers} markers, noise {args.noise} mm")
    print(f"  wall time            {wall:.2f} s (best of {args.repeat}: loading + fit; the fit alone "
          f"{result.wall_seconds:.2f} s)  target < 30 s")
    print(f"  forward solves       {result.forward_solves} (grid {result.grid_solves}, "
          f"least squares {result.forward_solves - result.grid_solves}); cold starts "
          f"{result.cold_starts}; Newton iterations {result.newton_iterations}")
    print(f"  lame_lambda          {result.lame_lambda:.6g} MPa (true {TRUE.lame_lambda}, "
          f"{100 * (result.lame_lambda / TRUE.lame_lambda - 1):+.2f} %, sigma {u[0]:.2g})")
    print(f"  lame_mu              {result.lame_mu:.6g} MPa (true {TRUE.lame_mu}, "
          f"{100 * (result.lame_mu / TRUE.lame_mu - 1):+.2f} %, sigma {u[1]:.2g})")
    print(f"  marker residual      {result.distances.mean():.4f} +- {result.distances.std():.4f} mm")


if __name__ == "__main__":
    main()
