"""Whether the needle's track as a cut makes the 2.5 mm soft slab's exit error converge.

In the plane model the needle is a blade through the slab's thickness: the tissue it passes
is parted, and each side slides along it on its own. The package holds the track's material,
one line of it, on the needle, the tissue continuous across it; on soft slabs the free edge
at the entry is then drawn into a fold along the needle that sharpens at every refinement
(needle_width.md, entry_newton.md). Here the track near the entry is a cut instead, patched
in for the runs (a probe of the model, not an option of the package):

- CutVisibility: no shape function reaches across the cut (a polyline, the first CUT_SPAN mm
  of the track from the entry), the visibility criterion of the package's shape functions
  (stitchplan.tissue.shape_functions.Visibility) applied to it;
- FaceRows: where the coupling evaluates the tissue at a track point on the cut, the mean of
  the two faces (FACE_OFFSET mm to either side of the cut's nearest point): the needle's
  constraint holds that mean on its circle and its loads act half on each face;
- FaceTie: a penalty (a run's own, x mu t per station spacing / particle spacing) on the
  faces' jump at stations along the cut (a run's own number per particle spacing): the whole jump ahead of the tip (the tissue not yet
  parted), its normal part behind it (both faces on the blade, sliding along it apart), the
  tangential part of the stations the tip passes in a step released with the step's load
  (Algorithm 1's ramp).

The cut must lie on the track the run makes, which depends on the cut: a fixed point. The
first cut is the line needle's track; each next one the run's own track (its first CUT_SPAN mm),
averaged with the cut it ran on (RELAXATION), until the track lies within TRACK_TOLERANCE
particle spacings of its cut or after ROUNDS runs. Before such a cut's convergence under
refinement means anything its answer must not depend on the tie: soft_t2.5 (needle_coupling's:
configs/sh12_100x100.yaml as a neo-Hookean slab 2.5 mm thick) at h with the penalties 1e2 to
1e7 at STATIONS_PER_SPACING stations, and with 1 station at 1e4; sh12_100x100 at h with 1e2,
1e4, 1e6.

Writes benchmarks/results/track_cut.{csv,md,png}: every round of every run. About 2 minutes on
two cores; `--report` redraws the table and chart from the CSV.
Run from the repository root:  python benchmarks/track_cut.py
"""

from __future__ import annotations

import os

# single-threaded BLAS, as the `stitchplan` command sets it
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import contextlib  # noqa: E402
import dataclasses  # noqa: E402
import math  # noqa: E402
import re  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from unittest import mock  # noqa: E402

import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402

import _common as common  # noqa: E402
import entry_newton  # noqa: E402
import needle_coupling  # noqa: E402
import needle_width  # noqa: E402
import stitchplan.needle.equilibrium as equilibrium  # noqa: E402
import stitchplan.tissue.model as tissue_model  # noqa: E402
from stitchplan.config import with_discretization  # noqa: E402
from stitchplan.errors import InsertionFailure  # noqa: E402
from stitchplan.needle.coupling import NeedleCoupling  # noqa: E402
from stitchplan.needle.equilibrium import NeedleInsertion  # noqa: E402
from stitchplan.needle.insertion import run_insertion  # noqa: E402

CUT_SPAN = 8.0  # mm of the track from the entry that is cut (the fold is at the entry)
FACE_OFFSET = 1e-3  # mm off the cut where a face is evaluated
ON_CUT = 0.25  # a track point within this many particle spacings of the cut is on it
STATIONS_PER_SPACING = 4  # FaceTie's stations per local particle spacing along the cut (a run's own)
RELAXATION = 0.5  # the next cut: this share of the run's track, the rest the cut it ran on
CUT_SAMPLES = 65  # stations the cuts are averaged at, over [0, CUT_SPAN]
TRACK_TOLERANCE = 0.02  # particle spacings: the track on its cut
ROUNDS = 6
PENALTIES = (1e2, 1e3, 1e4, 1e5, 1e6, 1e7)
# (scene, level, spacing factor, FaceTie's penalty, its stations per particle spacing)
RUNS = ([("soft_t2.5", "h", 1.0, penalty, STATIONS_PER_SPACING) for penalty in PENALTIES]
        + [("sh12_100x100", "h", 1.0, penalty, STATIONS_PER_SPACING) for penalty in PENALTIES[::2]]
        + [("soft_t2.5", "h", 1.0, 1e4, 1)])
COLUMNS = ["scene", "level", "factor", "needle_spacing_mm", "penalty", "stations", "round", "exit_error_mm", "failure",
           "track_off_cut_mm", "edge_least_stretch", "edge_turn_deg", "flank_gap_mm", "seconds"]


