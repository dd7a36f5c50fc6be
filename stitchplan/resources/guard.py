"""The guard: refuses runs past the limits, in one line each naming the setting that lowers the cost."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, replace

from ..config import DEFAULT_NEEDLE_REFINEMENT
from ..config.blocks import coarsest_spacing
from ..errors import InputError
from .costs import (BASE_MEMORY, HELD_RUNS, REFERENCE_NEIGHBOURS, REFERENCE_POINTS_PER_PARTICLE, Data, Estimate,
                    condition_particles_within, held_at_once, held_in_one_process, size_scale)
from .formatting import amount_text, bytes_text, count_text, duration_text
from .limits import Limits
from .machine import (ADDRESS_GROWTH, ADDRESS_SPACE_RESERVE, address_space, address_space_needed, available_memory,
                      memory_within_address_space)
from .model_size import capped_count

CONDITION_OPTION = "--condition-numbers"

log = logging.getLogger(__package__)  # "stitchplan.resources", the name its records carry

# runs estimated longer than this are announced by a warning line before they start (the
# time is a guide: benchmarks/results/resource_costs.md)
LONG_RUN_SECONDS = 600.0
# what lifts each limit: --max-particles raises the particle limit only; nothing but
# skipping the guard passes the memory share
OVERRIDE = "raise --max-particles or pass --no-resource-check to run it anyway"
SKIP_GUARD = "pass --no-resource-check to run it anyway"


def check_resources(estimates: list[Estimate], limits: Limits = Limits(),
                    memory: float | None = None, alongside: list[Estimate] | None = None,
                    forked: bool = True, workers: int | None = None,
                    space: tuple[float, float] | None = None, in_one_process: bool = False,
                    beside: list[Estimate] = (), data: Data | None = None) -> None:
    """Refuse (InputError, one line per limit passed) runs beyond the limits; log the
    estimates otherwise. `memory`: bytes available (default: available_memory()).

    `alongside`: runs that go on at the same time as `estimates`, in other processes but for
    the predicted aim's (a command's replays at twice the spacing: the exit error estimate's
    in a helper process, the predicted aim's in this one, counted as a helper's; the sampled
    plans on local Dask workers), counted only in the memory all of them hold at once.
    Given (even empty), the runs of `estimates` are taken to
    go on at once too, and their memory together must stay within the share
    (_together_refusal): each within it alone still leaves the machine short when two or
    three hold as much (a plan at a small needle step: its own passes, its verification's
    replays and the predicted aim's each keep their steps' states). `forked`: the processes
    of `alongside` are this command's helpers (HELPER_BASE_MEMORY of an interpreter each: the
    libraries' pages shared), not Dask workers (a whole interpreter each). `workers`: the runs of `estimates` go on in
    this many worker processes, one each at a time and none in this process (a study's on a
    local cluster): the largest `workers` of them are counted together, beside this process's
    interpreter (BASE_MEMORY). `space`: (the address-space limit, what the process maps now)
    in bytes (default: machine.address_space(), None without a limit): a run of this process
    that needs more address space than the limit allows (machine.address_space_needed) is
    refused naming the limit. `in_one_process`: the runs of `estimates` are held at once in this
    process (costs.held_in_one_process: a material calibration's experiments), together
    within the memory share and the address-space limit. `beside`: runs held with them in this
    process that count only in that memory, with no refusal line of their own (a calibration's
    discretization estimate, each experiment refitted at twice the spacing: smaller than the
    fit's models, whose lines name the same settings, and one too coarse for the tissue is not
    made, the calibration recording its estimate as not made, rather than refusing the fit).
    `data`: measured data held with the runs of `in_one_process` (a calibration's markers),
    refused naming its file where the runs would fit without it (_data_refusal)."""
    memory = available_memory() if memory is None else memory
    space = address_space() if space is None else space
    lines = []
    for item in estimates:
        size, what = item.size, f"estimated {item.describe()}"
        too_many_steps = item.needle_step is not None and item.steps > limits.max_needle_steps
        too_long = item.condition_seconds > limits.max_condition_seconds
        if size.neighbours > limits.max_neighbours:
            most = math.sqrt(limits.max_neighbours) / 2.0
            lines.append(f"{item.origin.name('dilation')}: got {item.discretization.dilation:g}, expected at "
                         f"most {most:g} (a kernel support of {amount_text(size.neighbours)} particles per point, "
                         f"at most {limits.max_neighbours}; RKPM uses 1.5-3)")
        elif size.particles > limits.max_particles:
            lines.append(_particles_refusal(item, limits.max_particles))
        elif memory is not None and item.memory_bytes > limits.memory_share * memory:
            setting = _memory_setting(item, limits.memory_share * memory)
            # the step limit's and the condition numbers' lines below name these
            if not (setting.name == item.origin.name("step", "needle.step") and too_many_steps or setting.name == CONDITION_OPTION and too_long):
                lines.append(_memory_refusal(item, setting, limits.memory_share, memory))
        elif space is not None and workers is None and \
                address_space_needed(space[1], item.memory_bytes, BASE_MEMORY) > space[0]:
            lines.append(_address_space_refusal(item, *space))
        coarse = _coarse_refusal(item)
        if coarse is not None:
            lines.append(coarse)
        if too_many_steps:
            lines.append(f"{item.origin.name('step', 'needle.step')}: got {item.needle_step:g} rad, expected a step "
                         f"giving at most {limits.max_needle_steps} needle steps ({what}); take a larger step, or pass "
                         "--no-resource-check")
        if too_long and not too_many_steps:  # fewer steps are the way under both
            lines.append(_condition_refusal(item, limits.max_condition_seconds))
    together = estimates if workers is None else sorted(estimates, key=lambda item: -item.memory_bytes)[:workers]
    held = [*together, *(alongside or [])]
    here = 0.0 if workers is None else BASE_MEMORY
    if not lines and alongside is not None and memory is not None and (len(held) > 1 or workers is not None) \
            and here + held_at_once([item.memory_bytes for item in held], forked) > limits.memory_share * memory:
        lines.append(_together_refusal(held, limits.memory_share, memory, forked, here))
    if in_one_process and not lines and estimates:
        held_here = [*estimates, *beside]
        total = held_in_one_process([item.memory_bytes for item in held_here])
        largest = max(held_here, key=lambda item: item.memory_bytes)
        if memory is not None and total > limits.memory_share * memory:
            lines.append(_together_refusal(held_here, limits.memory_share, memory, total=total))
        elif space is not None and address_space_needed(space[1], total, BASE_MEMORY) > space[0]:
            lines.append(_address_space_refusal(largest, *space, beside=total - largest.memory_bytes))
        elif data is not None:
            budget = data_budget(total, limits, memory, space)
            if budget is not None and data.memory_bytes > budget[0]:
                lines.append(_data_refusal(data, total, *budget, "the experiments' models"))
    if lines:
        lines = _one_per_field(lines)
        error = InputError("\n".join(lines))
        error.lines = lines
        raise error
    for item in estimates:
        log.info("resources: %s", item.describe())
        if item.seconds > LONG_RUN_SECONDS:  # a run this long should not start in silence
            log.warning("a long run: estimated %s; -v shows its progress", item.describe())
    for item in [*(alongside or []), *beside]:  # no longer than the runs they go with: no warning of their own
        log.info("resources: %s", item.describe())
    if data is not None:
        log.info("resources: %s", data.describe())


def data_budget(held: float, limits: Limits, memory: float | None = None,
                space: tuple[float, float] | None = None) -> tuple[float, str] | None:
    """(bytes, the limit as a refusal says it) that measured data may take beside `held` bytes
    (the interpreter's BASE_MEMORY included) within the memory share and the address-space
    limit (defaults as check_resources's), the tighter of the two; None where neither is known."""
    memory = available_memory() if memory is None else memory
    space = address_space() if space is None else space
    budgets = []
    if memory is not None:
        budgets.append((limits.memory_share * memory - held,
                        f"within {limits.memory_share:.0%} of the {bytes_text(memory)} of memory available"))
    if space is not None:
        limit, mapped = space
        budgets.append((memory_within_address_space(limit, mapped, BASE_MEMORY) - held,
                        f"within the memory the process's address-space limit of {bytes_text(limit)} (ulimit -v "
                        f"{limit / 1024:.0f}) leaves it"))
    return min(budgets, key=lambda budget: budget[0], default=None)


def items_within(bytes_per_item: float, budget: float) -> int:
    """The items of `bytes_per_item` that `budget` bytes hold (none below zero)."""
    return max(int(budget // bytes_per_item), 0)


def _data_refusal(data: Data, held: float, budget: float, within: str, models: str) -> str:
    """The line refusing data whose items take more than `budget` bytes beside the `held` bytes
    of `models` (and the interpreter): the file, its items, and how many would fit."""
    total = f" ({data.total} {data.others})" if data.total != data.count else ""
    return (f"{data.name}: got {data.count} {data.unit}{total}, expected at most "
            f"{items_within(data.bytes_per_item, budget)} {data.unit}{f' {data.others}' if data.others else ''} {within} (~"
            f"{bytes_text(data.bytes_per_item)} each beside ~{bytes_text(held)} for {models}); {data.advice}, or "
            f"{SKIP_GUARD}")


def _one_per_field(lines: list[str]) -> list[str]:
    """The first refusal of each field or option (what precedes ': got'): the runs of one
    command (a study's families, a plan's replays) refused for one setting say it once."""
    seen, kept = set(), []
    for line in lines:
        name = line.split(": got ", 1)[0] if ": got " in line else line
        if name not in seen:
            seen.add(name)
            kept.append(line)
    return kept


@dataclass(frozen=True)
class Setting:
    """What a refusal names: the field or option, the value it got, what it should give
    (completed by "at most N particles"), how to lower the cost by it, and how it reaches
    the model (ends in "; " when given)."""

    name: str
    got: str
    expected: str
    advice: str
    note: str = ""


def _particles_refusal(item: Estimate, limit: int) -> str:
    setting = _particle_setting(item, lambda particles: particles <= limit)
    particles = "particle" if limit == 1 else "particles"
    return (f"{setting.name}: got {setting.got}, expected {setting.expected} at most {limit} {particles}"
            f"{item.origin.derived} ({setting.note}estimated {item.describe()}); {setting.advice}, "
            f"{_skip(item)}or {OVERRIDE}")


def _memory_refusal(item: Estimate, setting: Setting, share: float, memory: float) -> str:
    return (f"{setting.name}: got {setting.got}, expected a model within {share:.0%} of the {bytes_text(memory)} of "
            f"memory available{item.origin.derived} ({setting.note}estimated {item.describe()}); "
            f"{setting.advice}, {_skip(item)}or {SKIP_GUARD}")


def _address_space_refusal(item: Estimate, limit: float, mapped: float, beside: float = 0.0) -> str:
    """The line refusing a run that fits the machine's memory but not the process's address-space
    limit (a run short of address space crashes or hangs): the setting that drives the model
    past what the limit leaves, as a memory refusal names it, where a model would fit at all;
    else the limit itself, what to change. `beside`: bytes the runs held with it in the
    process take (check_resources `in_one_process`)."""
    needed = address_space_needed(mapped, item.memory_bytes + beside, BASE_MEMORY)
    budget = memory_within_address_space(limit, mapped, BASE_MEMORY) - beside
    others = f" beside the ~{bytes_text(beside)} of the runs held with it" if beside else ""
    if budget > BASE_MEMORY:
        setting = _memory_setting(item, budget)
        return (f"{setting.name}: got {setting.got}, expected a model within the ~{bytes_text(budget)} of memory the "
                f"process's address-space limit of {bytes_text(limit)} (ulimit -v {limit / 1024:.0f}) leaves it{others}"
                f"{item.origin.derived} ({setting.note}estimated {item.describe()}); {setting.advice}, raise the "
                f"limit (ulimit -v {math.ceil(needed / 1024)}), {_skip(item)}or {SKIP_GUARD}")
    arrays = max(item.memory_bytes - BASE_MEMORY, 0.0) + beside
    return (f"ulimit -v: got {limit / 1024:.0f} (the process's address-space limit of {bytes_text(limit)}; "
            f"{bytes_text(mapped)} mapped now), expected at least ~{bytes_text(needed)} for this "
            f"run{' and the runs held with it' if beside else ''}{item.origin.derived} "
            f"({ADDRESS_GROWTH:g} x its ~{bytes_text(arrays)} of arrays, and {bytes_text(ADDRESS_SPACE_RESERVE)} of "
            f"libraries and buffers beyond the numerics' imports; estimated {item.describe()}); raise the limit "
            f"(ulimit -v {math.ceil(needed / 1024)}), {_skip(item)}or {SKIP_GUARD}")


def _together_refusal(held: list[Estimate], share: float, memory: float, forked: bool = True,
                      here: float = 0.0, total: float | None = None) -> str:
    """The line refusing runs that each fit the memory share but not all at once: it names
    what drives the largest (what it could take, with the others' models left out of the
    share) and lists every run's estimate, and `here`, the bytes this process holds beside
    them when it runs none of them. The others follow the same fields (a spacing, a needle
    step), so what lowers the largest lowers them too."""
    largest = max(held, key=lambda item: item.memory_bytes)
    if total is None:  # given where they are held in one process (check_resources `in_one_process`)
        total = here + held_at_once([item.memory_bytes for item in held], forked)
    # what the largest may take with the others' models beside it: a larger needle step
    # lowers what every run keeps of its steps, so theirs count without it
    others_kept = sum(item.step_memory for item in held) - largest.step_memory
    setting = _memory_setting(largest, share * memory - (total - largest.memory_bytes - others_kept))
    skips = list(dict.fromkeys(item.origin.skip for item in held if item.origin.skip))
    skip = "".join(f"{advice}, " for advice in skips)
    runs = "; ".join([item.describe() for item in held] + ([f"this process: {bytes_text(here)}"] if here else []))
    return (f"{setting.name}: got {setting.got}, expected runs within {share:.0%} of the {bytes_text(memory)} of "
            f"memory available when they run at once ({setting.note}estimated ~{bytes_text(total)} "
            f"together: {runs}); "
            f"{setting.advice}, {skip}or {SKIP_GUARD}")


def _condition_refusal(item: Estimate, limit: float) -> str:
    """The line refusing a run whose dense condition numbers (simulate --condition-numbers) take
    longer than `limit` seconds: what they take a step, and the particles they would fit."""
    steps = item.steps * item.runs
    unknowns = count_text(capped_count(2.0 * item.size.particles))
    fitting = condition_particles_within(limit, steps)
    return (f"{CONDITION_OPTION}: got a dense saddle system of {unknowns} unknowns (2 x "
            f"{count_text(item.size.particles)} particles) in each of {count_text(item.steps)} needle steps, expected "
            f"condition numbers within {duration_text(limit)}{item.origin.derived} (~"
            f"{duration_text(item.condition_seconds / steps)} a step, ~{duration_text(item.condition_seconds)} in all; "
            f"estimated {item.describe()}); leave it out or coarsen {item.origin.name('spacing')} to at most "
            f"~{fitting:.0f} particles, or {SKIP_GUARD}")


def _coarse_refusal(item: Estimate) -> str | None:
    """The line refusing a model too coarse for its tissue or needle (the package's docstring), or
    None. A needle spacing that follows the spacing (needle_refinement, or no grading) is
    named as the spacing."""
    d, origin = item.discretization, item.origin
    spacing = origin.value("spacing", d.spacing)
    width, height = item.tissue_size
    if d.spacing > coarsest_spacing((width, height)):
        # the spacing as set (a study's at the needle) may differ from the model's coarse one
        coarse = "" if math.isclose(spacing, d.spacing) else f" (a coarse spacing of {d.spacing:.3g} mm)"
        return (f"{origin.name('spacing')}: got {spacing:g} mm{coarse}, expected at most half the tissue's smaller "
                f"side ({width:g} x {height:g} mm), so that at least three particles span it{item.origin.derived}; "
                f"refine it, {_skip(item)}or {SKIP_GUARD}")
    at_needle = d.spacing if d.needle_spacing is None else d.needle_spacing
    if item.needle_radius is None or at_needle <= item.needle_radius:
        return None
    if d.needle_spacing is not None and d.needle_refinement is None:
        name, got = origin.name("needle_spacing"), f"{origin.value('needle_spacing', d.needle_spacing):g} mm"
    else:
        name, got = origin.name("spacing"), f"{spacing:g} mm"
        if d.needle_spacing is not None:
            got += f" (a needle spacing of {at_needle:.3g} mm)"
    return (f"{name}: got {got}, expected a spacing at the needle of at most its radius, {item.needle_radius:g} mm, "
            f"so that the particles follow the needle's curve{item.origin.derived}; refine it, {_skip(item)}or "
            f"{SKIP_GUARD}")


def _skip(item: Estimate) -> str:
    return f"{item.origin.skip}, " if item.origin.skip else ""


def _particle_setting(item: Estimate, fits: Callable[[float], bool]) -> Setting:
    """What makes the particles too many for `fits`: the spacing, unless a uniform grid at
    the spacing would fit and the needle zone is refined past the default; then the needle
    zone's refinement or its own spacing."""
    d, origin = item.discretization, item.origin
    if item.coarse_particles is None or not fits(item.coarse_particles):
        return _spacing_setting(item)
    derived = d.needle_refinement is not None and math.isclose(d.needle_spacing, d.spacing / d.needle_refinement)
    if derived and d.needle_refinement <= DEFAULT_NEEDLE_REFINEMENT:
        return _spacing_setting(item)  # the default grading follows the spacing: coarsening it coarsens both
    if derived:
        spacing, refinement = origin.value("spacing", d.spacing), d.needle_refinement
        note = f"a needle spacing of {spacing:g} mm / {refinement:g} = {spacing / refinement:.3g} mm"
        if not math.isclose(spacing, d.spacing):  # a replay's (a plan's verification at half the spacing)
            note += f", the replay's {d.spacing:.4g} mm / {refinement:g} = {d.needle_spacing:.3g} mm"
        # a spacing set by an option (--spacing) scaled the needle's with it: coarsening it helps too
        remedy = f"lower it or coarsen {origin.name('spacing')}" if "spacing" in origin.names else "lower it"
        return Setting(origin.name("needle_refinement"), f"{refinement:g}", "a refinement giving", remedy,
                       f"{note}; ")
    return Setting(origin.name("needle_spacing"), f"{origin.value('needle_spacing', d.needle_spacing):g} mm",
                   "a needle spacing giving", "coarsen it")


def _spacing_setting(item: Estimate) -> Setting:
    d, origin = item.discretization, item.origin
    spacing = origin.value("spacing", d.spacing)
    if item.radius_default is not None:  # the file gives no spacing: the radius sets it
        width, height = item.tissue_size
        return Setting("needle.radius", f"{item.radius_default:g} mm",
                       f"a radius whose default particle spacing (here {spacing:.3g} mm) gives",
                       f"check that it and the tissue's size ({width:g} x {height:g} mm) are in mm, "
                       "or give discretization.spacing")
    if item.size_default is not None:  # the file gives no spacing: the tissue's size sets it
        width, height = item.tissue_size
        shape = "size" if item.size_default == "tissue.size" else "outline"
        got = f"[{width:g}, {height:g}] mm" if shape == "size" else f"an outline of {width:g} x {height:g} mm"
        return Setting(item.size_default, got,
                       f"a {shape} whose default particle spacing (here {spacing:.3g} mm) gives",
                       "check that it is in mm, or give discretization.spacing")
    return Setting(origin.name("spacing"), f"{spacing:g} mm", "a spacing giving", "coarsen it")


def _memory_setting(item: Estimate, budget: float) -> Setting:
    """What takes the memory past `budget`: the needle step when the run would fit without
    what it keeps of its steps (_step_memory); else the particles (as _particle_setting) when
    even a standard kernel (dilation 2, 2 x 2 Gauss points per particle) would pass it, else
    the larger of the kernel's two factors, its support (dilation) or its quadrature points."""
    size, d, origin = item.size, item.discretization, item.origin
    if item.condition_memory and item.memory_bytes - item.condition_memory <= budget:
        unknowns = count_text(capped_count(2.0 * size.particles))
        return Setting(CONDITION_OPTION, f"a dense saddle system of {unknowns} unknowns",
                       "", "leave it out or coarsen the spacing",
                       f"~{bytes_text(item.condition_memory)} of dense matrices for the condition numbers of "
                       f"{count_text(size.particles)} particles; ")
    if item.needle_step is not None and item.memory_bytes - item.step_memory <= budget:
        held = min(item.runs, HELD_RUNS)
        both = f", {bytes_text(item.step_memory)} for the {held:g} runs held at once" if held > 1 else ""
        return Setting(origin.name("step", "needle.step"), f"{item.needle_step:g} rad", "", "take a larger step",
                       f"{count_text(item.steps)} needle steps keep ~{bytes_text(item.step_memory / held)} of states "
                       f"and solver blocks until the run ends{both}; ")

    def fits_with_a_standard_kernel(particles: float) -> bool:
        standard = replace(size, particles=capped_count(particles),
                           neighbours=min(size.neighbours, REFERENCE_NEIGHBOURS),
                           points_per_particle=min(size.points_per_particle, REFERENCE_POINTS_PER_PARTICLE))
        return BASE_MEMORY + size_scale(standard)[0] <= budget

    if not fits_with_a_standard_kernel(size.particles):
        return _particle_setting(item, fits_with_a_standard_kernel)
    neighbours = size.effective_neighbours / REFERENCE_NEIGHBOURS
    points = size.points_per_particle / REFERENCE_POINTS_PER_PARTICLE
    if neighbours >= points:
        return Setting(origin.name("dilation"), f"{d.dilation:g}", "", "lower it (RKPM uses 1.5-3)",
                       f"a kernel support of {amount_text(size.effective_neighbours)} particles per point takes "
                       f"{neighbours:.3g} times the memory of dilation 2's {REFERENCE_NEIGHBOURS:g}; ")
    order, cells = d.quadrature_order, d.cells_per_spacing
    key, got = ("quadrature_order", order) if order * order / 4 >= cells * cells else ("cells_per_spacing", cells)
    return Setting(origin.name(key), f"{got}", "", "lower it",
                   f"{order} x {order} Gauss points in each of {cells} x {cells} cells per particle take "
                   f"{points:.3g} times the memory of the default 2 x 2 in one; ")
