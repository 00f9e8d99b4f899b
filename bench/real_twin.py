"""Twins of the real captures: the virtual scanner rendering each development capture's scene (its board, paper and
printed squares, its calibration, albedos and noise; slwarp.sim.twin) through a chosen camera model, prepared as
`bench.real_captures prepare` prepares the real ones, so that `bench.real_captures run --data` measures both alike.

    python -m bench.real_twin fit --repo PATH_TO_CLONE          # captures 0-2 -> data/twin/capture_N/twin.json
    python -m bench.real_twin make --cameras procam,halo,linear # -> data/twin/<camera>/capture_N/{scan, reference.npz}
    python -m bench.real_captures run --data data/twin/procam --presets fast,accurate --stem twin-procam

`fit` reads a clone of kamino410/procam-calibration as `prepare` does (commit ccf1cd8), and for each development
capture fits the twin to its full 40-image decode, its white and black frames and its row-code pattern + inverse
pairs (the noise), and fits the lens's edge profile (a core, a near and a far halo) to every bit's profile at once
from the same frames (printed; the `procam` camera model holds the values measured so). It writes twin.json and
region.npy (the real plate's region: the twin's plate lies on the same pixels) per capture, and the capture's 42
projector patterns once (a pattern-set folder). Captures 3 and 4 are never read: they are the acceptance set.

`make` simulates each twin's 42 frames through each camera model (slwarp.sim.simulate.CAMERA_MODELS, with the
twin's radiometry and noise, the projector focused on the board) and prepares it: scan/ holds the 7 most
significant row-code images with the exact depth, reference.npz the full decode of the twin's 40 images, GC(7) of
the 7 and the plate's region. On a GPU a twin takes seconds, on two CPU cores about a minute.
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.real_captures import DEV_CAPTURES, _extract_repo, write_capture

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DEST = REPO / "data" / "twin"
LENS_BITS = (2, 3, 5, 6)  # row-code bits whose edge profiles the lens's tail is fitted to (edges 256 to 16 px apart)


def _pairs(full, axis: str = "row", bits=range(2, 8)):
    """(pattern, inverse) images of `full` for the noise fit: mid bits, whose stripes are wide against the blur."""
    out = []
    for b in bits:
        i = full.frame_with("gray", axis=axis, bit=b, inverse=False)
        j = full.frame_with("gray", axis=axis, bit=b, inverse=True)
        if i is not None and j is not None:
            out.append((full.images[i], full.images[j]))
    return out


def fit(args) -> None:
    from slwarp.decode import reconstruct_depth
    from slwarp.evaluation.metrics import chessboard_region
    from slwarp.scans.pattern_files import write_pattern_set
    from slwarp.scans.patterns import PatternSet
    from slwarp.scans.scan import load_scan
    from slwarp.sim.twin import fit_twin

    from bench.edge_profile import edge_profile, fit_lens_tail, projector_coordinate
    from bench.real_captures import DEPTH_RANGE

    dest = Path(args.dest)
    dest.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        sample = _extract_repo(Path(args.repo), Path(tmp))
        for n in DEV_CAPTURES:
            t = time.perf_counter()
            full = load_scan(sample / f"capture_{n}")
            white, black = (full.images[full.frame_with(k)] for k in ("white", "black"))
            region = chessboard_region(white)
            depth, _, _ = reconstruct_depth(full, "gc-interp", depth_range=DEPTH_RANGE)
            twin = fit_twin(depth, region, white, black, _pairs(full), full.camera, full.projector, DEPTH_RANGE)
            coord = projector_coordinate(full, "row", depth)
            twin.report["lens_tail"] = fit_lens_tail([edge_profile(full, coord, "row", b, 60.0, 1.0) for b in LENS_BITS])
            out = dest / f"capture_{n}"
            out.mkdir(parents=True, exist_ok=True)
            (out / "twin.json").write_text(json.dumps(twin.to_dict(), indent=1))
            np.save(out / "region.npy", region)
            if n == DEV_CAPTURES[0]:
                write_pattern_set(dest / "patterns", PatternSet(full.patterns, list(full.names)),
                                  meta={"source": "kamino410/procam-calibration, sample_data/graycode_pattern"})
            r, tail = twin.report, twin.report["lens_tail"]
            print(f"capture_{n}: plate {r['plate_distance_mm']:.0f} mm, wall "
                  f"{r.get('wall_distance_mm', float('nan')):.0f} mm ({r.get('wall_share', 0):.0%} of the image), desk "
                  f"{r.get('desk_share', 0):.0%}, squares {r['square_mm']:.1f} mm, albedo "
                  + ", ".join(f"{k} {v:.3f}" for k, v in r["albedo"].items())
                  + f"; full well {twin.radiometry['full_well']:.0f}, read noise {twin.radiometry['read_noise']:.4f}, "
                  f"black level {twin.radiometry['black_level']:.3f}; lens: core {tail['core_px']:.2f} px, halos "
                  + ", ".join(f"{h:.3f} at {s:.1f} px" for h, s in tail["halos"])
                  + f" ({time.perf_counter() - t:.1f} s)", flush=True)


def make(args) -> None:
    from slwarp.scans.pattern_files import read_pattern_set
    from slwarp.sim.simulate import simulate
    from slwarp.sim.twin import Twin

    src = Path(args.dest)
    twins = sorted(p.parent for p in src.glob("capture_*/twin.json"))
    if not twins:
        raise SystemExit(f"{src}: no twins (run `python -m bench.real_twin fit --repo PATH` first)")
    patterns = read_pattern_set(src / "patterns")
    for camera_name in args.cameras.split(","):
        for folder in twins:
            t = time.perf_counter()
            twin = Twin.from_dict(json.loads((folder / "twin.json").read_text()))
            camera, projector = twin.rig()
            scan = simulate(twin.scene_objects(), camera, projector, patterns, twin.sim_options(camera_name, args.seed),
                            depth_range=twin.depth_range, device=args.device,
                            meta={"twin_of": folder.name, "camera_model": camera_name})
            out = src / camera_name / folder.name
            ref = write_capture(scan, np.load(folder / "region.npy"), out)
            ok = np.isfinite(ref) & np.isfinite(scan.gt_depth)
            err = np.abs(ref[ok] - scan.gt_depth[ok])
            print(f"{camera_name} {folder.name}: -> {out}; the full decode of the twin: MAE {err.mean():.3f} mm on "
                  f"{ok.sum() / max(int(np.isfinite(scan.gt_depth).sum()), 1):.1%} of the surface "
                  f"({time.perf_counter() - t:.1f} s)", flush=True)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    pf = sub.add_parser("fit", help="fit a twin to each development capture")
    pf.add_argument("--repo", required=True, help="a clone of kamino410/procam-calibration (work tree or bare)")
    pf.add_argument("--dest", default=str(DEFAULT_DEST))
    pm = sub.add_parser("make", help="simulate and prepare each twin through each camera model")
    pm.add_argument("--cameras", default="procam", help="camera models (slwarp.sim.simulate.CAMERA_MODELS)")
    pm.add_argument("--dest", default=str(DEFAULT_DEST))
    pm.add_argument("--seed", type=int, default=0, help="the noise's seed")
    pm.add_argument("--device", default=None, help="cpu or cuda:N (default: CUDA when present)")
    args = p.parse_args(argv)
    (fit if args.cmd == "fit" else make)(args)


if __name__ == "__main__":
    main()
