"""Pictures: colourised depth maps, error and confidence maps with a colour bar, scan previews, point-cloud renders.

All writers take depth in mm with NaN where invalid and write 8-bit RGB PNGs. A map is drawn at its own resolution
(pixel (u, v) of the picture is pixel (u, v) of the map, below a title when there is one) with its colour bar to the
right: the colour map from the low end (bottom) to the high end (top), ticks in the map's unit. The maps and bars are
drawn with numpy and OpenCV (a matplotlib figure took about a second per 1280x1024 map).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

_LUTS: dict[str, np.ndarray] = {}


def _finite_range(depth: np.ndarray, value_range=None) -> tuple[float, float]:
    if value_range is not None:
        return float(value_range[0]), float(value_range[1])
    v = depth[np.isfinite(depth)]
    if v.size == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(v, [1, 99])
    return float(lo), float(max(hi, lo + 1e-6))


def colormap_lut(cmap: str = "turbo") -> np.ndarray:
    """[256, 3] uint8 RGB: a colour map's 256 entries, OpenCV's where it has the map (turbo, viridis, inferno, magma,
    plasma, ...: matplotlib's tables, rounded instead of truncated, so within 1 of them), else matplotlib's.
    Why OpenCV first: importing matplotlib costs a fresh process a noticeable part of a second."""
    lut = _LUTS.get(cmap)
    if lut is None:
        import cv2

        code = getattr(cv2, f"COLORMAP_{cmap.upper()}", None)
        if code is not None:
            lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], code)[:, 0, ::-1].copy()
        else:
            from matplotlib import colormaps

            lut = (colormaps[cmap](np.arange(256))[:, :3] * 255).astype(np.uint8)
        _LUTS[cmap] = lut
    return lut


def colorize(values: np.ndarray, value_range=None, cmap: str = "turbo", nan_color=(0, 0, 0)) -> np.ndarray:
    """[H, W] values -> [H, W, 3] uint8 RGB through a matplotlib colour map (values outside the range take its end
    colours; the 1st to 99th percentile by default); NaN -> nan_color (black)."""
    lo, hi = _finite_range(values, value_range)
    v = np.asarray(values, np.float64)
    bad = ~np.isfinite(v)
    # entry floor(256 t) of t = (v - lo) / (hi - lo) in [0, 1], the last one for t = 1: matplotlib's own lookup
    x = (v - lo) * (256.0 / (hi - lo) if hi > lo else 0.0)  # an empty range: the low end's colour
    np.clip(x, 0.0, 255.0, out=x)
    x[bad] = 0.0
    rgb = np.take(colormap_lut(cmap), x.astype(np.uint8), axis=0)
    rgb[bad] = nan_color
    return rgb


def write_rgb(path, rgb: np.ndarray) -> None:
    """An RGB picture [H, W, 3] uint8 as PNG (or the format of path's suffix)."""
    import cv2

    ok, encoded = cv2.imencode(Path(path).suffix or ".png", np.ascontiguousarray(rgb[..., ::-1]))
    if not ok:
        raise ValueError(f"{path}: OpenCV cannot encode a picture of this kind")
    # written by Python, not by OpenCV: a full disk or a read-only folder raises an OSError that says so
    Path(path).write_bytes(encoded.tobytes())


# ----------------------------------------------------------------------------------------------
# colour bars

BAR_BACKGROUND = (0, 0, 0)
BAR_TEXT = (235, 235, 235)


def _text_scale(height: int) -> float:
    """OpenCV font scale for a picture `height` rows tall: about 22 px text at 1024 rows, never below legible."""
    return float(np.clip(height / 1024.0, 0.4, 1.2))


def _ticks(lo: float, hi: float, count: int = 6) -> tuple[np.ndarray, int]:
    """(tick values within [lo, hi] at a round step giving about `count` ticks, decimals their labels need)."""
    span = hi - lo
    if not span > 1e-6 * max(1.0, abs(lo)):  # a constant map (its range widened by rounding): one tick
        return np.array([lo]), 2
    raw = span / (count - 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw * (1 - 1e-9))
    ticks = np.arange(math.ceil(lo / step - 1e-9) * step, hi + step * 1e-6, step)
    decimals = next((d for d in range(10) if abs(round(step, d) - step) <= 1e-6 * step), 10)
    return ticks[(ticks >= lo - step * 1e-6) & (ticks <= hi + step * 1e-6)], decimals


def colorbar_panel(height: int, lo: float, hi: float, cmap: str, label: str) -> np.ndarray:
    """[height, w, 3] uint8: a vertical colour bar of `cmap` from lo (bottom row of the strip) to hi (top), ticks
    labelled with their values and `label` (e.g. "depth mm") above, on BAR_BACKGROUND; to be put beside a map of
    `height` rows."""
    import cv2

    font, scale = cv2.FONT_HERSHEY_SIMPLEX, _text_scale(height)
    thick = 1 if scale < 0.9 else 2
    (_, text_h), _ = cv2.getTextSize("0", font, scale, thick)
    ticks, decimals = _ticks(lo, hi)
    labels = [f"{v:.{decimals}f}" for v in ticks]
    label_w = max(cv2.getTextSize(t, font, scale, thick)[0][0] for t in labels)
    gap, strip_w, tick_len = text_h, max(8, text_h), max(3, text_h // 3)
    title_w = cv2.getTextSize(label, font, scale, thick)[0][0]
    width = max(gap + strip_w + tick_len + gap // 2 + label_w + gap, gap + title_w + gap)
    top, bottom = 3 * text_h, height - 1 - text_h  # the strip's first and last rows
    panel = np.empty((height, width, 3), np.uint8)
    panel[:] = BAR_BACKGROUND
    if bottom - top < 2:  # too short for a bar: the caller pads the picture first (with_colorbar does)
        raise ValueError(f"colorbar_panel: {height} rows hold no bar (at least {5 * text_h} are needed)")
    rows = np.arange(top, bottom + 1)
    values = hi - (rows - top) / (bottom - top) * (hi - lo)
    panel[top:bottom + 1, gap:gap + strip_w] = colorize(values[:, None], (lo, hi), cmap)
    cv2.putText(panel, label, (gap, top - text_h), font, scale, BAR_TEXT, thick, cv2.LINE_AA)
    for v, text in zip(ticks, labels):
        y = int(round(top + (hi - v) / (hi - lo) * (bottom - top))) if hi > lo else (top + bottom) // 2
        x = gap + strip_w
        cv2.line(panel, (x, y), (x + tick_len - 1, y), BAR_TEXT, 1)
        cv2.putText(panel, text, (x + tick_len + gap // 2, y + text_h // 2), font, scale, BAR_TEXT, thick, cv2.LINE_AA)
    return panel


def _title_rows(title: str, width: int, scale: float) -> np.ndarray:
    """[h, width, 3]: `title` on BAR_BACKGROUND, wrapped at spaces to fit `width`."""
    import cv2

    font, thick = cv2.FONT_HERSHEY_SIMPLEX, 1 if scale < 0.9 else 2
    (_, text_h), _ = cv2.getTextSize("0", font, scale, thick)
    lines: list[str] = []
    for word in title.split():
        if lines and cv2.getTextSize(lines[-1] + " " + word, font, scale, thick)[0][0] <= width - text_h:
            lines[-1] += " " + word
        else:
            lines.append(word)
    step = 2 * text_h
    rows = np.empty((step * len(lines) + text_h, width, 3), np.uint8)
    rows[:] = BAR_BACKGROUND
    for i, line in enumerate(lines):
        cv2.putText(rows, line, (text_h // 2, step * (i + 1)), font, scale, BAR_TEXT, thick, cv2.LINE_AA)
    return rows


def with_colorbar(rgb: np.ndarray, value_range: tuple[float, float], cmap: str, label: str,
                  title: str | None = None) -> np.ndarray:
    """The picture `rgb` [H, W, 3] (a map coloured with `cmap` over value_range) with its colour bar to the right
    (colorbar_panel) and, when given, a title above; a map too short for the bar is padded below."""
    import cv2

    h, w = rgb.shape[:2]
    (_, text_h), _ = cv2.getTextSize("0", cv2.FONT_HERSHEY_SIMPLEX, _text_scale(h), 1 if _text_scale(h) < 0.9 else 2)
    rows = max(h, 8 * text_h)
    panel = colorbar_panel(rows, float(value_range[0]), float(value_range[1]), cmap, label)
    out = np.empty((rows, w + panel.shape[1], 3), np.uint8)
    out[:] = BAR_BACKGROUND
    out[:h, :w] = rgb
    out[:, w:] = panel
    if title:
        out = np.concatenate([_title_rows(title, out.shape[1], _text_scale(h)), out], axis=0)
    return out


def save_depth_color(path, depth: np.ndarray, value_range=None) -> None:
    """Colourised depth PNG (turbo, near = blue; the 1st to 99th percentile, or value_range in mm), NaN black, with
    its colour bar in mm to the right: the map keeps its pixels at the left, so the picture is wider than the map."""
    lo, hi = _finite_range(depth, value_range)
    write_rgb(path, with_colorbar(colorize(depth, (lo, hi)), (lo, hi), "turbo", "depth mm"))


NAN_GRAY = (38, 38, 38)  # where a map with a colour bar has no value


def save_map_with_colorbar(path, values: np.ndarray, title: str, label: str, value_range=None,
                           cmap: str = "turbo", dpi: int = 100) -> None:
    """A map with a title above and a labelled colour bar to the right, at the map's resolution; NaN dark gray.
    dpi: unused (the picture has the map's own pixels), kept for callers that pass it."""
    lo, hi = _finite_range(values, value_range)
    write_rgb(path, with_colorbar(colorize(values, (lo, hi), cmap, NAN_GRAY), (lo, hi), cmap, label, title))


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
    save_map_with_colorbar(path, err, title, "error mm", value_range=(0.0, max_mm), cmap="inferno")


def save_scan_preview(path, scan, max_frames: int = 3) -> None:
    """Montage of the first frames, the GT depth (colourised) and the mask, downscaled to <= 1600 px wide."""
    import cv2

    tiles = []
    for i in range(min(max_frames, len(scan.names))):
        g = (np.clip(scan.images[i], 0, 1) * 255).astype(np.uint8)
        tiles.append(np.repeat(g[..., None], 3, axis=2))
    if scan.gt_depth is not None:
        lo_hi = _finite_range(scan.gt_depth)
        tiles.append(with_colorbar(colorize(scan.gt_depth, lo_hi), lo_hi, "turbo", "depth mm"))
    if scan.mask is not None:
        tiles.append(np.repeat((scan.mask * 255).astype(np.uint8)[..., None], 3, axis=2))
    rows = max(t.shape[0] for t in tiles)  # a short map's colour bar may be taller than the map
    row = np.concatenate([np.pad(t, ((0, rows - t.shape[0]), (0, 0), (0, 0))) for t in tiles], axis=1)
    scale = min(1.0, 1600.0 / row.shape[1])
    if scale < 1.0:
        row = cv2.resize(row, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    write_rgb(path, row)


def save_point_cloud_render(path, points: np.ndarray, colors: np.ndarray | None = None, title: str = "",
                            elev: float = 20.0, azim: float = -110.0, max_points: int = 60000) -> None:
    """A 3-D scatter render of a point cloud [P, 3] (mm, camera frame), viewed obliquely; coloured by depth (with a
    colour bar in mm) unless `colors` are given."""
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
        drawn = ax.scatter(pts[:, 0], pts[:, 2], -pts[:, 1], c=c, s=0.3, cmap="turbo", linewidths=0)
        ax.set_box_aspect((np.ptp(pts[:, 0]) + 1, np.ptp(pts[:, 2]) + 1, np.ptp(pts[:, 1]) + 1))
        if colors is None:  # coloured by depth: say which colour is which depth
            fig.colorbar(drawn, ax=ax, shrink=0.6, pad=0.08, label="depth mm")
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


# a colour per pixel fate (slwarp.neural.extraction.PIXEL_FATES and the stages' own): pixels with depth in grays
# and blues, the stages that left pixels without depth in warm colours, no contrast black
FATE_COLOURS = {"measured": (0.55, 0.55, 0.55), "repaired": (0.2, 0.4, 1.0), "filled": (0.3, 0.85, 0.95),
                "no_contrast": (0.0, 0.0, 0.0), "no_surface": (1.0, 1.0, 1.0), "out_of_range": (0.85, 0.2, 0.85),
                "flying_pixel": (1.0, 0.55, 0.0), "low_confidence": (0.9, 0.1, 0.1), "search_doubt": (1.0, 0.9, 0.1),
                "edge_side": (0.6, 0.3, 0.1), "interpolated": (0.75, 0.9, 0.75), "edge_band": (0.75, 0.45, 0.55),
                "split": (0.45, 0.3, 0.9)}


def _legend_panel(entries: list[tuple[tuple[int, int, int], str]], height: int, title: str | None = None) -> np.ndarray:
    """[height, w, 3] uint8: a legend of (RGB swatch, text) lines, top-aligned, on BAR_BACKGROUND, for a map of
    `height` rows."""
    import cv2

    font, scale = cv2.FONT_HERSHEY_SIMPLEX, _text_scale(height)
    thick = 1 if scale < 0.9 else 2
    (_, text_h), _ = cv2.getTextSize("0", font, scale, thick)
    step, gap = 2 * text_h, text_h
    texts = ([title] if title else []) + [t for _, t in entries]
    width = gap + 2 * text_h + gap + max(cv2.getTextSize(t, font, scale, thick)[0][0] for t in texts) + gap
    rows = max(height, step * (len(texts) + 1))
    panel = np.empty((rows, width, 3), np.uint8)
    panel[:] = BAR_BACKGROUND
    y = step
    if title:
        cv2.putText(panel, title, (gap, y), font, scale, BAR_TEXT, thick, cv2.LINE_AA)
        y += step
    for rgb, text in entries:
        cv2.rectangle(panel, (gap, y - text_h), (gap + 2 * text_h, y), tuple(int(c) for c in rgb), -1)
        cv2.rectangle(panel, (gap, y - text_h), (gap + 2 * text_h, y), (80, 80, 80), 1)
        cv2.putText(panel, text, (2 * gap + 2 * text_h, y), font, scale, BAR_TEXT, thick, cv2.LINE_AA)
        y += step
    return panel


def save_fate_map(path, fate: np.ndarray, names: tuple[str, ...], title: str = "what became of each pixel") -> None:
    """fate [H, W] (indices into `names`, e.g. PIXEL_FATES) at its own resolution with a legend to the right giving
    each fate's share of the pixels; fates without a colour in FATE_COLOURS are drawn gray-green."""
    fate = np.asarray(fate)
    if fate.size and int(fate.max()) >= len(names):
        raise ValueError(f"save_fate_map: fate value {int(fate.max())} has no name (names: {', '.join(names)})")
    colours = np.rint(255 * np.array([FATE_COLOURS.get(n, (0.5, 0.6, 0.5)) for n in names])).astype(np.uint8)
    h, w = fate.shape
    counts = np.bincount(fate.ravel(), minlength=len(names))
    entries = [(tuple(colours[i]), f"{n.replace('_', ' ')} {100.0 * c / fate.size:.2f}%")
               for i, (n, c) in enumerate(zip(names, counts)) if c > 0]
    legend = _legend_panel(entries, h, title)
    out = np.empty((legend.shape[0], w + legend.shape[1], 3), np.uint8)
    out[:] = BAR_BACKGROUND
    out[:h, :w] = colours[fate]
    out[:, w:] = legend
    write_rgb(path, out)


# the loss curves' colours (RGB) and the picture's size
CURVE_COLOURS = ((31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40))
CURVE_PANEL = (520, 360)  # width, height of each panel in pixels


def _curve_panel(x: np.ndarray, curves: list[tuple[str, np.ndarray]], title: str) -> np.ndarray:
    """[h, w, 3]: `curves` (name, values > 0) against x on a log scale, axes with decade ticks, a legend, a title."""
    import cv2

    w, h = CURVE_PANEL
    font, scale, thick = cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1
    panel = np.full((h, w, 3), 255, np.uint8)
    left, right, top, bottom = 62, w - 12, 26, h - 36
    ys = np.concatenate([np.asarray(v, np.float64) for _, v in curves])
    ys = ys[np.isfinite(ys) & (ys > 0)]
    lo, hi = (math.floor(math.log10(ys.min())), math.ceil(math.log10(ys.max()))) if ys.size else (0, 1)
    hi = max(hi, lo + 1)
    x0, x1 = float(x.min()), float(max(x.max(), x.min() + 1))

    def px(xv, yv):
        ly = np.log10(np.clip(yv, 10.0 ** lo, None))
        return (left + (xv - x0) / (x1 - x0) * (right - left), bottom - (ly - lo) / (hi - lo) * (bottom - top))

    cv2.rectangle(panel, (left, top), (right, bottom), (0, 0, 0), 1)
    for d in range(lo, hi + 1):
        y = int(round(px(x0, 10.0 ** d)[1]))
        cv2.line(panel, (left, y), (right, y), (225, 225, 225), 1)
        cv2.putText(panel, f"1e{d}", (8, y + 4), font, scale, (0, 0, 0), thick, cv2.LINE_AA)
    for t in _ticks(x0, x1, 5)[0]:
        xx = int(round(px(t, 10.0 ** lo)[0]))
        cv2.line(panel, (xx, bottom), (xx, bottom + 3), (0, 0, 0), 1)
        cv2.putText(panel, f"{t:.0f}", (xx - 12, bottom + 16), font, scale, (0, 0, 0), thick, cv2.LINE_AA)
    cv2.putText(panel, "iteration", (w // 2 - 30, h - 6), font, scale, (0, 0, 0), thick, cv2.LINE_AA)
    cv2.putText(panel, title, (left, 18), font, scale, (0, 0, 0), thick, cv2.LINE_AA)
    for k, (name, v) in enumerate(curves):
        v = np.asarray(v, np.float64)
        ok = np.isfinite(v) & (v > 0)
        if ok.sum() >= 2:
            pts = np.stack(px(x[ok].astype(np.float64), v[ok]), axis=1)
            colour = CURVE_COLOURS[k % len(CURVE_COLOURS)][::-1]  # OpenCV draws BGR
            cv2.polylines(panel, [np.round(pts).astype(np.int32)], False, colour, 1, cv2.LINE_AA)
        if len(curves) > 1:
            y = top + 16 + 16 * k
            cv2.line(panel, (right - 190, y - 4), (right - 170, y - 4), CURVE_COLOURS[k % len(CURVE_COLOURS)][::-1], 2)
            cv2.putText(panel, name, (right - 165, y), font, scale, (0, 0, 0), thick, cv2.LINE_AA)
    return panel[..., ::-1]  # drawn as BGR: back to RGB


def save_loss_curves(path, iters, losses: dict[str, np.ndarray], inv_s) -> None:
    """The training's loss terms (log scale) and NeuS's inv_s (1/mm) against the iteration, two panels side by
    side (drawn with OpenCV: a matplotlib figure cost a fresh process about a second)."""
    x = np.asarray(iters, np.float64)
    left = _curve_panel(x, [(k, np.asarray(v)) for k, v in losses.items()], "loss terms")
    right = _curve_panel(x, [("inv_s", np.asarray(inv_s))], "inv_s (1/mm)")
    write_rgb(path, np.concatenate([left, right], axis=1))
