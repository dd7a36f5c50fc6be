"""What the needle's hold on the tissue at its entry does to the exit error's convergence.

benchmarks/exit_components.py shows the free edge at the needle's entry drawn into a cusp
along the needle that sharpens at every level on the soft scenes, so their exit error does not
settle. Here the same `simulate` runs (needle_coupling.scene, each file as shipped) are
repeated with the track released from the needle near the entry, as if the tissue there were
torn from it, to see which of the needle's terms draws the cusp and whether the exit error
converges without it. RELEASES:

- `held`: the model as shipped (the track held to the needle from the entry on);
- `constraint 1 mm`: the constraint's quadrature points within 1 mm of the entry (reference
  arc length along the track) dropped, the multipliers whose support lies wholly there with
  them; the friction as shipped;
- `constraint and friction 1 mm, ramp 2 mm`: besides, no friction within 1 mm and the friction
  rising linearly to its full value over the next 2 mm (a friction step at the release's end
  would be a line load's end again);
- `constraint and friction 2 mm, ramp 2 mm`: the same from 2 mm.

The release is patched into needle/coupling.py's NeedleCoupling for the runs (`released`): it
is a probe of the model, not an option of the package. Per scene and release: the exit error
at h, h/sqrt2, h/2 and h/4 (h the file's spacing), the change from h to h/2 and from h/2 to
h/4, and the free edge within 3 mm of the entry once the tip has left (least stretch, turn of
its tangent: exit_components.entry_edge).

Writes benchmarks/results/entry_release.{csv,md}. About 12 minutes.
Run from the repository root:  python benchmarks/entry_release.py
"""

from __future__ import annotations

import os

# single-threaded BLAS, as the `stitchplan` command sets it
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import contextlib  # noqa: E402
import math  # noqa: E402
from dataclasses import dataclass  # noqa: E402

import numpy as np  # noqa: E402

import _common as common  # noqa: E402
import exit_components  # noqa: E402
import needle_coupling  # noqa: E402
from stitchplan.config import with_discretization  # noqa: E402
from stitchplan.needle import coupling as coupling_module  # noqa: E402

SCENES = ("soft_t3", "soft_t2.5", needle_coupling.THESIS_FIT[3], "sh12_100x100", "sh12_100x100_mid", "sh12_100x40")
FACTORS = (1.0, 1.0 / math.sqrt(2.0), 0.5, 0.25)
LEVELS = ("h", "h/sqrt2", "h/2", "h/4")


@dataclass(frozen=True)
class Release:
    name: str
    constraint: float  # mm of track from the entry without the constraint
    friction: float | None  # mm without friction (None: friction as shipped)
    ramp: float = 0.0  # mm over which the friction rises to its full value after that

    def friction_share(self, arc: np.ndarray) -> np.ndarray:
        """The share of the shipped friction at reference arc lengths `arc` from the entry."""
        if self.friction is None:
            return np.ones_like(arc)
        if self.ramp > 0.0:
            return np.clip((arc - self.friction) / self.ramp, 0.0, 1.0)
        return (arc >= self.friction).astype(float)


RELEASES = (Release("held", 0.0, None),
            Release("constraint 1 mm", 1.0, None),
            Release("constraint and friction 1 mm, ramp 2 mm", 1.0, 1.0, 2.0),
            Release("constraint and friction 2 mm, ramp 2 mm", 2.0, 2.0, 2.0))
FIELDS = ("scene", "release", "factor", "spacing_mm", "particles", "exit_error_mm", "edge_least_stretch",
          "edge_turn_deg", "seconds", "failure")


def _gauss_arc(coupling) -> np.ndarray:
    """Reference arc length from the entry of each segment Gauss point, (Q,)."""
    lengths = coupling._segment_lengths()
    arc = np.concatenate([[0.0], np.cumsum(lengths)])
    return (arc[:-1, None] + coupling.gauss[None, :] * lengths[:, None]).ravel()


