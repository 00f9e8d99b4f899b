"""`slwarp design-patterns`: projector patterns optimised for a rig (slwarp.design), written ready to project.

OUT/ receives the pattern-set folder (one 8-bit PNG per pattern and patterns.yaml, slwarp.scans.pattern_files), which
`slwarp simulate --patterns OUT` and `slwarp reconstruct SCAN --patterns OUT` read; design.json (options, the
objective's history, the baselines, timings) and design.png (the patterns, a close-up, the objective's curves).
Ctrl-C stops the descent and writes the best patterns so far (design.json says so), then exits with status 130.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from .errors import UserError
from .options import _add_outside_paths, _parse_range, _positive_int

BASELINES = ("random6", "gray6", "gray7")  # scored beside the design on the same validation pixels
# (steps, camera pixels per step) by default: on a GPU a design of 4 for the default rig takes 27 s (H100); on 2 CPU
# cores 300 steps of 1024 pixels took 116 s for the small rig and reached the objective of the GPU's 1500 x 4096
# (9.2% against 8.9% misses: bench/results/designed-patterns-cpu.md, design-patterns-cli-cuda-default4.md)
GPU_STEPS = (1500, 4096)
CPU_STEPS = (300, 1024)
# the window a design scores by default, (radius, step) camera px: 3 patterns or fewer on a camera at least
# WINDOW_MIN_WIDTH px wide get 5 x 5 windows of pixels 3 px apart (fast, 1280 x 1024 rigs: 0.46-0.71 mm against
# 0.8-5.5 for each pixel alone); otherwise each pixel alone (4 patterns: 0.55-1.20x random 6 against 1.5-3.6x with
# those windows; 3 on the 320 x 256 small rigs: 0.75-0.95 mm against 0.88-1.59; bench/results/README.md, Designed patterns)
SPACED_WINDOW = (2, 3)
WINDOW_MAX_COUNT = 3
WINDOW_MIN_WIDTH = 1280


def default_window(count: int, camera_width: int) -> tuple[int, int]:
    """(window radius, window step) camera px a design of `count` patterns scores by default for a camera
    `camera_width` px wide (see SPACED_WINDOW)."""
    return SPACED_WINDOW if count <= WINDOW_MAX_COUNT and camera_width >= WINDOW_MIN_WIDTH else (0, 1)


def cmd_design(args) -> int:
    import numpy as np
    import torch

    from ..design import DesignOptions, NoiseModel, design_patterns
    from ..devices import torch_device

    camera, projector, depth_range, source = _rig_of(args)
    device = torch_device(args.device or "auto")
    try:
        noise = NoiseModel(ambient=args.ambient, modulation=_pair(args.modulation, "--modulation"),
                           read_noise=args.read_noise, full_well=args.full_well, blur_px=args.blur_px,
                           blur_spread=args.blur_spread)
        steps, pixels = CPU_STEPS if device.type == "cpu" else GPU_STEPS
        steps = steps if args.iterations is None else args.iterations
        window, window_step = default_window(args.count, camera.width) if args.window is None else (args.window, 1)
        window_step = window_step if args.window_step is None else args.window_step
        opts = DesignOptions(count=args.count, iterations=steps, pixels=args.pixels or pixels, lr=args.lr,
                             tol_px=args.tol_px, binary=args.binary, seed=args.seed, noise=noise,
                             window=window, window_step=window_step,
                             report_every=max(1, min(100, steps // 10 or 1)))
    except ValueError as e:
        raise UserError(f"design-patterns: {e}") from None
    axis_baselines = _baselines_for(camera, projector, depth_range)
    say = (lambda s: None) if args.quiet else (lambda s: print(s, flush=True))
    say(f"designing {opts.count} patterns for {source}: projector {projector.width}x{projector.height}, depth "
        f"{depth_range[0]:g}-{depth_range[1]:g} mm, {opts.iterations} steps of {opts.pixels} pixels on {device}, "
        + (f"each pixel in a {2 * opts.window + 1} x {2 * opts.window + 1} window of pixels {opts.window_step} px apart"
           if opts.window else "each pixel alone"))
    try:
        res = design_patterns(camera, projector, depth_range, opts, device=device, baselines=axis_baselines,
                              progress=say)
    except ValueError as e:  # a rig whose rays miss the projector over the depth range
        raise UserError(f"design-patterns: {source}: {e}") from None
    yaml_path = write_design(args.out, res, source, depth_range, {"device": str(device), "torch": torch.__version__})
    lines = [f"{'set':<16} {'loss':>7} {'misses':>8}",
             f"{f'designed {opts.count}':<16} {res.final['loss']:7.4f} {100 * res.final['miss_rate']:7.2f}%"]
    lines += [f"{name:<16} {m['loss']:7.4f} {100 * m['miss_rate']:7.2f}%" for name, m in res.baselines.items()]
    say("\n".join(lines))
    say(f"wrote {yaml_path} ({opts.count} PNGs), design.json, design.png in {res.timings['total_s']:.1f} s"
        + (" (interrupted: the best patterns so far)" if res.interrupted else ""))
    if opts.window_step > 1:  # the search must sum the windows the design scored: the roles tell it
        say(f"the set's roles say window_step={opts.window_step}: reconstruct searches its scans with windows "
            f"{opts.window_step} camera px apart (--search-window-step overrides)")
    if res.interrupted:
        print("slwarp design-patterns: interrupted; the best patterns so far are written", file=sys.stderr)
        return 130
    return 0


def write_design(folder, res, source: str, depth_range, extra: dict | None = None):
    """A design's folder: the pattern set (PNGs + patterns.yaml, its meta saying where the design came from), design.json
    (`extra`, then the DesignResult) and design.png. Returns the path of patterns.yaml."""
    from ..scans.pattern_files import write_pattern_set

    out = Path(folder)
    doc = {"source": source, "depth_range_mm": list(depth_range), **(extra or {}), **res.to_json()}
    meta = {"source": source, "depth_range_mm": list(depth_range), "count": res.options.count,
            "binary": res.options.binary, "objective": "expected miss along the epipolar line (slwarp.design.objective)",
            "final": res.final, "interrupted": res.interrupted, "date": time.strftime("%Y-%m-%d"),
            "noise": doc["options"]["noise"]}
    yaml_path = write_pattern_set(out, res.patterns, meta)
    (out / "design.json").write_text(json.dumps(doc, indent=2))
    save_design_preview(out / "design.png", res)
    return yaml_path


def _pair(text: str, flag: str) -> tuple[float, float]:
    try:
        lo, hi = (float(x) for x in text.split(","))
    except ValueError:
        raise UserError(f"{flag} must be LO,HI, got {text!r}") from None
    return lo, hi


def _rig_of(args):
    """(camera, projector, depth range, a description) from --rig or --scan (and --depth-range)."""
    depth_range = _parse_range(args.depth_range)
    if bool(args.rig) == bool(args.scan):
        raise UserError("design-patterns: give either --rig NAME (a built-in rig) or --scan SCAN (a real rig's calibration)")
    if args.rig:
        from ..sim.rigs import DEPTH_RANGE_MM, make_rig

        try:
            camera, projector = make_rig(args.rig)
        except ValueError as e:
            raise UserError(f"--rig: {e}") from None
        return camera, projector, depth_range or DEPTH_RANGE_MM, f"rig {args.rig}"
    from ..scans.scan import load_scan

    scan = load_scan(args.scan, outside_paths=args.allow_outside_paths)
    if depth_range is None and scan.depth_range is None:
        raise UserError(f"{args.scan}: the scan declares no depth range: pass --depth-range NEAR,FAR (mm)")
    return scan.camera, scan.projector, depth_range or tuple(scan.depth_range), f"the rig of {scan.source}"


def _baselines_for(camera, projector, depth_range) -> tuple[str, ...]:
    """The classical sets to compare with: the paper's random6 and Gray code along the axis that carries depth."""
    from ..design import epipolar_direction

    e = epipolar_direction(camera, projector, depth_range)
    row = abs(e[1]) > abs(e[0])
    return tuple(b if b.startswith("random") or not row else b + "_row" for b in BASELINES)


