"""Reading fields of text files with one error per bad entry: checksums, JSON documents, CSV rows,
integers, frames, numbers and world coordinates, each failing with :class:`gt3dkit.errors.InputError`
naming the file and the entry. Used by every reader (annotations, calibrations, results)."""

from __future__ import annotations

import contextlib
import csv
import hashlib
import io
import json
import math
import tomllib
from collections.abc import Callable, Generator, Iterator
from operator import itemgetter
from pathlib import Path
from typing import Any, BinaryIO, Protocol, SupportsFloat, SupportsIndex, SupportsInt, TypeVar

import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.rig import MAX_WORLD_M

T = TypeVar("T")

class LineCounted(Protocol):
    """A ``csv.reader``: the line it has read to."""

    line_num: int


#: A CSV file's rows as :func:`csv.reader` gives them.
class CsvRows(Protocol):
    """What the readers use of ``csv.reader``'s rows: them, and the line the last one ended on."""

    @property
    def line_num(self) -> int: ...

    def __iter__(self) -> Iterator[list[str]]: ...

    def __next__(self) -> list[str]: ...


def sha256(path: Path) -> str:
    """Hex SHA-256 of a file, or :class:`InputError` if it cannot be read (a folder, no
    permission)."""
    h = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
    except OSError as e:
        raise InputError(str(path), f"cannot read ({e.strerror})") from None
    return h.hexdigest()


#: Frame numbers are 0 .. FRAME_MAX; ids are integers of magnitude up to ID_MAX (exact in a
#: float64, so they survive every array and file they pass through).
FRAME_MAX = 2**31 - 1
ID_MAX = 2**53


def load_json(path: Path) -> Any:
    """The document in a JSON file, or :class:`InputError` naming the file: unreadable,
    malformed, truncated or absurdly nested. A UTF-8 byte-order mark is allowed."""
    return _json_doc(path, _read_bytes(path))


def load_toml(path: Path) -> dict[str, Any]:
    """The document in a TOML file, or :class:`InputError` naming the file: unreadable or
    malformed. A UTF-8 byte-order mark is allowed."""
    try:
        return tomllib.loads(Path(path).read_text(encoding="utf-8-sig"))
    except tomllib.TOMLDecodeError as e:
        raise InputError(str(path), f"malformed TOML ({e})") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(str(path), f"cannot read ({e})") from None


class _HashingRaw(io.RawIOBase):
    """A raw binary file whose bytes are hashed as they are first read (a byte read again after a
    seek back is not hashed twice)."""

    def __init__(self, raw: io.FileIO) -> None:
        self.raw, self.h, self.upto = raw, hashlib.sha256(), 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        return self.raw.seek(offset, whence)

    def tell(self) -> int:
        return self.raw.tell()

    def readinto(self, b: bytearray | memoryview) -> int:  # type: ignore[override]
        at = self.raw.tell()
        n = self.raw.readinto(b) or 0
        if at <= self.upto < at + n:
            self.h.update(memoryview(b)[self.upto - at:n])
            self.upto = at + n
        return n

    def close(self) -> None:
        self.raw.close()
        super().close()


class HashedFile:
    """A file opened once for a reader that streams it, its SHA-256 taken from the reads that parse
    it (:meth:`hexdigest` reads what they left). A context manager; the CSV readers take it as
    ``shared`` (:func:`iter_csv_blocks`, :func:`iter_csv_rows`) in place of opening ``path``."""

    def __init__(self, path: Path) -> None:
        try:
            raw = open(path, "rb", buffering=0)  # noqa: SIM115 (closed by close())
        except OSError as e:
            raise InputError(str(path), f"cannot read ({e.strerror})") from None
        self.path = Path(path)
        self._raw = _HashingRaw(raw)
        self.file = io.BufferedReader(self._raw)

    def at(self, offset: int) -> BinaryIO:
        """The open file, at byte ``offset``."""
        self.file.seek(offset)
        return self.file

    def hexdigest(self) -> str:
        """The file's SHA-256: what the reads hashed and the rest, read now."""
        self.file.seek(self._raw.upto)
        try:
            while self.file.read(1 << 20):
                pass
        except OSError as e:
            raise InputError(str(self.path), f"cannot read ({e.strerror})") from None
        return self._raw.h.hexdigest()

    def __enter__(self) -> HashedFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self.file.close()


