"""The `slwarp` command: one subcommand per pipeline stage.

    slwarp info SCAN                      validate a scan and print its summary
    slwarp simulate --scene NAME ...      render a scan with exact ground truth (virtual scanner)
    slwarp decode SCAN --method M --out D classical decoding (Gray code, CGC, PMP, ...) + triangulation
    slwarp evaluate PRED SCAN             depth metrics of a depth map against the scan's ground truth
    slwarp reconstruct SCAN --out D       the neural SDF method: train, then depth, mesh, point cloud
    slwarp demo                           the paper's comparison on an embedded default scene

Bad input exits with status 2 and a one-line message naming the file and the problem
(SLWARP_DEBUG=1 shows the traceback instead).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path


class UserError(Exception):
    """An error caused by the user's input: printed as one line, exit status 2."""


def _known_errors():
    from .scans.scan import ScanError
    from .scans.scanner import CalibrationError

    from .neural.train import TrainingDiverged

    return (UserError, ScanError, CalibrationError, FileNotFoundError, ValueError, TrainingDiverged)


# ----------------------------------------------------------------------------------------------


def cmd_info(args) -> int:
    from .scans.scan import load_scan

    scan = load_scan(args.scan, frames=args.frames)
    print(scan.summary())
    return 0


def _add_info(sub):
    p = sub.add_parser("info", help="validate a scan and print its summary (rig, frames, ground truth)")
    p.add_argument("scan", help="scan folder (native scan.yaml, NeSS config.ini or procam calibration_result.xml)")
    p.add_argument("--frames", help="frame selection: names, globs, indices or slices, comma-separated")
    p.set_defaults(func=cmd_info)


def cmd_simulate(args) -> int:
    from .scans.patterns import named_set
    from .sim.rigs import DEPTH_RANGE_MM, describe_rigs, make_rig
    from .sim.scenes import SCENE_NAMES, build_scene, load_mesh_objects
    from .sim.simulate import SimOptions, simulate
    from .evaluation.viz import save_scan_preview

    if args.list:
        from .scans.patterns import NAMED_SETS

        print("scenes: " + ", ".join(SCENE_NAMES))
        print("rigs (geometry / small-resolution twin; full: camera 1280x1024, projector 1280x800; small: 320x256, 640x400):")
        for line in describe_rigs():
            print(f"  {line}")
        print("pattern sets (join with '+'):")
        for k, v in NAMED_SETS.items():
            print(f"  {k:22s} {v}")
        return 0
    if not args.out:
        raise UserError("simulate: --out DIR is required")
    if bool(args.scene) == bool(args.mesh):
        raise UserError("simulate: give either --scene NAME or --mesh FILE (repeatable)")
    camera, projector = make_rig(args.rig)
    pset = named_set(args.patterns, projector.width, projector.height, seed=args.pattern_seed)
    if args.scene:
        if args.scene not in SCENE_NAMES:
            raise UserError(f"unknown scene {args.scene!r}; built-in scenes: {', '.join(SCENE_NAMES)}")
        objects, depth_range = build_scene(args.scene), DEPTH_RANGE_MM
    else:
        for m in args.mesh:
            if not Path(m).is_file():
                raise UserError(f"mesh not found: {m}")
        objects, depth_range = load_mesh_objects(args.mesh), None
    opts = SimOptions(
        noise=not args.no_noise, defocus=not args.no_defocus, gamma=args.gamma, bits=args.bits,
        ambient=args.ambient, shading=not args.no_shading, texture=not args.no_texture, seed=args.seed,
    )
    t0 = time.perf_counter()
    scan = simulate(objects, camera, projector, pset, opts, depth_range=depth_range, device=args.device,
                    meta={"scene": args.scene or "meshes", "rig": args.rig, "patterns": args.patterns})
    out = scan.save(args.out, bits=16 if args.bits in (0, 16) else 8)
    save_scan_preview(Path(out) / "preview.png", scan)
    t1 = time.perf_counter()
    scan.source = str(out)
    print(scan.summary())
    tm = scan.meta["timings"]
    print(f"rendered {len(scan)} frames in {tm['total_s']:.2f} s (ray casting {tm['raycast_s']:.2f} s, "
          f"patterns {tm['patterns_s']:.2f} s, imaging {tm['imaging_s']:.2f} s); written in {t1 - t0 - tm['total_s']:.2f} s")
    print(f"wrote {out}/scan.yaml and preview.png")
    return 0