def save_design_preview(path, res) -> None:
    """design.png: each pattern (downscaled to 640 px wide) beside a 4x close-up of its centre, and the validation
    loss and miss rate against the step."""
    import cv2
    import numpy as np

    from ..evaluation.viz import _curve_panel, write_rgb

    pats = res.patterns.patterns
    K, H, W = pats.shape
    scale = 640.0 / W
    rows = []
    ch, cw = 64, 96  # the close-up: a 96 x 64 px window at the centre, 4x
    for k in range(K):
        small = cv2.resize(pats[k], (640, max(1, int(round(H * scale)))), interpolation=cv2.INTER_AREA)
        crop = pats[k, H // 2 - ch // 2: H // 2 + ch // 2, W // 2 - cw // 2: W // 2 + cw // 2]
        zoom = cv2.resize(crop, (cw * 4, ch * 4), interpolation=cv2.INTER_NEAREST)
        zoom = cv2.resize(zoom, (int(zoom.shape[1] * small.shape[0] / zoom.shape[0]), small.shape[0]),
                          interpolation=cv2.INTER_NEAREST)
        sep = np.ones((small.shape[0], 8), np.float32)
        rows.append(np.concatenate([small, sep, zoom], axis=1))
        rows.append(np.ones((8, rows[-1].shape[1]), np.float32))
    grid = (np.clip(np.concatenate(rows[:-1], axis=0), 0, 1) * 255).astype(np.uint8)
    grid = np.repeat(grid[..., None], 3, axis=2)
    h = res.history
    it = np.asarray(h["iteration"], np.float64)
    if len(it) >= 2:
        curve = _curve_panel(it, [("loss", np.asarray(h["loss"])), ("miss rate", np.asarray(h["miss_rate"]))],
                             f"design of {K} patterns: validation loss and miss rate")
        if curve.shape[1] != grid.shape[1]:
            curve = cv2.resize(curve, (grid.shape[1], int(curve.shape[0] * grid.shape[1] / curve.shape[1])))
        grid = np.concatenate([grid, np.full((8, grid.shape[1], 3), 255, np.uint8), curve], axis=0)
    write_rgb(path, grid)


def _add_design(p):
    p.add_argument("--rig", help="a built-in rig (see `slwarp simulate --list`)")
    p.add_argument("--scan", help="a scan folder whose calibration (and depth range) the design is for")
    p.add_argument("--count", type=_positive_int, default=4, help="patterns to design (default 4; on the virtual scanner 4 designed gave 0.6-1.2x "
                   "the MAE of the paper's 6 random ones, 6 designed under half of it, 3 far more)")
    p.add_argument("--out", required=True, help="output folder: PNGs + patterns.yaml, design.json, design.png")
    p.add_argument("--depth-range", help="NEAR,FAR camera depth in mm (default: the rig's or the scan's)")
    p.add_argument("--iterations", type=int, help="descent steps (default 1500 on a GPU, 300 on the CPU)")
    p.add_argument("--pixels", type=_positive_int, help="camera pixels per step (default 4096 on a GPU, 1024 on the CPU)")
    p.add_argument("--lr", type=float, default=0.05, help="step size (default 0.05)")
    p.add_argument("--tol-px", type=float, default=2.0,
                   help="a code comparison misses when it picks a depth farther than this along the line (projector px; default 2)")
    p.add_argument("--window", type=int, default=None,
                   help="score each pixel with the (2 W + 1)^2 camera pixels around it at one depth, as the depth "
                        "search matches them (its windows: 2); 0: each pixel alone. Default: 2 with --window-step 3 "
                        "for 3 patterns or fewer on a camera >= 1280 px wide, else 0 (the best measured)")
    p.add_argument("--window-step", type=int, default=None,
                   help="camera px between the window's pixels (default 1 unless the window is the default's; 2: as "
                        "many pixels over twice the span); the set's roles record it and reconstruct searches with it")
    p.add_argument("--binary", action="store_true", help="black and white patterns (DLP projectors): sharpened during the descent, rounded at the end")
    p.add_argument("--blur-px", type=float, default=1.0, help="the camera's view of the pattern: Gaussian sigma in projector px (default 1)")
    p.add_argument("--blur-spread", type=float, default=2.0,
                   help="the camera's blur may be up to this factor off --blur-px either way (defocus changes with "
                        "depth): the design is scored over that range; 1: exactly --blur-px (default 2)")
    p.add_argument("--ambient", type=float, default=0.08, help="ambient offset up to this, full scale (default 0.08)")
    p.add_argument("--modulation", default="0.15,0.8", help="LO,HI range of the pattern's modulation at the camera, full scale (default 0.15,0.8)")
    p.add_argument("--read-noise", type=float, default=0.004, help="camera read noise std, full scale (default 0.004)")
    p.add_argument("--full-well", type=float, default=6000.0, help="electrons at full scale, for shot noise (default 6000)")
    p.add_argument("--seed", type=int, default=0, help="seed of every random draw (default 0)")
    p.add_argument("--device", help="cpu or cuda:N (default: CUDA when present)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    _add_outside_paths(p)
    p.set_defaults(func=cmd_design)
