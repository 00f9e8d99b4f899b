"""Depth error metrics (the paper's: mean absolute error and the share of pixels with error above 1, 2
and 5 mm) plus RMSE, median and completeness, and a plain-text table of them.

Depth maps are [H, W] in mm with NaN (or non-finite) where invalid. Errors are computed over pixels where
the ground truth is finite (and inside `mask`, when given) AND the prediction is finite; completeness is
the share of those ground-truth pixels that got a finite prediction, so a method cannot look accurate by
answering only where it is easy without that showing.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["depth_metrics", "metrics_document", "METRICS_SCHEMA", "format_table", "METRIC_COLUMNS", "error_map", "chessboard_region", "plane_rms"]

THRESHOLDS_MM = (1.0, 2.0, 5.0)

# (key, header, format) of the table columns
METRIC_COLUMNS = [
    ("mae", "MAE mm", "{:.3f}"),
    ("rmse", "RMSE mm", "{:.3f}"),
    ("median", "median mm", "{:.3f}"),
    ("over_1mm", ">1 mm %", "{:.2%}"),
    ("over_2mm", ">2 mm %", "{:.2%}"),
    ("over_5mm", ">5 mm %", "{:.2%}"),
    ("completeness", "complete %", "{:.2%}"),
    ("n_valid", "valid px", "{:d}"),
]


def _check_pair(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None):
    pred, gt = np.asarray(pred, np.float64), np.asarray(gt, np.float64)
    if pred.ndim != 2 or pred.shape != gt.shape:
        raise ValueError(f"prediction shape {pred.shape} != ground truth shape {gt.shape} (need the same [H, W])")
    if mask is not None:
        mask = np.asarray(mask, bool)
        if mask.shape != gt.shape:
            raise ValueError(f"mask shape {mask.shape} != depth shape {gt.shape}")
    return pred, gt, mask


def depth_metrics(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> dict:
    """Metrics of a predicted depth map against ground truth (both [H, W] mm, NaN invalid).

    Returns a dict: mae, rmse, median (mm, over compared pixels); over_1mm, over_2mm, over_5mm (fractions
    of the compared pixels with |error| above the threshold); completeness (compared / ground-truth
    pixels); n_valid (compared pixels), n_gt (ground-truth pixels, inside `mask`). With no compared
    pixel, the error entries are NaN.
    """
    pred, gt, mask = _check_pair(pred, gt, mask)
    ref = np.isfinite(gt) & (gt > 0)
    if mask is not None:
        ref &= mask
    both = ref & np.isfinite(pred)
    n_gt, n = int(ref.sum()), int(both.sum())
    out = {"n_valid": n, "n_gt": n_gt, "completeness": n / n_gt if n_gt else math.nan}
    if n == 0:
        out.update(mae=math.nan, rmse=math.nan, median=math.nan,
                   **{f"over_{t:g}mm": math.nan for t in THRESHOLDS_MM})
        return out
    err = np.abs(pred[both] - gt[both])
    out.update(mae=float(err.mean()), rmse=float(np.sqrt((err * err).mean())), median=float(np.median(err)))
    for t in THRESHOLDS_MM:
        out[f"over_{t:g}mm"] = float((err > t).mean())
    return out


METRICS_SCHEMA = "slwarp.metrics/1"  # the version of metrics_document's layout; bump it when a key changes meaning


def metrics_document(metrics: dict, *, method: str | None = None, prediction: str | None = None,
                     scan: str | None = None, frames: list[str] | None = None, mask: str = "none", **extra) -> dict:
    """The one JSON layout of depth metrics that `reconstruct` (metrics.json), `decode` (metrics.json) and
    `evaluate` (evaluation.json) write: {"schema", "method", "prediction", "scan", "frames", "mask", "metrics", ...}.
    metrics: `depth_metrics`' dict (more keys may be added to it, e.g. accuracy at a fixed completeness); extra:
    further top-level entries (e.g. the decoder's params). Entries that do not apply are None."""
    return {"schema": METRICS_SCHEMA, "method": method, "prediction": prediction, "scan": scan,
            "frames": None if frames is None else list(frames), "mask": mask, **extra, "metrics": dict(metrics)}


def error_map(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """|pred - gt| [H, W] mm, NaN where either is invalid or outside `mask`."""
    pred, gt, mask = _check_pair(pred, gt, mask)
    err = np.abs(pred - gt)
    if mask is not None:
        err[~mask] = np.nan
    return err


def format_table(rows, columns=None, title_header: str = "method") -> str:
    """A markdown table of metrics: rows is a dict {name: metrics} or a list of (name, metrics);
    columns: (key, header, format) triples (default `METRIC_COLUMNS`). Missing or NaN entries show '-'."""
    items = list(rows.items()) if isinstance(rows, dict) else list(rows)
    columns = columns or METRIC_COLUMNS
    header = [title_header] + [h for _, h, _ in columns]
    body = []
    for name, m in items:
        cells = [str(name)]
        for key, _, fmt in columns:
            v = m.get(key)
            if v is None or (isinstance(v, float) and math.isnan(v)):
                cells.append("-")
            else:
                cells.append(fmt.format(int(v) if fmt == "{:d}" else v))
        body.append(cells)
    widths = [max(len(r[i]) for r in [header] + body) for i in range(len(header))]

    def line(cells):
        return "| " + " | ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(cells, widths))) + " |"

    sep = "|" + "|".join(("-" * (w + 2)) if i == 0 else ("-" * (w + 1) + ":") for i, w in enumerate(widths)) + "|"
    return "\n".join([line(header), sep] + [line(r) for r in body])


def chessboard_region(white: np.ndarray, inner_corners=(9, 7)) -> np.ndarray:
    """[H, W] bool: the quadrilateral spanned by the outermost inner corners of a chessboard that OpenCV
    finds in `white` (float [0, 1] or 8-bit). Raises ValueError when no board is found."""
    import cv2

    img = np.asarray(white)
    if img.dtype != np.uint8:
        img = np.clip(np.rint(img * 255), 0, 255).astype(np.uint8)
    found, corners = cv2.findChessboardCorners(img, tuple(inner_corners))
    if not found:
        raise ValueError(f"no {inner_corners[0]}x{inner_corners[1]} chessboard found in the image")
    c = corners.reshape(inner_corners[1], inner_corners[0], 2)
    quad = np.round([c[0, 0], c[0, -1], c[-1, -1], c[-1, 0]]).astype(np.int32)
    mask = np.zeros(img.shape[:2], np.uint8)
    cv2.fillConvexPoly(mask, quad, 1)
    return mask.astype(bool)


def plane_rms(points: np.ndarray) -> tuple[float, int]:
    """RMS distance (mm) of the finite points [P, 3] to their least-squares plane, and their count."""
    P = np.asarray(points, np.float64).reshape(-1, 3)
    P = P[np.isfinite(P).all(1)]
    if len(P) < 3:
        return math.nan, len(P)
    c = P.mean(0)
    normal = np.linalg.svd(P - c, full_matrices=False)[2][2]
    return float(np.sqrt((((P - c) @ normal) ** 2).mean())), len(P)
