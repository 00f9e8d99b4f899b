"""The `slwarp` command: one subcommand per pipeline stage.

    slwarp info SCAN                      validate a scan and print its summary
    slwarp simulate --scene NAME ...      render a scan with exact ground truth (virtual scanner)
    slwarp decode SCAN --method M --out D classical decoding (Gray code, CGC, PMP, ...) + triangulation
    slwarp evaluate PRED SCAN             depth metrics of a depth map against the scan's ground truth
    slwarp reconstruct SCAN... --out D    the neural SDF method: train, then depth, mesh, point cloud (several
                                          scans: a batch, sharded over torchrun's processes; see slwarp.batch)
    slwarp demo                           the paper's comparison on an embedded default scene

    slwarp --version                      slwarp's version, with torch's and Warp's

The training options of `reconstruct` and `demo` are generated from slwarp.neural.config.TrainConfig (flag,
type, choices, help and the chosen preset's default); `--config FILE.yaml` reads a config, and flags override it.
Their --help shows the common options (COMMON_OPTIONS), --help-all every one, --help-all SECTION one section's.

Bad input (a user error: a missing or malformed file, an option out of range) exits with status 2 and a
one-line message naming the file or option and the problem (SLWARP_DEBUG=1 shows the traceback instead); a
command line argparse rejects adds one line pointing to the command's --help, never the usage. Anything else is
a bug and keeps its traceback.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import textwrap
import time
from pathlib import Path

from . import timeline

timeline.mark("started")  # the interpreter has started and imported the command's module


class UserError(Exception):
    """An error caused by the user's input: printed as one line, exit status 2."""


def _user_errors() -> tuple:
    """The exceptions that report bad input (printed as one line); every other exception is a bug."""
    from .decode.frames import MissingFrames
    from .devices import DeviceError
    from .neural.config import ConfigError
    from .neural.train import CheckpointError, TrainingDiverged
    from .scans.scan import ScanError
    from .scans.scanner import CalibrationError

    # OSError: a file that cannot be found, read or written (a missing folder, no permission, a full disk, an
    # output folder that is a file); CheckpointError: a truncated checkpoint, --resume of another run, a new
    # run over a checkpoint
    return (UserError, ScanError, CalibrationError, ConfigError, DeviceError, MissingFrames, OSError, TrainingDiverged,
            CheckpointError)


# Commands whose library code reports input that does not fit (a method the scan has no codes for, a
# triangulation it cannot do) as a plain ValueError: there it is a user error too.
_VALUE_ERRORS_ARE_USER_ERRORS = {"decode"}


# ----------------------------------------------------------------------------------------------


OUTSIDE_PATHS_HELP = ("read the scan's files (frames, patterns, gt_depth, mask) that lie outside its folder, links "
                      "followed (default: only when its scan.yaml says allow_outside_paths: true; "
                      "--no-allow-outside-paths refuses them even then, for scans from others; see docs/inputs.md)")


def _add_outside_paths(p) -> None:
    p.add_argument("--allow-outside-paths", action=argparse.BooleanOptionalAction, default=None, help=OUTSIDE_PATHS_HELP)


FRAMES_HELP = ("frame selection, comma-separated tokens: frame names, indices, slices (0:7), role selectors "
               "(gray:col:bit=0-6:noinv, phase:row:period=40, white, random:size=20) or name globs (gc_col_b*)")


def cmd_info(args) -> int:
    from .scans.scan import load_scan

    scan = load_scan(args.scan, frames=args.frames, outside_paths=args.allow_outside_paths)
    print(scan.summary(each_frame=args.roles))
    _warn_problems(scan, sys.stdout)
    return 0


def _warn_problems(scan, stream=None) -> None:
    """One 'warning:' line per problem of the scan (Scan.problems: too few frames, black, saturated, no contrast)."""
    for problem in scan.problems():
        print(f"warning: {problem}", file=stream or sys.stderr)


def _add_info(p):
    p.add_argument("scan", help="scan folder (native scan.yaml, NeSS config.ini or procam calibration_result.xml)")
    p.add_argument("--frames", help=FRAMES_HELP)
    p.add_argument("--roles", action="store_true", help="also list every frame with its role")
    _add_outside_paths(p)
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


def _add_simulate(p):
    from .sim.rigs import RIG_NAMES

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


