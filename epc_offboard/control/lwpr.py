"""Locally Weighted Projection Regression (LWPR), incremental and vectorised over fields.

The learner of thesis 3.1.1 (eqs. 3.1-3.4), after Vijayakumar, D'Souza & Schaal,
"Incremental Online Learning in High Dimensions" (Neural Computation 17, 2005), with the
defaults and safety heuristics documented for the reference library (Klanke, Vijayakumar &
Schaal, JMLR 2008). Written from the equations; pure numpy, no I/O beyond explicit save/load.

Each output has its own set of receptive fields (the reference library's "sub-models"). A
field j owns a Gaussian kernel w_j(x) = exp(-1/2 (x - c_j)' D_j (x - c_j)), D_j = M_j' M_j,
and a local linear model fitted by incremental partial least squares (PLS) with forgetting.
The prediction of one output is the w-weighted mean of its trusted fields' local models.

The fields of all outputs share one set of arrays, one contiguous array per quantity with a
row per field (shape (capacity, ...), see ``_schema``; the capacity doubles when it runs out).
An update runs every array operation over all fields at once, never a Python loop over
fields (only over the at most n_in PLS projections); a field below the update threshold gets
weight 0 and forgetting factor 1 in those operations, which leaves it bit-for-bit unchanged.

Two implementations of the same equations: ``LwprReference`` runs them as numpy array
operations over all fields (above); ``LWPR`` runs the per-sample work (activations,
prediction, the update of the active fields) as compiled loops over the fields
(``epc_offboard.control.lwpr_kernels``, numba), a few microseconds instead of a few hundred numpy
calls. Both share the field store, the adding and pruning of fields (Python, rare) and the
file format; the tests hold the compiled one to the reference. Without numba, ``LWPR`` is the
reference. Call ``warm_up()`` before a control loop, so its first tick does not compile.

Inputs and outputs are divided by ``norm_in`` / ``norm_out`` before learning (as in the
reference library): choose them near the typical range of each signal, so that ``init_d`` and
``penalty`` mean the same thing for every input and output.
"""

from __future__ import annotations

import io
import json
import math
import operator
import os
import tempfile
import time
import zipfile
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from epc_offboard.common import jit
from epc_offboard.common.blobs import Npz
from epc_offboard.common.errors import EpcError
from epc_offboard.control import lwpr_kernels as kernels

FloatArray = npt.NDArray[np.float64]
ArrayLike = npt.ArrayLike

FORMAT_NAME = "epc-offboard-lwpr"
FORMAT_VERSION = 1

_W_UPDATE_MIN = kernels.W_UPDATE_MIN  # a field takes part in an update only above this
_INITIAL_CAPACITY = 16
# how many times any model's field store was reallocated (ModelGroup's cache key)
_reallocations = 0


class LwprError(EpcError, ValueError):
    """Bad input to, or bad file for, an LWPR model. The model is left unchanged."""


# Per-field quantities, by shape. d = n_in, R = n_in (the most PLS projections a field has).
_VEC = ("c", "mean_x", "var_x", "slope")  # (d,)
_MAT = ("M", "D", "alpha", "meta_b", "meta_h")  # (d, d)
_PROJ = (  # (R,) one value per PLS projection
    "ss2",  # sum of w s^2 (variance of the projected input)
    "syres",  # sum of w s y_res
    "beta",  # regression coefficient of each projection
    "sum_w",
    "sum_e_cv2",  # weighted leave-one-out error with the first r+1 projections
    "n_data",  # (forgetting-discounted) number of updates
    "lam",  # forgetting factor
    "H",  # leave-one-out cost statistics of the distance-metric gradient
    "r",
)
# (R, d): projection directions u_r, input regressions p_r, their statistics, and the
# projections as linear maps of the centred input, s_r = g_r'x (see _projection_rows).
_PROJV = ("U", "P", "sxres_yres", "ssxres", "G")
_SCALAR = ("beta0", "sum_e2", "ssp")
# The field store in the order the compiled update takes it (lwpr_kernels.update), and the
# part the compiled predictions read.
_UPDATE_ARGS = (
    "c", "mean_x", "var_x", "slope", "M", "D", "alpha", "meta_b", "meta_h", "ss2", "syres",
    "beta", "sum_w", "sum_e_cv2", "n_data", "lam", "H", "r", "U", "P", "sxres_yres", "ssxres",
    "G", "beta0", "sum_e2", "ssp",
)  # fmt: skip
_PREDICT_ARGS = ("c", "D", "beta0", "mean_x", "slope")


def _schema(n_in: int) -> dict[str, tuple[int, ...]]:
    """Trailing shape of each per-field quantity (one contiguous array per quantity)."""
    d = r = n_in
    shapes: dict[str, tuple[int, ...]] = {}
    for names, tail in ((_VEC, (d,)), (_MAT, (d, d)), (_PROJ, (r,)), (_PROJV, (r, d))):
        shapes.update(dict.fromkeys(names, tail))
    shapes.update(dict.fromkeys(_SCALAR, ()))
    return shapes


def _with_diagonals(arrays: dict[str, FloatArray], n_in: int) -> dict[str, FloatArray]:
    """``arrays`` plus a writable view ``<name>_diag`` (k, d) of each (k, d, d) matrix."""
    out = dict(arrays)
    for name in _MAT:
        m = arrays[name]
        out[name + "_diag"] = m.reshape(m.shape[0], n_in * n_in)[:, :: n_in + 1]
    return out


def _as_matrix(value: float | ArrayLike, n: int, what: str) -> FloatArray:
    """A scalar, an (n,) diagonal or an (n, n) matrix, as an (n, n) float matrix."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        out = float(arr) * np.eye(n)
    elif arr.shape == (n,):
        out = np.diag(arr)
    elif arr.shape == (n, n):
        out = arr.copy()
    else:
        raise LwprError(f"{what} must be a scalar, ({n},) or ({n}, {n}); got shape {arr.shape}")
    if not np.all(np.isfinite(out)):
        raise LwprError(f"{what} must be finite")
    return out


def _positive_vector(value: ArrayLike | None, n: int, what: str) -> FloatArray:
    if value is None:
        return np.ones(n)
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.shape != (n,):
        raise LwprError(f"{what} must have shape ({n},), got {arr.shape}")
    if not np.all(np.isfinite(arr)) or np.any(arr <= 0.0):
        raise LwprError(f"{what} must be finite and > 0, got {arr}")
    return arr.copy()


def check_vector(value: ArrayLike, n: int, name: str) -> FloatArray:
    """``value`` as a finite float array of shape (n,); else LwprError naming ``name``."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise LwprError(f"{name} must be a numeric array of shape ({n},): {exc}") from exc
    if arr.shape != (n,):
        raise LwprError(f"{name} must have shape ({n},), got {arr.shape}")
    # (for the few values of a sample, 1/6 of the cost of numpy's isfinite + all)
    if not all(map(math.isfinite, arr.tolist())):
        raise LwprError(f"{name} must be finite, got {arr}")
    return arr


