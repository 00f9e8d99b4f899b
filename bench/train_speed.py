"""Training speed: milliseconds per iteration of a preset under several settings, where the time of an
iteration goes, and the end-to-end time from a loaded scan to a depth map for the Warp and torch backends.

    python -m bench.train_speed                                  # CUDA: the default preset, bunny, default rig
    python -m bench.train_speed --configs warp:compile:tf32:graph torch:compile:tf32:graph
    python -m bench.train_speed --end-to-end                     # + reconstruct() with backend warp and torch
    python -m bench.train_speed --preset cpu --rig small         # CPU: the demo preset
    python -m bench.train_speed --preset accurate --configs warp:compile:tf32:graph warp:compile:tf32:graph:twin
    python -m bench.train_speed --preset fast --configs warp:compile:tf32:graph --end-to-end --backends warp
    python -m bench.train_speed --preset tiny --set field=hashgrid iters=4 --iters 2 --warmup 1   # CPU smoke test

Each config is BACKEND:MODE:MATMUL[:graph][:twin]: backend warp|torch (the renderer's kernels), mode
eager|compile (torch.compile of the field), matmul fp32|tf32, graph = the whole step captured once as a CUDA
graph and replayed, twin = a hash-grid field's encoding in its pure-torch twin instead of the Warp kernels
(the like-for-like comparison of the encoding: warp:...:graph against warp:...:graph:twin). --set applies
options (key=value, the flat names of slwarp.neural.config) to the preset.

Breakdown (CUDA): the step announces its phases to the renderer's phase_hook; the bench turns each
announcement into an empty marker kernel, so the profiler's kernel timeline splits into phases: MLP
forward (the up-sampling and final field evaluations, explicit gradient included), losses and gathers,
MLP backward (the gradient of the explicit Eikonal gradient is this model's double backward), our Warp
kernels (every phase), Adam, and the rest of the wall time (Python, launches, synchronisation: the GPU idles).
With a hash-grid field the "MLP" columns hold the whole field (encoding included: its Warp kernels are
counted in "our Warp kernels"). Peak GPU memory per config. --end-to-end: reconstruct() from the loaded scan
(depth search, blur fit, training, marching cubes, depth, filters), after a short run of the same preset that
builds the kernels and compiles the field (reported apart as warm-up; Warp's kernel cache keeps the build
across processes, torch.compile's in-process).
Writes <out>/train-speed-<device>.json and .md (and end-to-end rows with --end-to-end).
"""
from __future__ import annotations

import argparse
import datetime
import json
import re
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

# Warp's CUDA kernels are named <kernel>_cuda_kernel_forward (the hash grid's encode, gradient, ...)
WARP_KERNEL_MARKERS = ("render_kernels", "cast_camera", "upsample", "merge_sorted", "stratified", "camera_rays",
                       "_cuda_kernel_forward")
MARKER_KERNEL = "spin_kernel"  # torch.cuda._sleep's kernel: the phase marker
PHASE_COLUMNS = {"batch": "losses_other", "rays": "mlp_forward", "field": "mlp_forward", "render": "losses_other",
                 "backward": "mlp_backward", "optimizer": "adam", "end": "losses_other"}


TOP_KERNELS = 16  # the kernels listed per config (by GPU time per iteration)


def is_warp_kernel(name: str) -> bool:
    return any(m in name for m in WARP_KERNEL_MARKERS)


def kernel_label(name: str) -> str:
    """A kernel's name, short: Warp's <kernel>_<hash>_cuda_kernel_forward -> warp:<kernel>; C++ templates cut."""
    m = re.match(r"(\w+?)(_[0-9a-f]{6,})?_cuda_kernel_forward", name)
    if m:
        return "warp:" + m.group(1)
    return name if len(name) <= 70 else name[:67] + "..."


