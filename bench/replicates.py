"""Replicates: one simulated scan reconstructed again and again with other training seeds, to measure how often a
preset fails on it and what each run looked like. For a failure seen once in a sweep (a lost surface), whether it
belongs to the scan and the preset or to the process that ran it.

    python -m bench.replicates --cases oblique,torus,fast:level_adam_steps=true --runs 10          # GPU
    python -m bench.replicates --small --cases default,steps,cpu-hashgrid --runs 2 --set iters=100  # CPU smoke run

Each case is RIG,SCENE,PRESET (PRESET or PRESET:key=value:...): the scan is simulated once (random6 + gray7, simulator
seed --seed, as bench.accuracy_sweep makes it), then `reconstruct` trains on its 6 random patterns with seeds
0..runs-1, without the lost-surface retry, so that every run shows what it did. Per run: MAE, completeness, the shares
the lost-surface rule reads (lit pixels lost, lit pixels the depth search found), whether the rule fired, whether the
training step ran as a CUDA graph, the wall time. Writes <out>/<stem>.json and .md and prints the table.
"""
from __future__ import annotations

import argparse
import datetime
import json
import sys
import time
from pathlib import Path


def parse_case(text: str) -> tuple[str, str, str, dict]:
    """'RIG,SCENE,PRESET[:key=value...]' -> (rig, scene, label, {"preset": name, **overrides})."""
    parts = text.split(",")
    if len(parts) != 3 or not all(parts):
        raise ValueError(f"case {text!r}: expected RIG,SCENE,PRESET (e.g. oblique,torus,fast)")
    rig, scene, label = parts
    from slwarp.neural.config import parse_assignments

    name, *assignments = label.split(":")
    return rig, scene, label, {"preset": name, **parse_assignments(assignments)}


def table(rows: list[dict]) -> str:
    """The runs as a markdown table."""
    head = ("| case | seed | MAE mm | complete | lit lost | search found | rule | CUDA graph | s |\n"
            "|---|---:|---:|---:|---:|---:|---|---|---:|")
    lines = [head]
    for r in rows:
        shares = r["surface_shares"] or {}
        found = shares.get("searched")
        lines.append(f"| {r['rig']} {r['scene']} {r['case']} | {r['seed']} | {r['mae']:.3f} | "
                     f"{100 * r['completeness']:.1f}% | {100 * shares.get('lost', float('nan')):.1f}% | "
                     f"{'-' if found is None else f'{100 * found:.1f}%'} | {'lost' if r['surface_lost'] else 'ok'} | "
                     f"{'yes' if r['graph_captured'] else 'no'} | {r['wall_s']:.1f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", required=True, help="semicolon-separated RIG,SCENE,PRESET[:key=value...]")
    ap.add_argument("--runs", type=int, default=10, help="training seeds 0..runs-1 per case (default 10)")
    ap.add_argument("--small", action="store_true", help="each geometry's small-resolution rig")
    ap.add_argument("--seed", type=int, default=0, help="simulator seed (default 0)")
    ap.add_argument("--set", default="", help="option overrides for every case, e.g. 'iters=300'")
    ap.add_argument("--device", default=None, help="torch device (default: cuda:0 when there is one, else cpu)")
    ap.add_argument("--out", default="bench/results")
    ap.add_argument("--stem", default=None, help="output file name without suffix (default replicates-<cpu|cuda>)")
    args = ap.parse_args(argv)

    import torch

    import bench.accuracy_sweep as sweep
    from slwarp.neural.config import parse_assignments, preset
    from slwarp.neural.reconstruct import reconstruct
    from slwarp.sim.rigs import rig_name

    try:
        cases = [parse_case(c) for c in args.cases.split(";") if c]
        cases = [(rig_name(rig, args.small), scene, label, opts) for rig, scene, label, opts in cases]
        common = parse_assignments([a for a in args.set.split(",") if a])
    except Exception as e:  # noqa: BLE001 - a bad argument is the user's to fix: say which
        print(f"replicates: {e}", file=sys.stderr)
        return 2
    device = args.device or ("cuda:0" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda"):
        torch.cuda.set_device(torch.device(device))
    rows = []
    for rig, scene, label, opts in cases:
        scan, axis = sweep._scan(rig, scene, args.seed, device=device)
        frames = scan.select(sweep.neural_frames({"frames": "random6"}, axis))
        overrides = {k: v for k, v in opts.items() if k != "preset"}
        for seed in range(args.runs):
            cfg = preset(opts["preset"], **{**common, **overrides, "device": device, "seed": seed,
                                            "retry_lost_surface": False})
            t0 = time.perf_counter()
            rec = reconstruct(frames, cfg, progress=False)
            t = rec.timings
            rows.append({"rig": rig, "scene": scene, "case": label, "seed": seed, "mae": rec.metrics["mae"],
                         "rmse": rec.metrics["rmse"], "completeness": rec.metrics["completeness"],
                         "surface_shares": t.get("surface_shares"), "surface_lost": t.get("surface_lost"),
                         "graph_captured": t.get("graph_captured"), "pixels": t.get("pixels"),
                         "wall_s": time.perf_counter() - t0})
            r = rows[-1]
            print(f"{rig} {scene} {label} seed {seed}: MAE {r['mae']:.3f} mm, complete {100 * r['completeness']:.1f}%, "
                  f"{'lost the surface' if r['surface_lost'] else 'ok'}, {r['wall_s']:.1f} s", flush=True)
    md = table(rows)
    print(md)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = args.stem or f"replicates-{'cuda' if device.startswith('cuda') else 'cpu'}"
    name = torch.cuda.get_device_name(torch.device(device)) if device.startswith("cuda") else "CPU"
    command = "python -m bench.replicates " + " ".join(sys.argv[1:] if argv is None else argv)
    doc = {"date": datetime.date.today().isoformat(), "device": name, "command": command, "rows": rows}
    (out / f"{stem}.json").write_text(json.dumps(doc, indent=1, default=str))
    (out / f"{stem}.md").write_text(f"# Replicates ({name}, {doc['date']})\n\n`{command}`\n\n{md}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
