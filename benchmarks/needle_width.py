"""Whether a needle of finite width makes the soft slabs' exit error converge.

The needle is a line here (needle/coupling.py): its friction, cutting force and constraint
act on the track Gamma_N, a line load ending at the free surface where the needle enters.
On the soft slabs (needle_coupling's soft_t3 and soft_t2.5: configs/sh12_100x100.yaml as a
neo-Hookean slab 3 and 2.5 mm thick) the free edge at the entry is drawn into a cusp along the
needle that every refinement sharpens, and soft_t2.5 stops at a quarter spacing with the
entry's two sides 25 um apart (entry_stability.md, entry_newton.md). Two parts of a needle of
width w, patched in for the runs (probes of the model, not options of the package):

- the band: a line load's displacement gradient is log-singular at its end; spread over a band
  of width w it is bounded. Every shape-function row the coupling evaluates at a track point X
  (its loads' quadrature points, its constraint's, the tip) becomes the average of the rows
  across the band, at X + s n(X) for s in [-w/2, w/2] (Gauss-Legendre, ACROSS_PER_SPACING
  points per local particle spacing across it, at least MIN_ACROSS), n(X) the normal of the
  reference needle circle at X: the loads spread uniformly over the band, the constraint
  holding the band's mean on the needle circle;
- the contact (EntryContact): the needle's body holding the entry's free edge off it, the
  edge's points outside the band kept w/2 from the needle's circle on their own side by a
  penalty (CONTACT_PENALTY x mu t per point spacing / particle spacing, N/mm: it stiffens as
  the particles are refined).

w = 0 is the package's line needle. Runs: sh12_100x100, soft_t3 and soft_t2.5 at h, h/2, h/4
(h the file's spacings, `--spacing` moving both as `stitchplan simulate --spacing` does) with
the line needle, the band of w = 0.6 mm (about the wire diameter of a needle of this size) and
the band with the contact (penalty 10); soft_t2.5 also with the band alone at h/8, at w = 1.5
and 3 mm (wider than any such needle: how far the band alone goes) and at spacings that put one
particle spacing across the band at the coarsest level (the needle spacing 0.6, 0.3, 0.15 mm),
and with the contact at the penalties 1 and 100 (how much its answer depends on it) and 10 at h/8,
and with the contact's pressures raised after each equilibrium until the edge is out of the
needle (an augmented Lagrangian, penalties 10 and 100) at h, h/2, h/4, and penalty 10 at h/8.

Writes benchmarks/results/needle_width.{csv,md,png}. About 20 minutes on two cores;
`--missing` runs only what the CSV lacks, `--report` redraws the table and chart from it.
Run from the repository root:  python benchmarks/needle_width.py
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
from stitchplan.errors import InsertionFailure  # noqa: E402
from stitchplan.needle.coupling import NeedleCoupling  # noqa: E402
from stitchplan.needle.equilibrium import NeedleInsertion  # noqa: E402
from stitchplan.needle.insertion import run_insertion  # noqa: E402

ACROSS_PER_SPACING = 2  # Gauss points across the band per local particle spacing ...
MIN_ACROSS = 4  # ... and at least this many
# the soft slabs' spacing at the needle, configs/sh12_100x100.yaml's (7.104 mm / needle_refinement 8)
SOFT_NEEDLE_SPACING = needle_coupling.scene("soft_t2.5", needle_coupling.SHIPPED_COUPLING).discretization.needle_spacing
LEVELS = (("h", 1.0), ("h/2", 0.5), ("h/4", 0.25))
RESOLVED = tuple((name, 0.6 / SOFT_NEEDLE_SPACING * factor) for name, factor in
                 (("0.6 mm", 1.0), ("0.3 mm", 0.5), ("0.15 mm", 0.25)))  # one spacing across w = 0.6 at the first
PENALTIES = (1.0, 10.0, 100.0)  # CONTACT_PENALTY of the runs with EntryContact
# (scene, w mm, contact penalty or 0 for none, level, spacing factor, augmented Lagrangian)
RUNS = ([(scene, width, 0.0, level, factor, False) for scene in ("sh12_100x100", "soft_t3") for width in (0.0, 0.6)
         for level, factor in LEVELS]
        + [("soft_t2.5", width, 0.0, level, factor, False) for width in (0.0, 0.6, 1.5, 3.0)
           for level, factor in LEVELS]
        + [("soft_t2.5", 0.6, 0.0, "h/8", 0.125, False)]
        + [("soft_t2.5", 0.6, 0.0, f"needle spacing {level}", factor, False) for level, factor in RESOLVED]
        + [("soft_t2.5", 0.6, penalty, level, factor, False) for penalty in PENALTIES for level, factor in LEVELS]
        + [("soft_t2.5", 0.6, 10.0, "h/8", 0.125, False)]
        + [(scene, 0.6, 10.0, level, factor, False) for scene in ("sh12_100x100", "soft_t3")
           for level, factor in LEVELS]
        + [("soft_t2.5", 0.6, penalty, level, factor, True) for penalty in (10.0, 100.0) for level, factor in LEVELS]
        + [("soft_t2.5", 0.6, 10.0, "h/8", 0.125, True)])
COLUMNS = ["scene", "width_mm", "contact_penalty", "augmented", "level", "factor", "needle_spacing_mm", "across", "exit_error_mm",
           "failure", "edge_least_stretch", "edge_turn_deg", "flank_gap_mm", "seconds"]


class OffsetRows:
    """The tissue model as the coupling sees it, each row it asks for at a point the weighted
    sum of the rows at points set off from it along a normal: `offsets` (mm) with `weights`,
    about the base and normal `frame` gives (BandRows; track_cut.FaceRows)."""

    offsets: np.ndarray
    weights: np.ndarray

    def __init__(self, model):
        self._model = model

    def __getattr__(self, name: str):
        return getattr(self._model, name)

    def frame(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The base points the offsets start from and the unit normals they go along, (n, 2) each."""
        raise NotImplementedError

    def placed(self, points: np.ndarray) -> np.ndarray:
        """The offset points where the rows are evaluated."""
        return points

    def free_rows_at(self, points: np.ndarray) -> sp.csr_matrix:
        points = np.atleast_2d(points)
        if not len(points):
            return self._model.free_rows_at(points)
        base, normal = self.frame(points)
        rows = [weight * self._model.free_rows_at(self.placed(base + offset * normal))
                for offset, weight in zip(self.offsets, self.weights)]
        return sum(rows[1:], rows[0]).tocsr()


