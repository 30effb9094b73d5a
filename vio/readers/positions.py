"""Known body positions (`--positions FILE`): a tripod ring, a turntable or GNSS, as GPS-like graph factors.

File: CSV with rows `t_s,x,y,z,sigma_m` (seconds in the capture's clock, world metres z up, 1-sigma metres), fields
separated by commas or tabs; lines starting with `#` and a leading header row are skipped. Parsed by
`vio.readers.tables` (times exact to 1 ns).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vio.errors import CaptureError
from vio.readers.tables import NS_PER_S, read_strict_table


def read_positions(path: str | Path) -> list[tuple[int, np.ndarray, float]]:
    """[(t_ns, p_world (3,) m, sigma_m)] in time order; a malformed row raises CaptureError naming it."""
    p = Path(path)
    table = read_strict_table(p, 5, "positions", "t_s,x,y,z,sigma_m", unit_ns=NS_PER_S, sep=",\t")
    out: list[tuple[int, np.ndarray, float]] = []
    for t_ns, v, row in zip(table.t_ns.tolist(), table.values, table.rows.tolist(), strict=True):
        if not np.isfinite(v).all() or v[3] <= 0:
            raise CaptureError("position must be finite and sigma_m positive", p, row)
        if out and t_ns <= out[-1][0]:
            raise CaptureError("times must increase", p, row)
        out.append((t_ns, v[:3].copy(), float(v[3])))
    if not out:
        raise CaptureError("no positions", p)
    return out
