"""stitchplan: curved suture needle insertion simulation and trajectory planning."""

# the one place the version is written: pyproject.toml reads it ([tool.setuptools.dynamic]),
# run logs record it, `stitchplan --version` prints it
__version__ = "0.2.0"
