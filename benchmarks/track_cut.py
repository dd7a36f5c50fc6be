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
  faces' jump at stations along the cut (a run's own number per particle spacing), at every
  station or on its mean over elements of a run's number of stations: the whole jump ahead
  of the tip (the tissue not yet parted), its normal part behind it (both faces on the blade,
  sliding along it apart), the tangential part of the stations the tip passes in a step
  released with the step's load (Algorithm 1's ramp).

The cut must lie on the track the run makes, which depends on the cut: a fixed point. The
first cut is the line needle's track; each next one the run's own track (its first CUT_SPAN mm),
averaged with the cut it ran on (RELAXATION), until the track lies within TRACK_TOLERANCE
particle spacings of its cut or after ROUNDS runs. Before such a cut's convergence under
refinement means anything its answer must depend neither on the tie nor on the cut's own
polyline: soft_t2.5 (needle_coupling's: configs/sh12_100x100.yaml as a neo-Hookean slab 2.5 mm
thick) at h tied at every station with the penalties 1e2 to 1e7, with one station per spacing
at 1e4, and tied per element of ELEMENT and 2 ELEMENT stations at 1e4, 1e6, 1e8;
sh12_100x100 at h tied at every station with 1e2, 1e4, 1e6; soft_t2.5 at h with cuts of 17,
33, 65 and 129 points (tied per ELEMENT stations at TIED). Then both scenes at h and h/2
with CUT_POINTS and that tie (h/4 not run: a first version of this probe had not finished one
round there in 9 minutes).

