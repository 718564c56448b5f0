"""What of a vehicle's controllers is kept on disk, and how it comes back: the translation
between a :class:`~epc_offboard.control.cascade.Cascade` and the
:class:`~epc_offboard.store.database.LibraryStore`.

Stored is experience, never gains: each EPC library (its active sets with importance, uses
and origin, and the transitions between them) under its problem's signature, and the
position loop's disturbance estimator as an opaque blob under the position problem's
signature (also with a PD or MPC position controller, which keep no library).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Mapping
from dataclasses import replace

from epc_offboard.control.cascade import Cascade
from epc_offboard.control.library_types import (
    DeferredBlob,
    LibrarySnapshot,
    SignatureSnapshot,
)
from epc_offboard.store.database import LibraryStore

log = logging.getLogger(__name__)


def _estimator_key(cascade: Cascade) -> str:
    return f"estimator.{cascade.position.estimator_cfg.kind}"


def estimator_models(cascade: Cascade) -> dict[str, DeferredBlob]:
    """The estimator's learned model, copied now (its arrays: ``to_npz``); its bytes are
    built where it is saved (:meth:`LibraryStore.save_snapshot`, in the store process)."""
    return {_estimator_key(cascade): cascade.position.estimator.to_npz()}


def estimator_model_steps(cascade: Cascade) -> Iterator[dict[str, DeferredBlob] | None]:
    """:func:`estimator_models` in steps (None between them, the models last), for a saver
    that lets the loops tick between steps: an estimator that copies itself in parts
    (``to_npz_steps``: LWPR, a model a step) is taken a part at a time."""
    estimator = cascade.position.estimator
    steps = getattr(estimator, "to_npz_steps", None)
    if steps is None:
        yield estimator_models(cascade)
        return
    for npz in steps():
        yield None if npz is None else {_estimator_key(cascade): npz}


def snapshot(
    cascade: Cascade, models: Mapping[str, bytes | DeferredBlob] | None = None
) -> LibrarySnapshot:
    """Every controller (importance, uses, transitions) and the estimator (``models``: its
    :func:`estimator_models` taken before, else now), copied now.

    Take it on the thread that runs the loops (the library is not thread-safe); the copy
    can then be saved (:meth:`LibraryStore.save_snapshot`) from a worker thread while the
    loops fly on.
    """
    *_, snap = snapshot_steps(cascade, models)
    assert snap is not None
    return snap


def snapshot_steps(
    cascade: Cascade, models: Mapping[str, bytes | DeferredBlob] | None = None
) -> Iterator[LibrarySnapshot | None]:
    """:func:`snapshot` in steps (None after each loop's library, the snapshot last), for a
    saver that lets the loops tick in between."""
    parts: dict[str, SignatureSnapshot] = {}
    for _name, ctrl in cascade.experience_controllers():
        # packed: no object per entry on the loops' thread (the store process makes them);
        # their origin travels with them (the store writes "" as solved)
        parts[ctrl.problem.signature()] = SignatureSnapshot(*ctrl.export_packed())
        yield None
    pos_sig = cascade.position.problem.signature()
    parts[pos_sig] = replace(
        parts.get(pos_sig, SignatureSnapshot()),
        models=models if models is not None else estimator_models(cascade),
    )
    yield LibrarySnapshot(parts)


def loop_names(cascade: Cascade) -> dict[str, str]:
    """signature -> the loop it is the problem of ("position", "attitude")."""
    return {ctrl.problem.signature(): name for name, ctrl in cascade.experience_controllers()}


def save(cascade: Cascade, store: LibraryStore) -> None:
    """Snapshot and save at once (on the loops' thread, e.g. at shutdown)."""
    store.save_snapshot(snapshot(cascade))


def load(cascade: Cascade, store: LibraryStore) -> dict[str, int]:
    """Load the prior library (thesis M_prior) and estimator; returns counts per part.

    Every stored controller is re-validated against this problem; one that fails is
    skipped with a log line, never applied (and, as always, only KKT-checked use).
    """
    loaded: dict[str, int] = {}
    for name, ctrl in cascade.experience_controllers():
        sig = ctrl.problem.signature()
        entries = store.load_controllers(sig)[: ctrl.max_size]
        index = {e.active_set: i for i, e in enumerate(entries)}
        transitions = {
            (index[a], index[b]): n
            for (a, b), n in store.load_transitions(sig).items()
            if a in index and b in index and n >= 1
        }
        try:
            loaded[name] = ctrl.import_entries(entries, "prior", transitions=transitions)
        except ValueError as exc:
            log.warning("stored %s library: %s; importing entry by entry", name, exc)
            loaded[name] = 0
            for e in entries:
                try:
                    loaded[name] += ctrl.import_entries([e], "prior")
                except ValueError as exc_one:
                    log.warning("stored %s controller %s skipped: %s", name, e.active_set, exc_one)
    blob = store.load_model(_estimator_key(cascade), cascade.position.problem.signature())
    if blob is not None:
        try:
            cascade.position.estimator.load_bytes(blob)
            loaded["estimator"] = 1
        except ValueError as exc:
            log.warning("stored estimator ignored: %s", exc)
    return loaded

