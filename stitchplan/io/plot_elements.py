"""Pieces every figure draws the same way: the tissue outline at rest and deformed, clamped
edges hatched, loads as arrows on their segments, probes, one colour scale per figure,
legends below the data and log axes labelled with plain numbers.

Points are (n, 2) arrays in mm; the figures themselves live in `plots`.
"""

from __future__ import annotations

import itertools
import math
import re
from collections.abc import Callable

import numpy as np

REST = {"color": "0.45", "ls": "--", "lw": 0.9}
DEFORMED = {"color": "black", "lw": 1.3}
FORCE_COLOUR, DISPLACEMENT_COLOUR = "tab:red", "tab:purple"
CMAP = "viridis"

# The PNGs' resolution. Figures are made at it, not at matplotlib's default 100: what a plot
# function measures before saving (a label's room, a legend's place) is measured as it is
# drawn, text at 7-8 pt being relatively wider at 120 dpi than at 100 (hinting).
SAVED_DPI = 120


def pyplot():
    """matplotlib.pyplot on the file-only Agg backend (imported on first use)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def literal(text: str) -> str:
    """A user's text (a name, a file name) as a figure shows it: matplotlib reads what lies
    between two `$` as mathtext, and a lone one failed the figure, so each is escaped."""
    return text.replace("$", r"\$")


# --- the tissue outline ---------------------------------------------------------------------


def outline_loops(domain) -> list[np.ndarray]:
    """Closed reference outlines, outer first then holes; each (k, 2) vertices, first not
    repeated. A domain with an `outline` polygon (and `holes` polygons) gives those; the
    rectangle its four corners."""
    outline = getattr(domain, "outline", None)
    if outline is not None:
        loops = [np.asarray(outline, dtype=float)]
        for hole in getattr(domain, "holes", ()) or ():
            vertices = np.asarray(getattr(hole, "vertices", hole), dtype=float)
            if vertices.ndim == 2 and len(vertices) >= 3:
                loops.append(vertices)
        return loops
    w, h = domain.size
    return [np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])]


def _closed(loop: np.ndarray) -> np.ndarray:
    return np.vstack([loop, loop[:1]])


def _along_loop(points: np.ndarray, loop: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance of each point (n, 2) to the closed polygon `loop` and the arc length of its
    nearest polygon point, measured from the first vertex."""
    distance = np.full(len(points), np.inf)
    arc = np.zeros(len(points))
    start_length = 0.0
    closed = _closed(loop)
    for a, b in itertools.pairwise(closed):  # the polygon's edges: a handful
        edge = b - a
        length = float(np.hypot(*edge))
        if length == 0.0:
            continue
        t = np.clip((points - a) @ edge / length**2, 0.0, 1.0)  # (n,)
        d = np.linalg.norm(points - (a + t[:, None] * edge), axis=1)
        closer = d < distance
        distance[closer] = d[closer]
        arc[closer] = start_length + t[closer] * length
        start_length += length
    return distance, arc


def deformed_loops(domain, particles: np.ndarray, displacement: np.ndarray,
                   scale: float = 1.0) -> list[np.ndarray]:
    """The deformed outline: the particles on each reference loop and the loop's vertices, in
    order along it, moved by `scale` x the displacement (the RK interpolant at the particles,
    linear along the loop between them at the vertices: a circular hole's wall carries a
    particle one spacing apart, not one at each of its vertices, and its outline stays round);
    closed polylines."""
    extent = float(np.ptp(particles, axis=0).max()) or 1.0
    loops = []
    for loop in outline_loops(domain):
        distance, arc = _along_loop(particles, loop)
        on = distance <= 1e-6 * extent
        if on.sum() < 3:
            continue
        lengths = np.linalg.norm(np.diff(_closed(loop), axis=0), axis=1)
        perimeter, vertex_arc = float(lengths.sum()), np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
        order = np.argsort(arc[on], kind="stable")
        along, moved_by = arc[on][order], displacement[on][order]
        at_vertices = np.column_stack([np.interp(vertex_arc, along, moved_by[:, i], period=perimeter)
                                       for i in range(2)])
        points = np.vstack([particles[on][order], loop])
        moved = points + scale * np.vstack([moved_by, at_vertices])
        loops.append(_closed(moved[np.argsort(np.concatenate([along, vertex_arc]), kind="stable")]))
    return loops


