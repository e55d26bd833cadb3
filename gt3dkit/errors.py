"""The one exception users see for bad input."""

from __future__ import annotations


class InputError(ValueError):
    """Bad input: the message names the file and the entry.

    The CLI prints ``error: <message>`` and exits with status 2, without a traceback.
    """

    def __init__(self, where: str, problem: str) -> None:
        self.where = where
        self.problem = problem
        super().__init__(f"{where}: {problem}")