def read_hashed(path: Path) -> tuple[bytes, str]:
    """A file's bytes and their :func:`sha256` (InputError when unreadable)."""
    raw = _read_bytes(path)
    return raw, hashlib.sha256(raw).hexdigest()


def json_of(path: Path, raw: bytes) -> Any:
    """The JSON document in ``raw``, the bytes of ``path``: :func:`load_json` of read bytes."""
    return _json_doc(path, raw)


def _read_bytes(path: Path) -> bytes:
    try:
        return Path(path).read_bytes()
    except OSError as e:
        raise InputError(str(path), f"cannot read ({e.strerror})") from None


def _json_doc(path: Path, raw: bytes) -> Any:
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise InputError(str(path), f"not a UTF-8 text file ({e.reason} at byte {e.start})") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise InputError(str(path), f"malformed JSON ({e})") from None
    except RecursionError:
        raise InputError(str(path), "malformed JSON (nested too deeply)") from None


def read_json_field(path: Path, key: str, what: str) -> Any:
    """``json.load(path)[key]``, or :class:`InputError` naming the file (malformed, truncated
    or without ``key``)."""
    return json_field(path, _read_bytes(path), key, what)


def json_field(path: Path, raw: bytes, key: str, what: str) -> Any:
    """:func:`read_json_field` of ``raw``, the bytes of ``path`` already read."""
    doc = _json_doc(path, raw)
    if not isinstance(doc, dict) or key not in doc:
        raise InputError(str(path), f"expected {{'{key}': {what}}}")
    return doc[key]


def parse_int(where: str, text: object, name: str, lo: int = -ID_MAX, hi: int = ID_MAX) -> int:
    """An integer field (text or JSON value) in ``[lo, hi]``, or :class:`InputError`."""
    if isinstance(text, bool) or isinstance(text, float) and not text.is_integer():
        raise InputError(where, f"{name} must be an integer, got {text!r}")
    try:
        if not isinstance(text, str | SupportsInt | SupportsIndex):
            raise TypeError
        v = int(text)
    except (TypeError, ValueError, OverflowError):
        raise InputError(where, f"{name} must be an integer, got {text!r}") from None
    if not lo <= v <= hi:
        raise InputError(where, f"{name} {v} is outside {lo}..{hi}")
    return v


def parse_frame(where: str, text: object) -> int:
    return parse_int(where, text, "frame", 0, FRAME_MAX)


def parse_float(where: str, text: object, name: str, limit: float = math.inf) -> float:
    """A finite number field of magnitude up to ``limit``, or :class:`InputError`."""
    try:
        if not isinstance(text, str | SupportsFloat | SupportsIndex):
            raise TypeError
        v = float(text)
    except (TypeError, ValueError, OverflowError):
        raise InputError(where, f"{name} must be a number, got {text!r}") from None
    if not math.isfinite(v):
        raise InputError(where, f"{name} is not finite ({text})")
    if abs(v) > limit:
        raise InputError(where, f"{name} {v:g} is beyond {limit:g}")
    return v


def parse_metres(where: str, text: object, name: str) -> float:
    """A world coordinate or length (m): finite, within :data:`MAX_WORLD_M`."""
    return parse_float(where, text, f"{name} (m)", MAX_WORLD_M)


def read_csv_rows(path: Path, columns: tuple[str, ...], warnings: list[str] | None = None,
                  header: bool = True) -> list[tuple[int, dict[str, str]]]:
    """:func:`iter_csv_rows` as a list."""
    return list(iter_csv_rows(path, columns, warnings, header))


#: Bytes of whole lines :func:`iter_csv_blocks` reads and parses at once.
CSV_CHUNK_BYTES = 1 << 22


