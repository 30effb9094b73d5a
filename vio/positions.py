"""Known body positions (`--positions FILE`): a tripod ring, a turntable or GNSS, as GPS-like graph factors.

File: CSV with rows `t_s,x,y,z,sigma_m` (seconds in the capture's clock, world metres z up, 1-sigma metres);
lines starting with `#` and a leading header row are skipped.
"""

from __future__ import annotations

import math
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from vio.errors import CaptureError


def read_positions(path: str | Path) -> list[tuple[int, np.ndarray, float]]:
    """[(t_ns, p_world (3,) m, sigma_m)] in time order; a malformed row raises CaptureError naming it."""
    p = Path(path)
    try:
        lines = p.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise CaptureError("positions file not found", p) from None
    out: list[tuple[int, np.ndarray, float]] = []
    for row, line in enumerate(lines, start=1):
        s = line.strip()
        if not s or s.startswith("#") or (not out and s[0].isalpha()):
            continue
        fields = [f.strip() for f in s.replace("\t", ",").split(",")]
        if len(fields) != 5:
            raise CaptureError(f"expected 5 fields t_s,x,y,z,sigma_m, found {len(fields)}", p, row)
        try:
            t_ns = int(Decimal(fields[0]) * 1_000_000_000)
            x, y, z, sigma = (float(f) for f in fields[1:])
        except (InvalidOperation, ValueError):
            raise CaptureError(f"non-numeric field in {s[:60]!r}", p, row) from None
        if not all(math.isfinite(v) for v in (x, y, z, sigma)) or sigma <= 0:
            raise CaptureError("position must be finite and sigma_m positive", p, row)
        if out and t_ns <= out[-1][0]:
            raise CaptureError("times must increase", p, row)
        out.append((t_ns, np.array([x, y, z]), sigma))
    if not out:
        raise CaptureError("no positions", p)
    return out
