"""Microbenchmark: the fused structured-light render + losses, Warp vs the torch twin (eager and compiled).

For each size (R rays, S samples per ray, N patterns of 1280x800 projector pixels) it builds realistic
inputs on the device, checks the Warp outputs and gradients against the twin, then times
    fwd:      render + the three losses
    fwd+bwd:  the same and the backward to sdf, sdf_grad and inv_s
for backend warp, the twin in eager mode, and torch.compile of the twin. It also prints the floor: the
bytes the fused Warp kernels must move (each input read once, each output written once) over the
device's measured copy bandwidth, and the fraction of it the Warp path achieves.

The sampling ops of a training step (`bench_sampling`: one NeuS up-sampling step and the merge of the new
samples, at the training step's ray counts) are timed the same way, with the GPU time of each of their kernels,
and so are the hash-grid ops (`bench_hashgrid`: encoding, spatial gradient and their backward passes at the
points of a fast or accurate step).

    python -m bench.kernels                  # CUDA if present, else CPU (a reduced grid)
    python -m bench.kernels --device cpu --sizes 2048x64x6
    python -m bench.kernels --parts hashgrid,render --backends warp,warp+graph   # the Warp kernels only
    python -m bench.kernels --sampling-only  # only the up-sampling and merge ops
Writes bench/results/kernels-<device>[-<parts>].json and .md, and prints the tables.
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
from slwarp.neural.fields.hashgrid import TETRAHEDRON, HashGridLayout, hashgrid_encode, hashgrid_gradient
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
    """GPU time per kernel (us) of one warp fwd+bwd (see profiled_kernel_times), longest first."""
    f = loss_fn("warp", inp)
    args = [inp["sdf"].clone().requires_grad_(), inp["grad"].clone().requires_grad_(), inp["inv_s"].clone().requires_grad_()]
    out = profiled_kernel_times([lambda: torch.autograd.grad(f(*args)[0], args)], device, ("",))
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


def profiled_kernel_times(fns, device, markers) -> dict:
    """GPU time per call (us) of each kernel whose name holds one of `markers` ("" for all), over the calls fns, from
    the torch profiler (CUPTI sees Warp's kernels)."""
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
        if t and any(m in ev.key for m in markers):
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
        row["kernel_us"] = profiled_kernel_times([lambda: calls["upsample"]("warp"), lambda: calls["merge"]("warp")], device,
                                                 ("upsample", "merge_sorted"))
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


# (R rays, S samples per ray, L levels): the hash grid evaluated at the 4 tetrahedral taps around each sample (P = 4 R S
# points, ray after ray), 2 features per level, 2^19 entries per hashed level, 16..2048 cells: the fast (1024 rays) and
# accurate (2048 rays) presets' 8 levels, and 16 levels
HASHGRID_GRID = [(1024, 64, 8), (2048, 64, 8), (2048, 64, 16)]
CPU_HASHGRID_GRID = [(64, 32, 8)]


def hashgrid_inputs(R, S, levels, device, seed=0) -> dict:
    """Unit-cube points x [4 R S, 3] as the field sees them in a step, a table, meta, active (all levels on) and
    cotangents g [P, 2 L] of the features and h [P, 3] of the spatial gradient."""
    layout = HashGridLayout(levels=levels, features=2, log2_table_size=19, base_resolution=16, finest_resolution=2048)
    g = torch.Generator().manual_seed(seed)
    o = torch.rand(R, 3, generator=g) * 0.3 + 0.35
    d = torch.nn.functional.normalize(torch.randn(R, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, 1.0]), dim=-1)
    x = o[:, None] + d[:, None] * torch.linspace(-0.3, 0.3, S)[None, :, None]  # [R, S, 3]
    taps = torch.tensor(TETRAHEDRON) / layout.resolutions[-1]
    x = (x.reshape(1, -1, 3) + taps[:, None]).reshape(-1, 3)
    return dict(x=x.to(device), table=(torch.randn(layout.n_entries, 2, generator=g) * 1e-2).to(device),
                meta=layout.meta(device), active=torch.tensor([levels], dtype=torch.int32, device=device),
                g=torch.randn(x.shape[0], 2 * levels, generator=g).to(device), h=torch.randn(x.shape[0], 3, generator=g).to(device))


def bench_hashgrid(R, S, levels, device, reps) -> dict:
    """Median ms per call of the hash-grid ops, Warp (eager and, on CUDA, replayed from a CUDA graph of 20 calls):
    the encoding, it and its backward into the table (the finite-difference fields' path), the spatial gradient,
    and it and its backward into the table and g (the analytic path); the GPU time of each kernel; the relative
    error against the twin on the first 4096 points."""
    inp = hashgrid_inputs(R, S, levels, device)
    x, table, meta, active, g, h = (inp[k] for k in ("x", "table", "meta", "active", "g", "h"))
    tp, gp = table.clone().requires_grad_(), g.clone().requires_grad_()
    calls = {
        "encode": lambda: hashgrid_encode(x, table, meta, active),
        "encode_fwd_bwd": lambda: torch.autograd.grad(hashgrid_encode(x, tp, meta, active), [tp], g),
        "gradient": lambda: hashgrid_gradient(x, table, g, meta, active),
        "gradient_fwd_bwd": lambda: torch.autograd.grad(hashgrid_gradient(x, tp, gp, meta, active), [tp, gp], h),
    }
    row = {"R": R, "S": S, "levels": levels, "points": x.shape[0]}
    k = slice(0, 4096)
    for name, op, args in (("encode", hashgrid_encode, (x[k], table)), ("gradient", hashgrid_gradient, (x[k], table, g[k]))):
        w, t = op(*args, meta, active), op(*args, meta, active, backend="torch")
        row[f"{name}_rel_err"] = float((w - t).abs().max() / t.abs().max().clamp(min=1e-30))
    for name, call in calls.items():
        row[f"{name}_ms"] = timeit(call, device, reps) * 1e3
        if device.type == "cuda":
            replay, n = graphed_repeat(call, device)
            row[f"{name}_graph_ms"] = timeit(replay, device, reps) * 1e3 / n
    if device.type == "cuda":
        row["kernel_us"] = profiled_kernel_times(list(calls.values()), device, ("hashgrid",))
    return row


