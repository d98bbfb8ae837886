"""The one reader of spectral tables in CSV form (camera sensitivities,
reflectances, light spectra): one row per wavelength, the wavelength in nm
first, one column per spectrum or channel.

Format: an optional header row of names (a first row with a non-numeric
field); separators ``,``, ``;`` or tab (decimal commas allowed with ``;``
and tab), else white space; blank lines and lines starting with ``#`` are
skipped. Every failure is an :class:`~recovery.errors.InputError` with code
``bad_csv`` naming the line and column at fault.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from .errors import InputError

__all__ = ["CsvTable", "read_csv_table", "MAX_CSV_ROWS", "MAX_CSV_VALUES"]

#: Rows a table may have (a spectrum has a few hundred).
MAX_CSV_ROWS = 100_000


@dataclass
class CsvTable:
    """``wavelengths`` (R,), ``values`` (R, K) and the header's fields (or None)."""

    wavelengths: np.ndarray
    values: np.ndarray
    header: list | None

    def names(self, default: str = "column") -> list:
        """The columns' names from the header, else ``"<default> k"``."""
        k = self.values.shape[1]
        if self.header and len(self.header) == k + 1:
            return [str(h) for h in self.header[1:]]
        return [f"{default} {i + 1}" for i in range(k)]


def _text(data, what: str) -> str:
    if isinstance(data, str):
        return data
    if not data:
        raise InputError(f"{what} is empty", code="bad_csv")
    try:
        return bytes(data).decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(f"{what} is not UTF-8 text (byte {exc.start}); send a plain CSV", code="bad_csv") from None


def _split(line: str) -> list[str]:
    """Fields of a CSV line: ``;`` or tab separated (then ``,`` is a decimal
    comma), else ``,``, else whitespace; surrounding double quotes removed."""
    for delim in (";", "\t"):
        if delim in line:
            return [_unquote(f).replace(",", ".") for f in line.split(delim)]
    if "," in line:
        return [_unquote(f) for f in line.split(",")]
    return [_unquote(f) for f in line.split()]


def _unquote(field: str) -> str:
    f = field.strip()
    return f[1:-1].strip() if len(f) >= 2 and f[0] == f[-1] == '"' else f


#: Values a table may hold unless the caller says otherwise (64 million, as
#: the service's ``WANDELL_MAX_RENDER_VALUES``).
MAX_CSV_VALUES = 64_000_000
#: Longest header row split into names (longer: default names).
_MAX_HEADER_FIELDS = 100_000
#: Values parsed per np.loadtxt call (2 MB of float64, ~50 ms).
_CHUNK_VALUES = 250_000
_NUMERIC_CHARS = re.compile(r'[^0-9eE+\-.,;\t "]')


def _delimiter(line: str) -> str | None:
    """The separator of a line, as :func:`_split` chooses it (``None``: white space)."""
    for delim in (";", "\t", ","):
        if delim in line:
            return delim
    return None


def _count_fields(line: str, delim: str | None) -> int:
    """Fields in ``line`` without splitting it (a 50 MB row would be 25
    million Python strings): a count of separators, or of white-space runs."""
    if delim is not None:
        return line.count(delim) + 1
    b = np.frombuffer(line.encode("utf-8"), np.uint8)
    space = (b == 32) | (b == 9)
    return int(np.count_nonzero(space[:-1] & ~space[1:])) + int(not space[0]) if b.size else 0


def _loadtxt(lines: list, delim: str | None) -> np.ndarray:
    if delim in (";", "\t"):
        lines = [ln.replace(",", ".") for ln in lines]       # decimal commas
    return np.loadtxt(lines, dtype=np.float64, delimiter=delim, comments=None, quotechar='"', ndmin=2)


