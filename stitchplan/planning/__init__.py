"""The planning layer: the needle-centre trajectory that compensates the tissue's deformation
(planner, thesis Algorithm 2) and its table for a manipulator (trajectory)."""
