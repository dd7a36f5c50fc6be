"""Replays of a needle-centre path on a second model: the verification's refined model and
the error estimate's coarse one (planning/verification.py), here or in a helper process
that runs them while this process plans.

A plan's replay needs the plan's trajectory, but not all of it at once: a planner pass's
centre for step n is final once step n is done (planning.planner.run_plan streams each
pass through `begin`, `row` and `end`). `BackgroundReplays` forks a helper process that
builds the second model (and factors its K0) while this process builds its own, then
replays each pass as its centres arrive, on the machine's second core: the replay of the
pass that is kept overlaps the planning instead of following it. The `plan` and `simulate`
commands fork it as they start, before their imports; `plan` hands it its scenario once its
inputs are guarded, before its own imports of the numerics (early_helper.hand), and otherwise
it is handed it here (a helper handed another model is ended and another forked); a
BackgroundReplays made without one forks its own the same way (early_helper.fork_helper). A pass that is not kept
is dropped at the helper's next step once the next pass begins (it reads what has come at
every step), unless the next pass keeps every centre the replay has used so far (a re-aimed
pass keeps the first pass's early steps): the replay then goes on with the next pass's
centres; and a replay that has already ended, or the steps a dropped one had done, give a
next pass from the same start the steps where their centres agree (run_insertion
`take_over_only`, to the last bit what they would compute). A trajectory that is not the
last streamed one (the best of several passes) is replayed whole when asked for. `submit`
starts a path known from the start (`simulate`'s estimate run) at once.

Both kinds replay with run_insertion on the same inputs, one model kept for all their
replays, each replay started from the one returned before it (run_insertion
`start_from`, as the verification rounds want), so a result does not depend on where it
ran (tests/test_replays.py); the helper sends it without its states and with its model's
outline for the model (tissue.model.ModelOutline: what the summaries read), which is all the
command reads of a replay. The helper is used where it can be: Linux (fork is its own
way of starting a process; macOS's system libraries are not fork-safe), two or more cores,
one thread in this process (forking a threaded process can deadlock the child), and
STITCHPLAN_REPLAY_HELPER not 0; `replays_for` falls back to `InlineReplays` otherwise.
Should the helper fail in a way the project does not report as a StitchplanError (it
died, or a bug), the replay runs again here, where the failure is reported as usual.
"""

from __future__ import annotations

import collections
import logging
import os
import signal
import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import replace

import numpy as np

from ..config import Scenario
from .. import early_helper
from ..early_helper import helper_available
from ..errors import StitchplanError
from ..needle.prepared_tissue import PreparedTissue
from ..needle.insertion import CenterReplay, InsertionStopped, run_insertion
from ..needle.results import InsertionResult, StepsDone

log = logging.getLogger(__name__)

SERVER = f"{__name__}:serve"  # what the helper runs (early_helper.fork_helper)
STOP_SECONDS = 1.0  # how long closing waits for the helper (idle unless a run failed) before terminating it


class InlineReplays:
    """Replays run here, when asked for; the streaming calls do nothing."""

    where = "this process"  # where the replays ran (the plan summary's verification.replayed_in)

    def __init__(self, scenario: Scenario, **options):
        self.scenario = scenario
        self.options = options  # run_insertion's linear_solver and tip_tracking
        self._tissue: PreparedTissue | None = None
        self._last: InsertionResult | None = None  # the replay returned last

    def begin(self, entry_center: np.ndarray) -> None:
        """A planner pass starts at `entry_center` (row 0 of its trajectory)."""

    def row(self, step: int, center: np.ndarray) -> None:
        """The pass's centre for `step`, final."""

    def end(self, centers: np.ndarray) -> None:
        """The pass ended with these exported centres (trajectory.exported_centers)."""

    def submit(self, centers: np.ndarray | None) -> None:
        """A path that will be asked for (None: the needle centre stays fixed)."""

    def replay(self, centers: np.ndarray | None) -> InsertionResult:
        """The path replayed on this object's model (None: the fixed centre), started from
        the replay returned before; raises what run_insertion raises."""
        if self._tissue is None:
            self._tissue = PreparedTissue(self.scenario)
        start, self._last = self._last, None
        self._last = run_insertion(self.scenario, center_path=centers, tissue=self._tissue, start_from=start,
                                   **self.options)
        return self._last

    def close(self) -> None:
        pass


