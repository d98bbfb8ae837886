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

import math
from dataclasses import dataclass

import numpy as np

from .errors import InputError

__all__ = ["CsvTable", "read_csv_table", "MAX_CSV_ROWS"]

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


def read_csv_table(data, what: str = "the CSV", *, finite: bool = True, max_rows: int = MAX_CSV_ROWS) -> CsvTable:
    """Parse a spectral table (see the module). ``finite``: NaN/Inf values
    are refused here (else left to the caller). Needs at least one numeric
    row; every row as long as the first (or the header)."""
    text = _text(data, what)
    header = None
    rows: list[list[float]] = []
    ncols = None
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        fields = _split(s)
        values = []
        bad = None
        for col, f in enumerate(fields, start=1):
            try:
                values.append(float(f))
            except ValueError:
                bad = (col, f)
                break
        if bad is not None:
            if header is None and not rows:
                header = fields
                ncols = len(fields)
                continue
            raise InputError(f"line {lineno}, column {bad[0]}: {bad[1]!r} is not a number", code="bad_csv")
        if ncols is None:
            ncols = len(values)
        if len(values) != ncols:
            raise InputError(f"line {lineno} has {len(values)} columns, expected {ncols} "
                             f"({'as the header' if header else 'as the first row'})", code="bad_csv")
        if finite and not all(math.isfinite(v) for v in values):
            col = next(i for i, v in enumerate(values, 1) if not math.isfinite(v))
            raise InputError(f"line {lineno}, column {col}: {fields[col - 1]!r} is NaN or Inf", code="bad_csv")
        rows.append(values)
        if len(rows) > max_rows:
            raise InputError(f"more than {max_rows} rows", code="bad_csv")
    if not rows:
        raise InputError(f"{what} has no numeric rows", code="bad_csv")
    arr = np.asarray(rows, dtype=np.float64)
    return CsvTable(arr[:, 0].copy(), arr[:, 1:], header)
