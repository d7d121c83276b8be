"""Errors that stop a run with one clear line naming the file and the problem.

A validator that looks at a whole dataset collects :class:`Problem` records
instead of stopping at the first one; :meth:`InputError.from_problems` turns
such a list into the one-line error a stage raises.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Problem:
    """One thing wrong with the input: where (file, line, column), what, and how to fix it."""

    path: Path | None
    line: int | None = None
    column: str | None = None
    message: str = ""
    fix: str = ""

    def where(self) -> str:
        """``line 3, column 'kind'`` (the parts that are known), or ''.

        Returns
        -------
        str
            The line and column of the problem, those that are known, joined by a comma; empty when neither is.
        """
        parts = []
        if self.line is not None:
            parts.append(f"line {self.line}")
        if self.column is not None:
            parts.append(f"column {self.column!r}")
        return ", ".join(parts)

    def text(self) -> str:
        """The problem without the file: ``line 3, column 'kind': 'x' is not one of ...``.

        Returns
        -------
        str
            :meth:`where` (when known) and the message.
        """
        where = self.where()
        return f"{where}: {self.message}" if where else self.message

    def __str__(self) -> str:
        return f"{self.path}: {self.text()}" if self.path is not None else self.text()


class InputError(Exception):
    """Bad input from a lab or a user: unreadable file, missing tag, wrong column.

    The message is one line that names the file and says what is wrong; the
    workflow prints it as it is, without a traceback.  ``problems`` holds every
    problem found when the error comes from a validator (the message names the
    first one and counts the others).
    """

    def __init__(self, path: str | Path | None, problem: str, problems: list[Problem] | None = None):
        self.path = None if path is None else Path(path)
        self.problem = problem
        self.problems = list(problems) if problems else [Problem(self.path, message=problem)]
        where = f"{self.path}: " if self.path is not None else ""
        super().__init__(f"{where}{problem}")

    @classmethod
    def from_problems(cls, problems: list[Problem], more_hint: str = "") -> "InputError":
        """One error for a non-empty list: the first problem, plus how many more there are.

        Parameters
        ----------
        problems : list of Problem
            Every problem a validator found, the first one named in the message; kept in the error's ``problems``.
        more_hint : str, optional
            Appended to the count of other problems (e.g. where the full list is shown); default none.

        Returns
        -------
        InputError
            The error (of the class it is called on) whose path is the first problem's file.

        Raises
        ------
        ValueError
            When ``problems`` is empty.
        """
        if not problems:
            raise ValueError("from_problems needs at least one problem")
        first = problems[0]
        text = first.text()
        others = len(problems) - 1
        if others:
            text += f" (and {others} more problem{'s' if others > 1 else ''}"
            text += f"; {more_hint})" if more_hint else ")"
        return cls(first.path, text, problems)


class ArtefactError(InputError):
    """An artefact that a later stage cannot use (unknown version, wrong stage)."""


class ImpossibleResult(InputError):
    """A physically impossible fit result (negative gain, noise or radiance): the stage stops
    with this message instead of writing an artefact."""
