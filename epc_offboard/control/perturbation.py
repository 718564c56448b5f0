"""Perturbation estimators: the one-step model error p^ that corrects the affine model.

Thesis 3.1.1: the affine model x[k+1] = A x[k] + B u[k] + c is corrected to
c~ = c + p^, where p^ estimates p = x[k+1] - x_nom[k+1], the difference between the
measured next state and the model's prediction from z = [x[k]; u[k]]. Every estimator here
has the same protocol, so scenarios can compare them side by side:

    est.observe(z, p_measured)   # after each model step: z (n_z,), p_measured (nx,)
    p_hat = est.estimate(z)      # once per control tick, at the current query point: (nx,)
    dp = est.variation(z, zs)    # (m, nx): how the estimate changes from z to each row of zs
    p_hat, dp = est.estimate_along(zs)   # both at once, z = zs[0]: one prediction pass
    est.reset()                  # back to the initial state (nothing learned, filter at 0)
    blob = est.to_bytes(); est.load_bytes(blob)   # the learned state, e.g. for a database

``estimate`` advances the estimator's first-order low-pass filter by one tick (dt_s), so the
estimate entering the model varies on the dynamics' timescale (thesis 3.1.1); call it once
per tick. ``variation`` is what the estimator knows about the perturbation elsewhere, e.g.
along a prediction horizon: an LWPR model's p(zs) - p(z); zero for estimators whose estimate
does not depend on z. Implementations: ``NoPerturbation`` (zeros), ``LwprPerturbation``
(LWPR on a chosen subspace of z, one output per learned state element) and
``KalmanPerturbation`` (a Kalman filter disturbance observer for a constant or slowly
varying, random-walk disturbance).
Pure numerics: no asyncio and no I/O.
"""

from __future__ import annotations

import io
import math
import zipfile
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, fields
from typing import Any, Literal, Protocol

import numpy as np
import numpy.typing as npt

from epc_offboard.common.blobs import Npz
from epc_offboard.control.lwpr import LWPR, LwprError, ModelGroup, check_vector

FloatArray = npt.NDArray[np.float64]

FORMAT_NAME = "epc-offboard-perturbation"
FORMAT_VERSION = 1

EstimatorKind = Literal["none", "lwpr", "kf"]


class PerturbationEstimator(Protocol):
    """What the model update needs from an estimator (see the module docstring)."""

    nx: int
    n_z: int

    def observe(self, z: npt.ArrayLike, p_measured: npt.ArrayLike) -> None: ...

    def estimate(self, z: npt.ArrayLike) -> FloatArray: ...

    def variation(self, z: npt.ArrayLike, zs: npt.ArrayLike) -> FloatArray: ...

    def estimate_along(self, zs: npt.ArrayLike) -> tuple[FloatArray, FloatArray]: ...

    def reset(self) -> None: ...

    def to_bytes(self) -> bytes: ...

    def to_npz(self) -> Npz: ...

    def load_bytes(self, data: bytes) -> None: ...


# --------------------------------------------------------------------------- configs


@dataclass(frozen=True)
class LwprPerturbationConfig:
    """LWPR estimator. Indices refer to z = [x; u] (inputs) and to x (outputs).

    outputs: state elements learned; the others are estimated as 0. Empty: all of x.
    inputs: one shared subspace of z for every output (e.g. the velocity elements), or one
        subspace per output element (a list of lists). Empty: all of z.
    norm_z, norm_p: typical magnitude of each z / p element (LWPR's normalisation); empty:
        ones. init_d is in these normalised units.
    residual_kf: the position loop's Kalman observer (``[estimator.kf]``) also follows what
        LWPR leaves, the measured disturbance less LWPR's prediction, and its estimate is
        added to LWPR's (control/position.py; not the estimator's own state).
    The remaining keys are the LWPR learner's (epc_offboard.control.lwpr.LWPR), same meaning and
    defaults.
    """

    outputs: tuple[int, ...] = ()
    inputs: tuple[int, ...] | tuple[tuple[int, ...], ...] = ()
    lowpass_cutoff_hz: float = 2.0
    dt_s: float = 0.01
    norm_z: tuple[float, ...] = ()
    norm_p: tuple[float, ...] = ()
    init_d: float = 25.0
    init_alpha: float = 50.0
    penalty: float = 1e-6
    w_gen: float = 0.1
    w_prune: float = 1.0
    init_lambda: float = 0.999
    final_lambda: float = 0.99999
    tau_lambda: float = 0.9999
    diag_only: bool = True
    update_d: bool = True
    meta: bool = False
    init_s2: float = 1e-10
    add_threshold: float = 0.5
    max_rfs: int | None = None
    residual_kf: bool = False

    def __post_init__(self) -> None:
        _check_filter_settings(self.lowpass_cutoff_hz, self.dt_s)


