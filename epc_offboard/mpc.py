"""The EPC core as one import (CONTRACTS.md): ``from epc_offboard.mpc import ...``."""

from __future__ import annotations

from epc_offboard.baselines import MpcController, PdController
from epc_offboard.decision import Controller, Decision, Source
from epc_offboard.epc import EpcStats, ExperienceController, LibraryEntry
from epc_offboard.models import LinearModel, attitude_model, position_model
from epc_offboard.qp import MpcProblem, OsqpSolver, QpResult, QpStatus

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
