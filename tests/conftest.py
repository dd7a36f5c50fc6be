"""Shared fixtures: the shipped scenario, scratch scenario files and small slab geometry.

Tests never write into the source tree: every file a test creates lives in `tmp_path`.
"""

from __future__ import annotations

import copy
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import yaml

REPOSITORY = Path(__file__).resolve().parents[1]
CONFIGS = REPOSITORY / "configs"
SLAB_EDGE_LOAD = CONFIGS / "slab_edge_load.yaml"
# a needle step's Newton to 5e-6 of the needle force and 1e-9 R (the mortar coupling's
# defaults are 1e-3 and 1e-7, whose solves leave up to 1.4e-4 mm in an exit point): for tests
# that reach the same equilibria two ways (warm and cold starts, MINRES and direct, a pass
# alone or in sequence) and compare them to ~1e-7 mm
TIGHT_NEEDLE_NEWTON = {"needle_residual_tolerance": 5e-6, "needle_constraint_tolerance": 1e-9}


@pytest.fixture
def rng() -> np.random.Generator:
    """A seeded generator: every random test point is reproducible."""
    return np.random.default_rng(20240611)


@pytest.fixture
def slab_raw() -> dict:
    """The shipped slab_edge_load scenario as a fresh, mutable dict."""
    return copy.deepcopy(yaml.safe_load(SLAB_EDGE_LOAD.read_text()))


@pytest.fixture
def slab_path(tmp_path: Path) -> Path:
    """A copy of configs/slab_edge_load.yaml in tmp_path."""
    target = tmp_path / "slab_edge_load.yaml"
    shutil.copyfile(SLAB_EDGE_LOAD, target)
    return target


@pytest.fixture
def write_scenario(tmp_path: Path) -> Callable[[dict, str], Path]:
    """write_scenario(raw, name) dumps a scenario dict as YAML into tmp_path."""

    def write(raw: dict, name: str = "scenario.yaml") -> Path:
        path = tmp_path / name
        path.write_text(yaml.safe_dump(raw, sort_keys=False))
        return path

    return write


@pytest.fixture
def rectangle_edges() -> Callable[[float, float], tuple]:
    """rectangle_edges(W, H): the four edges of [0, W] x [0, H] as boundary segments."""

    def edges(width: float, height: float) -> tuple:
        corners = [(0.0, 0.0), (width, 0.0), (width, height), (0.0, height)]
        return tuple((corners[k], corners[(k + 1) % 4]) for k in range(4))

    return edges
