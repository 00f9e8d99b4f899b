"""Microbenchmark: the fused structured-light render + losses, Warp vs the torch twin (eager and compiled).

For each size (R rays, S samples per ray, N patterns of 1280x800 projector pixels) it builds realistic
inputs on the device, checks the Warp outputs and gradients against the twin, then times
    fwd:      render + the three losses
    fwd+bwd:  the same and the backward to sdf, sdf_grad and inv_s
for backend warp, the twin in eager mode, and torch.compile of the twin. It also prints the floor: the
bytes the fused Warp kernels must move (each input read once, each output written once) over the
device's measured copy bandwidth, and the fraction of it the Warp path achieves.

The sampling ops of a training step (`bench_sampling`: one NeuS up-sampling step and the merge of the new
samples, at the training step's ray counts) are timed the same way, with the GPU time of each of their kernels.

    python -m bench.kernels                  # CUDA if present, else CPU (a reduced grid)
    python -m bench.kernels --device cpu --sizes 2048x64x6
    python -m bench.kernels --sampling-only  # only the up-sampling and merge ops
Writes bench/results/kernels-<device>.json and prints a markdown table.
"""
from __future__ import annotations

import argparse
import datetime
import json
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

from slwarp.neural import ops
from slwarp.neural.render import structured_light_losses
from slwarp.scans.patterns import random_binary
from slwarp.sim.rigs import make_rig

REPO = Path(__file__).resolve().parents[1]

FULL_GRID = [(R, S, N) for R in (2048, 16384, 65536) for S in (64, 128) for N in (6, 9)]
CPU_GRID = [(R, S, N) for R in (2048, 16384) for S in (64,) for N in (6,)]


