"""Typed records of an insertion: one per needle step, and the whole run (what the writers,
the planner and the studies read)."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from ..config import Scenario
from ..events import Event
from ..tissue.model import TissueModel
from .geometry import NeedleGeometry


@dataclass(frozen=True)
class Snapshot:
    """One state of an insertion: the tissue's free coefficients (n_free, 2), the
    multipliers, the centre and the largest constraint violation (mm); after a needle step
    also the needle coupling's state (NeedleCoupling.state) and the saddle-point solver's
    (SaddlePointSolver.state: its factor and kept columns), for a later run that takes the
    step over (run_insertion `start_from`) and then solves on as this run did."""

    free: np.ndarray
    multipliers: np.ndarray
    center: np.ndarray
    violation: float
    coupling: dict | None = None
    solver: tuple | None = None  # holds the factor itself: not pickled (another process solves with its own)

    def __getstate__(self) -> dict:
        return {**self.__dict__, "solver": None}


@dataclass
class NeedleStep:
    step: int
    rotation: float  # rad since entry
    center: np.ndarray  # (2,) needle centre, spatial
    needle_tip: np.ndarray  # (2,) rigid needle tip, spatial
    tip_reference: np.ndarray  # (2,) tip material point, reference
    tip_spatial: np.ndarray  # (2,) tip material point, spatial
    needle_points: int
    friction_force: float  # N, total along the needle inside the tissue, as applied
    cutting_force: float  # N, as applied (a ramp's share while the cutting edge enters)
    newton_iterations: int  # every Newton iteration of the step (the planner's centre tries too)
    minres_iterations: int
    constraint_violation: float  # mm, max |g_k|
    tracking: str
    exit_displacement: np.ndarray  # (2,) u at the desired exit point
    planner_iterations: int = 0
    equilibrium_solves: int = 0  # equilibrium solves of the step (one per centre tried)
    eq42_ratio: float = float("nan")  # planned: ||du(X_exit)/dO||_2 (eq. 4.2 holds below 1)
    wall_seconds: float = float("nan")  # the step: tip tracking, equilibrium and the planner's centre
    condition_saddle: float = float("nan")
    condition_preconditioned: float = float("nan")

    @property
    def insertion_force(self) -> float:
        return self.friction_force + self.cutting_force


@dataclass
class InsertionResult:
    scenario: Scenario
    model: TissueModel  # a ModelOutline for a replay made in the helper process (planning/replays.py)
    geometry: NeedleGeometry
    steps: list[NeedleStep]
    coefficients: np.ndarray  # (n_steps + 1, NP, 2) particle coefficients d after each step, step 0 = rest
    needle_points: np.ndarray  # (k, 2) reference trajectory Gamma_N at exit
    desired_exit: np.ndarray
    desired_exit_def: np.ndarray
    achieved_exit: np.ndarray
    achieved_exit_def: np.ndarray
    exit_rotation: float
    wall_seconds: float
    timings: dict[str, float]
    events: list[Event] = field(default_factory=list)
    # and the linear solver, its backend and the needle steps' Newton tolerances
    solver_counts: dict[str, int | float | str] = field(default_factory=dict)
    # every boundary crossing of the undeformed circle after the entry, the final exit last
    # (more than one across a wound): kind, desired / desired_def / achieved / achieved_def
    # (2,), error_mm; achieved, achieved_def and error_mm None for a crossing the tip missed
    crossings: list[dict] = field(default_factory=list)
    # a stitch across a wound: each side's bite (deformed distance between the needle's
    # surface crossing and the wound edge) and their difference, mm; None otherwise
    bites: dict | None = None
    # the equilibrium after each step (steps[n] -> states[n]): where a later run on the same
    # model with a nearby centre path starts its steps' Newton solves (run_insertion start_from)
    states: list[Snapshot] = field(default_factory=list, repr=False)
    # the centre the needle entered about: a replayed path's row 0 (trajectory.csv writes the
    # scenario's centre rounded), else the scenario's; None: the scenario's
    entry_center: np.ndarray | None = None

    @property
    def exit_error_mm(self) -> float:
        return float(np.linalg.norm(self.achieved_exit_def - self.desired_exit_def))

    @property
    def exit_error_vector_mm(self) -> np.ndarray:
        """achieved_exit_def - desired_exit_def (mm): the exit error the planner's passes aim."""
        return np.asarray(self.achieved_exit_def - self.desired_exit_def, dtype=float)

    @cached_property
    def displacements(self) -> np.ndarray:
        """(n_steps + 1, NP, 2) particle displacements u(X_I) after each step, step 0 = rest:
        the RK interpolant at the particles from `coefficients`, made when first read (by the
        writers and plots; the planning reads none, and a run whose outputs do not show the
        field makes none). Every step's in one product with the shape functions at the
        particles, each value the sum a product per step would give. Not for a replay made in
        the helper process (its model is a ModelOutline)."""
        steps, count, _ = self.coefficients.shape
        stacked = self.coefficients.transpose(1, 0, 2).reshape(count, 2 * steps)  # (NP, steps x 2)
        return np.ascontiguousarray((self.model.particle_shape_values() @ stacked).reshape(count, steps, 2)
                                    .transpose(1, 0, 2))

    def center_after(self, step: int) -> np.ndarray:
        """The needle centre after `step` (0: the entry centre)."""
        if step > 0:
            return self.steps[step - 1].center
        return self.geometry.center if self.entry_center is None else self.entry_center

    @property
    def exit_error_material_mm(self) -> float:
        return float(np.linalg.norm(self.achieved_exit - self.desired_exit))


@dataclass
class StepsDone:
    """The steps a run had completed when its centre control stopped it (InsertionStopped):
    what a later run along the same first centres takes over (run_insertion `start_from`)."""

    model: TissueModel
    geometry: NeedleGeometry
    entry_center: np.ndarray
    steps: list[NeedleStep]
    events: list[Event]
    states: list[Snapshot] = field(repr=False)

    center_after = InsertionResult.center_after
