"""Command-line interface (typer): `stitchplan` and `python -m stitchplan`.

Start-up is instant: numpy, scipy, h5py, matplotlib and rich are imported inside the
commands that use them, never for `--help` or `--version`.
"""

from . import calibrate, commands  # noqa: F401  (register the commands on the app)
from .app import EXIT_CODES, app, exit_code, main, usage_message  # noqa: F401
from .options import LinearSolver, TipTracking  # noqa: F401
