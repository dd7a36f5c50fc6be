"""The project's own error types: the CLI turns these, and only these, into one-line messages.

- InputError: something the user gave cannot be used (a scenario field, an option, a file).
  The message names the field or file, what was received and what was expected.
  Exit code 2.
- NumericalFailure: a numerical method failed on an input it accepted; the message says
  what failed and where (load step and fraction, needle step and angle). Exit code 1.

Anything else that escapes a command is a bug and is reported as one, with its traceback.
"""

from __future__ import annotations


class StitchplanError(Exception):
    """Base of the errors a user can meet; the message is one line."""

    exit_code = 1


class InputError(StitchplanError, ValueError):
    """A scenario, option or input file that cannot be used."""

    exit_code = 2


# the name the scenario layer has used since 0.1.0
ScenarioError = InputError


class NumericalFailure(StitchplanError, RuntimeError):
    """A numerical method failed; the message says what and where."""

    exit_code = 1


class SolverDivergence(NumericalFailure):
    """Newton failed even after cutting the load step; the message says where. `last_try`: the
    failure of the last try, after the step cuts (None: not a load step's)."""

    last_try: Exception | None = None


class IterationLimit(SolverDivergence):
    """Newton ran out of solver.max_iterations with a finite residual (not an inverted material
    or a failed linear solve): the solver's settings may be what stops it."""


class InvertedMaterial(NumericalFailure, ArithmeticError):
    """det F <= 0 at a quadrature point: the trial state is not admissible."""


class SingularMomentMatrix(NumericalFailure):
    """The moment matrix M(X) of eq. 3.20 is singular: too few particles cover a point."""


class TipTrackingJump(NumericalFailure, ArithmeticError):
    """The inverse-gradient step departs from the expected one (thesis section 5.1.1)."""


class InsertionFailure(NumericalFailure):
    """A numerical method failed during the insertion; the message says at which step and angle."""


class NonFiniteResidual(InsertionFailure):
    """Newton met a residual that is not finite: the loads or the deformation overflow."""


class NewtonExhausted(InsertionFailure):
    """Newton used up solver.max_iterations at a step with its forces still out of balance."""


class UnstableEquilibrium(InsertionFailure):
    """Newton converged, within a cut load ramp, to a state the tissue would not stay in: the
    tangent's least stiffness on the needle's constraints is negative there (needle/stability.py)."""


class ConstraintStall(InsertionFailure):
    """Newton balanced the forces but the needle constraints stalled above their tolerance:
    constraint rows nearly dependent (needle points closer together than the particles resolve)."""


class PlanningFailure(InsertionFailure):
    """The planner's convergence condition (eq. 4.2) fails (raised only when strict)."""
