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
    from ..sim.simulate import CAMERA_MODELS, camera_model, simulate
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
        print("camera models (--camera; the options --gamma, --halo, ... override theirs):")
        for k, v in CAMERA_MODELS.items():
            print(f"  {k:8s} " + (", ".join(f"{o} {x:g}" if isinstance(x, float) else f"{o} {x}" for o, x in v.items())
                                   or "one ray a pixel, linear response, no halo (the built-in scanner)"))
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
    # the camera model's settings, then each option given on the command line over them
    given = {k: getattr(args, k) for k in ("gamma", "ambient", "halo", "halo_sigma", "near_halo", "near_halo_sigma",
                                           "black_level", "bits") if getattr(args, k) is not None}
    given.update({k: False for k in ("noise", "defocus", "shading", "texture") if getattr(args, f"no_{k}")})
    try:
        opts = camera_model(args.camera, seed=args.seed, **given)
    except ValueError as e:  # an unknown camera model, an option out of its range (--gamma, --halo, ...)
        raise UserError(str(e)) from None
    t0 = time.perf_counter()
    scan = simulate(objects, camera, projector, pset, opts, depth_range=depth_range, device=args.device,
                    meta={"scene": args.scene or "meshes", "rig": args.rig, "patterns": args.patterns})
    out = scan.save(args.out, bits=16 if opts.bits in (0, 16) else 8)
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
    p.add_argument("--camera", default="linear",
                   help="camera model (see --list): its optics and response, which the options below override "
                        "(linear: one ray a pixel, linear; procam: the real procam-calibration capture's lens, halos "
                        "and black level; default: linear)")
    p.add_argument("--gamma", type=float, default=None, help="camera gamma (linear camera: 1)")
    p.add_argument("--ambient", type=float, default=None, help="ambient light, full-scale units (linear camera: 0.03)")
    p.add_argument("--halo", type=float, default=None, help="share of the projected light a lens halo spreads around the "
                   "patterns (the real capture's: about 0.1; linear camera: 0, none)")
    p.add_argument("--halo-sigma", type=float, default=None, help="the halo's Gaussian sigma, projector px (default: 40)")
    p.add_argument("--near-halo", type=float, default=None, help="share of the light a second, nearer halo spreads (the "
                   "real capture's: about 0.15 at 3 px; linear camera: 0)")
    p.add_argument("--near-halo-sigma", type=float, default=None, help="the near halo's sigma, projector px (default: 3)")
    p.add_argument("--black-level", type=float, default=None, help="the camera's offset, full-scale units (the real "
                   "capture's: about 0.02; linear camera: 0)")
    p.add_argument("--bits", type=int, default=None, choices=[0, 8, 16], help="image quantisation (0 = none; default: 8)")
    p.add_argument("--device", default=None, help="cpu or cuda:N (default: CUDA when present)")
    p.add_argument("--list", action="store_true", help="list scenes, rigs and pattern sets")
    p.set_defaults(func=cmd_simulate)