Writes benchmarks/results/track_cut.{csv,md,png}: every round of every run. About 10 minutes on
two cores; `--report` redraws the table and chart from the CSV.
Run from the repository root:  python benchmarks/track_cut.py
"""

from __future__ import annotations

import os

# single-threaded BLAS, as the `stitchplan` command sets it
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import contextlib  # noqa: E402
import functools  # noqa: E402
import math  # noqa: E402
import re  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from unittest import mock  # noqa: E402

import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402

import _common as common  # noqa: E402
import entry_newton  # noqa: E402
import needle_coupling  # noqa: E402
import needle_width  # noqa: E402
import stitchplan.needle.prepared_tissue as prepared_tissue  # noqa: E402
import stitchplan.tissue.model as tissue_model  # noqa: E402
from stitchplan.needle.coupling import NeedleCoupling  # noqa: E402

CUT_SPAN = 8.0  # mm of the track from the entry that is cut (the fold is at the entry)
FACE_OFFSET = 1e-3  # mm off the cut where a face is evaluated
ON_CUT = 0.25  # a track point within this many particle spacings of the cut is on it
STATIONS_PER_SPACING = 4  # FaceTie's stations per local particle spacing along the cut (a run's own)
RELAXATION = 0.5  # the next cut: this share of the run's track, the rest the cut it ran on
CUT_POINTS = 65  # points of a cut, evenly over [0, CUT_SPAN] (a run's own)
TRACK_TOLERANCE = 0.02  # particle spacings: the track on its cut
ROUNDS = 6
PENALTIES = (1e2, 1e3, 1e4, 1e5, 1e6, 1e7)
TIED = 1e6  # the penalty of the levels' runs, with ELEMENT stations per tie element
ELEMENT = 2
LEVELS = (("h", 1.0), ("h/2", 0.5))
# (scene, level, spacing factor, FaceTie's penalty, its stations per particle spacing, stations per tie element,
#  points of the cut)
RUNS = ([("soft_t2.5", "h", 1.0, penalty, STATIONS_PER_SPACING, 1, CUT_POINTS) for penalty in PENALTIES]
        + [("sh12_100x100", "h", 1.0, penalty, STATIONS_PER_SPACING, 1, CUT_POINTS) for penalty in PENALTIES[::2]]
        + [("soft_t2.5", "h", 1.0, 1e4, 1, 1, CUT_POINTS)]
        + [("soft_t2.5", "h", 1.0, penalty, STATIONS_PER_SPACING, element, CUT_POINTS)
           for element in (ELEMENT, 2 * ELEMENT) for penalty in (1e4, 1e6, 1e8)]
        + [("soft_t2.5", "h", 1.0, TIED, STATIONS_PER_SPACING, ELEMENT, points) for points in (17, 33, 129)]
        + [(scene, level, factor, TIED, STATIONS_PER_SPACING, ELEMENT, CUT_POINTS) for scene in ("soft_t2.5", "sh12_100x100")
           for level, factor in LEVELS if (scene, level) != ("soft_t2.5", "h")])
COLUMNS = ["scene", "level", "factor", "needle_spacing_mm", "penalty", "stations", "element", "cut_points", "round",
           "exit_error_mm",
           "failure", "track_off_cut_mm", "edge_least_stretch", "edge_turn_deg", "flank_gap_mm", "seconds"]


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
        boxed = np.flatnonzero(np.all(np.maximum(p, q) >= self.low, axis=1) & np.all(np.minimum(p, q) <= self.high, axis=1))
        asked = np.unique(rows[boxed])
        to_cut = np.full(len(points), np.inf)
        to_cut[asked] = self.nearest(points[asked])[3]  # a segment shorter than its point's distance cannot cross
        near = boxed[to_cut[rows[boxed]] <= np.linalg.norm(p[boxed] - q[boxed], axis=1)]
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


def along_directions(rows: sp.csr_matrix, directions: np.ndarray) -> sp.csr_matrix:
    """Rows (m, n_free) acting on (n_free, 2) coefficients turned into rows on the
    interleaved dofs (m, 2 n_free) of their component along `directions` (m, 2)."""
    coo = rows.tocoo()
    scale = directions[coo.row]
    return sp.csr_matrix((np.concatenate([coo.data * scale[:, 0], coo.data * scale[:, 1]]),
                          (np.concatenate([coo.row, coo.row]), np.concatenate([2 * coo.col, 2 * coo.col + 1]))),
                         shape=(rows.shape[0], 2 * rows.shape[1]))


class FaceTie:
    """The penalty on the faces' jump [u] = u(+) - u(-) along the cut: per tie element (a
    run's `element` stations in a row, each a run's `stations` per particle spacing apart) the
    mean of n.[u] and the mean of c t.[u] over its stations, energy k/2 (mean^2 + mean^2) with
    c = 1 ahead of the tip, 0 behind it, 1 - beta (the step's load factor) at the stations the
    tip passed in the step, k the penalty times the element's stations. One station per
    element: the jump tied at every station. Its stiffness k (A_n^T A_n + A_t^T A_t) joins K + H."""

    def __init__(self, insertion, cut: CutVisibility, penalty: float, stations: int, element: int):
        model = insertion.model
        spacing = model.needle_spacing or model.spacing
        step = spacing / stations
        along = np.arange(0.5 * step, cut.arc[-1], step)
        stations = np.column_stack([np.interp(along, cut.arc, cut.cut[:, 0]), np.interp(along, cut.arc, cut.cut[:, 1])])
        normal = cut.nearest(stations)[2]
        inside = (insertion.domain.contains(stations + FACE_OFFSET * normal)
                  & insertion.domain.contains(stations - FACE_OFFSET * normal))
        self.along, normal, stations = along[inside], normal[inside], stations[inside]
        jump = (model.free_rows_at(stations + FACE_OFFSET * normal)
                - model.free_rows_at(stations - FACE_OFFSET * normal)).tocsr()
        self.normal_rows = along_directions(jump, normal)
        self.tangent_rows = along_directions(jump, np.column_stack([-normal[:, 1], normal[:, 0]]))
        group = np.arange(len(self.along)) // element
        counts = np.bincount(group)
        self.mean = sp.csr_matrix((1.0 / counts[group], (group, np.arange(len(group)))), shape=(len(counts), len(group)))
        material = insertion.scenario.tissue.material
        self.penalty = penalty * material.lame_mu * insertion.scenario.tissue.thickness * step / spacing * element
        normal_means = (self.mean @ self.normal_rows).tocsr()
        self.normal_part = normal_means.T @ normal_means  # A_n^T A_n: the same at every state
        self.cut = cut
        self.tip_before = self.tip = 0.0  # the tip's arc length on the cut at the step's start, and now
        self.track_points = -1
        self.stiffness_at = (None, None)  # (tip_before, tip, load factor), its stiffness

    def follow_tip(self, insertion) -> None:
        """At a step's start: where the tip has got to on the cut."""
        points = insertion.points
        if len(points) != self.track_points:
            self.track_points, self.tip_before = len(points), self.tip
            if len(points):
                self.tip = float(self.cut.nearest(points[-1])[1][0])

    def stiffness(self, load_factor: float) -> sp.csr_matrix:
        """k (A_n^T A_n + A_t^T A_t), A_t with this step's sliding c: made once per step and load."""
        key = (self.tip_before, self.tip, load_factor)
        if self.stiffness_at[0] != key:
            passed = (self.along > self.tip_before) & (self.along <= self.tip)
            sliding = np.where(self.along <= self.tip_before, 0.0, np.where(passed, 1.0 - load_factor, 1.0))
            tangent_means = (self.mean @ sp.diags(sliding) @ self.tangent_rows).tocsr()
            self.stiffness_at = (key, (self.penalty * (self.normal_part + tangent_means.T @ tangent_means)).tocsr())
        return self.stiffness_at[1]

    def terms(self, insertion, free: np.ndarray, center: np.ndarray) -> tuple[np.ndarray, sp.csr_matrix]:
        stiffness = self.stiffness(insertion.coupling.load_factor)
        return stiffness @ free.ravel(), stiffness

    def equilibrate(self, equilibrate, insertion, *arguments, **keywords):
        self.follow_tip(insertion)
        return equilibrate(insertion, *arguments, **keywords)


@contextlib.contextmanager
def track_cut(cut: CutVisibility, penalty: float, stations: int, element: int):
    """The tissue model built with the cut's visibility, the coupling on FaceRows and FaceTie's
    terms in the insertion, while inside."""
    shape_functions, build = tissue_model.rk_shape_functions, tissue_model.build_tissue_model
    couple = NeedleCoupling.__init__

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

    with mock.patch.object(tissue_model, "rk_shape_functions", seeing_across), \
            mock.patch.object(prepared_tissue, "build_tissue_model", built), \
            mock.patch.object(NeedleCoupling, "__init__", faced), \
            needle_width.added_term(lambda insertion: FaceTie(insertion, cut, penalty, stations, element)):
        yield


def first_span(track: np.ndarray, points: int) -> np.ndarray:
    """The track's first CUT_SPAN mm as `points` points evenly along it."""
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(track, axis=0), axis=1))])
    along = np.linspace(0.0, min(CUT_SPAN, arc[-1]), points)
    return np.column_stack([np.interp(along, arc, track[:, 0]), np.interp(along, arc, track[:, 1])])


