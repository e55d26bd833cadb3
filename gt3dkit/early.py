"""The Dask connection ``gt3d reconstruct --scheduler`` makes first, before this process loads
gt3dkit's own imports (:mod:`gt3dkit.cli`): the scheduler's first worker loads its imports and
compiled kernels (about 2 s on a fresh worker) while this process loads its own (about 1 s),
instead of after them. This module imports only the standard library and, when asked to
connect, Dask; so do the modules it imports (:mod:`gt3dkit.errors`)."""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from gt3dkit.errors import InputError
from gt3dkit.sealed import submit

if TYPE_CHECKING:
    from distributed import Client, Future

#: ``--estimator``'s default (``gt3d reconstruct``, ``reconstruct-many``): the one the early
#: connection warms when none is given.
DEFAULT_ESTIMATOR = "ukf"

#: The kinds of tiny scene a worker is warmed on (:func:`gt3dkit.api.tiny_scene`), one task each,
#: in this order: the run lets go of the kind its input does not use as soon as it has loaded
#: (:meth:`gt3dkit.windows.cluster.Cluster.warm_only`), and Dask cancels that one where it has
#: not started.
WARM_KINDS = ("boxes", "joints")


def check_scheduler_address(address: str) -> None:
    """InputError naming ``--scheduler`` unless ``address`` is one Dask can connect to: a known
    scheme (``tcp://`` when none is given) and, for the network schemes, a host and a port
    (Dask's own parsers; they raised inside the client as an internal error)."""
    from distributed.comm.addressing import parse_address, parse_host_port
    from distributed.comm.registry import backends

    try:
        scheme, loc = parse_address(address)
        if scheme not in backends:
            raise ValueError(f"unknown address scheme {scheme!r} (known: {', '.join(sorted(backends))})")
        if scheme in ("tcp", "tls", "ws", "wss"):
            host, _ = parse_host_port(loc)
            if not host:
                raise ValueError("no host")
    except ValueError as e:
        raise InputError("--scheduler", f"{address!r} is not a Dask scheduler address ({e}): give "
                                        "tcp://HOST:PORT") from None


@dataclass
class Early:
    """A connection to the Dask scheduler at ``address`` made before the command line was read
    whole (:func:`connect_early`): its ``client``, or the ``error`` connecting raised (said where
    the run connects, as if it had connected then: :func:`gt3dkit.windows.cluster.connect_scheduler`),
    and the futures of the warm-ups sent to its workers by address (none: no worker had joined
    yet), by worker and kind (:data:`WARM_KINDS`). Who takes the client closes it; :meth:`close`
    closes it if nobody did."""

    address: str
    client: Client | None = None
    error: BaseException | None = None
    warming: dict[tuple[str, str], Future[object]] = field(default_factory=dict)

    def close(self) -> None:
        self.warming = {}
        if self.client is not None:
            with contextlib.suppress(Exception):
                self.client.close()


def connect_early(address: str, warm: Callable[..., None], *args: object) -> Early:
    """Connect to the Dask scheduler at ``address`` and send ``warm(*args, kind)`` for each of
    :data:`WARM_KINDS` to its first worker (sorted by address: the one the noise search runs on),
    not waiting for them. The others are sent theirs when the run takes this connection over
    (:class:`gt3dkit.windows.cluster.Cluster`): on 2 cores, warming them all now made the
    client's own imports wait, and the windows started 0.4-0.7 s later than with the first alone
    (3 runs each). Connecting as the run would, with Dask's own timeout; whatever goes wrong is
    kept, not raised (the run says it where it connects)."""
    from distributed import Client

    try:
        check_scheduler_address(address)
        client = Client(address)
    except Exception as e:  # noqa: BLE001 - said later, as the run's own connection says it
        return Early(address, error=e)
    first = sorted(client.scheduler_info()["workers"])[:1]
    return Early(address, client=client, warming={
        (w, kind): submit(client, warm, *args, kind, workers=[w], allow_other_workers=False)
        for w in first for kind in WARM_KINDS})
