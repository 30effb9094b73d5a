"""Small, strict CSV parsing that names the file and row of every problem."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vio.errors import CaptureError


def read_numeric_csv(path: Path, ncols: int, int_first: bool = True) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Read a headered CSV of numbers: returns (first column as int64, the rest as float64, source row numbers).

    Lines starting with '#' or a letter are treated as headers only before the first data row. A row with the
    wrong column count or a non-numeric field raises CaptureError naming the file and (1-based) row.
    """
    try:
        text = Path(path).read_text(encoding="utf-8", errors="strict")
    except FileNotFoundError:
        raise CaptureError("file not found", path) from None
    except UnicodeDecodeError:
        raise CaptureError("not a text file", path) from None
    first: list[int] = []
    rest: list[list[float]] = []
    rows: list[int] = []
    seen_data = False
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#") or (not seen_data and s[0].isalpha()):
            continue
        fields = [f.strip() for f in s.split(",")]
        if len(fields) != ncols:
            raise CaptureError(f"expected {ncols} columns, found {len(fields)}", path, lineno)
        try:
            t = int(fields[0]) if int_first else float(fields[0])
            vals = [float(f) for f in fields[1:]]
        except ValueError:
            raise CaptureError(f"non-numeric field in {line.strip()[:60]!r}", path, lineno) from None
        seen_data = True
        first.append(t)
        rest.append(vals)
        rows.append(lineno)
    t_arr = np.asarray(first, dtype=np.int64 if int_first else np.float64)
    v_arr = np.asarray(rest, dtype=np.float64).reshape(len(rest), ncols - 1)
    return t_arr, v_arr, rows
