"""Peak memory of the calibrations against the resource guard's estimate, with many markers
and long force recordings (resources/costs.py: MARKER_BYTES, MEMORY_PER_RECORDING_ROW;
tests/test_resource_guard.py: MEASURED_MARKER_PEAKS).

calibrate material: sample_runs/calibration/calibration.yaml with its first experiment's
markers replaced by N markers spread over the tissue, moved as the sample's material moves
them (stitchplan.calibration.simulate_markers at spacing 1.5 mm) plus 0.05 mm noise; its
second experiment's 20 markers kept. calibrate needle: a straight force recording in tissue
of N rows (the sample's friction and cutting force, 0.02 N noise) beside the sample's air
recording, with and without --plot. Each command runs in its own wrapper process, which
reports its child's peak resident memory (ru_maxrss); the estimate is the guard's own
(cli.options.guard_calibration, recording_rows' per-row cost).

Writes benchmarks/results/calibration_memory.{csv,md} and prints the table. About 3 minutes
(the million-marker fit takes most of it). Run from the repository root:
python benchmarks/calibration_memory.py  (--markers / --rows choose the sizes)
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import _common as common  # noqa: E402
import numpy as np  # noqa: E402

SAMPLE = common.REPO_ROOT / "sample_runs" / "calibration"
MARKERS = (10_000, 100_000, 300_000, 1_000_000)
ROWS = (10_000, 1_000_000)

# the child's peak resident memory, in a process of its own
PEAK = """
import resource, subprocess, sys
done = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
print(done.returncode, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024, done.stderr[-300:].replace(chr(10), ' '))
"""


def peak_bytes(arguments: list[str], cwd: Path) -> float:
    done = subprocess.run([sys.executable, "-c", PEAK, *arguments], capture_output=True, text=True, cwd=cwd,
                          env={**os.environ, "OPENBLAS_NUM_THREADS": "1"}, check=True)
    code, peak, tail = done.stdout.split(" ", 2)
    if code != "0":
        raise SystemExit(f"{' '.join(arguments)} failed: {tail}")
    return float(peak)


def marker_files(folder: Path, count: int) -> Path:
    """The sample calibration with `count` markers in its first experiment, in `folder`."""
    from stitchplan.calibration import load_material_calibration, simulate_markers
    from stitchplan.config import Material

    truth = Material("saint-venant-kirchhoff", lame_lambda=0.189151, lame_mu=0.147688)  # the sample's (its header)
    problem = load_material_calibration(SAMPLE / "calibration.yaml")
    first = problem.experiments[0]
    rng = np.random.default_rng(count)
    width, height = problem.tissue.bounding_size
    rest = np.unique(np.round(np.column_stack([rng.uniform(2.0, width - 5.0, count),
                                               rng.uniform(2.0, height - 2.0, count)]), 6), axis=0)
    moved = simulate_markers(replace(problem.tissue, material=truth), problem.discretization.replaced(spacing=1.5),
                             first.loads, rest, truth)
    moved += 0.05 * rng.standard_normal(moved.shape)
    np.savetxt(folder / f"markers{count}.csv", np.hstack([rest, moved]), fmt="%.6f", delimiter=",",
               header="x,y,x_def,y_def", comments="")
    text = (SAMPLE / "calibration.yaml").read_text()
    text = text.replace("markers1.csv", f"markers{count}.csv").replace("markers2.csv", str(SAMPLE / "markers2.csv"))
    path = folder / f"calibration{count}.yaml"
    path.write_text(text)
    return path


def material_estimate(path: Path) -> float:
    """The guard's estimate for the calibration at `path`: its models held at once and its markers."""
    from stitchplan.calibration import load_material_calibration
    from stitchplan.cli.options import guard_calibration
    from stitchplan.resources import guard
    from stitchplan.resources.costs import held_in_one_process
    from stitchplan.resources.limits import Limits

    seen = {}
    original = guard.check_resources
    guard.check_resources = lambda estimates, limits, **options: seen.update(options, estimates=list(estimates))
    try:
        guard_calibration(path, load_material_calibration(path), Limits())
    finally:
        guard.check_resources = original
    models = held_in_one_process([item.memory_bytes for item in [*seen["estimates"], *seen["beside"]]])
    return models + seen["data"].memory_bytes


def recording(folder: Path, rows: int) -> Path:
    rng = np.random.default_rng(rows)
    angle = np.linspace(0.0, 2.5, rows)
    force = 0.12 + 0.035 * angle + 0.7 + 0.0602 * 8.88 * angle + 0.02 * rng.standard_normal(rows)
    path = folder / f"tissue{rows}.csv"
    np.savetxt(path, np.column_stack([angle, force]), fmt="%.9f", delimiter=",", header="angle_rad,force_N",
               comments="")
    return path


def main() -> None:
    from stitchplan.resources.costs import BASE_MEMORY, MEMORY_PER_RECORDING_ROW, PLOT_MEMORY

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--markers", type=int, nargs="*", default=list(MARKERS))
    parser.add_argument("--rows", type=int, nargs="*", default=list(ROWS))
    options = parser.parse_args()
    stitchplan = str(Path(sys.executable).parent / "stitchplan")
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch)
        for count in options.markers:
            path = marker_files(folder, count)
            peak = peak_bytes([stitchplan, "calibrate", "material", str(path), "--out", str(folder / "fitted.yaml")],
                              folder)
            total = count + 20
            rows.append(["calibrate material", f"{total} markers", peak / 1e6, material_estimate(path) / 1e6])
            print(json.dumps(rows[-1]), flush=True)
        for count in options.rows:
            tissue = recording(folder, count)
            for plot in (False, True):
                arguments = [stitchplan, "calibrate", "needle", "--air", str(SAMPLE / "air.csv"), "--tissue",
                             str(tissue), "--radius", "8.88", "--out", str(folder / "needle.yaml"),
                             *(["--plot", str(folder / "forces.png")] if plot else [])]
                air_rows = len((SAMPLE / "air.csv").read_text().splitlines()) - 1
                estimate = BASE_MEMORY + (PLOT_MEMORY if plot else 0.0) + MEMORY_PER_RECORDING_ROW * (count + air_rows)
                rows.append([f"calibrate needle{' --plot' if plot else ''}", f"{count + air_rows} rows",
                             peak_bytes(arguments, folder) / 1e6, estimate / 1e6])
                print(json.dumps(rows[-1]), flush=True)
    header = ["command", "data", "peak (MB)", "guard's estimate (MB)", "estimate / peak"]
    table = [[command, data, f"{peak:.0f}", f"{estimate:.0f}", f"{estimate / peak:.2f}"]
             for command, data, peak, estimate in rows]
    lines = ["# Calibrations' peak memory against the resource guard", "",
             f"Generated by `python benchmarks/calibration_memory.py` ({common.machine_note()}). Peak: the "
             "command's ru_maxrss in a process of its own; estimate: the guard's (models held at once and "
             "markers for calibrate material, interpreter, figure and rows for calibrate needle). MB: 10^6 bytes."]
    common.write_results("calibration_memory", header, table, lines)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