def make_inputs(R, S, N, device, seed=0, layout="sample-major"):
    cam, proj = make_rig("default")
    g = torch.Generator().manual_seed(seed)
    pats = torch.as_tensor(random_binary(proj.width, proj.height, per_scale=-(-N // 3), seed=seed).patterns[:N]).to(device)
    pix = torch.rand(R, 2, generator=g) * torch.tensor([cam.width - 1.0, cam.height - 1.0])
    o, d, near, far = ops.camera_rays(pix.double(), cam, (450.0, 1100.0), backend="torch")
    z = ops.stratified_samples(near, far, S, torch.rand(R, generator=g, dtype=torch.float64) - 0.5, backend="torch")
    t_surf = 750.0 / d[:, 2] + torch.randn(R, generator=g, dtype=torch.float64) * 40
    sdf = (t_surf[:, None] - z) + torch.randn(R, S, generator=g, dtype=torch.float64) * 0.5
    grad = -d[:, None, :].expand(R, S, 3) + torch.randn(R, S, 3, generator=g, dtype=torch.float64) * 0.1
    f = lambda t: t.to(device=device, dtype=torch.float32).contiguous()  # noqa: E731
    if layout == "sample-major":  # [S, R] memory viewed as [R, S], as StructuredLightRenderer builds them
        sm = lambda t: t.to(device=device, dtype=torch.float32).transpose(0, 1).contiguous().transpose(0, 1)  # noqa: E731
        sdf, grad, z = sm(sdf), sm(grad), sm(z)
    obs = torch.rand(R, N, generator=g)
    bounds = [[-500.0, -400.0, 450.0], [500.0, 400.0, 1100.0]]
    keep = (lambda t: t) if layout == "sample-major" else f  # noqa: E731
    return dict(sdf=keep(sdf), grad=keep(grad), z=keep(z), o=f(o), d=f(d), a=f(torch.rand(R, generator=g) * 0.1),
                b=f(torch.rand(R, generator=g) * 0.5 + 0.2), pats=pats, pats_hwn=ops.pack_patterns(pats),
                obs=f(obs), valid=torch.ones(R, dtype=torch.bool, device=device),
                inv_s=torch.tensor(0.05, device=device), proj=ops.pack_projector(proj), bounds=bounds)


def loss_fn(backend, inp):
    def f(sdf, grad, inv_s):
        pat = inp["pats_hwn"] if backend == "warp" else inp["pats"]
        out = ops.render_structured_light(sdf, grad, inp["z"], inp["o"], inp["d"], inp["a"], inp["b"], pat, inp["proj"],
                                          inv_s, cos_anneal_ratio=1.0, backend=backend, bounds=inp["bounds"],
                                          patterns_layout="HWN" if backend == "warp" else "NHW")
        lc, ls, le = structured_light_losses(out, inp["obs"], inp["valid"])
        return lc + ls + 0.1 * le, out

    return f


def floor_bytes(R, S, N, H=800, W=1280) -> dict:
    """Bytes the fused kernels must move: every input read once, every output written once.
    Forward: sdf, sdf_grad, z (20 B/sample) in; weights, eikonal (8 B/sample) out; per-ray and pattern
    terms. Backward: the same inputs and the Eikonal cotangent (24 B/sample) in; d_sdf, d_grad
    (16 B/sample) out. The patterns (4 B per pixel per pattern) are read once per kernel."""
    rs = R * S
    per_ray_fwd = 4 * (3 + 3 + 1 + 1) + 4 * (N + 3 + N + 1 + 1 + 1)
    per_ray_bwd = 4 * (3 + 3 + 1 + 1) + 4 * (N + 3 + N + 1 + 1) + 4
    pat = 4 * H * W * N
    fwd = 28 * rs + per_ray_fwd * R + pat
    bwd = 40 * rs + per_ray_bwd * R + pat
    return {"fwd": fwd, "fwd_bwd": fwd + bwd}


def measure_bandwidth(device) -> float:
    """Device copy bandwidth (bytes/s), counting bytes read plus bytes written."""
    n = (1 << 28) if device.type == "cuda" else (1 << 25)
    x = torch.empty(n, dtype=torch.float32, device=device).uniform_()
    y = torch.empty_like(x)
    times = []
    for _ in range(10):
        times.append(timeit(lambda: y.copy_(x), device, reps=1, warmup=1 if not times else 0))
    return 2 * 4 * n / min(times)


def timeit(fn, device, reps=20, warmup=3) -> float:
    """Median seconds per call (CUDA events on GPU, perf_counter on CPU), after warm-up."""
    for _ in range(warmup):
        fn()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        ts = []
        for _ in range(reps):
            s, e = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            s.record()
            fn()
            e.record()
            e.synchronize()
            ts.append(s.elapsed_time(e) / 1e3)
        return statistics.median(ts)
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def check(inp) -> dict:
    """Agreement of the Warp outputs and gradients with the float32 twin.

    Per quantity: the largest error relative to the quantity's scale, over all but the worst 0.1% of
    rays. Those few rays have their surface point within ~1e-4 px of a projector pixel edge, where the
    bilinear pattern's slope jumps: float32 rounding (a few ulps of ~700 mm) decides which side the two
    implementations land on, and the surface term's gradient differs by the jump. `kink_rays` counts
    rays beyond 1e-3 relative error.
    """
    res = {}
    grads = {}
    outs = {}
    for be in ("warp", "torch"):
        args = [inp["sdf"].clone().requires_grad_(), inp["grad"].clone().requires_grad_(), inp["inv_s"].clone().requires_grad_()]
        loss, out = loss_fn(be, inp)(*args)
        grads[be] = torch.autograd.grad(loss, args)
        outs[be] = [t.detach() for t in out]
    names = ("rendered", "surface_points", "surface_rendered", "weights", "depth", "eikonal")
    pairs = [(f, getattr(ops.RenderOutput(*outs["warp"]), f), getattr(ops.RenderOutput(*outs["torch"]), f)) for f in names]
    pairs += list(zip(("d_sdf", "d_grad"), grads["warp"][:2], grads["torch"][:2]))
    worst = 0
    for name, w, t in pairs:
        assert torch.isfinite(w).all(), f"warp {name} not finite"
        per_ray = ((w - t).abs().reshape(w.shape[0], -1).amax(1) / t.abs().max().clamp(min=1e-12)).float()
        res[name] = float(torch.quantile(per_ray, 0.999)) if per_ray.numel() > 1 else float(per_ray.max())
        worst = max(worst, int((per_ray > 1e-3).sum()))
    dw, dt = grads["warp"][2], grads["torch"][2]
    res["d_inv_s"] = float((dw - dt).abs() / dt.abs().clamp(min=1e-12))
    res["kink_rays"] = worst
    return res


def kernel_times(inp, device) -> dict:
    """GPU time per kernel (us) of one warp fwd+bwd, from the torch profiler (CUPTI sees Warp's kernels)."""
    from torch.profiler import ProfilerActivity, profile

    f = loss_fn("warp", inp)
    args = [inp["sdf"].clone().requires_grad_(), inp["grad"].clone().requires_grad_(), inp["inv_s"].clone().requires_grad_()]
    for _ in range(3):
        torch.autograd.grad(f(*args)[0], args)
    torch.cuda.synchronize(device)
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(5):
            torch.autograd.grad(f(*args)[0], args)
        torch.cuda.synchronize(device)
    out = {}
    for ev in prof.key_averages():
        t = getattr(ev, "device_time_total", None) or getattr(ev, "cuda_time_total", 0)
        if t:
            out[ev.key[:60]] = t / 5
    return dict(sorted(out.items(), key=lambda kv: -kv[1]))


def graphed(fn, device):
    """fn replayed from a CUDA graph (warm-up on a side stream first, as torch requires)."""
    s = torch.cuda.Stream(device)
    s.wait_stream(torch.cuda.current_stream(device))
    with torch.cuda.stream(s):
        for _ in range(3):
            fn()
    torch.cuda.current_stream(device).wait_stream(s)
    g = torch.cuda.CUDAGraph()
    with torch.cuda.graph(g):
        fn()
    return g.replay


def twin_loss(sdf, grad, inv_s, z, o, d, a, b, pats, obs, valid, proj, bounds):
    """The twin's render + losses as one function of tensors (what torch.compile compiles)."""
    out = ops.render_structured_light(sdf, grad, z, o, d, a, b, pats, proj, inv_s, backend="torch", bounds=bounds)
    lc, ls, le = structured_light_losses(out, obs, valid)
    return lc + ls + 0.1 * le


# one compiled function per grad mode, shared by all sizes: torch.compile specialises on the first
# size and then compiles a dynamic-shape version, instead of recompiling for every size
COMPILED = {}


def bench_size(R, S, N, device, reps, backends, layout) -> dict:
    inp = make_inputs(R, S, N, device, layout=layout)
    row = {"R": R, "S": S, "N": N, "check": check(inp)}
    args = [inp["sdf"].clone().requires_grad_(), inp["grad"].clone().requires_grad_(), inp["inv_s"].clone().requires_grad_()]
    rest = [inp[k] for k in ("z", "o", "d", "a", "b", "pats", "obs", "valid")] + [inp["proj"], inp["bounds"]]
    for be in backends:
        if be.startswith("compile"):
            if not COMPILED:
                torch._dynamo.config.recompile_limit = 64
                COMPILED["fwd"], COMPILED["grad"] = torch.compile(twin_loss), torch.compile(twin_loss)
            f_fwd = lambda a, b, c: COMPILED["fwd"](a, b, c, *rest)  # noqa: E731
            f_grad = lambda a, b, c: COMPILED["grad"](a, b, c, *rest)  # noqa: E731
        else:
            base = loss_fn(be.replace("+graph", ""), inp)
            f_fwd = f_grad = lambda a, b, c: base(a, b, c)[0]  # noqa: E731

        def fwd():
            with torch.no_grad():
                return f_fwd(*args)

        def fwd_bwd():
            return torch.autograd.grad(f_grad(*args), args)

        try:
            if be.endswith("+graph"):
                fwd_run, fwd_bwd_run = graphed(fwd, device), graphed(fwd_bwd, device)
            else:
                fwd_run, fwd_bwd_run = fwd, fwd_bwd
            row[f"{be}_fwd_ms"] = timeit(fwd_run, device, reps) * 1e3
            row[f"{be}_fwd_bwd_ms"] = timeit(fwd_bwd_run, device, reps) * 1e3
        except Exception as e:  # noqa: BLE001 - a backend that fails at one size is reported, not fatal
            row[f"{be}_error"] = f"{type(e).__name__}: {e}"[:300]
    row["floor_bytes"] = floor_bytes(R, S, N)
    if device.type == "cuda" and R == 65536 and S == 64:
        row["kernel_us"] = kernel_times(inp, device)
    return row


# (R rays, S current samples, n new samples): the fast preset's two up-sampling steps (32 + 16, 48 + 16 at 1024 rays),
# four steps of 64 + 64 samples, and a large batch
SAMPLING_GRID = [(1024, 32, 16), (1024, 48, 16), (1024, 112, 16), (16384, 64, 16)]
CPU_SAMPLING_GRID = [(1024, 32, 16), (1024, 48, 16)]


def sampling_inputs(R, S, device, seed=0):
    """Rays of the default rig, stratified samples (row-major [R, S], as the sampler makes them) and an SDF with
    a surface near 750 mm, plus the bounds of the working volume."""
    cam, _ = make_rig("default")
    g = torch.Generator().manual_seed(seed)
    pix = (torch.rand(R, 2, generator=g) * torch.tensor([cam.width - 1.0, cam.height - 1.0])).to(device)
    o, d, near, far = ops.camera_rays(pix, cam, (450.0, 1100.0))
    z = ops.stratified_samples(near, far, S, (torch.rand(R, generator=g) - 0.5).to(device))
    t_surf = 750.0 / d[:, 2] + (torch.randn(R, generator=g) * 40).to(device)
    sdf = t_surf[:, None] - z + (torch.randn(R, S, generator=g) * 0.5).to(device)
    return dict(z=z, sdf=sdf, o=o, d=d, t_surf=t_surf, bounds=[[-500.0, -400.0, 450.0], [500.0, 400.0, 1100.0]])


def graphed_repeat(fn, device, n=20):
    """Replay of a CUDA graph holding n calls of fn, and n: the GPU time per call without launch overhead."""
    replay = graphed(lambda: [fn() for _ in range(n)], device)
    return replay, n


def sampling_kernel_times(fns, device) -> dict:
    """GPU time per call (us) of each Warp kernel the sampling ops launch, from the torch profiler."""
    from torch.profiler import ProfilerActivity, profile

    for f in fns:
        f()
    torch.cuda.synchronize(device)
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(10):
            for f in fns:
                f()
        torch.cuda.synchronize(device)
    out = {}
    for ev in prof.key_averages():
        t = getattr(ev, "device_time_total", None) or getattr(ev, "cuda_time_total", 0)
        if t and ("upsample" in ev.key or "merge_sorted" in ev.key):
            out[ev.key[:60]] = t / 10
    return out


def bench_sampling(R, S, n, device, reps) -> dict:
    """Median ms per call of one up-sampling step (S -> n new samples) and of the merge S + n, for Warp (eager
    and, on CUDA, replayed from a graph of 20 calls) and the torch twin; the Warp results against the twin."""
    inp = sampling_inputs(R, S, device)
    z, sdf, o, d, bounds = inp["z"], inp["sdf"], inp["o"], inp["d"], inp["bounds"]
    inv_s = 64.0 / 500.0
    z_new = ops.upsample_samples(z, sdf, o, d, n, inv_s, bounds=bounds)
    f_new = inp["t_surf"][:, None] - z_new
    row = {"R": R, "S": S, "n": n}
    ref = ops.upsample_samples(z, sdf, o, d, n, inv_s, bounds=bounds, backend="torch")
    row["upsample_max_abs_err_mm"] = float((z_new - ref).abs().max())
    mz, mf = ops.merge_samples(z, sdf, z_new, f_new)
    tz, tf = ops.merge_samples(z, sdf, z_new, f_new, backend="torch")
    row["merge_equal"] = bool(torch.equal(mz, tz) and torch.equal(mf, tf))
    calls = {
        "upsample": lambda be: ops.upsample_samples(z, sdf, o, d, n, inv_s, bounds=bounds, backend=be),
        "merge": lambda be: ops.merge_samples(z, sdf, z_new, f_new, backend=be),
    }
    for name, call in calls.items():
        for be in ("warp", "torch"):
            row[f"{name}_{be}_ms"] = timeit(lambda: call(be), device, reps) * 1e3
        if device.type == "cuda":
            replay, k = graphed_repeat(lambda: call("warp"), device)
            row[f"{name}_warp+graph_ms"] = timeit(replay, device, reps) * 1e3 / k
    if device.type == "cuda":
        row["kernel_us"] = sampling_kernel_times([lambda: calls["upsample"]("warp"), lambda: calls["merge"]("warp")], device)
    return row


def format_sampling_table(rows) -> str:
    cols = [c for c in ("warp", "warp+graph", "torch") if any(f"upsample_{c}_ms" in r for r in rows)]
    head = "| R | S | n | " + " | ".join(f"upsample {c}" for c in cols) + " | " + " | ".join(f"merge {c}" for c in cols) + \
           " | upsample vs twin (mm) | merge equal |"
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        cells = [str(r["R"]), str(r["S"]), str(r["n"])]
        cells += [f"{r[f'upsample_{c}_ms']:.4f}" for c in cols] + [f"{r[f'merge_{c}_ms']:.4f}" for c in cols]
        cells += [f"{r['upsample_max_abs_err_mm']:.1e}", str(r["merge_equal"])]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--sizes", nargs="*", help="RxSxN sizes (default: the full grid on CUDA, a reduced one on CPU)")
    p.add_argument("--backends", default=None, help="comma-separated: warp, warp+graph, torch, torch+graph, compile "
                   "(default: all of warp, warp+graph, torch, compile on CUDA; warp, torch, compile on CPU)")
    p.add_argument("--reps", type=int, default=None)
    p.add_argument("--layout", default="sample-major", choices=["sample-major", "ray-major"],
                   help="memory order of the [R, S] inputs (default: sample-major, as the renderer builds them)")
    p.add_argument("--out", default=str(REPO / "bench" / "results"))
    p.add_argument("--sampling-only", action="store_true", help="time only the up-sampling and merge ops (bench_sampling)")
    args = p.parse_args(argv)
    device = torch.device(args.device)
    grid = [tuple(int(v) for v in s.split("x")) for s in args.sizes] if args.sizes else (FULL_GRID if device.type == "cuda" else CPU_GRID)
    reps = args.reps or (30 if device.type == "cuda" else 3)
    backends = (args.backends or ("warp,warp+graph,torch,compile" if device.type == "cuda" else "warp,torch,compile")).split(",")
    bw = measure_bandwidth(device)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else (platform.processor() or platform.machine()) + f" ({torch.get_num_threads()} threads)"
    print(f"device: {name}; measured copy bandwidth {bw / 1e9:.0f} GB/s")
    sampling_rows = []
    for R, S, n in (SAMPLING_GRID if device.type == "cuda" else CPU_SAMPLING_GRID):
        row = bench_sampling(R, S, n, device, reps)
        sampling_rows.append(row)
        print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()}), flush=True)
    sampling_table = format_sampling_table(sampling_rows)
    print(sampling_table)
    rows = []
    for R, S, N in ([] if args.sampling_only else grid):
        row = bench_size(R, S, N, device, reps, backends, args.layout)
        for key in ("fwd", "fwd_bwd"):
            row[f"floor_{key}_ms"] = row["floor_bytes"][key] / bw * 1e3
            for be in ("warp", "warp+graph"):
                if f"{be}_{key}_ms" in row:
                    row[f"{be}_{key}_floor_fraction"] = row[f"floor_{key}_ms"] / row[f"{be}_{key}_ms"]
        rows.append(row)
        print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()}), flush=True)
    table = format_table(rows, backends)
    if rows:
        print(table)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tag = "cuda" if device.type == "cuda" else "cpu"
    meta = {"device": name, "date": datetime.date.today().isoformat(), "torch": torch.__version__, "layout": args.layout,
            "copy_bandwidth_GBps": bw / 1e9, "rows": rows, "sampling": sampling_rows}
    try:
        import warp

        meta["warp"] = warp.__version__
    except ImportError:
        pass
    tag += "" if args.layout == "sample-major" else "-raymajor"
    tag += "-sampling" if args.sampling_only else ""
    (out / f"kernels-{tag}.json").write_text(json.dumps(meta, indent=1))
    title = "Sampling ops" if args.sampling_only else "Fused render + losses"
    render_part = "" if args.sampling_only else table + "\n\n"
    (out / f"kernels-{tag}.md").write_text(f"# {title}, {name}, {meta['date']}\n\n"
                                           f"Copy bandwidth {bw / 1e9:.0f} GB/s (read + write). Inputs {args.layout}. Times: median ms.\n\n" + render_part +
                                           "## Sampling ops (one up-sampling step, S -> n new samples; the merge S + n)\n\n"
                                           "warp+graph: per call, replayed from a CUDA graph of 20 calls. Times: median ms.\n\n"
                                           + sampling_table + "\n")
    return 0


