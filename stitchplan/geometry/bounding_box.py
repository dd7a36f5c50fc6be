"""BoundingBox, the base of every domain: its size, round-off tolerance and input tolerance."""

from __future__ import annotations

# How far off the boundary a point a person typed or measured (a needle entry, the end of a
# load or clamped segment, a probe) may lie and still mean a boundary point: a micrometre, or
# a millionth of the tissue's size when that is larger. Coordinates written to three decimals
# (mm) lie within 0.71 um of the point meant; points on a slanted edge or a circular hole's
# wall typed to three to six decimals were 2.4e-7 to 1.5e-4 mm off it, and refused. A micrometre is
# also the finest accuracy the tool accepts (discretization.accuracy, the planner's tolerance)
# and a thousandth of a typical particle spacing: moving a point that far onto the boundary
# changes nothing the model resolves. Beyond a metre of tissue, 1e-6 of its size is the
# rounding of coordinates typed to seven significant digits.
INPUT_TOLERANCE_MM = 1e-3
INPUT_TOLERANCE_RELATIVE = 1e-6


class BoundingBox:
    """`size` and `tolerance` of a domain from its bounding box's `width` and `height` (mm)."""

    width: float
    height: float

    @property
    def size(self) -> tuple[float, float]:
        """The bounding box's sides (mm)."""
        return (self.width, self.height)

    @property
    def tolerance(self) -> float:
        """Distance below which a point counts as on the boundary (round-off of the input)."""
        return 1e-9 * max(self.width, self.height)

    @property
    def input_tolerance(self) -> float:
        """Distance within which a point a file gives is moved onto the boundary (snap_to_boundary)."""
        return max(INPUT_TOLERANCE_MM, INPUT_TOLERANCE_RELATIVE * max(self.width, self.height))
