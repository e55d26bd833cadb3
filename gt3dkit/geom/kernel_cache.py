"""numba's disk cache kept in step with the kernel sources.

numba caches each compiled function next to its own source file and checks that file alone: a
kernel that calls (and so compiles in) a function of another file keeps the old machine code
after that other file changes. :func:`drop_stale` runs when the first kernel module is imported
(before any compiled function is called, so before numba reads a cache): when the digest of all
kernel files differs from the one recorded beside their caches, every cache of those files is
removed and the new digest recorded. Editing any kernel file therefore recompiles them all.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1]
#: Every file holding compiled functions (numba ``cache=True``), relative to the package.
KERNEL_FILES = ("geom/boxrig.py", "geom/boxkernel.py", "geom/smallmat.py", "geom/trikernel.py",
                "fusion/motion.py", "fusion/ukf/kalman.py", "fusion/preparation/robust.py",
                "fusion/ukf/update.py", "fusion/ukf/filterloop.py", "fusion/ukf/boxupdate.py",
                "fusion/preparation/boxlm.py", "fusion/ukf/jointupdate.py", "io/numtext.py")
STAMP = PACKAGE / "__pycache__" / "numba-kernels.sha256"
_checked = False


def digest() -> str:
    """SHA-256 over the kernel files' names and contents."""
    h = hashlib.sha256()
    for rel in KERNEL_FILES:
        h.update(rel.encode())
        h.update((PACKAGE / rel).read_bytes())
    return h.hexdigest()


def cache_files() -> list[Path]:
    """numba's index and data files of the kernel files (``__pycache__/<module>.*.nbi|nbc``)."""
    out: list[Path] = []
    for rel in KERNEL_FILES:
        src = PACKAGE / rel
        out += [p for p in (src.parent / "__pycache__").glob(f"{src.stem}.*") if p.suffix in (".nbi", ".nbc")]
    return out


def drop_stale() -> bool:
    """Remove every kernel cache if any kernel file changed since the caches were made; returns
    whether it did. Once per process; a read-only install (numba then caches elsewhere, or not at
    all) or ``NUMBA_CACHE_DIR`` (numba's own location) is left alone."""
    global _checked
    if _checked or os.environ.get("NUMBA_CACHE_DIR"):
        return False
    _checked = True
    now = digest()
    try:
        if STAMP.is_file() and STAMP.read_text().strip() == now:
            return False
        for p in cache_files():
            p.unlink(missing_ok=True)
        STAMP.parent.mkdir(exist_ok=True)
        tmp = STAMP.with_name(f"{STAMP.name}.{os.getpid()}")
        tmp.write_text(now + "\n")
        tmp.replace(STAMP)
    except OSError:
        return False
    return True
