"""parse.HashedFile: a file read by a streaming reader and hashed from the same reads, against
hashlib over the whole file (brute force), whichever way the reader goes through it."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from gt3dkit.errors import InputError
from gt3dkit.parse import CSV_CHUNK_BYTES, HashedFile, iter_csv_blocks, iter_csv_rows


def _csv(path: Path, rows: int, quoted_from: int | None = None) -> Path:
    lines = ["frame,camera,id,xmin,ymin,xmax,ymax"]
    for k in range(rows):
        cam = f'"c{k % 3}"' if quoted_from is not None and k >= quoted_from else f"c{k % 3}"
        lines.append(f"{k},{cam},{k % 7},{k}.5,1,{k + 10}.25,20")
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("quoted_from", [None, 5, 0])
def test_blocks_read_through_it_hash_the_whole_file(tmp_path: Path, quoted_from: int | None) -> None:
    """Plain chunks, a text tail from a quoted line on (the reader seeks back to it), or text from
    the header: the digest is the file's, and the rows are those of a reading by path."""
    rows = 3 * CSV_CHUNK_BYTES // 40 if quoted_from is None else 200
    p = _csv(tmp_path / "boxes.csv", rows, quoted_from)
    cols = ("frame", "camera", "id", "xmin", "ymin", "xmax", "ymax")
    by_path = [b.lines.tolist() for b in iter_csv_blocks(p, cols, None, 64, "isiffff")]
    with HashedFile(p) as hashed:
        shared = [b.lines.tolist() for b in iter_csv_blocks(p, cols, None, 64, "isiffff", hashed)]
        digest = hashed.hexdigest()
    assert shared == by_path
    assert digest == hashlib.sha256(p.read_bytes()).hexdigest()


def test_a_reader_that_stops_early_still_gets_the_whole_files_digest(tmp_path: Path) -> None:
    p = _csv(tmp_path / "boxes.csv", 500)
    with HashedFile(p) as hashed:
        rows = iter_csv_rows(p, ("frame", "camera"), [], shared=hashed)
        assert next(rows)[0] == 2
        rows.close()
        assert hashed.hexdigest() == hashlib.sha256(p.read_bytes()).hexdigest()


def test_an_unreadable_file_is_one_input_error(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="cannot read"):
        HashedFile(tmp_path)  # a folder
