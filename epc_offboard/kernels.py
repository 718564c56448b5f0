"""The EPC hit path's inner loop: apply one cached active-set map and KKT-check it.

``apply_map(M, width, theta_aug, n_check, u_out, u_min, u_max) -> bool`` computes
``w = M theta_aug`` row by row; the first ``n_check`` rows must satisfy ``0 <= w <= width``
(the KKT check, see :class:`epc_offboard.epc.ActiveSetMap`), the last ``nu`` rows are the
first input, written clipped to ``[u_min, u_max]`` into ``u_out`` when the check passes.

Compiled with numba when it is installed: one call instead of five numpy calls, and an early
exit on the first violated row, which makes refusing a candidate cheaper than applying it.
The numpy version below is the reference and the fallback; the tests run both.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import cast

import numpy as np

from epc_offboard.frames import FloatArray

ApplyMap = Callable[[FloatArray, FloatArray, FloatArray, int, FloatArray, FloatArray,
                     FloatArray], bool]


def apply_map_numpy(
    M: FloatArray,
    width: FloatArray,
    theta_aug: FloatArray,
    n_check: int,
    u_out: FloatArray,
    u_min: FloatArray,
    u_max: FloatArray,
) -> bool:
    w = M @ theta_aug
    chk = w[:n_check]
    # chk >= 0 and chk <= width in one comparison: a non-negative double orders like its bits
    # as an unsigned integer; a negative one (sign bit set) or NaN compares above any width
    if not (chk.view(np.uint64) <= width.view(np.uint64)).all():
        return False
    np.minimum(w[n_check:], u_max, out=u_out)
    np.maximum(u_out, u_min, out=u_out)
    return True


def _compile() -> ApplyMap | None:
    try:
        import numba
    except ImportError:  # numba is a dependency; keep working without it, only slower
        return None

    def apply_map_numba(
        M: FloatArray,
        width: FloatArray,
        theta_aug: FloatArray,
        n_check: int,
        u_out: FloatArray,
        u_min: FloatArray,
        u_max: FloatArray,
    ) -> bool:
        rows, cols = M.shape
        for i in range(n_check):
            s = 0.0
            for j in range(cols):
                s += M[i, j] * theta_aug[j]
            if not (s >= 0.0 and s <= width[i]):
                return False
        for i in range(n_check, rows):
            s = 0.0
            for j in range(cols):
                s += M[i, j] * theta_aug[j]
            k = i - n_check
            u_out[k] = min(max(s, u_min[k]), u_max[k])
        return True

    # reassoc/contract let the dot product vectorise; no nnan/ninf: widths may be +inf.
    # The on-disk cache spares the ~1 s compile on later starts; without a writable cache
    # location numba refuses cache=True, so compile in memory then.
    fastmath = {"reassoc", "contract"}
    try:
        compiled = numba.njit(apply_map_numba, cache=True, nogil=True, fastmath=fastmath)
    except RuntimeError:
        compiled = numba.njit(apply_map_numba, cache=False, nogil=True, fastmath=fastmath)
    return cast(ApplyMap, compiled)


_NUMBA = _compile()
apply_map: ApplyMap = _NUMBA if _NUMBA is not None else apply_map_numpy
HAVE_NUMBA = _NUMBA is not None