def _add_simulate(sub):
    from .sim.rigs import RIG_NAMES

    p = sub.add_parser("simulate", help="render a scan with exact ground truth on the virtual scanner")
    p.add_argument("--scene", help="built-in scene (see --list)")
    p.add_argument("--mesh", action="append", help="mesh file in mm, camera frame (repeatable)")
    p.add_argument("--patterns", default="random6", help="pattern set, e.g. random6, gray7, gt, random6+gray7 (default: random6)")
    p.add_argument("--rig", default="default", choices=list(RIG_NAMES),
                   help="built-in rig: geometry default, vertical, oblique or rolled, at full resolution or small "
                        "(small, small-vertical, ...; see --list; default: default)")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default: 0)")
    p.add_argument("--pattern-seed", type=int, default=0, help="seed of the random patterns (default: 0)")
    p.add_argument("--out", help="output scan folder")
    p.add_argument("--no-noise", action="store_true", help="switch shot and read noise off")
    p.add_argument("--no-defocus", action="store_true", help="switch projector defocus off")
    p.add_argument("--no-shading", action="store_true", help="switch the cosine and fall-off terms off")
    p.add_argument("--no-texture", action="store_true", help="switch albedo textures off")
    p.add_argument("--gamma", type=float, default=1.0, help="camera gamma (default: 1, linear)")
    p.add_argument("--ambient", type=float, default=0.03, help="ambient light, full-scale units (default: 0.03)")
    p.add_argument("--bits", type=int, default=8, choices=[0, 8, 16], help="image quantisation (0 = none; default: 8)")
    p.add_argument("--device", default=None, help="cpu or cuda:N (default: CUDA when present)")
    p.add_argument("--list", action="store_true", help="list scenes, rigs and pattern sets")
    p.set_defaults(func=cmd_simulate)


def _write_metrics(out: Path, pred, scan, mask, title: str, extra: dict) -> dict:
    """Metrics of `pred` against the scan's ground truth: metrics.json + error_map.png in `out`."""
    import json

    import numpy as np

    from .evaluation.metrics import depth_metrics
    from .evaluation.viz import save_error_map

    m = depth_metrics(pred, scan.gt_depth, mask)
    doc = {**extra, "mask": "scan mask" if mask is not None else "none", "metrics": m}
    (out / "metrics.json").write_text(json.dumps(doc, indent=2, default=float) + "\n")
    shown = pred if mask is None else np.where(mask, pred, np.nan)  # the map shows what the numbers count
    save_error_map(out / "error_map.png", shown, scan.gt_depth, title=title)
    return m