def breakdown(trainer, steps: int = 5) -> dict:
    """GPU ms per iteration by phase, from marker kernels in the profiler's timeline (see module doc)."""
    import torch
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    phases: list[str] = []

    def hook(name):
        phases.append(name)
        torch.cuda._sleep(0)

    trainer.renderer.phase_hook = hook
    trainer.reset_graph()  # recapture with the markers inside
    trainer.step()
    trainer.step()
    torch.cuda.synchronize()
    phases.clear()
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(steps):
            trainer.step()
        torch.cuda.synchronize()
    trainer.renderer.phase_hook = None
    trainer.reset_graph()
    evs = [e for e in prof.profiler.kineto_results.events() if e.device_type() == DeviceType.CUDA]
    evs.sort(key=lambda e: e.start_ns())
    order = ["batch", "rays", "field", "render", "backward", "optimizer", "end"]
    cats = {"mlp_forward": 0.0, "losses_other": 0.0, "mlp_backward": 0.0, "warp_kernels": 0.0, "adam": 0.0}
    per_kernel: dict[str, list] = {}  # name -> [ms per iteration, launches per iteration]
    phase = "end"
    n_markers = 0
    for e in evs:
        ms = e.duration_ns() / 1e6 / steps
        if MARKER_KERNEL in e.name():
            phase = order[n_markers % len(order)]
            n_markers += 1
            continue
        k = per_kernel.setdefault(kernel_label(e.name()), [0.0, 0.0])
        k[0] += ms
        k[1] += 1.0 / steps
        if is_warp_kernel(e.name()):
            cats["warp_kernels"] += ms
        else:
            cats[PHASE_COLUMNS[phase]] += ms
    if n_markers == 0:  # no phase markers in the trace: say so instead of booking everything to one phase
        names = sorted({e.name()[:60] for e in evs})
        print("breakdown: no marker kernels seen; kernel names:", names[:40], flush=True)
    cats["gpu_total"] = sum(cats.values())
    top = sorted(per_kernel.items(), key=lambda kv: -kv[1][0])[:TOP_KERNELS]
    cats["kernels"] = [{"kernel": name, "ms": ms, "launches": n} for name, (ms, n) in top]
    cats["markers_seen"] = n_markers
    cats["markers_expected"] = steps * len(order)
    return cats


def cpu_breakdown(trainer, steps: int = 10) -> dict:
    """CPU ms per iteration by phase (work on the CPU is synchronous: host timestamps at the phase
    announcements). Our Warp kernels run inside the phases here: the up-sampling kernels with the MLP
    forward, the fused render with the losses, its backward with the MLP backward."""
    marks: list = []
    trainer.renderer.phase_hook = lambda name: marks.append((name, time.perf_counter()))
    trainer.step()
    marks.clear()
    for _ in range(steps):
        trainer.step()
    trainer.renderer.phase_hook = None
    cats = {"mlp_forward": 0.0, "losses_other": 0.0, "mlp_backward": 0.0, "adam": 0.0}
    for (name, t), (_, t_next) in zip(marks, marks[1:]):
        if name != "end":
            cats[PHASE_COLUMNS[name]] += (t_next - t) * 1e3 / steps
    cats["warp_kernels"] = float("nan")
    cats["gpu_total"] = sum(v for k, v in cats.items() if k != "warp_kernels")  # here: CPU time inside the phases
    return cats


def parse_spec(spec: str) -> dict:
    """BACKEND:MODE:MATMUL[:graph][:twin] -> the options it sets and whether the encoding runs in the twin."""
    parts = spec.split(":")
    if len(parts) < 3 or parts[0] not in ("warp", "torch") or parts[1] not in ("eager", "compile") \
            or parts[2] not in ("fp32", "tf32") or not set(parts[3:]) <= {"graph", "twin"}:
        raise SystemExit(f"config {spec!r}: expected BACKEND:MODE:MATMUL[:graph][:twin], e.g. warp:compile:tf32:graph")
    return {"options": dict(backend=parts[0], compile=parts[1] == "compile", matmul=parts[2],
                            cuda_graph="graph" in parts[3:]), "twin": "twin" in parts[3:]}


