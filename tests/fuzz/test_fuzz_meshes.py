"""Hostile meshes for `vio compare` (issue 20): each must end with exit 0 and a report, or one `vio compare: error:`
line; never a traceback or a hang, never a file written outside `--out`.

The cases `vio compare` does not survive yet are marked xfail(strict) with what happens: the part-model stage
(vio/model/) owns the fix, and the marker goes when it lands.
"""

from __future__ import annotations

import json
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import ROOT
from tests.fuzz.run import _snapshot
from tests.fuzz.test_fuzz import _limit_memory
from vio.writers.mesh import stl_bytes

CASE_TIMEOUT_S = 120


def _box() -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    m = trimesh.creation.box(extents=(40.0, 30.0, 20.0))  # mm
    for _ in range(3):
        m = m.subdivide()
    return np.asarray(m.vertices), np.asarray(m.faces)


def _records(data: bytes) -> tuple[bytes, int]:
    return data[:84], struct.unpack("<I", data[80:84])[0]


def _mutate(name: str, good: bytes) -> bytes:
    head, n = _records(good)
    body = bytearray(good[84:])
    if name == "billion_triangle_header":
        return good[:80] + struct.pack("<I", 1_000_000_000) + good[84 : 84 + 50 * 3]
    if name == "empty":
        return b""
    if name == "ascii_garbage":
        return b"solid x\n facet normal 0 0 nan\n  outer loop\n   vertex a b c\n  endloop\n endfacet\nendsolid x\n"
    if name == "ply_billion_vertices":
        return b"ply\nformat ascii 1.0\nelement vertex 1000000000\nproperty float x\nend_header\n1\n"
    if name == "duplicated_faces":  # non-manifold: every edge shared by four faces
        return good[:80] + struct.pack("<I", 2 * n) + good[84:] + good[84:]
    if name in ("some_zero_area", "all_zero_area"):
        step = 10 if name == "some_zero_area" else 1
        for i in range(0, n, step):
            o = 50 * i
            body[o + 24 : o + 36] = body[o + 12 : o + 24]
            body[o + 36 : o + 48] = body[o + 12 : o + 24]
        return head + bytes(body)
    if name == "nan_vertices":
        for i in range(0, n, 3):
            body[50 * i + 12 : 50 * i + 16] = struct.pack("<f", float("nan"))
        return head + bytes(body)
    if name == "huge_coordinate":
        body[12:16] = struct.pack("<f", 3e38)
        return head + bytes(body)
    raise ValueError(name)


CASES = [
    "billion_triangle_header",
    "empty",
    "ascii_garbage",
    "ply_billion_vertices",
    "duplicated_faces",
    "some_zero_area",
    pytest.param(
        "all_zero_area", marks=pytest.mark.xfail(strict=True, reason="traceback: QhullError in register._frames")
    ),
    pytest.param(
        "nan_vertices",
        marks=pytest.mark.xfail(strict=True, reason="accepted without an error or a warning"),
    ),
    "huge_coordinate",
]


@pytest.mark.parametrize("name", CASES)
def test_vio_compare_on_a_hostile_mesh(name, tmp_path):
    vertices, faces = _box()
    cad = tmp_path / "cad.stl"
    cad.write_bytes(stl_bytes(vertices, faces, header="box 40x30x20 mm"))
    suffix = ".ply" if name.startswith("ply") else ".stl"
    model = tmp_path / f"model{suffix}"
    model.write_bytes(_mutate(name, cad.read_bytes()))
    out = tmp_path / "out"
    before = _snapshot(tmp_path, out)
    cmd = [sys.executable, "-m", "vio.cli", "compare", str(model), "--cad", str(cad), "--out", str(out)]
    res = subprocess.run(
        cmd, cwd=ROOT, capture_output=True, text=True, timeout=CASE_TIMEOUT_S, preexec_fn=_limit_memory
    )
    assert "Traceback" not in res.stderr, res.stderr[-1500:]
    assert res.returncode in (0, 2), res.stderr[-1500:]
    assert _snapshot(tmp_path, out) == before  # only --out written
    if res.returncode == 2:
        assert res.stderr.strip().splitlines()[-1].startswith("vio compare: error: ")
        return
    report = json.loads((out / "report.json").read_text())
    text = json.dumps(report)
    assert "NaN" not in text and "Infinity" not in text
    if name == "nan_vertices":  # a model with NaN coordinates must not pass for a perfect match
        pytest.fail("a model with NaN vertices was compared without an error or warning")


def test_a_model_path_that_is_a_symlink_loop_or_a_folder(tmp_path):
    loop = tmp_path / "loop.stl"
    loop.symlink_to(loop.name)
    vertices, faces = _box()
    cad = tmp_path / "cad.stl"
    cad.write_bytes(stl_bytes(vertices, faces))
    for model in (loop, tmp_path):
        cmd = [sys.executable, "-m", "vio.cli", "compare", str(model), "--cad", str(cad), "--out", str(tmp_path / "o")]
        res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=CASE_TIMEOUT_S)
        assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr[-1500:]
        assert res.stderr.strip().splitlines()[-1].startswith("vio compare: error: "), Path(model).name
