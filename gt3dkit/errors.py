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

    def __reduce__(self) -> tuple[type, tuple[str, str]]:
        """Pickled as made (a window's reading raises it in a worker process, :mod:`gt3dkit.windows`)."""
        return type(self), (self.where, self.problem)


class EstimationError(RuntimeError):
    """An estimator could not solve a (valid) input, e.g. a singular factor graph.

    The CLI prints ``error: <estimator>: <problem>`` and exits with status 1; nothing is
    written. Not a bug report: the message says which object and what to try.
    """

    def __init__(self, estimator: str, problem: str) -> None:
        self.estimator = estimator
        self.problem = problem
        super().__init__(f"{estimator}: {problem}")

    def __reduce__(self) -> tuple[type, tuple[str, str]]:
        """Pickled as made (raised in a worker process, :mod:`gt3dkit.windows`)."""
        return type(self), (self.estimator, self.problem)