def draw_outline(ax, domain, particles: np.ndarray | None = None, displacement: np.ndarray | None = None,
                 scale: float = 1.0, deformed_label: str = "tissue outline, deformed") -> None:
    """Reference outline dashed grey; with `displacement`, the deformed outline solid black."""
    for k, loop in enumerate(outline_loops(domain)):
        ax.plot(*_closed(loop).T, **REST, label="tissue at rest" if k == 0 else None)
    if displacement is not None:
        for k, loop in enumerate(deformed_loops(domain, particles, displacement, scale)):
            ax.plot(*loop.T, **DEFORMED, label=deformed_label if k == 0 else None)


REGION_COLOURS = ("tab:orange", "tab:cyan", "tab:pink", "tab:olive", "tab:brown")


def draw_regions(ax, tissue) -> None:
    """Material regions at rest: a light fill and a dotted edge each, labelled with their
    material law and moduli (the first region holding a point gives its material, so later ones are drawn
    underneath), clipped to the tissue (a region may reach past it)."""
    from matplotlib.patches import PathPatch, Polygon
    from matplotlib.path import Path as DrawnPath

    regions = getattr(tissue, "regions", ()) or ()
    if not regions:
        return
    outer, *holes = outline_loops(tissue.domain)
    loops = [_closed(loop) for loop in (outer, *(hole[::-1] for hole in holes))]  # holes the other way
    codes = [np.r_[DrawnPath.MOVETO, np.full(len(loop) - 2, DrawnPath.LINETO), DrawnPath.CLOSEPOLY]
             for loop in loops]
    inside = PathPatch(DrawnPath(np.concatenate(loops), np.concatenate(codes)), transform=ax.transData)
    for k in range(len(regions) - 1, -1, -1):
        region = regions[k]
        colour = REGION_COLOURS[k % len(REGION_COLOURS)]
        material = region.material
        patch = ax.add_patch(Polygon(region.vertices(), closed=True, facecolor=colour,
                                     alpha=0.15, edgecolor=colour, ls=":", lw=1.2, zorder=0.5,
                                     label=f"region {k} (at rest): {material.model}, lambda "
                                           f"{material.lame_lambda:g}, mu {material.lame_mu:g} MPa"))
        patch.set_clip_path(inside)


# --- boundary conditions --------------------------------------------------------------------


def clamped_segments(tissue) -> list[tuple[np.ndarray, np.ndarray]]:
    """End points of every clamped piece of the boundary: named edges or `segment`s."""
    pieces = []
    for item in tissue.clamped:
        if isinstance(item, str):
            pieces.append(tissue.domain.edge(item))
        else:
            start, end = getattr(item, "segment", item)
            pieces.append((np.asarray(start, dtype=float), np.asarray(end, dtype=float)))
    return pieces


def outward_normal(domain, start, end) -> np.ndarray:
    """Unit normal of the boundary segment start-end pointing out of the tissue."""
    start, end = np.asarray(start, dtype=float), np.asarray(end, dtype=float)
    direction = end - start
    normal = np.array([direction[1], -direction[0]]) / np.hypot(*direction)
    extent = max(domain.size) if hasattr(domain, "size") else np.hypot(*direction)
    ahead = 0.5 * (start + end) + 1e-3 * extent * normal
    return normal if not bool(domain.contains(ahead)) else -normal


