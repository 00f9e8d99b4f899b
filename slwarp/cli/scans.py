"""`slwarp info` (a scan's summary and problems) and `slwarp simulate` (the virtual scanner)."""
from __future__ import annotations

import sys
import time
from pathlib import Path

from .errors import UserError
from .options import FRAMES_HELP, _add_outside_paths


def cmd_info(args) -> int:
    from ..scans.scan import load_scan

    scan = load_scan(args.scan, frames=args.frames, outside_paths=args.allow_outside_paths)
    print(scan.summary(each_frame=args.roles))
    _warn_problems(scan, sys.stdout)
    return 0


def _warn_problems(scan, stream=None, problems: list[str] | None = None) -> None:
    """One 'warning:' line per problem of the scan (Scan.problems: too few frames, black, saturated, no contrast;
    `problems` when they were found already)."""
    for problem in scan.problems() if problems is None else problems:
        print(f"warning: {problem}", file=stream or sys.stderr)


def _add_info(p):
    p.add_argument("scan", help="scan folder (native scan.yaml, NeSS config.ini or procam calibration_result.xml)")
    p.add_argument("--frames", help=FRAMES_HELP)
    p.add_argument("--roles", action="store_true", help="also list every frame with its role")
    _add_outside_paths(p)
    p.set_defaults(func=cmd_info)


def cmd_simulate(args) -> int:
    from ..scans.patterns import named_set
    from ..sim.rigs import DEPTH_RANGE_MM, describe_rigs, make_rig
    from ..sim.scenes import SCENE_NAMES, build_scene, load_mesh_objects
    from ..sim.simulate import SimOptions, simulate
    from ..evaluation.viz import save_scan_preview

    if args.list:
        from ..scans.patterns import NAMED_SETS

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
    try:
        pset = named_set(args.patterns, projector.width, projector.height, seed=args.pattern_seed)
    except ValueError as e:  # an unknown or malformed pattern set name
        raise UserError(f"--patterns: {e}") from None
    if args.scene:
        if args.scene not in SCENE_NAMES:
            raise UserError(f"unknown scene {args.scene!r}; built-in scenes: {', '.join(SCENE_NAMES)}")
        objects, depth_range = build_scene(args.scene), DEPTH_RANGE_MM
    else:
        for m in args.mesh:
            if not Path(m).is_file():
                raise UserError(f"mesh not found: {m}")
        objects, depth_range = load_mesh_objects(args.mesh), None
    try:
        opts = SimOptions(
            noise=not args.no_noise, defocus=not args.no_defocus, gamma=args.gamma, bits=args.bits,
            ambient=args.ambient, shading=not args.no_shading, texture=not args.no_texture, seed=args.seed,
            halo=args.halo, halo_sigma=args.halo_sigma,
        )
    except ValueError as e:  # an option out of its range (--gamma, --halo, ...)
        raise UserError(str(e)) from None
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


def _add_simulate(p):
    from ..sim.rigs import RIG_NAMES

    p.add_argument("--scene", help="built-in scene (see --list)")
    p.add_argument("--mesh", action="append", help="mesh file in mm, camera frame (repeatable)")
    p.add_argument("--patterns", default="random6",
                   help="pattern set, e.g. random6, gray7, gt, random6+gray7, or a pattern-set file PATH/patterns.yaml "
                        "(see --list; default: random6)")
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
    p.add_argument("--halo", type=float, default=0.0, help="share of the projected light a lens halo spreads around the "
                   "patterns (the real capture's: about 0.1; default: 0, none)")
    p.add_argument("--halo-sigma", type=float, default=40.0, help="the halo's Gaussian sigma, projector px (default: 40)")
    p.add_argument("--bits", type=int, default=8, choices=[0, 8, 16], help="image quantisation (0 = none; default: 8)")
    p.add_argument("--device", default=None, help="cpu or cuda:N (default: CUDA when present)")
    p.add_argument("--list", action="store_true", help="list scenes, rigs and pattern sets")
    p.set_defaults(func=cmd_simulate)