@contextlib.contextmanager
def released(release: Release):
    """NeedleCoupling with `release` for the runs inside: the mortar partition without the
    quadrature points within release.constraint of the entry (a multiplier left with none is
    dropped; the tip's is always kept), the friction on the segments' Gauss points scaled by
    release.friction_share (the cutting force's shares untouched)."""
    cls = coupling_module.NeedleCoupling
    partition, layout = cls._partition, cls._load_layout

    def _partition(self) -> np.ndarray:
        shares = partition(self)
        if release.constraint <= 0.0 or not self.multiplier_count:
            return shares
        assert self.kind == coupling_module.MORTAR and not self.arc_ends, "segment Gauss points only"
        kept = (_gauss_arc(self) >= release.constraint).astype(float)
        ds = np.repeat(self.gauss_weight * self._segment_lengths(), len(self.gauss))
        shares = shares * kept[:, None]
        weighted = shares * ds[:, None]
        columns = weighted.sum(axis=0) > 0.0
        columns[-1] = True  # the tip's multiplier: the tip stays on the needle
        if weighted[:, -1].sum() == 0.0:  # a track shorter than the release: the tip point alone
            shares[-1, -1] = weighted[-1, -1] = 1.0
        shares, weighted = shares[:, columns], weighted[:, columns]
        self.weights = weighted / weighted.sum(axis=0)
        self.multiplier_count = shares.shape[1]
        self.multiplier_nodes = self.multiplier_nodes[columns]
        return shares

    def _load_layout(self):
        magnitudes, points, lumping = layout(self)
        segments = len(self.points) - 1
        if release.friction is None or segments < 1:
            return magnitudes, points, lumping
        friction = np.repeat(self.gauss_weight * self.needle.friction * self.geometry.insertion_step
                             * self.segment_fraction, len(self.gauss))
        magnitudes = magnitudes.copy()
        magnitudes[:len(friction)] -= friction * (1.0 - release.friction_share(_gauss_arc(self)))
        return magnitudes, points, lumping

    cls._partition, cls._load_layout = _partition, _load_layout
    try:
        yield
    finally:
        cls._partition, cls._load_layout = partition, layout


def run(scene: str, release: Release, factor: float) -> dict:
    base = needle_coupling.scene(scene, needle_coupling.SHIPPED_COUPLING)
    spacing = base.discretization.spacing * factor
    row = {"scene": scene, "release": release.name, "factor": f"{factor:.4f}", "spacing_mm": f"{spacing:.4f}",
           **exit_components.edge_run(with_discretization(base, spacing=spacing), released(release))}
    print(row, flush=True)
    return row


def table(rows: list[dict]) -> tuple[list[str], list[list]]:
    header = ["scene", "release", *(f"exit error at {level} (mm)" for level in LEVELS),
              "h -> h/2", "h/2 -> h/4", "edge turn (deg) at h .. h/4", "edge least stretch at h .. h/4"]
    body = []
    for scene in SCENES:
        for release in RELEASES:
            levels = [next((r for r in rows if r["scene"] == scene and r["release"] == release.name
                            and r["factor"] == f"{f:.4f}"), None) for f in FACTORS]
            errors = [float(r["exit_error_mm"]) if r and r["exit_error_mm"] else None for r in levels]

            def change(a, b):
                return "—" if a is None or b is None else f"{100.0 * (b - a) / a:+.2f} %"

            def series(key):
                return " / ".join(r[key] if r and r[key] else "—" for r in levels)

            shown = [f"{e:.4f}" if e is not None else (f"stops: {r['failure'][:60]}" if r else "—")
                     for e, r in zip(errors, levels)]
            body.append([scene, release.name, *shown, change(errors[0], errors[2]), change(errors[2], errors[3]),
                         series("edge_turn_deg"), series("edge_least_stretch")])
    return header, body


def main() -> None:
    rows = [run(scene, release, factor) for scene in SCENES for release in RELEASES for factor in FACTORS]
    common.write_csv(common.results_path("entry_release.csv"), FIELDS, [[row[key] for key in FIELDS] for row in rows])
    header, body = table(rows)
    lines = ["# The needle's hold on the tissue at its entry",
             f"Generated by `python benchmarks/entry_release.py` ({common.machine_note()}). `simulate` on each "
             "scene's file as shipped (soft_t3, soft_t2.5: configs/sh12_100x100.yaml as neo-Hookean slabs 3 and "
             "2.5 mm thick) at h, h/sqrt2, h/2, h/4 (h the file's spacing), with the track held to the needle "
             "from the entry on (`held`, the model) or released near the entry (the constraint's quadrature "
             "points within 1 or 2 mm of it dropped; the friction there removed and ramped in over 2 mm, or "
             "kept). Edge: the free edge within 3 mm of the entry once the tip has left, how far its tangent "
             "turns (0: straight, 180: folded back) and its least stretch (exit_components.entry_edge)."]
    common.write_report("entry_release.md", [*lines, "", common.markdown_table(header, body)])


if __name__ == "__main__":
    common.command_line(__doc__)
    main()
