"""Write a whole output directory or nothing."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path


def write_dir_atomically(out: Path, write: Callable[[Path], None]) -> None:
    """Call ``write(tmpdir)``, then move every file it wrote into ``out``.

    The files are written in a temporary sibling directory of ``out`` (same file
    system) and each is renamed into place only after all were written, so a
    failure part way leaves ``out`` as it was. Existing files of the same names
    are replaced; other files in ``out`` are left alone.
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        write(tmp)
        out.mkdir(parents=True, exist_ok=True)
        for src in sorted(tmp.rglob("*")):
            if src.is_file():
                dst = out / src.relative_to(tmp)
                dst.parent.mkdir(parents=True, exist_ok=True)
                os.replace(src, dst)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