def _write_metrics(json_path: Path, map_path: Path, pred, scan, mask, title: str, confidence=None,
                   **info) -> tuple[dict, dict | None]:
    """Metrics of `pred` against the scan's ground truth: the metrics document (evaluation.metrics_document) at
    `json_path`, the error map at `map_path`; with a confidence map [H, W], also how well it ranks the errors
    (`confidence_metrics`, the document's "confidence"). Returns (metrics, confidence metrics or None)."""
    import json

    import numpy as np

    from .evaluation.metrics import confidence_metrics, depth_metrics, metrics_document
    from .evaluation.viz import save_error_map

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
    from .evaluation.metrics import CONFIDENCE_COLUMNS, format_table

    print("confidence ranking: MAE of the most confident 90% and 75% of the pixels with depth; AUSE: the mean excess "
          "MAE of the most confident x% over the x% with the smallest errors, x = 100 to 50 (0: a perfect ranking; "
          "'random': a confidence that ranks nothing)")
    print(format_table([(name, cm)], CONFIDENCE_COLUMNS, title_header="confidence of"))


def cmd_decode(args) -> int:
    import json

    import numpy as np

    from .decode import METHODS, decoding_confidence, reconstruct_depth
    from .evaluation.metrics import format_table
    from .evaluation.outputs import write_confidence, write_depth_png
    from .evaluation.outputs import write_points_ply as write_ply
    from .evaluation.outputs import check_output_folder
    from .evaluation.viz import ensure_dir, save_confidence_map, save_depth_color
    from .scans.scan import load_scan

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
    from .decode import METHODS
    from .decode.frames import DEFAULT_MIN_AMPLITUDE

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

    from .evaluation.metrics import format_table
    from .evaluation.outputs import read_confidence
    from .scans.scan import load_scan, read_depth
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
    from .evaluation.outputs import check_output_folder

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