def cmd_decode(args) -> int:
    import json

    import numpy as np

    from .decode import METHODS, reconstruct_depth, write_ply
    from .evaluation.metrics import format_table
    from .scans.scan import load_scan, write_depth_png
    from .evaluation.viz import ensure_dir, save_depth_color

    scan = load_scan(args.scan)
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
    out = ensure_dir(args.out)
    np.save(out / "depth.npy", depth.astype(np.float32))
    write_depth_png(out / "depth.png", depth)
    save_depth_color(out / "depth_color.png", depth)
    for axis, coord in (("col", dec.col), ("row", dec.row)):
        if coord is not None:
            np.save(out / f"projector_{axis}.npy", coord.astype(np.float32))
    shade = scan.image("white") if "white" in scan.names else scan.images.max(axis=0)
    n_pts = write_ply(out / "points.ply", points, shade)
    valid = np.isfinite(depth)
    print(f"decoded {scan.source or 'scan'} with {args.method} ({METHODS[args.method].summary})")
    print(f"  frames ({len(dec.frames)}): {', '.join(dec.frames)}")
    print(f"  triangulation: {dec.extra['triangulation']}; valid depth: {valid.mean():.1%} of pixels"
          + (f", {np.nanmin(depth):.1f} .. {np.nanmax(depth):.1f} mm" if valid.any() else ""))
    print(f"  time: decode {dec.extra['decode_s']:.2f} s, triangulate {dec.extra['triangulate_s']:.2f} s, "
          f"total {t1 - t0:.2f} s")
    info = {"scan": scan.source, "method": args.method, "frames": dec.frames, "triangulation": dec.extra["triangulation"],
            "params": params}
    written = ["depth.npy", "depth.png", "depth_color.png", "points.ply"]
    if scan.gt_depth is not None:
        mask = scan.mask if scan.mask is not None else None
        m = _write_metrics(out, depth, scan, mask, f"{args.method}: |depth error|", info)
        print(format_table([(args.method, m)]))
        written += ["metrics.json", "error_map.png"]
    else:
        (out / "decode.json").write_text(json.dumps({**info, "valid_share": float(valid.mean())}, indent=2) + "\n")
        written.append("decode.json")
    print(f"wrote {out}/: {', '.join(written)} ({n_pts} points)")
    return 0


def _add_decode(sub):
    from .decode import METHODS
    from .decode.frames import DEFAULT_MIN_AMPLITUDE

    p = sub.add_parser("decode", help="decode a scan with a classical method and triangulate (depth map, point cloud)")
    p.add_argument("scan", help="scan folder")
    p.add_argument("--method", required=True, choices=list(METHODS),
                   help="; ".join(f"{k}: {m.summary} (sets: {m.pattern_sets})" for k, m in METHODS.items()))
    p.add_argument("--frames", help="use only these frames (names, globs, indices, slices; comma-separated), "
                   "e.g. 'gc_col_b[0-5]' for GC(6) from a scan with more bits")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--triangulation", default="auto", choices=["auto", "col", "row", "midpoint"],
                   help="projector column/row plane, ray-ray midpoint (needs column and row codes), or auto: "
                        "the plane along the baseline (default)")
    p.add_argument("--axis", choices=["col", "row"], help="axis of the phase methods' patterns (default: col)")
    p.add_argument("--min-amplitude", type=float, default=DEFAULT_MIN_AMPLITUDE,
                   help="shadow threshold: half the on/off difference or the phase modulation, in full-scale units "
                        f"(images in [0, 1]; default: {DEFAULT_MIN_AMPLITUDE:g})")
    p.add_argument("--min-bit-contrast", type=float, default=0.0,
                   help="Gray code: minimum per-bit |signal| relative to the amplitude (default: 0, off)")
    p.add_argument("--fallback", default="extrapolate", choices=["extrapolate", "center", "nan"],
                   help="gc-interp: pixels not between two stripe transitions (default: extrapolate)")
    p.add_argument("--no-depth-range", action="store_true", help="keep points outside the scan's depth range")
    p.set_defaults(func=cmd_decode)


def cmd_evaluate(args) -> int:
    import numpy as np

    from .evaluation.metrics import format_table
    from .scans.scan import load_scan, read_depth
    from .evaluation.viz import ensure_dir

    pred = read_depth(args.pred, "prediction")
    scan = load_scan(args.scan)
    if scan.gt_depth is None:
        raise UserError(f"{args.scan}: the scan has no ground-truth depth to evaluate against")
    if pred.shape != scan.gt_depth.shape:
        raise UserError(f"{args.pred}: depth map is {pred.shape[1]}x{pred.shape[0]}, the scan's camera is "
                        f"{scan.gt_depth.shape[1]}x{scan.gt_depth.shape[0]}")
    mask = None if args.no_mask else scan.mask
    out = ensure_dir(args.out or Path(args.pred).parent)
    m = _write_metrics(out, pred.astype(np.float64), scan, mask, f"{Path(args.pred).name}: |depth error|",
                       {"prediction": str(args.pred), "scan": scan.source})
    print(format_table([(Path(args.pred).name, m)], title_header="prediction"))
    print(f"over {m['n_gt']} ground-truth pixels ({'inside the scan mask' if mask is not None else 'no mask'}); "
          f"wrote {out}/metrics.json and error_map.png")
    return 0