def run(scene: str, level: str, factor: float, penalty: float, stations: int, element: int,
        cut_points: int) -> list[dict]:
    """The fixed point of the cut on one scene and level: a row per round."""
    scenario = needle_coupling.refined(scene, factor)
    spacing = scenario.discretization.needle_spacing or scenario.discretization.spacing
    cut = first_span(needle_width.insertion_run(scenario)[2].points, cut_points)  # the line needle's track
    rows = []
    for round_ in range(1, ROUNDS + 1):
        start = time.perf_counter()
        visibility = CutVisibility(cut)
        exit_error, failure, insertion = needle_width.insertion_run(scenario,
                                                                    track_cut(visibility, penalty, stations, element))
        _, along, _, distance = visibility.nearest(insertion.points)
        off = float(distance[along < CUT_SPAN - spacing].max(initial=0.0))
        stretch, turn, gap = entry_newton.entry_flanks(insertion)
        rows.append({"scene": scene, "level": level, "factor": f"{factor:g}", "needle_spacing_mm": f"{spacing:.4g}",
                     "penalty": f"{penalty:g}", "stations": stations, "element": element, "cut_points": cut_points,
                     "round": round_, "exit_error_mm": exit_error, "failure": failure,
                     "track_off_cut_mm": f"{off:.4f}", "edge_least_stretch": f"{stretch:.4f}",
                     "edge_turn_deg": f"{turn:.1f}", "flank_gap_mm": f"{gap:.4f}",
                     "seconds": f"{time.perf_counter() - start:.1f}"})
        print(rows[-1], flush=True)
        if off <= TRACK_TOLERANCE * spacing or len(insertion.points) < 2:
            break
        cut = RELAXATION * first_span(insertion.points, cut_points) + (1.0 - RELAXATION) * cut
    return rows


def runs(rows: list[dict]) -> dict[tuple[str, ...], list[dict]]:
    """Rows per (scene, level, penalty, stations, element, cut points), rounds in order."""
    groups: dict[tuple[str, ...], list[dict]] = {}
    for row in rows:
        key = (row["scene"], row["level"], row["penalty"], row["stations"], row["element"], row["cut_points"])
        groups.setdefault(key, []).append(row)
    return groups


def settled(group: list[dict]) -> tuple[float, float]:
    """A run's exit error: the mean of its last two rounds (the last alone if one), and half
    their difference (how far the fixed point still swings); NaN where its last round stopped."""
    if not group or not group[-1]["exit_error_mm"]:
        return math.nan, math.nan
    values = [float(row["exit_error_mm"]) for row in group if row["exit_error_mm"]][-2:]
    return float(np.mean(values)), 0.5 * abs(values[-1] - values[0])


