"""Speed against accuracy, and models no bigger than the scene needs.

- runner: one configured insertion, run and timed, a failure recorded with its reason;
  exit-point deviations between two runs;
- auto: the auto discretization (`discretization: {accuracy: ...}`), chosen by runs;
- sweep: `stitchplan study`, families of discretization and method choices swept over
  spacings and compared with the finest run.

Imports go one way: sweep -> auto -> runner. The study's files are written by
stitchplan.io.study_reports.
"""
