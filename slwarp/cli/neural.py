"""The commands of the neural SDF method: `slwarp reconstruct` (one scan, or a batch: slwarp.batch), `slwarp watch`
(a scanning station: slwarp.watch) and `slwarp demo` (the paper's comparison: slwarp.demo)."""
from __future__ import annotations

import os
import sys

from .. import timeline
from .errors import UserError
from .loader import load_beside
from .options import (_add_config_options, _add_outside_paths, _chosen_preset, _config_from_args, _non_negative_int,
                      _parse_range, _positive_int)
from .scans import _warn_problems


def cmd_reconstruct(args) -> int:
    """One scan folder: reconstructed here into --out. Several scans (or a folder of them, or a glob), under
    torchrun, or with --per-device: a batch (_reconstruct_batch)."""
    from ..batch.launch import pin_torchrun_rank

    pin_torchrun_rank(_requested_device(args))  # a torchrun rank sees only its own GPU, before CUDA starts here
    found = _found_or_none(args)  # the scans, looked for once here; None: the command reports why, in its order
    args.per_device, args.per_device_default = _per_device(args, found), args.per_device is None
    ahead = load_beside(args)  # one scan: loaded in a process of its own while this one imports (cli.loader)
    pool = _early_pool(args, found)  # --per-device: the workers start before this process imports torch
    try:
        return _reconstruct(args, pool, ahead, found)
    finally:
        if pool is not None:
            pool.close()


# Scans at a time on each GPU for a batch on GPUs when --per-device is not given. Two workers share a GPU's idle
# moments (the setup's host work, the extraction): on one H200 16 `fast` scans took 39.3 s against 51.0 one after
# another (1.30x) and 8 `accurate` scans 55.7 s against 62.5 (1.12x); on four H200s two each 15.6-15.7 s against
# 16.1-17.0 with one (bench/results/batch-throughput-cuda-h200-two-per-gpu.md). A worker held at most 6.1 GiB of its
# GPU there (`accurate`): two only where every GPU has at least DEFAULT_PER_GPU_MIN_GIB.
DEFAULT_PER_GPU = 2
DEFAULT_PER_GPU_MIN_GIB = 20.0


def _found_or_none(args):
    """batch.find_scans(args.scans), or None where it raises (the command raises it again where it reports errors)."""
    from ..batch.discovery import find_scans

    try:
        return find_scans(args.scans)
    except Exception:  # noqa: BLE001
        return None


def _per_device(args, found) -> int | None:
    """The batch's scans at a time per device: --per-device K as given (0: one after another in this process, None);
    without it DEFAULT_PER_GPU for several scans on GPUs of DEFAULT_PER_GPU_MIN_GIB or more, told without torch
    (the driver's GPU listing and NVML), else None: one after another in this process (the CPU, one scan folder,
    torchrun's ranks, MIG slices, GPUs that cannot be told). found: _found_or_none(args)."""
    from ..batch.launch import launched_by_torchrun, visible_device_ids
    from ..driver import smallest_gpu_memory_gib

    if args.per_device is not None:
        return args.per_device or None
    device = _requested_device(args)
    ids = None if launched_by_torchrun() or device == "cpu" else visible_device_ids(device)
    # a MIG slice's memory is a share of the GPU's, which is all NVML's total says: one worker there
    if not ids or any(i.upper().startswith("MIG") for i in ids):
        return None
    if found is None or found.single or len(found.scans) < 2:
        return None
    memory = smallest_gpu_memory_gib()
    return DEFAULT_PER_GPU if memory is not None and memory >= DEFAULT_PER_GPU_MIN_GIB else None


