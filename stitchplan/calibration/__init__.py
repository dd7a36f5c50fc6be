"""Model parameters fitted to measurements: Lame moduli from markers, needle friction and
cutting force from force recordings."""

from .core import *  # noqa: F401,F403
