"""Property tests: whatever garbage or truncation hits a log, a reader gives a CaptureError or a valid capture."""

from __future__ import annotations

import shutil
import uuid
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from tests.rotation_capture import rotation_capture
from tests.writers.phone import write_mars
from vio.errors import VioError
from vio.readers import open_capture
from vio.readers.tables import ensure_increasing, read_table
from vio.writers.asl import AslWriter

PROFILE = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.fixture(scope="module")
def master(tmp_path_factory):
    src = rotation_capture(duration_s=1.0, fps=10.0)
    base = tmp_path_factory.mktemp("prop")
    with AslWriter(base / "asl") as w:
        w.write_camera(src.camera)
        w.write_imu(src.imu_calib, src.imu)
        for i in range(src.num_frames):
            w.add_frame(int(src.frame_t_ns[i]), src.load_image(i))
    write_mars(src, base / "mars")
    return base


def _check_valid(cap) -> None:
    imu = cap.imu
    assert imu is not None and len(imu) >= 2
    assert np.all(np.diff(imu.t_ns) > 0)
    assert np.isfinite(imu.gyro).all() and np.isfinite(imu.acc).all()
    assert imu.gyro.shape == imu.acc.shape == (len(imu), 3)
    assert cap.num_frames > 0 and np.all(np.diff(cap.frame_t_ns) > 0)
    assert cap.frame_t_ns[0] >= imu.t_ns[0] and cap.frame_t_ns[-1] <= imu.t_ns[-1]
    assert all(isinstance(w, str) and "\n" not in w for w in cap.warnings)


mutation = st.one_of(
    st.tuples(st.just("truncate"), st.floats(0.0, 1.0)),
    st.tuples(st.just("delete"), st.floats(0.0, 1.0), st.integers(1, 400)),
    st.tuples(st.just("insert"), st.floats(0.0, 1.0), st.text(alphabet="0123456789,.-enaNx \n#", max_size=40)),
    st.tuples(st.just("swap"), st.floats(0.0, 1.0), st.floats(0.0, 1.0)),
    st.tuples(st.just("dup"), st.floats(0.0, 1.0)),
)


def _mutate(text: str, ops: list[tuple]) -> str:
    for op in ops:
        n = len(text)
        if op[0] == "truncate":
            text = text[: int(op[1] * n)]
        elif op[0] == "delete":
            i = int(op[1] * n)
            text = text[:i] + text[i + op[2] :]
        elif op[0] == "insert":
            i = int(op[1] * n)
            text = text[:i] + op[2] + text[i:]
        else:
            lines = text.split("\n")
            i = int(op[1] * (len(lines) - 1))
            if op[0] == "swap":
                j = int(op[2] * (len(lines) - 1))
                lines[i], lines[j] = lines[j], lines[i]
            else:
                lines.insert(i, lines[i])
            text = "\n".join(lines)
    return text


def _open_mutated(root: Path, p: Path, ops) -> None:
    """Mutate file `p` of the capture at `root`; opening must give one-line VioError or a valid capture."""
    p.write_text(_mutate(p.read_text(), ops))
    try:
        cap = open_capture(root)
    except VioError as exc:
        assert "\n" not in str(exc)
        event(f"error: {type(exc).__name__}")
        return
    event("valid capture" + (" with warnings" if cap.warnings else ""))
    _check_valid(cap)


@PROFILE
@given(ops=st.lists(mutation, min_size=1, max_size=4))
def test_mutated_asl_imu_gives_error_or_valid_capture(master, tmp_path, ops):
    root = Path(tmp_path) / f"asl-{uuid.uuid4().hex}"
    shutil.copytree(master / "asl", root)
    _open_mutated(root, root / "mav0" / "imu0" / "data.csv", ops)


@PROFILE
@given(
    ops=st.lists(mutation, min_size=1, max_size=4), which=st.sampled_from(["gyro_accel.csv", "frame_timestamps.txt"])
)
def test_mutated_mars_logs_give_error_or_valid_capture(master, tmp_path, ops, which):
    root = Path(tmp_path) / f"mars-{uuid.uuid4().hex}"
    shutil.copytree(master / "mars", root)
    _open_mutated(root, root / which, ops)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(text=st.text(alphabet="0123456789,.-+eE naNif#\n", max_size=300))
def test_random_text_tables_are_error_or_clean(tmp_path, text):
    p = Path(tmp_path) / "t.csv"
    p.write_text(text)
    try:
        t = ensure_increasing(read_table(p, 0, [1, 2]), "sample")
    except VioError as exc:
        assert str(exc).startswith(str(p)) and "\n" not in str(exc)
        return
    assert t.values.shape == (len(t), 2) and np.isfinite(t.values).all()
    assert np.all(np.diff(t.t_ns) > 0)
