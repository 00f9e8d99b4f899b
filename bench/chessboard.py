"""The real capture (../shared/data/procam_chessboard): the chessboard plate's planarity (RMS distance of its
points to their least-squares plane, and to their least-squares quadric: the local error alone) for the full
40-image Gray code decode, classical decoding of the 7 most
significant ROW bits (no inverses), and the neural SDF trained on those same 7 images.

The rig's baseline is mostly vertical (the projector 273 mm below the camera), so the projector's rows carry
the depth: the decoders triangulate with the row plane (`--triangulation auto`). One row shows the 7 column
bits for contrast: their plane nearly contains the camera rays, so their depth is ill-conditioned.

    python -m bench.chessboard --skip-neural                 # classical rows only (CPU, a minute)
    python -m bench.chessboard --preset paper                # with the neural SDF: needs a GPU
    python -m bench.chessboard --preset tiny --out /tmp/cb   # smoke check of the neural path on a CPU
    python -m bench.chessboard --preset tuned --also-extract refine_range=0,search_repair=true
                                                             # one field, extracted three ways
Writes <out>/chessboard-<cpu|cuda>.json and .md.
"""
from __future__ import annotations

import argparse
import sys
import datetime
import json
import time
from pathlib import Path

import numpy as np

from slwarp.scans.data import data_dir

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = data_dir() / "procam_chessboard"  # $SLWARP_DATA, else ../shared/data (docs/real-captures.md)
DEPTH_RANGE = (1050.0, 1750.0)  # the full decode spans 1117 to 1649 mm (0.5 and 99.5 percentiles)
SEVEN_ROWS = "gray:row:bit=0-6:noinv"  # the 7 most significant row bits, no inverses (role selector)
SEVEN_COLS = "gray:col:bit=0-6:noinv"


def main(argv=None):
    import torch

    from slwarp.decode import reconstruct_depth
    from slwarp.evaluation.metrics import chessboard_region, plane_rms, quadric_rms
    from slwarp.neural.depth_maps import depth_to_points
    from slwarp.neural.reconstruct import reconstruct
    from slwarp.devices import torch_device
    from slwarp.neural.config import default_preset_name, preset
    from slwarp.scans.scan import load_scan

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default=str(DEFAULT_DATA))
    p.add_argument("--preset", default=None, help="neural presets, comma-separated, each PRESET or "
                   "PRESET:key=value:key=value (default: the device's default preset)")
    p.add_argument("--also-extract", default=None, help="extraction variants (comma-separated, each "
                   "key=value:key=value) applied to each trained field after its own extraction")
    p.add_argument("--iters", type=int, default=None)
    p.add_argument("--skip-neural", action="store_true")
    p.add_argument("--out", default=str(REPO / "bench" / "results"))
    args = p.parse_args(argv)
    scan = load_scan(args.data)
    region = chessboard_region(scan.images[scan.frame_with("white")])
    rows = {}

    def record(name, depth, seconds, frames, triangulation):
        pts = depth_to_points(np.where(region, depth, np.nan), scan.camera)
        rms, n = plane_rms(pts)
        rows[name] = {"plane_rms_mm": rms, "quadric_rms_mm": quadric_rms(pts), "points": n,
                      "board_pixels": int(region.sum()), "frames": frames, "triangulation": triangulation,
                      "seconds": seconds}
        print(f"{name}: plane RMS {rms:.3f} mm (about a quadric {rows[name]['quadric_rms_mm']:.3f}) over {n} points "
              f"({n / region.sum():.1%} of the board), {triangulation}, {seconds:.1f} s", flush=True)

    for name, method, frames in (("GC full (40 images)", "gc", None),
                                 ("GC full (40 images) interp", "gc-interp", None),
                                 ("GC 7 row bits", "gc", SEVEN_ROWS),
                                 ("GC 7 row bits interp", "gc-interp", SEVEN_ROWS),
                                 ("GC 7 column bits interp (little depth on this rig)", "gc-interp", SEVEN_COLS)):
        t = time.perf_counter()
        d, _, dec = reconstruct_depth(scan, method, frames=frames, depth_range=DEPTH_RANGE)
        record(name, d, time.perf_counter() - t, len(dec.frames), dec.extra["triangulation"])
    if not args.skip_neural:
        from bench.accuracy_sweep import parse_overrides
        from slwarp.neural.extraction import extract_depth

        seven = scan.select(SEVEN_ROWS)
        for label in (args.preset or default_preset_name(torch_device("auto"))).split(","):
            name, *variant = label.split(":")
            cfg = preset(name, **parse_overrides(",".join(variant)),
                         **({"iters": args.iters} if args.iters is not None else {}))
            t = time.perf_counter()
            res = reconstruct(seven, cfg, out_dir=None, depth_range=DEPTH_RANGE, progress=False, log_every_s=30)
            record(f"neural SDF, 7 row bits (`{label}`)", res.depth, time.perf_counter() - t, len(seven), "-")
            valid = res.trainer.renderer.valid_map.cpu().numpy()
            for extra in filter(None, (args.also_extract or "").split(",")):
                # the same field, other extraction options
                res.trainer.cfg = cfg.with_options(**parse_overrides(extra.replace(":", ",")))
                t = time.perf_counter()
                depth = extract_depth(res.trainer, valid)[0]
                record(f"neural SDF, 7 row bits (`{label}`, extracted with `{extra}`)", depth,
                       time.perf_counter() - t, len(seven), "-")
    device = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "CPU"
    lines = [f"# Real capture: chessboard plate planarity, {device}, {datetime.date.today()}", "",
             "RMS distance (mm) of the reconstructed points inside the 9x7 inner-corner quadrilateral to their plane, and "
             "to their least-squares quadratic surface (the local error without the smooth bend that a calibration error "
             "gives every decoder alike). Vertical baseline: the row codes carry depth. "
             f"`python -m bench.chessboard {' '.join(sys.argv[1:] if argv is None else argv)}`", "",
             "| method | images | triangulation | plane RMS mm | quadric RMS mm | points | share of board | time s |",
             "|---|---|---|---|---|---|---|---|"]
    for k, r in rows.items():
        lines.append(f"| {k} | {r['frames']} | {r['triangulation']} | {r['plane_rms_mm']:.3f} | "
                     f"{r['quadric_rms_mm']:.3f} | {r['points']} | "
                     f"{r['points'] / r['board_pixels']:.1%} | {r['seconds']:.1f} |")
    print("\n".join(lines))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tag = "cuda" if torch.cuda.is_available() else "cpu"
    (out / f"chessboard-{tag}.json").write_text(json.dumps({"device": device, "date": str(datetime.date.today()),
                                                           "rows": rows}, indent=1))
    (out / f"chessboard-{tag}.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
