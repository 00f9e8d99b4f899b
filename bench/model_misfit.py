"""How well the refinement's pattern model explains a scan's images at its true depth (`pattern_model.model_misfit`,
the median relative misfit of the lit pixels), per scene, rig and camera model, and on the real capture at its
full 40-image Gray code decode; against the limit above which the defaults skip the refinement
(`refine_max_misfit`, REFINE_MAX_MISFIT).

The refinement moves each pixel to the depth that best fits this model; where the model lacks part of the optics
(a camera response, a real lens) it fits those errors and the depth gets worse. The limit has to sit above every
scan where the refinement helps and below those where it hurts.

    python -m bench.model_misfit                                   # 8 scenes x 4 rigs linear, 3 cameras on default
    python -m bench.model_misfit --rigs default --scenes bunny --cameras linear,gamma --no-real   # quick
    python -m bench.model_misfit --frames gray7 --cameras linear --rigs default,vertical --stem model-misfit-cpu-gray7

The linear-camera scans are the accuracy sweep's own (bench/accuracy_sweep.py: random6 + 7 Gray code bits, seed 0);
the other camera models (slwarp.sim.simulate.CAMERA_MODELS) are the same scenes through that camera. CPU, about
30 s a scan. Writes bench/results/model-misfit-cpu.{json,md} (or --out).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from bench import DATE, markdown_table, write_study
from slwarp.scans.data import data_dir

SCENES = ("spheres", "torus", "boxes", "bunny", "vase", "steps", "checker", "rods")
RIGS = ("default", "vertical", "oblique", "rolled")


def scan_misfit(rig: str, scene: str, camera: str, frames: str = "random6") -> float:
    """model_misfit of the scan's 6 random-pattern frames (frames "gray7": its 7 most significant Gray code images
    along the depth axis, no inverses, the real captures' case) at its true depth (inside its mask)."""
    from bench.accuracy_sweep import _scan, neural_frames
    from slwarp.neural.pattern_model import model_misfit

    if camera == "linear":
        scan, axis = _scan(rig, scene, 0)
    else:
        from slwarp.sim.simulate import SimOptions, simulate_scene

        if frames != "random6":
            raise SystemExit("--frames gray7 is measured with the linear camera only")
        scan, axis = simulate_scene(scene, "random6", rig, SimOptions(seed=0, **_camera_options(camera))), None
    rand = scan.select(neural_frames({"frames": frames}, axis))
    gt = np.where(rand.mask, rand.gt_depth, np.nan).astype(np.float32)
    return model_misfit(gt, rand.camera, rand.projector, rand.images, rand.patterns)


def _camera_options(camera: str) -> dict:
    from slwarp.sim.simulate import CAMERA_MODELS

    if camera not in CAMERA_MODELS:
        raise SystemExit(f"unknown camera model {camera!r}; models: {', '.join(CAMERA_MODELS)}")
    return dict(CAMERA_MODELS[camera])


def real_misfit(data: Path) -> float:
    """model_misfit of the real capture's 7 most significant row-code images at its full gc-interp decode."""
    from bench.chessboard import DEPTH_RANGE, SEVEN_ROWS
    from slwarp.decode import reconstruct_depth
    from slwarp.neural.pattern_model import model_misfit
    from slwarp.scans.scan import load_scan

    scan = load_scan(str(data))
    depth, _, _ = reconstruct_depth(scan, "gc-interp", frames=None, depth_range=DEPTH_RANGE)
    seven = scan.select(SEVEN_ROWS)
    return model_misfit(depth, seven.camera, seven.projector, seven.images, seven.patterns)


