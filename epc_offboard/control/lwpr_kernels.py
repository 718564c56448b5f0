"""LWPR's per-sample work in compiled loops: activations, prediction, and the update of the
active receptive fields (incremental PLS, distance metric, new projections).

These are the equations of :class:`epc_offboard.control.lwpr.LwprReference` (the numpy
implementation, vectorised over fields), written as one loop over the fields that skips the
inactive ones, with the same operations in the same order wherever numpy's order is known:
the tests hold the two to 1e-9 over streams of thousands of samples. The arrays are the
model's field store (see ``epc_offboard.control.lwpr._schema``, one row per field, full capacity);
the kernels read rows [0, n) and update them in place. Only adding and pruning fields, which
change the number of rows and happen on a few percent of the samples at most, stay in Python.

Compiled with numba when it is installed (as in ``control.kernels``: cached on disk when
the package directory is writable, else compiled in memory); without numba ``HAVE_NUMBA`` is
False and ``epc_offboard.control.lwpr.LWPR`` runs the numpy implementation.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np

from epc_offboard.common import jit
from epc_offboard.common.frames import FloatArray

# A field takes part in an update only above this activation (reference library).
W_UPDATE_MIN = 0.001

# Layout of the settings vector ``cfg`` every kernel takes (one array: cheaper to pass).
CFG_CUTOFF = 0
CFG_W_GEN = 1
CFG_W_PRUNE = 2
CFG_PEN = 3  # penalty / n_in
CFG_TAU_LAMBDA = 4
CFG_FINAL_LAMBDA = 5
CFG_ADD_THRESHOLD = 6
CFG_META_RATE = 7
CFG_DIAG_ONLY = 8  # flags: 1.0 true, 0.0 false
CFG_UPDATE_D = 9
CFG_META = 10
CFG_SIZE = 11

# Bits of the update kernel's result.
STATUS_NOT_FINITE = 1  # an updated field's statistics overflowed: drop it (Python)
STATUS_ADD_OR_PRUNE = 2  # some output needs a new field, or two fields overlap (Python)

if jit.enabled():
    try:
        import numba
    except ImportError:  # numba is a dependency; LWPR falls back to numpy without it
        numba = None  # type: ignore[assignment]
else:  # the numpy twins (a cold start, see common.jit): not even numba's import
    numba = None  # type: ignore[assignment]

HAVE_NUMBA = numba is not None

F = TypeVar("F", bound=Callable[..., Any])


def _jit(fn: F) -> F:
    """``fn`` compiled (nopython, no GIL, strict IEEE arithmetic: no fastmath, so that the
    results follow the numpy oracle), or ``fn`` itself without numba."""
    if numba is None:
        return fn
    return jit.njit_cached(fn, nogil=True)


@_jit
def activations(
    xn: FloatArray, n: int, c: FloatArray, D: FloatArray, diag_only: bool, w: FloatArray
) -> None:
    """w[j] = exp(-1/2 (xn - c_j)' D_j (xn - c_j)) for the fields j < n (thesis eq. 3.3)."""
    d = xn.shape[0]
    for j in range(n):
        q = 0.0
        if diag_only:
            for i in range(d):
                dx = xn[i] - c[j, i]
                q += dx * dx * D[j, i, i]
        else:
            for i in range(d):
                dxi = xn[i] - c[j, i]
                acc = 0.0
                for k in range(d):
                    acc += D[j, i, k] * (xn[k] - c[j, k])
                q += dxi * acc
        w[j] = math.exp(-0.5 * q)


@_jit
def predict_from(
    xn: FloatArray,
    n: int,
    w: FloatArray,
    cutoff: float,
    beta0: FloatArray,
    mean_x: FloatArray,
    slope: FloatArray,
    trusted: Any,
    out: Any,
    y: FloatArray,
) -> None:
    """y (n_out,) = the w-weighted mean of the trusted fields' linear models
    beta0_j + slope_j'(xn - mean_x_j) over the fields above ``cutoff``; 0 where none is."""
    d = xn.shape[0]
    n_out = y.shape[0]
    sw = np.zeros(n_out)
    for o in range(n_out):
        y[o] = 0.0
    for j in range(n):
        wj = w[j]
        if wj > cutoff and trusted[j]:
            acc = 0.0
            for i in range(d):
                acc += (xn[i] - mean_x[j, i]) * slope[j, i]
            o = out[j]
            sw[o] += wj
            y[o] += wj * (beta0[j] + acc)
    for o in range(n_out):
        if sw[o] > 0.0:
            y[o] /= sw[o]


@_jit
def predict_many(
    xn: FloatArray,
    n: int,
    cfg: FloatArray,
    y: FloatArray,
    c: FloatArray,
    D: FloatArray,
    beta0: FloatArray,
    mean_x: FloatArray,
    slope: FloatArray,
    trusted: Any,
    out: Any,
) -> bool:
    """Predictions at the rows of xn (m, d) into the rows of y (m, n_out); False, and y
    untouched, if a value of xn is not finite (checked here: cheaper than numpy's check)."""
    for row in range(xn.shape[0]):
        for i in range(xn.shape[1]):
            if not math.isfinite(xn[row, i]):
                return False
    w = np.empty(n)
    diag_only = cfg[CFG_DIAG_ONLY] != 0.0
    for row in range(xn.shape[0]):
        activations(xn[row], n, c, D, diag_only, w)
        predict_from(xn[row], n, w, cfg[CFG_CUTOFF], beta0, mean_x, slope, trusted, out, y[row])
    return True


@_jit
def predict_groups(
    zs: FloatArray,
    raw: FloatArray,
    ns: Any,
    cfgs: Any,
    ins: Any,
    norm_ins: Any,
    outs: Any,
    norm_outs: Any,
    cs: Any,
    Ds: Any,
    beta0s: Any,
    mean_xs: Any,
    slopes: Any,
    trusteds: Any,
    field_outs: Any,
) -> bool:
    """Several models' :func:`predict_many` in one call (an estimator's models, each on its
    own columns of the same points): for model g, the predictions at ``zs[:, ins[g]] /
    norm_ins[g]`` times ``norm_outs[g]`` into ``raw[:, outs[g]]``; a model without fields
    leaves its columns of ``raw`` as they are. The per-model arguments are tuples, one
    element a model (``ns``: its field count; the rest as :func:`predict_many`'s).

    The same numbers as a call of :func:`predict_many` per model: the normalisation and
    the scaling are the divisions and products the Python side did, and every activation
    and sum is :func:`activations` and :func:`predict_from`'s, in their order. Only what
    cannot reach a prediction is skipped: a field that is not trusted, and the exponential
    of a field whose activation is far below ``cutoff`` (its exponent more than 1 below
    log(cutoff): exp is monotone and correct to an ulp). False if a value of zs, or a
    normalised input, is not finite (then nothing is promised of ``raw``)."""
    m = zs.shape[0]
    for row in range(m):
        for i in range(zs.shape[1]):
            if not math.isfinite(zs[row, i]):
                return False
    for g in range(len(ns)):
        n = ns[g]
        if n == 0:
            continue
        cols = ins[g]
        norm_in = norm_ins[g]
        d = cols.shape[0]
        xn = np.empty((m, d))
        for row in range(m):
            for i in range(d):
                v = zs[row, cols[i]] / norm_in[i]
                if not math.isfinite(v):
                    return False
                xn[row, i] = v
        cfg = cfgs[g]
        cutoff = cfg[CFG_CUTOFF]
        diag_only = cfg[CFG_DIAG_ONLY] != 0.0
        # below this exponent exp() is below cutoff whatever its last ulp
        far = math.log(cutoff) - 1.0 if cutoff > 0.0 else -math.inf
        c, D, beta0, mean_x, slope = cs[g], Ds[g], beta0s[g], mean_xs[g], slopes[g]
        trusted, out = trusteds[g], field_outs[g]
        out_cols = outs[g]
        norm_out = norm_outs[g]
        n_out = out_cols.shape[0]
        y = np.empty(n_out)
        sw = np.empty(n_out)
        # activations() and predict_from() written out here, not called: each call per
        # field passes every array as a struct, and as helpers (numba's inline="always"
        # too) they doubled this kernel's cost (6.6 -> 12-14 us, the position tick's 21
        # stages); the same operations in their order, so the same bits
        for row in range(m):
            x = xn[row]
            for o in range(n_out):
                y[o] = 0.0
                sw[o] = 0.0
            for j in range(n):
                if not trusted[j]:
                    continue
                q = 0.0  # activations()'s exponent, in its order
                if diag_only:
                    for i in range(d):
                        dx = x[i] - c[j, i]
                        q += dx * dx * D[j, i, i]
                else:
                    for i in range(d):
                        dxi = x[i] - c[j, i]
                        acc = 0.0
                        for k in range(d):
                            acc += D[j, i, k] * (x[k] - c[j, k])
                        q += dxi * acc
                e = -0.5 * q
                if e < far:
                    continue
                wj = math.exp(e)
                if wj > cutoff:  # predict_from()'s sums, in its order
                    acc = 0.0
                    for i in range(d):
                        acc += (x[i] - mean_x[j, i]) * slope[j, i]
                    o = out[j]
                    sw[o] += wj
                    y[o] += wj * (beta0[j] + acc)
            for o in range(n_out):
                if sw[o] > 0.0:
                    y[o] /= sw[o]
                raw[row, out_cols[o]] = y[o] * norm_out[o]
    return True


@_jit
def _meta_step(
    meta_b: FloatArray,
    meta_h: FloatArray,
    alpha: FloatArray,
    j: int,
    a: int,
    b: int,
    meta_rate: float,
    tm: float,
    dJdM: float,
    ddJdMdM: float,
) -> None:
    """Incremental delta-bar-delta on log(alpha) of one metric entry (a, b) of field j."""
    step = min(max(meta_rate * tm * dJdM * meta_h[j, a, b], -0.1), 0.1)
    meta_b[j, a, b] = min(max(meta_b[j, a, b] - step, -10.0), 10.0)
    al = math.exp(meta_b[j, a, b])
    alpha[j, a, b] = al
    decay = max(1.0 - al * ddJdMdM * tm, 0.0)
    meta_h[j, a, b] = meta_h[j, a, b] * decay - al * tm * dJdM


@_jit
def _update_metric(
    j: int,
    xn: FloatArray,
    wj: float,
    nr: int,
    i_cv: int,
    s: FloatArray,
    e_cv_r: float,
    e: float,
    cfg: FloatArray,
    metric: tuple[FloatArray, ...],
    stats: tuple[FloatArray, ...],
    scratch: tuple[FloatArray, ...],
) -> None:
    """Gradient step on M (D = M'M) of field j against the leave-one-out cost, and the
    update of its cost statistics H, r (LwprReference._update_metric, one field).

    metric: the store's (c, M, D, alpha, meta_b, meta_h); stats: its (ss2, sum_w, sum_e_cv2,
    sum_e2, n_data, lam, H, r); scratch: work arrays (d,), (d,), (d,), (d, d).
    """
    c, M, D, alpha, meta_b, meta_h = metric
    ss2, sum_w, sum_e_cv2, sum_e2, n_data, lam, H, r = stats
    ps, dx, Mdx, dJdM = scratch
    d = xn.shape[0]
    R = d
    # projections with enough data; the metric is adapted only if the first one has
    one_minus_lam0 = 1.0 - lam[j, 0]
    if not (n_data[j, 0] * one_minus_lam0 > 0.1 and nr > 0):
        return
    h_acc = 0.0
    for rr in range(R):
        if rr < nr and n_data[j, rr] * one_minus_lam0 > 0.1:
            ps[rr] = s[rr] / ss2[j, rr]
        else:
            ps[rr] = 0.0
        h_acc += ps[rr] * s[rr]
    h = wj * h_acc
    W = sum_w[j, 0]
    E = sum_e_cv2[j, i_cv]
    trans = min((sum_e2[j] / (E + 1e-10)) ** 4.0, 1.0)  # pow(), as numpy's ** 4
    e_cv2 = e_cv_r * e_cv_r
    acc = 0.0
    for rr in range(R):
        acc += 2.0 * (e * ps[rr] * H[j, rr] + ps[rr] * ps[rr] * r[j, rr])
    dJ1dw = (-E / W + e_cv2 - acc) / W
    wW = wj / W
    pen = cfg[CFG_PEN]
    tm = trans
    meta = cfg[CFG_META] != 0.0
    meta_rate = cfg[CFG_META_RATE]
    ddJ1dwdw = 0.0
    if meta:
        s_pse = 0.0
        for rr in range(R):
            s_pse += s[rr] * (e * ps[rr])
        acc2 = 2.0 * (e * e * h / max(wj, 1e-300) - e_cv2 / W) + E / (W * W)
        acc3 = 0.0
        for rr in range(R):
            acc3 += 4.0 * ((e * ps[rr]) / W + ps[rr] * s_pse) * H[j, rr]
        ddJ1dwdw = (acc2 + acc3) / W
    for i in range(d):
        dx[i] = xn[i] - c[j, i]

    if cfg[CFG_DIAG_ONLY] != 0.0:
        max_m = 0.0
        for i in range(d):
            m = M[j, i, i]
            dd = D[j, i, i]
            dwdM = -wj * m * dx[i] * dx[i]
            dJ2dM = 4.0 * pen * m * dd
            dJdM[i, i] = wW * dJ2dM + dwdM * dJ1dw
            if meta and tm > 0.0:
                ddwdMdM = wj * ((m * dx[i] * dx[i]) ** 2 - dx[i] * dx[i])
                ddJ2dMdM = 12.0 * pen * dd
                ddJdMdM = wW * ddJ2dMdM + ddwdMdM * dJ1dw + dwdM * dwdM * ddJ1dwdw
                _meta_step(meta_b, meta_h, alpha, j, i, i, meta_rate, tm, dJdM[i, i], ddJdMdM)
            max_m = max(max_m, abs(m))
        for i in range(d):
            delta = alpha[j, i, i] * tm * dJdM[i, i]
            if delta > 0.1 * max_m:  # a step that would shrink M too much halves the rate
                alpha[j, i, i] = 0.5 * alpha[j, i, i]
            else:
                M[j, i, i] = M[j, i, i] - delta
            D[j, i, i] = M[j, i, i] * M[j, i, i]
    else:
        # w = exp(-q/2), q = |M dx|^2: dw/dM = -w (M dx) dx'; d/dM sum D_ij^2 = 4 M D;
        # only the upper triangle of M is adapted (mask).
        for a in range(d):
            acc = 0.0
            for b in range(d):
                acc += M[j, a, b] * dx[b]
            Mdx[a] = acc
        max_m = 0.0
        for a in range(d):
            for b in range(d):
                mask = 1.0 if b >= a else 0.0
                dq = Mdx[a] * dx[b]
                dwdM = -wj * dq * mask
                md = 0.0
                for k in range(d):
                    md += M[j, a, k] * D[j, k, b]
                dJ2dM = 4.0 * pen * md * mask
                dJdM[a, b] = wW * dJ2dM + dwdM * dJ1dw
                if meta and tm > 0.0:
                    ddwdMdM = wj * (dq**2 - dx[b] * dx[b]) * mask
                    row2 = 0.0
                    for k in range(d):
                        row2 += M[j, a, k] * M[j, a, k]
                    ddJ2dMdM = 4.0 * pen * (D[j, b, b] + row2 + M[j, a, b] * M[j, a, b]) * mask
                    ddJdMdM = wW * ddJ2dMdM + ddwdMdM * dJ1dw + dwdM * dwdM * ddJ1dwdw
                    _meta_step(meta_b, meta_h, alpha, j, a, b, meta_rate, tm, dJdM[a, b], ddJdMdM)
                max_m = max(max_m, abs(M[j, a, b] * mask))
        for a in range(d):
            for b in range(d):
                delta = alpha[j, a, b] * tm * dJdM[a, b]
                if delta > 0.1 * max_m:
                    alpha[j, a, b] = 0.5 * alpha[j, a, b]
                else:
                    M[j, a, b] = M[j, a, b] - delta
        for a in range(d):
            for b in range(d):
                acc = 0.0
                for k in range(d):
                    acc += M[j, k, a] * M[j, k, b]
                D[j, a, b] = acc

    g = trans / (1.0 - h)
    for rr in range(R):
        if rr < nr and n_data[j, rr] * one_minus_lam0 > 0.1:
            H[j, rr] = lam[j, rr] * H[j, rr] + (wj * g * e_cv_r) * s[rr]
            r[j, rr] = lam[j, rr] * r[j, rr] + (wj * wj * e_cv2 * g) * s[rr] * s[rr]


@_jit
def update(
    xn: FloatArray,
    yn: FloatArray,
    n: int,
    cfg: FloatArray,
    w: FloatArray,
    y_before: FloatArray,
    c: FloatArray,
    mean_x: FloatArray,
    var_x: FloatArray,
    slope: FloatArray,
    M: FloatArray,
    D: FloatArray,
    alpha: FloatArray,
    meta_b: FloatArray,
    meta_h: FloatArray,
    ss2: FloatArray,
    syres: FloatArray,
    beta: FloatArray,
    sum_w: FloatArray,
    sum_e_cv2: FloatArray,
    n_data: FloatArray,
    lam: FloatArray,
    H: FloatArray,
    r: FloatArray,
    U: FloatArray,
    P: FloatArray,
    sxy: FloatArray,
    ssxres: FloatArray,
    G: FloatArray,
    beta0: FloatArray,
    sum_e2: FloatArray,
    ssp: FloatArray,
    out: Any,
    nreg: Any,
    trusted: Any,
    nuse: Any,
) -> int:
    """Learn one sample (xn (d,), yn (n_out,), normalised) in the fields j < n, in place.

    Writes the activations into w (n,) and the prediction from before the update into
    y_before (n_out,). Returns STATUS_* bits for the work left to Python.
    """
    d = xn.shape[0]
    R = d
    n_out = yn.shape[0]
    activations(xn, n, c, D, cfg[CFG_DIAG_ONLY] != 0.0, w)
    predict_from(xn, n, w, cfg[CFG_CUTOFF], beta0, mean_x, slope, trusted, out, y_before)
    update_d = cfg[CFG_UPDATE_D] != 0.0
    tau = cfg[CFG_TAU_LAMBDA]
    final = cfg[CFG_FINAL_LAMBDA]
    xmz = np.empty(d)
    s = np.empty(R)
    s_new = np.empty(R)
    e_cv = np.empty(R)
    ytarget = np.empty(R)
    ws = np.empty(R)
    xres = np.empty((R, d))
    cum = np.empty(d)
    T = np.empty((d, d))
    metric = (c, M, D, alpha, meta_b, meta_h)
    stats = (ss2, sum_w, sum_e_cv2, sum_e2, n_data, lam, H, r)
    scratch = (np.empty(R), np.empty(d), np.empty(d), np.empty((d, d)))
    status = 0
    for j in range(n):
        wj = w[j]
        if not wj > W_UPDATE_MIN:
            continue
        nr = nreg[j]
        # Weighted means of x and y with forgetting: m <- m + w/(lambda W + w) (x - m).
        gain = wj / (sum_w[j, 0] * lam[j, 0] + wj)
        for i in range(d):
            mean_x[j, i] += gain * (xn[i] - mean_x[j, i])
        for i in range(d):
            xmz[i] = xn[i] - mean_x[j, i]
            var_x[j, i] += gain * (xmz[i] * xmz[i] - var_x[j, i])
        beta0[j] += gain * (yn[out[j]] - beta0[j])
        ymz = yn[out[j]] - beta0[j]

        # Incremental PLS (the errors e_cv use the coefficients from before this sample).
        for rr in range(R):
            acc = 0.0
            for i in range(d):
                acc += G[j, rr, i] * xmz[i]
            s[rr] = acc
        # Input residual entering each projection: x_0 = x, x_r = x - sum_{i<r} p_i s_i.
        for i in range(d):
            xres[0, i] = xmz[i]
            cum[i] = 0.0
        for rr in range(1, R):
            for i in range(d):
                cum[i] += P[j, rr - 1, i] * s[rr - 1]
                xres[rr, i] = xmz[i] - cum[i]
        acc = 0.0
        for rr in range(R):  # errors with the first rr+1 projections
            acc += beta[j, rr] * s[rr]
            e_cv[rr] = ymz - acc
        ytarget[0] = ymz
        for rr in range(1, R):
            ytarget[rr] = e_cv[rr - 1]
        # Unused projection slots see weight 0 and forgetting 1: they stay as initialised.
        for rr in range(R):
            lu = lam[j, rr] if rr < nr else 1.0
            wr = wj if rr < nr else 0.0
            sum_w[j, rr] = sum_w[j, rr] * lu + wr
            forget = 0.9 + 0.1 * lu  # the directions forget more slowly
            wy = wr * ytarget[rr]
            norm2 = 0.0
            for i in range(d):
                v = sxy[j, rr, i] * forget + wy * xres[rr, i]
                sxy[j, rr, i] = v
                norm2 += v * v
            unorm = math.sqrt(norm2)
            if unorm > 1e-12:
                for i in range(d):
                    U[j, rr, i] = sxy[j, rr, i] / unorm
            ws[rr] = wr * s[rr]
            ss2[j, rr] = ss2[j, rr] * lu + ws[rr] * s[rr]
            syres[j, rr] = syres[j, rr] * lu + ws[rr] * ytarget[rr]
            for i in range(d):
                ssxres[j, rr, i] = ssxres[j, rr, i] * lu + ws[rr] * xres[rr, i]
            beta[j, rr] = syres[j, rr] / ss2[j, rr]
            for i in range(d):
                P[j, rr, i] = ssxres[j, rr, i] / ss2[j, rr]
        lam_last = lam[j, nr - 1]
        acc = 0.0
        for rr in range(R):
            acc += ws[rr] * ws[rr] / ss2[j, rr]
        ssp[j] = ssp[j] * lam_last + acc

        # The projections as linear maps, s_r = g_r'x: g_r = T_r'u_r with T_0 = I,
        # T_{r+1} = T_r - p_r g_r'.
        for i in range(d):
            G[j, 0, i] = U[j, 0, i]
        if R > 1:
            for a in range(d):
                for b in range(d):
                    T[a, b] = (1.0 if a == b else 0.0) - P[j, 0, a] * U[j, 0, b]
            for rr in range(1, R):
                for b in range(d):
                    acc = 0.0
                    for a in range(d):
                        acc += U[j, rr, a] * T[a, b]
                    G[j, rr, b] = acc
                if rr + 1 < R:
                    for a in range(d):
                        for b in range(d):
                            T[a, b] = T[a, b] - P[j, rr, a] * G[j, rr, b]
        for rr in range(R):  # projections with the updated directions
            acc = 0.0
            for i in range(d):
                acc += G[j, rr, i] * xmz[i]
            s_new[rr] = acc
        n_use = nuse[j]
        y_fit = 0.0
        for rr in range(n_use):
            y_fit += beta[j, rr] * s_new[rr]
        i_cv = max(n_use - 1, 0)
        e_cv_r = e_cv[i_cv]  # leave-one-out error of the projections in use
        e = ymz - y_fit
        if n_data[j, 0] * (1.0 - lam[j, 0]) > 0.1:
            sum_e2[j] = sum_e2[j] * lam_last + wj * e * e
            for rr in range(R):
                lu = lam[j, rr] if rr < nr else 1.0
                wr = wj if rr < nr else 0.0
                sum_e_cv2[j, rr] = sum_e_cv2[j, rr] * lu + wr * e_cv[rr] * e_cv[rr]
        if n_data[j, 0] > 2 * d:
            trusted[j] = True

        if update_d:
            _update_metric(j, xn, wj, nr, i_cv, s_new, e_cv_r, e, cfg, metric, stats, scratch)

        # A new PLS projection where the newest one cut the leave-one-out error enough.
        last = nr - 1
        n_last = n_data[j, last]
        if nr < d and n_last * (1.0 - lam[j, last]) > 0.5:
            mse_last = sum_e_cv2[j, last] / sum_w[j, last] + 1e-10
            prev = max(nr - 2, 0)
            mse_prev = sum_e_cv2[j, prev] / sum_w[j, prev] + 1e-10
            if mse_last < cfg[CFG_ADD_THRESHOLD] * mse_prev and n_last > 0.99 * n_data[j, 0]:
                nr += 1
                nreg[j] = nr
                ssp[j] = 0.0
        for rr in range(nr):
            n_data[j, rr] = n_data[j, rr] * lam[j, rr] + 1.0
            lam[j, rr] = tau * lam[j, rr] + (1.0 - tau) * final
        # The newest projection is used once it has seen more than 2 n_in updates.
        n_use = nr - 1 if n_data[j, nr - 1] <= 2 * d else nr
        nuse[j] = n_use
        # Cache the field's linear model y = beta0 + slope'(x - mean_x) for predictions.
        health = beta0[j]
        for i in range(d):
            acc = 0.0
            for rr in range(n_use):
                acc += beta[j, rr] * G[j, rr, i]
            slope[j, i] = acc
            health += acc + M[j, i, i]
        if not math.isfinite(health):
            status |= STATUS_NOT_FINITE

    # Fast path, almost every update: each output has a field above w_gen, and no two
    # fields exceed w_prune.
    w_best = np.zeros(n_out)
    n_over = 0
    for j in range(n):
        w_best[out[j]] = max(w_best[out[j]], w[j])
        if w[j] > cfg[CFG_W_PRUNE]:
            n_over += 1
    for o in range(n_out):
        if not w_best[o] > cfg[CFG_W_GEN]:
            n_over = 2
    if n_over >= 2:
        status |= STATUS_ADD_OR_PRUNE
    return status


@_jit
def update_groups(
    z: FloatArray,
    p: FloatArray,
    ns: Any,
    cfgs: Any,
    ins: Any,
    norm_ins: Any,
    outs: Any,
    norm_outs: Any,
    w_bufs: Any,
    y_bufs: Any,
    fields: Any,
    status: Any,
) -> None:
    """Several models' :func:`update` in one call (an estimator's models, each learning its
    columns of one sample): model g learns ``z[ins[g]] / norm_ins[g]`` ->
    ``p[outs[g]] / norm_outs[g]`` (the divisions the Python side did) with its field store
    ``fields[g]`` (:func:`update`'s arguments after ``y_before``, as a tuple) and writes
    :func:`update`'s result into ``status[g]``. The work left to Python (``STATUS_*`` bits)
    is done by the caller, model by model, as after :func:`update`."""
    for g in range(len(ns)):
        cols = ins[g]
        norm_in = norm_ins[g]
        xn = np.empty(cols.shape[0])
        for i in range(cols.shape[0]):
            xn[i] = z[cols[i]] / norm_in[i]
        out_cols = outs[g]
        norm_out = norm_outs[g]
        yn = np.empty(out_cols.shape[0])
        for o in range(out_cols.shape[0]):
            yn[o] = p[out_cols[o]] / norm_out[o]
        status[g] = update(xn, yn, ns[g], cfgs[g], w_bufs[g], y_bufs[g], *fields[g])


# -- one object to unbox ----------------------------------------------------------------------
# A compiled function called from Python unboxes each array of its arguments (a reference and
# a numba record each). The estimator's update took its models' field stores as ~110 arrays:
# 5 us a call warm and 48 us when the caches were cold, as they are 10 ms after the last
# tick in real time (issue 21), for a kernel whose work is a few us. Packed once into a
# one-element typed list (the arrays inside it are the same memory: the kernel's writes are
# the model's), a call unboxes one object. Not the list itself, though: numba unboxes a typed
# list by calling back into Python (``numba.core.serialize._numba_unpickle``, for the class
# it checks the object against), ~45 us of a cold tick. The kernels take the list's memory
# handle (``handle``: its ``_opaque`` MemInfo, unboxed in C) and its type (a TypeRef: nothing
# to unbox) and rebuild the list inside (``listobject._from_meminfo``, numba's own way back
# from a handle): in isolation, a cold call 24-32 -> 9-16 us.


def _packed_numpy(args: Any) -> Any:
    return [args]


def _handle_numpy(packed_args: Any) -> tuple[Any, Any]:
    return packed_args, None


def _unpack_numpy(handle: Any, list_type: Any) -> Any:
    return handle[0]


def _packed_jit(args: Any) -> Any:
    out = List()
    out.append(args)
    return out


def _unpack_jit(handle: Any, list_type: Any) -> Any:
    return listobject._from_meminfo(handle, list_type)[0]  # type: ignore[call-arg]


def _handle_jit(packed_args: Any) -> tuple[Any, Any]:
    return packed_args._opaque, numba.typeof(packed_args)  # type: ignore[no-untyped-call]


if numba is not None:
    from numba.typed import List, listobject

    packed = _jit(_packed_jit)
    """``args`` (a tuple) as a one-element numba typed list, made inside a cached compiled
    function (a typed list's own methods called from Python compile in every process)."""
    handle = _handle_jit
    """What a kernel taking ``packed(args)`` is handed: (its memory handle, its type). Keep
    the list alive while the handle is used (the handle holds its memory too)."""
    _unpack = _jit(_unpack_jit)
else:
    packed = _packed_numpy
    handle = _handle_numpy
    _unpack = _unpack_numpy


@_jit
def update_groups_packed(z: FloatArray, p: FloatArray, ns: Any, args: Any,
                         args_type: Any) -> None:
    """:func:`update_groups` with its arguments after ``ns`` in ``packed(args)``, handed as
    ``handle(packed(args))``."""
    a = _unpack(args, args_type)
    update_groups(z, p, ns, a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7], a[8])


@_jit
def predict_groups_packed(zs: FloatArray, raw: FloatArray, ns: Any, args: Any,
                          args_type: Any) -> bool:
    """:func:`predict_groups` with its arguments after ``ns`` in ``packed(args)``, handed as
    ``handle(packed(args))``."""
    a = _unpack(args, args_type)
    return predict_groups(zs, raw, ns, a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7], a[8],
                          a[9], a[10], a[11])