class BackgroundReplays(InlineReplays):
    """Replays run by a forked helper process (module docstring). `while_waiting`: work of
    the command's own that can go on while it waits for a replay (called once, the first
    time the answer is not there yet; the outputs' libraries, cli.runs._plan_with_replays)."""

    def __init__(self, scenario: Scenario, while_waiting: Callable[[], None] | None = None, **options):
        super().__init__(scenario, **options)
        self._while_waiting = while_waiting
        started = early_helper.take()  # forked as the command started (stitchplan/early_helper.py)
        handed = None
        if started is not None:
            pid, connection, handed = started
            log.info("replays: the helper process forked as the command started (pid %d)%s", pid,
                     "" if handed is None else ", handed its scenario before the command's imports")
            if handed is not None and handed != (scenario, options):  # it builds another model
                log.info("replays: that helper was handed another model; forking one for this one")
                connection.close()
                discarded = _StartedHelper(pid)
                discarded.terminate()
                discarded.join(STOP_SECONDS)
                started = handed = None
        if started is None:
            pid, connection = early_helper.fork_helper(SERVER)
        self._process, self._connection = _StartedHelper(pid), connection
        if handed is None:
            early_helper.send_scenario(self._connection, scenario, options)
        self.jobs = 0  # replays started in the helper (streamed passes and whole paths)
        self.steps_run = 0  # needle steps of the helper's replays, of dropped passes too
        self._newest: tuple[int, np.ndarray | None] | None = None  # the helper's newest job and its path
        self._streaming: int | None = None  # the streamed job whose rows are still coming
        self._last_job: int | None = None  # the job whose replay was returned last (start_from)
        self._failed = False  # the helper is gone: replays run here

    def _send(self, message: tuple) -> None:
        if self._failed:
            return
        try:
            self._connection.send(message)
        except (OSError, EOFError, ValueError):
            self._fail("the helper process stopped")

    def _start(self, kind: str, payload) -> int:
        self.jobs += 1
        self._newest = None  # its path is known once the job's rows have ended
        self._send((kind, self.jobs, self._last_job, payload))
        return self.jobs

    def begin(self, entry_center: np.ndarray) -> None:
        self._streaming = self._start("stream", np.array(entry_center, dtype=float))

    def row(self, step: int, center: np.ndarray) -> None:
        if self._streaming is not None:
            self._send(("row", self._streaming, step, np.array(center, dtype=float)))

    def end(self, centers: np.ndarray) -> None:
        if self._streaming is not None:
            centers = np.array(centers, dtype=float)
            self._send(("end", self._streaming, centers))
            self._newest = (self._streaming, centers)
            self._streaming = None

    def submit(self, centers: np.ndarray | None) -> None:
        centers = None if centers is None else np.array(centers, dtype=float)
        self._newest = (self._start("path", centers), centers)

    def replay(self, centers: np.ndarray | None) -> InsertionResult:
        if self._failed:
            return self._replay_here(centers)
        if self._streaming is not None:  # a pass that never ended (it failed): not this path
            self._send(("end", self._streaming, np.zeros((0, 2))))
            self._streaming = None
        if self._newest is None or not _same_path(self._newest[1], centers):
            self.submit(centers)
        job = self._newest[0]
        self._send(("send", job))
        self._use_the_wait()
        try:
            answer = self._connection.recv() if not self._failed else None
        except (OSError, EOFError):
            answer = None
        if answer is None or answer[0] != "result" or answer[1] != job:
            self._fail("the helper process stopped")
            return self._replay_here(centers)
        _, _, result, error, steps = answer
        self.steps_run += steps
        self._last_job = None
        if error is not None:
            if isinstance(error, StitchplanError):
                raise error
            self._fail(f"the helper process failed ({error})")
            return self._replay_here(centers)
        self._last_job = job
        self._last = result
        return result

    def _use_the_wait(self) -> None:
        """Run `while_waiting` (once) when the helper's answer has not come yet. What it does
        the command does later anyway, so an answer that comes meanwhile costs nothing; a
        failure there is left to meet again where the command needs it."""
        work, self._while_waiting = self._while_waiting, None
        try:
            if work is None or self._failed or self._connection.poll():
                return
        except (OSError, EOFError):
            return
        try:
            work()
        except Exception as error:  # noqa: BLE001 -- met again, and reported, where the command needs it
            log.info("replays: the work done while waiting failed (%s)", error)

    @property
    def where(self) -> str:
        return "this process" if self._failed else "helper process"

    def _fail(self, reason: str) -> None:
        if not self._failed:
            log.info("replays: %s; replaying in this process", reason)
        self._failed = True

    def _replay_here(self, centers: np.ndarray | None) -> InsertionResult:
        """After a helper failure: replay here (from no earlier replay: the helper's are gone)."""
        self._last = None
        return super().replay(centers)

    def close(self) -> None:
        self._send(("stop",))
        self._connection.close()
        self._process.join(STOP_SECONDS)
        if self._process.is_alive():
            self._process.terminate()
            self._process.join()