def time_config(scan, spec: str, preset_name: str, warmup: int, iters: int, dev: str, options: dict | None = None,
                init: str = "preset") -> dict:
    import torch

    from slwarp.neural.config import preset
    from slwarp.neural.training import Trainer

    parsed = parse_spec(spec)
    # init "preset": the preset's own start (its depth search, so the step carries the terms that need the map: the
    # surface and free-space terms); "sphere": NeuS's sphere, no map and none of those terms (the figures before
    # 2026-11-25 were timed so, and read 0.6 ms per step faster than `fast` trains); "trained": the preset's start,
    # then its whole schedule before the timed steps (a trained field puts NeuS's samples near its surface; `fast` on
    # an H100 steps at 1.57 ms from there as from the start, train-speed-cuda-fast-trained.md: the slower steps of some
    # end-to-end runs came from Inductor's compile workers, train-speed-cuda-fast-compile-workers.md)
    cfg = preset(preset_name, **{**(options or {}), **parsed["options"], **({"init": "sphere"} if init == "sphere" else {})})
    if dev == "cuda":
        torch.cuda.reset_peak_memory_stats()
    tr = Trainer(scan, cfg, progress=False)
    if parsed["twin"]:
        if not hasattr(tr.field, "backend"):
            raise SystemExit(f"config {spec!r}: 'twin' needs a hash-grid field (--set field=hashgrid or a hash-grid preset)")
        tr.field.backend = "torch"  # the encoding's gathers in torch; the renderer's kernels as the config says
    trained = 0  # the iterations trained before the timed steps
    if init == "trained":
        tr.train()
        trained = tr.iteration
    # time main-phase steps at the end of the schedule, where every hash-grid level is on (the depth-search
    # warm-up's steps run with the coarsest levels only: timed there, a hash grid looks faster than it trains)
    tr.iteration = tr.warmup_iters + cfg.schedule.iters
    sync = torch.cuda.synchronize if dev == "cuda" else (lambda: None)
    t0 = time.perf_counter()
    for _ in range(warmup):
        tr.step()
    sync()
    t_warm = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(iters):
        tr.step()
    sync()
    ms = (time.perf_counter() - t0) / iters * 1e3
    row = {"config": spec, "preset": preset_name, "init": cfg.init.method + (", trained" if init == "trained" else ""),
           "trained_iters": trained, "field": cfg.field.kind, "ms_per_it": ms, "it_per_s": 1e3 / ms, "warmup_s": t_warm,
           "projected_s": cfg.schedule.iters * ms / 1e3, "iters_of_preset": cfg.schedule.iters, "graph_used": tr.graph_captured}
    if dev == "cuda":
        b = breakdown(tr)
        b["host_and_idle"] = max(0.0, ms - b["gpu_total"])
        row["breakdown_ms"] = b
        row["peak_gpu_mem_GB"] = torch.cuda.max_memory_allocated() / 1e9
    else:
        b = cpu_breakdown(tr)
        b["host_and_idle"] = max(0.0, ms - b["gpu_total"])
        row["breakdown_ms"] = b
    torch.backends.cuda.matmul.allow_tf32 = False
    return row


def end_to_end(scan, backend: str, preset_name: str, dev: str, options: dict | None = None) -> dict:
    """reconstruct() from the loaded scan: wall time of each stage, it/s, MAE, peak GPU memory; first a short
    run of the same preset (its warm-up: kernel builds, torch.compile, CUDA-graph capture), timed apart."""
    import torch

    from slwarp.neural.reconstruct import reconstruct
    from slwarp.neural.config import preset

    cfg = preset(preset_name, **{**(options or {}), "backend": backend})
    short = cfg.with_options(iters=min(cfg.schedule.iters, 5), init_iters=min(cfg.init.iters, 5), mc_resolution=16)
    t0 = time.perf_counter()
    reconstruct(scan, short, out_dir=None, progress=False)
    if dev == "cuda":
        torch.cuda.synchronize()
    warmup_s = time.perf_counter() - t0
    if dev == "cuda":
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
    t0 = time.perf_counter()
    res = reconstruct(scan, cfg, out_dir=None, progress=False)
    wall = time.perf_counter() - t0
    t = res.timings
    row = {"backend": backend, "preset": preset_name, "field": cfg.field.kind, "warmup_s": warmup_s, "wall_s": wall,
           "timings": t, "it_per_s": t["iterations"] / t["train_s"],
           "graph_used": res.trainer.graph_captured, "pattern_blur_px": res.trainer.renderer.pattern_blur,
           "metrics": res.metrics, "timeline": timeline(res.trainer)}
    if dev == "cuda":
        row["peak_gpu_mem_GB"] = torch.cuda.max_memory_allocated() / 1e9
    torch.backends.cuda.matmul.allow_tf32 = False
    return row