def orientation(p: np.ndarray, q: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Twice the signed area of (p, q, r), row by row."""
    return (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0])


class CutVisibility:
    """Visibility (the package's keep(points, particles, rows, cols) interface) across a
    polyline: a point and a particle whose segment crosses it do not interact."""

    def __init__(self, cut: np.ndarray):
        self.cut = np.asarray(cut, dtype=float)
        self.starts, self.ends = self.cut[:-1], self.cut[1:]
        self.low, self.high = self.cut.min(axis=0), self.cut.max(axis=0)
        self.arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(self.ends - self.starts, axis=1))])

    def keep(self, points, particles, rows, cols) -> np.ndarray:
        p, q = points[rows], particles[cols]
        keep = np.ones(len(rows), dtype=bool)
        near = np.flatnonzero(np.all(np.maximum(p, q) >= self.low, axis=1) & np.all(np.minimum(p, q) <= self.high, axis=1))
        crossed = np.zeros(len(near), dtype=bool)
        p, q = p[near], q[near]
        for a, b in zip(self.starts, self.ends):  # a few dozen pieces, each against every pair near the cut
            crossed |= ((orientation(p, q, a) * orientation(p, q, b) < 0)
                        & (orientation(a, b, p) * orientation(a, b, q) < 0))
        keep[near] = ~crossed
        return keep

    def nearest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per point: the cut's nearest point, its arc length from the entry, the cut's unit
        normal there and the distance to it."""
        points = np.atleast_2d(points)
        pieces = self.ends - self.starts
        lengths = np.linalg.norm(pieces, axis=1)
        along = np.clip(np.einsum("pkj,kj->pk", points[:, None, :] - self.starts[None], pieces) / lengths ** 2, 0, 1)
        feet = self.starts[None] + along[..., None] * pieces[None]
        distance = np.linalg.norm(points[:, None] - feet, axis=2)
        piece = np.argmin(distance, axis=1)
        index = np.arange(len(points))
        tangent = pieces[piece] / lengths[piece, None]
        return (feet[index, piece], self.arc[piece] + along[index, piece] * lengths[piece],
                np.column_stack([-tangent[:, 1], tangent[:, 0]]), distance[index, piece])


class FaceRows(needle_width.OffsetRows):
    """The tissue model as the coupling sees it: at a track point on the cut (within ON_CUT
    particle spacings of it), the mean of its two faces' rows at the cut's nearest point."""

    offsets, weights = np.array([-FACE_OFFSET, FACE_OFFSET]), np.array([0.5, 0.5])

    def __init__(self, model, cut: CutVisibility):
        super().__init__(model)
        self._cut = cut

    def frame(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        foot, _, normal, distance = self._cut.nearest(points)
        on = distance < ON_CUT * (self._model.needle_spacing or self._model.spacing)
        return np.where(on[:, None], foot, points), normal


class FaceTie:
    """The penalty on the faces' jump [u] = u(+) - u(-) at stations along the cut, energy
    k/2 ((n.[u])^2 + c (t.[u])^2): c = 1 ahead of the tip, 0 behind it, 1 - beta (the step's
    load factor) at the stations the tip passed in the step. Its stiffness k J^T (n n^T +
    c t t^T) J joins K + H."""

    def __init__(self, insertion, cut: CutVisibility, penalty: float, stations: int):
        model = insertion.model
        spacing = model.needle_spacing or model.spacing
        step = spacing / stations
        along = np.arange(0.5 * step, cut.arc[-1], step)
        stations = np.column_stack([np.interp(along, cut.arc, cut.cut[:, 0]), np.interp(along, cut.arc, cut.cut[:, 1])])
        normal = cut.nearest(stations)[2]
        inside = (insertion.domain.contains(stations + FACE_OFFSET * normal)
                  & insertion.domain.contains(stations - FACE_OFFSET * normal))
        self.along, self.normal, stations = along[inside], normal[inside], stations[inside]
        self.jump = (model.free_rows_at(stations + FACE_OFFSET * self.normal)
                     - model.free_rows_at(stations - FACE_OFFSET * self.normal)).tocsr()
        material = insertion.scenario.tissue.material
        self.penalty = penalty * material.lame_mu * insertion.scenario.tissue.thickness * step / spacing
        self.insertion, self.cut = insertion, cut
        self.tip_before = self.tip = 0.0  # the tip's arc length on the cut at the step's start, and now
        self.track_points = -1

    def follow_tip(self) -> None:
        """At a step's start: where the tip has got to on the cut."""
        points = self.insertion.points
        if len(points) != self.track_points:
            self.track_points, self.tip_before = len(points), self.tip
            if len(points):
                self.tip = float(self.cut.nearest(points[-1])[1][0])

    def terms(self, free: np.ndarray) -> tuple[np.ndarray, sp.csr_matrix]:
        jump = self.jump @ free.reshape(-1, 2)
        normal = self.normal
        tangent = np.column_stack([-normal[:, 1], normal[:, 0]])
        passed = (self.along > self.tip_before) & (self.along <= self.tip)
        sliding = np.where(self.along <= self.tip_before, 0.0,
                           np.where(passed, 1.0 - self.insertion.coupling.load_factor, 1.0))
        normal_jump, tangent_jump = np.einsum("ij,ij->i", jump, normal), np.einsum("ij,ij->i", jump, tangent)
        force = self.penalty * (normal_jump[:, None] * normal + (sliding * tangent_jump)[:, None] * tangent)
        blocks = self.penalty * (normal[:, :, None] * normal[:, None, :]
                                 + sliding[:, None, None] * tangent[:, :, None] * tangent[:, None, :])
        return (self.jump.T @ force).ravel(), entry_newton.point_blocks_on_dofs(self.jump, blocks)


@contextlib.contextmanager
def track_cut(cut: CutVisibility, penalty: float, stations: int):
    """The tissue model built with the cut's visibility, the coupling on FaceRows and FaceTie's
    terms in the insertion, while inside."""
    shape_functions, build = tissue_model.rk_shape_functions, tissue_model.build_tissue_model
    couple = NeedleCoupling.__init__
    residuals, stiffness, equilibrate = NeedleInsertion.residuals, NeedleInsertion._stiffness, \
        NeedleInsertion.equilibrate

    def seeing_across(points, particles, *arguments):  # the visibility argument, None on a rectangle
        arguments = list(arguments)
        arguments[6] = cut if arguments[6] is None else arguments[6]
        return shape_functions(points, particles, *arguments)

    def built(*arguments, **keywords):
        model = build(*arguments, **keywords)
        model.visibility = cut  # the rows asked for later (the coupling's, tip tracking's)
        return model

    def faced(coupling, model, geometry, needle, dilation=2.0):
        couple(coupling, model, geometry, needle, dilation)
        coupling.model = FaceRows(model, cut)

    def tie(insertion) -> FaceTie:
        if "face_tie" not in insertion.__dict__:
            insertion.face_tie = FaceTie(insertion, cut, penalty, stations)
        return insertion.face_tie

    def with_tie(insertion, free, multipliers, center):
        state = residuals(insertion, free, multipliers, center)
        force, insertion.tie_stiffness = tie(insertion).terms(free)
        return dataclasses.replace(state, residual=state.residual + force)

    def stiffness_with_tie(insertion, multipliers, state):
        tangent = stiffness(insertion, multipliers, state)
        return lambda: (tangent() + insertion.tie_stiffness).tocsr()

    def equilibrate_at(insertion, *arguments, **keywords):
        tie(insertion).follow_tip()
        return equilibrate(insertion, *arguments, **keywords)

    with mock.patch.object(tissue_model, "rk_shape_functions", seeing_across), \
            mock.patch.object(equilibrium, "build_tissue_model", built), \
            mock.patch.object(NeedleCoupling, "__init__", faced), \
            mock.patch.multiple(NeedleInsertion, residuals=with_tie, _stiffness=stiffness_with_tie,
                                equilibrate=equilibrate_at):
        yield


def first_span(track: np.ndarray) -> np.ndarray:
    """The track's first CUT_SPAN mm as CUT_SAMPLES points evenly along it."""
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(track, axis=0), axis=1))])
    along = np.linspace(0.0, min(CUT_SPAN, arc[-1]), CUT_SAMPLES)
    return np.column_stack([np.interp(along, arc, track[:, 0]), np.interp(along, arc, track[:, 1])])


