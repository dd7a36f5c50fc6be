"""Command-line interface (typer): `stitchplan` and `python -m stitchplan`.

Start-up is instant: `stitchplan --version` imports nothing but the version, the app
(typer and the commands) loads on first use, and numpy, scipy, h5py, matplotlib and rich
are imported inside the commands that use them, never for `--help` or `--version`.
"""

from __future__ import annotations

import sys

# what `from stitchplan.cli import ...` finds, and the module that defines it
_LAZY = {"app": "group", "EXIT_CODES": "group", "exit_code": "group", "usage_message": "group",
         "LinearSolver": "options", "TipTracking": "options"}


def main() -> None:
    """Console entry point of `stitchplan` and `python -m stitchplan`."""
    if sys.argv[1:] == ["--version"]:  # answered before typer is imported
        from .. import __version__

        print(f"stitchplan {__version__}")
        return
    __getattr__("app")()


def __getattr__(name: str):
    """The app and its helpers, loaded with the commands registered on first use."""
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from importlib import import_module

    import_module(".calibrate", __name__)  # registers the commands on the app
    import_module(".commands", __name__)
    for attribute, module in _LAZY.items():
        globals()[attribute] = getattr(import_module(f".{module}", __name__), attribute)
    return globals()[name]
