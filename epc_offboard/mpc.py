"""CONTRACTS.md's import path for the EPC core, kept so scripts written against it keep working.

Not the MPC baseline (that is :class:`epc_offboard.control.baselines.MpcController`) and no
code of its own: the core lives in ``epc_offboard/control/``, and new code imports it from the
package root (``from epc_offboard import ExperienceController, MpcProblem, LinearModel``).
"""

from __future__ import annotations

from epc_offboard.control.baselines import MpcController, PdController
from epc_offboard.control.decision import Controller, Decision, Source
from epc_offboard.control.epc import EpcStats, ExperienceController
from epc_offboard.control.library import LibraryEntry
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
