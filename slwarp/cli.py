"""The `slwarp` command: one subcommand per pipeline stage.

    slwarp info SCAN                      validate a scan and print its summary
    slwarp simulate --scene NAME ...      render a scan with exact ground truth (virtual scanner)

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
    from .scan import ScanError
    from .scanner import CalibrationError

    return (UserError, ScanError, CalibrationError, FileNotFoundError, ValueError)


# ----------------------------------------------------------------------------------------------


def cmd_info(args) -> int:
    from .scan import load_scan

    scan = load_scan(args.scan, frames=args.frames)
    print(scan.summary())
    return 0


def _add_info(sub):
    p = sub.add_parser("info", help="validate a scan and print its summary (rig, frames, ground truth)")
    p.add_argument("scan", help="scan folder (native scan.yaml, NeSS config.ini or procam calibration_result.xml)")
    p.add_argument("--frames", help="frame selection: names, globs, indices or slices, comma-separated")
    p.set_defaults(func=cmd_info)


def cmd_simulate(args) -> int:
    from .patterns import named_set
    from .rigs import DEPTH_RANGE_MM, make_rig
    from .scenes import SCENE_NAMES, build_scene, load_mesh_objects
    from .simulate import SimOptions, simulate
    from .viz import save_scan_preview

    if args.list:
        from .patterns import NAMED_SETS

        print("scenes: " + ", ".join(SCENE_NAMES))
        print("rigs: default, small")
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
    p = sub.add_parser("simulate", help="render a scan with exact ground truth on the virtual scanner")
    p.add_argument("--scene", help="built-in scene (see --list)")
    p.add_argument("--mesh", action="append", help="mesh file in mm, camera frame (repeatable)")
    p.add_argument("--patterns", default="random6", help="pattern set, e.g. random6, gray7, gt, random6+gray7 (default: random6)")
    p.add_argument("--rig", default="default", choices=["default", "small"], help="built-in rig (default: default)")
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


_COMMANDS = [_add_info, _add_simulate]


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