@dataclass(frozen=True)
class KalmanPerturbationConfig:
    """Kalman-filter disturbance observer: p[k+1] = p[k] + w (random walk), measured as
    p_measured = p + v. Variances per step, in the units of p squared.

    outputs: state elements estimated (others 0); empty: all of x.
    lowpass_cutoff_hz: 0 disables the extra low-pass (the filter's own bandwidth, set by
        process_noise / measurement_noise, already smooths the estimate).
    """

    outputs: tuple[int, ...] = ()
    process_noise: float = 1e-8
    measurement_noise: float = 1e-6
    initial_variance: float = 1e-4
    lowpass_cutoff_hz: float = 0.0
    dt_s: float = 0.01

    def __post_init__(self) -> None:
        for name in ("process_noise", "measurement_noise", "initial_variance"):
            value = getattr(self, name)
            if not value > 0.0:
                raise ValueError(f"{name} must be > 0, got {value}")
        _check_filter_settings(self.lowpass_cutoff_hz, self.dt_s, allow_off=True)


@dataclass(frozen=True)
class PerturbationConfig:
    """Settings of every estimator kind; ``make_estimator`` picks the one it builds."""

    lwpr: LwprPerturbationConfig = field(default_factory=LwprPerturbationConfig)
    kf: KalmanPerturbationConfig = field(default_factory=KalmanPerturbationConfig)



def _default_lwpr() -> LwprPerturbationConfig:
    # z = velocity (m/s), p = acceleration disturbance (m/s^2).
    # inputs: each axis's disturbance learned on that axis's velocity (thesis 3.1.1: the
    #   subspace the disturbance depends on). Drag acts along the airspeed, and a multirotor's
    #   horizontal drag is the same along north and east, so d_i depends on v_i; a full 3-D
    #   input makes incremental PLS split each local model over three projections, which
    #   converges far slower on noisy targets (figure-8: 4-6 cm/s^2 error against 0.4-0.9).
    # init_d = 4 on these norms: fields about 2 m/s (1 m/s vertically) wide. Drag varies
    #   smoothly with airspeed, so one local linear model spans the usual envelope and new
    #   fields grow only beyond it; narrow fields each start from scratch and blend in
    #   half-trained.
    # lowpass 5 Hz (time constant 32 ms, below the inner loop's lag): the prediction is a
    #   function of the measured velocity, not a raw measurement, so it needs little
    #   smoothing; a 1 Hz filter lagged the figure-8's drag by 0.16 s (3 cm/s^2 error).
    return LwprPerturbationConfig(
        inputs=((0,), (1,), (2,)),
        norm_z=(4.0, 4.0, 2.0),
        norm_p=(1.0, 1.0, 1.0),
        init_d=4.0,
        lowpass_cutoff_hz=5.0,
    )


@dataclass(frozen=True)
class EstimatorConfig:
    """The acceleration-disturbance estimator of the position loop (thesis 3.1.1).

    It learns d (3,) m/s^2 from the velocity (3,) m/s: the thesis's subspace example, and
    what wind acting through drag depends on. ``dt_s`` of the sub-tables is set from the
    position loop's period.
    """

    kind: EstimatorKind = "lwpr"
    lwpr: LwprPerturbationConfig = field(default_factory=_default_lwpr)
    kf: KalmanPerturbationConfig = field(default_factory=KalmanPerturbationConfig)


