"""The output writers: depth maps (.npy and 16-bit PNG in 0.1 mm) and PLY point clouds and meshes."""
import cv2
import numpy as np
import trimesh

from slwarp.evaluation.outputs import write_depth, write_mesh_ply, write_points_ply
from slwarp.scans.scan import read_depth


def test_write_depth_npy_and_png(tmp_path):
    d = np.array([[523.46, np.nan], [-3.0, 7000.0]], np.float32)
    write_depth(tmp_path, d)
    np.testing.assert_array_equal(np.load(tmp_path / "depth.npy"), d)
    png = cv2.imread(str(tmp_path / "depth.png"), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint16 and png.tolist() == [[5235, 0], [0, 65535]]  # 0.1 mm counts, 0 invalid, clipped
    back = read_depth(tmp_path / "depth.png")
    assert back[0, 0] == np.float32(523.5) and np.isnan(back[0, 1]) and np.isnan(back[1, 0])


def test_points_without_colours_and_meshes(tmp_path):
    pts = np.array([[0.0, 1.0, 500.0], [np.nan, 0.0, 0.0], [2.0, 3.0, 4.0]])
    assert write_points_ply(tmp_path / "p.ply", pts) == 2
    cloud = trimesh.load(tmp_path / "p.ply")
    np.testing.assert_array_equal(np.asarray(cloud.vertices), pts[[0, 2]])
    box = trimesh.creation.box(extents=(10.0, 20.0, 30.0))
    write_mesh_ply(tmp_path / "m.ply", box)
    back = trimesh.load(tmp_path / "m.ply", process=False)
    assert len(back.faces) == len(box.faces) and np.allclose(back.bounds, box.bounds)
