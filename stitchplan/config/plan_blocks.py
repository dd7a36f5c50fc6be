"""The blocks of a scenario file that say how a plan is made and written for a manipulator:
`planner` (Algorithm 2's tolerances and passes, the centre's move limits, the target, the
needle's lean at entry) and `robot` (the robot base frame and the needle's angular speed of
trajectory.csv), as validated, frozen dataclasses like config.blocks'.
"""

from __future__ import annotations

from typing import Any

from pydantic import model_validator

from .blocks import MAX_ENTRY_TILT, block
from .fields import Flag, Point, PositiveMM, choice, described, integer, number, pair, problem
from .messages import Shown


@block(title="planner")
class Planner:
    tolerance: described(PositiveMM, "planner convergence tolerance, mm") = 1e-3
    max_iterations: described(integer(1, 1000), "planner iterations per step") = 10
    strict: described(Flag, "fail instead of warning when the planner does not converge") = False
    exit_tolerance: described(PositiveMM, "exit-point tolerance of the planner passes, mm") = 0.005
    max_passes: described(integer(1, 20), "planner passes over the whole insertion") = 4
    center_step_limit: described(PositiveMM, "largest centre move per 0.08 rad of needle step, mm "
                                 "(scaled with the step; the robot's speed bound)") = 0.28
    center_second_difference_limit: described(PositiveMM, "largest change of the centre's move per "
                                              "0.08 rad of needle step, mm (scaled with the step)") = 0.14
    # a stitch across a wound: aim the final exit (exit), or trade its error for equal bites
    # on both sides of the wound (symmetric: the passes aim the exit-side bite at the entry side's)
    target: described(choice(("exit", "symmetric")),
                      "exit: aim the desired exit; symmetric (a stitch across a wound): aim equal bites "
                      "on both sides of the wound, trading exit error for symmetry") = "exit"
    predicted_aim: described(Flag, "plan with verification: aim the passes after the first by the refined "
                             "model's offset predicted from a replay of the first pass at twice the spacing") = True
    aim_entry_tilt: described(Flag, "lean the needle at entry (needle.entry_tilt, within max_entry_tilt) "
                                    "so that the first pass, its centre path within the move limits, "
                                    "exits at the desired exit; for scenes whose compensation the move "
                                    "limits cannot carry") = False
    max_entry_tilt: described(number(f"a positive angle of at most {MAX_ENTRY_TILT:g} rad", gt=0,
                                     le=MAX_ENTRY_TILT),
                              "rad the planner may lean the needle at entry (aim_entry_tilt)") = 0.35

    @model_validator(mode="wrap")
    @classmethod
    def _lean_aims_the_exit(cls, data: Any, handler) -> Planner:
        """aim_entry_tilt aims the exit; the symmetric target's aim follows the bites pass by
        pass, which a lean chosen before the passes cannot."""
        planner = handler(data)
        if planner.aim_entry_tilt and planner.target == "symmetric":
            raise problem("false with target symmetric (the lean is chosen for the exit, before the passes "
                          "that aim the bites)", field="aim_entry_tilt", value=Shown("true"))
        return planner


# bounds of the robot's frame and speed (the same for `plan`'s --base-transform and
# --angular-speed, stitchplan.cli.options): a base more than 10 m from the tissue is a unit or
# typing mistake, not a robot cell, and a needle turning slower than 1e-6 rad/s (a half turn
# in 36 days) is one too; within them every column of the trajectory stays finite
MAX_BASE_OFFSET_MM = 10_000.0
MAX_BASE_ROTATION_DEG = 360.0
MIN_ANGULAR_SPEED = 1e-6  # rad/s
# and one turning its step in less than a nanosecond: time_s is written to 1e-12 s, and at
# 1e12 rad/s every time after row 0 was written 0, refused by the trajectory's own replay
MIN_STEP_SECONDS = 1e-9


def speed_problem(speed: float, step: float) -> str | None:
    """What a needle speed (rad/s) is expected to be with the needle's `step` (rad), or None
    when it turns each step in at least MIN_STEP_SECONDS."""
    if step / speed >= MIN_STEP_SECONDS:
        return None
    return (f"a speed of at most {step / MIN_STEP_SECONDS:g} rad/s (the needle's step of {step:g} rad in at least "
            f"{MIN_STEP_SECONDS:g} s: a needle turning faster is a typing or unit mistake, and time_s would stop "
            "increasing)")

ROTATION = "rotation of the tissue frame in the base frame, deg, counter-clockwise about the slab normal"
TRANSLATION = "tissue origin in the base frame, mm"
SPEED = "rad/s of needle rotation: adds time_s to trajectory.csv"


@block()
class Robot:
    """Tissue frame -> robot base frame: p_base = R(rotation) p_tissue + translation. Its
    values are not bounded here (planning.trajectory refuses a trajectory they make
    infinite); a file's `robot:` block (RobotBlock) and the options are."""

    rotation_deg: described(number("a number (deg)"), ROTATION) = 0.0
    translation: described(Point, TRANSLATION) = (0.0, 0.0)
    angular_speed: described(number("a positive number (rad/s)", gt=0) | None, SPEED) = None
    given: Flag = False


BaseOffset = number(f"a number between {-MAX_BASE_OFFSET_MM:g} and {MAX_BASE_OFFSET_MM:g} (mm; a base more than "
                    "10 m from the tissue is a typing or unit mistake)", ge=-MAX_BASE_OFFSET_MM, le=MAX_BASE_OFFSET_MM)


@block(title="base_transform")
class BaseTransform:
    rotation_deg: described(number(f"a number between {-MAX_BASE_ROTATION_DEG:g} and {MAX_BASE_ROTATION_DEG:g} "
                                   "(deg)", ge=-MAX_BASE_ROTATION_DEG, le=MAX_BASE_ROTATION_DEG), ROTATION) = 0.0
    translation: described(pair(f"a pair [tx, ty] of numbers between {-MAX_BASE_OFFSET_MM:g} and "
                                f"{MAX_BASE_OFFSET_MM:g} (mm)", BaseOffset), TRANSLATION) = (0.0, 0.0)


@block(title="robot")
class RobotBlock:
    """The `robot:` block of a file, as Robot holds it."""

    base_transform: described(BaseTransform | None, "p_base = R(rotation_deg) p + translation") = None
    angular_speed: described(number(f"a positive number of at least {MIN_ANGULAR_SPEED:g} (rad/s; a needle "
                                    "turning slower is a typing or unit mistake)", ge=MIN_ANGULAR_SPEED) | None,
                             SPEED) = None

    def robot(self) -> Robot:
        transform = self.base_transform or BaseTransform()
        return Robot(transform.rotation_deg, transform.translation, self.angular_speed,
                     given=self.base_transform is not None)