def format_table(rows, backends) -> str:
    fastest = [b for b in ("warp+graph", "warp") if b in backends]
    head = "| R | S | N | " + " | ".join(f"{b} fwd | {b} fwd+bwd" for b in backends) + \
           " | floor fwd+bwd | best warp / floor | eager / best warp | compile / best warp | check (rel err, kink rays) |"
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        cells = [str(r["R"]), str(r["S"]), str(r["N"])]
        for b in backends:
            for k in ("fwd", "fwd_bwd"):
                v = r.get(f"{b}_{k}_ms")
                cells.append(f"{v:.3f}" if v is not None else "err")
        warp = [r[f"{b}_fwd_bwd_ms"] for b in fastest if r.get(f"{b}_fwd_bwd_ms")]
        w = min(warp) if warp else None
        cells.append(f"{r['floor_fwd_bwd_ms']:.3f}")
        cells.append(f"{w / r['floor_fwd_bwd_ms']:.1f}x" if w else "-")
        for b in ("torch", "compile"):
            v = r.get(f"{b}_fwd_bwd_ms")
            cells.append(f"{v / w:.1f}x" if v and w else "-")
        chk = r["check"]
        cells.append(f"{max(v for k, v in chk.items() if k != 'kink_rays'):.1e}, {chk['kink_rays']}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
