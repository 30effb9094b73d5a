"""The stereo-and-fusion oracle's region: the part's own box from the capture's CAD and pose."""

from __future__ import annotations

import numpy as np

from vio.bench.fusion_truth import part_roi
from vio.sim.parts import build_part, write_stl


def test_part_roi_is_the_cad_box_grown_sideways_and_up_not_below_the_base(tmp_path):
    part = build_part("cube")
    scene = tmp_path / "scene"
    scene.mkdir()
    write_stl(scene / "cad.stl", part.vertices_mm, part.faces, "cube, mm")
    pose = np.eye(4)
    pose[:3, 3] = [0.1, -0.2, 0.75]
    (scene / "part_pose.yaml").write_text("world_T_part:\n" + "".join(f"- {row.tolist()}\n" for row in pose))
    roi = part_roi(tmp_path, 0.01)
    np.testing.assert_allclose(roi.world_T_support, pose)
    np.testing.assert_allclose(roi.lo, [-0.0481, -0.0481, 0.0], atol=1e-6)
    np.testing.assert_allclose(roi.hi, [0.0481, 0.0481, 0.0862], atol=1e-6)