def _check_filter_settings(cutoff_hz: float, dt_s: float, *, allow_off: bool = False) -> None:
    if not (math.isfinite(dt_s) and dt_s > 0.0):
        raise ValueError(f"dt_s must be > 0, got {dt_s}")
    if not math.isfinite(cutoff_hz) or cutoff_hz < 0.0 or (cutoff_hz == 0.0 and not allow_off):
        raise ValueError(f"lowpass_cutoff_hz must be > 0, got {cutoff_hz}")


# --------------------------------------------------------------------------- helpers


class LowPassFilter:
    """First-order low-pass per element, exact for a signal held over each tick:
    y[k+1] = y[k] + a (u[k] - y[k]), a = 1 - exp(-2 pi f_c dt). Starts at 0.
    cutoff_hz = 0 passes the input through unchanged."""

    def __init__(self, n: int, cutoff_hz: float, dt_s: float) -> None:
        _check_filter_settings(cutoff_hz, dt_s, allow_off=True)
        self.cutoff_hz = cutoff_hz
        self.dt_s = dt_s
        self.gain = 1.0 if cutoff_hz == 0.0 else 1.0 - math.exp(-2.0 * math.pi * cutoff_hz * dt_s)
        self.state = np.zeros(n)

    def step(self, u: FloatArray) -> FloatArray:
        """Advance one tick with input u (n,); returns a copy of the new output."""
        self.state += self.gain * (u - self.state)
        return self.state.copy()

    def reset(self) -> None:
        self.state[:] = 0.0


def _settings(cfg: Any) -> dict[str, Any]:
    """A config dataclass as the keyword arguments of the estimator it configures."""
    return {f.name: getattr(cfg, f.name) for f in fields(cfg)}


def _indices(indices: Sequence[int], n: int, what: str) -> tuple[int, ...]:
    """Distinct indices into a vector of length n; empty means all of it."""
    out = tuple(int(i) for i in indices) or tuple(range(n))
    if len(set(out)) != len(out) or any(i < 0 or i >= n for i in out):
        raise ValueError(f"{what} must be distinct indices in [0, {n}), got {list(out)}")
    return out


def _selector(indices: tuple[int, ...]) -> slice | npt.NDArray[np.intp]:
    """Indices as a slice where they are a run (the usual per-axis groups: a view, not a
    fancy-indexed copy, every tick), else an index array."""
    if indices == tuple(range(indices[0], indices[0] + len(indices))):
        return slice(indices[0], indices[0] + len(indices))
    return np.array(indices, dtype=np.intp)