def _positive_int(text: str) -> int:
    """argparse's `type` for a count of at least 1."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r} is not allowed; it takes an integer >= 1")
    return value


def _parse_range(text: str | None):
    if text is None:
        return None
    try:
        near, far = (float(x) for x in text.replace(" ", "").split(","))
    except ValueError:
        raise UserError(f"--depth-range must be NEAR,FAR in mm, got {text!r}") from None
    if not (math.isfinite(near) and math.isfinite(far) and 0 < near < far):
        raise UserError(f"--depth-range needs 0 < NEAR < FAR, got {near}, {far}")
    return near, far


# ----------------------------------------------------------------------------------------------
# training options, generated from TrainConfig


# the TrainConfig options that `reconstruct --help` and `demo --help` show; --help-all shows every one
COMMON_OPTIONS = ("field", "iters", "rays", "device", "seed")


def _given(argv, flag: str) -> str | None:
    """The value of `flag` on a command line (--flag VALUE or --flag=VALUE; the last one wins), else None."""
    argv = list(argv or [])
    value = None
    for i, word in enumerate(argv):
        if word == flag and i + 1 < len(argv):
            value = argv[i + 1]
        elif word.startswith(flag + "="):
            value = word.split("=", 1)[1]
    return value


def _chosen_preset(argv) -> str:
    """The preset a reconstruct or demo command line runs with: --preset, else the device's default
    (slwarp.neural.config.DEFAULT_PRESET; the device from --device, default auto). Used for the defaults --help shows."""
    from .devices import DeviceError, torch_device
    from .neural.config import PRESETS, default_preset_name

    if _given(argv, "--preset") in PRESETS:
        return _given(argv, "--preset")
    try:
        return default_preset_name(torch_device(_given(argv, "--device") or "auto"))
    except DeviceError:
        return default_preset_name("cpu")


def _add_config_options(p, preset_name: str, training: bool = True, argv=None) -> None:
    """--preset, --config, --help-all and one flag per TrainConfig option (grouped by section), with the help and
    the default the config declares (and, with `training`, which options may change on --resume); flags the user
    does not give stay out of the namespace. --help shows the COMMON_OPTIONS, --help-all every option."""
    import dataclasses

    from .neural.config import DEFAULT_PRESET, OPTIONS, PRESET_SUMMARIES, PRESETS, SECTIONS
    from .neural.describe import describe

    p.add_argument("--preset", choices=list(PRESETS), help="the starting configuration (see the list below); default: "
                   f"{DEFAULT_PRESET['cuda']} when the device is CUDA, else {DEFAULT_PRESET['cpu']}")
    p.add_argument("--config", metavar="FILE.yaml", help="a TrainConfig in YAML (sections field, sampling, schedule, "
                   "init, runtime, extraction; any option may be left out) applied over the preset; a run's "
                   "config.yaml reads back; flags override it")
    p.add_argument("--help-all", action=_HelpAll, choices=["all", *SECTIONS], help="show every option, grouped by "
                   f"section, and exit; with SECTION ({', '.join(SECTIONS)}) that section's")
    p.description = textwrap.fill(p.description, 100)
    width = max(map(len, PRESET_SUMMARIES))
    default_on = {v: k.replace("cuda", "CUDA").replace("cpu", "the CPU") for k, v in DEFAULT_PRESET.items()}
    # --help: one line per preset, generated from its config; --help-all: what each preset is for
    p.epilog = "presets (--help-all says what each is for):\n" + "\n".join(
        f"  {k:{width}s} {describe(cfg)}" + (f"; default on {default_on[k]}" if k in default_on else "")
        for k, cfg in PRESETS.items())
    p.epilog += (f"\n\n{len(OPTIONS) - len(COMMON_OPTIONS)} more options: '{p.prog} --help-all' lists every option "
                 f"by section, '{p.prog} --help-all SECTION' one section")
    p.epilog_all = "presets:\n" + "\n".join(
        textwrap.fill(v, 100, initial_indent=f"  {k:{width}s} ", subsequent_indent=" " * (width + 3))
        for k, v in PRESET_SUMMARIES.items())
    p.formatter_class = _Formatter
    defaults = PRESETS[preset_name]
    # the field that trains: the preset's, or --field's; the other kind's options do not apply to it
    kind = _given(argv, "--field") if _given(argv, "--field") in ("mlp", "hashgrid") else defaults.field.kind
    field_keys = dataclasses.replace(defaults.field, kind=kind).network()
    for section, cls in SECTIONS.items():
        title = cls.__doc__.splitlines()[0].rstrip(".")
        group = p.add_argument_group(f"{section}: {title[0].lower() + title[1:]}")
        for opt in (o for o in OPTIONS.values() if o.section == section):
            default = defaults.get(opt.name)
            shown = "none" if default is None else str(default).lower() if opt.is_bool else default
            if section == "field" and opt.key not in field_keys:
                shown = f"not used by the {kind} field"
            resumable = "; may change on resume" if opt.resumable and training else ""
            kw = dict(dest=opt.name, default=argparse.SUPPRESS,
                      help=f"{opt.help} (preset {preset_name}: {shown}{resumable})")
            if opt.is_bool:
                kw["action"] = argparse.BooleanOptionalAction
            else:
                kw["type"] = _option_parser(opt)
                kw["metavar"] = opt.metavar()
            action = group.add_argument("--" + opt.name.replace("_", "-"), **kw)
            if opt.name not in COMMON_OPTIONS:
                action.help_section = section


def _option_parser(opt):
    """argparse's `type` for an option: its parser, with errors as argparse reports them (naming the flag, so
    the config's 'option NAME (section.key): ' prefix is left out)."""

    def parse(text):
        from .neural.config import ConfigError

        try:
            return opt.parse(text)
        except ConfigError as e:
            message, prefix = str(e), f"option {opt.name} ({opt.section}.{opt.key}): "
            raise argparse.ArgumentTypeError(message[len(prefix):] if message.startswith(prefix) else message) from None

    return parse


def _config_from_args(args):
    """(preset name, TrainConfig, torch device) of a reconstruct or demo command line: the preset, the --config
    file over it, the flags given over both; the device resolved."""
    from .devices import torch_device
    from .neural.config import OPTIONS, default_preset_name, load_config, preset

    given = {name: getattr(args, name) for name in OPTIONS if hasattr(args, name)}
    name = args.preset or default_preset_name(torch_device(given.get("device", "auto")))
    cfg = preset(name)
    if args.config:
        cfg = load_config(args.config, base=cfg)
    cfg = cfg.with_options(**given)
    dev = torch_device(cfg.runtime.device)
    return name, cfg.with_options(device=str(dev)), dev


