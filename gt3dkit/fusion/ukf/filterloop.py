r"""The filter loop, written once: forward along a chain of rows with fading and the gap's
spread, then the RTS pass back, for the boxes' ellipsoid (:mod:`gt3dkit.fusion.ukf.boxupdate`, a
chain per object) and for each joint (:mod:`gt3dkit.fusion.ukf.jointupdate`, a chain per person and
joint) alike.

The loop reads and writes a chain's states only through its *steps*, each a compiled function of
the kind's bundle ``ctx`` (a NamedTuple: the chains, the arrays it reads and writes, work
arrays), the element ``e`` (what the kind needs to find a chain's own states: the joint chain's
index; the boxes need none) and the rows:

========================== =============================================================
``start(ctx, e, row)``     the chain's first prediction: its initial state
``predict(ctx, e, row, prev, f)`` row's prediction from ``prev``'s filtered state, the motion's
                           noise on position and velocity scaled by ``f`` (1: as it is)
``fades(ctx, e, row)``     whether the prediction is tested against the frame's own fit
``fade(ctx, e, row)``      the fading factor (:func:`gt3dkit.fusion.ukf.kalman.fade_factor`)
``faded(ctx, e, row, f)``  the prediction's covariance widened by ``f`` (``f`` != 1) and
                           the row marked faded
``measured(ctx, e, row)``  whether the row has a measurement of this chain
``keep(ctx, e, row)``      the filtered state := the prediction (a row without measurements)
``update(ctx, e, row)``    the measurement update (its linearisation point, the iterated
                           robust update of :mod:`gt3dkit.fusion.ukf.update`)
``smooth(ctx, e, row, nxt)`` the RTS step of ``row`` from the smoothed ``nxt``
========================== =============================================================

A kind registers its steps for its bundle's class (:func:`register`); the loop's compiled code
is specialised per bundle (numba's overloads), so each kind runs as fast as its own loop did.

In compiled code a step call is the kind's step compiled in place, from its Python source (the
overload's implementation is the step's ``py_func``), and the two chain loops are inlined into
each kind's ``forward`` and ``backward`` (numba's ``inline="always"``). numba links each
compiled function with everything it calls and optimises and compiles the whole again, so each
level between a kind's ``forward`` and its steps' code cost that code's compilation once more:
a wrapper that called the step's own compiled function, and the chain loops as functions of
their own, were two such levels. Without them the box kernels compile in 77 s instead of 118 s
and the joint kernels in 52 s instead of 84 s (``make setup``'s two processes side by side,
empty caches, this 2-core machine); every output file is the same (``scripts/same_outputs.py``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple, Protocol

import numba
import numpy as np
from numba import types
from numba.extending import overload

from gt3dkit.geom.kernel_cache import drop_stale
from gt3dkit.types import F64, I64

drop_stale()  # before any compiled function below is called (and its cache read)


class Chains(NamedTuple):
    """Each object's rows as a chain: ``next_row, prev_row (R,)`` (-1: none), the rows taken
    ``run (R,)`` and their times ``t_s (R,)`` (s)."""

    next_row: I64
    prev_row: I64
    run: np.ndarray
    t_s: F64


class Bundle(Protocol):
    """What the loop itself reads of a kind's bundle ``ctx`` (a NamedTuple): its chains. The
    steps read the rest (their kind's own fields)."""

    @property
    def chains(self) -> Chains: ...


#: (step name, bundle class) -> the kind's step, its Python source (``py_func``): what compiled
#: code compiles in place (:func:`_resolved`) and what a call from Python runs (:func:`_step`).
_STEPS: dict[tuple[str, type], Callable[..., object]] = {}
STEP_NAMES = ("start", "predict", "fades", "fade", "faded", "measured", "keep", "update", "smooth")


def register(bundle: type, **steps: Callable[..., object]) -> None:
    """The compiled ``steps`` (every one of :data:`STEP_NAMES`) of a kind whose bundle is of
    class ``bundle``."""
    if set(steps) != set(STEP_NAMES):
        raise ValueError(f"steps must be exactly {', '.join(STEP_NAMES)}")
    for name, fn in steps.items():
        _STEPS[(name, bundle)] = getattr(fn, "py_func", fn)


def _step(name: str) -> Callable[..., Any]:
    """Step ``name`` as the loop calls it (its arguments: the module doc's table): the kind's
    step for the bundle's class. In compiled code numba resolves it (:func:`_resolved`); called
    from Python (a test, a debugger) it runs that step's Python source (``py_func``: nothing
    compiled for the call, and a debugger steps into it)."""
    def step(ctx: tuple[object, ...], *args: object) -> object:
        impl = _STEPS.get((name, type(ctx)))
        if impl is None:
            raise TypeError(f"no kind registered for {type(ctx).__name__} (filterloop.register)")
        return impl(ctx, *args)
    step.__name__ = step.__qualname__ = name
    return step


start, predict, fades, fade, faded, measured, keep, update, smooth = (_step(n) for n in STEP_NAMES)


def _resolved(name: str) -> Callable[..., object]:
    """numba's typing of step ``name``: the kind's step for the bundle's class, compiled from its
    Python source where it is called (its own compiled function would be one more level for
    numba to compile again: the module doc)."""
    def typer(ctx: object, *args: object) -> Callable[..., object] | None:
        bundle = getattr(ctx, "instance_class", None) if isinstance(ctx, types.BaseNamedTuple) else None
        return None if bundle is None else _STEPS.get((name, bundle))
    return typer


for _name, _fn in zip(STEP_NAMES, (start, predict, fades, fade, faded, measured, keep, update, smooth),
                      strict=True):
    # strict=False: the step's own arguments are named (ctx, e, row, ...), the typing's are *args
    overload(_fn, strict=False)(_resolved(_name))


@numba.njit(cache=True, nogil=True)
def spread_over_gap(ctx: Bundle, e: int, row: int, f: float) -> bool:
    """Where row ``row`` (whose prediction the frame's own fit contradicts by the fading factor
    ``f``) follows rows without measurements (a dense run's frames between labels): the process
    noise of every step since the last measured row scaled by ``f`` and those rows predicted
    again, their filtered values the new predictions. The manoeuvre then has the whole gap to
    happen in, and the smoother spreads it over the gap's frames instead of putting it into the
    last step (where the earlier frames would keep the old heading). False, and nothing changed,
    where the previous row is measured or no measured row precedes the gap."""
    chains = ctx.chains
    last = chains.prev_row[row]
    while last >= 0 and chains.run[last] and not measured(ctx, e, last):
        last = chains.prev_row[last]
    if last < 0 or not chains.run[last] or last == chains.prev_row[row]:
        return False
    prev = last
    cur = chains.next_row[last]
    while True:
        predict(ctx, e, cur, prev, f)
        if cur == row:
            return True
        keep(ctx, e, cur)
        prev = cur
        cur = chains.next_row[cur]


@numba.njit(cache=True, nogil=True, inline="always")
def forward_chain(ctx: Bundle, e: int, row0: int) -> None:
    """The forward filter of one chain from its first row ``row0`` along ``chains.next_row``
    while ``chains.run``: each row predicted (the first: its initial state), tested against the
    frame's own fit and faded where that contradicts it (the gap before it spread, where it
    follows rows without measurements), then updated."""
    chains = ctx.chains
    row = row0
    prev = -1
    while row >= 0 and chains.run[row]:
        if prev < 0:
            start(ctx, e, row)
        else:
            predict(ctx, e, row, prev, 1.0)
            if fades(ctx, e, row):
                f = fade(ctx, e, row)
                if f != 1.0:
                    if spread_over_gap(ctx, e, row, f):
                        f = fade(ctx, e, row)
                    faded(ctx, e, row, f)
        update(ctx, e, row)
        prev = row
        row = chains.next_row[row]


@numba.njit(cache=True, nogil=True, inline="always")
def backward_chain(ctx: Bundle, e: int, last: int) -> None:
    """The RTS smoother of one chain from its last row ``last`` back along ``chains.prev_row``
    while ``chains.run``: the filtered states on entry, the smoothed ones on exit."""
    chains = ctx.chains
    nxt = last
    row = chains.prev_row[nxt] if nxt >= 0 else -1
    while row >= 0 and chains.run[row] and chains.run[nxt]:
        smooth(ctx, e, row, nxt)
        nxt = row
        row = chains.prev_row[row]
