"""What a needle step's failure says (needle/equilibrium.py raises them): Newton's, diverged
or stopped short of equilibrium; Algorithm 1's ramp's, when even its smallest increment
fails, with whether the tissue itself gave way (the tangent's least stiffness on the
needle's constraints, needle/stability.py) and what to try. Each names the step and the
needle's rotation.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..config.boundary_points import shown_point
from ..errors import ConstraintStall, InsertionFailure, NewtonExhausted, NonFiniteResidual
from ..tissue.model import TissueModel
from .geometry import length
from .newton import Balance
from .stability import SoftestMode, mode_peak


def diverged(step: int, rotation: float, losses: int, balance: Balance) -> InsertionFailure:
    """Newton gave up: `losses` steps on a freshly factored tangent raised the residual
    (needle/newton.py FRESH_FACTOR_LOSSES)."""
    return InsertionFailure(
        f"Newton diverged at step {step} (needle rotation {rotation:.3f} rad): {losses} steps on "
        f"a freshly factored tangent raised the residual (now {balance.residual_norm:.3e} N, constraint "
        f"violation {balance.worst:.3e} mm)")


def not_converged(step: int, rotation: float, iteration: int, balance: Balance, max_iterations: int,
                  point_coupling: bool, constraint_tolerance: float) -> InsertionFailure:
    """Newton stopped short of equilibrium at its last `iteration`: a residual that is not
    finite, the forces out of balance after `max_iterations`, or the forces balanced with the
    needle constraints stalled above `constraint_tolerance` (mm)."""
    if not balance.finite:
        return NonFiniteResidual(
            f"Newton stopped at step {step} (needle rotation {rotation:.3f} rad): the residual is not finite "
            f"after {iteration} iterations (needle force {balance.needle_force:.3e} N): the loads or the "
            "deformation overflow floating point")
    message = (f"Newton did not converge at step {step} (needle rotation {rotation:.3f} rad): residual "
               f"{balance.residual_norm:.3e} N, constraint violation {balance.worst:.3e} mm after "
               f"{max_iterations} iterations")
    if not balance.forces_balance:
        return NewtonExhausted(message)
    remedy = "refine the spacing or lengthen the needle step"
    if point_coupling:
        remedy = "refine the spacing, lengthen the needle step or use `needle.coupling: mortar`"
    return ConstraintStall(f"{message}; the forces balance, but the needle constraints stall above their "
                           f"tolerance of {constraint_tolerance:.3e} mm: their rows are nearly dependent, "
                           f"needle points closer together than the particles resolve ({remedy})")


def ramp_failure(step: int, rotation: float, carried: float, smallest: float, failure: InsertionFailure,
                 max_iterations: int, default_iterations: int, material_models: set[str],
                 stability_note: Callable[[], str]) -> str:
    """What went wrong when even the ramp's `smallest` load increment fails at `carried` of
    the step's load, and what to try: more iterations where Newton was given few, whether the
    tissue gave way (`stability_note`, asked only where the material may be the cause), and
    neo-Hookean for Saint Venant-Kirchhoff."""
    message = (f"step {step} (needle rotation {rotation:.3f} rad): the needle's load could not be "
               f"carried: {100 * carried:.3g} % of the step's cutting force and added friction held, "
               f"the next {100 * smallest:.3g} % increment failed ({failure})")
    if isinstance(failure, (NonFiniteResidual, ConstraintStall)):  # not the material's doing
        return message
    if isinstance(failure, NewtonExhausted) and max_iterations < default_iterations:
        # Newton ran out of the few iterations it was given: no sign of the material's doing
        return message + (f"; solver.max_iterations is {max_iterations} (the default "
                          f"{default_iterations}): give Newton more iterations")
    message += stability_note()
    if "saint-venant-kirchhoff" in material_models:
        message += ("; Saint Venant-Kirchhoff is unstable under strong compression (its stress "
                    "turns back to zero as det F -> 0, so the tissue in front of the tip collapses): "
                    "use `model: neo-hookean`, which stiffens instead")
    return message


def stability_note(now: SoftestMode, where: str, before: SoftestMode | None) -> str:
    """Whether the tissue itself gave way where a step's load could not be carried: its least
    stiffness on the needle's constraints `now`, at the last load carried, negative (the state
    is unstable) or against the step's start `before` (falling toward zero, a limit point, or
    not: Newton's failure); `where` its mode moves the tissue most. Empty without a stable
    start to compare (None: nothing of the step carried, or the eigensolver gave no answer)."""
    if now.stiffness < 0.0:
        return (f"; the state carried is unstable: the tangent's least stiffness on the needle's constraints "
                f"is negative, {where}: the tissue buckles or creases there, which the model does not follow "
                "(the needle is a line and the tissue does not touch itself)")
    if before is None or before.stiffness <= 0.0:
        return ""
    percent = round(100.0 * now.stiffness / before.stiffness)
    if percent < 100:
        return (f"; the tangent's least stiffness on the needle's constraints fell to {percent} % of the "
                f"step's start (at zero the tissue has no stable equilibrium), {where}")
    return (f"; the tangent's least stiffness on the needle's constraints did not fall over the step "
            f"({percent} % of the step's start): the tissue is not softening, Newton's steps failed")


def mode_place(mode: SoftestMode, model: TissueModel, dilation: float, entry: np.ndarray,
               tip: np.ndarray | None) -> str:
    """`its mode largest at [x, y] mm`, the particle it moves most, with `, the needle's entry`,
    `tip` or `entry and tip`: those of the two (reference) within two of the particle's
    spacings of it."""
    particle = mode_peak(mode, model.boundary.free_map)
    near = 2.0 * model.support[particle] / dilation
    where = model.particles[particle]
    points = {"entry": entry, "tip": tip}
    names = [name for name, point in points.items()
             if point is not None and length(where - np.asarray(point, dtype=float)) <= near]
    return f"its mode largest at {shown_point(where)} mm" + (f", the needle's {' and '.join(names)}" if names else "")