class CsvBlock:
    """Rows of a CSV file (:func:`iter_csv_blocks`): their line numbers (``lines``) and their
    fields, as numbers where the block was parsed at once (:meth:`ints`, :meth:`floats`) and as
    text (:meth:`texts`; :meth:`rows` for the row-by-row checks of a block that fails the
    caller's)."""

    def __init__(self, lines: np.ndarray | list[int], rows: list[list[str]] | None = None, text: str = "",
                 columns: list[np.ndarray] | None = None, kinds: str = "", path: Path | None = None) -> None:
        self.lines = np.asarray(lines, np.int64)
        self.path = path
        self._rows, self._text = rows, text
        self._columns, self._kinds = columns, kinds
        self._texts: list[tuple[str, ...]] | None = None

    def __len__(self) -> int:
        return len(self.lines)

    def rows(self) -> list[list[str]]:
        """Each row's fields as text (unstripped)."""
        if self._rows is None:  # a block parsed at once: a row a line
            reader = csv.reader(io.StringIO(self._text))
            try:
                self._rows = list(reader)
            except csv.Error as e:  # a field longer than csv.reader reads, that numpy read as a number
                raise _malformed(self.path or Path("input"), reader, int(self.lines[0]) - 1, e) from None
        return self._rows

    def _parsed(self, k: int, kind: str) -> np.ndarray | None:
        return self._columns[k] if self._columns is not None and self._kinds[k:k + 1] == kind else None

    def _column_text(self, k: int) -> tuple[str, ...]:
        if self._texts is None:
            self._texts = block_columns(self.rows())
        return self._texts[k]

    def ints(self, k: int) -> np.ndarray:
        """``(P,)`` int64 of column ``k``, as :func:`int_column` parses it (ValueError or
        OverflowError where a field is not an int64)."""
        got = self._parsed(k, "i")
        return got if got is not None else int_column(self._column_text(k))

    def floats(self, k: int) -> np.ndarray:
        """``(P,)`` float64 of column ``k``, as :func:`float_column` parses it (ValueError where
        a field is not a number)."""
        got = self._parsed(k, "f")
        return got if got is not None else float_column(self._column_text(k))

    def texts(self, k: int) -> np.ndarray | tuple[str, ...]:
        """Column ``k``'s fields as text (unstripped)."""
        got = self._parsed(k, "s")
        return got if got is not None else self._column_text(k)


def iter_csv_blocks(path: Path, columns: tuple[str, ...], warnings: list[str] | None = None,
                    size: int = 65536, kinds: str = "", shared: HashedFile | None = None
                    ) -> Iterator[CsvBlock]:
    """:func:`iter_csv_rows` (a header) in blocks (:class:`CsvBlock`), for readers that check a
    block at once with numpy and fall back to the row-by-row checks only for a block that fails
    them. The same checks of the header and of every row's field count. ``kinds``: the leading
    columns' types, one letter each (``i`` int64, ``f`` float64, ``s`` text).

    Where a stretch of the file is plain (UTF-8 without quotes, NUL bytes, lone carriage returns
    or blank lines: the text ``csv.reader`` splits at every comma and line end), its
    :data:`CSV_CHUNK_BYTES` at a time are parsed by ``numpy.loadtxt``, which reads those numbers
    as ``int`` and ``float`` do and refuses what they refuse, with a field count as the header's
    in every row; a chunk it refuses is read as text. The rest of a file, from its first stretch
    that is not plain, is read by ``csv.reader`` in blocks of up to ``size`` rows, one loop per
    block (not a generator per row: a 3.6-million-row file read in 4 s, not 8). A 712 798-row
    ``keypoints.csv`` parsed in 0.4 s against 2.6 s as text. ``shared``: the file already open
    (:class:`HashedFile`: read through it, not opened again)."""
    if not kinds:
        return _text_blocks(path, columns, warnings, size, shared=shared)
    return _chunked_blocks(path, columns, warnings, size, kinds, shared)


