"""Planning under parameter uncertainty (`stitchplan plan --uncertainty`).

- sampling: the seeded low-discrepancy design of parameter sets (training and held-out),
  truncated to positive values, and the scenarios they make;
- evaluation: one sampled run (a centre path replayed on a sampled scenario), a Dask task;
- robust: the nominal and robust plans, exit statistics on held-out samples, sensitivities,
  and the exported plan checked as `plan` checks its own.

Imports go one way: robust -> evaluation, sampling. Below: planning, needle, config and
stitchplan.parallel (the executor the sampled runs go to); the files are written by
stitchplan.io.uncertainty_reports.
"""