def _add_evaluate(sub):
    p = sub.add_parser("evaluate", help="depth metrics (MAE, RMSE, >1/2/5 mm, completeness) against a scan's ground truth")
    p.add_argument("pred", help="predicted depth: .npy (float, mm) or 16-bit PNG (0.1 mm, 0 = invalid)")
    p.add_argument("scan", help="scan folder with ground-truth depth")
    p.add_argument("--out", help="folder for metrics.json and error_map.png (default: the prediction's folder)")
    p.add_argument("--no-mask", action="store_true", help="evaluate every ground-truth pixel, not only the scan's mask")
    p.set_defaults(func=cmd_evaluate)


def _parse_range(text: str | None):
    if text is None:
        return None
    try:
        near, far = (float(x) for x in text.replace(" ", "").split(","))
    except ValueError:
        raise UserError(f"--depth-range must be NEAR,FAR in mm, got {text!r}") from None
    if not 0 < near < far:
        raise UserError(f"--depth-range needs 0 < NEAR < FAR, got {near}, {far}")
    return near, far


def cmd_reconstruct(args) -> int:
    import numpy as np
    import torch

    from .evaluation.metrics import format_table
    from .neural.reconstruct import reconstruct
    from .scans.scan import load_scan
    from .neural.train import preset, resolve_device

    scan = load_scan(args.scan, frames=args.frames)
    dev = resolve_device(args.device)
    name = args.preset or ("paper" if dev.type == "cuda" else "cpu")
    cfg = preset(name, iters=args.iters, rays=args.rays, lr=args.lr, seed=args.seed, device=str(dev), backend=args.backend,
                 incremental=args.incremental or None, start_frames=args.start_frames, add_every=args.add_every,
                 matmul=args.matmul, depth_method=args.depth_method, mc_resolution=args.mc_resolution,
                 pattern_blur=_parse_blur(args.pattern_blur), photometric_filter=args.photometric_filter)
    depth_range = _parse_range(args.depth_range)
    if depth_range is None and scan.depth_range is None:
        raise UserError(f"{args.scan}: the scan declares no depth range: pass --depth-range NEAR,FAR (mm)")
    print(f"reconstructing {scan.source} ({len(scan)} frames: {', '.join(scan.names)}) with preset '{name}' "
          f"({cfg.iters} iterations, {cfg.rays} rays, {cfg.n_samples}+{cfg.n_importance} samples, "
          f"{cfg.hidden}x{cfg.layers} field) on {dev}" + (f" ({torch.cuda.get_device_name(dev)})" if dev.type == "cuda" else ""))
    res = reconstruct(scan, cfg, out_dir=args.out, resume=args.resume, depth_range=depth_range, use_mask=args.use_mask,
                      progress=not args.quiet)
    t = res.timings
    valid = np.isfinite(res.depth)
    print(f"trained {t['iterations']} iterations in {t['train_wall_s_total']:.1f} s; marching cubes {t['marching_cubes_s']:.1f} s; "
          f"depth {t['depth_s']:.1f} s; valid depth on {valid.mean():.1%} of pixels")
    if res.metrics is not None:
        print(format_table([("neural SDF", res.metrics)]))
    print(f"wrote {args.out}/: depth.npy, depth.png, depth_color.png, mesh.ply, points.ply, loss.png, history.json"
          + (", metrics.json, error_map.png" if res.metrics is not None else "") + "; train/checkpoint.pt (--resume continues)")
    return 0


