"""Many independent runs on a Dask cluster: the sampled runs of `plan --uncertainty` and the
sweep of `stitchplan study`.

`Executor` maps a top-level (picklable) function over argument lists and returns the
results in submission order, so a result never depends on where or in which order its
task ran. Three ways to run:

- `workers=0`: in this process, one after another (tests, debugging, profiling);
- `workers=N` (default: the machine's cores): a `dask.distributed.LocalCluster` of N
  single-threaded worker processes started for the run and closed after it;
- `scheduler="tcp://host:port"`: an existing cluster (`dask scheduler` and `dask worker
  tcp://...` on any machines that can import stitchplan).

Tasks are submitted with `pure=False` (each is run, none deduplicated) and `retries=2`, so
the tasks of a worker that dies are run again on another one. A cluster without a worker
holds its tasks forever, so the wait for results is watched: while no task completes the
scheduler is asked every few seconds for its workers, and when it has had none for
`worker_wait_seconds()` (WORKER_WAIT_S, or the STITCHPLAN_WORKER_WAIT environment variable)
the run ends as a ClusterFailure saying whether no worker ever came or the cluster lost its
workers, and how many tasks were done. The wait is logged at INFO (-v) as it goes. A task's own failure is the
task's business: the functions mapped here record the failures a run may end with
(RUN_FAILURES) in their result instead of raising them, so a failed sample is a recorded
failure, not a lost run; anything else escaping a task is a bug and is raised here.

Worker processes of a local cluster run with BLAS at one thread (OMP/OpenBLAS/MKL
variables), so N workers use N cores, and the sparse solves give the same numbers in every
process.

What the user gives is checked before any work (`check_workers`): a worker count from 0 to
MAX_WORKERS_PER_CORE x the cores this process may use (more only queue for the same cores and
each costs a process), and a scheduler address SCHEME://HOST:PORT with a scheme of
distributed's comm layer that reaches another process (tcp, tls, ws, wss). Reaching the
scheduler is bounded by CONNECT_TIMEOUT_S: an address where nothing listens, a server that
never answers and one that answers something else than Dask's protocol each end as one
InputError naming --scheduler, never as a hang or a traceback. The workers attached to a scheduler are
asked for this package's version (check_package_on_workers) when it is reached and before
each batch: one that cannot import it, or runs another version, is an InputError too.

Dask's log records stay off the console: in this process, while an executor runs, they go
to this module's logger at DEBUG (shown with -vv); the worker processes of a local cluster
drop them (`dask_setup`, run in each worker as a preload), so the heartbeat errors of a
normal shutdown never reach the user. Those workers ignore Ctrl-C (SIGINT, which a terminal
sends to the whole process group): the command stops them when it closes the cluster, so an
interrupt ends with the command's own exit and no traceback of theirs. What fails for real
ends as the package's own error:
InputError when the cluster cannot be reached or started, ClusterFailure when it loses tasks.

Its modules, each importing only those listed before it: `failures` (RUN_FAILURES, what a
mapped function records instead of raising, and ClusterFailure), `scheduler` (a scheduler's
address checked by its form, probe_scheduler reaching it within CONNECT_TIMEOUT_S),
`workers` (the usable cores, the bounds of --workers, the wait for workers, check_workers),
`signals` (signals_deferred: Ctrl-C held back while a local cluster starts), `dask_logs`
(Dask's log records forwarded to the package's logger; dask_setup, a local cluster's worker
preload) and `executor` (Executor, run_all).
"""
