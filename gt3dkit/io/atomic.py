"""Write a whole output folder or nothing, and never mix two runs' files.

A run writes its complete result into a temporary sibling of ``OUT`` (same file system)
and then swaps it in with one rename: ``renameat2(RENAME_EXCHANGE)`` where the kernel and
file system have it (the previous result stays whole until that instant), else two renames
under a lock. Files of an earlier run that this run does not write are gone with the old
folder, so ``OUT`` only ever holds one run's files. The swap is serialised by an
``flock`` on the parent folder, so two concurrent runs into one ``OUT`` leave the complete
result of one of them.

``OUT`` is only replaced when it is empty or holds a gt3dkit output (the marker file
:data:`MARKER`): a folder of someone else's files is refused, never deleted.

A run killed with SIGKILL leaves its temporary folder (``.OUT.gt3d-tmp-<pid>-*``) behind;
the next run into the same ``OUT`` removes those whose process is gone.
"""

from __future__ import annotations

import contextlib
import ctypes
import datetime as _dt
import errno
import fcntl
import json
import os
import re
import shutil
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

from gt3dkit.errors import InputError

#: Written into every folder gt3dkit writes: proof that replacing it loses nobody's files.
MARKER = ".gt3dkit-output"
_TMP = ".gt3d-tmp-"
_OLD = ".gt3d-old-"
_AT_FDCWD = -100
_RENAME_EXCHANGE = 2


def _nearest_existing(p: Path) -> Path:
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def check_out(out: str | Path, option: str = "--out") -> None:
    """Raise :class:`InputError` now, before any work, if ``out`` cannot take a result: it is a
    file, a folder of files gt3dkit did not write, or lies where nothing can be created."""
    out = Path(out)
    if out.is_symlink() or (out.exists() and not out.is_dir()):
        raise InputError(option, f"{out} exists and is not a folder")
    if out.is_dir():
        try:
            entries = [e.name for e in os.scandir(out)]
        except OSError as e:
            raise InputError(option, f"{out}: cannot read the folder ({e.strerror})") from None
        if entries and MARKER not in entries and not _legacy_output(out):
            some = ", ".join(sorted(entries)[:3]) + (", ..." if len(entries) > 3 else "")
            raise InputError(option, f"{out} holds files gt3dkit did not write ({some}): choose "
                                     "a new or empty folder, or an earlier gt3dkit output")
    base = _nearest_existing(out.absolute().parent)
    if not base.is_dir():
        raise InputError(option, f"{out}: {base} is not a folder")
    if not os.access(base, os.W_OK | os.X_OK):
        raise InputError(option, f"{out}: no permission to write in {base}")


def _legacy_output(out: Path) -> bool:
    """An output of gt3dkit 0.1 (before :data:`MARKER`): its ``meta.json`` names gt3dkit."""
    try:
        return "gt3dkit_version" in json.loads((out / "meta.json").read_text())
    except (OSError, ValueError, TypeError, RecursionError):
        return False


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def clean_stale(out: Path) -> list[Path]:
    """Remove the temporary folders of earlier runs into ``out`` whose process is gone
    (killed with SIGKILL, or the machine stopped). Returns what was removed."""
    out = Path(out).absolute()
    removed: list[Path] = []
    if not out.parent.is_dir():
        return removed
    pat = re.compile(re.escape(f".{out.name}") + f"(?:{re.escape(_TMP)}|{re.escape(_OLD)})" + r"(\d+)-")
    for p in out.parent.iterdir():
        m = pat.match(p.name)
        if m and p.is_dir() and not p.is_symlink() and not _pid_alive(int(m.group(1))):
            shutil.rmtree(p, ignore_errors=True)
            removed.append(p)
    return removed


@contextlib.contextmanager
def _locked(folder: Path) -> Iterator[None]:
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


def _exchange(a: Path, b: Path) -> bool:
    """Atomically swap two existing paths; False where the system cannot."""
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except AttributeError:
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(b))


def _swap_in(tmp: Path, out: Path) -> None:
    """Make ``tmp`` be ``out``; the previous ``out`` (if any) ends up at ``tmp``."""
    if not out.exists():
        try:
            os.rename(tmp, out)
            return
        except OSError as e:  # created meanwhile by someone else
            if e.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                raise
    if _exchange(tmp, out):
        return
    old = tmp.with_name(tmp.name.replace(_TMP, _OLD, 1))
    os.rename(out, old)
    os.rename(tmp, out)
    os.rename(old, tmp)


def write_dir_atomically(out: str | Path, write: Callable[[Path], None], option: str = "--out") -> None:
    """Call ``write(tmpdir)`` and make what it wrote be ``out``, whole, in one step (a folder
    that cannot take it is an :class:`InputError` naming ``option``, the user's option for it).

    On any failure or interruption (``KeyboardInterrupt``, SIGTERM turned into
    ``SystemExit``) the temporary folder is removed and ``out`` is left as it was.
    """
    out = Path(out).absolute()
    check_out(out, option)
    out.parent.mkdir(parents=True, exist_ok=True)
    clean_stale(out)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}{_TMP}{os.getpid()}-", dir=out.parent))
    try:
        write(tmp)
        (tmp / MARKER).write_text(json.dumps({
            "written_by": "gt3dkit", "pid": os.getpid(),
            "created_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")}) + "\n")
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes 0o700
        with _locked(out.parent):
            check_out(out, option)  # another program may have put files there meanwhile
            _swap_in(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