def _add_reconstruct(sub):
    from .neural.train import PRESETS

    p = sub.add_parser("reconstruct", help="depth, mesh and point cloud from a scan with the neural SDF method")
    p.add_argument("scan", help="scan folder")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--preset", choices=list(PRESETS), help="paper (GPU), cpu (small field, minutes on a CPU), tiny (tests); "
                   "default: paper with a GPU, else cpu")
    p.add_argument("--frames", help="use only these frames (names, globs, indices, slices; comma-separated)")
    p.add_argument("--iters", type=int, help="training iterations (default: the preset's)")
    p.add_argument("--rays", type=int, help="rays per iteration (default: the preset's)")
    p.add_argument("--lr", type=float, help="Adam learning rate (default: the preset's)")
    p.add_argument("--seed", type=int, help="random seed (default: 0)")
    p.add_argument("--device", default="auto", help="auto (CUDA when present), cpu or cuda:N")
    p.add_argument("--backend", default="warp", choices=["warp", "torch"], help="fused Warp kernels or the torch twin")
    p.add_argument("--incremental", action="store_true", help="start with a few frames and add one every --add-every iterations")
    p.add_argument("--start-frames", type=int, help="incremental: frames at the start (default: 3)")
    p.add_argument("--add-every", type=int, help="incremental: iterations between added frames (default: 500)")
    p.add_argument("--resume", action="store_true", help="continue from OUT/train/checkpoint.pt")
    p.add_argument("--depth-range", help="NEAR,FAR camera depth in mm (default: the scan's)")
    p.add_argument("--depth-method", choices=["mesh", "sphere"], help="depth from the marching-cubes mesh (default) or by sphere tracing")
    p.add_argument("--mc-resolution", type=int, help="marching-cubes cells along the volume's longest side")
    p.add_argument("--matmul", choices=["fp32", "tf32"], help="CUDA matrix precision for the MLP (default: the preset's; tf32 for paper and tuned)")
    p.add_argument("--pattern-blur", help="Gaussian blur of the rendered patterns, projector px, or 'auto' (default: "
                   "fitted to the images at the depth-search map)")
    p.add_argument("--photometric-filter", type=float, help="drop depth pixels whose relative RMS residual reaches this "
                   "(default: 0.4; 0 = off)")
    p.add_argument("--use-mask", action="store_true", help="also restrict the depth map to the scan's mask")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_reconstruct)


def _parse_blur(text):
    if text is None or text == "auto":
        return text
    try:
        value = float(text)
    except ValueError:
        raise UserError(f"--pattern-blur: expected a number of projector px or 'auto', got {text!r}") from None
    if not value >= 0:
        raise UserError(f"--pattern-blur must be >= 0, got {text}")
    return value


def cmd_demo(args) -> int:
    from .demo import run_demo

    run_demo(args.out, scene=args.scene, device=args.device, preset_name=args.preset, iters=args.iters,
             backend=args.backend, progress=not args.quiet)
    return 0


def _add_demo(sub):
    from .demo import DEMO_SCENE
    from .sim.scenes import SCENE_NAMES
    from .neural.train import PRESETS

    p = sub.add_parser("demo", help="simulate a scene, reconstruct it with the neural SDF and with Gray code, compare")
    p.add_argument("--out", default="slwarp-demo", help="output folder (default: ./slwarp-demo)")
    p.add_argument("--scene", default=DEMO_SCENE, choices=list(SCENE_NAMES), help=f"built-in scene (default: {DEMO_SCENE})")
    p.add_argument("--device", default="auto", help="auto (CUDA when present), cpu or cuda:N")
    p.add_argument("--preset", choices=list(PRESETS), help="default: paper with a GPU (default rig), cpu without (small rig)")
    p.add_argument("--iters", type=int, help="training iterations (default: the preset's)")
    p.add_argument("--backend", default="warp", choices=["warp", "torch"])
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_demo)


# ----------------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="slwarp",
        description="Depth reconstruction with neural SDFs in camera + projector structured-light systems.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for add in _COMMANDS:
        add(sub)
    return parser


_COMMANDS = [_add_demo, _add_info, _add_simulate, _add_decode, _add_evaluate, _add_reconstruct]


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except _known_errors() as e:
        if os.environ.get("SLWARP_DEBUG"):
            raise
        print(f"slwarp {args.command}: error: {e}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # output piped into `head` and the like
        return 0
    except KeyboardInterrupt:
        print(f"slwarp {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