@functools.cache
def needle_width_rows() -> tuple[dict, ...]:
    """needle_width.csv, read once: the report asks it for the line needle at every level."""
    return tuple(common.csv_rows(common.results_path("needle_width.csv")))


def line_needle(scene: str, level: str) -> str:
    """The package's line needle on `scene` at `level` (needle_width.csv; empty where it stopped)."""
    found = [row["exit_error_mm"] for row in needle_width_rows()
             if row["scene"] == scene and row["width_mm"] == "0" and row["level"] == level]
    return found[0] if found else ""


def short_failure(row: dict) -> str:
    """Where a run stopped: its step and load, and the inverted material where the message says."""
    text = row["failure"]
    inverted = re.search(r"det F = \S+ at \([^)]+\) mm", text)
    return text.split(", the next")[0] + (f", {inverted.group(0)}" if inverted else "")


def sweep(rows: list[dict], scene: str, stations: int, element: int) -> list[tuple[float, list[dict]]]:
    """(penalty, rounds) of `scene`'s runs at h with this tie and CUT_POINTS, by penalty."""
    return sorted((float(key[2]), group) for key, group in runs(rows).items()
                  if key[:2] == (scene, "h") and key[3:] == (str(stations), str(element), str(CUT_POINTS)))


def cut_points(rows: list[dict]) -> list[tuple[int, float]]:
    """(points of the cut, exit error) of soft_t2.5's runs at h with the levels' tie."""
    return sorted((int(key[5]), settled(group)[0]) for key, group in runs(rows).items()
                  if key[:5] == ("soft_t2.5", "h", f"{TIED:g}", str(STATIONS_PER_SPACING), str(ELEMENT)))


def ladder(rows: list[dict], scene: str) -> list[tuple[str, float]]:
    """(level, exit error) of `scene`'s runs with the levels' tie and CUT_POINTS, coarsest first."""
    groups = runs(rows)
    return [(level, settled(groups.get((scene, level, f"{TIED:g}", str(STATIONS_PER_SPACING), str(ELEMENT),
                                        str(CUT_POINTS)), []))[0]) for level, _ in LEVELS]


def percent(a: float, b: float) -> str:
    return f"{100 * (b / a - 1):+.2f}" if math.isfinite(a) and math.isfinite(b) else "—"


def reading(rows: list[dict]) -> str:
    """What the runs say, from their numbers."""
    text = []
    for scene, element in (("soft_t2.5", 1), ("sh12_100x100", 1), ("soft_t2.5", ELEMENT), ("soft_t2.5", 2 * ELEMENT)):
        found = sweep(rows, scene, STATIONS_PER_SPACING, element)
        done = [(penalty, settled(group)[0]) for penalty, group in found]
        ran = [(penalty, value) for penalty, value in done if math.isfinite(value)]
        tie = "the jump tied at every station" if element == 1 else f"tied per element of {element} stations"
        stopped = [(penalty, group) for (penalty, group), (_, value) in zip(found, done) if not math.isfinite(value)]
        if len(ran) >= 2:
            text.append(f"{scene}, {tie}: " + ", ".join(f"{value:.3f}" for _, value in ran) + " mm for the penalties "
                        + ", ".join(f"{penalty:g}" for penalty, _ in ran)
                        + f", the last {ran[-1][0] / ran[-2][0]:g} times stiffer one moving it {percent(ran[-2][1], ran[-1][1])} %"
                        + "".join(f", at {penalty:g} it stops ({short_failure(group[-1])})" for penalty, group in stopped))
        elif found:
            text.append(f"{scene}, {tie}: stops at every penalty ({short_failure(found[0][1][-1])})")
    coarse = sweep(rows, "soft_t2.5", 1, 1)
    sentence = "Reading: " + "; ".join(text) + "."
    if coarse:
        group = coarse[0][1]
        stopped = [row for row in group if not row["exit_error_mm"]]
        sentence += (f" With one station per particle spacing {len(stopped)} of its {len(group)} rounds stop"
                     + (f" (the last: {short_failure(stopped[-1])})" if stopped else "") + ".")
    sentence += (" Tied at every station the answer follows the penalty (likely locking: the jump held to zero at more "
                 "points than the faces' coefficients can follow); tied per element it moves less with it. ")
    resolution = [(points, value) for points, value in cut_points(rows) if math.isfinite(value)]
    if len(resolution) > 1:
        sentence += ("The cut's own resolution moves it too: soft_t2.5 at h gives " + ", ".join(
            f"{value:.3f}" for _, value in resolution) + " mm with a cut of " + ", ".join(
            str(points) for points, _ in resolution) + f" points over its {CUT_SPAN:g} mm (tied per {ELEMENT} stations at "
            f"{TIED:g}), the last doubling still {percent(resolution[-2][1], resolution[-1][1])} % (likely the "
            "visibility criterion's shape functions following the polyline's kinks; not measured). ")
    parts = []
    for scene in ("soft_t2.5", "sh12_100x100"):
        values = ladder(rows, scene)
        line = [float(line_needle(scene, level)) if line_needle(scene, level) else math.nan for level, _ in LEVELS]
        shown = ", ".join(f"{value:.3f}" if math.isfinite(value) else "stops" for _, value in values)
        parts.append(f"{scene} {shown} mm at h, h/2 ({percent(values[0][1], values[1][1])} %; the line needle "
                     f"{percent(line[0], line[1])} %)")
    sentence += (f"With {CUT_POINTS} points and that tie the cut gives " + "; ".join(parts) + ": as probed here the cut "
                 "moves more under refinement than the line needle, and its own two discretizations (the tie, the "
                 "polyline) each move the answer by more than the criterion's 2 %.")
    return sentence


