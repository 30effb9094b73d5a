"""CSV tables: the one place where text rows of sensor logs, ground truth and trajectories become numbers.

Every reader of a delimited text file goes through here, so every problem names the file and the 1-based row the
same way. Blank lines and lines starting with `#` are skipped; a timestamp is parsed exactly into integer ns.
Two policies:
- `read_table`, for sensor logs (DESIGN.md "Bad input"), is tolerant where going on is safe:
  - a last row cut off mid-write (no final newline) is dropped with a warning;
  - a few garbage rows (non-numeric or too few fields, at most 1% of the rows) are dropped with a warning naming
    the first; more than that is a CaptureError naming the first bad row;
  - rows with NaN/inf values are dropped with a warning;
  - a timestamp going backwards is a CaptureError naming the row; repeated timestamps are dropped with a warning
    (`ensure_increasing`).
- `strict_rows` / `read_strict_table`, for files with a fixed layout (ground truth, trajectories, known positions,
  image lists): lines starting with a letter before the first data row are headers; the first row with the wrong
  field count or an unreadable field is a CaptureError naming it. NaN values are left to the caller.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass
from decimal import ROUND_HALF_UP, Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from vio.errors import CaptureError

log = logging.getLogger(__name__)

MAX_GARBAGE_FRACTION = 0.01
NS_PER_S = 1_000_000_000


@dataclass(frozen=True)
class Table:
    """Numeric rows of one CSV file: integer time (ns) plus float value columns, with their source rows."""

    path: Path
    header: list[str] | None  # column names of the header line, if the file has one
    t_ns: np.ndarray  # (N,) int64, ns
    values: np.ndarray  # (N, K) float64, the selected value columns in the order asked for
    rows: np.ndarray  # (N,) int64, 1-based line numbers in the file

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    def select(self, keep: np.ndarray | slice) -> Table:
        return Table(self.path, self.header, self.t_ns[keep], self.values[keep], self.rows[keep])


def parse_time_ns(text: str, unit_ns: int = 1, *, integer: bool = False) -> int:
    """A timestamp in units of `unit_ns` ns (1: ns, 10**9: s) as exact integer ns; raises ValueError.

    Decimal digits are exact (no float on the way); below 1 ns they round half away from zero. With `integer`
    only an integer literal is accepted (nanosecond columns of files that carry exact times).
    """
    s = text.strip()
    try:
        if integer or (unit_ns == 1 and s.isdigit()):
            t = int(s) * unit_ns
        else:
            t = int((Decimal(s) * unit_ns).to_integral_value(rounding=ROUND_HALF_UP))
    except (InvalidOperation, ValueError, ArithmeticError):
        raise ValueError(f"timestamp {s[:30]!r} is not a number") from None
    if not -(2**63) < t < 2**63:
        raise ValueError(f"timestamp {s[:30]!r} is out of range")
    return t


def read_lines(path: Path) -> tuple[list[str], bool]:
    """The file's lines and whether it ends with a newline (False means the last row may be truncated)."""
    try:
        raw = Path(path).read_bytes()
    except FileNotFoundError:
        raise CaptureError("file not found", path) from None
    except IsADirectoryError:
        raise CaptureError("expected a file, found a folder", path) from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise CaptureError("not a text file (cannot decode as UTF-8)", path) from None
    return text.splitlines(), text.endswith(("\n", "\r"))


def data_lines(path: Path) -> tuple[list[tuple[int, str]], bool]:
    """(1-based line number, stripped text) of every line that is neither blank nor a `#` comment, and whether the
    file ends with a newline."""
    lines, ends_with_newline = read_lines(path)
    return [(n, s.strip()) for n, s in enumerate(lines, start=1) if s.strip() and not s.lstrip().startswith("#")], (
        ends_with_newline
    )


