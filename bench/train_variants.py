"""Run several neural-SDF training variants side by side (one process each) and tabulate their accuracy.

Each variant is NAME:key=value,key=value with keys scene, rig, patterns, frames, noise_seed, preset and any
TrainConfig option by its flat name (slwarp.neural.config.OPTIONS: iters, lr, init, matmul, depth_method, ...). Processes run `--parallel` at a time, which
fills a large GPU better than one 2048-ray run. Each writes <out>/<NAME>.json (metrics, timings, config).

    python -m bench.train_variants --out bench/results/variants A:scene=bunny B:scene=bunny,init=camera
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

SCAN_KEYS = {"scene": str, "rig": str, "patterns": str, "frames": str, "noise_seed": int}


def parse(spec: str):
    name, _, rest = spec.partition(":")
    kv = {}
    for item in filter(None, rest.split(",")):
        k, _, v = item.partition("=")
        kv[k] = v
    return name, kv


def run_one(name: str, kv: dict, out: Path) -> dict:
    import torch

    from slwarp.neural.reconstruct import reconstruct
    from slwarp.sim.simulate import SimOptions, simulate_scene
    from slwarp.neural.config import OPTIONS, preset

    scene = kv.pop("scene", "bunny")
    rig = kv.pop("rig", "default")
    patterns = kv.pop("patterns", "random6")
    frames = kv.pop("frames", None)
    noise_seed = int(kv.pop("noise_seed", 0))
    pname = kv.pop("preset", "paper")
    unknown = sorted(set(kv) - set(OPTIONS))
    if unknown:
        raise SystemExit(f"{name}: unknown option(s) {', '.join(unknown)}; options: {', '.join(OPTIONS)}")
    cfg = preset(pname, **{k: OPTIONS[k].parse(v) for k, v in kv.items()})
    t0 = time.perf_counter()
    scan = simulate_scene(scene, patterns, rig=rig, options=SimOptions(seed=noise_seed),
                          device="cuda:0" if torch.cuda.is_available() else "cpu")
    if frames:
        scan = scan.select(frames.replace(";", ","))
    t1 = time.perf_counter()
    print(f"{name}: simulated {scene} in {t1 - t0:.1f} s; training {cfg.schedule.iters} iterations", flush=True)
    res = reconstruct(scan, cfg, out_dir=out / name, progress=False, log_every_s=20.0, overwrite=True)
    doc = {"name": name, "scene": scene, "rig": rig, "patterns": patterns, "frames": scan.names, "preset": pname,
           "config": cfg.to_dict(), "pattern_blur_px": res.trainer.renderer.pattern_blur, "metrics": res.metrics, "timings": {**res.timings, "simulate_s": t1 - t0},
           "device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu",
           "peak_gpu_mem_GB": torch.cuda.max_memory_allocated() / 1e9 if torch.cuda.is_available() else None}
    (out / f"{name}.json").write_text(json.dumps(doc, indent=1, default=float))
    return doc


def run_variants(specs: list[str], out: Path, parallel: int = 4, log=print) -> dict:
    """Run each spec in its own process, `parallel` at a time; returns name -> result doc (missing on failure)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    pending = list(specs)
    running = []
    t0 = time.perf_counter()
    while pending or running:
        while pending and len(running) < parallel:
            spec = pending.pop(0)
            name = parse(spec)[0]
            logf = open(out / f"{name}.log", "w")
            running.append((name, subprocess.Popen([sys.executable, __file__, "--one", "--out", str(out), spec],
                                                   stdout=logf, stderr=subprocess.STDOUT, env=os.environ.copy())))
        time.sleep(1.0)
        for item in list(running):
            if item[1].poll() is not None:
                running.remove(item)
                f = out / f"{item[0]}.json"
                msg = ""
                if f.is_file():
                    d = json.loads(f.read_text())
                    m, t = d["metrics"] or {}, d["timings"]
                    msg = (f": MAE {m.get('mae', float('nan')):.3f} mm, median {m.get('median', float('nan')):.3f}, "
                           f">5 mm {m.get('over_5mm', float('nan')):.2%}, train {t['train_s']:.1f} s")
                log(f"[{time.perf_counter() - t0:6.0f} s] {item[0]} finished (exit {item[1].returncode}){msg}")
    docs = {}
    for spec in specs:
        name = parse(spec)[0]
        f = out / f"{name}.json"
        if f.is_file():
            docs[name] = json.loads(f.read_text())
        else:
            tail = (out / f"{name}.log").read_text()[-600:] if (out / f"{name}.log").is_file() else ""
            log(f"{name}: no result\n{tail}")
    return docs


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("variants", nargs="+")
    p.add_argument("--out", default=str(REPO / "bench" / "results" / "variants"))
    p.add_argument("--parallel", type=int, default=4)
    p.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.one:
        name, kv = parse(args.variants[0])
        run_one(name, kv, out)
        return 0
    docs = run_variants(args.variants, out, args.parallel, log=lambda s: print(s, flush=True))
    rows = []
    for spec in args.variants:
        name = parse(spec)[0]
        if name not in docs:
            continue
        d = docs[name]
        m, t = d["metrics"] or {}, d["timings"]
        rows.append(f"| {name} | {spec.partition(':')[2]} | {m.get('mae', float('nan')):.3f} | {m.get('median', float('nan')):.3f} | "
                    f"{m.get('over_1mm', float('nan')):.2%} | {m.get('over_5mm', float('nan')):.2%} | {m.get('completeness', float('nan')):.1%} | "
                    f"{t['train_s']:.1f} | {t['iterations'] / max(t['train_s'], 1e-9):.1f} |")
    table = "| variant | settings | MAE mm | median mm | >1 mm | >5 mm | complete | train s | it/s |\n|---|---|---|---|---|---|---|---|---|\n" + "\n".join(rows)
    print(table)
    (out / "summary.md").write_text(table + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
