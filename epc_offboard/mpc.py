"""A compatibility shim: the EPC core's import path that docs/CONTRACTS.md (Python API)
promises, ``from epc_offboard.mpc import LinearModel, MpcProblem, ExperienceController``, kept so
scripts written against it keep working.

Re-exports only, no code of its own, and nothing inside the package imports it
(``tests/test_layers.py`` checks): the core lives in ``epc_offboard/control/``, and new code
imports it from there or from the package root (``from epc_offboard import
ExperienceController, MpcProblem, LinearModel``). Not the MPC baseline either: that is
:class:`epc_offboard.control.baselines.MpcController`.
"""

from __future__ import annotations

from epc_offboard.control.baselines import MpcController, PdController
from epc_offboard.control.decision import Controller, Decision, Source
from epc_offboard.control.epc import EpcStats, ExperienceController
from epc_offboard.control.library_types import LibraryEntry
from epc_offboard.control.models import LinearModel, attitude_model, position_model
from epc_offboard.control.qp import MpcProblem, OsqpSolver, QpResult, QpStatus

__all__ = [
    "Controller",
    "Decision",
    "EpcStats",
    "ExperienceController",
    "LibraryEntry",
    "LinearModel",
    "MpcController",
    "MpcProblem",
    "OsqpSolver",
    "PdController",
    "QpResult",
    "QpStatus",
    "Source",
    "attitude_model",
    "position_model",
]
