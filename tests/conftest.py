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