def _text_blocks(path: Path, columns: tuple[str, ...], warnings: list[str] | None, size: int,
                 width: int = 0, line: int = 1, offset: int = 0, shared: HashedFile | None = None
                 ) -> Iterator[CsvBlock]:
    """:func:`iter_csv_blocks` read by ``csv.reader``; from byte ``offset`` on (line ``line``,
    rows of ``width`` fields) where it is not 0."""
    blocks = _read_csv(path, lambda reader: _record_blocks(path, columns, warnings, reader, size, width,
                                                           line - 1), offset, line - 1, shared)
    return (CsvBlock(lines, rows) for lines, rows in blocks)


def _chunked_blocks(path: Path, columns: tuple[str, ...], warnings: list[str] | None, size: int,
                    kinds: str, shared: HashedFile | None = None) -> Iterator[CsvBlock]:
    """:func:`iter_csv_blocks` with ``kinds``: chunks of plain lines parsed at once, the rest read
    as text from the first that is not plain."""
    if shared is not None:
        f: Any = contextlib.nullcontext(shared.at(0))  # the caller's, left open
    else:
        try:
            f = open(path, "rb")  # noqa: SIM115 (closed below)
        except OSError as e:
            raise InputError(str(path), f"cannot read ({e.strerror})") from None
    with f as f:
        offset, line, width, dtype = 0, 1, 0, None
        try:
            for chunk in _line_chunks(f):
                text = _plain_text(chunk, first=offset == 0)
                if text is None:
                    break
                if offset == 0:  # the header
                    head, _, text = text.partition("\n")
                    width = _checked_header(path, columns, warnings, csv.reader([head]))
                    dtype = np.dtype([(f"f{k}", {"i": "i8", "f": "f8"}.get(kinds[k:k + 1], "O"))
                                      for k in range(width)])
                    line = 2
                offset += len(chunk)
                n = text.count("\n") + (not text.endswith("\n")) if text else 0  # its lines
                block = _chunk_block(path, text, line, n, width, kinds, dtype) if text and dtype else None
                if block is not None:
                    yield block
                line += n
            else:
                if offset:  # read whole (an empty file: no header, said by the text reading)
                    return
        except OSError as e:
            raise InputError(str(path), f"cannot read ({e.strerror})") from None
    # the rest as text, from the first chunk that is not plain (the header's: the whole file)
    yield from _text_blocks(path, columns, warnings, size, width, line, offset, shared)


def _line_chunks(f: BinaryIO) -> Iterator[bytes]:
    """The bytes of the binary file ``f`` about :data:`CSV_CHUNK_BYTES` at a time, each ending
    at a line end (the last as the file ends)."""
    rest = b""
    while True:
        got = f.read(CSV_CHUNK_BYTES)
        if not got:
            if rest:
                yield rest
            return
        got = rest + got
        cut = got.rfind(b"\n") + 1
        if cut == 0:
            rest = got
            continue
        yield got[:cut]
        rest = got[cut:]


def _plain_text(chunk: bytes, first: bool) -> str | None:
    """``chunk`` as text with ``\\n`` line ends, where ``csv.reader`` would split it at every
    comma and line end alone and read every line as a row: UTF-8 (a byte-order mark first),
    without quotes, NUL bytes, carriage returns but before a line feed, or empty lines; else
    None."""
    if b'"' in chunk or b"\0" in chunk or chunk.count(b"\r") != chunk.count(b"\r\n"):
        return None
    try:
        text = chunk.decode("utf-8-sig" if first else "utf-8").replace("\r\n", "\n")
    except UnicodeDecodeError:
        return None
    if text.startswith("\n") or "\n\n" in text:
        return None
    return text


