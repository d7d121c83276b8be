"""Errors that stop a run with one clear line naming the file and the problem."""

from __future__ import annotations

from pathlib import Path


class InputError(Exception):
    """Bad input from a lab or a user: unreadable file, missing tag, wrong column.

    The message is one line that names the file and says what is wrong; the
    workflow prints it as it is, without a traceback.
    """

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else Path(path)
        self.problem = problem
        where = f"{self.path}: " if self.path is not None else ""
        super().__init__(f"{where}{problem}")


class ArtefactError(InputError):
    """An artefact that a later stage cannot use (unknown version, wrong stage)."""


class ImpossibleResult(InputError):
    """A physically impossible fit result (negative gain, noise or radiance): the stage stops
    with this message instead of writing an artefact."""
