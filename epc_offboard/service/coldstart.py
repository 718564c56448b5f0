"""`epc-offboard run` on a cold kernel cache: fly at once on the numpy twins, compile in the
background for the next start.

A cold start (numba's cache empty: first start, new version, a wiped state directory)
compiled every kernel before the loops started: 10-30 s on a companion computer, and a real
vehicle reached offboard only 30-52 s after the service started. Now, decided before any
kernel module is imported (:func:`choose`):

* cache warm (``common.jit`` marks it after a complete compile): the kernels load from the
  cache and are warmed before READY, as before (``Cascade.warm_up``);
* cache cold: this process runs the numpy twin of every kernel (``EPC_OFFBOARD_JIT=0``, the
  kernels' own reference implementations, the same numbers) and never imports numba, so no
  kernel can compile on the control loop; a child process at idle priority (SCHED_IDLE,
  :func:`main`) builds the same cascade, compiles and warms every kernel into the cache,
  and marks it warm. The next start flies compiled. The child dies with the service.

An explicit ``EPC_OFFBOARD_JIT`` in the environment wins (0: twins, 1: compile at start).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import signal
import subprocess
import sys
import threading
import time

from epc_offboard.common import jit
from epc_offboard.common.children import die_with_launcher

log = logging.getLogger("epc_offboard.service")

# Where SCHED_IDLE is refused (not Linux): the lowest nice
_CHILD_NICE = 19


def choose() -> str:
    """The kernels of this process: "compiled", "numpy", or "numpy-cold" (the cache is
    cold: ``EPC_OFFBOARD_JIT=0`` is set for it and the processes it spawns). Call before
    importing the kernels; later calls return the first answer."""
    global _choice
    if _choice is None:
        _choice = _choose()
    return _choice


_choice: str | None = None


def _choose() -> str:
    if jit.ENV in os.environ:
        return "compiled" if jit.enabled() and jit.numba_installed() else "numpy"
    if not jit.numba_installed() or jit.cache_warm():
        return "compiled" if jit.numba_installed() else "numpy"
    os.environ[jit.ENV] = "0"
    return "numpy-cold"


def start_background_compile(config_path: str) -> subprocess.Popen[bytes]:
    """The child that compiles every kernel of ``config_path``'s cascade into the cache."""
    env = dict(os.environ, **{jit.ENV: "1"})

    def lower_priority() -> None:
        # SCHED_IDLE: only a CPU nobody else wants. At nice 10 it still took a tenth of
        # the service's group's CPU for its 10-30 s of compiling, at the very time the
        # service's own start-up (imports, its helpers' imports) competes for the same two
        # cores with the loops' first ticks; on a loaded companion computer it may then
        # finish only on a later start, which flies the twins again meanwhile
        try:
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
        except (AttributeError, OSError):
            with contextlib.suppress(OSError):
                os.nice(_CHILD_NICE)

    return subprocess.Popen(
        [sys.executable, "-m", "epc_offboard.service.coldstart", config_path, str(os.getpid())],
        env=env,
        stdin=subprocess.DEVNULL,
        preexec_fn=lower_priority,
    )


def run(args: argparse.Namespace) -> int:
    """`epc-offboard run`: choose the kernels, start the compile when cold, run the service."""
    from epc_offboard.service.startup import TIMELINE

    TIMELINE.mark("entry")
    die_with_launcher()
    mode = choose()
    # first: starting the compile's child took up to 0.6 s of wall clock at load 12 (it is
    # at idle priority from its first instruction whatever its parent's)
    _start_up_at_loop_priority(args.config)
    child = start_background_compile(args.config) if mode == "numpy-cold" else None
    TIMELINE.mark("kernels_chosen")
    from epc_offboard.service.service import run_service_command

    try:
        return run_service_command(args)
    finally:
        if child is not None and child.poll() is None:
            child.terminate()
            with contextlib.suppress(subprocess.TimeoutExpired):
                child.wait(timeout=2.0)


def _start_up_at_loop_priority(config: str) -> None:
    """The rest of the start-up (imports, the service's parts, the warm-up, the gc freeze,
    the first commands) at the loops' SCHED_FIFO priority (``loops.realtime_priority``),
    which the loops' thread keeps: at normal priority, beside a real PX4 at load 10-15, its
    0.6-1.3 s of CPU took 2.4-5.6 s of wall clock before the first command. Read with the
    TOML parser alone: the config's own loader imports numpy and the service's types (2.8 s
    at load 10 before the priority applied). Helpers started from here run at normal
    priority (SCHED_RESET_ON_FORK), the background compile at idle priority. Silent when
    the file or the value is not usable or the priority is refused: the service's own load
    names the first, ``realtime.prepare`` logs the last."""
    import tomllib

    from epc_offboard.common.bundled import bundled_config
    from epc_offboard.service import realtime
    from epc_offboard.service.startup import TIMELINE

    try:
        with bundled_config(config).open("rb") as fh:
            loops = tomllib.load(fh).get("loops", {})
        priority = loops.get("realtime_priority", 0) if isinstance(loops, dict) else 0
        if isinstance(priority, int) and not isinstance(priority, bool) and 0 < priority < 100:
            realtime.apply_priority(priority)
            TIMELINE.mark("start_up_priority")
    except (OSError, ValueError):  # (tomllib.TOMLDecodeError, realtime.PriorityError)
        return


def _die_with(parent_pid: int) -> None:
    """Exit as soon as ``parent_pid`` is gone (even killed with SIGKILL)."""

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, name="die-with-parent", daemon=True).start()


def main(argv: list[str] | None = None) -> int:
    """The background compile: CONFIG PARENT_PID."""
    config_path, parent = (argv if argv is not None else sys.argv[1:])[:2]
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C of the group: the parent stops
    _die_with(int(parent))
    from epc_offboard.control.cascade import Cascade
    from epc_offboard.service.config import load_service_config

    cfg = load_service_config(config_path)
    t0 = time.perf_counter()
    cascade = Cascade(
        cfg.position, cfg.attitude, cfg.estimator, 1.0 / cfg.loops.position_rate_hz,
        learn_on_miss=False, airframe=cfg.vehicle,
    )  # fmt: skip
    cascade.warm_up()
    if not jit.mark_cache_warm():
        print(f"epc-offboard: cannot mark the kernel cache warm in {jit.cache_dir()}: every "
              "start will fly the numpy twins (set NUMBA_CACHE_DIR to a writable directory)",
              file=sys.stderr)  # fmt: skip
        return 1
    print(
        f"epc-offboard: kernels compiled into the cache in {time.perf_counter() - t0:.1f} s "
        "(background, for the next start)",
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