def report(rows: list[dict]) -> str:
    summary = []
    for (scene, level, penalty, stations, element, points), group in runs(rows).items():
        value, swing = settled(group)
        last = group[-1]
        summary.append([scene, level, penalty, stations, element, points, len(group),
                        f"{value:.4f} ± {swing:.4f}" if math.isfinite(value) else "stops: " + short_failure(last),
                        line_needle(scene, level) or "stops", last["track_off_cut_mm"], last["edge_turn_deg"],
                        last["flank_gap_mm"]])
    text = ["# The needle's track as a cut", "",
            f"Generated by `python benchmarks/track_cut.py` ({common.machine_note()}). The first {CUT_SPAN:g} mm of the "
            "track from the entry cut (no shape function across it), the needle's constraint and loads on the mean of "
            "its two faces, the faces glued ahead of the tip and held together across the blade behind it by a penalty "
            "(the table's, x mu t per station spacing / particle spacing, at the table's stations per particle spacing, "
            "on the jump at every station or on its mean over elements of the table's stations; the cut a polyline of the table's points); the cut made to lie on "
            f"the run's own track by a fixed point (each next cut {RELAXATION:g} of the run's track and the rest the cut "
            f"it ran on, until the track is within {TRACK_TOLERANCE:g} particle spacings of its cut or after {ROUNDS} "
            "rounds). Patched in for the runs, not an option of the package. soft_t2.5: configs/sh12_100x100.yaml as a "
            "neo-Hookean slab 2.5 mm thick; h the file's spacings (0.888 mm at the needle).", "",
            "Per run, the exit error of its last two rounds (their mean ± half their difference), beside the package's "
            "line needle at the same level (needle_width.csv), and in the last round the track's distance from its cut, "
            "the entry's edge's turn and the least distance between its two sides:", "",
            common.markdown_table(["scene", "level", "penalty", "stations", "per element", "cut points", "rounds",
                                   "exit error (mm)", "line needle (mm)", "track off its cut (mm)", "entry edge turn (deg)",
                                   "its sides apart (mm)"], summary),
            "", reading(rows), "",
            "Every round:", "",
            common.markdown_table(["scene", "level", "penalty", "stations", "per element", "cut points", "round",
                                   "exit error (mm)",
                                   "track off its cut (mm)", "entry edge: least stretch", "turn (deg)",
                                   "sides apart (mm)", "seconds"],
                                  [[row["scene"], row["level"], row["penalty"], row["stations"], row["element"],
                                    row["cut_points"], row["round"], row["exit_error_mm"] or "stops: " + row["failure"].replace("|", "‖"),
                                    row["track_off_cut_mm"], row["edge_least_stretch"], row["edge_turn_deg"],
                                    row["flank_gap_mm"], row["seconds"]] for row in rows]), ""]
    return "\n".join(text) + "\n"


