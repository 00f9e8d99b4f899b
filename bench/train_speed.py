"""Training speed: milliseconds per iteration of the paper preset under several settings, with a GPU-time
breakdown (our Warp kernels, matrix products, other GPU work, and host time the GPU waits for).

    python bench/train_speed.py                       # bunny, default rig, paper preset, CUDA
    python bench/train_speed.py --configs warp:eager:fp32 warp:compile:tf32 torch:compile:tf32
Each config is BACKEND:MODE:MATMUL (backend warp|torch, mode eager|compile, matmul fp32|tf32).
Writes bench/results/train-speed-<device>.json and .md.
"""
from __future__ import annotations

import argparse
import datetime
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

WARP_KERNEL_MARKERS = ("render_kernels", "cast_camera", "upsample", "merge_sorted", "stratified", "camera_rays")
GEMM_MARKERS = ("gemm", "xmma", "cutlass", "sm90_", "sm80_", "ampere", "hopper", "cublas")


def breakdown(trainer, steps: int = 5) -> dict:
    """GPU time per iteration (ms) by category, from the torch profiler."""
    import torch
    from torch.profiler import ProfilerActivity, profile

    torch.cuda.synchronize()
    t0 = time.perf_counter()
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(steps):
            trainer.step()
        torch.cuda.synchronize()
    wall = (time.perf_counter() - t0) / steps * 1e3
    cats = {"warp_kernels": 0.0, "matmul": 0.0, "other_gpu": 0.0}
    for ev in prof.key_averages():
        t = (getattr(ev, "device_time_total", None) or getattr(ev, "cuda_time_total", 0)) / 1e3 / steps
        if not t or ev.key.startswith(("aten::", "autograd::", "Optimizer.", "ProfilerStep", "cudaGraph")):
            continue
        k = ev.key.lower()
        if any(m.lower() in k for m in WARP_KERNEL_MARKERS):
            cats["warp_kernels"] += t
        elif any(m in k for m in GEMM_MARKERS):
            cats["matmul"] += t
        else:
            cats["other_gpu"] += t
    gpu = sum(cats.values())
    cats["gpu_total"] = gpu
    cats["wall_profiled"] = wall
    cats["host_wait"] = max(0.0, wall - gpu)
    return cats


def main(argv=None):
    import torch

    from slwarp.simulate import simulate_scene
    from slwarp.train import Trainer, preset

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--configs", nargs="*", default=["warp:eager:fp32", "warp:compile:fp32", "warp:compile:tf32",
                                                     "torch:compile:tf32", "torch:eager:fp32"])
    p.add_argument("--scene", default="bunny")
    p.add_argument("--rig", default="default")
    p.add_argument("--warmup", type=int, default=20)
    p.add_argument("--iters", type=int, default=50)
    p.add_argument("--out", default=str(REPO / "bench" / "results"))
    args = p.parse_args(argv)
    dev = "cuda" if torch.cuda.is_available() else "cpu"
    scan = simulate_scene(args.scene, "random6", rig=args.rig, device="cuda:0" if dev == "cuda" else "cpu")
    rows = []
    for spec in args.configs:
        backend, mode, mm = spec.split(":")
        cfg = preset("paper" if dev == "cuda" else "cpu", backend=backend, compile=(mode == "compile"), matmul=mm,
                     init="sphere")
        torch.manual_seed(0)
        torch.cuda.reset_peak_memory_stats() if dev == "cuda" else None
        tr = Trainer(scan, cfg, progress=False)
        t0 = time.perf_counter()
        for _ in range(args.warmup):
            tr.step()
        if dev == "cuda":
            torch.cuda.synchronize()
        t_warm = time.perf_counter() - t0
        t0 = time.perf_counter()
        for _ in range(args.iters):
            tr.step()
        if dev == "cuda":
            torch.cuda.synchronize()
        ms = (time.perf_counter() - t0) / args.iters * 1e3
        row = {"config": spec, "ms_per_it": ms, "it_per_s": 1e3 / ms, "warmup_s": t_warm,
               "projected_4000_it_s": 4000 * ms / 1e3}
        if dev == "cuda":
            row["breakdown_ms"] = breakdown(tr)
            row["peak_gpu_mem_GB"] = torch.cuda.max_memory_allocated() / 1e9
        rows.append(row)
        print(json.dumps(row), flush=True)
        torch.backends.cuda.matmul.allow_tf32 = False
        del tr
    name = torch.cuda.get_device_name(0) if dev == "cuda" else "CPU"
    lines = [f"# Training speed, paper preset, {args.scene} ({args.rig} rig), {name}, {datetime.date.today()}", "",
             "| backend:mode:matmul | ms/it | it/s | 4000 it (s) | warm-up (s) | Warp kernels ms | matmul ms | other GPU ms | host wait ms | peak GB |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        b = r.get("breakdown_ms", {})
        lines.append(f"| {r['config']} | {r['ms_per_it']:.2f} | {r['it_per_s']:.1f} | {r['projected_4000_it_s']:.1f} | "
                     f"{r['warmup_s']:.1f} | {b.get('warp_kernels', float('nan')):.2f} | {b.get('matmul', float('nan')):.2f} | "
                     f"{b.get('other_gpu', float('nan')):.2f} | {b.get('host_wait', float('nan')):.2f} | {r.get('peak_gpu_mem_GB', float('nan')):.2f} |")
    print("\n".join(lines))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tag = "cuda" if dev == "cuda" else "cpu"
    (out / f"train-speed-{tag}.json").write_text(json.dumps({"device": name, "date": str(datetime.date.today()), "rows": rows}, indent=1))
    (out / f"train-speed-{tag}.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