def timeline(trainer) -> list[dict]:
    """Wall ms per step between the run's logged iterations (each log reads the loss, which waits for the GPU),
    with NeuS's inv_s (1/mm) at the segment's end, the hash grid's active levels and whether the step was in the
    depth-search warm-up."""
    h = trainer.history
    rows, prev_it, prev_t = [], 0, 0.0
    for it, t, inv_s in zip(h.iters, h.elapsed_s, h.inv_s):
        if it > prev_it:
            rows.append({"from": prev_it, "to": it, "ms_per_it": (t - prev_t) / (it - prev_it) * 1e3, "inv_s": inv_s,
                         "levels": trainer.active_levels(it - 1), "warmup": trainer.in_warmup(it - 1)})
        prev_it, prev_t = it, t
    return rows


def markdown(doc: dict) -> str:
    nan = float("nan")
    opts = f" with {' '.join(doc['options'])}" if doc.get("options") else ""
    lines = [f"# Training speed, preset `{doc['preset']}`{opts}, {doc['scene']} ({doc['rig']} rig), {doc['device']}, {doc['date']}", ""]
    if doc.get("bench_command"):
        lines += [f"`{doc['bench_command'].strip()}`", ""]
    if doc["rows"]:
        lines += [f"Per iteration ({doc['iters']} timed after {doc['warmup']} untimed ones, at the end of the schedule "
                  f"with every hash-grid level on, start `{doc['rows'][0].get('init', 'sphere')}`; the preset runs "
                  f"{doc['rows'][0]['iters_of_preset']} + the depth-search warm-up). Breakdown: GPU ms per iteration "
                  "by phase, from the profiler; 'host/idle' is the wall time the GPU had no work (Python, launches, "
                  "synchronisation)." + (" On the CPU: CPU ms per phase, our Warp kernels counted inside the phases "
                  "(sampling kernels in MLP fwd, the fused render in losses, its backward in MLP bwd); 'host/idle' is the "
                  "rest (drawing the batch, Python between phases)." if doc["device"] == "CPU" else ""), "",
                  "| backend:mode:matmul[:graph] | ms/it | it/s | preset iters (s) | MLP fwd | losses, gathers | MLP bwd (incl. Eikonal) | our Warp kernels | Adam | host/idle | peak GB |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in doc["rows"]:
            b = r.get("breakdown_ms", {})
            cells = [f"{b.get(k, nan):.2f}" for k in ("mlp_forward", "losses_other", "mlp_backward", "warp_kernels", "adam", "host_and_idle")]
            lines.append(f"| {r['config']}{'' if r['graph_used'] or not r['config'].endswith('graph') else ' (capture failed)'} | "
                         f"{r['ms_per_it']:.2f} | {r['it_per_s']:.1f} | {r['projected_s']:.1f} | " + " | ".join(cells)
                         + f" | {r.get('peak_gpu_mem_GB', nan):.2f} |")
        for r in doc["rows"]:
            ks = r.get("breakdown_ms", {}).get("kernels")
            if ks:
                lines += ["", f"Kernels of `{r['config']}` by GPU time per iteration (the {len(ks)} largest):", "",
                          "| kernel | ms/it | launches/it |", "|---|---:|---:|"]
                lines += [f"| {k['kernel'].replace('|', '/')} | {k['ms']:.3f} | {k['launches']:.0f} |" for k in ks]
        base = {r["config"]: r["ms_per_it"] for r in doc["rows"]}
        for fast, slow in (("warp:compile:tf32:graph", "warp:compile:tf32:graph:twin"),
                           ("warp:eager:fp32", "warp:eager:fp32:twin"),
                           ("warp:compile:tf32:graph", "torch:compile:tf32:graph"), ("warp:compile:tf32:graph", "torch:compile:tf32"),
                           ("warp:compile:tf32:graph", "warp:compile:tf32"), ("warp:compile:tf32", "torch:compile:tf32"),
                           ("warp:eager:fp32", "torch:eager:fp32")):
            if fast in base and slow in base:
                lines.append(f"\n{slow} / {fast}: {base[slow] / base[fast]:.2f}x")
    if doc.get("end_to_end"):
        lines += ["", "## End to end: loaded scan to depth map (reconstruct(), default options of the preset)", "",
                  "Warm-up: a 5 + 5 iteration run of the same preset before (kernel builds, compile, capture).", "",
                  "'to depth map': reconstruct() up to the finished depth map; 'wall' adds the point cloud and the metrics "
                  "against the ground truth.", "",
                  "| backend | warm-up s | to depth map s | wall s | search + blur fit s | train s | it/s | marching cubes s | depth s | MAE mm | median mm | >5 mm | complete | peak GB |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in doc["end_to_end"]:
            t, m = r["timings"], r["metrics"] or {}
            lines.append(f"| {r['backend']}{' (graph)' if r['graph_used'] else ''} | {r.get('warmup_s', nan):.1f} | "
                         f"{t.get('depth_map_s', nan):.2f} | {r['wall_s']:.2f} | {t['setup_s']:.2f} | {t['train_s']:.2f} | "
                         f"{r['it_per_s']:.1f} | {t['marching_cubes_s']:.1f} | {t['depth_s']:.1f} | {m.get('mae', nan):.3f} | "
                         f"{m.get('median', nan):.3f} | {100 * m.get('over_5mm', nan):.2f}% | {100 * m.get('completeness', nan):.1f}% | "
                         f"{r.get('peak_gpu_mem_GB', nan):.2f} |")
        for r in doc["end_to_end"]:
            tl = r.get("timeline") or []
            if tl:
                lines += ["", f"Time per step along the `{r['backend']}` run (wall clock between logged iterations; "
                          "the first segment holds the plain steps before the capture):", "",
                          "| iterations | ms/it | levels | phase | inv_s 1/mm |", "|---|---:|---:|---|---:|"]
                lines += [f"| {x['from']}-{x['to']} | {x['ms_per_it']:.2f} | {x['levels'] if x['levels'] is not None else '-'} | "
                          f"{'warm-up' if x['warmup'] else 'main'} | {x.get('inv_s', float('nan')):.3g} |" for x in tl]
            t = r["timings"]
            stages = {k: v for k, v in t.items() if k.endswith("_s") and isinstance(v, float)
                      and k not in ("total_s", "train_wall_s_total", "depth_map_s")}
            lines += ["", f"Stages of the `{r['backend']}` run (s): " + ", ".join(f"{k[:-2]} {v:.3f}" for k, v in stages.items())]
        e = {r["backend"]: r for r in doc["end_to_end"]}
        if "warp" in e and "torch" in e:
            lines.append(f"\ntraining torch / warp: {e['torch']['timings']['train_s'] / e['warp']['timings']['train_s']:.2f}x; "
                         f"end to end: {e['torch']['wall_s'] / e['warp']['wall_s']:.2f}x")
    if doc.get("seeds"):
        lines += ["", "## Final accuracy of the two backends over seeds (paper preset, bunny)", "",
                  "Seed 0 from the end-to-end runs above; seeds 1 and 2 ran four at a time on the same GPU (their times "
                  "are not speed figures).", "",
                  "| seed | warp MAE mm | torch MAE mm | warp median mm | torch median mm |", "|---|---|---|---|---|"]
        by = {}
        for r in doc["seeds"]:
            by.setdefault(r["seed"], {})[r["backend"]] = r["metrics"]
        e = {r["backend"]: r["metrics"] for r in doc.get("end_to_end", [])}
        if "warp" in e and "torch" in e:
            by.setdefault(0, e)
        for seed in sorted(by):
            w, t = by[seed].get("warp") or {}, by[seed].get("torch") or {}
            lines.append(f"| {seed} | {w.get('mae', nan):.3f} | {t.get('mae', nan):.3f} | {w.get('median', nan):.3f} | {t.get('median', nan):.3f} |")
        import statistics

        for be in ("warp", "torch"):
            maes = [by[s_][be]["mae"] for s_ in by if by[s_].get(be)]
            if len(maes) > 1:
                lines.append(f"\n{be}: mean MAE {statistics.mean(maes):.3f} mm, spread (max - min) {max(maes) - min(maes):.3f} mm over {len(maes)} seeds")
    return "\n".join(lines)


def main(argv=None):
    import torch

    from slwarp.sim.simulate import simulate_scene

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--configs", nargs="*", default=None,
                   help="default CUDA: warp:eager:fp32 warp:compile:tf32 warp:compile:tf32:graph torch:compile:tf32 "
                        "torch:compile:tf32:graph; CPU: warp:eager:fp32 torch:eager:fp32")
    p.add_argument("--preset", default=None, help="default: the device's default preset (DEFAULT_PRESET)")
    p.add_argument("--scene", default="bunny")
    p.add_argument("--rig", default=None, help="default: default on CUDA, small on the CPU")
    p.add_argument("--warmup", type=int, default=20)
    p.add_argument("--iters", type=int, default=50)
    p.add_argument("--end-to-end", action="store_true", help="also run reconstruct() with each of --backends")
    p.add_argument("--backends", nargs="*", default=["warp", "torch"], choices=["warp", "torch"],
                   help="the backends of --end-to-end")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                   help="options applied to the preset (flat names of slwarp.neural.config, e.g. field=hashgrid)")
    p.add_argument("--init", default="preset", choices=["preset", "sphere", "trained"],
                   help="the timed steps' start: the preset's own (default; with a depth-search map, the terms that "
                        "use it are in the step), NeuS's sphere (no map: how figures before 2026-11-25 were timed), or "
                        "trained (the preset's start and its whole schedule first: the state at the end of training)")
    p.add_argument("--stem", default=None, help="output name (default train-speed-<device>[-<preset>])")
    p.add_argument("--out", default=str(REPO / "bench" / "results"))
    args = p.parse_args(argv)
    from slwarp.neural.config import ConfigError, parse_assignments

    try:
        options = parse_assignments(args.set)
    except ConfigError as e:
        raise SystemExit(f"--set {e}") from None
    dev = "cuda" if torch.cuda.is_available() else "cpu"
    from slwarp.neural.config import default_preset_name

    preset_name = args.preset or default_preset_name(dev)
    rig = args.rig or ("default" if dev == "cuda" else "small")
    configs = args.configs if args.configs is not None else (
        ["warp:eager:fp32", "warp:compile:tf32", "warp:compile:tf32:graph", "torch:compile:tf32", "torch:compile:tf32:graph"]
        if dev == "cuda" else ["warp:eager:fp32", "torch:eager:fp32"])
    scan = simulate_scene(args.scene, "random6", rig=rig, device="cuda:0" if dev == "cuda" else "cpu")
    name = torch.cuda.get_device_name(0) if dev == "cuda" else "CPU"
    doc = {"device": name, "date": str(datetime.date.today()), "preset": preset_name, "options": args.set,
           "bench_command": "python -m bench.train_speed " + " ".join(argv if argv is not None else sys.argv[1:]),
           "scene": args.scene, "rig": rig,
           "warmup": args.warmup, "iters": args.iters, "rows": [], "end_to_end": []}
    for spec in configs:
        torch.manual_seed(0)
        row = time_config(scan, spec, preset_name, args.warmup, args.iters, dev, options, init=args.init)
        doc["rows"].append(row)
        print(json.dumps(row), flush=True)
    if args.end_to_end:
        for backend in args.backends:
            row = end_to_end(scan, backend, preset_name, dev, options)
            doc["end_to_end"].append(row)
            print(json.dumps(row, default=float), flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tag = ("cuda" if dev == "cuda" else "cpu") + ("" if args.preset is None else f"-{preset_name}")
    stem = args.stem or f"train-speed-{tag}"
    old = out / f"{stem}.json"
    if old.is_file():  # a run of only the per-config rows or only --end-to-end keeps the other part
        prev = json.loads(old.read_text())
        if prev.get("device") == name and prev.get("preset") == preset_name and prev.get("options", []) == args.set:
            for part in ("rows", "end_to_end", "seeds"):
                if not doc.get(part) and prev.get(part):
                    doc[part] = prev[part]
    md = markdown(doc)
    print(md)
    (out / f"{stem}.json").write_text(json.dumps(doc, indent=1, default=float))
    (out / f"{stem}.md").write_text(md + "\n")


if __name__ == "__main__":
    main()