def read_csv_table(data, what: str = "the CSV", *, finite: bool = True, max_rows: int = MAX_CSV_ROWS,
                   max_values: int = MAX_CSV_VALUES, min_rows: int = 1) -> CsvTable:
    """Parse a spectral table (see the module). ``finite``: NaN/Inf values
    are refused here (else left to the caller). Needs at least one numeric
    row (``min_rows``); every row as long as the first (or the header).

    The counts are checked before any value is parsed: lines (blank and
    comment lines included, at most ``4 * max_rows + 1000``), data rows
    (``max_rows``), rows times the first row's fields (``max_values``) and
    ``min_rows``, from a scan that splits no row into fields (codes
    ``bad_csv``, ``too_many_values``, ``too_few_rows``); the values are
    then read by numpy's C reader (``np.loadtxt``) into one float64 array, so
    the peak memory is the text, its lines and that array, never Python
    lists of every value.
    """
    text = _text(data, what)
    max_lines = 4 * max_rows + 1000
    if text.count("\n") > max_lines:
        raise InputError(f"{what}: more than {max_lines} lines (at most {max_rows} rows)", code="bad_csv")
    rows: list[str] = []
    linenos: list[int] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if s and not s.startswith("#"):
            rows.append(s)
            linenos.append(lineno)
    del text
    if not rows:
        raise InputError(f"{what} has no numeric rows", code="bad_csv")
    header = None
    first = rows[0]
    delim = _delimiter(first)
    # a header is a first row with a field that is not a number: a long row is
    # judged by its first 10,000 characters (its counts are not checked yet)
    probe = first if len(first) < 10_000 else first[:10_000].rsplit(delim, 1)[0]
    if len(first) < 10_000 or _NUMERIC_CHARS.search(probe) is not None:   # short, or letters (names, nan/inf)
        try:
            _loadtxt([probe], delim)
        except ValueError:
            n = _count_fields(first, delim)
            header = [_unquote(f) for f in first.split(delim)] if n <= _MAX_HEADER_FIELDS else []
            if delim in (";", "\t"):
                header = [f.replace(",", ".") for f in header]
            rows, linenos = rows[1:], linenos[1:]
    if not rows:
        raise InputError(f"{what} has no numeric rows", code="bad_csv")
    if len(rows) > max_rows:
        raise InputError(f"{what}: {len(rows)} rows, more than {max_rows}", code="bad_csv")
    delim = _delimiter(rows[0])
    ncols = _count_fields(rows[0], delim)
    if len(rows) * ncols > max_values:
        raise InputError(f"{what}: {len(rows)} rows of {ncols} values, more than {max_values} values",
                         code="too_many_values")
    if len(rows) < min_rows:
        err = InputError(f"{what} has {len(rows)} numeric row(s); at least {min_rows} are needed",
                         code="too_few_rows")
        err.rows = len(rows)
        raise err
    if header is not None and header and len(header) != ncols:
        raise InputError(f"line {linenos[0]} has {ncols} columns, expected {len(header)} (as the header)",
                         code="bad_csv")
    # parsed in chunks of about 250,000 values (numpy's reader holds the GIL:
    # ~50 ms each, so the event loop's thread keeps answering) into one
    # column-major array (spectra are its columns: ``values.T`` is
    # contiguous); a row wider than a chunk is read in pieces cut at its
    # separators; each chunk's lines are dropped once read, so the peak is
    # the array, the lines and a chunk
    arr = np.empty((len(rows), ncols), np.float64, order="F")
    where = "as the header" if header is not None else "as the first row"
    step = max(1, _CHUNK_VALUES // max(ncols, 1))
    for r0 in range(0, len(rows), step):
        chunk = rows[r0:r0 + step]
        try:
            if ncols <= _CHUNK_VALUES:
                part = _loadtxt(chunk, delim)
                if part.shape[1] != ncols:
                    raise InputError(f"line {linenos[r0]} has {part.shape[1]} columns, expected {ncols} ({where})",
                                     code="bad_csv")
                arr[r0:r0 + len(chunk)] = part
            else:
                _wide_row(chunk[0], delim, arr[r0], linenos[r0], where)
        except InputError:
            raise
        except ValueError as e:
            raise _located(str(e), chunk, linenos[r0:], delim, ncols, header is not None, what) from None
        if finite:
            block = arr[r0:r0 + len(chunk)]
            if not np.all(np.isfinite(block)):
                r, c = (int(v[0]) for v in np.nonzero(~np.isfinite(block)))
                field = _field(chunk[r], delim, c)
                raise InputError(f"line {linenos[r0 + r]}, column {c + 1}: {field!r} is NaN or Inf", code="bad_csv")
        rows[r0:r0 + step] = [None] * len(chunk)
        del chunk
    return CsvTable(arr[:, 0].copy(), arr[:, 1:], header if header else None)


def _wide_row(row: str, delim: str | None, out: np.ndarray, lineno: int, where: str) -> None:
    """One row of more than a chunk of values, into ``out``, in pieces of
    about 8 characters per chunk value cut at separators."""
    size, pos, col, n = _CHUNK_VALUES * 8, 0, 0, len(row)
    space = re.compile(r"\s")
    while pos < n:
        end = pos + size
        if end >= n:
            end = n
        else:
            m = row.find(delim, end) if delim is not None else (space.search(row, end) or None)
            end = n if m is None or m == -1 else (m if delim is not None else m.start())
        try:
            vals = _loadtxt([row[pos:end]], delim)[0]
        except ValueError as e:
            m = re.search(r"could not convert string '(.*)' to", str(e))
            raise InputError(f"line {lineno}: {m.group(1) if m else row[pos:pos + 20]!r} is not a number",
                             code="bad_csv") from None
        if col + vals.size > out.size:
            raise InputError(f"line {lineno} has more than {out.size} columns, expected {out.size} ({where})",
                             code="bad_csv")
        out[col:col + vals.size] = vals
        col += vals.size
        pos = end + 1
    if col != out.size:
        raise InputError(f"line {lineno} has {col} columns, expected {out.size} ({where})", code="bad_csv")


def _field(row: str, delim: str | None, col: int) -> str:
    """Field ``col`` (0-based) of one row, for a message."""
    parts = row.split(delim, col + 1) if delim else row.split(None, col + 1)
    return _unquote(parts[col]) if col < len(parts) else ""


def _located(msg: str, rows, linenos, delim, ncols, has_header, what) -> InputError:
    """numpy's parse error as this module's message (line and column in the file)."""
    m = re.search(r"could not convert string '(.*)' to \w+ at row (\d+), column (\d+)", msg)
    if m:
        r, c = int(m.group(2)), int(m.group(3))
        line = linenos[r] if r < len(linenos) else "?"
        return InputError(f"line {line}, column {c}: {_field(rows[r], delim, c - 1) if r < len(rows) else m.group(1)!r}"
                          " is not a number", code="bad_csv")
    m = re.search(r"number of columns changed from (\d+) to (\d+) at row (\d+)", msg)
    if m:
        r = int(m.group(3)) - 1
        line = linenos[r] if 0 <= r < len(linenos) else "?"
        return InputError(f"line {line} has {m.group(2)} columns, expected {m.group(1)} "
                          f"({'as the header' if has_header else 'as the first row'})", code="bad_csv")
    return InputError(f"{what}: {msg[:200]}", code="bad_csv")