def insertion_run(scenario, context=contextlib.nullcontext()) -> tuple[str, str, object]:
    """One unplanned insertion inside `context`: its exit error or failure (CSV strings) and
    the NeedleInsertion as it ended."""
    kept = {}
    with context, needle_width.kept_insertion(kept):
        try:
            outcome = f"{run_insertion(scenario).exit_error_mm:.6f}", ""
        except InsertionFailure as failure:
            outcome = "", " ".join(str(failure).split())
    return *outcome, kept["insertion"]


def run(scene: str, level: str, factor: float, penalty: float, stations: int) -> list[dict]:
    """The fixed point of the cut on one scene and level: a row per round."""
    base = needle_coupling.scene(scene, needle_coupling.SHIPPED_COUPLING)
    scenario = with_discretization(base, spacing=base.discretization.spacing * factor)
    spacing = scenario.discretization.needle_spacing or scenario.discretization.spacing
    cut = first_span(insertion_run(scenario)[2].points)  # the line needle's track
    rows = []
    for round_ in range(1, ROUNDS + 1):
        start = time.perf_counter()
        visibility = CutVisibility(cut)
        exit_error, failure, insertion = insertion_run(scenario, track_cut(visibility, penalty, stations))
        _, along, _, distance = visibility.nearest(insertion.points)
        off = float(distance[along < CUT_SPAN - spacing].max(initial=0.0))
        stretch, turn, gap = entry_newton.entry_flanks(insertion)
        rows.append({"scene": scene, "level": level, "factor": f"{factor:g}", "needle_spacing_mm": f"{spacing:.4g}",
                     "penalty": f"{penalty:g}", "stations": stations, "round": round_, "exit_error_mm": exit_error, "failure": failure,
                     "track_off_cut_mm": f"{off:.4f}", "edge_least_stretch": f"{stretch:.4f}",
                     "edge_turn_deg": f"{turn:.1f}", "flank_gap_mm": f"{gap:.4f}",
                     "seconds": f"{time.perf_counter() - start:.1f}"})
        print(rows[-1], flush=True)
        if off <= TRACK_TOLERANCE * spacing or len(insertion.points) < 2:
            break
        cut = RELAXATION * first_span(insertion.points) + (1.0 - RELAXATION) * cut
    return rows