def format_hashgrid_table(rows) -> str:
    names = ("encode", "encode_fwd_bwd", "gradient", "gradient_fwd_bwd")
    cols = [f"{n}_ms" for n in names] + [f"{n}_graph_ms" for n in names if any(f"{n}_graph_ms" in r for r in rows)]
    head = "| R | S | levels | points | " + " | ".join(c[:-3].replace("_fwd_bwd", " fwd+bwd").replace("_graph", " graph")
                                                     for c in cols) + " | encode vs twin | gradient vs twin |"
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        cells = [str(r[c]) for c in ("R", "S", "levels", "points")] + [f"{r[c]:.4f}" for c in cols]
        cells += [f"{r['encode_rel_err']:.1e}", f"{r['gradient_rel_err']:.1e}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def print_row(row):
    print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()}), flush=True)


PARTS = ("sampling", "hashgrid", "render")


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
    p.add_argument("--parts", default=",".join(PARTS), help=f"comma-separated, of {', '.join(PARTS)} (default: all)")
    p.add_argument("--sampling-only", action="store_true", help="the same as --parts sampling")
    args = p.parse_args(argv)
    parts = ["sampling"] if args.sampling_only else args.parts.split(",")
    if not parts or not set(parts) <= set(PARTS):
        p.error(f"--parts: choose from {', '.join(PARTS)}")
    device = torch.device(args.device)
    cuda = device.type == "cuda"
    grid = [tuple(int(v) for v in s.split("x")) for s in args.sizes] if args.sizes else (FULL_GRID if cuda else CPU_GRID)
    reps = args.reps or (30 if cuda else 3)
    backends = (args.backends or ("warp,warp+graph,torch,compile" if cuda else "warp,torch,compile")).split(",")
    bw = measure_bandwidth(device)
    name = torch.cuda.get_device_name(device) if cuda else (platform.processor() or platform.machine()) + f" ({torch.get_num_threads()} threads)"
    print(f"device: {name}; measured copy bandwidth {bw / 1e9:.0f} GB/s")
    res = {"sampling": [], "hashgrid": [], "rows": []}
    for R, S, n in (SAMPLING_GRID if cuda else CPU_SAMPLING_GRID) if "sampling" in parts else []:
        res["sampling"].append(bench_sampling(R, S, n, device, reps))
        print_row(res["sampling"][-1])
    for R, S, levels in (HASHGRID_GRID if cuda else CPU_HASHGRID_GRID) if "hashgrid" in parts else []:
        res["hashgrid"].append(bench_hashgrid(R, S, levels, device, reps))
        print_row(res["hashgrid"][-1])
    for R, S, N in grid if "render" in parts else []:
        row = bench_size(R, S, N, device, reps, backends, args.layout)
        for key in ("fwd", "fwd_bwd"):
            row[f"floor_{key}_ms"] = row["floor_bytes"][key] / bw * 1e3
            for be in ("warp", "warp+graph"):
                if f"{be}_{key}_ms" in row:
                    row[f"{be}_{key}_floor_fraction"] = row[f"floor_{key}_ms"] / row[f"{be}_{key}_ms"]
        res["rows"].append(row)
        print_row(row)
    tag = ("cuda" if cuda else "cpu") + ("" if args.layout == "sample-major" else "-raymajor")
    tag += "" if parts == list(PARTS) else "-" + "-".join(parts)
    write_results(Path(args.out), tag, res, backends, args.layout, name, bw)
    return 0


def write_results(out: Path, tag: str, res: dict, backends, layout: str, name: str, bw: float):
    """kernels-<tag>.json (the rows of each part) and kernels-<tag>.md (their tables), also printed."""
    out.mkdir(parents=True, exist_ok=True)
    meta = {"device": name, "date": datetime.date.today().isoformat(), "torch": torch.__version__, "layout": layout,
            "copy_bandwidth_GBps": bw / 1e9, **res}
    try:
        import warp

        meta["warp"] = warp.__version__
    except ImportError:
        pass
    (out / f"kernels-{tag}.json").write_text(json.dumps(meta, indent=1))
    sections = []
    if res["rows"]:
        sections.append(f"## Fused render + losses (inputs {layout})\n\n" + format_table(res["rows"], backends))
    if res["sampling"]:
        sections.append("## Sampling ops (one up-sampling step, S -> n new samples; the merge S + n)\n\n"
                        "warp+graph: per call, replayed from a CUDA graph of 20 calls.\n\n" + format_sampling_table(res["sampling"]))
    if res["hashgrid"]:
        sections.append("## Hash-grid ops (Warp; 2 features per level, 2^19 entries per hashed level)\n\n"
                        "graph: per call, replayed from a CUDA graph of 20 calls.\n\n" + format_hashgrid_table(res["hashgrid"]))
    text = f"# Kernels, {name}, {meta['date']}\n\nCopy bandwidth {bw / 1e9:.0f} GB/s (read + write). Times: median ms.\n\n"
    text += "\n\n".join(sections) + "\n"
    print(text)
    (out / f"kernels-{tag}.md").write_text(text)


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