def _early_pool(args, found):
    """The WorkerPool of `reconstruct --per-device K` (given, or the default on GPUs: _per_device; not under
    torchrun), no more workers than scans, started now, while this process has imported nothing heavy: its
    workers' imports and runtime starts (about 2-3 s) overlap this process's own and its planning. None without
    workers to start, or when the device count cannot be told without torch (the batch then starts them itself).
    found: _found_or_none(args)."""
    from ..batch.launch import WorkerPool, launched_by_torchrun, visible_device_count

    if args.per_device is None or launched_by_torchrun():
        return None

    count = visible_device_count(_requested_device(args))
    if count is None:
        return None
    if found is None:  # no workers for a command that will fail: the command reports its errors in their order
        return None
    timeline.mark("pool")
    pool = WorkerPool(min(args.per_device * count, len(found.scans)), _WorkerConfig(args),
                      _batch_options(args, progress=False), per_device=args.per_device, device=_requested_device(args))
    timeline.mark("pool started")
    # This process only plans and collects: its check that CUDA is there counts the GPUs through NVML instead of
    # starting the driver (cuInit), which would queue in the driver with the workers' starts (slwarp.driver).
    os.environ.setdefault("PYTORCH_NVML_BASED_CUDA_CHECK", "1")
    return pool


class _WorkerConfig:
    """A worker's TrainConfig from the command line, made in the worker (picklable: the parsed arguments)."""

    def __init__(self, args):
        self.args = args

    def __call__(self):
        return _config_from_args(self.args)[1]


def _requested_device(args) -> str:
    """The device the command line asks for, unresolved: --device, else the --config file's, else 'auto'."""
    if getattr(args, "device", None):
        return args.device
    if args.config:
        try:
            from ..neural.config import load_config, preset

            return load_config(args.config, base=preset("tiny")).runtime.device
        except Exception:  # noqa: BLE001 - a bad file is reported by the command itself
            return "auto"
    return "auto"


def _batch_options(args, progress: bool):
    from ..batch.jobs import BatchOptions

    return BatchOptions(frames=args.frames, depth_range=_parse_range(args.depth_range), use_mask=args.use_mask,
                        resume=args.resume, overwrite=args.overwrite, progress=progress, log=not args.quiet,
                        outside_paths=args.allow_outside_paths, patterns=args.patterns, overlap=args.overlap)


def _reconstruct(args, pool, ahead=None, found=None) -> int:
    import numpy as np
    import torch

    from ..batch import find_scans, launched_by_torchrun
    from ..devices import start_runtimes
    from ..evaluation.metrics import format_table
    from ..neural.describe import describe
    from ..neural.reconstruct import reconstruct
    from ..scans.scan import load_scan

    timeline.mark("imports")
    name, cfg, dev = _config_from_args(args)
    if args.per_device is not None and launched_by_torchrun():
        raise UserError("--per-device starts its own worker processes: under torchrun use --nproc-per-node "
                        "(K x GPUs for K scans per GPU) instead")
    found = ahead.found if ahead is not None else found if found is not None else find_scans(args.scans)
    # a bad file is reported before any scan runs (with a loader process, by it, which reads the file for the scan)
    pset = _pattern_set(args.patterns) if ahead is None else None
    if not found.single or args.per_device is not None or launched_by_torchrun():
        return _reconstruct_batch(args, found, name, cfg, dev, pool)
    scan_path = args.scans[0]
    start_runtimes(dev)  # beside the scan's loading (or its receiving from the process that loaded it)
    if ahead is not None:
        scan = ahead.scan()
    else:
        scan = load_scan(scan_path, frames=args.frames, outside_paths=args.allow_outside_paths, patterns=pset)
    timeline.mark("scan loaded")
    _warn_problems(scan, problems=None if ahead is None else ahead.problems)
    depth_range = _parse_range(args.depth_range)
    if depth_range is None and scan.depth_range is None:
        raise UserError(f"{scan_path}: the scan declares no depth range: pass --depth-range NEAR,FAR (mm)")
    if dev.type == "cuda":  # CUDA's start now (needed next anyway): the device's name then comes without NVML's start
        torch.cuda.init()
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
    fit = t.get("pattern_halo_fit")
    if fit:
        print(f"lens halo: {t['pattern_halo']:.3f} of the light over {fit['sigma_px']:g} projector px (pattern model's "
              f"misfit {fit['misfits'][0]:.4f} without, {min(fit['misfits']):.4f} at best; --pattern-halo 0 leaves it out)")
    if t.get("lens_schedule"):
        print("trained for a lens with a halo: " + ", ".join(f"{k} {v:g}" for k, v in t["lens_schedule"].items())
              + " (--lens-variance-lr-factor none --lens-lambda-reg none trains as without one)")
    if t.get("refine_skipped") == "lens halo":
        print("photometric refinement skipped: the pattern model needed a lens halo, as real lenses have; it only "
              "approximates such optics, and refining would fit its errors (--refine-through-halo refines regardless; "
              "with --refine-check as well it is kept only if held-out frames agree)")
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
    retried = t.get("lost_surface_retry")
    if retried:
        print(f"the training with seed {retried['seed']} lost the surface ({retried['lost']:.0%} of the lit pixels without "
              f"a depth in range): trained again with seed {retried['seed'] + 1}"
              + (", which lost it too" if t.get("surface_lost") else ", which kept it"))
    if t.get("surface_lost"):
        from ..neural.reconstruct import lost_surface_message

        print(f"warning: {lost_surface_message(t['surface_lost'], res.trainer.depth_range)}", file=sys.stderr)
    if t.get("range_missed"):
        from ..neural.reconstruct import range_missed_message

        print(f"warning: {range_missed_message(t['range_missed'], res.trainer.depth_range)}", file=sys.stderr)
    if res.metrics is not None:
        print(format_table([("neural SDF", res.metrics)]))
    print(f"wrote {args.out}/: depth.npy, depth.png, depth_color.png, confidence.npy, confidence.png, pixel_fate.png, "
          "mesh.ply, "
          "points.ply, loss.png, history.json, "
          "config.yaml" + (", metrics.json, error_map.png" if res.metrics is not None else "")
          + "; train/checkpoint.pt (--resume continues)")
    return 0