def render(doc: dict) -> str:
    limit = doc["limit"]
    what = "the 7 Gray code images" if doc.get("frames") == "gray7" else "the 6 random patterns"
    lines = [f"# The pattern model's misfit at the true depth, {what} (CPU, {doc['date']})", "",
             f"`{doc['command']}`. `pattern_model.model_misfit`: the median over the lit pixels of mean_n |I_n - (a + b "
             "Q_n)| / b, the per-pixel cost the refinement minimises, at the scan's true depth (the real capture: at "
             f"its full 40-image decode). The defaults refine only at or below {limit} (`refine_max_misfit`).", ""]
    lin = doc["scans"].get("linear", {})
    if lin:
        rigs = [r for r in doc["rigs"] if r in lin]
        lines += ["## Linear camera (the accuracy sweep's scans)", ""]
        rows = [[scene] + [f"{lin[r][scene]:.4f}" for r in rigs] for scene in doc["scenes"]]
        rows.append(["max"] + [f"{max(lin[r].values()):.4f}" for r in rigs])
        lines += markdown_table(["scene"] + rigs, rows) + [""]
    others = {c: v for c, v in doc["scans"].items() if c != "linear"}
    if others:
        lines += [f"## Other camera models ({', '.join(doc['camera_rigs'])} rig)", ""]
        cams = list(others)
        rows = [[scene] + [f"{others[c][r][scene]:.4f}" for c in cams for r in doc["camera_rigs"]]
                for scene in doc["scenes"]]
        lines += markdown_table(["scene"] + [f"{c} ({r})" for c in cams for r in doc["camera_rigs"]], rows) + [""]
    if doc.get("real") is not None:
        lines += [f"Real capture (7 row-code images at the full decode): {doc['real']:.4f}.", ""]
    allv = {c: [v for r in d.values() for v in r.values()] for c, d in doc["scans"].items()}
    lines += ["Above the limit (refinement skipped): " + "; ".join(
        f"{c} {sum(v > limit for v in vals)} of {len(vals)}" for c, vals in allv.items())
        + (f"; real capture {'yes' if doc['real'] > limit else 'no'}" if doc.get("real") is not None else "") + "."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    from slwarp.neural.config import REFINE_MAX_MISFIT

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rigs", default=",".join(RIGS), help="rigs of the linear-camera scans")
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--cameras", default="linear,optics,gamma,srgb", help="camera models (CAMERA_MODELS)")
    ap.add_argument("--camera-rigs", default="default", help="rigs of the other camera models")
    ap.add_argument("--no-real", action="store_true", help="leave out the real capture")
    ap.add_argument("--data", default=str(data_dir() / "procam_chessboard"))  # $SLWARP_DATA (docs/real-captures.md)
    ap.add_argument("--frames", choices=("random6", "gray7"), default="random6",
                    help="the frames whose misfit is measured: the 6 random patterns, or the 7 Gray code images")
    ap.add_argument("--out", default=str(REPO / "bench" / "results"))
    ap.add_argument("--stem", default="model-misfit-cpu")
    args = ap.parse_args(argv)
    rigs, scenes = args.rigs.split(","), args.scenes.split(",")
    cameras, camera_rigs = args.cameras.split(","), args.camera_rigs.split(",")
    for c in cameras:
        if c != "linear":
            _camera_options(c)
    doc = {"date": DATE, "command": "python -m bench.model_misfit " + " ".join(sys.argv[1:] if argv is None else argv),
           "limit": REFINE_MAX_MISFIT, "frames": args.frames, "rigs": rigs, "scenes": scenes, "camera_rigs": camera_rigs, "scans": {}}
    for camera in cameras:
        for rig in (rigs if camera == "linear" else camera_rigs):
            for scene in scenes:
                t = time.perf_counter()
                m = scan_misfit(rig, scene, camera, args.frames)
                doc["scans"].setdefault(camera, {}).setdefault(rig, {})[scene] = m
                print(f"{camera} {rig} {scene}: {m:.4f} ({time.perf_counter() - t:.0f} s)", flush=True)
    if not args.no_real:
        if not Path(args.data).is_dir():
            raise SystemExit(f"{args.data}: no real capture there (--data FOLDER, or --no-real)")
        doc["real"] = real_misfit(Path(args.data))
        print(f"real capture: {doc['real']:.4f}", flush=True)
    write_study(Path(args.out) / args.stem, doc, render)
    return 0


if __name__ == "__main__":
    sys.exit(main())
