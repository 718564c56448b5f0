"""Exit codes and the usage error every command shares (CONTRACTS.md)."""

from __future__ import annotations

EXIT_OK = 0
EXIT_RUNTIME = 1
EXIT_USAGE = 2


class UsageError(ValueError):
    """Bad usage or invalid configuration: reported with exit code 2."""