def cmd_reconstruct(args) -> int:
    """One scan folder: reconstructed here into --out. Several scans (or a folder of them, or a glob), under
    torchrun, or with --per-device: a batch (_reconstruct_batch)."""
    import numpy as np
    import torch

    from .batch import find_scans, launched_by_torchrun
    from .evaluation.metrics import format_table
    from .neural.describe import describe
    from .neural.reconstruct import reconstruct
    from .scans.scan import load_scan

    timeline.mark("imports")
    name, cfg, dev = _config_from_args(args)
    if args.per_device is not None and launched_by_torchrun():
        raise UserError("--per-device starts its own worker processes: under torchrun use --nproc-per-node "
                        "(K x GPUs for K scans per GPU) instead")
    found = find_scans(args.scans)
    if not found.single or args.per_device is not None or launched_by_torchrun():
        return _reconstruct_batch(args, found, name, cfg, dev)
    scan_path = args.scans[0]
    scan = load_scan(scan_path, frames=args.frames, outside_paths=args.allow_outside_paths)
    timeline.mark("scan loaded")
    _warn_problems(scan)
    depth_range = _parse_range(args.depth_range)
    if depth_range is None and scan.depth_range is None:
        raise UserError(f"{scan_path}: the scan declares no depth range: pass --depth-range NEAR,FAR (mm)")
    print(f"reconstructing {scan.source} ({len(scan)} frames: {', '.join(scan.names)}) with preset '{name}'"
          + (f" + {args.config}" if args.config else "")
          + f" ({describe(cfg)}) on {dev}" + (f" ({torch.cuda.get_device_name(dev)})" if dev.type == "cuda" else ""))
    timeline.mark("reconstruct")
    res = reconstruct(scan, cfg, out_dir=args.out, resume=args.resume, depth_range=depth_range, use_mask=args.use_mask,
                      progress=not args.quiet, overwrite=args.overwrite)
    timeline.mark("reconstructed")
    t = res.timings
    valid = np.isfinite(res.depth)
    print(f"trained {t['iterations']} iterations in {t['train_wall_s_total']:.1f} s; marching cubes {t['marching_cubes_s']:.1f} s; "
          f"depth {t['depth_s']:.1f} s; confidence {t['confidence_s']:.1f} s; valid depth on {valid.mean():.1%} of pixels")
    print("pixels: " + ", ".join(f"{k.replace('_', ' ')} {v / valid.size:.1%}" for k, v in t["pixels"].items() if v)
          + " (pixel_fate.png)")
    if t.get("refine_misfit") is not None and not t["refined"] and t.get("refine_check") is None:
        print("photometric refinement skipped: the pattern model's misfit at the field's depth is "
              f"{t['refine_misfit']:.4f}, above --refine-max-misfit {cfg.extraction.refine_max_misfit} (optics the model lacks, e.g. a real "
              "lens or a camera response: refining would fit those; --refine-max-misfit 0 refines regardless)")
    check = t.get("refine_check")
    if check and check["before"]:
        before, after = np.mean(check["before"]), np.mean(check["after"])
        print(f"photometric refinement {'kept' if check['keep'] else 'not kept'}: held-out frames' median residual "
              f"{before:.4f} -> {after:.4f} ({len(check['before'])} frames held out in turn; without --refine-check it is kept "
              "regardless)")
    if res.metrics is not None:
        print(format_table([("neural SDF", res.metrics)]))
    print(f"wrote {args.out}/: depth.npy, depth.png, depth_color.png, confidence.npy, confidence.png, pixel_fate.png, "
          "mesh.ply, "
          "points.ply, loss.png, history.json, "
          "config.yaml" + (", metrics.json, error_map.png" if res.metrics is not None else "")
          + "; train/checkpoint.pt (--resume continues)")
    return 0