class StreamTee:
    """Hands a planner pass's centres to several replays (planning.planner.run_plan `stream`)."""

    def __init__(self, *replays: InlineReplays):
        self.replays = replays

    def begin(self, entry_center: np.ndarray) -> None:
        for replays in self.replays:
            replays.begin(entry_center)

    def row(self, step: int, center: np.ndarray) -> None:
        for replays in self.replays:
            replays.row(step, center)

    def end(self, centers: np.ndarray) -> None:
        for replays in self.replays:
            replays.end(centers)


@contextmanager
def replays_for(scenario: Scenario, background: bool = True, while_waiting: Callable[[], None] | None = None,
                **options):
    """Replays on `scenario`'s model: by a helper process when `background` and
    helper_available() (`while_waiting`: BackgroundReplays'), else here. Closes the helper
    on leaving."""
    replays = None
    if background and helper_available():
        try:
            replays = BackgroundReplays(scenario, while_waiting, **options)
        except OSError as error:  # no process to be had (fork refused): replay here
            log.info("replays: no helper process (%s); replaying in this process", error)
    replays = replays or InlineReplays(scenario, **options)
    log.info("replays at spacing %.4g mm run in: %s", scenario.discretization.spacing, replays.where)
    try:
        yield replays
    finally:
        replays.close()


