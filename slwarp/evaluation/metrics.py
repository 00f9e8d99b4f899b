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

__all__ = ["depth_metrics", "metrics_document", "METRICS_SCHEMA", "format_table", "METRIC_COLUMNS", "error_map",
           "chessboard_region", "plane_rms", "sparsification_curve", "confidence_metrics", "CONFIDENCE_COLUMNS",
           "SPARSIFICATION_FRACTIONS"]

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


# kept fractions of the sparsification curves: 100% down to 50% of the compared pixels, in steps of 1%
SPARSIFICATION_FRACTIONS = np.round(np.linspace(1.0, 0.5, 51), 2)
# the fixed shares of the most confident compared pixels that `confidence_metrics` reports the MAE of
CONFIDENCE_SHARES = (0.9, 0.75)

CONFIDENCE_COLUMNS = [
    ("mae_top90", "MAE top 90% mm", "{:.3f}"),
    ("mae_top75", "MAE top 75% mm", "{:.3f}"),
    ("ause", "AUSE mm", "{:.3f}"),
    ("ause_random", "AUSE random mm", "{:.3f}"),
]


def sparsification_curve(errors: np.ndarray, confidence: np.ndarray, fractions=SPARSIFICATION_FRACTIONS) -> np.ndarray:
    """MAE [len(fractions)] of the most confident `fractions` (each in (0, 1]) of the pixels.

    errors, confidence [P]: |error| (mm) and confidence (higher = more trusted; only the order counts) of the
    same P pixels. A fraction that cuts k = f P pixels where k is not whole takes the last pixel in part. Pixels
    of equal confidence are taken in no particular order: a tie group cut in part counts its mean error (what
    a random order within the group gives on average), so the curve does not depend on the pixel order.
    The oracle's curve is `sparsification_curve(errors, -errors)`.
    """
    e = np.asarray(errors, np.float64).ravel()
    c = np.asarray(confidence, np.float64).ravel()
    if e.shape != c.shape:
        raise ValueError(f"errors ({e.size}) and confidence ({c.size}) must hold the same pixels")
    f = np.asarray(fractions, np.float64)
    if e.size == 0:
        return np.full(f.shape, np.nan)
    if not ((f > 0) & (f <= 1)).all():
        raise ValueError(f"fractions must lie in (0, 1], got {f}")
    order = np.argsort(-c)  # any order within a tie group: the groups' means below make it irrelevant
    cs, es = c[order], e[order]
    # each tie group's pixels all carry the group's mean error (nothing to do when no two confidences are equal)
    starts = np.flatnonzero(np.r_[True, cs[1:] != cs[:-1]])
    if starts.size < es.size:
        sums = np.add.reduceat(es, starts)
        counts = np.diff(np.r_[starts, es.size])
        es = np.repeat(sums / counts, counts)
    return _mean_of_first(es, f)


def _mean_of_first(es: np.ndarray, f: np.ndarray) -> np.ndarray:
    """[len(f)]: the mean of the first f * P of the P errors es [P] in their order (a fraction that cuts a pixel
    takes it in part)."""
    cum = np.r_[0.0, np.cumsum(es)]
    k = f * es.size
    whole = np.minimum(np.floor(k).astype(np.int64), es.size)
    partial = np.where(whole < es.size, es[np.minimum(whole, es.size - 1)], 0.0)
    return (cum[whole] + (k - whole) * partial) / k


def _oracle_curve(errors: np.ndarray, fractions) -> np.ndarray:
    """sparsification_curve(errors, -errors, fractions), the pixels ranked by their own error: a plain sort of the
    errors (equal errors need no tie averaging), half the time of the argsort and gather."""
    e = np.sort(np.asarray(errors, np.float64).ravel())
    f = np.asarray(fractions, np.float64)
    return np.full(f.shape, np.nan) if e.size == 0 else _mean_of_first(e, f)


