"""`slwarp decode` (a classical method, triangulated) and `slwarp evaluate` (a depth map against a scan's ground
truth), with the metrics files they share."""
from __future__ import annotations

import time
from pathlib import Path

from .errors import UserError
from .options import FRAMES_HELP, _add_outside_paths
from .scans import _warn_problems


def _write_metrics(json_path: Path, map_path: Path, pred, scan, mask, title: str, confidence=None,
                   **info) -> tuple[dict, dict | None]:
    """Metrics of `pred` against the scan's ground truth: the metrics document (evaluation.metrics_document) at
    `json_path`, the error map at `map_path`; with a confidence map [H, W], also how well it ranks the errors
    (`confidence_metrics`, the document's "confidence"). Returns (metrics, confidence metrics or None)."""
    import json

    import numpy as np

    from ..evaluation.metrics import confidence_metrics, depth_metrics, metrics_document
    from ..evaluation.viz import save_error_map

    m = depth_metrics(pred, scan.gt_depth, mask)
    cm = None
    if confidence is not None:
        info["confidence"] = cm = confidence_metrics(pred, confidence, scan.gt_depth, mask)
    doc = metrics_document(m, scan=scan.source, mask="scan mask" if mask is not None else "none", **info)
    shown = pred if mask is None else np.where(mask, pred, np.nan)  # the map shows what the numbers count
    for path, write in ((json_path, lambda: json_path.write_text(json.dumps(doc, indent=2, default=float) + "\n")),
                        (map_path, lambda: save_error_map(map_path, shown, scan.gt_depth, title=title))):
        try:
            write()
        except OSError as e:  # a full disk or a read-only file system: name the file (some writers do not)
            raise OSError(f"{path}: cannot write it ({e.strerror or e})") from None
    return m, cm


def _print_confidence_metrics(name: str, cm: dict) -> None:
    from ..evaluation.metrics import CONFIDENCE_COLUMNS, format_table

    print("confidence ranking: MAE of the most confident 90% and 75% of the pixels with depth; AUSE: the mean excess "
          "MAE of the most confident x% over the x% with the smallest errors, x = 100 to 50 (0: a perfect ranking; "
          "'random': a confidence that ranks nothing)")
    print(format_table([(name, cm)], CONFIDENCE_COLUMNS, title_header="confidence of"))


