"""Whether this process compiles its kernels (numba) or runs their numpy twins, and whether
numba's on-disk cache already holds them.

Every compiled kernel has a numpy twin (its test oracle), so a process can fly on the
twins: ``EPC_OFFBOARD_JIT=0`` in its environment, read once when the kernel modules load
(``control.kernels``, ``control.lwpr_kernels``, ``control.trajectories``,
``control.rate_response``), makes them
behave exactly as without numba. A cold start (empty cache) compiles for 10-30 s on a
companion computer; the service then flies on the twins and compiles into the cache in a
background process (``service.coldstart``), which marks the cache warm when it is done.

No I/O beyond reading and writing that one marker file, and :func:`announce_cold_compile`'s
one line on stderr.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import sys
from collections.abc import Callable
from importlib import metadata
from pathlib import Path
from typing import Any, TypeVar, cast

F = TypeVar("F", bound=Callable[..., Any])

ENV = "EPC_OFFBOARD_JIT"  # "0": the numpy twins; anything else or unset: numba

# the sources whose kernels the marker vouches for: an edited kernel is a cold cache
_KERNEL_SOURCES = (
    "control/kernels.py",
    "control/lwpr_kernels.py",
    "control/trajectories.py",
    "control/rate_response.py",
)


def enabled() -> bool:
    """Whether the kernel modules compile with numba (when it is installed)."""
    return os.environ.get(ENV, "1") != "0"


def cache_dir() -> Path | None:
    """numba's cache directory when one is set (NUMBA_CACHE_DIR); None: beside the sources."""
    value = os.environ.get("NUMBA_CACHE_DIR", "")
    return Path(value) if value else None


def _key(package: Path | None = None) -> str:
    """What numba's cache checks before it loads a kernel: its source file's path (the
    cache's folder is named after it), modification time and size (the index's stamp), the
    source itself and numba's version. A marker keyed on the contents alone said "warm" for
    an upgraded or re-cloned package whose kernels had not changed, and the start compiled
    every kernel before the link opened (12.7 s beside two CPU hogs, on a real PX4)."""
    package = package or Path(__file__).resolve().parent.parent
    digest = hashlib.sha256()
    for name in _KERNEL_SOURCES:
        source = package / name
        stat = source.stat()
        digest.update(f"{source}\0{stat.st_mtime}\0{stat.st_size}\0".encode())
        digest.update(source.read_bytes())
    # (the installed version, without importing numba: a second of a cold start)
    with contextlib.suppress(metadata.PackageNotFoundError):
        digest.update(metadata.version("numba").encode())
    return digest.hexdigest()[:16]


def _marker() -> Path:
    base = cache_dir() or Path(__file__).resolve().parent.parent / "control" / "__pycache__"
    return base / f"epc-offboard-kernels-{_key()}.warm"


def cache_warm() -> bool:
    """Whether a complete compile of these kernels' sources was written to the cache."""
    try:
        return _marker().is_file()
    except OSError:
        return False


def numba_installed() -> bool:
    try:
        metadata.version("numba")
    except metadata.PackageNotFoundError:
        return False
    return True


def mark_cache_warm() -> bool:
    """Record that every kernel is in the cache (after a complete warm-up); False when the
    marker cannot be written (then every start flies the numpy twins: set NUMBA_CACHE_DIR
    to a writable directory, as the systemd unit's StateDirectory does)."""
    marker = _marker()
    try:
        marker.parent.mkdir(parents=True, exist_ok=True)
        marker.write_text("compiled\n")
    except OSError:
        return False
    return True


def will_compile() -> bool:
    """Whether this process, or the services it starts with ``EPC_OFFBOARD_JIT=1``, will
    compile the kernels now: numba installed, not switched off, and the cache not marked
    warm (a first run after an install, an upgrade or an edited kernel)."""
    return numba_installed() and enabled() and not cache_warm()


# what a first run says while numba compiles (a new user took the silence for a hang)
COLD_COMPILE_NOTE = (
    "first run: compiling the control kernels with numba into its cache (once per install "
    "or upgrade; 1-3 min on 2 busy cores, longer on a companion computer; nothing is "
    "printed meanwhile); later runs start in seconds"
)


def announce_cold_compile(command: str) -> bool:
    """Say once on stderr, for ``epc-offboard COMMAND``, that the kernels are about to
    compile (:func:`will_compile`); nothing when the cache is warm. Whether it said it."""
    if not will_compile():
        return False
    print(f"epc-offboard {command}: {COLD_COMPILE_NOTE}", file=sys.stderr, flush=True)
    return True


def njit_cached(fn: F, **options: Any) -> F:
    """``fn`` compiled by numba (``numba.njit(fn, **options)``) into its on-disk cache, or in
    memory where the cache has no writable location (numba refuses ``cache=True`` there).
    Imports numba: call it only where the kernels compile (:func:`enabled`)."""
    import numba

    try:
        return cast(F, numba.njit(fn, cache=True, **options))
    except RuntimeError:  # no writable cache location
        return cast(F, numba.njit(fn, cache=False, **options))


def entry_point(kernel: F, *args: Any) -> F:
    """``kernel``'s compiled function for the types of ``args`` (compiled, or loaded from
    numba's cache, now, as a call with them would be): called directly it skips numba's
    dispatch, the type of every argument looked up and matched on every call (1-2 us a
    call, a tick makes several). Only for a call site whose arguments always have exactly
    these types (the same dtypes, dimensions and layouts, tuples of the same length): the
    compiled function does not check them. A numpy twin (no numba) is returned as it is."""
    typeof = getattr(kernel, "typeof_pyval", None)
    if typeof is None:
        return kernel
    return cast(F, kernel.compile(tuple(typeof(a) for a in args)))  # type: ignore[attr-defined]
