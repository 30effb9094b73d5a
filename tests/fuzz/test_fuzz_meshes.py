"""Hostile meshes for `vio compare` and `vio measure` (issue 20): each must end with exit 0 and a report, or one
`vio compare: error:` line; never a traceback or a hang, never a file written outside `--out`.

Each case states which of the two it must end with (`EXPECT`; "either" where both are defensible), and a model
that is compared despite a problem (NaN vertices left out, faces wound inside out) must say so in report.json's
`warnings`. The CAD gets its own hostile cases: a CAD is refused with one `CAD:` line, never repaired.
"""

from __future__ import annotations

import json
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

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
    vertices, faces = _box()
    if name == "far_away":  # 10 m from the CAD: registration must still find it (it is the same part)
        return stl_bytes(vertices + [1.0e4, -3.0e3, 2.0e3], faces, header="far away, mm")
    if name == "inverted_normals":
        return stl_bytes(vertices, faces[:, ::-1], header="inside out, mm")
    if name == "flat_sheet":  # the box squashed into its mid-plane
        return stl_bytes(vertices * [1.0, 1.0, 0.0], faces, header="flat, mm")
    if name == "ply_face_index_out_of_range":
        head = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        return (
            head + "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n"
        ).encode()
    if name.startswith("ply_") and name != "ply_billion_vertices":
        rng = np.random.default_rng(3)
        points = trimesh.Trimesh(vertices, faces).sample(2_000, seed=3) + rng.normal(0.0, 0.05, (2_000, 3))
        if name == "ply_one_point":
            points = points[:1]
        elif name == "ply_points_on_a_line":
            points = np.outer(np.linspace(-20.0, 20.0, 500), [1.0, 0.5, 0.2])
        elif name == "ply_nan_points":
            points[::7] = np.nan
        return trimesh.PointCloud(points).export(file_type="ply", encoding="ascii")
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


# How each hostile model must end: "error" (one line), "report" (exit 0), "either"; and what a report must warn of.
EXPECT = {
    "billion_triangle_header": "error",
    "empty": "error",
    "ascii_garbage": "error",
    "ply_billion_vertices": "error",
    "duplicated_faces": "either",
    "some_zero_area": "report",
    "all_zero_area": "error",
    "nan_vertices": "report",
    "huge_coordinate": "either",
    "far_away": "report",
    "inverted_normals": "report",
    "flat_sheet": "report",
    "ply_one_point": "error",
    "ply_points_on_a_line": "error",
    "ply_nan_points": "report",
    "ply_face_index_out_of_range": "error",
}
WARNS = {"nan_vertices": "non-finite", "ply_nan_points": "non-finite", "inverted_normals": "inside out"}
ERRORS = {
    "all_zero_area": "zero area",
    "ply_one_point": "1 finite points",
    "ply_points_on_a_line": "on a line",
    "ply_face_index_out_of_range": "face 0 refers to vertex 7 of 3",
}


def _no_constant(name: str) -> None:
    raise AssertionError(f"report.json holds {name}")


def _run(command: str, model: Path, cad: Path, out: Path) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "vio.cli", command, str(model), "--cad", str(cad), "--out", str(out)]
    return subprocess.run(
        [*cmd, "--units", "mm"] if model.suffix == ".ply" else cmd,
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=CASE_TIMEOUT_S,
        preexec_fn=_limit_memory,
    )


def _ended_cleanly(res: subprocess.CompletedProcess, command: str, expect: str) -> bool:
    """True for a report (exit 0), False for one error line (exit 2); fails on anything else."""
    assert "Traceback" not in res.stderr, res.stderr[-1500:]
    assert res.returncode in (0, 2), res.stderr[-1500:]
    assert expect in ("either", "report" if res.returncode == 0 else "error"), res.stderr[-1500:]
    if res.returncode == 2:
        assert res.stderr.strip().splitlines()[-1].startswith(f"vio {command}: error: "), res.stderr[-1500:]
    return res.returncode == 0


def _files(tmp_path: Path, name: str) -> tuple[Path, Path]:
    vertices, faces = _box()
    cad = tmp_path / "cad.stl"
    cad.write_bytes(stl_bytes(vertices, faces, header="box 40x30x20 mm"))
    model = tmp_path / f"model{'.ply' if name.startswith('ply') else '.stl'}"
    model.write_bytes(_mutate(name, cad.read_bytes()))
    return model, cad


@pytest.mark.parametrize("name", list(EXPECT))
def test_vio_compare_on_a_hostile_mesh(name, tmp_path):
    model, cad = _files(tmp_path, name)
    out = tmp_path / "out"
    before = _snapshot(tmp_path, out)
    res = _run("compare", model, cad, out)
    assert _snapshot(tmp_path, out) == before  # only --out written
    if not _ended_cleanly(res, "compare", EXPECT[name]):
        assert ERRORS.get(name, "") in res.stderr.strip().splitlines()[-1]
        assert not out.exists()  # nothing half-written
        return
    report = json.loads((out / "report.json").read_text(), parse_constant=_no_constant)  # no NaN or Infinity
    assert sorted(p.name for p in out.iterdir()) == report["files"]
    assert any(WARNS[name] in w for w in report["warnings"]) if name in WARNS else not report["warnings"]
    if name in ("far_away", "inverted_normals"):  # the same part: a perfect match, wherever and however wound
        assert report["deviation"]["rms_mm"] < 1e-3 and report["completeness"] > 0.99


@pytest.mark.parametrize(
    "name", ["all_zero_area", "nan_vertices", "inverted_normals", "ply_one_point", "ply_points_on_a_line"]
)
def test_vio_measure_on_a_hostile_mesh(name, tmp_path):
    model, cad = _files(tmp_path, name)
    out = tmp_path / "out"
    res = _run("measure", model, cad, out)
    if not _ended_cleanly(res, "measure", EXPECT[name]):
        assert ERRORS[name] in res.stderr.strip().splitlines()[-1] and not out.exists()
        return
    report = json.loads((out / "measure.json").read_text())
    assert any(WARNS[name] in w for w in report["warnings"])
    assert sorted(round(d["measured"], 2) for d in report["dimensions"]) == [20.0, 30.0, 40.0]


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("nan_vertices", "non-finite"),
        ("all_zero_area", "zero area"),
        ("empty", "not an STL"),
        ("ascii_garbage", "STL"),
        ("billion_triangle_header", "STL"),
        ("flat_sheet", "not watertight"),
    ],
)
def test_vio_compare_refuses_a_hostile_cad(name, message, tmp_path):
    vertices, faces = _box()
    model = tmp_path / "model.stl"
    model.write_bytes(stl_bytes(vertices, faces, header="box 40x30x20 mm"))
    cad = tmp_path / "cad.stl"
    cad.write_bytes(_mutate(name, model.read_bytes()))
    res = _run("compare", model, cad, tmp_path / "out")
    assert not _ended_cleanly(res, "compare", "error")
    line = res.stderr.strip().splitlines()[-1]
    assert line.startswith("vio compare: error: CAD: ") and message in line, line
    assert not (tmp_path / "out").exists()


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
