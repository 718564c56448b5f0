"""The compiled hit-path kernel agrees with the numpy reference, NaN and infinities included."""

from __future__ import annotations

import numpy as np
import pytest

from epc_offboard.control.kernels import HAVE_NUMBA, apply_map, apply_map_numpy


@pytest.mark.skipif(not HAVE_NUMBA, reason="numba not installed: the numpy path is in use")
def test_numba_and_numpy_kernels_agree():
    rng = np.random.default_rng(3)
    u_min, u_max = np.array([-1.0, -2.0]), np.array([1.0, 0.5])
    for trial in range(300):
        M = rng.normal(size=(9, 5))
        theta = rng.normal(size=5)
        theta[-1] = 1.0
        if trial % 7 == 0:
            theta[0] = np.nan
        w = M @ theta
        width = np.abs(rng.normal(size=7)) * 2.0
        width[trial % 7] = np.inf
        # shift rows so that about half of the trials pass
        M[:7, -1] += np.where(w[:7] < 0, -w[:7] + 0.1 * (trial % 2), 0.0)
        u1, u2 = np.empty(2), np.empty(2)
        ok1 = apply_map(M, width, theta, 7, u1, u_min, u_max)
        ok2 = apply_map_numpy(M, width, theta, 7, u2, u_min, u_max)
        assert ok1 == ok2
        if ok1:
            assert np.allclose(u1, u2, atol=1e-13, rtol=0)
            assert np.all(u1 >= u_min)
            assert np.all(u1 <= u_max)


def test_numpy_kernel_refuses_a_tiny_negative_slack():
    M = np.array([[0.0, -1e-300], [1.0, 0.0]])
    ok = apply_map_numpy(M, np.array([1.0]), np.array([0.0, 1.0]), 1, np.empty(1),
                         np.array([-1.0]), np.array([1.0]))
    assert not ok  # -1e-300 < 0: a violation however small