def confidence_metrics(pred: np.ndarray, confidence: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None,
                       fractions=SPARSIFICATION_FRACTIONS) -> dict:
    """How well a confidence map [H, W] ranks the pixels of a depth map by their error (both against gt, NaN
    invalid; over the pixels `depth_metrics` compares).

    Returns a dict: mae_top90, mae_top75 (mm): MAE of the 90% and 75% most confident compared pixels (accuracy
    at a fixed share of the answers); ause (mm): the area between the sparsification curve (MAE of the most
    confident x% of the compared pixels, x = 100 down to 50) and the oracle's (pixels sorted by their true
    error), divided by the width of that range: the mean excess MAE over it, 0 for a perfect ranking;
    ause_random (mm): the same for a confidence that ranks nothing (a flat curve at the MAE), the scale AUSE
    is read against; sparsification: {fractions, curve, oracle}, both curves at `fractions`. Non-finite confidence at a compared pixel
    counts as the lowest. NaN entries when no pixel is compared.
    """
    pred, gt, mask = _check_pair(pred, gt, mask)
    conf = np.asarray(confidence, np.float64)
    if conf.shape != gt.shape:
        raise ValueError(f"confidence shape {conf.shape} != depth shape {gt.shape}")
    ref = np.isfinite(gt) & (gt > 0)
    if mask is not None:
        ref &= mask
    both = ref & np.isfinite(pred)
    err = np.abs(pred[both] - gt[both])
    c = np.where(np.isfinite(conf[both]), conf[both], -np.inf)
    f = np.asarray(fractions, np.float64)
    # one sort for the curve and the shares' MAEs together (a sort of every compared pixel is most of the time)
    with_shares = sparsification_curve(err, c, np.r_[f, CONFIDENCE_SHARES])
    curve, at_shares = with_shares[:f.size], with_shares[f.size:]
    oracle = _oracle_curve(err, f)
    width = float(f.max() - f.min())

    def area(y):  # trapezoids over the fractions, divided by their range
        o = np.argsort(f)
        x, y = f[o], y[o]
        return float(((y[1:] + y[:-1]) * np.diff(x)).sum() / (2.0 * width)) if width > 0 else float(y[0])

    out = {f"mae_top{round(s * 100)}": float(m) for s, m in zip(CONFIDENCE_SHARES, at_shares)}
    mae = float(err.mean()) if err.size else math.nan
    out.update(ause=area(curve - oracle), ause_random=area(mae - oracle),
               sparsification={"fractions": f.tolist(), "curve": curve.tolist(), "oracle": oracle.tolist()})
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


def depth_step_distance(gt: np.ndarray, step_mm: float = 5.0) -> np.ndarray:
    """[H, W] distance (px) of each pixel to the nearest depth step of the ground truth `gt` [H, W] (mm, NaN where
    no surface): a pair of 4-neighbours differing by more than step_mm, or the surface's end. Splits an error into
    what the depth edges cost and what the surfaces do (bench.real_captures on a twin)."""
    import cv2

    g = np.asarray(gt, np.float64)
    step = ~np.isfinite(g)
    with np.errstate(invalid="ignore"):
        dx, dy = np.abs(np.diff(g, axis=1)) > step_mm, np.abs(np.diff(g, axis=0)) > step_mm
    step[:, 1:] |= dx
    step[:, :-1] |= dx
    step[1:, :] |= dy
    step[:-1, :] |= dy
    return cv2.distanceTransform((~step).astype(np.uint8), cv2.DIST_L2, 5)


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


def quadric_rms(points: np.ndarray) -> float:
    """RMS distance (mm) of the finite points [P, 3] to their least-squares quadratic height field over their plane
    (z' = quadratic in x', y' in the plane's frame); NaN for fewer than 6 points.

    Why beside plane_rms: a flat board reconstructed through a slightly wrong calibration comes out bent, the same
    for every decoder that uses it. The plane's RMS holds that smooth bend and the local error; this one holds
    about the local error alone, so the two together say which one limits a method."""
    P = np.asarray(points, np.float64).reshape(-1, 3)
    P = P[np.isfinite(P).all(1)]
    if len(P) < 6:
        return math.nan
    Q = P - P.mean(0)
    frame = np.linalg.svd(Q, full_matrices=False)[2]
    x, y, z = (Q @ frame.T).T
    scale = max(float(np.abs(x).max()), float(np.abs(y).max()), 1e-9)  # conditioning: x, y in [-1, 1]
    x, y = x / scale, y / scale
    A = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], 1)
    coef = np.linalg.lstsq(A, z, rcond=None)[0]
    return float(np.sqrt(np.mean((z - A @ coef) ** 2)))
