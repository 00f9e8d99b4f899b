"""Virtual scanner speed: one scan of every built-in scene (default rig, 13 frames: random6 + gray7).

    python -m bench.simulate [--device cpu|cuda:0] [--rig default] [--patterns random6+gray7]
Prints a table and writes bench/results/simulate-<device>.json (first call includes kernel compilation,
reported separately).
"""
from __future__ import annotations

import argparse
import datetime
import json
import platform
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main(argv=None):
    import torch

    from slwarp.sim.scenes import SCENE_NAMES
    from slwarp.sim.simulate import simulate_scene

    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--device", default="cuda:0" if torch.cuda.is_available() else "cpu")
    p.add_argument("--rig", default="default")
    p.add_argument("--patterns", default="random6+gray7")
    p.add_argument("--out", default=str(REPO / "bench" / "results"))
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    simulate_scene("spheres", "gray6", rig="small", device=args.device)  # compile + first use
    warm = time.perf_counter() - t0
    rows = []
    for scene in SCENE_NAMES:
        t0 = time.perf_counter()
        scan = simulate_scene(scene, args.patterns, rig=args.rig, device=args.device)
        total = time.perf_counter() - t0
        tm = scan.meta["timings"]
        rows.append({"scene": scene, "frames": len(scan), "total_s": total, "scene_build_s": total - tm["total_s"], **tm})
    name = torch.cuda.get_device_name(0) if args.device.startswith("cuda") else f"{platform.machine()} CPU"
    lines = [f"# Virtual scanner, {args.rig} rig, {args.patterns}, {name}, {datetime.date.today()}", "",
             f"First call (kernel compilation and load, small rig): {warm:.1f} s", "",
             "| scene | frames | total s | scene build s | ray casting s | patterns s | imaging s |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['frames']} | {r['total_s']:.2f} | {r['scene_build_s']:.2f} | {r['raycast_s']:.2f} | "
                     f"{r['patterns_s']:.2f} | {r['imaging_s']:.2f} |")
    print("\n".join(lines))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tag = "cuda" if args.device.startswith("cuda") else "cpu"
    (out / f"simulate-{tag}.json").write_text(json.dumps({"device": name, "date": str(datetime.date.today()), "rig": args.rig,
                                                          "patterns": args.patterns, "first_call_s": warm, "rows": rows}, indent=1))
    (out / f"simulate-{tag}.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
