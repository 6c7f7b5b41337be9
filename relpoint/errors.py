"""Exception hierarchy shared by the core, the format layer and the CLI.

Every error relpoint raises on purpose derives from :class:`RelpointError`. The CLI turns each into
one line on stderr and the exit code of its class, so a user never sees a traceback for a problem
with their data or their options.
"""

from __future__ import annotations


class RelpointError(Exception):
    """Base of every error relpoint raises on purpose.

    Parameters
    ----------
    message:
        What went wrong, naming the file, topic or option concerned.
    hint:
        What the user can do about it (shown after the message).
    """

    exit_code = 1

    def __init__(self, message: str, hint: str | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.hint = hint

    def __str__(self) -> str:
        return self.message if not self.hint else f"{self.message}; {self.hint}"


class UsageError(RelpointError):
    """Options or configuration that cannot be honoured (bad value, unknown key)."""

    exit_code = 2


class InputError(RelpointError):
    """An input file that cannot be used: missing, not an MCAP, truncated, non-conforming."""

    exit_code = 3


class EstimatorError(RelpointError):
    """An estimator could not produce a result from usable input (e.g. too few points to start)."""

    exit_code = 4


class GateExceeded(RelpointError):
    """An evaluation figure exceeded a bound given with ``--fail-above``."""

    exit_code = 5


class Interrupted(RelpointError):
    """The run was stopped by SIGINT or SIGTERM before it completed."""

    exit_code = 130
