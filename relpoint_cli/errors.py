"""Turning errors into one line on stderr and an exit code (the table in the README)."""

from __future__ import annotations

import functools
import logging
import signal
import sys
import traceback
from collections.abc import Callable
from typing import Any, TypeVar

import click

from formats.outputs import OUTPUT_ERRNOS, os_error_message
from relpoint.errors import Interrupted, RelpointError

F = TypeVar("F", bound=Callable[..., Any])

EXIT_OK = 0
EXIT_INTERNAL = 1
EXIT_USAGE = 2
EXIT_INPUT = 3
EXIT_ESTIMATOR = 4
EXIT_GATE = 5
EXIT_INTERRUPTED = 130

log = logging.getLogger("relpoint")


def _raise_interrupted(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def handle_errors(command: F) -> F:
    """Wrap a click command so every failure is one clear stderr line and a documented exit code.

    SIGTERM is treated like Ctrl-C: outputs under way are discarded (they are written atomically)
    and the exit code is 130.
    """

    @functools.wraps(command)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        previous = signal.getsignal(signal.SIGTERM)
        try:
            signal.signal(signal.SIGTERM, _raise_interrupted)
        except ValueError:  # not the main thread (e.g. inside a test runner thread)
            previous = None
        try:
            return command(*args, **kwargs)
        except RelpointError as error:
            _fail(str(error), error.exit_code)
        except KeyboardInterrupt:
            _fail(str(Interrupted("interrupted; no output was written")), EXIT_INTERRUPTED)
        except click.exceptions.ClickException:
            raise
        except click.exceptions.Exit:
            raise
        except BrokenPipeError:
            quiet_broken_pipe()
        except OSError as error:  # the file system refused a path (full disk, read-only, permissions)
            if logging.getLogger().isEnabledFor(logging.DEBUG):
                traceback.print_exc()
            _fail(os_error_message(error), EXIT_USAGE if error.errno in OUTPUT_ERRNOS else EXIT_INPUT)
        except MemoryError:
            _fail("out of memory; the input is too large for this machine (see the size limits in the README)",
                  EXIT_INPUT)  # fmt: skip
        except Exception as error:  # a bug: still one line, the traceback only with --verbose
            if logging.getLogger().isEnabledFor(logging.DEBUG):
                traceback.print_exc()
            _fail(
                f"internal error: {type(error).__name__}: {error} (run again with --verbose and report it)",
                EXIT_INTERNAL,
            )
        finally:
            if previous is not None:
                signal.signal(signal.SIGTERM, previous)

    return wrapper  # type: ignore[return-value]


def quiet_broken_pipe() -> None:
    """The reader of stdout went away (``relpoint info LOG | head -1``): stop quietly, exit 0.

    Python would otherwise report the broken pipe again when it flushes stdout at exit.
    """
    import os

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):  # no real stdout (a test runner's capture)
        pass
    sys.exit(EXIT_OK)


def _fail(message: str, code: int) -> None:
    """One line on stderr, whatever a library put into the message (a parser's multi-line report)."""
    line = " ".join(part.strip() for part in message.splitlines() if part.strip())
    click.echo(f"relpoint: error: {line}", err=True)
    sys.exit(code)
