"""What every rule's thin script does around the package call: the job's log, and one line on bad input."""

from __future__ import annotations

import logging
import os
import signal
import sys
from pathlib import Path

from pipeline.errors import InputError

__all__ = ["EXIT_INTERRUPTED", "exit_on_input_error", "setup_log", "stop_quietly_on_interrupt"]

#: a job's exit status after Ctrl-C (128 + SIGINT, as shells report it)
EXIT_INTERRUPTED = 130


def _interrupted(signum, frame) -> None:
    sys.stderr.flush()
    os._exit(EXIT_INTERRUPTED)


def stop_quietly_on_interrupt() -> None:
    """A job's first call: Ctrl-C (the terminal sends SIGINT to every job of the run) ends it at once with
    130 and no traceback, also while its heavy imports load; the run's own line says it was interrupted.

    The job ends without the interpreter's clean-up: an exit after an interrupt in the middle of an import
    or a library call could hang there (seen with a job interrupted while starting), and Snakemake waits
    for every job before it ends the run. The artefact is written under a temporary name, so none is left
    half written."""
    signal.signal(signal.SIGINT, _interrupted)


def setup_log(path: str | None) -> None:
    """Log the package's INFO messages to stderr and, when a path is given, to a job's log file.

    Parameters
    ----------
    path : str or None
        The job's log file (its folder is created; the file is overwritten), or None for stderr alone.
    """
    handlers = [logging.StreamHandler(sys.stderr)]
    if path:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        handlers.append(logging.FileHandler(path, mode="w"))
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s", handlers=handlers,
                        force=True)


def exit_on_input_error(function, *args, **kwargs):
    """Call ``function``; bad input ends the process with one line naming the file and the problem.

    An :class:`~pipeline.errors.InputError` is logged and printed as ``error: ...`` on stderr and the process
    exits with status 1; Ctrl-C ends it at once with status 130 (:data:`EXIT_INTERRUPTED`); any other error is
    logged in one line and raised again (its traceback follows on stderr).

    Parameters
    ----------
    function : callable
        The package call a rule's script makes.
    *args
        Its positional arguments.
    **kwargs
        Its keyword arguments.

    Returns
    -------
    object
        What ``function`` returns.
    """
    try:
        return function(*args, **kwargs)
    except InputError as exc:
        logging.getLogger("pipeline").error("%s", exc)
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(1)
    except KeyboardInterrupt:
        # a job that did not call stop_quietly_on_interrupt: one line, no traceback, no clean-up
        logging.getLogger("pipeline").error("interrupted")
        _interrupted(signal.SIGINT, None)
    except Exception as exc:
        # one line into the job's log too (the traceback follows on stderr), where the report of a
        # failed run reads each job's error
        logging.getLogger("pipeline").error("unexpected %s: %s", type(exc).__name__, exc)
        raise
