"""The needle layer: a rigid circular needle driven through the tissue (thesis section 3.1.5).

- geometry: the needle at entry (centre, turning sense, desired exit);
- coupling: its loads and constraints on the needle track Gamma_N (eq. 3.58-3.65);
- constraint_rows: the track points' shape-function rows, appended as the track grows;
- load_quadrature: where the loads sit on the track (Gauss points, the cutting profile);
- saddle_point: the linear solves of the constrained equilibrium (eq. 3.62, 3.71-3.74);
- equilibrium: the state of one insertion and its Newton equilibrium (NeedleInsertion);
- newton: the parts of that Newton solve (tolerances, the factor's renewal, Anderson mixing);
- prepared_tissue: the tissue model and K0's factor every insertion starts from (PreparedTissue);
- tip_tracking: the material point the tip reaches in a step, and the exit (eq. 3.66-3.70);
- insertion: run_insertion, Algorithm 1 step by step;
- results: the typed records of a run.
"""