def cmd_decode(args) -> int:
    import json

    import numpy as np

    from ..decode import METHODS, decoding_confidence, reconstruct_depth
    from ..evaluation.metrics import format_table
    from ..evaluation.outputs import write_confidence, write_depth_png
    from ..evaluation.outputs import write_points_ply as write_ply
    from ..evaluation.outputs import check_output_folder
    from ..evaluation.viz import ensure_dir, save_confidence_map, save_depth_color
    from ..scans.scan import load_scan

    scan = load_scan(args.scan, outside_paths=args.allow_outside_paths)
    _warn_problems(scan)
    params = {"min_amplitude": args.min_amplitude}
    if args.method in ("gc", "gc-interp", "cgc", "gt"):
        params["min_bit_contrast"] = args.min_bit_contrast
    if args.method == "gc-interp":
        params["fallback"] = args.fallback
    if args.axis and args.method in ("ps", "cgc", "hpmp", "npmp", "gt"):
        params["axis"] = args.axis
    elif args.axis:
        raise UserError(f"--axis applies to the phase methods; {args.method} decodes every axis the scan has codes for")
    t0 = time.perf_counter()
    depth, points, dec = reconstruct_depth(scan, args.method, frames=args.frames, triangulation=args.triangulation,
                                           depth_range=None if args.no_depth_range else "scan", **params)
    t1 = time.perf_counter()
    out = ensure_dir(check_output_folder(args.out))
    np.save(out / "depth.npy", depth.astype(np.float32))
    write_depth_png(out / "depth.png", depth)
    save_depth_color(out / "depth_color.png", depth)
    confidence = decoding_confidence(dec, depth)  # code certainty x signal swing (slwarp.decode.confidence)
    write_confidence(out, confidence)
    save_confidence_map(out / "confidence.png", confidence, f"{args.method} confidence")
    for axis, coord in (("col", dec.col), ("row", dec.row)):
        if coord is not None:
            np.save(out / f"projector_{axis}.npy", coord.astype(np.float32))
    white = scan.frames_with("white")
    shade = scan.images[white[0]] if white else scan.images.max(axis=0)
    n_pts = write_ply(out / "points.ply", points, shade)
    valid = np.isfinite(depth)
    print(f"decoded {scan.source or 'scan'} with {args.method} ({METHODS[args.method].summary})")
    print(f"  frames ({len(dec.frames)}): {', '.join(dec.frames)}")
    print(f"  triangulation: {dec.extra['triangulation']}; valid depth: {valid.mean():.1%} of pixels"
          + (f", {np.nanmin(depth):.1f} .. {np.nanmax(depth):.1f} mm" if valid.any() else ""))
    if dec.extra["baseline_alignment"] < 0.5:
        print(f"  warning: the decoded projector {dec.extra['triangulation']}s see only "
              f"{dec.extra['baseline_alignment']:.0%} of the baseline on this rig: depth from them is ill-conditioned "
              "(decode the codes of the other projector axis)")
    print(f"  time: decode {dec.extra['decode_s']:.2f} s, triangulate {dec.extra['triangulate_s']:.2f} s, "
          f"total {t1 - t0:.2f} s")
    info = {"method": args.method, "frames": dec.frames, "triangulation": dec.extra["triangulation"], "params": params}
    written = ["depth.npy", "depth.png", "depth_color.png", "confidence.npy", "confidence.png", "points.ply"]
    if scan.gt_depth is not None:
        mask = scan.mask if scan.mask is not None else None
        m, cm = _write_metrics(out / "metrics.json", out / "error_map.png", depth, scan, mask,
                               f"{args.method}: |depth error|", confidence, **info)
        print(format_table([(args.method, m)]))
        _print_confidence_metrics(args.method, cm)
        written += ["metrics.json", "error_map.png"]
    else:
        (out / "decode.json").write_text(json.dumps({"scan": scan.source, **info, "valid_share": float(valid.mean())},
                                                    indent=2) + "\n")
        written.append("decode.json")
    print(f"wrote {out}/: {', '.join(written)} ({n_pts} points)")
    return 0


def _add_decode(p):
    from ..decode import METHODS
    from ..decode.frames import DEFAULT_MIN_AMPLITUDE

    p.add_argument("scan", help="scan folder")
    p.add_argument("--method", required=True, choices=list(METHODS),
                   help="; ".join(f"{k}: {m.summary} (sets: {m.pattern_sets})" for k, m in METHODS.items()))
    p.add_argument("--frames", help="use only these frames: " + FRAMES_HELP + "; e.g. 'gray:col:bit=0-5:noinv' "
                   "for GC(6) from a scan with more bits")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--triangulation", default="auto", choices=["auto", "col", "row", "both", "midpoint"],
                   help="projector column or row plane; both: the point on the camera ray that best matches column "
                        "and row; midpoint: ray-ray midpoint (both need column and row codes); auto (default): the "
                        "plane of the projector axis along the baseline, or both codes on an oblique baseline")
    p.add_argument("--axis", choices=["col", "row"], help="axis of the phase methods' patterns (default: the one "
                   "along the baseline when the scan has its frames, else the other)")
    p.add_argument("--min-amplitude", type=float, default=DEFAULT_MIN_AMPLITUDE,
                   help="shadow threshold: half the on/off difference or the phase modulation, in full-scale units "
                        f"(images in [0, 1]; default: {DEFAULT_MIN_AMPLITUDE:g})")
    p.add_argument("--min-bit-contrast", type=float, default=0.0,
                   help="Gray code: minimum per-bit |signal| relative to the amplitude (default: 0, off)")
    p.add_argument("--fallback", default="extrapolate", choices=["extrapolate", "center", "nan"],
                   help="gc-interp: pixels not between two stripe transitions (default: extrapolate)")
    p.add_argument("--no-depth-range", action="store_true", help="keep points outside the scan's depth range")
    _add_outside_paths(p)
    p.set_defaults(func=cmd_decode)