def _chunk_block(path: Path, text: str, line: int, n: int, width: int, kinds: str, dtype: np.dtype
                 ) -> CsvBlock | None:
    """The rows of the plain ``text`` (its ``n`` lines from ``line`` on, rows of ``width`` fields):
    parsed by ``numpy.loadtxt`` (the columns as ``kinds`` says), or read as text where it
    refuses them (a field ``int`` or ``float`` refuses too, a row of another width: the text
    reading says which, and a field longer than ``csv.reader`` reads); None: no rows (lines of
    spaces alone)."""
    try:
        a = np.loadtxt(io.StringIO(text), dtype=dtype, delimiter=",", comments=None, ndmin=1)
    except ValueError:
        a = None
    limit = csv.field_size_limit()
    if a is None or len(a) != n or any(max(map(len, a[name]), default=0) > limit
                                       for name in a.dtype.names or () if a.dtype[name].kind == "O"):
        reader = csv.reader(io.StringIO(text))
        try:
            rows = list(_record_blocks(path, (), None, reader, n + 1, width, line - 1))
        except csv.Error as e:
            raise _malformed(path, reader, line - 1, e) from None
        return CsvBlock(*rows[0]) if rows else None
    return CsvBlock(np.arange(line, line + n), text=text, columns=[a[f"f{k}"] for k in range(width)],
                    kinds=kinds, path=path)


def _record_blocks(path: Path, columns: tuple[str, ...], warnings: list[str] | None, reader: CsvRows,
                   size: int, width: int = 0, skipped: int = 0
                   ) -> Iterator[tuple[list[int], list[list[str]]]]:
    """The rows after a header starting with ``columns`` (checked by :func:`_checked_header`), in
    blocks of up to ``size`` rows ``(line numbers, rows)``: blank lines skipped, every row as wide as
    the header (:func:`iter_csv_blocks`; one row a block for :func:`iter_csv_rows`). ``width``:
    the rows' width, the header read already (``reader`` then starts after ``skipped`` lines)."""
    width = width or _checked_header(path, columns, warnings, reader)
    lines: list[int] = []
    rows: list[list[str]] = []
    for row in reader:
        if len(row) != width or not row[0].strip():
            if not row or all(not x.strip() for x in row):
                continue
            if len(row) != width:
                raise InputError(f"{path}: line {reader.line_num + skipped}", f"expected {width} fields (as "
                                                                               f"the header), got {len(row)}")
        lines.append(reader.line_num + skipped)
        rows.append(row)
        if len(rows) >= size:
            yield lines, rows
            lines, rows = [], []
    if rows:
        yield lines, rows


def block_columns(rows: list[list[str]]) -> list[tuple[str, ...]]:
    """A block of :func:`iter_csv_blocks` (rows of one width) as columns of text."""
    width = len(rows[0]) if rows else 0
    return [tuple(map(itemgetter(k), rows)) for k in range(width)]


def int_column(texts: tuple[str, ...]) -> np.ndarray:
    """``(N,)`` int64 of a block's column (:func:`block_columns`), parsed as ``int`` parses each
    field (numpy's text-to-number conversion does the same, ten times slower); ValueError or
    OverflowError when a field is not an int64."""
    return np.fromiter(map(int, texts), np.int64, len(texts))


def float_column(texts: tuple[str, ...]) -> np.ndarray:
    """``(N,)`` float64 of a block's column, parsed as ``float`` parses each field (NaN and inf
    kept for the caller's checks); ValueError when a field is not a number."""
    return np.fromiter(map(float, texts), np.float64, len(texts))


def iter_csv_rows(path: Path, columns: tuple[str, ...], warnings: list[str] | None = None,
                  header: bool = True, shared: HashedFile | None = None
                  ) -> Generator[tuple[int, dict[str, str]], None, None]:
    """Rows of a CSV whose header starts with ``columns``; (line number, row), one at a time
    (a bad line 2 is reported before line 2 million is read, and the file is never held whole).

    Every row must have as many fields as the header. Header columns beyond ``columns``
    are ignored, with a note in ``warnings`` (an error when ``warnings`` is None). A UTF-8
    byte-order mark (Excel's "CSV UTF-8") is allowed. ``header=False``: a file without a
    header (MOTChallenge), each row with at least ``len(columns)`` fields, the same number in
    every row.
    """
    def rows(reader: CsvRows) -> Iterator[tuple[int, list[str]]]:
        return _csv_records(path, columns, warnings, reader) if header else _headerless(path, columns, reader)

    for line, row in _read_csv(path, rows, shared=shared):
        yield line, dict(zip(columns, (x.strip() for x in row), strict=False))


