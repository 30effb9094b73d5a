"""Mutations of a capture folder, each one hostile input a user's file system can hold.

A mutation is `(op, pick, a, b)`: `op` names it, `pick` chooses the file (an index into the capture's sorted files,
modulo their number, or a relative path), `a` in [0, 1) and `b` (an int) choose where and what. Every mutation is
deterministic in its arguments, so a case is replayed exactly from its record (the checked-in corpus is such records).
"""

from __future__ import annotations

import os
import re
import struct
from pathlib import Path

import numpy as np

TEXT_SUFFIXES = (".csv", ".txt", ".yaml")
BAD_NUMBERS = ("nan", "inf", "-inf", "1e308", "-1e308", "99999999999999999999999999", "", "0x1F", "1,5")
UNIT_FACTORS = (9.81, 1 / 9.81, 180 / np.pi, np.pi / 180, 1e3, 1e-3, -1.0)
FAR_FUTURE_NS = ("4102444800000000000", "9223372036854775807", "18446744073709551616", "-1")
OPS = (
    "truncate",
    "empty",
    "flip_bytes",
    "huge_int",
    "remove",
    "bad_number",
    "drop_row",
    "repeat_row",
    "reverse_rows",
    "swap_columns",
    "far_future",
    "scale_columns",
    "python_yaml",
    "symlink_loop",
    "outside_name",
    "huge_png",
)
CANARY = "CANARY"  # a file the hostile YAML tries to create next to the case folder: it must never appear


def files_of(root: Path) -> list[Path]:
    """The capture's regular files (symlinks not followed), sorted."""
    out = []
    for dirpath, _, names in os.walk(root):
        out += [Path(dirpath) / n for n in names if not (Path(dirpath) / n).is_symlink()]
    return sorted(out)


def _rewrite(path: Path, data: bytes) -> None:
    path.unlink()  # a new file: the seeds are hard-linked into the case folder
    path.write_bytes(data)


def _lines(path: Path) -> list[str] | None:
    if path.suffix.lower() not in TEXT_SUFFIXES:
        return None
    try:
        return path.read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError:
        return None


def _write_lines(path: Path, lines: list[str]) -> None:
    _rewrite(path, ("\n".join(lines) + "\n").encode())


def _data_rows(lines: list[str]) -> list[int]:
    """Indices of the lines that hold data (not headers or comments)."""
    return [i for i, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith(("#", "%")) and ln[0] != "t"]


def apply(root: Path, op: str, pick: int | str, a: float, b: int) -> None:
    """Apply one mutation to the capture under `root` (a no-op when it does not fit the file picked). `pick` is an
    index into the sorted files, or a path relative to `root` (the corpus names its files)."""
    files = files_of(root)
    if not files:
        return
    path = root / pick if isinstance(pick, str) else files[pick % len(files)]
    if not path.is_file() or path.is_symlink():
        return
    data = path.read_bytes()
    rng = np.random.default_rng(b)
    if op == "truncate":
        _rewrite(path, data[: int(a * len(data))])
    elif op == "empty":
        _rewrite(path, b"")
    elif op == "flip_bytes":
        buf = bytearray(data)
        for i in rng.integers(0, max(len(buf), 1), size=1 + b % 16):
            if buf:
                buf[int(i)] ^= int(rng.integers(1, 256))
        _rewrite(path, bytes(buf))
    elif op == "huge_int":  # a length or size field gone wrong (bag message length, PNG chunk length...)
        at = int(a * max(len(data) - 4, 0)) if b < 16 else min(b, max(len(data) - 4, 0))  # b >= 16: at byte b
        _rewrite(path, data[:at] + struct.pack("<I", 0xFFFFFFF0 - b % 16) + data[at + 4 :])
    elif op == "remove":
        path.unlink()
    elif op == "python_yaml":
        yamls = [f for f in files if f.suffix == ".yaml"] or [path]
        target = path if path.suffix == ".yaml" else yamls[(pick if isinstance(pick, int) else 0) % len(yamls)]
        canary = root.parent / CANARY
        _rewrite(target, f'cam0: !!python/object/apply:os.system ["touch {canary}"]\n'.encode())
    elif op == "symlink_loop":
        target = path if b % 2 == 0 else path.parent
        if target == root:
            target = path
        if target.is_dir():
            import shutil

            shutil.rmtree(target)
        else:
            target.unlink()
        target.symlink_to(target.name)  # points to itself: ELOOP on open
    elif op == "huge_png":
        if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 24:
            w = h = 0x7FFFFFFF if b % 2 else 60000
            _rewrite(path, data[:16] + struct.pack(">II", w, h) + data[24:])
    else:
        _text_op(root, path, op, a, b)


def _text_op(root: Path, path: Path, op: str, a: float, b: int) -> None:
    lines = _lines(path)
    if lines is None:
        return
    rows = _data_rows(lines)
    if not rows:
        return
    r = rows[int(a * len(rows))]
    sep = "," if "," in lines[r] else " "
    fields = lines[r].split(sep)
    col = b % 16 % len(fields)
    if op == "bad_number":
        fields[col] = BAD_NUMBERS[b % len(BAD_NUMBERS)]
        lines[r] = sep.join(fields)
    elif op == "drop_row":
        del lines[r]
    elif op == "repeat_row":
        lines[r:r] = [lines[r]] * (1 + b % 3)
    elif op == "reverse_rows":
        lines[rows[0] : rows[-1] + 1] = lines[rows[0] : rows[-1] + 1][::-1]
    elif op == "swap_columns":
        c2 = (col + 1 + b // 7) % len(fields)
        for i in rows:
            f = lines[i].split(sep)
            if len(f) > max(col, c2):
                f[col], f[c2] = f[c2], f[col]
                lines[i] = sep.join(f)
    elif op == "far_future":  # the row's timestamp (its longest integer field) far in the future or out of range
        stamps = [i for i, f in enumerate(fields) if re.fullmatch(r"-?\d{9,}", f.strip())]
        t = stamps[0] if stamps else col
        fields[t] = FAR_FUTURE_NS[b % len(FAR_FUTURE_NS)]
        lines[r] = sep.join(fields)
    elif op == "scale_columns":  # a unit mistake: three columns (a sensor's axes) from `col` scaled
        factor = UNIT_FACTORS[(b // 16) % len(UNIT_FACTORS)]
        for i in rows:
            f = lines[i].split(sep)
            for c in range(col, min(col + 3, len(f))):
                try:
                    f[c] = repr(float(f[c]) * factor)
                except ValueError:
                    continue
            lines[i] = sep.join(f)
    elif op == "outside_name":  # an image name that points outside the capture folder
        outside = ["../../../../../../../../etc/passwd", str(root.parent / "outside.png"), "/dev/zero", "../" * 3]
        fields[-1] = outside[b % len(outside)]
        lines[r] = sep.join(fields)
    else:
        raise ValueError(f"unknown mutation {op!r}")
    _write_lines(path, lines)