def chart(rows: list[dict], path) -> None:
    """Exit error at h against the faces' penalty per scene and tie, and against the cut's
    points; the exit error relative to h against the spacing, the cut's beside the line needle's."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 4, figsize=(21, 5.2))
    for axis, scene in zip(axes[:2], ("soft_t2.5", "sh12_100x100")):
        for k, element in enumerate((1, ELEMENT, 2 * ELEMENT)):
            tried = [(penalty, *settled(group)) for penalty, group in sweep(rows, scene, STATIONS_PER_SPACING, element)]
            done = [entry for entry in tried if math.isfinite(entry[1])]
            tie = "tied at every station" if element == 1 else f"tied per {element} stations"
            colour = None
            if done:
                bars = axis.errorbar([entry[0] for entry in done], [entry[1] for entry in done],
                                     yerr=[entry[2] for entry in done], fmt="o-", capsize=3, label=tie)
                colour = bars.lines[0].get_color()
            stopped = [entry[0] for entry in tried if not math.isfinite(entry[1])]
            if stopped:  # a run that stops has no exit error: a cross near the panel's top, a row per tie
                axis.plot(stopped, [0.97 - 0.05 * k] * len(stopped), "x", color=colour, ms=8, mew=2,
                          transform=axis.get_xaxis_transform(), label=f"{tie}: the run stops")
        line = line_needle(scene, "h")
        if line:
            axis.axhline(float(line), color="0.4", ls="--", label="line needle (the package)")
        axis.set_xscale("log")
        axis.set_xlabel("penalty on the faces' jump (x mu t per station spacing / particle spacing)")
        axis.set_ylabel("unplanned exit error at h (mm)")
        axis.set_title(f"{scene}: the tie", fontsize=10)
        # below the crosses of runs that stop (at the top), above the curves
        axis.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.62, 0.86))
    resolution = [(points, value) for points, value in cut_points(rows) if math.isfinite(value)]
    axes[2].plot(*zip(*resolution), "o-", label=f"track cut (penalty {TIED:g}, per {ELEMENT} stations)")
    axes[2].axhline(float(line_needle("soft_t2.5", "h")), color="0.4", ls="--", label="line needle (the package)")
    axes[2].set_xscale("log", base=2)
    axes[2].set_xticks([points for points, _ in resolution], [str(points) for points, _ in resolution])
    axes[2].minorticks_off()
    axes[2].set_xlabel(f"points of the cut over its {CUT_SPAN:g} mm")
    axes[2].set_ylabel("unplanned exit error at h (mm)")
    axes[2].set_title("soft_t2.5: the cut's polyline", fontsize=10)
    axes[2].legend(fontsize=8)
    for scene, marker in (("soft_t2.5", "o"), ("sh12_100x100", "^")):
        spacing = {row["level"]: float(row["needle_spacing_mm"]) for row in rows if row["scene"] == scene}
        cut = [(spacing[level], value) for level, value in ladder(rows, scene) if math.isfinite(value)]
        line = [(spacing[level], float(line_needle(scene, level))) for level, _ in LEVELS
                if level in spacing and line_needle(scene, level)]
        for values, style, name in ((cut, "-", "track cut"), (line, "--", "line needle")):
            if values:
                axes[3].plot([x for x, _ in values], [y / values[0][1] for _, y in values], marker + style,
                             label=f"{scene}, {name}")
        ticks = sorted(set(spacing.values()), reverse=True)
    axes[3].set_xscale("log")
    axes[3].set_xticks(ticks, [f"{tick:g}" for tick in ticks])
    axes[3].minorticks_off()
    axes[3].invert_xaxis()
    axes[3].set_xlabel("particle spacing at the needle (mm)")
    axes[3].set_ylabel("exit error / its value at h")
    axes[3].set_title(f"under refinement ({CUT_POINTS} points, penalty {TIED:g} per {ELEMENT} stations)", fontsize=10)
    axes[3].legend(fontsize=8)
    figure.suptitle("The needle's track near the entry as a cut: its tie, its polyline, then refinement")
    common.save_figure(figure, path, (0, 0, 1, 0.93))
    plt.close(figure)


def main() -> None:
    path = common.results_path("track_cut.csv")
    if "--report" not in common.command_line(__doc__, ("--report",)):
        order = sorted(RUNS, key=lambda run_: run_[2])  # the slow, fine runs first
        with ProcessPoolExecutor(max_workers=2) as pool:
            finished = dict(zip(order, pool.map(run, *zip(*order))))
        common.write_csv(path, COLUMNS, [[row[column] for column in COLUMNS] for run_ in RUNS
                                         for row in finished[run_]])
    rows = common.csv_rows(path)
    common.publish("track_cut", report(rows), chart, rows)


if __name__ == "__main__":
    main()
