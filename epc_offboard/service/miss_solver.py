"""EPC's miss path off the control loop: full QP solves in a worker process.

On a library miss the tick applies the intermediate controller at once (thesis 3.1.3) and
the controller queues the parameter vector θ (``ExperienceController(learn_on_miss=False)``,
its ``pending``). :class:`MissSolver` takes those θ, solves the full QP, recovers and
verifies its active set in ONE worker process (fed through two pipes, :class:`MissSolver`
says why; each problem is sent once, at start, then only θ travels), and hands
the active set back with its KKT map, built there (0.3-1.3 ms of factorisation and products
for the position problem that the loop's tick no longer pays). The loop adds it only after
its own KKT check passes at that θ (:meth:`ExperienceController.add_built`; a map for another
model is built on the loop by :meth:`ExperienceController.add_solved`). A 10-30 ms solve never
stalls the loops: on a real PX4 in wind it starved the 200 Hz attitude loop and, in
body-rate mode, flipped the vehicle.

* one solve in flight per controller; further misses wait in a small bounded buffer, and
  those the returning controller already covers are dropped (a region is solved once);
* the worker's death is survived: a new one is started, the lost solve counted; so is its
  wedging (SIGSTOP, starvation): a request unanswered for ``wedged_s``;
* ``wait=True`` (lockstep simulation) blocks until the solve in flight has returned, so the
  result enters the library at the same tick every run: deterministic.

Fleet candidates (:class:`~epc_offboard.control.epc.candidates.CandidatePool`) are screened
here too, so a flood of received controllers costs the loops nothing but bookkeeping: the loop's
controller keeps the bounded pool of active sets, the worker a copy with their maps, built
in slices bounded by its CPU time (``slice_s``) between solves. A miss is first checked against
the built candidates; one that passes is handed back with its origin instead of a solve,
and the loop promotes it after its own KKT check at that θ. Candidates never optimal for a
real tick stay in the pool until newer ones push them out: they never take library slots.

Once a peer's candidate has been promoted (the peer is *proven*), the loop's pool refocuses
that peer's quota on the controllers likely next (its transitions after the controller in
use) and asks the worker for their maps (:meth:`ExperienceController.wanted_maps`): the
worker builds them in the same slices and hands the maps back, and the loop checks them
before it counts a miss — mat-vecs, no factorisation on the loop. That is what lets a late
joiner fly on the fleet's library instead of missing once per region; memory stays bounded
by the pool's size in maps, the rest of a snapshot waiting as tuples. In lockstep (``wait``)
the wanted maps (at most a few per slice) are a count, not a time, and the slice is waited
for, so maps arrive at the same tick every run.

The worker builds no controller: per problem it holds the full QP's
:class:`~epc_offboard.control.epc.learner.Learner`, the
:class:`~epc_offboard.control.epc.maps.MapBuilder` and its copy of the candidate pool.

No asyncio here: :meth:`pump` is called from the position loop's tick.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import select
import sys
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import TYPE_CHECKING, Any, Generic, TypeVar, cast

import numpy as np

from epc_offboard.common import logpipe
from epc_offboard.common.channel import (
    ChannelClosedError,
    FrameInbox,
    FrameOutbox,
    read_frames,
    write_frame,
)
from epc_offboard.common.children import (
    KILL_WAIT_S,
    die_with_parent,
    enlarge_pipe,
    join_or_kill,
    spawn_fed,
)
from epc_offboard.common.errors import EpcError
from epc_offboard.common.frames import FloatArray
from epc_offboard.common.procstats import WATCH_EVERY_S, StartWatch, process_report
from epc_offboard.control import kernels
from epc_offboard.control.epc.candidates import CandidatePool
from epc_offboard.control.epc.learner import Learner
from epc_offboard.control.epc.maps import ActiveSetMap, DependentActiveSetError, MapBuilder
from epc_offboard.control.library_types import LibraryEntry
from epc_offboard.control.qp import MpcProblem

if TYPE_CHECKING:  # the loop's side only: the worker never builds a controller
    from epc_offboard.control.epc.controller import ExperienceController

log = logging.getLogger(__name__)
# close(): the task in flight returns and the worker ends within this (a slice's solve is
# tens of ms; at load 6 a few hundred), inside the unit's TimeoutStopSec (5 s) with the rest
STOP_TIMEOUT_S = 2.0
# its start (imports, problems, learners) is judged by progress (StartWatch): it fails once
# the worker used and waited for no CPU this long (SIGSTOP, a block), or was not up in the
# cap though running; a clock did not hold: 93-156 s at load 12-17, every second running
START_TIMEOUT_S = 30.0
START_CAP_S = 600.0
WAIT_TIMEOUT_S = 30.0  # lockstep's wait for an answer: longer, and the worker is wedged
WEDGED_S = 10.0  # real time: a request unanswered that long (a solve is tens of ms)
_PIPE_BYTES = 1 << 20  # each pipe (Linux's default ceiling): a reply with its maps in one read
# requests waiting for room in the pipe: the problems (1.2 MB) at the start, then a solve's θ
# and a slice's candidates per lane at a time; beyond, the worker takes nothing: wedged
_MAX_PENDING_BYTES = 16 << 20
_T = TypeVar("_T")

# an active set, its origin ("solved" or a peer's) and its map, built here: the loop only
# checks it (building it there cost 0.3-1.3 ms, most of a miss tick's time)
Found = tuple[tuple[int, ...], str, ActiveSetMap | None]
Built = list[tuple[tuple[int, ...], ActiveSetMap | None]]
_MAX_WANTED = 8  # candidate maps asked of the worker per slice (it builds what its time allows)
_RECENT = 8  # active sets the worker remembers having solved (not screened again as offers)


@dataclass
class _Worker:
    """The worker's state for one problem: the full QP, the map builder, its copy of the
    candidate pool (no backlog: the loop's pool keeps that and asks for maps), and the sets
    it solved last (an offer of one of those is not screened again)."""

    builder: MapBuilder
    learner: Learner
    pool: CandidatePool
    recent: OrderedDict[tuple[int, ...], None] = field(default_factory=OrderedDict)

    def solved(self, active: tuple[int, ...]) -> None:
        self.pool.take(active)  # solved here: no longer a candidate
        self.recent[active] = None
        if len(self.recent) > _RECENT:
            self.recent.popitem(last=False)

    def screen(self, theta_aug: FloatArray, budget_s: float) -> Found | None:
        """A pool candidate optimal at ``theta_aug``, taken out of the pool, with its origin
        and map: the worker's half of a promotion (the loop checks it again). Builds for up
        to ``budget_s`` first."""
        self.pool.build(self.builder.build, budget_s)
        p = self.builder.problem
        found = self.pool.find(theta_aug, np.empty(p.nu), p.u_min, p.u_max)
        if found is None:
            return None
        active, cand = found
        self.pool.take(active)
        if cand.map is None:  # find() returns built candidates only
            return None
        return active, cand.origin, cand.map

    def build_maps(self, actives: list[tuple[int, ...]], budget_s: float | None) -> Built:
        """Maps for ``actives`` (None where the rows are dependent), reusing the pool's,
        until ``budget_s`` of the worker's CPU time is spent (at least one), as
        :meth:`CandidatePool.build`."""
        t0 = time.thread_time()
        out: Built = []
        for active in actives:
            if budget_s is not None and out and time.thread_time() - t0 >= budget_s:
                break
            amap = self.pool.map_of(active)
            if amap is None:
                try:
                    amap = self.builder.build(active)
                except DependentActiveSetError:
                    amap = None
            out.append((active, amap))
        return out


# worker-process state: one per problem, built once by the first request
_WORKERS: dict[str, _Worker] = {}


def _init_worker(problems: dict[str, tuple[MpcProblem, float, int, int]]) -> bool:
    kernels.warm_up()  # the KKT check's compiled scan: before the first solve, not in it
    _WORKERS.clear()
    for name, (problem, tol, pool, per_origin) in problems.items():
        builder = MapBuilder(problem, tol)
        _WORKERS[name] = _Worker(builder, Learner(builder),
                                 CandidatePool(pool, per_origin, pool, per_origin))
    return True


def _worker_main(requests: Connection, parent_pid: int, replies: Connection) -> None:
    """The worker process: each request ``(seq, fn, args)`` run in order, answered
    ``(seq, ok, value or the error)``; ends at the requests' EOF or when its answer finds
    the replies' pipe closed (the service stopping)."""
    die_with_parent(parent_pid)  # no 168 MB orphan when the service is SIGKILLed
    logpipe.direct_stderr()  # its warnings: a held stderr (journald) holds no solve
    out = replies.fileno()
    with contextlib.suppress(ChannelClosedError):
        for seq, fn, args in read_frames(requests.fileno()):
            try:
                answer = (seq, True, fn(*args))
            except Exception as exc:  # said to the service, which counts it
                answer = (seq, False, f"{type(exc).__name__}: {exc}")
            write_frame(out, answer)
    # it holds no file, and nothing else waits: no interpreter teardown (its 168 MB of
    # objects and compiled kernels, freed one by one: most of a second at load 13, and
    # beside two hogs beyond the service's 2 s for the stop)
    sys.stderr.flush()
    os._exit(0)


def _solve(name: str, theta: FloatArray, slice_s: float) -> Found | None:
    worker = _WORKERS[name]
    theta_aug = np.append(np.asarray(theta, dtype=np.float64), 1.0)
    found = worker.screen(theta_aug, slice_s)
    if found is not None:
        return found
    amap = worker.learner.solve(theta_aug, np.empty(worker.builder.problem.nu))
    if amap is None:
        return None
    worker.solved(amap.active)
    return amap.active, "solved", amap


def _offer(
    name: str, items: list[tuple[tuple[int, ...], str]], wanted: list[tuple[int, ...]],
    slice_s: float | None,
) -> tuple[int, Built]:
    """Copy candidates into the worker's pool; build the maps the loop wants for one slice,
    or, when it wants none, a slice of the pool's. Returns how many of the pool's wait
    unbuilt, and the maps built for the loop."""
    worker = _WORKERS[name]
    for active, origin in items:
        worker.pool.offer_checked(worker.builder.check_entry, worker.recent,
                                  [LibraryEntry(active)], origin)
    if wanted:
        built = worker.build_maps(wanted, slice_s)
    else:
        built = []
        worker.pool.build(worker.builder.build, slice_s)
    return worker.pool.unbuilt, built


class _WorkerError(EpcError, RuntimeError):
    """A request the worker answered with an error (a solve that raised)."""


@dataclass(eq=False)
class _Reply(Generic[_T]):
    """A request's answer, ``done`` once the worker's reply has been read."""

    sent_s: float
    done: bool = False
    ok: bool = False
    value: Any = None

    def result(self) -> _T:
        if not self.ok:
            raise _WorkerError(self.value)
        return cast(_T, self.value)


@dataclass
class _Process:
    """The worker process and its two pipes: requests out (bounded, never blocking) and
    replies in (read without blocking, a bounded amount per call)."""

    proc: BaseProcess
    outbox: FrameOutbox
    inbox: FrameInbox
    conns: tuple[Connection, Connection]
    ready: _Reply[bool]
    watch: StartWatch  # its start's progress
    replies: dict[int, _Reply[Any]] = field(default_factory=dict)
    next_seq: int = 0
    ready_waited: bool = False  # whether a read has started the start's clock

    def close(self) -> None:
        for conn in self.conns:  # its EOF; its answer finds a closed pipe
            conn.close()


@dataclass
class _Lane:
    """One controller's queue: at most one solve in flight, a few waiting."""

    ctrl: ExperienceController
    waiting: deque[FloatArray]
    in_flight: _Reply[Found | None] | None = None
    in_flight_theta: FloatArray | None = None
    offer: _Reply[tuple[int, Built]] | None = None  # candidates copied / maps built there
    unbuilt: int = 0  # candidate maps the worker still has to build (its last report)
    resend: list[tuple[tuple[int, ...], str]] = field(default_factory=list)  # after a restart
    model_epoch: int = 0  # the controller's model when the worker got its problem


class MissSolver:
    """``slice_s``: the most CPU time the worker spends building candidate maps before it
    takes the next solve (a flood must not delay the misses of the flight). ``wedged_s``:
    in real time, a request unanswered that long means a wedged worker (SIGSTOPped, or
    starved): it is killed and restarted.

    The worker is one ``spawn``-ed process fed through two pipes (:mod:`common.channel`),
    and this side of them never blocks and starts no thread: the requests go out through a
    bounded :class:`~epc_offboard.common.channel.FrameOutbox`, the answers are read by
    :meth:`pump` itself. A ``ProcessPoolExecutor`` here had a manager and a queue-feeder
    thread in the control process: they took its interpreter lock to pickle, read and
    unpickle, at their own priority, and a CPU hog that preempted one holding the lock
    stalled the loops (146 ms to 1.4 s, issue 21); raised to FIFO they still took the lock
    whenever the worker answered. Now every byte of it is moved by the loops' thread, at a
    time the loop chose, bounded per call."""

    def __init__(
        self,
        controllers: dict[str, ExperienceController],
        *,
        max_waiting: int = 4,
        slice_s: float = 0.005,
        wedged_s: float = WEDGED_S,
    ) -> None:
        self._slice_s = slice_s
        self._wedged_s = wedged_s
        self._lanes = {
            name: _Lane(c, deque(maxlen=max_waiting)) for name, c in controllers.items()
        }
        self.counters: Counter[str] = Counter()
        self._worker: _Process | None = None
        self._killed: list[BaseProcess] = []  # not yet reaped
        self._start_timeout_s = START_TIMEOUT_S
        self._start_error: BaseException | None = None

    def start(self, timeout_s: float = START_TIMEOUT_S, *, wait: bool = True) -> None:
        """Start the worker and wait until it has imported and built its learners (before
        READY: a worker that cannot start is an error now, not mid-flight). ``wait`` False:
        return at once and :meth:`wait_ready` or :meth:`poll_ready` later (its start overlaps
        other work; until it is up, :meth:`pump` keeps the misses waiting)."""
        self._start_timeout_s = timeout_s
        self._start_error = None
        try:
            self._spawn()
        except Exception as exc:
            if wait:
                raise
            self._start_error = exc  # said by wait_ready
            return
        if wait:
            self.wait_ready(timeout_s)

    def _spawn(self) -> None:
        """Spawn the worker (from the loops' thread, which lives as long as the process:
        the worker's parent-death signal follows the thread that started it) and send it
        its problems. They are 1.2 MB, more than a pipe takes, and the worker reads them
        only once it has imported all that unpickling them needs (a second on a quiet
        machine, 7 s at load 15 beside a real PX4): the outbox writes what the pipe takes
        now, :meth:`pump` the rest."""
        problems = {
            name: (lane.ctrl.problem, lane.ctrl.tol, lane.ctrl.candidates.max_size,
                   lane.ctrl.candidates.max_per_origin)
            for name, lane in self._lanes.items()
        }  # fmt: skip
        for lane in self._lanes.values():  # maps the worker builds are for this model
            lane.model_epoch = lane.ctrl.model_epoch
        ctx = multiprocessing.get_context("spawn")
        replies_r, replies_w = ctx.Pipe(duplex=False)
        enlarge_pipe(replies_r, _PIPE_BYTES)  # a reply with its maps in one read
        try:
            proc, requests_w = spawn_fed(_worker_main, "epc-miss-worker", replies_w,
                                         pipe_bytes=_PIPE_BYTES)  # fmt: skip
        except BaseException:
            replies_r.close()
            raise
        finally:
            replies_w.close()  # the worker's end: EOF here when it dies
        now = time.monotonic()
        worker = _Process(
            proc, FrameOutbox(requests_w.fileno(), _MAX_PENDING_BYTES),
            FrameInbox(replies_r.fileno(), _PIPE_BYTES), (requests_w, replies_r), _Reply(now),
            StartWatch(proc.pid or 0, self._start_timeout_s, START_CAP_S),
        )  # fmt: skip
        self._worker = worker
        self._send(worker, worker.ready, _init_worker, problems)

    @staticmethod
    def _send(worker: _Process, reply: _Reply[Any], fn: Callable[..., Any],
              *args: object) -> bool:
        """Queue ``fn(*args)`` for the worker (False: the outbox is full, the worker takes
        nothing); ChannelClosedError if it is gone."""
        seq = worker.next_seq
        if not worker.outbox.send((seq, fn, args)):
            return False
        worker.next_seq += 1
        worker.replies[seq] = reply
        return True

    def poll_ready(self) -> bool:
        """Whether the worker is up, never blocking (the real-time start's wait).
        RuntimeError if it failed to start, TimeoutError if it did not within the start's
        timeout."""
        worker = self._worker
        if worker is None:
            raise RuntimeError(f"EPC miss worker did not start: {self._start_error}")
        self._read(worker, wait=False, restart=False)
        if worker.ready.done:
            if not worker.ready.ok:
                raise RuntimeError(f"EPC miss worker did not start: {worker.ready.value}")
            return True
        if self._worker is not worker or not worker.proc.is_alive():
            raise RuntimeError("EPC miss worker died in its start")
        why = worker.watch.verdict_every(WATCH_EVERY_S)  # its death: is_alive, above
        if why is not None:
            raise TimeoutError(f"EPC miss worker not started: {why}")
        return False

    def wait_ready(self, timeout_s: float = START_TIMEOUT_S) -> None:
        """Wait until a worker started with ``start(wait=False)`` is up; TimeoutError once
        it made no progress for ``timeout_s`` (or was not up in START_CAP_S)."""
        self._start_timeout_s = timeout_s
        if self._worker is not None:
            self._worker.watch.stall_s = timeout_s
        while not self.poll_ready():
            self._wait_io(self._worker, 0.5)

    def close(self, timeout_s: float = STOP_TIMEOUT_S, reap_s: float = KILL_WAIT_S) -> None:
        """Stop the worker: the EOF of its requests, and its answer in flight refused (the
        replies' pipe closed), end it after the request it works on. A worker that does not
        end in ``timeout_s`` is killed all the same (waited ``reap_s`` more), counted
        (``worker_stop_timeouts``); the service's bounded exit covers the rest."""
        worker, self._worker = self._worker, None
        if worker is None:
            return
        worker.close()
        if not join_or_kill(worker.proc, timeout_s, reap_s):
            self.counters["worker_stop_timeouts"] += 1
            log.warning("EPC miss worker not stopped in %.1f s: killed", timeout_s)

    def _up(self, wait: bool) -> bool:
        """Read what the worker answered; whether it is up and takes requests (``wait``:
        waits for its start)."""
        if self._killed:
            self._reap()
        worker = self._worker
        if worker is None:
            return False
        self._read(worker, wait)
        worker = self._worker
        if worker is not None and wait and not worker.ready.done:
            self._wait(worker.ready, self._start_timeout_s)
            worker = self._worker
        if worker is None or not worker.ready.done:
            return False
        if not worker.ready.ok:  # the loops fly on: misses stay intermediate
            log.error("EPC miss worker did not start: %s", worker.ready.value)
            self._stop_now()
            return False
        return True

    def _read(self, worker: _Process, wait: bool, *, restart: bool = True) -> None:
        """Write what waits for the worker, read its answers; a worker gone or wedged is
        restarted (``restart``)."""
        if not worker.ready_waited:  # the start's clock runs from the first write after the
            worker.ready_waited = True  # spawn: until then no one fed it the rest of its
            worker.ready.sent_s = time.monotonic()  # problems (a cold warm-up: 50 s and more)
            worker.watch.restart_clock(worker.ready.sent_s)
        try:
            worker.outbox.flush()
            # Nothing asked, nothing to read: the worker writes only answers. The read of an
            # empty pipe was a system call and an exception on every position tick, 30-45
            # us of the tick in real time (issue 21); a worker that died meanwhile is found
            # by the next request's write, or by this read once one is in flight.
            if worker.replies:
                for seq, ok, value in worker.inbox.read():
                    reply = worker.replies.pop(seq, None)
                    if reply is not None:
                        reply.done, reply.ok, reply.value = True, ok, value
        except ChannelClosedError:
            if restart:
                self._restart("the worker died", wait)
            return
        if not restart or not worker.replies:
            return
        now = time.monotonic()
        answer_s = WAIT_TIMEOUT_S if wait else self._wedged_s
        for reply in worker.replies.values():
            if reply is worker.ready:
                # asked every WATCH_EVERY_S, not every tick (two /proc reads): a worker
                # that dies meanwhile is its replies' EOF above, at the next tick
                why = worker.watch.verdict_every(WATCH_EVERY_S, now)
                if why is not None:
                    self._restart(f"not started: {why}", wait)
                    return
            elif now - reply.sent_s > answer_s:
                self._restart(f"no answer in {answer_s:g} s (wedged)", wait)
                return

    def _wait_io(self, worker: _Process | None, timeout_s: float) -> None:
        """Block until the worker's answer or room for what waits for it, or ``timeout_s``."""
        if worker is None or timeout_s <= 0.0:
            return
        out = [worker.outbox.fd] if worker.outbox.pending_bytes else []
        with contextlib.suppress(OSError, ValueError):  # a pipe closed meanwhile: read says
            select.select([worker.inbox.fd], out, [], min(timeout_s, 0.5))

    def _wait(self, reply: _Reply[Any], timeout_s: float) -> None:
        """Block (lockstep) until ``reply`` is done or its worker was restarted; a worker
        silent for ``timeout_s`` is wedged: restarted."""
        deadline = time.monotonic() + timeout_s
        while not reply.done:
            worker = self._worker
            if worker is None or reply not in (worker.ready, *worker.replies.values()):
                return  # restarted meanwhile: the request is lost
            if reply is worker.ready:  # its start: judged by its progress (_read)
                deadline = time.monotonic() + timeout_s
            if time.monotonic() >= deadline:
                self._restart(f"no answer in {timeout_s:g} s (wedged)", wait=True)
                return
            self._wait_io(worker, deadline - time.monotonic())
            self._read(worker, wait=True)

    def _stop_now(self) -> None:
        worker, self._worker = self._worker, None
        if worker is not None:
            worker.close()
            worker.proc.kill()
            self._killed.append(worker.proc)
        self._reap()

    def _reap(self) -> None:
        """Reap the killed workers that have ended (no wait: SIGKILL takes a moment)."""
        for proc in self._killed:
            proc.join(0.0)
        self._killed = [proc for proc in self._killed if proc.exitcode is None]

    def pump(self, *, wait: bool = False, mark: Callable[[int], None] | None = None) -> int:
        """Collect returned solves into the libraries, queue new misses, submit the next.

        Returns the number of controllers added. ``wait``: block until every solve in flight
        has returned first (lockstep). ``mark``: called with 0 after each lane's collect
        (the worker's answers read, solves joined), 1 after its candidates' offer (maps
        attached) and 2 after its submit: the step's parts (``step_parts.StepParts.part``).
        """
        added = 0
        up = self._up(wait)  # else the misses wait for the worker's start
        for name, lane in self._lanes.items():
            if up:
                added += self._collect(name, lane, wait)
            if mark is not None:
                mark(0)
            self._queue_pending(lane)
            if up:
                self._offer_next(name, lane, wait)  # first: the worker takes tasks in order
                if mark is not None:
                    mark(1)
                self._submit_next(name, lane, wait)
            if mark is not None:
                mark(2)
        return added

    def hand_over(self, *, wait: bool = False) -> int:
        """The misses of the tick just run, handed to the worker at its end, not at the next
        tick's :meth:`pump`: the solve runs between the ticks and joins the library at the
        next one (in lockstep, always). Queued at the next tick instead, a new active set
        missed twice (lockstep) or more: of the Neural-Fly 12.1 m/s row's 332 misses, 130
        were queued again while their first was still unsolved (issue 24). Collects a solve
        in flight first (``wait``: blocks for it, as :meth:`pump`); no candidate traffic.
        Returns the number of controllers added."""
        if not any(lane.ctrl.pending for lane in self._lanes.values()) or not self._up(wait):
            return 0
        added = 0
        for name, lane in self._lanes.items():
            if not lane.ctrl.pending:
                continue
            added += self._collect(name, lane, wait)
            self._queue_pending(lane)
            self._submit_next(name, lane, wait)
        return added

    def drain(self, timeout_s: float = WAIT_TIMEOUT_S) -> None:
        """Block until every request in flight is answered (not collected: :meth:`pump`
        does), or ``timeout_s``: a benchmark's untimed wait."""
        deadline = time.monotonic() + timeout_s
        while (worker := self._worker) is not None and worker.replies:
            if time.monotonic() >= deadline:
                return
            self._wait_io(worker, deadline - time.monotonic())
            self._read(worker, wait=True)

    def _queue_pending(self, lane: _Lane) -> None:
        ctrl = lane.ctrl
        while ctrl.pending:
            if len(lane.waiting) == lane.waiting.maxlen:
                self.counters["misses_dropped"] += 1  # the oldest gives way
            lane.waiting.append(ctrl.pending.pop(0))

    def _result(self, reply: _Reply[_T], wait: bool) -> _Reply[_T] | None:
        """``reply`` once it is done (``wait``: blocks for it); None while it is not, or if
        the worker was restarted meanwhile (the request is lost)."""
        if wait and not reply.done:
            self._wait(reply, WAIT_TIMEOUT_S)
        return reply if reply.done else None

    def _offer_next(self, name: str, lane: _Lane, wait: bool) -> None:
        """Copy new candidates to the worker, have it build the maps the loop wants or a
        slice of its pool's, and attach the maps it returned (one task in flight per lane;
        the pool's own bounds keep what waits here bounded)."""
        ctrl = lane.ctrl
        if lane.offer is not None:
            reply = self._result(lane.offer, wait)
            if reply is None and lane.offer is not None:
                return  # not answered yet
            lane.offer = None
            if reply is not None:
                try:
                    lane.unbuilt, built = reply.result()
                    self.counters["candidate_maps_attached"] += ctrl.attach_maps(
                        built, lane.model_epoch
                    )
                except Exception as exc:  # candidates lost; the flight is not
                    self.counters["candidate_errors"] += 1
                    log.warning("%s candidate import failed: %s", name, exc)
        fresh = lane.resend + ctrl.candidates.pop_fresh()
        lane.resend = []
        wanted: list[tuple[int, ...]] = []
        if ctrl.model_epoch == lane.model_epoch:  # else the worker's maps would be stale
            ctrl.focus_candidates()
            wanted = ctrl.wanted_maps(_MAX_WANTED)
        if not (fresh or lane.unbuilt or wanted):
            return
        # lockstep: the wanted maps (at most _MAX_WANTED) are a count, whatever the machine's
        # speed, so the loop checks the same maps at the same tick every run
        slice_s: float | None = None if wait and wanted else self._slice_s
        lane.offer = self._submit("candidates", wait, _offer, name, fresh, wanted, slice_s)
        if lane.offer is None:
            return
        self.counters["candidate_maps_wanted"] += len(wanted)
        self.counters["candidates_sent"] += len(fresh)
        self.counters["candidate_slices"] += 1

    def _collect(self, name: str, lane: _Lane, wait: bool) -> int:
        if lane.in_flight is None:
            return 0
        reply = self._result(lane.in_flight, wait)
        if reply is None:
            return 0  # not answered yet, or lost with a dead worker (counted there)
        theta = lane.in_flight_theta
        lane.in_flight = lane.in_flight_theta = None
        try:
            active = reply.result()
        except _WorkerError as exc:  # a solve that raised: the miss stays a miss
            self.counters["solve_errors"] += 1
            log.warning("%s miss solve failed: %s", name, exc)
            return 0
        self.counters["solves_returned"] += 1
        if active is None or theta is None:
            self.counters["solves_without_controller"] += 1
            return 0
        aset, origin, amap = active
        if origin != "solved":
            self.counters["candidates_found"] += 1
        added = None if amap is None else lane.ctrl.add_built(theta, amap, lane.model_epoch,
                                                              origin)
        if added is None:  # no map, or one for another model: the loop builds it
            self.counters["maps_built_on_the_loop"] += 1
            added = lane.ctrl.add_solved(theta, aset, origin)
        if not added:
            self.counters["solves_refused_by_kkt_check"] += 1
            return 0
        return 1

    def _submit_next(self, name: str, lane: _Lane, wait: bool) -> None:
        # after a restart the new worker's pool is filled first (``resend``, the next
        # offer): a solve sent before it would screen an empty pool
        if lane.in_flight is not None or self._worker is None or lane.resend:
            return
        while lane.waiting:
            theta = lane.waiting.popleft()
            if lane.ctrl.covers(theta):
                self.counters["misses_already_covered"] += 1  # solved meanwhile: once only
                continue
            lane.in_flight = self._submit("a solve", wait, _solve, name, theta, self._slice_s)
            if lane.in_flight is None:
                return
            lane.in_flight_theta = theta
            self.counters["solves_submitted"] += 1
            return

    def _submit(
        self, what: str, wait: bool, fn: Callable[..., _T], *args: object
    ) -> _Reply[_T] | None:
        """Hand ``fn(*args)`` to the worker; None, and the worker restarted, if it cannot
        (gone, or so wedged that the outbox's bound is reached)."""
        worker = self._worker
        if worker is None or not worker.ready.done:
            return None
        reply: _Reply[_T] = _Reply(time.monotonic())
        try:
            if self._send(worker, reply, fn, *args):
                return reply
        except ChannelClosedError:
            pass
        self._restart(f"the worker could not take {what}", wait)
        return None

    def _restart(self, why: str, wait: bool) -> None:
        """A new worker for a dead or wedged one (killed first). Its start does not block
        the loops (``wait``, lockstep: it is waited for, so the next request meets it up);
        until it is up the misses wait, as at the start."""
        self.counters["worker_restarts"] += 1
        log.error("EPC miss worker: %s; restarting it", why)
        for lane in self._lanes.values():
            lane.in_flight = lane.in_flight_theta = lane.offer = None
            # the new worker's pool starts empty: send it every candidate again
            lane.ctrl.candidates.pop_fresh()
            lane.resend = lane.ctrl.candidates.items()
        self._stop_now()
        try:
            self._spawn()
            if wait:
                self.wait_ready(self._start_timeout_s)
        except Exception as exc:  # the loops fly on: misses stay intermediate
            self._stop_now()
            log.error("EPC miss worker cannot restart: %s", exc)

    @property
    def in_flight(self) -> int:
        return sum(lane.in_flight is not None for lane in self._lanes.values())

    def process_stats(self) -> dict[str, Any]:
        """The worker process: CPU, what waits for it, its restarts."""
        return process_report(
            self.worker_pid(), restarts=self.counters["worker_restarts"],
            in_flight=self.in_flight, waiting=sum(len(ln.waiting) for ln in self._lanes.values()),
            dropped=self.counters["misses_dropped"],
        )  # fmt: skip

    def worker_pid(self) -> int | None:
        """The worker process's pid (fault tests kill it)."""
        return None if self._worker is None else self._worker.proc.pid
