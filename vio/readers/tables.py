"""Tolerant, strict-where-it-matters CSV tables for sensor logs: every problem names the file and the row.

Policy (DESIGN.md "Bad input"):
- a last row cut off mid-write (no final newline) is dropped with a warning;
- a few garbage rows (non-numeric or too few fields, at most 1% of the rows) are dropped with a warning naming the
  first; more than that is a CaptureError naming the first bad row;
- rows with NaN/inf values are dropped with a warning;
- a timestamp going backwards is a CaptureError naming the row; repeated timestamps are dropped with a warning.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from vio.errors import CaptureError

log = logging.getLogger(__name__)

MAX_GARBAGE_FRACTION = 0.01


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

    def select(self, keep: np.ndarray) -> Table:
        return Table(self.path, self.header, self.t_ns[keep], self.values[keep], self.rows[keep])


def _parse_time(text: str, scale: int) -> int:
    """Parse a timestamp in a unit of `scale` ns (1: ns, 10**9: s) exactly into integer ns."""
    try:
        t = int(text) if scale == 1 and text.isdigit() else int(Decimal(text) * scale)
    except (InvalidOperation, ValueError, ArithmeticError):
        raise ValueError(text) from None
    if not -(2**63) < t < 2**63:
        raise ValueError(text)
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
    """Read a CSV with a time column (ns unless `time_scale` says otherwise) and float value columns.

    Columns are given by index, or by header name (then the file must have a header naming them).
    """
    path = Path(path)
    lines, ends_with_newline = read_lines(path)
    warn = warnings if warnings is not None else []
    header: list[str] | None = None
    idx_t: int | None = time_col if isinstance(time_col, int) else None
    idx_v: list[int] | None = [int(c) for c in value_cols] if all(isinstance(c, int) for c in value_cols) else None
    t_list: list[int] = []
    v_list: list[list[float]] = []
    r_list: list[int] = []
    garbage: list[tuple[int, str]] = []
    nonfinite: list[int] = []
    data_lines = [(n, s.strip()) for n, s in enumerate(lines, start=1) if s.strip() and not s.lstrip().startswith("#")]
    for k, (lineno, s) in enumerate(data_lines):
        fields = [f.strip().strip('"') for f in (s.split(",") if "," in s else s.split())]
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
        try:
            if len(fields) < need:
                raise ValueError(f"expected at least {need} fields, found {len(fields)}")
            t = _parse_time(fields[idx_t], time_scale)
            vals = [float(fields[i]) for i in idx_v]
        except ValueError as exc:
            last = k == len(data_lines) - 1
            if last and not ends_with_newline:
                warn.append(f"{path}:{lineno}: last row is truncated (file cut off mid-write); dropped")
                log.warning(warn[-1])
                continue
            garbage.append((lineno, str(exc) if "fields" in str(exc) else f"non-numeric field in {s[:50]!r}"))
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


def ensure_increasing(table: Table, what: str, warnings: list[str] | None = None) -> Table:
    """Backwards timestamps are an error naming the row; exact repeats are dropped with a warning."""
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
        return table.select(keep)
    return table