def _same_path(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return a.shape == np.shape(b) and bool(np.array_equal(a, b))


# --- the helper process ------------------------------------------------------------------------


class _Superseded(InsertionStopped):
    """A newer request reached the helper while a streamed replay waited for its rows."""


class _StreamedPath(CenterReplay):
    """The centres of a planner pass as they arrive; CenterReplay's once the pass has ended
    (its path then: a row the pass did not reach ends the replay as CenterReplay's does).

    A newer pass from the same warm start whose centres agree with every one used so far (a
    re-aimed pass keeps the earlier pass's first steps: planning.pass_offsets.PassPrefix) is
    adopted: the replay goes on with its centres instead of starting again. The pass's
    messages are kept: at the first centre that differs from one already used they go back to
    the inbox and the replay starts again from them (_Superseded)."""

    def __init__(self, receive, pending, inbox: collections.deque, message: tuple):
        super().__init__(np.zeros((0, 2)))
        self._receive, self._pending, self._inbox = receive, pending, inbox
        _, self.job, self._warm, entry_center = message  # job: the pass replayed now (adopted or not)
        self._rows = {0: entry_center}
        self._used: dict[int, np.ndarray] = {}  # the centres the replay has taken, by step
        self._kept: list[tuple] = [message]  # the pass's messages so far
        self.steps = 0  # steps asked for
        self._ended = False
        self._asked = False  # the main process waits for this replay: nothing more will come

    def predict(self, center: np.ndarray, step: int) -> np.ndarray:
        # every step reads what has come, so that a newer pass ends this replay at once
        # instead of after the whole of a pass that was dropped
        self.steps += step > 0
        while not self._asked and ((not self._ended and step not in self._rows) or self._pending()):
            message = self._receive()
            if message[0] == "send" and message[1] == self.job:
                self._inbox.appendleft(message)  # answered once the replay is done
                self._asked = True
                continue
            if message[0] == "stream" and message[2] == self._warm and self._agrees(0, message[3]):
                self._adopt(message)
                continue
            if message[0] in ("stream", "path", "send", "stop"):  # this pass is dropped
                self._inbox.appendleft(message)
                raise _Superseded
            if message[1] != self.job:  # a dropped job's
                continue
            self._kept.append(message)
            if message[0] == "row":
                if not self._agrees(message[2], message[3]):
                    self._start_again()
                self._rows[message[2]] = message[3]
            elif message[0] == "end":
                if not all(self._agrees(row_step, row) for row_step, row in enumerate(message[2])):
                    self._start_again()
                self._ended, self.path = True, message[2]
        center = super().predict(center, step) if self._ended else self._rows[step]
        self._used[step] = center
        return center

    def _agrees(self, step: int, center: np.ndarray) -> bool:
        """Whether `center` is the one the replay took at `step` (or took none there yet)."""
        return step not in self._used or np.array_equal(self._used[step], center)

    def _adopt(self, message: tuple) -> None:
        self.job, self._rows, self._ended = message[1], {0: message[3]}, False
        self._kept = [message]

    def _start_again(self) -> None:
        """End this replay; the pass's messages go back to the inbox, to be replayed afresh."""
        for kept in reversed(self._kept):
            self._inbox.appendleft(kept)
        raise _Superseded


def _end_with(parent: int) -> None:
    """Have Linux stop this process when the main process dies (killed, it cannot stop the
    helper, which would go on replaying for no one), and end now if it already has."""
    import ctypes

    try:
        ctypes.CDLL(None).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):  # no prctl to reach: the closed pipe still ends the loop
        pass
    if os.getppid() != parent:
        os._exit(0)


PR_SET_PDEATHSIG = 1  # prctl option: the signal this process gets when its parent dies


class _StartedHelper:
    """The helper process early_helper forked: its pid, whether it lives, waiting for its end
    and ending it."""

    def __init__(self, pid: int):
        self.pid = pid
        self._ended = False

    def is_alive(self) -> bool:
        if not self._ended:
            try:
                self._ended = os.waitpid(self.pid, os.WNOHANG)[0] != 0
            except ChildProcessError:  # reaped already
                self._ended = True
        return not self._ended

    def join(self, timeout: float | None = None) -> None:
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.is_alive() and (deadline is None or time.monotonic() < deadline):
            time.sleep(0.002)

    def terminate(self) -> None:
        self._signal(signal.SIGTERM)

    def kill(self) -> None:
        self._signal(signal.SIGKILL)

    def _signal(self, number: int) -> None:
        if self.is_alive():
            os.kill(self.pid, number)


