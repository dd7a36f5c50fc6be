"""The resource guard: what a run will cost, estimated before anything heavy is built, and
refused past documented limits.

It sits above needle/ (it needs the needle geometry for the step count and the needle zone
of graded particles) and below planning/ and study/ (the auto discretization asks it for
the finest model allowed); the commands call `check_resources` before any run.

A run's size is known from the scenario alone: the particles (counted from the particle
arrangement without building shape functions, or estimated from the spacing where even the
count would be costly), the kernel's neighbours per point (dilation), the quadrature
points, and the steps (load steps of deform, needle steps until the tip exits). From these
the guard estimates

- memory: the sparse shape-function, gradient and tangent matrices and the LU factor grow
  like particles x neighbours; bytes = MEMORY_PER_PARTICLE x particles^MEMORY_EXPONENT x
  (neighbours / 16) x (quadrature points per particle / 4), plus the interpreter's share,
  plus for a needle run what it keeps of its steps until it ends (_step_memory, counted
  from the arrays the code keeps: each step's state with the saddle-point solver's dense
  blocks, E K^-1 (2Q, 2 n_free) with 2Q ~ 4 x the steps and E K^-1 E^T (2Q, 2Q) while
  2Q <= 2 n_free, in doubling buffers the states share, and the coupling's weights (Q, m),
  sparse), which passes the rest from a few hundred steps on (SH 1/2: 0.45 GB measured at
  0.0025 rad, 0.09 GB at its 0.08 rad);
- time: the tangent assembly B^T W B costs ~ quadrature points x neighbours^2 per Newton
  iteration and the factorization grows a little faster than the particles; seconds =
  SECONDS_PER_PARTICLE_STEP x particles^TIME_EXPONENT x steps x (neighbours / 16)^2 x
  (quadrature points per particle / 4) x runs, for needle runs x (1 + steps / (2 x
  STEP_TIME_DOUBLES_AT)) (a step's solves read a row pair per needle point before it) and
  x MINRES_TIME_FACTOR where MINRES solves the steps;
- with `simulate --condition-numbers`, each needle step's dense condition numbers
  (condition_costs): CONDITION_SECONDS x (2 x particles / 1000)^3 seconds a step and
  CONDITION_MATRICES dense (2 x particles)^2 arrays of memory (benchmarks/results/
  condition_costs.md: 0.6-0.9 s a step on SH 1/2's 642 particles, the run alone 0.2 s).

A shaped tissue (an outline, holes, regions) is not a lattice the spacing alone counts: its
particles and quadrature points are placed as the model places them (a traced contour's
boundary particles, a circular hole's CIRCLE_SEGMENTS, the cut cells' extra Gauss points),
and both costs are multiplied by its `crowding`, the mean square of the particles a
quadrature point sees over a regular lattice's (16^2 at dilation 2), counted on a sample of
the points: boundary particles carry the support of the lattice around them, so around a
small hole a point sees several times the usual particles (measured on the audit's scenes
and the shipped shaped ones, deform: memory 0.52-0.89x of the estimate; time 1.0-1.5x, and
up to 2.4x where the solve of a point-like load on a traced outline needs many Newton
iterations).

The constants come from `python benchmarks/resource_costs.py` (benchmarks/results/
resource_costs.md), measured on the 2-core machine the tool is developed on, which is
shared: in its latest run the fitted memory model is within 0.79-1.28x of every measured
case, the fitted time model within 0.84-1.10x of the dilation-2 cases at the scenarios'
needle steps, and the (neighbours/16)^2 time scaling overestimated the unfitted dilation-3
case (0.62x there; 0.33x, 0.60x and 0.96x in earlier runs). What a needle run keeps of its steps is
not fitted: with the guard's constants the runs at 0.01 and 0.0025 rad on SH 1/2 peak at
0.78 and 0.88x of the estimate (the other cases at 0.46-0.84x), and their time per step
grows with the steps taken: each solve reads a row pair per needle point, and the estimate
takes a step k as a + b k (STEP_TIME_DOUBLES_AT = a / b, fitted on those runs alone), which
puts them at 0.56 and 0.54x of it (1.5x at 0.0025 rad with a time linear in the steps; 3.6x
while the solver formed every step's Schur complement from E K^-1 E^T). The
memory limit is what protects the machine; the time is a guide, not a promise.

Limits (Limits; the CLI's --max-particles raises the first, --no-resource-check skips
them all; nothing raises the memory share: a smaller model is the way under it):

- MAX_PARTICLES = 50 000: a deform at 1 mm spacing on the 100 x 100 mm slab (10 447
  particles) took 30 s and 0.77 GB; 50 000 particles are estimated at ~3 min and ~5.6 GB
  per 10-step solve, a plan (several insertions and a verification model of 4x the
  particles) at hours;
- MAX_NEEDLE_STEPS = 2 000: the shipped needles take 15-40 steps; 2 000 steps over a half
  circle advance the SH needle's tip by radius x step ~ 0.014 mm each, 1/130 of the default
  particle spacing at the needle (1.78 mm): nothing the model resolves, while the run time
  grows with every step, and the memory it keeps faster still (~0.9 GB estimated at 2 000
  steps on SH 1/2, past the memory share of a machine with less than 1.8 GB available: then
  refused naming needle.step);
- MAX_NEIGHBOURS = 400 particles in a kernel support (dilation 10): the RK functions stop
  being local well before (RKPM practice: dilation 1.5-3, 9-36 neighbours), and the
  tangent's cost grows with the square of the neighbours;
- MAX_CONDITION_SECONDS = 600 s of `--condition-numbers` (a diagnostic of small models: the
  thesis's figures use 441 particles; at 2104 particles they take ~22 s a step, 15 min over
  SH 1/2's 40 steps, against ~1 s for the run), refused naming the option;
- under an address-space limit (ulimit -v), the address space a run of this process maps
  (machine.address_space_needed: the numerics' imports, the libraries and buffers a run maps
  besides, 2.3x its arrays); past the limit the refusal names it, or the setting that drives
  the model where a smaller one would fit;
- MEMORY_SHARE = 0.5 of the memory the machine has available now, for the runs a command
  has going on at once together (check_resources `alongside`: a plan's passes, its
  verification's replays in a helper process and its replay at twice the spacing; a
  simulate and its estimate's replay; plan --uncertainty and the sampled plans of its local
  Dask workers; the largest of a study's runs, as many as its local workers, and the
  study's own process, which runs none of them, with its interpreter), each helper
  process with its own share of the interpreter (HELPER_BASE_MEMORY), each worker with the
  whole of its own; a material calibration's experiments, which its process holds at once
  with one more factor for a sensitivity (check_resources `in_one_process`,
  costs.held_in_one_process), within the share and the address-space limit together.

The guard also refuses a model too coarse to mean anything (`_coarse_refusal`), the other
side of a spacing typed wrong: a spacing above half the tissue's smaller side (fewer than
three particles across it), or a spacing at the needle above the needle's radius (the
needle's curve then falls between a few particles: on the SH 1/2 block, `--spacing 200`
runs on 4 particles to an exit error of 0.0175 mm, with an estimate of 0 from a second run on
the same 4 particles, against 0.4685 mm at half the default spacing).

A refusal names what drives the estimate past the limit (`_particle_setting`,
`_memory_setting`): the spacing, or the needle zone's refinement or spacing when the
coarse spacing alone would fit, or, when the spacing is the default of a file giving none,
the needle radius or the tissue's size that sets it; past the memory share with a standard
kernel fitting, the dilation or the quadrature points, and the needle step when the run
would fit but for what it keeps of its steps. A field set elsewhere than the scenario file's
`discretization:` block
(an option, a study's spacing, a plan's verification model) is named as the caller's
`Origin` says. Counts are estimated in floating point and held at COUNT_CAP, so any finite
positive input ends in a refusal, never in an overflow.

Its modules, each importing only those before it: `limits` (Limits and their defaults),
`model_size` (ModelSize, model_size: particles, neighbours, quadrature points, steps),
`origin` (Origin: what set a run's discretization), `formatting` (counts, bytes and
durations as messages write them), `costs` (Estimate, estimate: time and memory,
held_at_once, held_in_one_process), `machine` (available_memory, address_space_needed) and `guard` (check_resources, its refusals and
the settings they name).
"""
