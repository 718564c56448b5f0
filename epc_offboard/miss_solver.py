"""EPC's miss path off the control loop: full QP solves in a worker process.

On a library miss the tick applies the intermediate controller at once (thesis 3.1.3) and
the controller queues the parameter vector θ (``ExperienceController(learn_on_miss=False)``,
:attr:`~epc_offboard.epc.ExperienceController.pending`). :class:`MissSolver` takes those θ,
solves the full QP, recovers and verifies its active set in ONE worker process (a standard
``ProcessPoolExecutor``; each problem is sent once, at start, then only θ travels), and hands
the active set back. The loop adds it only after its own KKT check passes at that θ
(:meth:`~epc_offboard.epc.ExperienceController.add_solved`). A 10-30 ms solve therefore never
stalls the loops: on a real PX4 in wind it starved the 200 Hz attitude loop and, in
body-rate mode, flipped the vehicle.

* one solve in flight per controller; further misses wait in a small bounded buffer, and
  those the returning controller already covers are dropped (a region is solved once);
* the worker's death is survived: the pool is rebuilt, the lost solve counted;
* ``wait=True`` (lockstep simulation) blocks until the solve in flight has returned, so the
  result enters the library at the same tick every run: deterministic.

No asyncio here: :meth:`pump` is called from the position loop's tick.
"""

from __future__ import annotations

import logging
import multiprocessing
from collections import Counter, deque
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass

from epc_offboard.epc import ExperienceController
from epc_offboard.frames import FloatArray
from epc_offboard.qp import MpcProblem

log = logging.getLogger(__name__)

# worker-process state: one learner per problem, built once by the initializer
_LEARNERS: dict[str, ExperienceController] = {}


def _init_worker(problems: dict[str, MpcProblem]) -> None:
    _LEARNERS.clear()
    for name, problem in problems.items():
        # the worker only solves: its own library may stay tiny
        _LEARNERS[name] = ExperienceController(problem, max_size=8)


def _solve(name: str, theta: FloatArray) -> tuple[int, ...] | None:
    entry = _LEARNERS[name].learn_theta(theta)
    return None if entry is None else entry.active_set


def _ping() -> bool:
    return True


@dataclass
class _Lane:
    """One controller's queue: at most one solve in flight, a few waiting."""

    ctrl: ExperienceController
    waiting: deque[FloatArray]
    in_flight: Future[tuple[int, ...] | None] | None = None
    in_flight_theta: FloatArray | None = None


class MissSolver:
    def __init__(
        self, controllers: dict[str, ExperienceController], *, max_waiting: int = 4
    ) -> None:
        self._problems = {name: c.problem for name, c in controllers.items()}
        self._lanes = {
            name: _Lane(c, deque(maxlen=max_waiting)) for name, c in controllers.items()
        }
        self.counters: Counter[str] = Counter()
        self._pool: ProcessPoolExecutor | None = None

    def start(self, timeout_s: float = 30.0) -> None:
        """Start the worker and wait until it has imported and built its learners (before
        READY: a worker that cannot start is an error now, not mid-flight)."""
        self._pool = ProcessPoolExecutor(
            max_workers=1,
            mp_context=multiprocessing.get_context("spawn"),  # no fork of a threaded process
            initializer=_init_worker,
            initargs=(self._problems,),
        )
        self._pool.submit(_ping).result(timeout=timeout_s)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None

    def pump(self, *, wait: bool = False) -> int:
        """Collect returned solves into the libraries, queue new misses, submit the next.

        Returns the number of controllers added. ``wait``: block until every solve in flight
        has returned first (lockstep).
        """
        added = 0
        for name, lane in self._lanes.items():
            added += self._collect(name, lane, wait)
            ctrl = lane.ctrl
            while ctrl.pending:
                if len(lane.waiting) == lane.waiting.maxlen:
                    self.counters["misses_dropped"] += 1  # the oldest gives way
                lane.waiting.append(ctrl.pending.pop(0))
            self._submit_next(name, lane)
        return added

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
        if not lane.ctrl.add_solved(theta, active):
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
            try:
                lane.in_flight = self._pool.submit(_solve, name, theta)
            except (BrokenProcessPool, RuntimeError):
                self._restart("the worker could not take a solve")
                return
            lane.in_flight_theta = theta
            self.counters["solves_submitted"] += 1
            return

    def _restart(self, why: str) -> None:
        self.counters["worker_restarts"] += 1
        log.error("EPC miss worker: %s; restarting it", why)
        for lane in self._lanes.values():
            lane.in_flight = lane.in_flight_theta = None
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

    def worker_pid(self) -> int | None:
        """The worker process's pid (fault tests kill it)."""
        if self._pool is None:
            return None
        procs = getattr(self._pool, "_processes", None) or {}
        return next(iter(procs), None)