def _reconstruct_batch(args, found, name: str, cfg, dev) -> int:
    """The scans `found` (slwarp.batch.find_scans) as a batch: each into --out/<name>/ (--out for a lone scan
    folder), a summary printed by the process that gathers it; exit status 1 when a scan failed."""
    from .batch import BatchOptions, run_batch
    from .neural.describe import describe

    rank = int(os.environ.get("RANK", 0))
    if rank == 0:
        for folder in found.ignored:
            print(f"note: {folder} holds no scan: passed over", file=sys.stderr)
        how = (f"{args.per_device} per device" if args.per_device is not None else
               f"torchrun, {os.environ['WORLD_SIZE']} processes" if "WORLD_SIZE" in os.environ else "one after another")
        print(f"reconstructing {len(found.scans)} scans ({how}) with preset '{name}'" + (f" + {args.config}" if args.config else "")
              + f" ({describe(cfg)}) on {dev}", flush=True)
    options = BatchOptions(frames=args.frames, depth_range=_parse_range(args.depth_range), use_mask=args.use_mask,
                           resume=args.resume, overwrite=args.overwrite, progress=not args.quiet, log=not args.quiet,
                           outside_paths=args.allow_outside_paths)
    summary = run_batch(found.scans, cfg, args.out, options, single=found.single, per_device=args.per_device)
    if summary is None:  # a rank other than 0: rank 0 reports
        return 0
    print(summary.report())
    print(f"wrote {args.out}/summary.json and summary.md" + ("" if found.single else "; each scan's outputs in its folder"))
    return 1 if summary.failed else 0


def _add_reconstruct(p, argv=None):
    name = _chosen_preset(argv)
    p.description = ("Train the neural SDF on a scan, then write its depth map, mesh, point cloud and config.yaml. "
                     f"The defaults shown are preset {name}'s (--preset P --help shows P's).")
    p.add_argument("scans", nargs="+", metavar="SCAN",
                   help="a scan folder, a folder of scan folders, or a quoted glob; several scans (or a folder of "
                        "them, or a glob) write each scan's outputs into OUT/<scan name>/ and a summary "
                        "(OUT/summary.json, summary.md), and exit with status 1 when a scan failed; a lone scan "
                        "folder writes into OUT itself. Under torchrun the scans are shared over its processes "
                        "(GPU LOCAL_RANK %% device count)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--frames", help="use only these frames (names, globs, indices, slices; comma-separated)")
    p.add_argument("--resume", action="store_true", help="continue from OUT/train/checkpoint.pt: the same scan, frames, "
                   "depth range and options, except those marked 'may change on resume' below; with several scans: "
                   "skip the scans whose outputs are complete, continue those with a checkpoint, start the others")
    p.add_argument("--overwrite", action="store_true", help="start again, replacing the checkpoint in OUT (without it a "
                   "run into a folder with a checkpoint is refused)")
    p.add_argument("--per-device", type=_positive_int, metavar="K", help="run K scans at a time on each device (every visible "
                   "GPU for --device cuda or auto, the CPU for cpu) in worker processes started here, without torchrun")
    p.add_argument("--depth-range", help="NEAR,FAR camera depth in mm (default: the scan's)")
    p.add_argument("--use-mask", action="store_true",
                   help="also restrict the depth map to the scan's mask").help_section = "reconstruct"
    p.add_argument("--quiet", action="store_true", help="no progress output")
    _add_outside_paths(p)
    _add_config_options(p, name, argv=argv)
    p.set_defaults(func=cmd_reconstruct)


def cmd_watch(args) -> int:
    """A scanning station (slwarp.watch): each complete scan folder that appears in DIR, reconstructed into OUT/<name>/
    by this one process; stops on Ctrl-C / SIGTERM (exit status 130 / 143) or as --max-scans / --until-idle say."""
    from .batch import BatchOptions
    from .watch import watch

    _name, cfg, _dev = _config_from_args(args)
    options = BatchOptions(frames=args.frames, depth_range=_parse_range(args.depth_range), use_mask=args.use_mask)
    return watch(args.inbox, args.out, cfg, options, poll_s=args.poll, settle_s=args.settle, max_scans=args.max_scans,
                 until_idle=args.until_idle, say=lambda text: print(text, flush=True))