def split_fields(line: str, sep: str | None = ",") -> list[str]:
    """The stripped fields of a line, split at any one character of `sep` (None: at runs of whitespace)."""
    if sep is None:
        return line.split()
    parts = line.split(sep) if len(sep) == 1 else re.split(f"[{re.escape(sep)}]", line)
    return [f.strip() for f in parts]


def strict_rows(
    path: Path,
    ncols: int,
    what: str,
    layout: str,
    *,
    unit_ns: int = 1,
    at_least: bool = False,
    sep: str | None = ",",
    lines: list[tuple[int, str]] | None = None,
) -> Iterator[tuple[int, str, int, list[str]]]:
    """(line number, line, time ns, the next `ncols - 1` fields) of each data row of a fixed-layout file, in order.

    The time is the first field, in units of `unit_ns` (1: integer ns, 10**9: decimal s). A row with other than
    `ncols` fields (fewer than `ncols` when `at_least`) or an unreadable time raises CaptureError naming it, e.g.
    `<what> row needs 8 fields '<layout>', found 7`. `lines` are the file's `data_lines` when already read.
    """
    path = Path(path)
    if lines is None:
        lines = data_lines(path)[0]
    seen_data = False
    for lineno, s in lines:
        if not seen_data and s[0].isalpha():
            continue  # a header without '#'
        fields = split_fields(s, sep)
        if (len(fields) < ncols) if at_least else (len(fields) != ncols):
            need = f">= {ncols}" if at_least else f"{ncols}"
            raise CaptureError(f"{what} row needs {need} fields '{layout}', found {len(fields)}", path, lineno)
        try:
            t_ns = parse_time_ns(fields[0], unit_ns, integer=unit_ns == 1)
        except ValueError:
            kind = "an integer (ns)" if unit_ns == 1 else "a number (s)"
            raise CaptureError(f"timestamp {fields[0][:30]!r} is not {kind}", path, lineno) from None
        seen_data = True
        yield lineno, s, t_ns, fields[1:ncols]


def read_strict_table(path: Path, ncols: int, what: str, layout: str, **kwargs) -> Table:
    """A fixed-layout file of `time, value...` rows (see `strict_rows` for the arguments) as a Table of
    `ncols - 1` float columns; a non-numeric value raises CaptureError naming the row."""
    path = Path(path)
    t_list: list[int] = []
    v_list: list[list[float]] = []
    r_list: list[int] = []
    for lineno, s, t_ns, fields in strict_rows(path, ncols, what, layout, **kwargs):
        try:
            v_list.append([float(f) for f in fields])
        except ValueError:
            raise CaptureError(f"non-numeric field in {s[:60]!r}", path, lineno) from None
        t_list.append(t_ns)
        r_list.append(lineno)
    t_arr = np.asarray(t_list, dtype=np.int64)
    v_arr = np.asarray(v_list, dtype=np.float64).reshape(len(v_list), ncols - 1)
    return Table(path, None, t_arr, v_arr, np.asarray(r_list, dtype=np.int64))


def _is_header(fields: list[str]) -> bool:
    for f in fields:
        try:
            float(f)
        except ValueError:
            if f:
                return True
    return False