def _pattern_set(path):
    """The PatternSet of --patterns (None without it); a bad file is a ScanError naming it (one line)."""
    if path is None:
        return None
    from ..scans.pattern_files import read_pattern_set

    return read_pattern_set(path)


OVERLAP_HELP = "batches: extract each scan while the next one trains (default: on a GPU)"


def _add_overlap(p) -> None:
    import argparse

    p.add_argument("--overlap", action=argparse.BooleanOptionalAction, default=None, help=OVERLAP_HELP)


PATTERNS_HELP = ("a pattern-set file (PATH/patterns.yaml or its folder, e.g. from `slwarp design-patterns`): its "
                 "patterns and roles replace those of the scan's frames of the same names")


def _reconstruct_batch(args, found, name: str, cfg, dev, pool=None) -> int:
    """The scans `found` (slwarp.batch.find_scans) as a batch: each into --out/<name>/ (--out for a lone scan
    folder), a summary printed by the process that gathers it; exit status 1 when a scan failed."""
    from ..batch import run_batch
    from ..neural.describe import describe

    rank = int(os.environ.get("RANK", 0))
    if rank == 0:
        for folder in found.ignored:
            print(f"note: {folder} holds no scan: passed over", file=sys.stderr)
        how = (f"{args.per_device} per device" + (", the default on GPUs; --per-device 0 runs them one after another"
                                                  if getattr(args, "per_device_default", False) else "")
               if args.per_device is not None else
               f"torchrun, {os.environ['WORLD_SIZE']} processes" if "WORLD_SIZE" in os.environ else "one after another")
        print(f"reconstructing {len(found.scans)} scans ({how}) with preset '{name}'" + (f" + {args.config}" if args.config else "")
              + f" ({describe(cfg)}) on {dev}", flush=True)
    options = _batch_options(args, progress=not args.quiet)
    timeline.mark("batch")
    summary = run_batch(found.scans, cfg, args.out, options, single=found.single, per_device=args.per_device,
                        pool=pool)
    timeline.mark("batch done")
    if isinstance(summary, int):  # a rank other than 0 (the failed scans' count): rank 0 reports
        return 1 if summary else 0
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
    p.add_argument("--patterns", metavar="FILE", help=PATTERNS_HELP)
    p.add_argument("--resume", action="store_true", help="continue from OUT/train/checkpoint.pt: the same scan, frames, "
                   "depth range and options, except those marked 'may change on resume' below; with several scans: "
                   "skip the scans whose outputs are complete, continue those with a checkpoint, start the others")
    p.add_argument("--overwrite", action="store_true", help="start again, replacing the checkpoint in OUT (without it a "
                   "run into a folder with a checkpoint is refused)")
    p.add_argument("--per-device", type=_non_negative_int, metavar="K", help="K scans at a time on each device (every "
                   "visible GPU, or the CPU) in worker processes; 0: one after another in this process (default: "
                   f"{DEFAULT_PER_GPU} for several scans on GPUs of {DEFAULT_PER_GPU_MIN_GIB:g} GiB or more, else 0)")
    p.add_argument("--depth-range", help="NEAR,FAR camera depth in mm (default: the scan's)")
    p.add_argument("--use-mask", action="store_true",
                   help="also restrict the depth map to the scan's mask").help_section = "reconstruct"
    p.add_argument("--quiet", action="store_true", help="no progress output")
    _add_overlap(p)
    _add_outside_paths(p)
    _add_config_options(p, name, argv=argv)
    p.set_defaults(func=cmd_reconstruct)