def _add_watch(p, argv=None):
    name = _chosen_preset(argv)
    p.description = ("Watch DIR and reconstruct each scan folder that appears in it, once complete (its "
                     "scan.yaml and every file it names present, nothing still growing), into OUT/<name>/ as "
                     "`reconstruct` does, in this one warm process: one line per scan. Scans done before are "
                     "skipped, a scan with a checkpoint continues, a broken scan is reported and the station goes "
                     "on; links leading out of DIR are ignored. Ctrl-C or SIGTERM stops it without losing a "
                     f"finished scan. The defaults shown are preset {name}'s.")
    p.add_argument("inbox", metavar="DIR", help="the folder scans arrive in (one sub-folder per scan)")
    p.add_argument("--out", required=True, help="output folder: OUT/<scan folder name>/ per scan")
    p.add_argument("--frames", help="use only these frames of each scan (names, globs, indices, slices)")
    p.add_argument("--depth-range", help="NEAR,FAR camera depth in mm for scans that declare none")
    p.add_argument("--use-mask", action="store_true", help="also restrict each depth map to its scan's mask")
    p.add_argument("--poll", type=float, default=0.5, metavar="S", help="seconds between looks at DIR (default 0.5)")
    p.add_argument("--settle", type=float, default=1.0, metavar="S",
                   help="a scan folder is taken once no file in it changed for S seconds (default 1)")
    p.add_argument("--max-scans", type=_positive_int, metavar="N", help="stop after N scans")
    p.add_argument("--until-idle", action="store_true", help="stop once every scan in DIR is done or failed")
    _add_config_options(p, name, argv=argv)
    p.set_defaults(func=cmd_watch)


def cmd_demo(args) -> int:
    from .demo import run_demo

    name, cfg, _ = _config_from_args(args)
    run_demo(args.out, scene=args.scene, config=cfg, preset_name=name, progress=not args.quiet)
    return 0


def _add_demo(p, argv=None):
    from .demo import DEMO_SCENE
    from .sim.scenes import SCENE_NAMES

    name = _chosen_preset(argv)
    p.description = ("The paper's comparison on a simulated scene (the default rig on CUDA, the small rig on the CPU). "
                     f"The defaults shown are preset {name}'s (--preset P --help shows P's).")
    p.add_argument("--out", default="slwarp-demo", help="output folder (default: ./slwarp-demo)")
    p.add_argument("--scene", default=DEMO_SCENE, choices=list(SCENE_NAMES), help=f"built-in scene (default: {DEMO_SCENE})")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    _add_config_options(p, name, training=False, argv=argv)
    p.set_defaults(func=cmd_demo)


# ----------------------------------------------------------------------------------------------


class _Parser(argparse.ArgumentParser):
    """argparse as slwarp answers: a bad command line is one error line and a hint to --help (exit status 2, no
    usage dump); --help hides the options marked with a `help_section` (the rarely needed ones), which --help-all
    shows (every one, or one section's)."""

    help_shown: str | None = None  # set by --help-all: "all" or a section
    epilog_all: str | None = None  # the epilog of --help-all, when it differs from --help's

    def error(self, message):
        if message.startswith("argument "):  # argparse's "argument --iters: ...": the flag is enough
            message = message[len("argument "):]
        self.exit(2, f"{self.prog}: error: {message}\nsee '{self.prog} --help'\n")

    def format_help(self):
        hidden = [a for a in self._actions if getattr(a, "help_section", None)
                  and self.help_shown != "all" and a.help_section != self.help_shown]
        kept = [a.help for a in hidden], self.epilog
        for a in hidden:
            a.help = argparse.SUPPRESS
        if self.help_shown and self.epilog_all:
            self.epilog = self.epilog_all
        try:
            return super().format_help()
        finally:
            for a, h in zip(hidden, kept[0]):
                a.help = h
            self.epilog = kept[1]


class _Formatter(argparse.RawDescriptionHelpFormatter):
    """Option help wrapped at spaces only (a preset name such as cpu-hashgrid stays whole); the description and
    epilog as written."""

    def _split_lines(self, text, width):
        return textwrap.wrap(" ".join(text.split()), width, break_on_hyphens=False)


