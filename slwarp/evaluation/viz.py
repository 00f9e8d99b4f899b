"""Pictures: colourised depth maps, error and confidence maps with a colour bar, scan previews, point-cloud renders.

All writers take depth in mm with NaN where invalid and write 8-bit RGB PNGs.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np


def _finite_range(depth: np.ndarray, value_range=None) -> tuple[float, float]:
    if value_range is not None:
        return float(value_range[0]), float(value_range[1])
    v = depth[np.isfinite(depth)]
    if v.size == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(v, [1, 99])
    return float(lo), float(max(hi, lo + 1e-6))


def colorize(values: np.ndarray, value_range=None, cmap: str = "turbo") -> np.ndarray:
    """[H, W] values -> [H, W, 3] uint8 RGB through a matplotlib colour map; NaN -> black."""
    from matplotlib import colormaps

    lo, hi = _finite_range(values, value_range)
    t = np.clip((values - lo) / (hi - lo), 0.0, 1.0)
    rgb = (colormaps[cmap](np.nan_to_num(t))[..., :3] * 255).astype(np.uint8)
    rgb[~np.isfinite(values)] = 0
    return rgb


def write_rgb(path, rgb: np.ndarray) -> None:
    import cv2

    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1])):
        raise OSError(f"could not write {path}")


def save_depth_color(path, depth: np.ndarray, value_range=None) -> None:
    """Colourised depth PNG (turbo, near = blue), NaN black."""
    write_rgb(path, colorize(depth, value_range))


def save_map_with_colorbar(path, values: np.ndarray, title: str, label: str, value_range=None,
                           cmap: str = "turbo", dpi: int = 100) -> None:
    """A map with a labelled colour bar (matplotlib, headless); NaN shown in dark gray."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lo, hi = _finite_range(values, value_range)
    h, w = values.shape
    fig_w = 7.0
    fig, ax = plt.subplots(figsize=(fig_w, fig_w * h / w * 0.95 + 0.6), dpi=dpi)
    cm = matplotlib.colormaps[cmap].with_extremes(bad=(0.15, 0.15, 0.15))
    im = ax.imshow(np.ma.masked_invalid(values), cmap=cm, vmin=lo, vmax=hi, interpolation="nearest")
    ax.set_title(title, fontsize=10)
    ax.axis("off")
    cb = fig.colorbar(im, ax=ax, fraction=0.04, pad=0.02)
    cb.set_label(label)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def save_confidence_map(path, confidence: np.ndarray, title: str = "confidence") -> None:
    """Confidence [H, W] in [0, 1] (higher = more trusted) with a colour bar (viridis: dark = doubtful, yellow =
    trusted); gray where there is no depth (NaN)."""
    c = np.asarray(confidence, np.float64)
    shown = c[np.isfinite(c)]
    detail = f", median {np.median(shown):.2f} over {shown.size} px" if shown.size else ", no pixel"
    save_map_with_colorbar(path, c, title + detail, "confidence", value_range=(0.0, 1.0), cmap="viridis")


def save_error_map(path, pred: np.ndarray, gt: np.ndarray, title: str = "absolute depth error", max_mm: float = 5.0) -> None:
    """|pred - gt| in mm with a colour bar clipped at `max_mm`; gray where either is invalid."""
    err = np.abs(pred - gt)
    save_map_with_colorbar(path, err, title, "|error| (mm)", value_range=(0.0, max_mm), cmap="inferno")


def save_scan_preview(path, scan, max_frames: int = 3) -> None:
    """Montage of the first frames, the GT depth (colourised) and the mask, downscaled to <= 1600 px wide."""
    import cv2

    tiles = []
    for i in range(min(max_frames, len(scan.names))):
        g = (np.clip(scan.images[i], 0, 1) * 255).astype(np.uint8)
        tiles.append(np.repeat(g[..., None], 3, axis=2))
    if scan.gt_depth is not None:
        tiles.append(colorize(scan.gt_depth))
    if scan.mask is not None:
        tiles.append(np.repeat((scan.mask * 255).astype(np.uint8)[..., None], 3, axis=2))
    row = np.concatenate(tiles, axis=1)
    scale = min(1.0, 1600.0 / row.shape[1])
    if scale < 1.0:
        row = cv2.resize(row, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    write_rgb(path, row)


def save_point_cloud_render(path, points: np.ndarray, colors: np.ndarray | None = None, title: str = "",
                            elev: float = 20.0, azim: float = -110.0, max_points: int = 60000) -> None:
    """A 3-D scatter render of a point cloud [P, 3] (mm, camera frame), viewed obliquely."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pts = points[np.all(np.isfinite(points), axis=1)]
    if len(pts) > max_points:
        pts = pts[np.random.default_rng(0).choice(len(pts), max_points, replace=False)]
    fig = plt.figure(figsize=(7, 6), dpi=100)
    ax = fig.add_subplot(projection="3d")
    if len(pts):
        c = pts[:, 2] if colors is None else colors
        ax.scatter(pts[:, 0], pts[:, 2], -pts[:, 1], c=c, s=0.3, cmap="turbo", linewidths=0)
        ax.set_box_aspect((np.ptp(pts[:, 0]) + 1, np.ptp(pts[:, 2]) + 1, np.ptp(pts[:, 1]) + 1))
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("z (mm)")
    ax.set_zlabel("-y (mm)")
    ax.view_init(elev=elev, azim=azim)
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def ensure_dir(path) -> Path:
    p = Path(path)
    p.mkdir(parents=True, exist_ok=True)
    return p


# a colour per pixel fate (slwarp.neural.reconstruct.PIXEL_FATES): pixels with depth in grays and blues, the stages
# that left pixels without depth in warm colours, no contrast black
FATE_COLOURS = {"measured": (0.55, 0.55, 0.55), "repaired": (0.2, 0.4, 1.0), "filled": (0.3, 0.85, 0.95),
                "no_contrast": (0.0, 0.0, 0.0), "no_surface": (1.0, 1.0, 1.0), "out_of_range": (0.85, 0.2, 0.85),
                "flying_pixel": (1.0, 0.55, 0.0), "low_confidence": (0.9, 0.1, 0.1), "search_doubt": (1.0, 0.9, 0.1)}


def save_fate_map(path, fate: np.ndarray, names: tuple[str, ...], title: str = "what became of each pixel",
                  dpi: int = 100) -> None:
    """fate [H, W] (indices into `names`, e.g. PIXEL_FATES) as a picture with a legend giving each fate's share of
    the pixels; fates without a colour in FATE_COLOURS are drawn gray-green."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    fate = np.asarray(fate)
    colours = np.array([FATE_COLOURS.get(n, (0.5, 0.6, 0.5)) for n in names])
    if fate.size and int(fate.max()) >= len(names):
        raise ValueError(f"save_fate_map: fate value {int(fate.max())} has no name (names: {', '.join(names)})")
    h, w = fate.shape
    fig, ax = plt.subplots(figsize=(8.5, 7.0 * h / w * 0.95 + 0.6), dpi=dpi)
    ax.imshow(colours[fate], interpolation="nearest")
    ax.set_title(title, fontsize=10)
    ax.axis("off")
    counts = np.bincount(fate.ravel(), minlength=len(names))
    handles = [Patch(facecolor=colours[i], edgecolor="0.3", label=f"{n.replace('_', ' ')} {100.0 * c / fate.size:.2f}%")
               for i, (n, c) in enumerate(zip(names, counts)) if c > 0]
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    fig.savefig(path, bbox_inches="tight")  # the legend beside the map, inside the picture
    plt.close(fig)
