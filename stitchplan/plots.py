"""PNG figures: deformed tissue, needle paths, trajectories, calibration and studies."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .io import atomic_path


def _figure(width: float = 6.0, height: float = 6.0):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(figsize=(width, height))


def save(fig, path: str | Path) -> None:
    import matplotlib.pyplot as plt

    with atomic_path(path, suffix=".png") as temporary:
        fig.savefig(temporary, dpi=120, bbox_inches="tight", format="png")
    plt.close(fig)


def plot_deformed(path: str | Path, particles: np.ndarray, displacements: np.ndarray,
                  title: str = "", ax=None, fig=None) -> None:
    """Particles in the reference (grey) and deformed (coloured by |u|) configurations."""
    if ax is None:
        fig, ax = _figure()
    magnitude = np.linalg.norm(displacements, axis=1)
    deformed = particles + displacements
    ax.scatter(particles[:, 0], particles[:, 1], s=3, c="0.85", label="reference")
    points = ax.scatter(deformed[:, 0], deformed[:, 1], s=5, c=magnitude, cmap="viridis",
                        label="deformed")
    fig.colorbar(points, ax=ax, label="|u| (mm)", shrink=0.8)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(title)
    ax.legend(loc="upper right", fontsize=8)
    save(fig, path)
