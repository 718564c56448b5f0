"""Exit codes and the product's exception hierarchy (docs/CONTRACTS.md).

Every error epc-offboard raises is an :class:`EpcError`, and also the builtin it is a kind
of, as python-control does (``ControlArgument(TypeError)``): ``except ValueError`` keeps
working, and ``except EpcError`` catches everything of ours. A leaf module: numerics import
it without importing any I/O.
"""

from __future__ import annotations

EXIT_OK = 0
EXIT_RUNTIME = 1
EXIT_USAGE = 2


class EpcError(Exception):
    """Base of every error epc-offboard raises."""


class UsageError(EpcError, ValueError):
    """Bad usage or invalid configuration: reported with exit code 2."""