def _read_csv(path: Path, rows: Callable[[CsvRows], Iterator[T]], offset: int = 0, skipped: int = 0,
              shared: HashedFile | None = None) -> Iterator[T]:
    """``rows(reader)`` of a ``csv.reader`` on ``path`` (UTF-8, a byte-order mark allowed), from
    byte ``offset`` on (the start of the line after the first ``skipped``), with what goes wrong
    reading it as :class:`InputError` naming the file (and line); through ``shared`` where given
    (:class:`HashedFile`, left open)."""
    reader = None
    encoding = "utf-8" if offset else "utf-8-sig"
    try:
        if shared is not None:
            text = io.TextIOWrapper(shared.at(offset), encoding=encoding, newline="")
            try:
                reader = csv.reader(text)
                yield from rows(reader)
            finally:
                if not shared.file.closed:  # (a reader closed after its file)
                    text.detach()  # the shared file stays open
            return
        with open(path, "rb") as raw:
            raw.seek(offset)
            with io.TextIOWrapper(raw, encoding=encoding, newline="") as f:
                reader = csv.reader(f)
                yield from rows(reader)
    except UnicodeDecodeError as e:
        raise InputError(str(path), f"not a UTF-8 text CSV file ({e.reason} at byte {e.start + offset})"
                         ) from None
    except csv.Error as e:
        raise _malformed(path, reader, skipped, e) from None
    except OSError as e:
        raise InputError(str(path), f"cannot read ({e.strerror})") from None


def _malformed(path: Path, reader: LineCounted | None, skipped: int, e: csv.Error) -> InputError:
    """The error of a ``csv.reader`` (None: before it read) that found ``e`` after the first
    ``skipped`` lines of ``path``."""
    line = f": line {reader.line_num + skipped}" if reader is not None else ""
    return InputError(f"{path}{line}", f"malformed CSV ({e})")


def _headerless(path: Path, columns: tuple[str, ...], reader: CsvRows) -> Iterator[tuple[int, list[str]]]:
    """The rows of a CSV without a header (MOTChallenge): at least ``len(columns)`` fields, the
    same number in every row; blank lines skipped."""
    width = None
    for row in reader:
        line = reader.line_num
        if not row or all(not x.strip() for x in row):
            continue
        width = len(row) if width is None else width
        if len(row) < len(columns) or len(row) != width:
            want = width if len(row) >= len(columns) else len(columns)
            raise InputError(f"{path}: line {line}",
                             f"expected {want} fields ({','.join(columns)}, ...), got {len(row)}")
        yield line, row


def _checked_header(path: Path, columns: tuple[str, ...], warnings: list[str] | None, reader: CsvRows) -> int:
    """Reads the header, which must start with ``columns`` (more columns: a note in ``warnings``,
    an error when that is None); its width."""
    where = str(path)
    header = next(reader, None)
    if header is None or tuple(h.strip() for h in header[: len(columns)]) != columns:
        raise InputError(where, f"expected header {','.join(columns)}, got "
                                f"{','.join(header) if header else 'an empty file'}")
    extra = [h.strip() for h in header[len(columns):]]
    if extra:
        if warnings is None:
            raise InputError(where, f"unexpected columns {extra} after {','.join(columns)}")
        warnings.append(f"{path}: columns {', '.join(extra)} ignored")
    return len(header)


def _csv_records(path: Path, columns: tuple[str, ...], warnings: list[str] | None,
                 reader: CsvRows) -> Iterator[tuple[int, list[str]]]:
    """The rows after a header starting with ``columns`` (checked), as :func:`iter_csv_rows`
    reads them: (line number, fields), blank lines skipped, every row as wide as the header."""
    for lines, rows in _record_blocks(path, columns, warnings, reader, 1):
        yield lines[0], rows[0]