def cmd_evaluate(args) -> int:
    import numpy as np

    from ..evaluation.metrics import format_table
    from ..evaluation.outputs import read_confidence
    from ..scans.scan import load_scan, read_depth
    pred = read_depth(args.pred, "prediction")
    scan = load_scan(args.scan, outside_paths=args.allow_outside_paths)
    if scan.gt_depth is None:
        raise UserError(f"{args.scan}: the scan has no ground-truth depth to evaluate against")
    if pred.shape != scan.gt_depth.shape:
        raise UserError(f"{args.pred}: depth map is {pred.shape[1]}x{pred.shape[0]}, the scan's camera is "
                        f"{scan.gt_depth.shape[1]}x{scan.gt_depth.shape[0]}")
    mask = None if args.no_mask else scan.mask
    # the confidence map: --confidence FILE, else confidence.npy beside the prediction when there is one
    conf_path = Path(args.confidence) if args.confidence else Path(args.pred).parent / "confidence.npy"
    confidence = None
    if args.confidence or conf_path.is_file():
        try:
            confidence = read_confidence(conf_path, pred.shape)
        except ValueError as e:
            raise UserError(str(e)) from None
    json_path, map_path = _evaluation_paths(args.out, Path(args.pred), Path(args.scan))
    info = {"method": args.method, "prediction": str(args.pred)}
    if confidence is not None:
        info["confidence_map"] = str(conf_path)
    m, cm = _write_metrics(json_path, map_path, pred.astype(np.float64), scan, mask,
                           f"{Path(args.pred).name}: |depth error|", confidence, **info)
    print(format_table([(Path(args.pred).name, m)], title_header="prediction"))
    if cm is not None:
        _print_confidence_metrics(f"{conf_path.name} ({conf_path.parent.name})", cm)
    print(f"over {m['n_gt']} ground-truth pixels ({'inside the scan mask' if mask is not None else 'no mask'}); "
          f"wrote {json_path} and {map_path}")
    return 0


EVALUATION_JSON, EVALUATION_MAP = "evaluation.json", "evaluation_error_map.png"  # names no other command writes


def _evaluation_paths(out: str | None, pred: Path, scan_dir: Path) -> tuple[Path, Path]:
    """(metrics JSON, error map) of `evaluate`: --out FILE.json (the map beside it, named after it), --out FOLDER
    (evaluation.json and evaluation_error_map.png in it) or, by default, those names in the prediction's folder;
    never in the scan folder (its files belong to the scan)."""
    from ..evaluation.outputs import check_output_folder

    if out is not None and out.endswith(".json"):
        json_path = Path(out)
        map_path = json_path.with_name(json_path.stem + "_error_map.png")
    else:
        folder = Path(out) if out is not None else pred.parent
        json_path, map_path = folder / EVALUATION_JSON, folder / EVALUATION_MAP
    if json_path.parent.resolve() == scan_dir.resolve():
        raise UserError(f"{json_path.parent}: is the scan folder, which evaluate does not write into; give --out "
                        "FOLDER or FILE.json elsewhere")
    check_output_folder(json_path.parent).mkdir(parents=True, exist_ok=True)
    return json_path, map_path


def _add_evaluate(p):
    p.add_argument("pred", help="predicted depth: .npy (float, mm) or 16-bit PNG (0.1 mm, 0 = invalid)")
    p.add_argument("scan", help="scan folder with ground-truth depth")
    p.add_argument("--out", help=f"FILE.json, or a folder for {EVALUATION_JSON} and {EVALUATION_MAP} (default: the "
                   "prediction's folder; never the scan folder)")
    p.add_argument("--method", help="name of the method that made the prediction, recorded in the metrics")
    p.add_argument("--no-mask", action="store_true", help="evaluate every ground-truth pixel, not only the scan's mask")
    p.add_argument("--confidence", metavar="FILE.npy", help="a confidence map [H, W] in [0, 1] of the prediction "
                   "(default: confidence.npy beside it, when there is one): also report the MAE of its 90%% and 75%% "
                   "most confident pixels and the AUSE")
    _add_outside_paths(p)
    p.set_defaults(func=cmd_evaluate)

