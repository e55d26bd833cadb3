"""Calls and values sent to a Dask cluster sealed: pickled here into bytes that only the worker
running the task opens, in its task thread.

Dask's scheduler unpickles every task it is given (to find its dependencies). A task that names
gt3dkit's functions, or carries gt3dkit's objects, made the scheduler import them: gt3dkit's
estimators, numba and SciPy, 0.9 s of the scheduler's CPU on a run's first task (its process
sampled by a profiler on the 4 000-frame box scene). On a 2-core machine that second was taken
from the workers and from this process, at the start of the run, and the first worker's warm-up
waited for it (the scheduler sends a task on only once it has read it). Sealed, a task names this
module alone, which imports the standard library: the scheduler reads it at once, and it needs
no gt3dkit of its own beyond this file.

A worker opens a sealed value where it is used (a task's in the thread that runs the task), one at
a time (a lock), so no two of its threads import gt3dkit at once. Two did, the task thread and the
thread that reads the worker's messages as it unpickled the next task, and a worker died of it
in Python's import locks (``KeyError: 'gt3dkit.windows'``): now that thread unpickles only this
module's objects."""

from __future__ import annotations

import pickle
import threading
import uuid
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from distributed import Client, Future

#: Held while a sealed value is opened (its modules imported): one thread of a process at a time.
_OPENING = threading.Lock()


class Sealed:
    """A value pickled where it was made (``blob``), opened where it is used (:meth:`opened`)."""

    __slots__ = ("blob",)

    def __init__(self, blob: bytes) -> None:
        self.blob = blob

    @classmethod
    def of(cls, value: object) -> Sealed:
        """``value`` sealed: pickled as Dask pickles a task (cloudpickle: a function made in a
        test or a notebook goes by value, a module's by its name)."""
        import cloudpickle

        return cls(cloudpickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL))

    def opened(self) -> Any:
        """The value, unpickled here (its modules imported) while no other thread opens one."""
        with _OPENING:
            return pickle.loads(self.blob)  # noqa: S301 - made by this run's own client, as Dask's own are

    def __reduce__(self) -> tuple[type, tuple[bytes]]:
        return Sealed, (self.blob,)


def opened_call(fn: Sealed, *args: object) -> Any:
    """The sealed call ``fn(*args)``, run where the task runs: ``fn`` and each sealed argument
    opened (a scattered value's future gives the value sealed, as it was scattered)."""
    return fn.opened()(*(a.opened() if isinstance(a, Sealed) else a for a in args))


def submit(client: Client, fn: Callable[..., object], *args: object, **options: object) -> Future[object]:
    """``client.submit(fn, *args, pure=False, **options)`` with ``fn`` and the arguments sealed
    (the futures among them as they are: Dask waits for them and gives their values), named
    after ``fn`` as Dask names a task (its dashboard, its task stream): its future."""
    from dask.utils import funcname
    from distributed import Future

    return client.submit(opened_call, Sealed.of(fn),
                         *(a if isinstance(a, Future) else Sealed.of(a) for a in args),
                         key=f"{funcname(fn)}-{uuid.uuid4().hex}", pure=False, **options)


def scatter(client: Client, value: object, **options: object) -> Future[object]:
    """``client.scatter(value, hash=False, **options)``, sealed (a task's argument,
    :func:`submit`): its future."""
    return client.scatter(Sealed.of(value), hash=False, **options)