class _HelpAll(argparse.Action):
    """--help-all [SECTION]: the help with every option (or the common ones and SECTION's), then exit."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, choices=None, help=None):
        super().__init__(option_strings, dest, nargs="?", const="all", default=default, choices=choices,
                         metavar="SECTION", help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        parser.help_shown = values or "all"
        parser.print_help()
        parser.exit()


class _Version(argparse.Action):
    """--version: slwarp's version and those of torch and Warp, then exit."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS,
                 help="print the versions of slwarp, torch and Warp and exit"):
        super().__init__(option_strings, dest, nargs=0, default=default, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        print(version_text())
        parser.exit()


def version_text() -> str:
    """'slwarp X.Y.Z (torch A, warp B, Python C)' from the installed packages' metadata: nothing is imported, so it
    answers at once."""
    import platform
    from importlib import metadata

    def installed(dist):
        try:
            return metadata.version(dist)
        except metadata.PackageNotFoundError:
            return None

    own = installed("slwarp")
    if own is None:  # run from a source tree that is not installed
        from . import __version__ as own
    others = [f"{name} {v}" for name, v in (("torch", installed("torch")), ("warp", installed("warp-lang"))) if v]
    return f"slwarp {own} ({', '.join([*others, f'Python {platform.python_version()}'])})"


def build_parser(argv=None) -> argparse.ArgumentParser:
    """The `slwarp` parser. argv (the command line to parse) picks the preset whose defaults --help shows, and the
    command whose options are built: the others get their name and summary only, so that `slwarp --help`, `slwarp
    --version` and the light commands do not load the training configuration (and torch). argv None: every command
    in full."""
    parser = _Parser(prog="slwarp",
                     description="Depth reconstruction with neural SDFs in camera + projector structured-light systems.")
    parser.add_argument("--version", action=_Version)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    argv = None if argv is None else list(argv)
    named = argv[0] if argv and "--version" not in argv else None  # the top level has no option taking a value
    for name, (summary, add) in _COMMANDS.items():
        p = sub.add_parser(name, help=summary)
        p.add_argument("--version", action=_Version)
        if argv is None or name == named:
            add(p, argv) if name in _TRAINING_COMMANDS else add(p)
    parser.commands = sub.choices
    return parser


# name: (summary in the command list, the function that adds its options)
_COMMANDS = {
    "demo": ("simulate a scene, reconstruct it with the neural SDF and with Gray code, compare", _add_demo),
    "info": ("validate a scan and print its summary (rig, frames, ground truth)", _add_info),
    "simulate": ("render a scan with exact ground truth on the virtual scanner", _add_simulate),
    "decode": ("decode a scan with a classical method and triangulate (depth map, point cloud)", _add_decode),
    "evaluate": ("depth metrics (MAE, RMSE, >1/2/5 mm, completeness) against a scan's ground truth, and how well a "
                 "confidence map ranks the errors", _add_evaluate),
    "reconstruct": ("depth, mesh and point cloud from a scan with the neural SDF method", _add_reconstruct),
    "watch": ("a scanning station: reconstruct each scan folder that appears in a folder, in one warm process",
              _add_watch),
}
_TRAINING_COMMANDS = ("demo", "reconstruct", "watch")  # their options come from TrainConfig (and the chosen preset)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(argv)
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # reported by the command's parser: its name and its --help
        parser.commands[args.command].error(f"unrecognized arguments: {' '.join(unknown)}")
    try:
        return int(args.func(args) or 0)
    except BrokenPipeError:  # output piped into `head` and the like
        return 0
    except _interrupted() as e:
        print(f"slwarp {args.command}: {e}", file=sys.stderr)
        return e.exit_status
    except _user_errors() as e:
        return _report(args, e)
    except ValueError as e:
        if args.command not in _VALUE_ERRORS_ARE_USER_ERRORS:
            raise
        return _report(args, e)
    except KeyboardInterrupt:
        print(f"slwarp {args.command}: interrupted", file=sys.stderr)
        return 130


def entry() -> None:
    """The `slwarp` console command and `python -m slwarp`: `main`, then the process ends as soon as its output is
    flushed. Why not a plain return: the interpreter's teardown (torch's, Warp's and CUDA's exit handlers, every
    module's objects freed) ran for seconds after the last output file was closed, while the user waited on the
    prompt; every file a command writes is closed (or renamed into place) before `main` returns."""
    code = main()
    timeline.mark("exit")
    timeline.write()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def _interrupted():
    from .neural.train import TrainingInterrupted

    return TrainingInterrupted


def _report(args, error: Exception) -> int:
    """A user error as one line on stderr (exit status 2); SLWARP_DEBUG=1 re-raises it with its traceback."""
    if os.environ.get("SLWARP_DEBUG"):
        raise error
    print(f"slwarp {args.command}: error: {error}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