def serve(connection, scenario: Scenario, options: dict, parent: int) -> None:
    """The helper's loop: jobs ("stream" or "path", job, warm-start job, entry centre or
    path), their rows and ends, "send" (the job's result back) and "stop"."""
    _end_with(parent)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the main process stops the helper
    logging.disable(logging.CRITICAL)  # the main process reports
    server = _ReplayServer(connection, scenario, options)
    while True:
        try:
            message = server.receive()
        except (EOFError, OSError):
            return
        kind = message[0]
        if kind == "stop":
            return
        if kind == "send":
            if not server.send_back(message[1]):
                return  # the main process is gone
        elif kind in ("stream", "path"):
            server.replay(message)
        # other messages are the rows and end of a dropped job


class _ReplayServer:
    """What the helper keeps between messages: its model (built and factored at once, while
    the main process builds its own model and plans), the messages a streamed replay put back,
    the newest finished job, the replay to take steps over from and the work since the last
    answer."""

    def __init__(self, connection, scenario: Scenario, options: dict):
        self.connection, self.scenario, self.options = connection, scenario, options
        self.tissue = PreparedTissue(scenario)
        try:  # now, while the main process builds its own model and plans
            self.tissue.model
            self.tissue.factor_at_rest()
        except Exception:  # noqa: BLE001 -- the replay meets it again and reports it
            pass
        self.inbox: collections.deque = collections.deque()
        self.done: tuple = (None, None, None)  # the newest finished job: (job, result, error)
        # the newest replay made from no earlier one, or the steps it had done when dropped
        self.alone: InsertionResult | StepsDone | None = None
        self.steps_run = 0  # needle steps of every replay since the last answer, dropped ones too
        self.sent: tuple[int | None, InsertionResult | None] = (None, None)  # the replay last sent back

    def receive(self):
        return self.inbox.popleft() if self.inbox else self.connection.recv()

    def pending(self) -> bool:
        return bool(self.inbox) or self.connection.poll()

    def send_back(self, job) -> bool:
        """Answer "send": the finished job's result (or why there is none) and the steps run
        since the last answer; False if the main process is gone."""
        finished, result, error = self.done
        if finished != job:
            result, error = None, RuntimeError(f"no replay for job {job}")
        try:
            # without its states and its model's matrices (~27 MB on the refined SH 1/2 model,
            # ~0.1 s to pickle, send and load): the command reads only the outline of a replay's model
            self.connection.send(("result", job,
                                  None if result is None else replace(result, states=[], model=result.model.outline()),
                                  error, self.steps_run))
        except OSError:
            return False
        self.steps_run = 0
        self.sent = (job, result)
        return True

    def replay(self, message: tuple) -> None:
        """Run a "stream" or "path" job to its end, or until a newer message drops it."""
        kind, job, warm, payload = message[0], message[1], message[2], message[3]
        start = self.sent[1] if warm is not None and warm == self.sent[0] else None
        # a replay from no earlier one takes over the steps where its centres are those of the
        # last such replay (a re-aimed pass keeps the first pass's early steps), to the last bit
        # what it would compute
        take_over_only = warm is None and self.alone is not None
        if take_over_only:
            start = self.alone
        if kind == "stream":
            control, path = _StreamedPath(self.receive, self.pending, self.inbox, message), None
        else:
            control, path = None, payload
        try:
            result, error = run_insertion(self.scenario, control=control, center_path=path, tissue=self.tissue,
                                          start_from=start, take_over_only=take_over_only, **self.options), None
        except _Superseded as dropped:
            self.steps_run += control.steps
            if warm is None and dropped.done is not None and dropped.done.steps:
                self.alone = dropped.done  # the pass that dropped it keeps its first centres
            return
        except StitchplanError as failure:
            result, error = None, failure
        except Exception as failure:  # noqa: BLE001 -- the main process replays and reports it
            result, error = None, RuntimeError(f"{type(failure).__name__}: {failure}")
        self.done = (control.job if kind == "stream" else job, result, error)
        if warm is None and result is not None:
            self.alone = result
        self.steps_run += len(result.steps) if result is not None else getattr(control, "steps", 0)
