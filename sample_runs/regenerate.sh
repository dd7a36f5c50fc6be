#!/usr/bin/env bash
# Regenerate the shipped sample outputs from the scenarios in configs/.
# Usage (from the repository root, project installed): bash sample_runs/regenerate.sh
set -euo pipefail
cd "$(dirname "$0")/.."
out=sample_runs

stitchplan deform configs/slab_edge_load.yaml --probes-out $out/slab_edge_load/probes.csv \
  --reactions-out $out/slab_edge_load/reactions.csv --summary $out/slab_edge_load/summary.json \
  --out $out/slab_edge_load/run.h5 --plot $out/slab_edge_load/deformed.png

# tissue shapes: a layered skin patch, a hole next to the stitch, a stitch across a wound
for scene in skin_layered hole_near_stitch wound_closure; do
  stitchplan deform configs/$scene.yaml --probes-out $out/$scene/probes.csv \
    --summary $out/$scene/deform_summary.json --plot $out/$scene/deformed.png
  stitchplan simulate configs/$scene.yaml --summary $out/$scene/simulate_summary.json \
    --plot $out/$scene/simulate.png
done

for scene in sh12_100x100 sh12_100x100_mid sh12_100x50 sh12_100x40 sh12_100x30 skin_layered hole_near_stitch wound_closure \
    wound_closure_symmetric; do
  [ -f configs/$scene.yaml ] || continue
  stitchplan plan configs/$scene.yaml --export $out/$scene/trajectory.csv \
    --summary $out/$scene/plan_summary.json --plot $out/$scene/plan.png --angular-speed 0.5
done

stitchplan simulate configs/sh12_100x100.yaml --summary $out/sh12_100x100/simulate_summary.json \
  --out $out/sh12_100x100/simulate.h5 --plot $out/sh12_100x100/simulate.png --plot-steps 10,25,37

python sample_runs/plan_table.py > $out/plan_table.md

# calibration example: refit the shipped synthetic data (python sample_runs/calibration/generate.py
# remakes the data itself, seeded)
(cd $out/calibration
 stitchplan calibrate material calibration.yaml --out fitted.yaml --plot-dir plots
 stitchplan calibrate material displacement_only.yaml --out fitted_displacement_only.yaml \
   --plot-dir plots_displacement_only
 stitchplan calibrate material skin_layered.yaml --out fitted_skin_layered.yaml --plot-dir plots_skin_layered
 stitchplan calibrate material inclusion.yaml --out fitted_inclusion.yaml --plot-dir plots_inclusion
 stitchplan calibrate needle --air air.csv --tissue tissue.csv --radius 8.88 --out needle.yaml \
   --plot forces.png)

# planning under uncertainty on sh12_100x100 with the sample calibration's uncertainties
# (configs/uncertainty/uncertainty_sample.yaml reads calibration/fitted.yaml); under a minute on 2 cores
stitchplan plan configs/sh12_100x100.yaml --uncertainty configs/uncertainty/uncertainty_sample.yaml \
  --export $out/sh12_100x100/uncertainty/trajectory.csv --summary $out/sh12_100x100/uncertainty/summary.json \
  --uncertainty-plot $out/sh12_100x100/uncertainty/uncertainty.png

# the same on the layered skin patch, its subcutaneous moduli from the calibration around its
# skin layer (configs/uncertainty/uncertainty_skin_layered.yaml reads calibration/fitted_skin_layered.yaml)
stitchplan plan configs/skin_layered.yaml --uncertainty configs/uncertainty/uncertainty_skin_layered.yaml \
  --export $out/skin_layered/uncertainty/trajectory.csv --summary $out/skin_layered/uncertainty/summary.json \
  --uncertainty-plot $out/skin_layered/uncertainty/uncertainty.png
