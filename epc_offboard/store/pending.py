"""A library snapshot whose estimator is still pickled: the loops' thread pickles it (0.8 ms),
the store process formats it (``to_bytes``, numpy's npz: 2-8 ms beside two CPU hogs) before
the write. Kept apart from ``experience`` so the store process imports no controller until
a snapshot asks it to unpickle an estimator."""

from __future__ import annotations

import io
import pickle
from collections.abc import Mapping
from dataclasses import dataclass, replace

from epc_offboard.control.library_types import LibrarySnapshot, SignatureSnapshot

PICKLED = b"epc-pickled-estimator\0"  # before a pickled estimator's bytes (else: formatted)


@dataclass(frozen=True)
class PendingSnapshot:
    """A snapshot whose estimator models (``models``, under ``signature``) are still as
    :func:`estimator_state` took them: :meth:`complete` (in the store process) formats them."""

    snapshot: LibrarySnapshot
    signature: str
    models: Mapping[str, bytes]

    def complete(self) -> LibrarySnapshot:
        models = {name: _Unpickler(io.BytesIO(blob[len(PICKLED):])).load().to_bytes()
                  if blob.startswith(PICKLED) else blob
                  for name, blob in self.models.items()}  # fmt: skip
        parts = dict(self.snapshot.signatures)
        parts[self.signature] = replace(parts.get(self.signature, SignatureSnapshot()),
                                        models=models)  # fmt: skip
        return replace(self.snapshot, signatures=parts)


class _Unpickler(pickle.Unpickler):
    """What the saver's pickler left out (the models' compiled group) comes back as None."""

    def persistent_load(self, pid: object) -> None:
        return None
