"""The CSV block reader (gt3dkit.parse.iter_csv_blocks): where it parses whole chunks at once
(numpy.loadtxt) it reads every file as the row-by-row text reading (csv.reader, int, float) does:
the same rows on the same lines, the same numbers to the bit, the same error for a bad file."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from gt3dkit import parse
from gt3dkit.errors import InputError
from gt3dkit.parse import iter_csv_blocks

COLUMNS = ("frame", "camera", "u")
KINDS = "isf"


def _number(text: str, kind: str) -> object:
    """A field as the row-by-row checks read it: the number (a float by its bits), or the text."""
    try:
        v = int(text) if kind == "i" else float(text)
    except (ValueError, OverflowError):
        return ("text", text)
    if kind == "i":
        return v if -2**63 <= v < 2**63 else ("text", text)
    return struct.pack("<d", v)


def _read(path: Path, kinds: str) -> list[tuple[int, tuple[object, ...]]] | str:
    """Every row ``(line, fields)`` as a reader sees it (numbers where the block parsed them or
    where they parse), or the error the reading raised."""
    got: list[tuple[int, tuple[object, ...]]] = []
    try:
        for block in iter_csv_blocks(path, COLUMNS, [], 4, kinds):
            try:
                cols = [block.ints(0).tolist(), list(block.texts(1)),
                        [struct.pack("<d", v) for v in block.floats(2).tolist()]]
                rows = [tuple(c[k] for c in cols) + tuple(r[3:]) for k, r in enumerate(block.rows())]
            except (ValueError, OverflowError):
                rows = [(_number(r[0], "i"), r[1], _number(r[2], "f"), *r[3:]) for r in block.rows()]
            got += list(zip(block.lines.tolist(), rows, strict=True))
    except InputError as e:
        return str(e)
    return got


FIELDS = st.sampled_from(["1", "-2", " 3 ", "+4", "1_0", "1.5", "nan", "-inf", "1e400", "0x10", "", " ",
                          "9223372036854775808", "\u0661", "2.5e-3", "cam a", "x,y", '"q"', '"a,b"',
                          "\t7", "1e5", "Infinity"])
LINE_ENDS = st.sampled_from(["\n", "\r\n", "\r", "\n\n", "\n \n"])


@st.composite
def csv_files(draw: st.DrawFn) -> bytes:
    """A header (or none), then rows of 2-4 random fields with random line ends, sometimes a
    byte-order mark, a NUL byte, bytes that are not UTF-8, or the file cut short."""
    header = draw(st.sampled_from(["frame,camera,u", "frame,camera,u,extra", "frame, camera ,u", "frame,u",
                                   ""]))
    text = header + draw(LINE_ENDS)
    for _ in range(draw(st.integers(0, 14))):
        text += ",".join(draw(st.lists(FIELDS, min_size=2, max_size=4))) + draw(LINE_ENDS)
    raw = (b"\xef\xbb\xbf" if draw(st.booleans()) else b"") + text.encode()
    if draw(st.integers(0, 9)) == 0:  # a file cut short: nothing, or the header's first bytes
        raw = raw[:draw(st.integers(0, 8))]
    spoil = draw(st.sampled_from([b"", b"", b"", b"\0", b"\xff"]))
    if spoil:
        k = draw(st.integers(0, len(raw)))
        raw = raw[:k] + spoil + raw[k:]
    return raw


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(raw=csv_files(), chunk=st.sampled_from([16, 64, 1 << 22]))
def test_chunks_parsed_at_once_read_as_the_rows_do(raw: bytes, chunk: int, tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """Random files (quotes, blank and blank-looking lines, every line end, bad numbers, rows of
    another width, NUL bytes, broken UTF-8), cut into chunks of a few lines or read whole: the
    typed reading gives what the text reading gives, or the same error (bytes that are not UTF-8:
    an error; the text reading's decoder reads ahead of its rows, so it may say that before a bad
    row that comes first)."""
    monkeypatch.setattr(parse, "CSV_CHUNK_BYTES", chunk)
    path = tmp_path / "f.csv"
    path.write_bytes(raw)
    typed, text = _read(path, KINDS), _read(path, "")
    try:
        raw.decode("utf-8")
    except UnicodeDecodeError:  # both fail; which error comes first is the text reading's read-ahead
        assert isinstance(typed, str) and isinstance(text, str), (typed, text)
        return
    assert typed == text


def test_a_plain_file_is_parsed_at_once_with_its_line_numbers(tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """A plain file's chunks come parsed (no row-by-row text), each row on its own line; after a
    chunk that is not plain (a quoted field), the rest is read as text, on the right lines, and
    a bad row there is named by its line."""
    monkeypatch.setattr(parse, "CSV_CHUNK_BYTES", 32)
    rows = [f"{k},c{k % 3},{k / 7!r}" for k in range(40)]
    path = tmp_path / "f.csv"
    path.write_text("frame,camera,u\r\n" + "\r\n".join(rows) + "\r\n")
    blocks = list(iter_csv_blocks(path, COLUMNS, None, 65536, KINDS))
    assert len(blocks) > 5 and all(b._rows is None for b in blocks)
    np.testing.assert_array_equal(np.concatenate([b.lines for b in blocks]), np.arange(2, 42))
    np.testing.assert_array_equal(np.concatenate([b.floats(2) for b in blocks]), [k / 7 for k in range(40)])
    assert [t for b in blocks for t in b.texts(1)] == [f"c{k % 3}" for k in range(40)]
    rows[20] = '20,"c,2",' + repr(20 / 7)
    rows[30] = "30,c0"
    path.write_text("frame,camera,u\n" + "\n".join(rows) + "\n")
    with pytest.raises(InputError, match=r"f\.csv: line 32: expected 3 fields \(as the header\), got 2"):
        list(iter_csv_blocks(path, COLUMNS, None, 65536, KINDS))
    rows[30] = "30,c0,1.5"
    path.write_text("frame,camera,u\n" + "\n".join(rows) + "\n")
    blocks = list(iter_csv_blocks(path, COLUMNS, None, 65536, KINDS))
    assert blocks[0]._rows is None and blocks[-1]._rows is not None  # parsed, then text
    np.testing.assert_array_equal(np.concatenate([b.lines for b in blocks]), np.arange(2, 42))
    assert [t for b in blocks for t in b.texts(1)][20] == "c,2"
    assert math.isclose(blocks[-1].floats(2)[-1], 39 / 7)
