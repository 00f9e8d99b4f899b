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


# ----------------------------------------------------------------------------------------------
# pictures: every map with a colour bar beside it


def _read_rgb(path) -> np.ndarray:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert bgr is not None, path
    return bgr[..., ::-1]


def _bar_levels(picture: np.ndarray, x0: int, cmap: str) -> np.ndarray:
    """The colour-map entries (0..255) down the colour bar: the column right of x0 with the most pixels that are
    exactly an entry of `cmap`, read from top to bottom."""
    from slwarp.evaluation.viz import colormap_lut

    lut = colormap_lut(cmap).astype(int)
    best = np.array([], int)
    for x in range(x0, picture.shape[1]):
        col = picture[:, x].astype(int)
        hit = (col[:, None, :] == lut[None]).all(-1)  # [H, 256]
        rows = np.flatnonzero(hit.any(1) & col.any(1))  # black is the background
        if len(rows) > len(best):
            best = hit[rows].argmax(1)
    return best


def _assert_bar_follows(picture: np.ndarray, map_width: int, map_height: int, cmap: str) -> None:
    levels = _bar_levels(picture, map_width, cmap)
    assert len(levels) > 0.6 * map_height  # a strip nearly as tall as the map
    assert levels[0] >= 250 and levels[-1] <= 5 and np.all(np.diff(levels) <= 0)  # high end on top, every step down
    assert len(np.unique(levels)) > min(200, 0.5 * len(levels))  # a gradient, not a few bands


def test_depth_picture_has_a_colour_bar(tmp_path):
    from slwarp.evaluation.viz import colorize, save_depth_color

    h, w = 256, 320
    yy, xx = np.mgrid[0:h, 0:w]
    depth = 600.0 + 0.5 * xx + 0.2 * yy
    depth[100:140, 50:90] = np.nan
    save_depth_color(tmp_path / "d.png", depth, (600.0, 800.0))
    pic = _read_rgb(tmp_path / "d.png")
    assert pic.shape[0] == h and pic.shape[1] > w + 20  # the bar beside the map, the map's height kept
    np.testing.assert_array_equal(pic[:, :w], colorize(depth, (600.0, 800.0)))  # the map at its own pixels
    _assert_bar_follows(pic, w, h, "turbo")


def test_error_and_confidence_maps_have_a_colour_bar(tmp_path):
    from slwarp.evaluation.viz import save_confidence_map, save_error_map

    h, w = 200, 260
    gt = np.full((h, w), 700.0)
    pred = gt + np.linspace(0.0, 4.0, w)[None, :]
    pred[:20] = np.nan
    save_error_map(tmp_path / "e.png", pred, gt, title="|depth error|", max_mm=2.0)
    save_confidence_map(tmp_path / "c.png", np.clip(np.linspace(0, 1, w)[None, :].repeat(h, 0), 0, 1))
    for name, cmap in (("e.png", "inferno"), ("c.png", "viridis")):
        pic = _read_rgb(tmp_path / name)
        assert pic.shape[1] > w + 20 and pic.shape[0] > h  # the bar beside, the title above
        _assert_bar_follows(pic, w, h, cmap)


def test_short_maps_and_constant_maps_still_get_a_bar(tmp_path):
    from slwarp.evaluation.viz import save_depth_color

    flat = np.full((12, 16), 500.0)
    save_depth_color(tmp_path / "flat.png", flat)
    save_depth_color(tmp_path / "none.png", np.full((12, 16), np.nan))
    for name in ("flat.png", "none.png"):
        pic = _read_rgb(tmp_path / name)
        assert pic.shape[0] > 12 and pic.shape[1] > 16  # padded below to hold the bar and its labels


def _figure_labels(monkeypatch, draw) -> list[str]:
    """The y-axis labels of every axes of the matplotlib figures `draw()` saves (a colour bar's label is one)."""
    from matplotlib.figure import Figure

    labels, save = [], Figure.savefig

    def record(fig, *args, **kwargs):
        labels.extend(ax.get_ylabel() for ax in fig.axes)
        return save(fig, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", record)
    draw()
    return labels


def test_comparison_and_point_cloud_pictures_have_depth_bars(tmp_path, monkeypatch):
    from slwarp.demo import comparison_figure
    from slwarp.evaluation.viz import save_point_cloud_render

    gt = 700.0 + np.mgrid[0:24, 0:32][1].astype(float)
    results = {"a": {"depth": gt + 0.5, "metrics": {"mae": 0.5}}, "b": {"depth": gt - 1.0, "metrics": {"mae": 1.0}}}
    labels = _figure_labels(monkeypatch, lambda: comparison_figure(tmp_path / "cmp.png", gt, results))
    assert "depth mm" in labels and "error mm" in labels
    pts = np.stack([np.arange(50.0), np.zeros(50), 600.0 + np.arange(50.0)], 1)
    labels = _figure_labels(monkeypatch, lambda: save_point_cloud_render(tmp_path / "pc.png", pts))
    assert "depth mm" in labels
