"""``gt3d``'s commands run: parse, call the library, print. No maths here. (:mod:`gt3dkit.cli`, the
entry point, connects to a Dask scheduler first where it can, then calls :func:`main`.)"""

from __future__ import annotations

import sys
import warnings

from gt3dkit.commands.common import (
    Terminated,
    quiet_stdout,
    signals_handled,
    unexpected_error,
)
from gt3dkit.commands.parser import build_parser
from gt3dkit.early import Early
from gt3dkit.errors import EstimationError, InputError
from gt3dkit.threads import small_matrix_blas


def main(argv: list[str] | None = None, early: Early | None = None) -> int:
    """The ``gt3d`` command. Exit status: 0 done, 2 bad input or option (one ``error:`` line),
    1 an unexpected error (one line; ``--debug`` shows the traceback), 130 / 143 interrupted
    (SIGINT / SIGTERM); in every failure no output is written or changed. ``early``: the
    connection to ``gt3d reconstruct``'s ``--scheduler`` made before the imports, for the run
    to take over (:mod:`gt3dkit.cli`)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    debug = "--debug" in argv
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as e:  # --help (0) or a usage error (2, already printed)
        return int(e.code or 0)
    if "early" in vars(args):
        args.early = early
    try:
        with signals_handled(), warnings.catch_warnings(), small_matrix_blas():
            if not debug:  # numerical warnings are ours to handle, never the user's to read
                warnings.simplefilter("ignore", RuntimeWarning)
            code = int(args.func(args))
            sys.stdout.flush()  # here, where a closed pipe is handled, not at interpreter exit
        return code
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except EstimationError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    except BrokenPipeError:  # ``gt3d ... | head``: the reader left; the output is complete
        quiet_stdout()
        return 141
    except KeyboardInterrupt:
        print("error: interrupted (Ctrl-C): no output written or changed", file=sys.stderr)
        return 130
    except Terminated as e:
        print(f"error: stopped by {e}: no output written or changed", file=sys.stderr)
        return 128 + e.signum
    except OSError as e:  # the machine, not the input: a full disk, a vanished folder
        print(f"error: {e.filename or 'system'}: {e.strerror or e}", file=sys.stderr)
        return 1
    except MemoryError:
        print("error: out of memory: the input is too large for this machine", file=sys.stderr)
        return 1
    except Exception as e:  # noqa: BLE001 - the one place that turns a bug into one line
        return unexpected_error(e, debug)


if __name__ == "__main__":
    sys.exit(main())