def draw_clamps(ax, tissue, width: float) -> None:
    """Clamped edges: a hatched strip `width` mm wide outside the tissue along each. Call it
    after the limits are set: strips outside the view are left out (and out of the legend)."""
    from matplotlib.patches import Polygon

    (x0, x1), (y0, y1) = sorted(ax.get_xlim()), sorted(ax.get_ylim())
    shown = 0
    for start, end in clamped_segments(tissue):
        n = width * outward_normal(tissue.domain, start, end)
        strip = np.array([start, end, end + n, start + n])
        low, high = strip.min(axis=0), strip.max(axis=0)
        if high[0] < x0 or low[0] > x1 or high[1] < y0 or low[1] > y1:
            continue
        ax.add_patch(Polygon(strip, closed=True, fill=False, hatch="////", edgecolor="0.3", lw=0.0,
                             label="clamped edge" if shown == 0 else None))
        ax.plot([start[0], end[0]], [start[1], end[1]], "-", color="0.3", lw=2.0)
        shown += 1


def draw_loads(ax, loads, domain, arrow: float, move: Callable[[np.ndarray], np.ndarray] | None = None,
               ) -> np.ndarray:
    """Each load's segment drawn thick (red: force, purple: prescribed displacement) where
    `move` puts its points (default: at rest), and an arrow `arrow` mm long at its middle in
    the load's direction, outside the tissue, labelled with its size. Returns the end points
    of the arrows (k, 2), so the caller can keep them in the frame."""
    move = move or (lambda points: points)
    ends, labelled = [], set()
    for k, load in enumerate(loads):
        start, end = (np.asarray(p, dtype=float) for p in load.segment)
        points = move(start + np.linspace(0.0, 1.0, 21)[:, None] * (end - start))  # (21, 2)
        is_force = load.force is not None
        vector = np.asarray(load.force if is_force else load.displacement, dtype=float)
        colour = FORCE_COLOUR if is_force else DISPLACEMENT_COLOUR
        kind = "load: force (N, total)" if is_force else "load: prescribed displacement (mm)"
        ax.plot(*points.T, "-", color=colour, lw=3.5, solid_capstyle="butt", zorder=3,
                label=None if kind in labelled else kind)
        labelled.add(kind)
        size = float(np.hypot(*vector))
        middle = points[len(points) // 2]
        if size == 0.0:
            continue
        direction = vector / size
        outward = outward_normal(domain, start, end)
        away = direction if direction @ outward >= 0.0 else -direction  # the side outside the tissue
        # a hole or notch may leave no room outside for the arrow and its label (about 2.3
        # arrows wide): the arrow then stays within the gap and the label sits on the tissue's
        # side of its own segment, not beside the gap's other edge
        length, label_away = arrow, away
        free = _free_length(domain, middle, away, (1.0 + LABEL_ROOM) * arrow)
        if free < (1.0 + LABEL_ROOM) * arrow:
            length, label_away = 0.4 * free, -away
        if away is direction:  # pulling: the arrow leaves the segment
            tail, head = middle, middle + length * direction
        else:  # pushing: the arrow arrives at the segment from outside
            tail, head = middle - length * direction, middle
        at = middle + length * away if label_away is away else middle
        ax.annotate("", xy=head, xytext=tail,
                    arrowprops={"arrowstyle": "-|>", "color": colour, "lw": 2.0, "mutation_scale": 14}, zorder=4)
        unit = "N" if is_force else "mm"
        text = f"{'F' if is_force else 'u'}{k + 1} = ({vector[0]:.3g}, {vector[1]:.3g}) {unit}"
        ha = "right" if label_away[0] < -0.3 else "left" if label_away[0] > 0.3 else "center"
        va = "top" if label_away[1] < -0.3 else "bottom" if label_away[1] > 0.3 else "center"
        ax.annotate(text, at, xytext=6 * label_away, textcoords="offset points", fontsize=8, color=colour,
                    ha=ha, va=va, zorder=5, bbox={"boxstyle": "round", "fc": "white", "ec": colour, "alpha": 0.9})
        room = ({"right": -LABEL_ROOM, "left": LABEL_ROOM, "center": 0.0}[ha],
                {"top": -0.6, "bottom": 0.6, "center": 0.0}[va])
        reach = at + arrow * np.asarray(room)  # room for the label
        ends += [tail, head, reach]
    return np.asarray(ends).reshape(-1, 2)


LABEL_ROOM = 2.3  # a load label's width, in arrows


def _free_length(domain, start: np.ndarray, direction: np.ndarray, reach: float, samples: int = 200) -> float:
    """How far (mm, at most `reach`) the ray from boundary point `start` along `direction`
    runs outside the tissue before it meets it again (across a hole or a notch)."""
    t = reach * (np.arange(1, samples + 1) / samples)
    inside = np.asarray(domain.contains(start + t[:, None] * direction), dtype=bool)
    inside[t < 1e-3 * reach] = False  # the segment's own edge
    return float(t[np.argmax(inside)]) if inside.any() else reach


def draw_probes(ax, reference: np.ndarray, displaced: np.ndarray | None = None, size: float | None = None) -> None:
    """Probes: open circle at rest, filled where they moved to, joined; numbered P1, P2, ...,
    each number set off away from the probes within 8 % of `size` (mm, the tissue's larger
    side) of it, so that probes round a small hole keep their numbers apart."""
    if len(reference) == 0:
        return
    ax.plot(*reference.T, "o", mfc="none", mec="black", ms=7, mew=1.2, zorder=4, label="probe at rest")
    where = reference
    if displaced is not None:
        for a, b in zip(reference, displaced):
            ax.plot([a[0], b[0]], [a[1], b[1]], "-", color="black", lw=0.8, zorder=4)
        ax.plot(*displaced.T, "o", color="white", mec="crimson", ms=6, mew=1.8, zorder=4,
                label="probe, displaced")
        where = displaced
    for k, (point, direction) in enumerate(zip(where, _label_directions(where, size))):
        ax.annotate(f"P{k + 1}", point, xytext=7.0 * direction, textcoords="offset points", fontsize=8,
                    color="crimson", fontweight="bold", ha=_alignment(direction[0], "left", "right"),
                    va=_alignment(direction[1], "bottom", "top"))


def _label_directions(points: np.ndarray, size: float | None) -> np.ndarray:
    """Unit directions (n, 2) to set each point's label off in: up and right, or away from the
    points within 8 % of `size` of it (weighted by 1 / distance, nearest most)."""
    directions = np.tile([np.sqrt(0.5), np.sqrt(0.5)], (len(points), 1))
    if size is None or len(points) < 2:
        return directions
    apart = points[:, None, :] - points[None, :, :]  # (n, n, 2): from each other point to this one
    distance = np.linalg.norm(apart, axis=2)
    near = (distance > 0.0) & (distance < 0.08 * size)
    away = np.where(near[..., None], apart / np.where(near, distance**2, 1.0)[..., None], 0.0).sum(axis=1)
    length = np.linalg.norm(away, axis=1)
    crowded = length > 0.0
    directions[crowded] = away[crowded] / length[crowded, None]
    return directions


def _alignment(component: float, positive: str, negative: str) -> str:
    """A label's alignment along one axis for a set-off direction's component there."""
    return positive if component > 0.38 else negative if component < -0.38 else "center"


# --- scales, legends, axes -----------------------------------------------------------------


def magnitude_norm(*fields: np.ndarray):
    """One colour scale for |u| over all the (n, 2) displacement fields a figure shows."""
    from matplotlib.colors import Normalize

    top = max((float(np.linalg.norm(f, axis=-1).max()) for f in fields if f.size), default=0.0)
    return Normalize(vmin=0.0, vmax=top if top > 0 else 1.0)


def legend_below(fig, axes, columns: int = 4, gap: float = 0.01, **options):
    """One legend for the figure, just under the lowest of `axes` (their tick labels
    included), with the entries of all of them once each."""
    handles, labels = [], []
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            if label not in labels and not label.startswith("_"):
                handles.append(handle)
                labels.append(label)
    renderer = fig.canvas.get_renderer()  # the boxes lay out what they measure: no draw needed
    boxes = np.array([fig.transFigure.inverted().transform(ax.get_tightbbox(renderer).get_points())
                      for ax in axes])  # (n_axes, 2 corners, 2)
    middle = 0.5 * (boxes[:, 0, 0].min() + boxes[:, 1, 0].max())
    return fig.legend(handles, labels, loc="upper center", bbox_to_anchor=(middle, boxes[:, 0, 1].min() - gap),
                      ncol=columns, fontsize=8, frameon=False, **options)


def title_above(fig, axes, text: str, gap: float = 0.015, fontsize: float = 10):
    """The figure's title just above the highest of `axes` (their titles included). The
    axes' tight boxes apply their aspect and lay out their ticks and titles themselves, so no
    draw of the whole figure comes first (each cost as much as the PNG's own two)."""
    renderer = fig.canvas.get_renderer()
    tops = [fig.transFigure.inverted().transform(ax.get_tightbbox(renderer).get_points())[1, 1]
            for ax in axes]
    return fig.suptitle(text, y=max(tops) + gap, va="bottom", fontsize=fontsize)


def readable_log_axis(axis) -> None:
    """Log axis ticks as plain numbers (0.03, 0.5, 2) instead of 3 x 10^-2; minor ticks
    labelled (at 2 and 5 over more than a decade, 2, 3, 5 or more on a shorter axis) only
    when fewer than two powers of ten are in view. Call it once the limits are final."""
    from matplotlib.ticker import FuncFormatter, NullFormatter

    def plain(value, _position=None):
        text = f"{value:.3g}"
        if "e+" in text and abs(value) < 1e6:  # .3g writes 1000 as 1e+03
            text = np.format_float_positional(float(value), precision=3, fractional=False, trim="-")
        return text

    low, high = sorted(axis.get_view_interval())
    axis.set_major_formatter(FuncFormatter(plain))
    if low <= 0:
        return
    powers = math.floor(math.log10(high)) - math.ceil(math.log10(low)) + 1  # labelled major ticks
    if powers >= 2:
        axis.set_minor_formatter(NullFormatter())
        return
    span = math.log10(high / low)
    # over more than a decade 2 and 3 stand too close for labels like 0.0002 (they ran together)
    leads = ((2, 5) if span > 1.0 else (2, 3, 5) if span > 0.5 else (2, 3, 4, 5, 6, 8) if span > 0.3
             else tuple(range(1, 10)))

    def some(value, _position=None):
        lead = round(value / 10 ** math.floor(math.log10(value) + 1e-9))
        return plain(value) if lead in leads else ""

    axis.set_minor_formatter(FuncFormatter(some))


def label_with_multiplier(axis, quantity: str, unit: str) -> None:
    """The axis label `quantity (unit)`, or `quantity (x 10^k unit)` where the tick labels
    are scaled by 10^k: matplotlib's own `1e-3` at the axis' end stands apart from the label
    and reads as a note, the ticks as millimetres. Call it once the limits are final."""
    from matplotlib.ticker import ScalarFormatter

    formatter = ScalarFormatter(useOffset=False)
    formatter.set_powerlimits((-2, 3))
    axis.set_major_formatter(formatter)
    formatter.set_locs(axis.get_majorticklocs())  # the scaling for these ticks
    # its offset text ("1e-3", a Unicode minus where axes.unicode_minus) names the power: the
    # orderOfMagnitude attribute is deprecated since matplotlib 3.11
    scaled = re.search(r"e([-\u2212+]?\d+)", formatter.get_offset())
    power = int(scaled.group(1).replace("\u2212", "-")) if scaled else 0
    if power:
        axis.offsetText.set_visible(False)
        axis.set_label_text(rf"{quantity} ($\times 10^{{{power}}}$ {unit})")
    else:
        axis.set_label_text(f"{quantity} ({unit})")


def frame(ax, points: np.ndarray, margin: float = 0.06, floor: float = 0.0) -> None:
    """Limits that hold all `points` (n, 2) with a margin of the larger side, equal aspect."""
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    points = points[np.all(np.isfinite(points), axis=1)]
    low, high = points.min(axis=0), points.max(axis=0)
    pad = max(margin * float((high - low).max()), floor)
    ax.set_xlim(low[0] - pad, high[0] + pad)
    ax.set_ylim(low[1] - pad, high[1] + pad)
    ax.set_aspect("equal")


def label_mm(ax) -> None:
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