class BandRows(OffsetRows):
    """The rows averaged across the band: Gauss-Legendre across [-w/2, w/2] along the
    reference needle circle's normal, the points kept within the particles' box."""

    def __init__(self, model, center: np.ndarray, width: float, across: int):
        super().__init__(model)
        self._center = np.asarray(center, dtype=float)
        offsets, weights = np.polynomial.legendre.leggauss(across)
        self.offsets, self.weights = 0.5 * width * offsets, 0.5 * weights
        self._low, self._high = model.particles.min(axis=0), model.particles.max(axis=0)

    def frame(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        normal = points - self._center
        return points, normal / np.linalg.norm(normal, axis=1, keepdims=True)

    def placed(self, points: np.ndarray) -> np.ndarray:
        return np.clip(points, self._low, self._high)


@contextlib.contextmanager
def needle_band(width: float, across: int):
    """NeedleCoupling built on BandRows while inside (nothing changed for w = 0)."""
    build = NeedleCoupling.__init__

    def banded(coupling, model, geometry, needle, dilation=2.0):
        build(coupling, model, geometry, needle, dilation)
        if width > 0:
            coupling.model = BandRows(model, geometry.center, width, across)

    with mock.patch.object(NeedleCoupling, "__init__", banded):
        yield


CONTACT_SPAN = 4.0  # mm of the entry's edge on each side checked against the needle's body
CONTACT_SAMPLES = 4  # points per local particle spacing along it
CONTACT_PENALTY = 10.0  # penalty per point, x mu t (point spacing / particle spacing) N/mm (a run's own)
CONTACT_REACH = 1.0  # a point counts only within this many widths of the needle's circle
AUGMENTED_PENETRATION = 0.01  # augmented Lagrangian: penetration left, a share of w/2 ...
AUGMENTED_UPDATES = 60  # ... within at most this many updates of the pressures per step,
AUGMENTED_SMALLEST_MOVE = 1 / 64  # each update's move halved while Newton fails, down to this share


class EntryContact:
    """The needle's body, of width w, holding off the free edge at its entry: points of the
    edge more than w/2 from the entry on either side (outside the band the loads act on) kept
    at least w/2 from the needle's circle on their own side, wherever the needle's arc lies
    (inside the tissue or still outside it), by a penalty: energy k/2 <-g>^2 per point,
    g = side (abs(x - C) - R) - w/2, k = CONTACT_PENALTY mu t (point spacing / particle
    spacing); with `pressure` (augmented Lagrangian) the force max(0, p - k g) instead, p raised
    to it after each equilibrium until the penetration is below AUGMENTED_PENETRATION of w/2, so
    that the answer no longer depends on k. Its force joins r_u; its stiffness k N^T n n^T N
    (the curvature term of g, a force times 1/R, left out) joins K + H."""

    def __init__(self, insertion, width: float, penalty: float = CONTACT_PENALTY, augmented: bool = False):
        geometry, model = insertion.geometry, insertion.model
        spacing = model.needle_spacing or model.spacing
        step = spacing / CONTACT_SAMPLES
        along = np.arange(0.5 * width + step, CONTACT_SPAN + 0.5 * step, step)
        offsets = np.concatenate([-along[::-1], along])
        radial = (geometry.entry - geometry.center) / geometry.radius  # the edge's tangent at an orthogonal entry
        points = insertion.domain.clip(geometry.entry + offsets[:, None] * radial)
        self.rows = model.free_rows_at(points)
        self.points, self.side = points, np.sign(offsets)
        material = insertion.scenario.tissue.material
        self.penalty = penalty * material.lame_mu * insertion.scenario.tissue.thickness * step / spacing
        self.geometry, self.width = geometry, width
        self.pressure = np.zeros(len(points))  # augmented Lagrangian: each point's contact force, N (>= 0)
        self.gap = np.zeros(len(points))  # g at the last evaluation (where it counts; +inf elsewhere)
        self.augmented, self.rotation = augmented, 0.0  # the needle's rotation at the step being solved

    def terms(self, insertion, free: np.ndarray, center: np.ndarray) -> tuple[np.ndarray, sp.csr_matrix]:
        """The contact's force on r_u (2 n_free,) and its stiffness (2 n_free, 2 n_free)."""
        geometry, rotation = self.geometry, self.rotation
        deformed = self.points + self.rows @ free.reshape(-1, 2)
        offset = deformed - center
        distance = np.linalg.norm(offset, axis=1)
        normal = offset / distance[:, None]
        gap = self.side * (distance - geometry.radius) - 0.5 * self.width
        turned = geometry.sense * (np.arctan2(offset[:, 1], offset[:, 0]) - geometry.start_angle)
        turned = (turned + math.pi) % (2 * math.pi) - math.pi  # from the entry's angle, in the needle's sense
        on_needle = (turned <= rotation) & (turned >= rotation - geometry.arc)
        counts = on_needle & (np.abs(distance - geometry.radius) < CONTACT_REACH * self.width)
        self.gap = np.where(counts, gap, np.inf)
        pushing = np.where(counts, self.pressure - self.penalty * gap, 0.0)  # the contact force at each point, N
        active = pushing > 0
        n_dof = 2 * self.rows.shape[1]
        if not np.any(active):
            return np.zeros(n_dof), sp.csr_matrix((n_dof, n_dof))
        rows, normal = self.rows[active], normal[active]
        force = (-pushing[active] * self.side[active])[:, None] * normal  # dPi/dx per point
        blocks = self.penalty * normal[:, :, None] * normal[:, None, :]
        return (rows.T @ force).ravel(), entry_newton.point_blocks_on_dofs(rows, blocks)

    def penetration(self) -> float:
        """How far the edge lies inside the needle at the last evaluation, mm (0: nowhere)."""
        return -self.gap.min(initial=0.0)

    def equilibrate(self, equilibrate, insertion, rotation, step, *arguments, **keywords):
        """A step's equilibrium (`equilibrate`, the insertion's own); `augmented`: then the
        pressures updated (Uzawa) until the penetration is below AUGMENTED_PENETRATION of w/2 (an
        InsertionFailure if AUGMENTED_UPDATES do not get there), an update Newton cannot follow
        made in smaller moves (raise_pressures)."""
        self.rotation = rotation
        result = equilibrate(insertion, rotation, step, *arguments, **keywords)
        if not self.augmented:
            return result
        allowed = AUGMENTED_PENETRATION * 0.5 * self.width
        for update in range(AUGMENTED_UPDATES + 1):
            insertion.residuals(insertion.free, insertion.multipliers, insertion.center)  # self.gap there
            if self.penetration() <= allowed:
                return result
            if update < AUGMENTED_UPDATES:
                touching = np.where(np.isfinite(self.gap), self.gap, 0.0)
                result = self.raise_pressures(np.maximum(self.pressure - self.penalty * touching, 0.0), equilibrate,
                                              insertion, rotation, step, *arguments, **keywords)
        raise InsertionFailure(f"step {step} (needle rotation {rotation:.3f} rad): the entry's edge still "
                               f"{1000 * self.penetration():.1f} um inside the needle after "
                               f"{AUGMENTED_UPDATES} pressure updates")

    def raise_pressures(self, target, equilibrate, insertion, rotation, step, *arguments, **keywords):
        """Equilibrium with the pressures moved to `target`: the whole move first, halved while
        Newton fails (from the state before it), down to AUGMENTED_SMALLEST_MOVE."""
        share, start, before = 1.0, self.pressure, insertion.snapshot()
        while True:
            self.pressure = start + share * (target - start)
            try:
                return equilibrate(insertion, rotation, step, *arguments, **keywords)
            except InsertionFailure:
                insertion.restore(before)
                insertion.saddle.forget()
                self.pressure, share = start, 0.5 * share
                if share < AUGMENTED_SMALLEST_MOVE:
                    raise


@contextlib.contextmanager
def added_term(make):
    """NeedleInsertion with one more term while inside: `make(insertion)` builds it (once per
    insertion), its `terms(insertion, free, center)` gives the force joining r_u and the
    stiffness joining K + H, and its `equilibrate(equilibrate, insertion, rotation, step, ...)`
    solves each step with the insertion's own `equilibrate` (EntryContact, track_cut.FaceTie)."""
    residuals, stiffness, equilibrate = NeedleInsertion.residuals, NeedleInsertion._stiffness, \
        NeedleInsertion.equilibrate

    def term(insertion):
        if "added_term" not in insertion.__dict__:
            insertion.added_term = make(insertion)
        return insertion.added_term

    def with_term(insertion, free, multipliers, center):
        state = residuals(insertion, free, multipliers, center)
        force, insertion.added_stiffness = term(insertion).terms(insertion, free, center)
        return dataclasses.replace(state, residual=state.residual + force)

    def stiffness_with_term(insertion, multipliers, state):
        tangent = stiffness(insertion, multipliers, state)
        return lambda: (tangent() + insertion.added_stiffness).tocsr()

    def equilibrate_with_term(insertion, *arguments, **keywords):
        return term(insertion).equilibrate(equilibrate, insertion, *arguments, **keywords)

    with mock.patch.multiple(NeedleInsertion, residuals=with_term, _stiffness=stiffness_with_term,
                             equilibrate=equilibrate_with_term):
        yield


@contextlib.contextmanager
def entry_contact(width: float, penalty: float, augmented: bool = False):
    """NeedleInsertion with EntryContact while inside (nothing for a penalty 0)."""
    if penalty <= 0:
        yield
        return
    with added_term(lambda insertion: EntryContact(insertion, width, penalty, augmented)):
        yield


@contextlib.contextmanager
def kept_insertion(kept: dict):
    """The NeedleInsertion a run builds, in kept["insertion"] (its state the last one carried)."""
    equilibrate = NeedleInsertion.equilibrate

    def keeping(insertion, *arguments, **keywords):
        kept["insertion"] = insertion
        return equilibrate(insertion, *arguments, **keywords)

    with mock.patch.object(NeedleInsertion, "equilibrate", keeping):
        yield


def insertion_run(scenario, *contexts) -> tuple[str, str, NeedleInsertion]:
    """One unplanned insertion inside `contexts` (patches of the model): its exit error or
    failure (CSV strings) and the NeedleInsertion as it ended."""
    kept = {}
    with contextlib.ExitStack() as stack:
        for context in (*contexts, kept_insertion(kept)):
            stack.enter_context(context)
        try:
            outcome = f"{run_insertion(scenario).exit_error_mm:.6f}", ""
        except InsertionFailure as failure:
            outcome = "", " ".join(str(failure).split())
    return *outcome, kept["insertion"]


def run(scene: str, width: float, penalty: float, level: str, factor: float, augmented: bool = False) -> dict:
    """One insertion; with the entry's free edge where it ended (once the needle has left, or at
    the last load carried where it stopped): entry_newton.entry_flanks."""
    scenario = needle_coupling.refined(scene, factor)
    spacing = scenario.discretization.needle_spacing or scenario.discretization.spacing
    across = max(MIN_ACROSS, math.ceil(ACROSS_PER_SPACING * width / spacing)) if width > 0 else 0
    start = time.perf_counter()
    exit_error, failure, insertion = insertion_run(scenario, needle_band(width, across),
                                                   entry_contact(width, penalty, augmented))
    seconds = time.perf_counter() - start
    stretch, turn, gap = entry_newton.entry_flanks(insertion)
    row = {"scene": scene, "width_mm": f"{width:g}", "contact_penalty": f"{penalty:g}" if penalty else "",
           "augmented": "yes" if augmented else "",
           "level": level, "factor": f"{factor:.6g}", "needle_spacing_mm": f"{spacing:.4g}", "across": across,
           "exit_error_mm": exit_error, "failure": failure, "edge_least_stretch": f"{stretch:.4f}",
           "edge_turn_deg": f"{turn:.1f}", "flank_gap_mm": f"{gap:.4f}", "seconds": f"{seconds:.1f}"}
    print(row, flush=True)
    return row


def variant(row: dict) -> str:
    """The needle a row ran with."""
    if row["width_mm"] == "0":
        return "line"
    contact = f" + contact k={row['contact_penalty']}" if row["contact_penalty"] else ""
    contact += " (augmented Lagrangian)" if row.get("augmented") else ""
    return f"w = {row['width_mm']} mm{contact}"


def series(rows: list[dict]) -> dict[tuple[str, str, bool], list[dict]]:
    """Rows per (scene, variant, resolved-levels series), finest last."""
    groups: dict[tuple[str, str, bool], list[dict]] = {}
    for row in rows:
        groups.setdefault((row["scene"], variant(row), row["level"].startswith("needle")), []).append(row)
    return {key: sorted(group, key=lambda row: -float(row["factor"])) for key, group in groups.items()}


def ladder(group: list[dict]) -> tuple[str, str, str]:
    """Change from the first level to the second (%), whether the levels run are monotone, and
    the observed rate p = log2(abs(e1 - e0) / abs(e2 - e1)) from the first three (spacing ratio 2)."""
    values = [float(row["exit_error_mm"]) for row in group if row["exit_error_mm"]]
    change = f"{100 * (values[1] / values[0] - 1):+.2f}" if len(values) >= 2 else "—"
    if len(values) < 3:
        return change, "—", "—"
    steps = np.diff(values)
    monotone = "yes" if np.all(steps > 0) or np.all(steps < 0) else "no"
    rate = math.log2(abs(steps[0]) / abs(steps[1])) if steps[1] != 0 else math.inf
    return change, monotone, f"{rate:.2f}"


def failure_text(row: dict) -> str:
    """Where a run stopped: its step and the load carried, and what gave way where the
    message says (the tangent's least stiffness on the needle's constraints)."""
    text = row["failure"].replace("|", "‖")
    gave_way = text.find("; the tangent")
    return "stops: " + text.split(", the next")[0] + (", " + text[gave_way + 2:] if gave_way >= 0 else "")


def report(rows: list[dict]) -> str:
    text = ["# A needle of finite width on the soft slabs", "",
            f"Generated by `python benchmarks/needle_width.py` ({common.machine_note()}). The needle's loads and "
            "constraint spread uniformly across a band of width w about the track (patched in for the runs; w = 0 "
            "is the package's line needle); `+ contact k=K`: with the needle's body holding the entry's free edge off "
            "(EntryContact: a penalty K mu t per point spacing / particle spacing on the edge's gap to the needle's side); "
            "soft_t3 / soft_t2.5: configs/sh12_100x100.yaml as a neo-Hookean slab 3 / "
            "2.5 mm thick; h the file's spacings (0.888 mm at the needle).", "",
            common.markdown_table(["scene", "needle", "level", "needle spacing (mm)", "points across",
                                   "exit error (mm)", "entry edge: least stretch", "turn (deg)",
                                   "its sides apart (mm)", "seconds"],
                                  [[row["scene"], variant(row), row["level"], row["needle_spacing_mm"],
                                    row["across"] or "—", row["exit_error_mm"] or failure_text(row),
                                    row["edge_least_stretch"], row["edge_turn_deg"], row["flank_gap_mm"],
                                    row["seconds"]] for row in rows]), "",
            "The entry's edge (within exit_components.EDGE_SPAN of the entry) where the run ended: its least stretch, "
            "how far its tangent turns, and the least distance between two of its points more than "
            f"{entry_newton.FLANK_SEPARATION:g} mm apart along it (its two sides, drawn along the needle).", "",
            "Per scene and needle, from the coarsest level: the change to the next (the criterion: < 2 %), "
            "whether the three levels are monotone and their observed rate (spacing ratio 2):", "",
            common.markdown_table(["scene", "needle", "levels", "change to the next (%)", "monotone", "rate"],
                                  [[scene, name, "needle spacing 0.6 / 0.3 / 0.15 mm" if resolved else "h, h/2, h/4",
                                    *ladder(group)] for (scene, name, resolved), group in series(rows).items()]),
            "", *reading(rows), ""]
    return "\n".join(text) + "\n"


def short_stop(row: dict) -> str:
    """A stopped run in a few words: its step, the load carried, the least stiffness's fall
    and the entry's edge there."""
    text = row["failure"]
    step = re.match(r"step (\d+) \(needle rotation ([\d.]+) rad\)", text)
    held = re.search(r"(\d+) % of the step's cutting force", text)
    fell = re.search(r"fell to (\d+) % of the step's start", text)
    words = (f"stops at step {step.group(1)} ({held.group(1)} % of its load carried" if step and held
             else f"stops ({text.split(': ')[0]}")
    words += f"; least stiffness {fell.group(1)} % of the step's start" if fell else ""
    inverted = re.search(r"det F = (\S+) at (\([^)]+\)) mm", text)
    words += f"; det F = {inverted.group(1)} at {inverted.group(2)} mm" if inverted else ""
    return (words + f"; the entry's edge turning {float(row['edge_turn_deg']):.0f} deg, its sides "
            f"{1000 * float(row['flank_gap_mm']):.0f} um apart)")


def reading(rows: list[dict]) -> list[str]:
    """What the runs say, from their numbers."""
    groups = series(rows)

    def of(scene: str, name: str, resolved: bool = False) -> list[dict]:
        return groups.get((scene, name, resolved), [])

    def stop(group: list[dict]) -> str:
        stopped = [row for row in group if row["failure"]]
        return f"at {stopped[0]['level'].replace('needle spacing ', '')} it {short_stop(stopped[0])}" if stopped else ""

    line, band = of("soft_t2.5", "line"), of("soft_t2.5", "w = 0.6 mm")
    if not line or not band:
        return []
    change, monotone, rate = ladder(band)
    text = [f"Reading: on soft_t2.5 the band of w = 0.6 mm alone changes by {change} % from h to h/2 (line needle "
            f"{ladder(line)[0]} %; {stop(line)}) and carries the run at h/4 (h, h/2, h/4 monotone: {monotone}, "
            f"rate {rate})"]
    if stop(band):
        text.append(f"; {stop(band)}")
    wide = [(name, ladder(of("soft_t2.5", name))[0]) for name in ("w = 1.5 mm", "w = 3 mm") if of("soft_t2.5", name)]
    if wide:
        text.append(". Only bands wider than the needle move less from h to h/2 ("
                    + ", ".join(f"{name}: {value} %" for name, value in wide) + ")")
    resolved = of("soft_t2.5", "w = 0.6 mm", True)
    if resolved:
        text.append(f". With one particle spacing across the band at the coarsest level (0.6 mm) the change to "
                    f"half is {ladder(resolved)[0]} %, but {stop(resolved) or 'the finest runs'}")
    text.append(": the band bounds the line load's strain, yet below its width the entry's edge, nothing holding "
                "it off the needle, still folds along it, its sides closing to tens of um.")
    contact = of("soft_t2.5", "w = 0.6 mm + contact k=10")
    if contact:
        change, monotone, rate = ladder(contact)
        text.append(f" With the needle's body holding the entry's edge off (penalty 10) the change from h to h/2 is "
                    f"{change} %, h, h/2, h/4 monotone: {monotone} (rate {rate}: not yet settled)")
        text.append(f"; {stop(contact)}" if stop(contact) else ", and every level runs")
        at_h = [(penalty, [row for row in of("soft_t2.5", f"w = 0.6 mm + contact k={penalty}") if row["level"] == "h"])
                for penalty in ("1", "10", "100")]
        at_h = [(penalty, found[0]["exit_error_mm"]) for penalty, found in at_h if found and found[0]["exit_error_mm"]]
        if len(at_h) > 1:
            text.append(". The answer is the penalty's: at h the exit error is "
                        + ", ".join(f"{value} mm at penalty {penalty}" for penalty, value in at_h))
        stiff = of("soft_t2.5", "w = 0.6 mm + contact k=100")
        if stop(stiff):
            text.append(f", and with the stiffest {stop(stiff)}")
        others = [(scene, ladder(of(scene, "w = 0.6 mm + contact k=10"))) for scene in ("sh12_100x100", "soft_t3")
                  if of(scene, "w = 0.6 mm + contact k=10")]
        if others:
            text.append(". With the band and the contact (penalty 10) " + "; ".join(
                f"{scene} changes by {values[0]} % (monotone: {values[1]}, rate {values[2]})" for scene, values in others))
        exact = [(penalty, of("soft_t2.5", f"w = 0.6 mm + contact k={penalty} (augmented Lagrangian)"))
                 for penalty in ("10", "100")]
        exact = [(penalty, group) for penalty, group in exact if group]
        if exact:
            values = "; ".join(f"penalty {penalty}: " + ", ".join(row["exit_error_mm"] or "stops" for row in group)
                               for penalty, group in exact)
            group = exact[0][1]
            change, monotone, rate = ladder(group)
            done = [row for row in group if row["exit_error_mm"]]
            steps = np.diff([float(row["exit_error_mm"]) for row in done])
            trend = "growing, not converging" if len(steps) > 1 and abs(steps[-1]) > abs(steps[-2]) else "shrinking"
            both = [(float(a["exit_error_mm"]), float(b["exit_error_mm"])) for a, b in zip(*(group for _, group in exact))
                    if a["exit_error_mm"] and b["exit_error_mm"]]
            apart = max((abs(b / a - 1) for a, b in both), default=math.nan)
            last = done[-1]
            text.append(f". With the pressures raised until the edge stays out of the needle (augmented Lagrangian; an "
                        f"update Newton cannot follow made in halved moves) the answer no longer depends on the penalty "
                        f"where both run (within {100 * apart:.2f} %; {', '.join(level for level, _ in LEVELS)}, h/8 — "
                        f"{values} mm): {change} % from h to h/2, the levels run monotone: {monotone}, rate {rate} "
                        f"(steps {', '.join(f'{step:.3f}' for step in steps)} mm: {trend}); at {last['level']} the run ends with the entry's edge turning "
                        f"{float(last['edge_turn_deg']):.0f} deg, compressed to {float(last['edge_least_stretch']):.2f} "
                        f"of its length, its sides {1000 * float(last['flank_gap_mm']):.0f} um apart")
            text.append(f"; {stop(group)}" if stop(group) else "")
            if len(exact) > 1 and stop(exact[1][1]):
                text.append(f"; with penalty {exact[1][0]} {stop(exact[1][1])}")
            turns = ", ".join(f"{float(row['edge_turn_deg']):.0f}" for row in done)
            text.append(f". So the needle's width and its body's contact with the entry's edge delay the fold without "
                        f"removing it: the entry's edge is still drawn along the needle and folds tighter at every "
                        f"halving (its tangent turning {turns} deg from h to {last['level']}), and the exit error moves "
                        f"with it")
        text.append(". The runs with the contact that stop do so where the tissue has barely softened (the least "
                    "stiffness near 90 % of the step's start): in Newton, or with the material inverting at the entry's "
                    "edge.")
    return ["".join(text)]


def chart(rows: list[dict], path) -> None:
    """Exit error against the spacing at the needle per scene and needle; a run that stops
    marked by a dotted line at its spacing."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = (("sh12_100x100", lambda name, resolved: True),
              ("soft_t3", lambda name, resolved: True),
              ("soft_t2.5", lambda name, resolved: "contact" not in name and not resolved),
              ("soft_t2.5", lambda name, resolved: name in ("line", "w = 0.6 mm") or "contact" in name or resolved))
    figure, axes = plt.subplots(1, len(panels), figsize=(20, 6.2))
    for axis, (scene, shown) in zip(axes, panels):
        stops_at: dict[float, int] = {}  # labels already at a spacing: the next one drawn above them
        for (own_scene, name, resolved), group in series(rows).items():
            if own_scene != scene or not shown(name, resolved):
                continue
            done = [row for row in group if row["exit_error_mm"]]
            label = ("line needle (w = 0)" if name == "line" else name) + \
                (", needle spacing from 0.6 mm" if resolved else "")
            style = "s--" if resolved else "^-." if "contact" in name else "o-"
            lines = axis.semilogx([float(row["needle_spacing_mm"]) for row in done],
                                  [float(row["exit_error_mm"]) for row in done], style, label=label)
            for row in group:
                if row["failure"]:
                    spacing = float(row["needle_spacing_mm"])
                    axis.axvline(spacing, color=lines[0].get_color(), ls=":", lw=1.2)
                    height = 0.02 + 0.13 * stops_at.get(spacing, 0)
                    stops_at[spacing] = stops_at.get(spacing, 0) + 1
                    axis.text(spacing, height, " stops", transform=axis.get_xaxis_transform(),
                              fontsize=7, color=lines[0].get_color(), rotation=90, va="bottom", ha="right")
        spacings = sorted({float(row["needle_spacing_mm"]) for row in rows if row["scene"] == scene}, reverse=True)
        axis.set_xticks(spacings, [f"{spacing:g}" for spacing in spacings], fontsize=8)
        axis.minorticks_off()
        axis.invert_xaxis()
        axis.set_xlabel("particle spacing at the needle (mm)")
        axis.set_ylabel("unplanned exit error (mm)")
        axis.set_title(scene, fontsize=10)
        axis.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2)
    figure.suptitle("Exit error under refinement: the line needle, a band of width w, the band with the needle's body "
                    "in contact with the entry's edge (dotted: a run that stops)")
    common.save_figure(figure, path, (0, 0, 1, 0.94))
    plt.close(figure)


def main() -> None:
    """All RUNS; with `--missing` only those the CSV has no row for (appended); `--report`
    redraws the table and chart from the CSV."""
    path = common.results_path("needle_width.csv")
    arguments = sys.argv[1:]
    if "--report" not in arguments:
        kept = common.csv_rows(path) if "--missing" in arguments and path.exists() else []

        def key(scene: str, width: float, penalty: float, level: str, augmented: bool) -> tuple:
            return scene, f"{width:g}", f"{penalty:g}" if penalty else "", level, "yes" if augmented else ""

        have = {(row["scene"], row["width_mm"], row["contact_penalty"], row["level"], row["augmented"]) for row in kept}
        order = sorted((run_ for run_ in RUNS if key(*run_[:4], run_[5]) not in have),
                       key=lambda run_: run_[4])  # the slow, fine runs first
        with ProcessPoolExecutor(max_workers=2) as pool:
            finished = list(pool.map(run, *zip(*order))) if order else []
        by_run = {(row["scene"], row["width_mm"], row["contact_penalty"], row["level"], row["augmented"]): row
                  for row in kept + finished}
        rows = [by_run[key(*run_[:4], run_[5])] for run_ in RUNS]
        common.write_csv(path, COLUMNS, [[row[column] for column in COLUMNS] for row in rows])
    rows = common.csv_rows(path)
    common.publish("needle_width", report(rows), chart, rows)


if __name__ == "__main__":
    common.command_line(__doc__, ("--missing", "--report"))
    main()