def cmd_watch(args) -> int:
    """A scanning station (slwarp.watch): each complete scan folder that appears in DIR, reconstructed into OUT/<name>/
    by this one process; stops on Ctrl-C / SIGTERM (exit status 130 / 143) or as --max-scans / --until-idle say."""
    from ..batch import BatchOptions
    from ..watch import watch

    _name, cfg, _dev = _config_from_args(args)
    _pattern_set(args.patterns)  # a bad file is reported before the station starts
    options = BatchOptions(frames=args.frames, depth_range=_parse_range(args.depth_range), use_mask=args.use_mask,
                           patterns=args.patterns, overlap=args.overlap)
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
    p.add_argument("--patterns", metavar="FILE", help=PATTERNS_HELP.replace("the scan's", "each scan's"))
    p.add_argument("--depth-range", help="NEAR,FAR camera depth in mm for scans that declare none")
    p.add_argument("--use-mask", action="store_true", help="also restrict each depth map to its scan's mask")
    p.add_argument("--poll", type=float, default=0.5, metavar="S", help="seconds between looks at DIR (default 0.5)")
    p.add_argument("--settle", type=float, default=1.0, metavar="S",
                   help="a scan folder is taken once no file in it changed for S seconds (default 1)")
    p.add_argument("--max-scans", type=_positive_int, metavar="N", help="stop after N scans")
    p.add_argument("--until-idle", action="store_true", help="stop once every scan in DIR is done or failed")
    _add_overlap(p)
    _add_config_options(p, name, argv=argv)
    p.set_defaults(func=cmd_watch)


def cmd_demo(args) -> int:
    from ..demo import run_demo

    name, cfg, _ = _config_from_args(args)
    run_demo(args.out, scene=args.scene, config=cfg, preset_name=name, progress=not args.quiet)
    return 0


def _add_demo(p, argv=None):
    from ..demo import DEMO_SCENE
    from ..sim.scenes import SCENE_NAMES

    name = _chosen_preset(argv)
    p.description = ("The paper's comparison on a simulated scene (the default rig on CUDA, the small rig on the CPU). "
                     f"The defaults shown are preset {name}'s (--preset P --help shows P's).")
    p.add_argument("--out", default="slwarp-demo", help="output folder (default: ./slwarp-demo)")
    p.add_argument("--scene", default=DEMO_SCENE, choices=list(SCENE_NAMES), help=f"built-in scene (default: {DEMO_SCENE})")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    _add_config_options(p, name, training=False, argv=argv)
    p.set_defaults(func=cmd_demo)

