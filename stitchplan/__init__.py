"""stitchplan: curved suture needle insertion simulation and trajectory planning."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("stitchplan")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.1.0"
