"""EPC's miss path off the control loop: full QP solves in a worker process.

On a library miss the tick applies the intermediate controller at once (thesis 3.1.3) and
the controller queues the parameter vector θ (``ExperienceController(learn_on_miss=False)``,
its ``pending``). :class:`MissSolver` takes those θ, solves the full QP, recovers and
verifies its active set in ONE worker process (a standard
``ProcessPoolExecutor``; each problem is sent once, at start, then only θ travels), and hands
the active set back with its KKT map, built there (0.3-1.3 ms of factorisation and products
for the position problem that the loop's tick no longer pays). The loop adds it only after
its own KKT check passes at that θ (:meth:`ExperienceController.add_built`; a map for another
model is built on the loop by :meth:`ExperienceController.add_solved`). A 10-30 ms solve never
stalls the loops: on a real PX4 in wind it starved the 200 Hz attitude loop and, in
body-rate mode, flipped the vehicle.

* one solve in flight per controller; further misses wait in a small bounded buffer, and
  those the returning controller already covers are dropped (a region is solved once);
* the worker's death is survived: the pool is rebuilt, the lost solve counted;
* ``wait=True`` (lockstep simulation) blocks until the solve in flight has returned, so the
  result enters the library at the same tick every run: deterministic.

Fleet candidates (:class:`~epc_offboard.control.epc.candidates.CandidatePool`) are screened
here too, so a flood of received controllers costs the loops nothing but bookkeeping: the loop's
controller keeps the bounded pool of active sets, the worker a copy with their maps, built
in slices bounded by time (``slice_s``) between solves. A miss is first checked against
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

import logging
import multiprocessing
import os
import threading
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from epc_offboard.common.children import die_with_parent
from epc_offboard.common.frames import FloatArray
from epc_offboard.common.procstats import process_report
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
        until ``budget_s`` is spent (at least one)."""
        t0 = time.perf_counter()
        out: Built = []
        for active in actives:
            if budget_s is not None and out and time.perf_counter() - t0 >= budget_s:
                break
            amap = self.pool.map_of(active)
            if amap is None:
                try:
                    amap = self.builder.build(active)
                except DependentActiveSetError:
                    amap = None
            out.append((active, amap))
        return out


# worker-process state: one per problem, built once by the initializer
_WORKERS: dict[str, _Worker] = {}


def _init_worker(
    problems: dict[str, tuple[MpcProblem, float, int, int]], parent_pid: int
) -> None:
    die_with_parent(parent_pid)  # no 168 MB orphan when the service is SIGKILLed
    kernels.warm_up()  # the KKT check's compiled scan: before the first solve, not in it
    _WORKERS.clear()
    for name, (problem, tol, pool, per_origin) in problems.items():
        builder = MapBuilder(problem, tol)
        _WORKERS[name] = _Worker(builder, Learner(builder),
                                 CandidatePool(pool, per_origin, pool, per_origin))


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


def _ping() -> bool:
    return True


@dataclass
class _Lane:
    """One controller's queue: at most one solve in flight, a few waiting."""

    ctrl: ExperienceController
    waiting: deque[FloatArray]
    in_flight: Future[Found | None] | None = None
    in_flight_theta: FloatArray | None = None
    offer: Future[tuple[int, Built]] | None = None  # candidates copied / maps built there
    unbuilt: int = 0  # candidate maps the worker still has to build (its last report)
    resend: list[tuple[tuple[int, ...], str]] = field(default_factory=list)  # after a restart
    model_epoch: int = 0  # the controller's model when the worker got its problem