def _check_rows(value: npt.ArrayLike, n: int, name: str) -> FloatArray:
    """``value`` as a finite float array of shape (m, n); else LwprError naming ``name``."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise LwprError(f"{name} must be a numeric array of shape (m, {n}): {exc}") from exc
    if arr.ndim != 2 or arr.shape[1] != n:
        raise LwprError(f"{name} must have shape (m, {n}), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise LwprError(f"{name} must be finite")
    return arr


def _query_rows(zs: npt.ArrayLike, n: int) -> FloatArray:
    """:func:`_check_rows` for ``estimate_along``: at least one row, the query point."""
    rows = _check_rows(zs, n, "zs")
    if len(rows) == 0:
        raise LwprError("zs must have at least one row (the query point)")
    return rows


def _dims(nx: int, n_z: int) -> tuple[int, int]:
    for name, value in (("nx", nx), ("n_z", n_z)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
    return nx, n_z


def _npz(kind: str, nx: int, n_z: int, arrays: dict[str, Any]) -> Npz:
    """An estimator's state file: its ``arrays`` copied now (a nested :class:`Npz` kept as
    it is), zipped by :meth:`Npz.build` where it is saved (the library store's process)."""
    return Npz.of({
        "format": np.array(FORMAT_NAME),
        "version": np.array(FORMAT_VERSION),
        "kind": np.array(kind),
        "dims": np.array([nx, n_z]),
        **arrays,
    })  # fmt: skip


def _unpack(data: bytes, kind: str, nx: int, n_z: int) -> dict[str, Any]:
    """The arrays of an ``_npz`` blob made by the same kind of estimator with the same
    dimensions; anything else raises ValueError."""
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            arrays = {key: z[key] for key in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise ValueError(f"not a perturbation-estimator state (unreadable npz: {exc})") from exc
    try:
        if str(arrays["format"]) != FORMAT_NAME or int(arrays["version"]) != FORMAT_VERSION:
            raise ValueError(
                f"not a perturbation-estimator state of version {FORMAT_VERSION} "
                f"(format {str(arrays['format'])!r}, version {int(arrays['version'])})"
            )
        if str(arrays["kind"]) != kind:
            raise ValueError(f"state is for a {str(arrays['kind'])!r} estimator, not {kind!r}")
        if [int(v) for v in arrays["dims"]] != [nx, n_z]:
            raise ValueError(f"state has dims {arrays['dims'].tolist()}, expected [{nx}, {n_z}]")
    except KeyError as exc:
        raise ValueError(f"not a perturbation-estimator state (missing {exc})") from exc
    return arrays


# --------------------------------------------------------------------------- estimators


class NoPerturbation:
    """No correction: the estimate is always zero."""

    def __init__(self, nx: int, n_z: int) -> None:
        self.nx, self.n_z = _dims(nx, n_z)

    def observe(self, z: npt.ArrayLike, p_measured: npt.ArrayLike) -> None:
        check_vector(z, self.n_z, "z")
        check_vector(p_measured, self.nx, "p_measured")

    def estimate(self, z: npt.ArrayLike) -> FloatArray:
        check_vector(z, self.n_z, "z")
        return np.zeros(self.nx)

    def variation(self, z: npt.ArrayLike, zs: npt.ArrayLike) -> FloatArray:
        check_vector(z, self.n_z, "z")
        return np.zeros((len(_check_rows(zs, self.n_z, "zs")), self.nx))

    def estimate_along(self, zs: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """``estimate(zs[0])`` and ``variation(zs[0], zs)``: zeros."""
        rows = _query_rows(zs, self.n_z)
        return self.estimate(rows[0]), np.zeros((len(rows), self.nx))

    def reset(self) -> None:
        pass

    def to_bytes(self) -> bytes:
        return self.to_npz().build()

    def to_npz(self) -> Npz:
        return _npz("none", self.nx, self.n_z, {})

    def load_bytes(self, data: bytes) -> None:
        _unpack(data, "none", self.nx, self.n_z)


class LwprPerturbation:
    """p^ learned by LWPR from (z, p_measured) pairs, then low-pass filtered.

    One LWPR output per learned state element (``outputs``), trained on a subspace of z
    (``inputs``: one shared list of z indices, or one list per output element); the other
    state elements are estimated as 0. ``lwpr_kwargs`` go to each LWPR learner.
    """

    def __init__(
        self,
        nx: int,
        n_z: int,
        *,
        inputs: Sequence[int] | Sequence[Sequence[int]] | npt.NDArray[np.integer[Any]] = (),
        outputs: Sequence[int] = (),
        lowpass_cutoff_hz: float,
        dt_s: float,
        norm_z: npt.ArrayLike | None = None,
        norm_p: npt.ArrayLike | None = None,
        **lwpr_kwargs: Any,
    ) -> None:
        self.nx, self.n_z = _dims(nx, n_z)
        self.outputs = _indices(outputs, nx, "outputs")
        # (z indices, state indices) learned by each LWPR model
        self.groups: list[tuple[tuple[int, ...], tuple[int, ...]]]
        if len(inputs) > 0 and not isinstance(inputs[0], int | np.integer):
            per_output = [_indices(s, n_z, "inputs") for s in inputs]  # type: ignore[arg-type]
            if len(per_output) != len(self.outputs):
                raise ValueError(
                    f"inputs has {len(per_output)} subspaces for {len(self.outputs)} outputs"
                )
            self.groups = [(s, (o,)) for s, o in zip(per_output, self.outputs, strict=True)]
        else:
            shared = _indices(inputs, n_z, "inputs")  # type: ignore[arg-type]
            self.groups = [(shared, self.outputs)]
        # Empty (a config's default) or None: no normalisation.
        self.norm_z = check_vector(
            np.ones(n_z) if norm_z is None or np.size(norm_z) == 0 else norm_z, n_z, "norm_z"
        )
        self.norm_p = check_vector(
            np.ones(nx) if norm_p is None or np.size(norm_p) == 0 else norm_p, nx, "norm_p"
        )
        self.lwpr_kwargs = dict(lwpr_kwargs)
        self._index = [(_selector(ins), _selector(outs)) for ins, outs in self.groups]
        self.models = self._new_models()  # raises on bad LWPR settings, before anything else
        self._group: ModelGroup | None = None  # self.models in one compiled call
        self.filter = LowPassFilter(nx, lowpass_cutoff_hz, dt_s)

    @classmethod
    def from_config(cls, nx: int, n_z: int, cfg: LwprPerturbationConfig) -> LwprPerturbation:
        settings = _settings(cfg)
        del settings["residual_kf"]  # the position loop's, not the learner's
        return cls(nx, n_z, **settings)

    def _new_models(self) -> list[LWPR]:
        return [
            LWPR(
                len(ins),
                len(outs),
                norm_in=self.norm_z[list(ins)],
                norm_out=self.norm_p[list(outs)],
                **self.lwpr_kwargs,
            )
            for ins, outs in self.groups
        ]

    def observe(self, z: npt.ArrayLike, p_measured: npt.ArrayLike) -> None:
        zv = check_vector(z, self.n_z, "z")
        pv = check_vector(p_measured, self.nx, "p_measured")
        group = self._group
        if group is None or group.models is not self.models:
            group = self._model_group()
        if group.update(zv, pv):  # every model in one compiled call
            return
        for model, (ins, outs) in zip(self.models, self._index, strict=True):
            model.update_finite(zv[ins], pv[outs])  # (checked above, as a whole)

    def _model_group(self) -> ModelGroup:
        """self.models, in one compiled call (rebuilt when they are replaced)."""
        group = self._group
        if group is None or group.models is not self.models:
            group = self._group = ModelGroup(
                self.models, [ins for ins, _ in self.groups],
                [outs for _, outs in self.groups], self.n_z, self.nx,
            )  # fmt: skip
        return group

    def prediction_args(self) -> tuple[tuple[int, ...], Any, Any, object] | None:
        """The compiled prediction's arguments for every model at once after the points and
        the output (``ModelGroup.predict_args``), and the group they are for (their types
        are fixed while it is the same: an entry point made for them stays valid); None: not
        compiled."""
        group = self._group
        if group is None or group.models is not self.models:
            group = self._model_group()
        args = group.predict_args()
        return None if args is None else (*args, group)

    def predict_raw(self, z: npt.ArrayLike) -> FloatArray:
        """The unfiltered LWPR prediction of p at z, shape (nx,)."""
        zv = check_vector(z, self.n_z, "z")
        raw = np.zeros(self.nx)
        for model, (ins, outs) in zip(self.models, self._index, strict=True):
            raw[outs] = model.predict(zv[ins])
        return raw

    def predict_raw_many(self, zs: npt.ArrayLike) -> FloatArray:
        """The unfiltered LWPR predictions at the rows of zs (m, n_z): shape (m, nx)."""
        if (
            type(zs) is np.ndarray and zs.dtype == np.float64 and zs.ndim == 2
            and zs.shape[1] == self.n_z and zs.flags.c_contiguous
        ):  # fmt: skip
            # the position tick's query: every model in one compiled call, the same numbers
            group = self._group
            if group is None or group.models is not self.models:
                group = self._model_group()
            raw_fast = group.predict_many(zs)
            if raw_fast is not None:
                return raw_fast
        zv = _check_rows(zs, self.n_z, "zs")
        raw = np.zeros((len(zv), self.nx))
        for model, (ins, outs) in zip(self.models, self._index, strict=True):
            raw[:, outs] = model.predict_many(zv[:, ins])
        return raw

    def estimate(self, z: npt.ArrayLike) -> FloatArray:
        return self.filter.step(self.predict_raw(z))

    def variation(self, z: npt.ArrayLike, zs: npt.ArrayLike) -> FloatArray:
        """How the learned perturbation changes from z to each row of zs: p(zs) - p(z),
        unfiltered (the low-pass smooths the estimate in time, not its dependence on z)."""
        out: FloatArray = self.predict_raw_many(zs) - self.predict_raw(z)
        return out

    def estimate_along(self, zs: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """``estimate(zs[0])`` and ``variation(zs[0], zs)`` from one prediction pass over the
        rows of zs (m, n_z), m >= 1: the same numbers (a row of ``predict_many`` is
        ``predict`` at that row), half the LWPR calls. Advances the filter like ``estimate``."""
        raw = self.predict_raw_many(zs)
        if len(raw) == 0:
            raise LwprError("zs must have at least one row (the query point)")
        variation: FloatArray = raw - raw[0]
        return self.filter.step(raw[0]), variation

    def reset(self) -> None:
        self.models = self._new_models()
        self.filter.reset()

    def to_bytes(self) -> bytes:
        return self.to_npz().build()

    def to_npz(self) -> Npz:
        *_, npz = self.to_npz_steps()
        assert npz is not None
        return npz

    def to_npz_steps(self) -> Iterator[Npz | None]:
        """The state's arrays in steps, None after each model, the whole last: a caller on
        the loops' thread lets them tick in between. Each step copies one model's arrays
        (:meth:`LWPR.to_npz`, a memcpy); the npz files are made by whoever builds the
        result (the store process): made here, they took 4-14 ms of the loops' thread a
        save (issue 21). Each model is its state when its step ran, the filter the last
        step's."""
        arrays: dict[str, Any] = {}
        for i, m in enumerate(self.models):
            arrays[f"model_{i}"] = m.to_npz()
            yield None
        yield _npz("lwpr", self.nx, self.n_z, {"filter": self.filter.state, **arrays})

    def load_bytes(self, data: bytes) -> None:
        arrays = _unpack(data, "lwpr", self.nx, self.n_z)
        try:
            models = [
                LWPR.from_bytes(arrays[f"model_{i}"].tobytes()) for i in range(len(self.groups))
            ]
            state = np.asarray(arrays["filter"], dtype=np.float64)
        except KeyError as exc:
            raise ValueError(f"LWPR estimator state is missing {exc}") from exc
        except LwprError as exc:
            raise ValueError(f"LWPR estimator state holds a bad model: {exc}") from exc
        for model, (ins, outs) in zip(models, self.groups, strict=True):
            if (model.n_in, model.n_out) != (len(ins), len(outs)):
                raise ValueError("LWPR estimator state was saved with other inputs/outputs")
        if state.shape != (self.nx,) or not np.isfinite(state).all():
            raise ValueError("LWPR estimator state has a bad filter state")
        self.models = models
        self.filter.state[:] = state


class KalmanPerturbation:
    """A Kalman-filter disturbance observer (filterpy): the state is the disturbance of the
    learned elements, a random walk; each p_measured is a direct noisy measurement of it.
    The estimate does not depend on z (a constant or slowly varying disturbance)."""

    def __init__(
        self,
        nx: int,
        n_z: int,
        *,
        outputs: Sequence[int] = (),
        process_noise: float = 1e-8,
        measurement_noise: float = 1e-6,
        initial_variance: float = 1e-4,
        lowpass_cutoff_hz: float = 0.0,
        dt_s: float = 0.01,
    ) -> None:
        self.nx, self.n_z = _dims(nx, n_z)
        self.outputs = _indices(outputs, nx, "outputs")
        # Validates the noise settings with the config's messages.
        KalmanPerturbationConfig(
            self.outputs,
            process_noise,
            measurement_noise,
            initial_variance,
            lowpass_cutoff_hz,
            dt_s,
        )
        self.process_noise = process_noise
        self.measurement_noise = measurement_noise
        self.initial_variance = initial_variance
        # imported here: filterpy pulls in scipy.stats, seconds of a cold start that the
        # default (LWPR) estimator never needs
        from filterpy.kalman import KalmanFilter

        m = len(self.outputs)
        self.kf = KalmanFilter(dim_x=m, dim_z=m)
        self.kf.F = np.eye(m)
        self.kf.H = np.eye(m)
        self.kf.Q = process_noise * np.eye(m)
        self.kf.R = measurement_noise * np.eye(m)
        self.filter = LowPassFilter(nx, lowpass_cutoff_hz, dt_s)
        self.reset()

    @classmethod
    def from_config(cls, nx: int, n_z: int, cfg: KalmanPerturbationConfig) -> KalmanPerturbation:
        return cls(nx, n_z, **_settings(cfg))

    def observe(self, z: npt.ArrayLike, p_measured: npt.ArrayLike) -> None:
        check_vector(z, self.n_z, "z")
        pv = check_vector(p_measured, self.nx, "p_measured")
        self.kf.predict()
        self.kf.update(pv[list(self.outputs)].reshape(-1, 1))

    def estimate(self, z: npt.ArrayLike) -> FloatArray:
        check_vector(z, self.n_z, "z")
        raw = np.zeros(self.nx)
        raw[list(self.outputs)] = self.kf.x[:, 0]
        return self.filter.step(raw)

    def variation(self, z: npt.ArrayLike, zs: npt.ArrayLike) -> FloatArray:
        """Zero: the observer's disturbance does not depend on z."""
        check_vector(z, self.n_z, "z")
        return np.zeros((len(_check_rows(zs, self.n_z, "zs")), self.nx))

    def estimate_along(self, zs: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """``estimate(zs[0])`` and ``variation(zs[0], zs)`` (zeros)."""
        rows = _query_rows(zs, self.n_z)
        return self.estimate(rows[0]), np.zeros((len(rows), self.nx))

    def reset(self) -> None:
        m = len(self.outputs)
        self.kf.x = np.zeros((m, 1))
        self.kf.P = self.initial_variance * np.eye(m)
        self.filter.reset()

    def to_bytes(self) -> bytes:
        return self.to_npz().build()

    def to_npz(self) -> Npz:
        return _npz(
            "kf", self.nx, self.n_z, {"x": self.kf.x, "P": self.kf.P, "filter": self.filter.state}
        )

    def load_bytes(self, data: bytes) -> None:
        arrays = _unpack(data, "kf", self.nx, self.n_z)
        m = len(self.outputs)
        try:
            x, P, state = (np.asarray(arrays[k], dtype=np.float64) for k in ("x", "P", "filter"))
        except KeyError as exc:
            raise ValueError(f"Kalman estimator state is missing {exc}") from exc
        if (
            x.shape != (m, 1)
            or P.shape != (m, m)
            or state.shape != (self.nx,)
            or not all(np.isfinite(a).all() for a in (x, P, state))
        ):
            raise ValueError("Kalman estimator state does not fit this estimator")
        self.kf.x, self.kf.P = x, P
        self.filter.state[:] = state


def make_estimator(
    kind: EstimatorKind,
    nx: int,
    n_z: int,
    config: PerturbationConfig | None = None,
) -> NoPerturbation | LwprPerturbation | KalmanPerturbation:
    """The estimator of ``kind`` ("none", "lwpr" or "kf") for a model with nx states and
    query points z of length n_z, configured from ``config`` (defaults if None)."""
    cfg = config or PerturbationConfig()
    if kind == "none":
        return NoPerturbation(nx, n_z)
    if kind == "lwpr":
        return LwprPerturbation.from_config(nx, n_z, cfg.lwpr)
    if kind == "kf":
        return KalmanPerturbation.from_config(nx, n_z, cfg.kf)
    raise ValueError(f"unknown estimator kind {kind!r} (known: none, lwpr, kf)")