def read_table(
    path: Path,
    time_col: int | str,
    value_cols: list[int] | list[str],
    *,
    time_scale: int = 1,
    warnings: list[str] | None = None,
    what: str = "sample",
) -> Table:
    """Read a sensor log with a time column (ns unless `time_scale` says otherwise) and float value columns.

    Columns are given by index, or by header name (then the file must have a header naming them). Fields are
    separated by commas, or by whitespace in a line without commas.
    """
    path = Path(path)
    data, ends_with_newline = data_lines(path)
    warn = warnings if warnings is not None else []
    header: list[str] | None = None
    idx_t: int | None = time_col if isinstance(time_col, int) else None
    idx_v: list[int] | None = [int(c) for c in value_cols] if all(isinstance(c, int) for c in value_cols) else None
    t_list: list[int] = []
    v_list: list[list[float]] = []
    r_list: list[int] = []
    garbage: list[tuple[int, str]] = []
    nonfinite: list[int] = []
    for k, (lineno, s) in enumerate(data):
        fields = [f.strip('"') for f in split_fields(s, "," if "," in s else None)]
        if header is None and not t_list and not garbage and _is_header(fields):
            header = fields
            if idx_t is None or idx_v is None:
                names = [h.lower() for h in header]
                try:
                    idx_t = names.index(str(time_col).lower()) if idx_t is None else idx_t
                    idx_v = [names.index(str(c).lower()) for c in value_cols] if idx_v is None else idx_v
                except ValueError:
                    want = [str(time_col), *(str(c) for c in value_cols)]
                    raise CaptureError(f"header lacks column(s) {want} (found {header})", path, lineno) from None
            continue
        if idx_t is None or idx_v is None:
            raise CaptureError("expected a header line naming the columns", path, lineno)
        need = max([idx_t, *idx_v]) + 1
        problem = f"expected at least {need} fields, found {len(fields)}" if len(fields) < need else None
        if problem is None:
            try:
                t = parse_time_ns(fields[idx_t], time_scale)
                vals = [float(fields[i]) for i in idx_v]
            except ValueError:
                problem = f"non-numeric field in {s[:50]!r}"
        if problem is not None:
            if k == len(data) - 1 and not ends_with_newline:
                warn.append(f"{path}:{lineno}: last row is truncated (file cut off mid-write); dropped")
                log.warning(warn[-1])
            else:
                garbage.append((lineno, problem))
            continue
        if not all(map(math.isfinite, vals)):
            nonfinite.append(lineno)
            continue
        t_list.append(t)
        v_list.append(vals)
        r_list.append(lineno)
    n_total = len(t_list) + len(garbage) + len(nonfinite)
    if garbage:
        first_row, problem = garbage[0]
        if len(garbage) > max(1, MAX_GARBAGE_FRACTION * n_total) or len(t_list) < 2:
            raise CaptureError(f"{problem} ({len(garbage)} bad row(s) of {n_total})", path, first_row)
        warn.append(f"{path}:{first_row}: {len(garbage)} garbage {what} row(s) dropped (first here: {problem})")
        log.warning(warn[-1])
    if nonfinite:
        warn.append(f"{path}:{nonfinite[0]}: {len(nonfinite)} {what} row(s) with NaN/inf dropped (first here)")
        log.warning(warn[-1])
    t_arr = np.asarray(t_list, dtype=np.int64)
    v_arr = np.asarray(v_list, dtype=np.float64).reshape(len(v_list), len(value_cols))
    return Table(path, header, t_arr, v_arr, np.asarray(r_list, dtype=np.int64))


def increasing_mask(table: Table, what: str, warnings: list[str] | None = None) -> np.ndarray:
    """Keep-mask of a table's rows: a timestamp going backwards is an error naming the row; exact repeats are
    dropped (False) with a warning naming the first."""
    d = np.diff(table.t_ns)
    back = np.flatnonzero(d < 0)
    if back.size:
        i = int(back[0]) + 1
        raise CaptureError(
            f"{what} timestamp goes backwards ({table.t_ns[i]} after {table.t_ns[i - 1]})",
            table.path,
            int(table.rows[i]),
        )
    keep = np.ones(len(table), bool)
    keep[1:] = d != 0
    if not keep.all():
        first = int(table.rows[np.flatnonzero(~keep)[0]])
        msg = f"{table.path}:{first}: {int((~keep).sum())} repeated {what} timestamp(s) dropped (first here)"
        log.warning(msg)
        if warnings is not None:
            warnings.append(msg)
    return keep


def ensure_increasing(table: Table, what: str, warnings: list[str] | None = None) -> Table:
    """The table with strictly increasing times (see `increasing_mask`)."""
    keep = increasing_mask(table, what, warnings)
    return table if keep.all() else table.select(keep)