class MissSolver:
    """``slice_s``: the most CPU time the worker spends building candidate maps before it
    takes the next solve (a flood must not delay the misses of the flight)."""

    def __init__(
        self,
        controllers: dict[str, ExperienceController],
        *,
        max_waiting: int = 4,
        slice_s: float = 0.005,
    ) -> None:
        self._slice_s = slice_s
        self._lanes = {
            name: _Lane(c, deque(maxlen=max_waiting)) for name, c in controllers.items()
        }
        self.counters: Counter[str] = Counter()
        self._pool: ProcessPoolExecutor | None = None
        self._ready: Future[Any] | None = None
        # start(wait=False): the thread that spawned the worker, parked until close() (the
        # worker's PR_SET_PDEATHSIG fires when the spawning THREAD ends), and whether it has
        # handed the worker its problems
        self._spawning: threading.Thread | None = None
        self._handed = threading.Event()
        self._release = threading.Event()
        self._spawn_error: BaseException | None = None

    def start(self, timeout_s: float = 30.0, *, wait: bool = True) -> None:
        """Start the worker and wait until it has imported and built its learners (before
        READY: a worker that cannot start is an error now, not mid-flight). ``wait`` False:
        return at once and :meth:`wait_ready` later (its start overlaps other work; until
        it is up, :meth:`pump` keeps the misses waiting)."""
        problems = {
            name: (lane.ctrl.problem, lane.ctrl.tol, lane.ctrl.candidates.max_size,
                   lane.ctrl.candidates.max_per_origin)
            for name, lane in self._lanes.items()
        }  # fmt: skip
        for lane in self._lanes.values():  # maps the worker builds are for this model
            lane.model_epoch = lane.ctrl.model_epoch
        self._pool = ProcessPoolExecutor(
            max_workers=1,
            mp_context=multiprocessing.get_context("spawn"),  # no fork of a threaded process
            initializer=_init_worker,
            initargs=(problems, os.getpid()),
        )
        self._spawn_error = None
        if wait:
            self._ready = self._pool.submit(_ping)
            self.wait_ready(timeout_s)
            return
        # The first submit spawns the worker and writes it its problems (1.2 MB through a
        # pipe): the write returns only once the worker has imported all that unpickling
        # them needs, a second of this process idle on a quiet machine, 7 s at load 15 beside
        # a real PX4, all of it before the link opened. A thread waits for it instead, and
        # stays (parked) as long as the worker: the worker dies with the thread that
        # spawned it (PR_SET_PDEATHSIG is per thread), as it does with the process.
        self._handed.clear()
        self._spawning = threading.Thread(
            target=self._spawn, args=(self._pool,), name="miss-worker-start", daemon=True
        )
        self._spawning.start()

    def _spawn(self, pool: ProcessPoolExecutor) -> None:
        try:
            self._ready = pool.submit(_ping)
        except BaseException as exc:  # said by wait_ready
            self._spawn_error = exc
        self._handed.set()
        self._release.wait()

    def _spawned(self) -> bool:
        """Whether the pool may be used: a start(wait=False) has handed the worker its
        problems (until then a submit would wait on the pool's lock for that write)."""
        if self._spawning is not None and not self._handed.is_set():
            return False
        return self._spawn_error is None

    def wait_ready(self, timeout_s: float = 30.0) -> None:
        """Wait until a worker started with ``start(wait=False)`` is up."""
        if self._spawning is not None and not self._handed.wait(timeout_s):
            raise TimeoutError(f"EPC miss worker not started in {timeout_s:g} s")
        if self._spawn_error is not None:
            raise RuntimeError(f"EPC miss worker did not start: {self._spawn_error}")
        if self._ready is not None:
            self._ready.result(timeout=timeout_s)
            self._ready = None

    def close(self, timeout_s: float = STOP_TIMEOUT_S) -> None:
        """Stop the worker: its queued tasks cancelled, the one in flight let return, then
        the worker ends by itself; only then the spawning thread (the worker dies with it).
        Killed mid-answer, the worker left the pool's manager thread reading half a message
        for good (the pool's own end of the pipe keeps it open), and the process's exit,
        which joins that thread, waiting on it: a finished `sim` flight's service hung for
        minutes. A worker that does not end in ``timeout_s`` is killed all the same,
        counted (``worker_stop_timeouts``); the service's bounded exit covers the rest."""
        pool, self._pool = self._pool, None
        if pool is not None:
            stopping = threading.Thread(
                target=pool.shutdown, kwargs={"wait": True, "cancel_futures": True},
                name="miss-worker-stop", daemon=True,
            )  # fmt: skip
            stopping.start()
            stopping.join(timeout_s)
            if stopping.is_alive():
                self.counters["worker_stop_timeouts"] += 1
                log.warning("EPC miss worker not stopped in %.1f s: killed", timeout_s)
        self._release.set()  # the spawning thread ends, and with it the worker

    def pump(self, *, wait: bool = False) -> int:
        """Collect returned solves into the libraries, queue new misses, submit the next.

        Returns the number of controllers added. ``wait``: block until every solve in flight
        has returned first (lockstep).
        """
        added = 0
        spawned = self._spawned()  # else the misses wait for the worker's start
        for name, lane in self._lanes.items():
            if spawned:
                added += self._collect(name, lane, wait)
            self._queue_pending(lane)
            if spawned:
                self._offer_next(name, lane, wait)  # first: the worker takes tasks in order
                self._submit_next(name, lane)
        return added

    def hand_over(self, *, wait: bool = False) -> int:
        """The misses of the tick just run, handed to the worker at its end, not at the next
        tick's :meth:`pump`: the solve runs between the ticks and joins the library at the
        next one (in lockstep, always). Queued at the next tick instead, a new active set
        missed twice (lockstep) or more: of the Neural-Fly 12.1 m/s row's 332 misses, 130
        were queued again while their first was still unsolved (issue 24). Collects a solve
        in flight first (``wait``: blocks for it, as :meth:`pump`); no candidate traffic.
        Returns the number of controllers added."""
        if not self._spawned():
            return 0
        added = 0
        for name, lane in self._lanes.items():
            if not lane.ctrl.pending:
                continue
            added += self._collect(name, lane, wait)
            self._queue_pending(lane)
            self._submit_next(name, lane)
        return added

    def _queue_pending(self, lane: _Lane) -> None:
        ctrl = lane.ctrl
        while ctrl.pending:
            if len(lane.waiting) == lane.waiting.maxlen:
                self.counters["misses_dropped"] += 1  # the oldest gives way
            lane.waiting.append(ctrl.pending.pop(0))

    def _offer_next(self, name: str, lane: _Lane, wait: bool) -> None:
        """Copy new candidates to the worker, have it build the maps the loop wants or a
        slice of its pool's, and attach the maps it returned (one task in flight per lane;
        the pool's own bounds keep what waits here bounded)."""
        fut = lane.offer
        ctrl = lane.ctrl
        if fut is not None:
            if not (wait or fut.done()):
                return
            lane.offer = None
            try:
                lane.unbuilt, built = fut.result(timeout=30.0 if wait else 0.0)
                self.counters["candidate_maps_attached"] += ctrl.attach_maps(
                    built, lane.model_epoch
                )
            except BrokenProcessPool:
                self._restart("the worker died")  # then the new one gets the pool, below
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
        lane.offer = self._submit("candidates", _offer, name, fresh, wanted, slice_s)
        if lane.offer is None:
            return
        self.counters["candidate_maps_wanted"] += len(wanted)
        self.counters["candidates_sent"] += len(fresh)
        self.counters["candidate_slices"] += 1

    def _collect(self, name: str, lane: _Lane, wait: bool) -> int:
        fut = lane.in_flight
        if fut is None or not (wait or fut.done()):
            return 0
        theta = lane.in_flight_theta
        lane.in_flight = lane.in_flight_theta = None
        try:
            active = fut.result(timeout=30.0 if wait else 0.0)
        except BrokenProcessPool:
            self._restart("the worker died")
            return 0
        except Exception as exc:  # a solve that raised: the miss stays a miss
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

    def _submit_next(self, name: str, lane: _Lane) -> None:
        if lane.in_flight is not None or self._pool is None:
            return
        while lane.waiting:
            theta = lane.waiting.popleft()
            if lane.ctrl.covers(theta):
                self.counters["misses_already_covered"] += 1  # solved meanwhile: once only
                continue
            lane.in_flight = self._submit("a solve", _solve, name, theta, self._slice_s)
            if lane.in_flight is None:
                return
            lane.in_flight_theta = theta
            self.counters["solves_submitted"] += 1
            return

    def _submit(self, what: str, fn: Callable[..., _T], *args: object) -> Future[_T] | None:
        """Hand ``fn(*args)`` to the worker; None, and the worker restarted, if it cannot."""
        if self._pool is None:
            return None
        try:
            return self._pool.submit(fn, *args)
        except (BrokenProcessPool, RuntimeError):
            self._restart(f"the worker could not take {what}")
            return None

    def _restart(self, why: str) -> None:
        self.counters["worker_restarts"] += 1
        log.error("EPC miss worker: %s; restarting it", why)
        for lane in self._lanes.values():
            lane.in_flight = lane.in_flight_theta = lane.offer = None
            # the new worker's pool starts empty: send it every candidate again
            lane.ctrl.candidates.pop_fresh()
            lane.resend = lane.ctrl.candidates.items()
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
        try:
            self.start()
        except Exception as exc:  # the loops fly on: misses stay intermediate
            self._pool = None
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
        if self._pool is None:
            return None
        procs = getattr(self._pool, "_processes", None) or {}
        return next(iter(procs), None)