class LWPR:
    """Incremental LWPR regression from R^n_in to R^n_out.

    ``update(x, y)`` learns one sample and returns the prediction at x from before it;
    ``predict(x)`` and ``predict_conf(x)`` evaluate. Arrays in, arrays out: x has shape
    (n_in,), y (n_out,). Parameters are those of the reference library, with its defaults:

    init_d: initial distance metric D of a new field (scalar, (n_in,) diagonal or
        (n_in, n_in) positive definite), in normalised input units.
    init_alpha: learning rate of the distance-metric gradient descent.
    penalty: weight of the penalty sum(D_ij^2) against shrinking fields without bound.
    w_gen: a sample that activates no field of an output above this gets a new field.
    w_prune: two fields of an output activated above this by one sample: one is removed.
    init_lambda, final_lambda, tau_lambda: the forgetting factor of each field starts at
        init_lambda and anneals as lambda <- tau*lambda + (1 - tau)*final_lambda.
    diag_only: adapt only the diagonal of the metric. update_d: adapt the metric at all.
    meta, meta_rate: incremental delta-bar-delta adaptation of the learning rates.
    init_s2: initial PLS projection variance (regularisation).
    add_threshold: a PLS projection is added when the leave-one-out error with the newest
        projection is below add_threshold times the error without it.
    norm_in, norm_out: input/output scales; the learner sees x / norm_in and y / norm_out.
    max_rfs: at most this many fields per output (None: unbounded); once reached, samples
        that activate no field are still learned by the nearest fields, but add none.
    cutoff: fields activated at or below this are ignored by predictions.

    A field is trusted for prediction once it has seen more than 2*n_in updates, and its
    newest PLS projection is used once that projection has seen more than 2*n_in updates.
    Of two overlapping fields (both activated above w_prune) the narrower one, with the larger
    trace of D, is removed. Counters: n_updates, n_pruned (per output), n_dropped (fields
    removed because their statistics overflowed, e.g. on an absurdly large target).
    Bad inputs raise ``LwprError`` (a ``ValueError``) and leave the model unchanged.

    ``update``, ``predict`` and ``predict_many`` run compiled (``compiled`` is True when numba
    is installed); ``LwprReference`` is the same learner in numpy, its test oracle.
    """

    compiled: ClassVar[bool] = kernels.HAVE_NUMBA

    def __init__(
        self,
        n_in: int,
        n_out: int,
        *,
        init_d: float | ArrayLike = 25.0,
        init_alpha: float | ArrayLike = 50.0,
        penalty: float = 1e-6,
        w_gen: float = 0.1,
        w_prune: float = 1.0,
        init_lambda: float = 0.999,
        final_lambda: float = 0.99999,
        tau_lambda: float = 0.9999,
        diag_only: bool = True,
        update_d: bool = True,
        meta: bool = False,
        meta_rate: float = 250.0,
        init_s2: float = 1e-10,
        add_threshold: float = 0.5,
        norm_in: ArrayLike | None = None,
        norm_out: ArrayLike | None = None,
        max_rfs: int | None = None,
        cutoff: float = 0.001,
    ) -> None:
        if isinstance(n_in, bool) or not isinstance(n_in, int | np.integer) or n_in < 1:
            raise LwprError(f"n_in must be an integer >= 1, got {n_in!r}")
        if isinstance(n_out, bool) or not isinstance(n_out, int | np.integer) or n_out < 1:
            raise LwprError(f"n_out must be an integer >= 1, got {n_out!r}")
        self.n_in = int(n_in)
        self.n_out = int(n_out)
        d = self.n_in
        self.init_d = _as_matrix(init_d, d, "init_d")
        if not np.allclose(self.init_d, self.init_d.T):
            raise LwprError("init_d must be symmetric")
        if diag_only and np.any(self.init_d[~np.eye(d, dtype=bool)] != 0.0):
            raise LwprError("init_d must be diagonal when diag_only is True")
        try:
            # D = M'M with M upper triangular, as the reference library stores it.
            self.init_m = np.linalg.cholesky(self.init_d).T
        except np.linalg.LinAlgError as exc:
            raise LwprError("init_d must be positive definite") from exc
        if np.ndim(init_alpha) == 0:
            init_alpha = np.full((d, d), float(init_alpha))  # type: ignore[arg-type]
        self.init_alpha = _as_matrix(init_alpha, d, "init_alpha")
        if np.any(self.init_alpha[np.triu_indices(d)] <= 0.0):
            raise LwprError("init_alpha must be > 0")
        scalars = {
            "penalty": (penalty, 0.0, math.inf, True),
            "w_gen": (w_gen, 0.0, 1.0, False),
            "w_prune": (w_prune, 0.0, math.inf, False),
            "init_lambda": (init_lambda, 0.0, 1.0, False),
            "final_lambda": (final_lambda, 0.0, 1.0, False),
            "tau_lambda": (tau_lambda, 0.0, 1.0, True),
            "meta_rate": (meta_rate, 0.0, math.inf, True),
            "init_s2": (init_s2, 0.0, math.inf, False),
            "add_threshold": (add_threshold, 0.0, math.inf, False),
            "cutoff": (cutoff, 0.0, 1.0, True),
        }
        for name, (value, lo, hi, lo_ok) in scalars.items():
            v = float(value)
            if not (math.isfinite(v) and (v >= lo if lo_ok else v > lo) and v <= hi):
                bound = "[" if lo_ok else "("
                raise LwprError(f"{name} must be in {bound}{lo}, {hi}], got {value!r}")
        self.penalty = float(penalty)
        self.w_gen = float(w_gen)
        self.w_prune = float(w_prune)
        self.init_lambda = float(init_lambda)
        self.final_lambda = float(final_lambda)
        self.tau_lambda = float(tau_lambda)
        self.meta_rate = float(meta_rate)
        self.init_s2 = float(init_s2)
        self.add_threshold = float(add_threshold)
        self.cutoff = float(cutoff)
        self.diag_only = bool(diag_only)
        self.update_d = bool(update_d)
        self.meta = bool(meta)
        if max_rfs is not None and (isinstance(max_rfs, bool) or int(max_rfs) < 1):
            raise LwprError(f"max_rfs must be None or an integer >= 1, got {max_rfs!r}")
        self.max_rfs = None if max_rfs is None else int(max_rfs)
        self.norm_in = _positive_vector(norm_in, d, "norm_in")
        self.norm_out = _positive_vector(norm_out, self.n_out, "norm_out")

        self._schema = _schema(d)
        self._r_idx = np.arange(d)  # projection index, for masks (k, R)
        self._metric_mask = np.eye(d) if self.diag_only else np.triu(np.ones((d, d)))
        self._ones = np.ones(d)  # reductions over a length-d axis as a matmul (fast)
        self._cumsum = np.triu(np.ones((d, d)))  # x @ this: cumulative sum over projections
        self._store = {k: np.zeros((_INITIAL_CAPACITY, *t)) for k, t in self._schema.items()}
        # Views of rows [0, n) of every store array, rebuilt when n or the capacity changes.
        self._views: dict[str, FloatArray] = {}
        self._views_n = -1
        self._out = np.zeros(_INITIAL_CAPACITY, dtype=np.int64)  # output of each field
        self._nreg = np.zeros(_INITIAL_CAPACITY, dtype=np.int64)  # PLS projections in use
        self._trusted = np.zeros(_INITIAL_CAPACITY, dtype=bool)
        self._nuse = np.zeros(_INITIAL_CAPACITY, dtype=np.int64)  # projections predictions use
        self._n = 0  # fields in use: rows [0, _n)
        self.n_updates = 0
        self.n_pruned = np.zeros(self.n_out, dtype=np.int64)
        self.n_dropped = 0  # fields removed because their statistics overflowed
        cfg = np.zeros(kernels.CFG_SIZE)
        cfg[kernels.CFG_CUTOFF] = self.cutoff
        cfg[kernels.CFG_W_GEN] = self.w_gen
        cfg[kernels.CFG_W_PRUNE] = self.w_prune
        cfg[kernels.CFG_PEN] = self.penalty / self.n_in
        cfg[kernels.CFG_TAU_LAMBDA] = self.tau_lambda
        cfg[kernels.CFG_FINAL_LAMBDA] = self.final_lambda
        cfg[kernels.CFG_ADD_THRESHOLD] = self.add_threshold
        cfg[kernels.CFG_META_RATE] = self.meta_rate
        cfg[kernels.CFG_DIAG_ONLY] = float(self.diag_only)
        cfg[kernels.CFG_UPDATE_D] = float(self.update_d)
        cfg[kernels.CFG_META] = float(self.meta)
        self._cfg = cfg
        # The compiled kernels' arguments (whole-capacity arrays), rebuilt with the store.
        self._update_args: tuple[npt.NDArray[Any], ...] = ()
        self._predict_args: tuple[npt.NDArray[Any], ...] = ()
        self._w_buf = np.zeros(0)  # activations, (capacity,)
        self._y_buf = np.zeros(self.n_out)

    # ----------------------------------------------------------------- public API

    @property
    def num_rfs(self) -> tuple[int, ...]:
        """Number of receptive fields of each output."""
        counts = np.bincount(self._out[: self._n], minlength=self.n_out)
        return tuple(int(c) for c in counts)

    def update(self, x: ArrayLike, y: ArrayLike) -> FloatArray:
        """Learn one sample (x (n_in,), y (n_out,)); return the prediction at x before it."""
        return self.update_finite(check_vector(x, self.n_in, "x"), check_vector(y, self.n_out, "y"))

    def update_finite(self, x: FloatArray, y: FloatArray) -> FloatArray:
        """:meth:`update` of a sample its caller has checked: float arrays of shapes (n_in,)
        and (n_out,), finite (the estimator checks its whole sample once, not each model's
        share of it again: the position tick updates three models)."""
        xn = x / self.norm_in
        yn = y / self.norm_out
        if self.compiled:
            self._kernel_args()
            w = self._w_buf[: self._n]
            status = kernels.update(
                xn, yn, self._n, self._cfg, self._w_buf, self._y_buf, *self._update_args
            )
            return self._after_update(int(status), w, xn, yn)
        else:
            v = self._active_views()
            w = self._activations(v, xn)
            y_before = self._predict_normalised(v, w, xn) * self.norm_out
            active = w > _W_UPDATE_MIN
            overflow = bool(active.any())
            if overflow:
                self._update_fields(v, xn, yn, w, active)
            crowded = True  # _add_or_prune checks its fast path itself
        self.n_updates += 1
        # A field whose statistics overflowed is dropped rather than left to poison
        # predictions (not seen in practice; counted in n_dropped).
        if overflow and self._drop_overflowed():
            return y_before
        if crowded:
            self._add_or_prune(w, xn, yn)
        return y_before

    def _after_update(self, status: int, w: FloatArray, xn: FloatArray,
                      yn: FloatArray) -> FloatArray:
        """What Python does after the compiled update of the sample (xn, yn) (normalised),
        whose ``status`` (STATUS_* bits) it returned, with the activations ``w`` (n,) it
        wrote: the prediction before it (n_out,), and the fields dropped, added or pruned."""
        y_before = self._y_buf * self.norm_out
        self.n_updates += 1
        if status & kernels.STATUS_NOT_FINITE and self._drop_overflowed():
            return y_before
        if status & kernels.STATUS_ADD_OR_PRUNE:
            self._add_or_prune(w, xn, yn)
        return y_before

    def predict(self, x: ArrayLike) -> FloatArray:
        """Prediction at x (n_in,): shape (n_out,); 0 where no trusted field is active."""
        xn = check_vector(x, self.n_in, "x") / self.norm_in
        if self.compiled:
            self._kernel_args()
            y = np.empty((1, self.n_out))
            # (False only if x is finite but too large for norm_in: numpy's answer, below)
            if kernels.predict_many(xn.reshape(1, -1), self._n, self._cfg, y, *self._predict_args):
                y_one: FloatArray = y[0] * self.norm_out
                return y_one
        v = self._active_views()
        return self._predict_normalised(v, self._activations(v, xn), xn) * self.norm_out

    def predict_many(self, xs: ArrayLike) -> FloatArray:
        """Predictions at the rows of xs (m, n_in): shape (m, n_out), each row equal to
        ``predict`` at that row, computed in one pass over the fields."""
        try:
            arr = np.asarray(xs, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise LwprError(f"xs must be a numeric array of shape (m, {self.n_in}): {exc}") from exc
        if arr.ndim != 2 or arr.shape[1] != self.n_in:
            raise LwprError(f"xs must have shape (m, {self.n_in}), got {arr.shape}")
        n = self._n
        xn = arr / self.norm_in
        if self.compiled and n > 0:
            xn = np.ascontiguousarray(xn)  # (the layout numba compiled for, whatever xs's)
            self._kernel_args()
            y_many = np.empty((arr.shape[0], self.n_out))
            # The kernel checks that xn is finite; if not, xs is not, or it is too large for
            # norm_in (then numpy's answer, below).
            if kernels.predict_many(xn, n, self._cfg, y_many, *self._predict_args):
                y_many *= self.norm_out
                return y_many
        if not np.isfinite(arr).all():
            raise LwprError("xs must be finite")
        if n == 0:
            return np.zeros((arr.shape[0], self.n_out))
        v = self._active_views()
        dx = xn[:, None, :] - v["c"][None]  # (m, n, d)
        if self.diag_only:
            q = (dx * dx * v["D_diag"][None]) @ self._ones
        else:
            q = np.einsum("mki,kij,mkj->mk", dx, v["D"], dx)
        w = np.exp(-0.5 * q)  # (m, n)
        local = v["beta0"] + ((xn[:, None, :] - v["mean_x"][None]) * v["slope"][None]) @ self._ones
        wu = np.where((w > self.cutoff) & self._trusted[:n], w, 0.0)
        onehot = np.zeros((n, self.n_out))
        onehot[np.arange(n), self._out[:n]] = 1.0
        sw = wu @ onehot
        swy = (wu * local) @ onehot
        y: FloatArray = swy / np.where(sw > 0.0, sw, 1.0) * self.norm_out
        return y

    def predict_conf(self, x: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Prediction at x and its confidence bound (one standard deviation), both (n_out,).

        The bound combines each field's leave-one-out error variance (inflated by how far x
        is from the field's data in projection space) with the spread of the fields'
        predictions; it is 1e20 where no trusted field is active.
        """
        xn = check_vector(x, self.n_in, "x") / self.norm_in
        n = self._n
        w = self._activations(self._active_views(), xn)
        use = (w > self.cutoff) & self._trusted[:n]
        y = np.zeros(self.n_out)
        conf = np.full(self.n_out, 1e20)
        if not use.any():
            return y * self.norm_out, conf
        v = {name: arr[use] for name, arr in self._active_views().items()}
        wu = w[use]
        rows_idx = np.arange(wu.size)
        n_use = self._nuse[:n][use]
        s, _ = self._project(xn - v["mean_x"], v["U"], v["P"])
        used = self._r_idx < n_use[:, None]
        yp = v["beta0"] + np.sum(v["beta"] * s * used, axis=1)
        last = n_use - 1
        gamma = v["sum_e_cv2"][rows_idx, last] / (v["sum_w"][rows_idx, last] - v["ssp"])
        sigma2 = gamma * (1.0 + wu * np.sum(s * s / v["ss2"] * used, axis=1))
        out = self._out[:n][use]
        sw = np.bincount(out, weights=wu, minlength=self.n_out)
        swy = np.bincount(out, weights=wu * yp, minlength=self.n_out)
        swyy = np.bincount(out, weights=wu * yp * yp, minlength=self.n_out)
        swc = np.bincount(out, weights=wu * sigma2, minlength=self.n_out)
        has = sw > 0.0
        y[has] = swy[has] / sw[has]
        conf[has] = np.sqrt(np.abs(swc[has] + swyy[has] - swy[has] * y[has])) / sw[has]
        return y * self.norm_out, np.where(has, conf * self.norm_out, conf)

    # -------------------------------------------------------------- persistence

    def to_bytes(self) -> bytes:
        """The whole model (parameters and learned state) as npz bytes."""
        return self.to_npz().build()

    def to_npz(self) -> Npz:
        """:meth:`to_bytes`'s arrays, copied now (a memcpy each, well under a millisecond),
        zipped later by :meth:`Npz.build`: making the npz here took a saver's slice of the
        loops' thread up to 13.6 ms (issue 21), and the library store's process makes it
        now."""
        params = {
            "n_in": self.n_in,
            "n_out": self.n_out,
            "penalty": self.penalty,
            "w_gen": self.w_gen,
            "w_prune": self.w_prune,
            "init_lambda": self.init_lambda,
            "final_lambda": self.final_lambda,
            "tau_lambda": self.tau_lambda,
            "diag_only": self.diag_only,
            "update_d": self.update_d,
            "meta": self.meta,
            "meta_rate": self.meta_rate,
            "init_s2": self.init_s2,
            "add_threshold": self.add_threshold,
            "max_rfs": self.max_rfs,
            "cutoff": self.cutoff,
        }
        n = self._n
        return Npz.of({
            "format": np.array(FORMAT_NAME),
            "version": np.array(FORMAT_VERSION),
            "params": np.array(json.dumps(params)),
            "init_d": self.init_d,
            "init_alpha": self.init_alpha,
            "norm_in": self.norm_in,
            "norm_out": self.norm_out,
            **{"f_" + name: arr[:n] for name, arr in self._store.items()},
            "out": self._out[:n],
            "nreg": self._nreg[:n],
            "trusted": self._trusted[:n],
            "n_pruned": self.n_pruned,
            "n_dropped": np.array(self.n_dropped),
            "n_updates": np.array(self.n_updates),
        })  # fmt: skip

    @classmethod
    def from_bytes(cls, data: bytes) -> LWPR:
        """Rebuild a model from ``to_bytes`` output; a wrong or corrupt blob raises LwprError."""
        try:
            with np.load(io.BytesIO(data), allow_pickle=False) as z:
                arrays = {key: z[key] for key in z.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
            raise LwprError(f"not an LWPR model (unreadable npz: {exc})") from exc
        return cls._from_arrays(arrays)

    def save(self, path: str | Path) -> None:
        """Write the model to ``path`` (npz), atomically: a crash leaves the old file."""
        p = Path(path)
        data = self.to_bytes()
        fd, tmp = tempfile.mkstemp(prefix=p.name + ".", suffix=".tmp", dir=p.parent or ".")
        try:
            with os.fdopen(fd, "wb") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, p)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise

    @classmethod
    def load(cls, path: str | Path) -> LWPR:
        """Read a model written by ``save``; a wrong or corrupt file raises LwprError."""
        p = Path(path)
        try:
            return cls.from_bytes(p.read_bytes())
        except LwprError as exc:
            raise LwprError(f"{p}: {exc}") from exc

    @classmethod
    def _from_arrays(cls, a: dict[str, Any]) -> LWPR:
        def need(key: str) -> Any:
            if key not in a:
                raise LwprError(f"not an LWPR model (missing `{key}`)")
            return a[key]

        if str(need("format")) != FORMAT_NAME:
            raise LwprError(f"not an LWPR model (format {str(a['format'])!r})")
        version = int(need("version"))
        if version != FORMAT_VERSION:
            raise LwprError(f"LWPR format version {version} is not supported ({FORMAT_VERSION})")
        try:
            params = json.loads(str(need("params")))
            n_in, n_out = int(params.pop("n_in")), int(params.pop("n_out"))
            model = cls(
                n_in,
                n_out,
                init_d=need("init_d"),
                init_alpha=need("init_alpha"),
                norm_in=need("norm_in"),
                norm_out=need("norm_out"),
                **params,
            )
        except (KeyError, TypeError, json.JSONDecodeError) as exc:
            raise LwprError(f"LWPR model has bad parameters: {exc}") from exc
        out, nreg, trusted = need("out"), need("nreg"), need("trusted")
        n = out.shape[0] if out.ndim == 1 else -1
        fields = {k: np.asarray(need("f_" + k), dtype=np.float64) for k in model._schema}
        if (
            any(arr.shape != (n, *model._schema[k]) for k, arr in fields.items())
            or nreg.shape != (n,)
            or trusted.shape != (n,)
            or not all(np.all(np.isfinite(arr)) for arr in fields.values())
            or np.any((out < 0) | (out >= n_out))
            or np.any((nreg < 1) | (nreg > n_in))
        ):
            raise LwprError("LWPR model has inconsistent field arrays")
        model._ensure_capacity(n)
        for k, arr in fields.items():
            model._store[k][:n] = arr
        model._out[:n] = out
        model._nreg[:n] = nreg
        model._trusted[:n] = trusted.astype(bool)
        model._n = n
        model._views_n = -1
        model._nuse[:n] = model._projections_in_use(model._active_views(), model._nreg[:n])
        n_pruned = np.asarray(need("n_pruned"), dtype=np.int64)
        if n_pruned.shape != (n_out,):
            raise LwprError("LWPR model has inconsistent field arrays")
        model.n_pruned = n_pruned.copy()
        model.n_updates = int(need("n_updates"))
        model.n_dropped = int(need("n_dropped"))
        return model

    # ----------------------------------------------------------------- internals

    def _kernel_args(self) -> None:
        """(Re)build the compiled kernels' arguments after the store was reallocated."""
        if self._w_buf.shape[0] == self._out.shape[0]:
            return
        store = self._store
        self._update_args = (
            *(store[name] for name in _UPDATE_ARGS),
            self._out,
            self._nreg,
            self._trusted,
            self._nuse,
        )
        self._predict_args = (*(store[name] for name in _PREDICT_ARGS), self._trusted, self._out)
        self._w_buf = np.zeros(self._out.shape[0])

    def _drop_overflowed(self) -> bool:
        """Remove the fields whose statistics are no longer finite; True if there were any."""
        v = self._active_views()
        health = v["beta0"] + v["slope"] @ self._ones + v["M_diag"] @ self._ones
        broken = np.flatnonzero(~np.isfinite(health))
        if broken.size == 0:
            return False
        self.n_dropped += broken.size
        self._remove_fields(broken)
        return True

    def _active_views(self) -> dict[str, FloatArray]:
        """Named views of the fields in use (rows [0, n)); writes go to the model."""
        n = self._n
        if self._views_n != n:
            views = {name: arr[:n] for name, arr in self._store.items()}
            self._views = _with_diagonals(views, self.n_in)
            self._views_n = n
        return self._views

    def _activations(self, v: dict[str, FloatArray], xn: FloatArray) -> FloatArray:
        """Kernel activation w_j(x) of every field (thesis eq. 3.3), shape (n,)."""
        dx = xn - v["c"]
        if self.diag_only:
            q = (dx * dx * v["D_diag"]) @ self._ones
        else:
            q = np.einsum("ki,kij,kj->k", dx, v["D"], dx)
        w: FloatArray = np.exp(-0.5 * q)
        return w

    def _predict_normalised(
        self, v: dict[str, FloatArray], w: FloatArray, xn: FloatArray
    ) -> FloatArray:
        """Weighted mean of the trusted active fields' linear models (eqs. 3.1, 3.2, 3.4)."""
        n = self._n
        local = v["beta0"] + ((xn - v["mean_x"]) * v["slope"]) @ self._ones
        wu = np.where((w > self.cutoff) & self._trusted[:n], w, 0.0)
        out = self._out[:n]
        sw = np.bincount(out, weights=wu, minlength=self.n_out)
        swy = np.bincount(out, weights=wu * local, minlength=self.n_out)
        y: FloatArray = swy / np.where(sw > 0.0, sw, 1.0)  # 0 where no field contributes
        return y

    def _project(
        self, x_c: FloatArray, U: FloatArray, P: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """PLS projections s (k, R) of centred inputs x_c (k, d), and the input residual
        entering each projection (k, R, d): x_0 = x_c, s_r = u_r'x_r, x_{r+1} = x_r - p_r s_r.
        """
        k, R, d = U.shape
        s = np.empty((k, R))
        xres = np.empty((k, R, d))
        xr = x_c
        for j in range(R):
            xres[:, j] = xr
            s[:, j] = (U[:, j] * xr) @ self._ones
            if j + 1 < R:
                xr = xr - P[:, j] * s[:, j, None]
        return s, xres

    def _projections_in_use(self, v: dict[str, FloatArray], nreg: npt.NDArray[np.int64]) -> Any:
        """Projections a prediction uses: the newest only once it has seen > 2 n_in updates."""
        last_n_data = v["n_data"][np.arange(nreg.size), nreg - 1]
        return nreg - (last_n_data <= 2 * self.n_in)

    def _update_fields(
        self,
        v: dict[str, FloatArray],
        xn: FloatArray,
        yn: FloatArray,
        w: FloatArray,
        active: npt.NDArray[np.bool_],
    ) -> None:
        """Update the fields activated above the update threshold with one sample, in place.

        Every array operation runs over all fields; an inactive field gets weight 0 and
        forgetting factor 1, which leaves each of its statistics bit-for-bit unchanged.
        """
        n = self._n
        d = self.n_in
        nreg = self._nreg[:n]
        rows = np.arange(n)
        wa = w * active
        y = yn[self._out[:n]]
        lam, n_data = v["lam"], v["n_data"]
        in_use = self._r_idx < nreg[:, None]  # (n, R)
        act_r = in_use & active[:, None]
        # Unused projection slots see weight 0 and forgetting 1, so they stay as initialised.
        lam_u = np.where(act_r, lam, 1.0)
        w_r = wa[:, None] * act_r

        # Weighted means of x and y with forgetting: m <- m + w/(lambda W + w) (x - m).
        gain = wa / (v["sum_w"][:, 0] * lam[:, 0] + wa)
        mean_x = v["mean_x"]
        mean_x += gain[:, None] * (xn - mean_x)
        xmz = xn - mean_x
        v["var_x"][...] += gain[:, None] * (xmz * xmz - v["var_x"])
        beta0 = v["beta0"]
        beta0 += gain * (y - beta0)
        ymz = y - beta0

        # Incremental PLS (the errors e_cv use the coefficients from before this sample).
        U, P, beta, ss2 = v["U"], v["P"], v["beta"], v["ss2"]
        s = (v["G"] * xmz[:, None, :]) @ self._ones
        # Input residual entering each projection: x_0 = x, x_r = x - sum_{i<r} p_i s_i.
        xres = np.empty(U.shape)
        xres[:, 0] = xmz
        np.subtract(
            xmz[:, None, :], np.cumsum(P[:, :-1] * s[:, :-1, None], axis=1), out=xres[:, 1:]
        )
        e_cv = ymz[:, None] - (beta * s) @ self._cumsum  # errors with the first r+1 projections
        ytarget = np.concatenate((ymz[:, None], e_cv[:, :-1]), axis=1)
        sum_w = v["sum_w"]
        sum_w *= lam_u
        sum_w += w_r
        sxy = v["sxres_yres"]
        sxy *= (0.9 + 0.1 * lam_u)[..., None]  # the directions forget more slowly
        sxy += (w_r * ytarget)[..., None] * xres
        unorm = np.sqrt((sxy * sxy) @ self._ones)[..., None]
        np.divide(sxy, unorm, out=U, where=unorm > 1e-12)
        ws = w_r * s
        ss2 *= lam_u
        ss2 += ws * s
        syres = v["syres"]
        syres *= lam_u
        syres += ws * ytarget
        ssxres = v["ssxres"]
        ssxres *= lam_u[..., None]
        ssxres += ws[..., None] * xres
        # Unused slots have zero statistics, so their beta and p stay 0 (p_r of the newest
        # slot is only ever used by the slots after it).
        np.divide(syres, ss2, out=beta)
        np.divide(ssxres, ss2[..., None], out=P)
        lam_last = lam_u[rows, nreg - 1]
        ssp = v["ssp"]
        ssp *= lam_last
        ssp += (ws * ws / ss2) @ self._ones

        G = v["G"]
        G[...] = self._projection_rows(U, P)
        s = (G * xmz[:, None, :]) @ self._ones  # projections with the updated directions
        n_use = self._nuse[:n]
        y_fit = (beta * s * (self._r_idx < n_use[:, None])) @ self._ones
        i_cv = np.maximum(n_use - 1, 0)
        e_cv_r = e_cv[rows, i_cv]  # leave-one-out error of the projections in use
        e = ymz - y_fit
        enough = (n_data[:, 0] * (1.0 - lam[:, 0]) > 0.1) & active
        sum_e2 = v["sum_e2"]
        np.copyto(sum_e2, sum_e2 * lam_last + wa * e * e, where=enough)
        sum_e_cv2 = v["sum_e_cv2"]
        np.copyto(sum_e_cv2, sum_e_cv2 * lam_u + w_r * e_cv * e_cv, where=enough[:, None])
        self._trusted[:n] |= active & (n_data[:, 0] > 2 * d)

        if self.update_d:
            self._update_metric(v, act_r, xn, w, s, e_cv_r, e, i_cv)

        self._add_projections(v, nreg, active)

        act_r = (self._r_idx < nreg[:, None]) & active[:, None]
        np.copyto(n_data, n_data * lam + 1.0, where=act_r)
        np.copyto(
            lam, self.tau_lambda * lam + (1.0 - self.tau_lambda) * self.final_lambda, where=act_r
        )
        # Cache each field's linear model y = beta0 + slope'(x - mean_x) for predictions.
        n_use = self._projections_in_use(v, nreg)
        self._nuse[:n] = n_use
        coef = beta * (self._r_idx < n_use[:, None])
        v["slope"][...] = np.einsum("kr,krd->kd", coef, G)

    def _update_metric(
        self,
        v: dict[str, FloatArray],
        act_r: npt.NDArray[np.bool_],
        xn: FloatArray,
        w: FloatArray,
        s: FloatArray,
        e_cv: FloatArray,
        e: FloatArray,
        i_cv: npt.NDArray[np.int64],
    ) -> None:
        """Gradient step on M (D = M'M) against the incremental leave-one-out cost
        J = 1/W sum w e_cv^2 + penalty/n_in sum D_ij^2 (Vijayakumar et al. 2005, appendix).
        """
        lam, n_data, ss2 = v["lam"], v["n_data"], v["ss2"]
        H, r = v["H"], v["r"]
        ok = (n_data * (1.0 - lam[:, :1]) > 0.1) & act_r  # projections with enough data
        upd = ok[:, 0]
        if not upd.any():
            return
        n = self._n
        rows = np.arange(n)
        ps = np.where(ok, s / ss2, 0.0)
        h = w * ((ps * s) @ self._ones)  # leverage of this sample
        W = v["sum_w"][:, 0]
        E = v["sum_e_cv2"][rows, i_cv]
        # Safety heuristic of the reference library: damp steps while the fit is transient.
        trans = np.minimum((v["sum_e2"] / (E + 1e-10)) ** 4, 1.0)
        pse = e[:, None] * ps
        e_cv2 = e_cv * e_cv
        dJ1dw = (-E / W + e_cv2 - (2.0 * (pse * H + ps * ps * r)) @ self._ones) / W
        wW = w / W
        pen = self.penalty / self.n_in
        M, D, alpha = v["M"], v["D"], v["alpha"]
        dx = xn - v["c"]
        tm = trans * upd  # no step where the metric may not be updated yet

        if self.diag_only:
            # Only the diagonal: w = exp(-1/2 sum m_i^2 dx_i^2), D_ii = m_i^2.
            m, dd, al = v["M_diag"], v["D_diag"], v["alpha_diag"]
            dwdM = -w[:, None] * m * dx * dx
            dJ2dM = 4.0 * pen * m * dd
            dJdM = wW[:, None] * dJ2dM + dwdM * dJ1dw[:, None]
            if self.meta:
                ddwdMdM = w[:, None] * ((m * dx * dx) ** 2 - dx * dx)
                ddJ2dMdM = 12.0 * pen * dd
                self._meta_step(
                    v["meta_b_diag"],
                    v["meta_h_diag"],
                    al,
                    dJdM,
                    dwdM,
                    ddwdMdM,
                    ddJ2dMdM,
                    tm[:, None],
                    wW[:, None],
                    dJ1dw[:, None],
                    self._dj1_dw_dw(s, pse, ps, H, e, e_cv2, h, w, W, E)[:, None],
                )
            max_m = np.abs(m).max(axis=1)
            delta = al * tm[:, None] * dJdM
            too_big = delta > 0.1 * max_m[:, None]
            # A step that would shrink M by more than a tenth halves that rate instead.
            np.copyto(al, 0.5 * al, where=too_big)
            np.copyto(m, m - delta, where=~too_big)
            dd[...] = m * m
        else:
            mask = self._metric_mask
            Mdx = np.einsum("kij,kj->ki", M, dx)
            # w = exp(-q/2), q = |M dx|^2: dw/dM = -w (M dx) dx'; d/dM sum D_ij^2 = 4 M D.
            dqdM_half = Mdx[:, :, None] * dx[:, None, :]
            dwdM = -w[:, None, None] * dqdM_half * mask
            dJ2dM = 4.0 * pen * np.matmul(M, D) * mask
            dJdM = wW[:, None, None] * dJ2dM + dwdM * dJ1dw[:, None, None]
            if self.meta:
                dx2 = (dx * dx)[:, None, :]
                ddwdMdM = w[:, None, None] * (dqdM_half**2 - dx2) * mask
                row2 = ((M * M) @ self._ones)[:, :, None]
                Dmm = np.diagonal(D, axis1=1, axis2=2)[:, None, :]
                ddJ2dMdM = 4.0 * pen * (Dmm + row2 + M * M) * mask
                self._meta_step(
                    v["meta_b"],
                    v["meta_h"],
                    alpha,
                    dJdM,
                    dwdM,
                    ddwdMdM,
                    ddJ2dMdM,
                    tm[:, None, None],
                    wW[:, None, None],
                    dJ1dw[:, None, None],
                    self._dj1_dw_dw(s, pse, ps, H, e, e_cv2, h, w, W, E)[:, None, None],
                )
            max_m = np.abs(M * mask).max(axis=(1, 2))
            delta = alpha * tm[:, None, None] * dJdM
            too_big = delta > 0.1 * max_m[:, None, None]
            np.copyto(alpha, 0.5 * alpha, where=too_big)
            np.copyto(M, M - delta, where=~too_big)
            D[...] = np.matmul(np.swapaxes(M, 1, 2), M)

        ok &= upd[:, None]
        g = trans / (1.0 - h)
        np.copyto(H, lam * H + (w * g * e_cv)[:, None] * s, where=ok)
        np.copyto(r, lam * r + (w * w * e_cv2 * g)[:, None] * s * s, where=ok)

    @staticmethod
    def _dj1_dw_dw(
        s: FloatArray,
        pse: FloatArray,
        ps: FloatArray,
        H: FloatArray,
        e: FloatArray,
        e_cv2: FloatArray,
        h: FloatArray,
        w: FloatArray,
        W: FloatArray,
        E: FloatArray,
    ) -> FloatArray:
        """Second derivative of the leave-one-out cost by the activation (meta learning)."""
        s_pse = np.sum(s * pse, axis=1)
        acc = 2.0 * (e * e * h / np.maximum(w, 1e-300) - e_cv2 / W) + E / (W * W)
        acc = acc + np.sum(4.0 * (pse / W[:, None] + ps * s_pse[:, None]) * H, axis=1)
        out: FloatArray = acc / W
        return out

    def _meta_step(
        self,
        meta_b: FloatArray,
        meta_h: FloatArray,
        alpha: FloatArray,
        dJdM: FloatArray,
        dwdM: FloatArray,
        ddwdMdM: FloatArray,
        ddJ2dMdM: FloatArray,
        tm: FloatArray,
        wW: FloatArray,
        dJ1dw: FloatArray,
        ddJ1dwdw: FloatArray,
    ) -> None:
        """Incremental delta-bar-delta (Sutton 1992) on b = log(alpha), with the reference
        library's clipping; all arrays broadcast to the shape of ``alpha``, in place."""
        ddJdMdM = wW * ddJ2dMdM + ddwdMdM * dJ1dw + dwdM * dwdM * ddJ1dwdw
        step = np.clip(self.meta_rate * tm * dJdM * meta_h, -0.1, 0.1)
        moving = tm > 0.0
        meta_b[...] = np.where(moving, np.clip(meta_b - step, -10.0, 10.0), meta_b)
        alpha[...] = np.where(moving, np.exp(meta_b), alpha)
        decay = np.maximum(1.0 - alpha * ddJdMdM * tm, 0.0)
        meta_h[...] = np.where(moving, meta_h * decay - alpha * tm * dJdM, meta_h)

    def _add_projections(
        self,
        v: dict[str, FloatArray],
        nreg: npt.NDArray[np.int64],
        active: npt.NDArray[np.bool_],
    ) -> None:
        """Add a PLS projection where the newest one cut the leave-one-out error enough."""
        rows = np.arange(nreg.size)
        last = nreg - 1
        n_data = v["n_data"]
        n_last = n_data[rows, last]
        can = (nreg < self.n_in) & active & (n_last * (1.0 - v["lam"][rows, last]) > 0.5)
        if not can.any():
            return
        mse = v["sum_e_cv2"] / v["sum_w"] + 1e-10
        add = (
            can
            & (mse[rows, last] < self.add_threshold * mse[rows, np.maximum(nreg - 2, 0)])
            & (n_last > 0.99 * n_data[:, 0])
        )
        # The new slot has been kept in its initial state (weight 0, no forgetting).
        nreg[add] += 1
        v["ssp"][add] = 0.0

    @staticmethod
    def _projection_rows(U: FloatArray, P: FloatArray) -> FloatArray:
        """The PLS projections as linear maps, G (k, R, d) with s_r = g_r'x: from
        x_{r+1} = x_r - p_r s_r, g_r = T_r'u_r with T_0 = I, T_{r+1} = T_r - p_r g_r'."""
        R, d = U.shape[1:]
        G = np.empty(U.shape)
        G[:, 0] = U[:, 0]
        if R > 1:
            T = np.eye(d) - P[:, 0, :, None] * U[:, 0, None, :]
            for j in range(1, R):
                G[:, j] = np.einsum("ki,kij->kj", U[:, j], T)
                if j + 1 < R:
                    T = T - P[:, j, :, None] * G[:, j, None, :]
        return G

    def _add_or_prune(self, w: FloatArray, xn: FloatArray, yn: FloatArray) -> None:
        """Per output: a new field where none is active above w_gen, else prune one of the
        two most active fields if both exceed w_prune (the narrower one, larger trace D)."""
        n = self._n
        out = self._out[:n]
        # Fast path, almost every update: each output has a field above w_gen, and no
        # two fields exceed w_prune.
        w_best = np.zeros(self.n_out)
        np.maximum.at(w_best, out, w)
        if (w_best > self.w_gen).all() and np.count_nonzero(w > self.w_prune) < 2:
            return
        counts = np.bincount(out, minlength=self.n_out)
        order = np.lexsort((w, out))  # by output, then by activation
        ends = np.cumsum(counts)
        trace_d = self._store["D"].reshape(-1, self.n_in * self.n_in)[:, :: self.n_in + 1]
        prune: list[int] = []
        add: list[tuple[int, dict[str, FloatArray] | None, int]] = []
        for o in range(self.n_out):
            c = int(counts[o])
            i_max = int(order[ends[o] - 1]) if c else -1
            w_max = float(w[i_max]) if c else 0.0
            if w_max <= self.w_gen:
                if self.max_rfs is None or c < self.max_rfs:
                    if w_max > 0.1 * self.w_gen and self._trusted[i_max]:
                        row = {k: a[i_max].copy() for k, a in self._store.items()}
                        add.append((o, row, int(self._nreg[i_max])))
                    else:
                        add.append((o, None, 2 if self.n_in > 1 else 1))
            elif c >= 2 and w[order[ends[o] - 2]] > self.w_prune:
                i_sec = int(order[ends[o] - 2])
                tr_max, tr_sec = trace_d[i_max].sum(), trace_d[i_sec].sum()
                prune.append(i_max if tr_max > tr_sec else i_sec)
                self.n_pruned[o] += 1
        if prune:
            self._remove_fields(np.array(prune))
        for o, template, nreg in add:
            self._append_field(o, xn, float(yn[o]), template, nreg)

    def _remove_fields(self, rows: npt.NDArray[np.intp]) -> None:
        n = self._n
        keep = np.ones(n, dtype=bool)
        keep[rows] = False
        m = int(keep.sum())
        for arr in (*self._store.values(), self._out, self._nreg, self._trusted, self._nuse):
            arr[:m] = arr[:n][keep]
        self._n = m
        self._views_n = -1

    def _ensure_capacity(self, n: int) -> None:
        cap = self._out.shape[0]
        if n <= cap:
            return
        while cap < n:
            cap *= 2

        def grown(old: npt.NDArray[Any]) -> npt.NDArray[Any]:
            new = np.zeros((cap, *old.shape[1:]), dtype=old.dtype)
            new[: self._n] = old[: self._n]
            return new

        self._store = {k: grown(a) for k, a in self._store.items()}
        self._out, self._nreg = grown(self._out), grown(self._nreg)
        self._trusted, self._nuse = grown(self._trusted), grown(self._nuse)
        self._views_n = -1
        global _reallocations
        _reallocations += 1  # a ModelGroup holding the old arrays rebuilds its arguments

    def _append_field(
        self, o: int, xn: FloatArray, yn: float, template: dict[str, FloatArray] | None, nreg: int
    ) -> None:
        """A new field of output o centred at xn, with ``nreg`` PLS projections. Its metric,
        learning rates and offset come from ``template`` (the nearest trusted field's row)
        if given, else from the initial settings."""
        self._ensure_capacity(self._n + 1)
        i = self._n
        d = self.n_in
        v = _with_diagonals({k: a[i : i + 1] for k, a in self._store.items()}, d)
        for arr in v.values():
            arr[...] = 0.0
        if template is None:
            v["M"][0], v["D"][0], v["alpha"][0] = self.init_m, self.init_d, self.init_alpha
            v["beta0"][0] = yn
        else:
            for name in ("M", "D", "alpha", "beta0"):
                v[name][0] = template[name]
        v["meta_b"][0] = np.log(v["alpha"][0] + 1e-10)
        v["c"][0] = xn
        v["mean_x"][0] = xn
        v["U"][0] = v["P"][0] = v["G"][0] = np.eye(d)
        v["ss2"][0] = self.init_s2
        v["sum_w"][0] = 1e-10
        v["lam"][0] = self.init_lambda
        v["n_data"][0, :nreg] = 1e-10
        self._out[i] = o
        self._nreg[i] = nreg
        self._nuse[i] = nreg - 1  # the newest projection waits for data
        self._trusted[i] = False
        self._n = i + 1
        self._views_n = -1


# each model's fields in use (its ``_n``), read in C: a comprehension is a Python-level call
# on the position tick's path (issue 21)
_FIELDS_IN_USE = operator.attrgetter("_n")


class ModelGroup:
    """Several compiled models predicted in one compiled call: model ``g`` reads the columns
    ``ins[g]`` of the points and writes its outputs into the columns ``outs[g]`` of the
    result (an estimator's models, each on its own subspace). The same numbers as each
    model's :meth:`LWPR.predict_many` on its columns; one call instead of a few dozen
    Python-level calls a model (checks, normalisation, dispatch), which a position tick
    paid three times.

    ``predict_many`` answers None where it cannot promise that (a model without the
    compiled kernels, a point that is not finite or too large for a model's ``norm_in``):
    the caller then asks the models one by one, as before.
    """

    def __init__(
        self,
        models: list[LWPR],
        ins: list[tuple[int, ...]],
        outs: list[tuple[int, ...]],
        n_z: int,
        n_y: int,
    ) -> None:
        self.models = models
        self.n_z, self.n_y = n_z, n_y
        self.compiled = all(type(m).compiled for m in models) and len(models) > 0
        self._ins = tuple(np.array(i, dtype=np.int64) for i in ins)
        self._outs = tuple(np.array(o, dtype=np.int64) for o in outs)
        self._static = (
            tuple(m._cfg for m in models), self._ins, tuple(m.norm_in for m in models),
            self._outs, tuple(m.norm_out for m in models),
        )  # fmt: skip
        self._epoch = -1
        # the models' field arrays, rebuilt only after a store was reallocated: for the
        # predictions by argument (a tuple of every model's c, then D, ...); for the update,
        # each model's activations and prediction buffers and its store
        self._fields: tuple[tuple[npt.NDArray[Any], ...], ...] = ()
        # the update's and the prediction's arguments after ns, packed (kept alive), and
        # what the kernels are handed of them: (memory handle, type), lwpr_kernels.handle
        self._update_packed: Any = None
        self._predict_packed: Any = None
        self._update_handle: tuple[Any, Any] = (None, None)
        self._predict_handle: tuple[Any, Any] = (None, None)
        self._status = np.zeros(len(models), dtype=np.int64)  # update_groups' results
        self._kernel: Any = None  # predict_groups for these argument types
        self._update_kernel: Any = None  # update_groups for these argument types

    def __getstate__(self) -> dict[str, Any]:
        """A copy (``copy.deepcopy``, pickle) without the packed arguments: numba's typed
        lists do not copy, and a copy's would be the original's arrays. They are packed
        again from the copy's models at its first call."""
        state = self.__dict__.copy()
        state.update(_update_packed=None, _predict_packed=None, _update_handle=(None, None),
                     _predict_handle=(None, None), _epoch=-1)
        return state

    def _field_args(self) -> tuple[tuple[npt.NDArray[Any], ...], ...]:
        if self._epoch != _reallocations:
            self._epoch = _reallocations
            models = self.models
            for m in models:
                m._kernel_args()
            self._fields = tuple(zip(*(m._predict_args for m in models), strict=True))
            update_fields = (
                tuple(m._w_buf for m in models), tuple(m._y_buf for m in models),
                tuple(m._update_args for m in models),
            )  # fmt: skip
            # each kernel's arguments beyond the sample as one object (kernels.packed). The
            # cost is at compile time: on an empty cache the packed kernels and their typed
            # lists take ~17 s more CPU (the whole warm-up 11 -> 27 s idle), once, in the
            # cold start's background compile; a start on a warm cache is unchanged
            self._update_packed = kernels.packed((*self._static, *update_fields, self._status))
            self._predict_packed = kernels.packed((*self._static, *self._fields))
            self._update_handle = kernels.handle(self._update_packed)
            self._predict_handle = kernels.handle(self._predict_packed)
        return self._fields

    def update(self, z: FloatArray, p: FloatArray) -> bool:
        """Each model learns its columns of the sample ``z`` (n_z,) -> ``p`` (n_y,), float64
        arrays, finite: the same as each model's :meth:`LWPR.update_finite` on its columns.
        False (nothing learnt): not compiled, or an array not contiguous; ask the models one
        by one."""
        if not (self.compiled and z.flags.c_contiguous and p.flags.c_contiguous):
            return False
        models = self.models
        if self._epoch != _reallocations:  # (inline: a call is a tick's cost, issue 21)
            self._field_args()
        ns = tuple(map(_FIELDS_IN_USE, models))
        kernel = self._update_kernel
        handle, handle_type = self._update_handle
        if kernel is None:  # (the types are fixed: z and p are checked by the caller)
            kernel = self._update_kernel = jit.entry_point(
                kernels.update_groups_packed, z, p, ns, handle, handle_type)
        kernel(z, p, ns, handle, handle_type)
        for g, status in enumerate(self._status.tolist()):
            model = models[g]
            if status:  # the rare work in Python (a field to add, prune or drop)
                xn = z[self._ins[g]] / model.norm_in
                yn = p[self._outs[g]] / model.norm_out
                model._after_update(status, model._w_buf[: ns[g]], xn, yn)
            else:
                model.n_updates += 1
        return True

    def predict_args(self) -> tuple[tuple[int, ...], Any, Any] | None:
        """The compiled prediction's arguments after the points and the output (each
        model's field count, the packed fields' handle and type:
        ``lwpr_kernels.predict_groups_packed``), up to date; None: not compiled."""
        if not self.compiled:
            return None
        if self._epoch != _reallocations:
            self._field_args()
        return tuple(map(_FIELDS_IN_USE, self.models)), *self._predict_handle

    def predict_many(self, zs: FloatArray) -> FloatArray | None:
        """(m, n_y) predictions at the rows of ``zs`` (m, n_z) float64, C-contiguous; the
        columns no model writes are 0. None: ask the models one by one."""
        packed = self.predict_args()
        if packed is None:
            return None
        raw = np.zeros((zs.shape[0], self.n_y))
        args = (zs, raw, *packed)
        kernel = self._kernel
        if kernel is None:  # (the types are fixed: zs is checked by the caller)
            kernel = self._kernel = jit.entry_point(kernels.predict_groups_packed, *args)
        return raw if kernel(*args) else None


class LwprReference(LWPR):
    """The numpy implementation of ``LWPR``: every quantity updated as array operations over
    all fields at once. The oracle of the compiled ``LWPR`` in the tests (same predictions, to
    the rounding of a different order of operations, over sample streams), and what ``LWPR``
    runs when numba is not installed. Same settings, methods and file format (a file saved by
    one loads into the other)."""

    compiled: ClassVar[bool] = False


def warm_up() -> float:
    """Compile the LWPR kernels now (or load them from numba's on-disk cache), so that the
    first ``update`` / ``predict`` / ``predict_many`` of a control loop does not: a model
    learns a few samples, adding fields, and predicts. Returns the seconds it took (0 without
    numba). The kernels take the same argument types for every model, so this covers all."""
    if not LWPR.compiled:
        return 0.0
    t0 = time.perf_counter()
    model = LWPR(2, 2, init_d=4.0, diag_only=False, meta=True)
    for k in range(40):
        x = np.array([math.sin(0.3 * k), math.cos(0.7 * k)])
        model.update(x, [x[0] * x[1], x[0] - x[1]])
    model.predict(x)
    model.predict_many(np.zeros((3, 2)))
    return time.perf_counter() - t0