def runs(rows: list[dict]) -> dict[tuple[str, str, str], list[dict]]:
    """Rows per (scene, penalty, stations), rounds in order."""
    groups: dict[tuple[str, str, str], list[dict]] = {}
    for row in rows:
        groups.setdefault((row["scene"], row["penalty"], row["stations"]), []).append(row)
    return groups


def settled(group: list[dict]) -> tuple[float, float]:
    """A run's exit error: the mean of its last two rounds (the last alone if one), and half
    their difference (how far the fixed point still swings); NaN where its last round stopped."""
    if not group[-1]["exit_error_mm"]:
        return math.nan, math.nan
    values = [float(row["exit_error_mm"]) for row in group if row["exit_error_mm"]][-2:]
    return float(np.mean(values)), 0.5 * abs(values[-1] - values[0])


def line_needle(scene: str) -> str:
    """The package's line needle on `scene` at h (needle_width.csv)."""
    found = [row["exit_error_mm"] for row in common.csv_rows(common.results_path("needle_width.csv"))
             if row["scene"] == scene and row["width_mm"] == "0" and row["level"] == "h"]
    return found[0] if found else "—"


def reading(rows: list[dict]) -> str:
    """What the runs say, from their numbers."""
    groups = runs(rows)
    text = []
    for scene in ("soft_t2.5", "sh12_100x100"):
        sweep = [(float(penalty), settled(group)[0]) for (own, penalty, stations), group in groups.items()
                 if own == scene and stations == str(STATIONS_PER_SPACING)]
        done = [(penalty, value) for penalty, value in sorted(sweep) if math.isfinite(value)]
        if len(done) < 2:
            continue
        values = ", ".join(f"{value:.3f}" for _, value in done)
        change = 100 * (done[-1][1] / done[-2][1] - 1)
        text.append(f"{scene}: {values} mm for the penalties {', '.join(f'{penalty:g}' for penalty, _ in done)} "
                    f"(the line needle {line_needle(scene)} mm), the last {done[-1][0] / done[-2][0]:g} times stiffer "
                    f"penalty still moving it {change:+.1f} %")
    coarse = [group for (own, penalty, stations), group in groups.items() if stations == "1"]
    sentence = "Reading: the exit error follows the faces' tie: " + "; ".join(text) + "."
    if coarse and not coarse[0][-1]["exit_error_mm"]:
        sentence += (" With one station per particle spacing the runs stop (" + short_failure(coarse[0][-1]) + ").")
    sentence += (" Likely locking (not measured further): a penalty at stations denser than the particles forces the "
                 "jump to zero at more points than the faces' coefficients can follow, stiffening the tissue near the cut "
                 "as it grows, while fewer stations let the faces part between them. The cut cannot be judged on this "
                 "tie: it needs one of its own, multipliers on the cut no finer than the particles (as the needle's mortar "
                 "coupling has), before its convergence under refinement means anything.")
    return sentence


def short_failure(row: dict) -> str:
    """Where a run stopped: its step and load, and the inverted material where the message says."""
    text = row["failure"]
    inverted = re.search(r"det F = \S+ at \([^)]+\) mm", text)
    return text.split(", the next")[0] + (f", {inverted.group(0)}" if inverted else "")


