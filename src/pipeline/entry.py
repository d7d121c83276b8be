"""What every rule's thin script does around the package call: the job's log, and one line on bad input."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

from pipeline.errors import InputError

__all__ = ["EXIT_INTERRUPTED", "exit_on_input_error", "setup_log"]

#: a job's exit status after Ctrl-C (128 + SIGINT, as shells report it)
EXIT_INTERRUPTED = 130


def setup_log(path: str | None) -> None:
    handlers = [logging.StreamHandler(sys.stderr)]
    if path:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        handlers.append(logging.FileHandler(path, mode="w"))
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s", handlers=handlers,
                        force=True)


def exit_on_input_error(function, *args, **kwargs):
    """Call ``function``; bad input ends the process with one line naming the file and the problem."""
    try:
        return function(*args, **kwargs)
    except InputError as exc:
        logging.getLogger("pipeline").error("%s", exc)
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(1)
    except KeyboardInterrupt:
        # Ctrl-C reaches the jobs too (the terminal's process group): one line, no traceback
        logging.getLogger("pipeline").error("interrupted")
        sys.exit(EXIT_INTERRUPTED)
    except Exception as exc:
        # one line into the job's log too (the traceback follows on stderr), where the report of a
        # failed run reads each job's error
        logging.getLogger("pipeline").error("unexpected %s: %s", type(exc).__name__, exc)
        raise