def report(rows: list[dict]) -> str:
    summary = []
    for (scene, penalty, stations), group in runs(rows).items():
        value, swing = settled(group)
        last = group[-1]
        summary.append([scene, penalty, stations, len(group),
                        f"{value:.4f} ± {swing:.4f}" if math.isfinite(value) else "stops: " + short_failure(last),
                        line_needle(scene), last["track_off_cut_mm"], last["edge_turn_deg"], last["flank_gap_mm"]])
    text = ["# The needle's track as a cut", "",
            f"Generated by `python benchmarks/track_cut.py` ({common.machine_note()}). The first {CUT_SPAN:g} mm of the "
            "track from the entry cut (no shape function across it), the needle's constraint and loads on the mean of "
            "its two faces, the faces glued ahead of the tip and held together across the blade behind it by a penalty "
            "(the table's, x mu t per station spacing / particle spacing, at the table's stations per particle spacing); "
            f"the cut made to lie on the run's own track by a fixed point (each next cut {RELAXATION:g} of the run's "
            f"track and the rest the cut it ran on, until the track is within {TRACK_TOLERANCE:g} particle spacings of "
            f"its cut or after {ROUNDS} rounds). Patched in for the runs, not an option of the package. soft_t2.5: "
            "configs/sh12_100x100.yaml as a neo-Hookean slab 2.5 mm thick; every run at the file's spacings (h, "
            "0.888 mm at the needle).", "",
            "Per run, the exit error of its last two rounds (their mean ± half their difference), beside the package's "
            "line needle (needle_width.csv), and in the last round the track's distance from its cut, the entry's "
            "edge's turn and the least distance between its two sides:", "",
            common.markdown_table(["scene", "penalty", "stations", "rounds", "exit error (mm)", "line needle (mm)",
                                   "track off its cut (mm)", "entry edge turn (deg)", "its sides apart (mm)"], summary),
            "", reading(rows), "",
            "Every round:", "",
            common.markdown_table(["scene", "penalty", "stations", "round", "exit error (mm)", "track off its cut (mm)",
                                   "entry edge: least stretch", "turn (deg)", "sides apart (mm)", "seconds"],
                                  [[row["scene"], row["penalty"], row["stations"], row["round"],
                                    row["exit_error_mm"] or "stops: " + row["failure"].replace("|", "‖"),
                                    row["track_off_cut_mm"], row["edge_least_stretch"], row["edge_turn_deg"],
                                    row["flank_gap_mm"], row["seconds"]] for row in rows]), ""]
    return "\n".join(text) + "\n"


def chart(rows: list[dict], path) -> None:
    """Exit error against the faces' penalty per scene, the line needle's beside it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = ("soft_t2.5", "sh12_100x100")
    figure, axes = plt.subplots(1, len(scenes), figsize=(12, 4.8))
    for axis, scene in zip(axes, scenes):
        sweep = sorted((float(penalty), settled(group)) for (own, penalty, stations), group in runs(rows).items()
                       if own == scene and stations == str(STATIONS_PER_SPACING))
        done = [(penalty, value, swing) for penalty, (value, swing) in sweep if math.isfinite(value)]
        axis.errorbar([penalty for penalty, _, _ in done], [value for _, value, _ in done],
                      yerr=[swing for _, _, swing in done], fmt="o-", capsize=3,
                      label=f"track cut, {STATIONS_PER_SPACING} stations per spacing (last two rounds)")
        line = line_needle(scene)
        if line != "—":
            axis.axhline(float(line), color="0.4", ls="--", label="line needle (the package)")
        axis.set_xscale("log")
        axis.set_xlabel("penalty on the faces' jump (x mu t per station spacing / particle spacing)")
        axis.set_ylabel("unplanned exit error at h (mm)")
        axis.set_title(scene, fontsize=10)
        axis.legend(fontsize=8)
    figure.suptitle("The needle's track near the entry as a cut: the exit error follows the faces' tie")
    common.save_figure(figure, path, (0, 0, 1, 0.93))
    plt.close(figure)


def main() -> None:
    path = common.results_path("track_cut.csv")
    if "--report" not in sys.argv[1:]:
        order = RUNS
        with ProcessPoolExecutor(max_workers=2) as pool:
            finished = dict(zip(order, pool.map(run, *zip(*order))))
        common.write_csv(path, COLUMNS, [[row[column] for column in COLUMNS] for run_ in RUNS
                                         for row in finished[run_]])
    rows = common.csv_rows(path)
    common.publish("track_cut", report(rows), chart, rows)


if __name__ == "__main__":
    main()
