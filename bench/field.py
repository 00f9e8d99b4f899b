"""Field benchmark: f + grad f (the renderer's field call) forward and backward per SDF field, eager and as
a CUDA graph, with peak memory; the hash grid's Warp encoding against its torch twin, and the accuracy of
the analytic and finite-difference gradients against a float64 reference.

    python -m bench.field                          # CUDA if present (P = 131072 points), else CPU (P = 4096)
    python -m bench.field --device cpu --points 1024 --repeats 3          # smoke run
    python -m bench.field --fields hashgrid-warp hashgrid-torch --compile  # + torch.compile'd rows

Order: (1) correctness: the Warp hash-grid field against the same field with the torch-twin encoding (value,
gradient, every parameter gradient of an Eikonal + value loss), and NeuS's explicit gradient against
autograd; a failure stops the run before any timing. (2) accuracy: on a default hash grid fitted to a bumpy
sphere (radius 200 mm, +-2 mm bumps of 15 mm period: mm-scale detail at the finest levels), the float32
analytic gradient (Warp) and the tetrahedral finite difference (step: the finest active level's cell)
against the float64 analytic gradient of the same field (torch twin, float64, CPU), near the surface. (3) timings per field and mode:
    fwd      value_and_gradient(x) on P points (what the renderer calls per sample)
    fwd+bwd  the same, an Eikonal + |f| loss, and its gradient into every parameter (first-order autograd)
modes: eager; graph (the whole fwd+bwd captured once as a CUDA graph and replayed); with --compile also
torch.compile'd (and compiled + graph). Peak memory: torch.cuda.max_memory_allocated during one fwd+bwd,
minus what was allocated before it (parameters and inputs), on CUDA.

Fields: neus-mlp (NeuSField 8 x 256, skip 4, 6 frequencies, weight norm: today's default field);
hashgrid-{warp,torch}-{analytic,fd}: HashGridSDF's defaults (16 levels x 2 features, 2^19 entries, 16..2048
cells, 1 x 64 Softplus) with the Warp or the torch-twin encoding and the analytic or the tetrahedral
finite-difference gradient; hashgrid-warp-fd-2x64 and hashgrid-warp-fd-relu (MLP variants, on request).
Points: uniform in the default rig's working volume (~790 mm wide; cells of 0.39 mm at the finest level).
Writes bench/results/field-<device>.json and .md.
"""
from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import platform
import sys
import time
from pathlib import Path

import torch

from bench.kernels import graphed, timeit

REPO = Path(__file__).resolve().parents[1]

from slwarp.neural.fields import HashGridSDF, NeuSField, Volume  # noqa: E402

# the default rig's working volume for the bunny (Volume.from_frustum of its lit pixels, 450..1100 mm)
DEFAULT_VOLUME = Volume((-410.3, -312.0, 434.8), (380.8, 311.1, 1115.2))

FIELDS = {
    "neus-mlp": lambda vol: NeuSField(vol),
    "hashgrid-warp-analytic": lambda vol: HashGridSDF(vol, backend="warp", gradient="analytic"),
    "hashgrid-torch-analytic": lambda vol: HashGridSDF(vol, backend="torch", gradient="analytic"),
    "hashgrid-warp-fd": lambda vol: HashGridSDF(vol, backend="warp", gradient="finite_difference"),
    "hashgrid-torch-fd": lambda vol: HashGridSDF(vol, backend="torch", gradient="finite_difference"),
    "hashgrid-warp-fd-2x64": lambda vol: HashGridSDF(vol, backend="warp", gradient="finite_difference", layers=2),
    "hashgrid-warp-fd-relu": lambda vol: HashGridSDF(vol, backend="warp", gradient="finite_difference", activation="relu"),
}
DEFAULT_FIELDS = ["neus-mlp", "hashgrid-warp-analytic", "hashgrid-torch-analytic", "hashgrid-warp-fd", "hashgrid-torch-fd"]


def sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def points(n, device, seed=0, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    lo = torch.tensor(DEFAULT_VOLUME.lo, dtype=torch.float64)
    hi = torch.tensor(DEFAULT_VOLUME.hi, dtype=torch.float64)
    return (torch.rand(n, 3, generator=g, dtype=torch.float64) * (hi - lo) + lo).to(device=device, dtype=dtype)


def roughen(field: HashGridSDF, amplitude: float = 1e-3, seed: int = 0) -> HashGridSDF:
    """Tables uniform in +-amplitude and perturbed MLP weights, so that every parameter gets a gradient."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        field.table.copy_((torch.rand(field.table.shape, generator=g) * 2 - 1) * amplitude)
        for lin in field.linears:
            lin.weight.add_((torch.randn(lin.weight.shape, generator=g) * 0.05).to(lin.weight.device))
    return field


def eikonal_loss(field, x):
    f, g = field.value_and_gradient(x)
    return ((g.norm(dim=-1) - 1.0) ** 2).mean() + f.abs().mean() / field.scale


def rel_err(a, b) -> float:
    """max |a - b| / max |b|."""
    return float((a.double().cpu() - b.double().cpu()).abs().max() / b.double().abs().max().clamp(min=1e-30).cpu())


def check_correctness(device, n: int) -> dict:
    """The Warp hash-grid field against the torch-twin field (same parameters), and NeuS's explicit
    gradient against autograd. Raises AssertionError with the numbers when they disagree."""
    out = {}
    x = points(n, device, seed=1)
    for gradient in ("analytic", "finite_difference"):
        torch.manual_seed(0)
        warp_field = roughen(HashGridSDF(DEFAULT_VOLUME, backend="warp", gradient=gradient)).to(device)
        twin_field = HashGridSDF(DEFAULT_VOLUME, backend="torch", gradient=gradient).to(device)
        twin_field.load_state_dict(warp_field.state_dict())
        res = {}
        for name, field in (("warp", warp_field), ("torch", twin_field)):
            f, g = field.value_and_gradient(x)
            loss = ((g.norm(dim=-1) - 1.0) ** 2).mean() + f.abs().mean() / field.scale
            res[name] = [f.detach(), g.detach(), *torch.autograd.grad(loss, list(field.parameters()))]
        names = ["f", "grad"] + ["d_" + k for k, _ in warp_field.named_parameters()]
        key = f"hashgrid_{gradient}_warp_vs_twin"
        out[key] = {k: rel_err(a, b) for k, a, b in zip(names, res["warp"], res["torch"])}
        bad = {k: v for k, v in out[key].items() if not v < 1e-3}
        assert not bad, f"Warp hash grid ({gradient} gradient) disagrees with its torch twin: {bad}"
    neus = NeuSField(DEFAULT_VOLUME).to(device)
    xs = points(min(n, 4096), device, seed=2).requires_grad_()
    f = neus(xs)
    (g_auto,) = torch.autograd.grad(f.sum(), xs)
    _, g_exp = neus.value_and_gradient(xs.detach())
    out["neus_explicit_vs_autograd"] = rel_err(g_exp, g_auto)
    assert out["neus_explicit_vs_autograd"] < 1e-4, f"NeuS explicit gradient: {out['neus_explicit_vs_autograd']}"
    return out


def target_sdf(x: torch.Tensor) -> torch.Tensor:
    """A bumpy sphere (mm): radius 200 mm at the volume's centre with +-2 mm bumps of 15 mm period."""
    c = torch.tensor(DEFAULT_VOLUME.center, dtype=x.dtype, device=x.device)
    w = 2 * torch.pi / 15.0
    bumps = 2.0 * torch.sin(w * x[..., 0]) * torch.sin(w * x[..., 1]) * torch.sin(w * x[..., 2])
    return (x - c).norm(dim=-1) - 200.0 - bumps


def near_surface(n: int, seed: int, band: float = 5.0, dtype=torch.float64) -> torch.Tensor:
    """n points within +-band mm of the bumpy sphere's base radius (uniform directions)."""
    g = torch.Generator().manual_seed(seed)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1)
    r = 200.0 + (torch.rand(n, 1, generator=g, dtype=torch.float64) * 2 - 1) * band
    return (torch.tensor(DEFAULT_VOLUME.center, dtype=torch.float64) + d * r).to(dtype)


def fitted_field(steps: int, device) -> HashGridSDF:
    """A default HashGridSDF (Warp encoding, on `device`) regressed onto the bumpy sphere near its surface (L1 on the
    value + 0.1 Eikonal, Adam 1e-2 on the tables and 1e-3 on the MLP as in Instant-NGP/NeuS2): a field with
    mm-scale detail at the finest levels, like a trained one."""
    torch.manual_seed(0)
    field = HashGridSDF(DEFAULT_VOLUME, backend="warp", gradient="analytic").to(device)
    opt = torch.optim.Adam([{"params": [field.table], "lr": 1e-2},
                            {"params": [p for n, p in field.named_parameters() if n != "table"], "lr": 1e-3}])
    for i in range(steps):
        x = near_surface(4096, seed=100 + i, band=20.0, dtype=torch.float32).to(device)
        f, g = field.value_and_gradient(x)
        loss = (f - target_sdf(x)).abs().mean() + 0.1 * ((g.norm(dim=-1) - 1.0) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return field


def gradient_accuracy(n: int, fit_steps: int, device) -> dict:
    """float32 analytic (Warp) and tetrahedral finite-difference gradients against the float64 analytic
    gradient (torch twin) of the same fitted field (see fitted_field), on `device` (Warp runs where the timings
    run: a GPU machine may have no CPU compiler for Warp), at n points within
    5 mm of its surface. Errors of the gradient vector relative to |grad| per point; vs_shape: against the
    bumpy sphere's own gradient (how well each method's gradient describes the shape the field learnt)."""
    fitted = fitted_field(fit_steps, device)
    ref = HashGridSDF(DEFAULT_VOLUME, backend="torch", gradient="analytic").double().to(device)
    ref.load_state_dict(fitted.state_dict())
    x64 = near_surface(n, seed=3).to(device)
    f_ref, g_ref = ref.value_and_gradient(x64)
    xt = x64.clone().requires_grad_()
    (g_target,) = torch.autograd.grad(target_sdf(xt).sum(), xt)
    out = {"points": n, "fit_steps": fit_steps, "fit_mae_mm": float((f_ref - target_sdf(x64)).abs().mean()),
           "active_levels": ref.n_active, "fd_step_mm": float(ref.finite_difference_step()),
           "ref_grad_norm_median": float(g_ref.norm(dim=-1).median())}
    for name, kw in (("analytic_float32", dict(gradient="analytic")), ("finite_difference_float32", dict(gradient="finite_difference")),
                     ("finite_difference_float64", dict(gradient="finite_difference", backend="torch"))):
        f = HashGridSDF(DEFAULT_VOLUME, **{"backend": "warp", **kw}).to(device)
        if kw.get("backend") == "torch":
            f = f.double()
        f.load_state_dict(ref.state_dict())
        xx = x64 if kw.get("backend") == "torch" else x64.float()
        with torch.no_grad():
            _, g = f.value_and_gradient(xx)
        e = ((g.double() - g_ref).norm(dim=-1) / g_ref.norm(dim=-1))
        n_err = (g.double().norm(dim=-1) - g_ref.norm(dim=-1)).abs()
        e_t = ((g.double() - g_target).norm(dim=-1) / g_target.norm(dim=-1))
        out[name] = {"rel_err_median": float(e.median()), "rel_err_p99": float(torch.quantile(e, 0.99)),
                     "abs_norm_err_median": float(n_err.median()), "vs_shape_rel_err_median": float(e_t.median())}
    out["analytic_float64"] = {"vs_shape_rel_err_median": float(((g_ref - g_target).norm(dim=-1) / g_target.norm(dim=-1)).median())}
    return out


def time_field(name: str, device, P: int, reps: int, modes: list[str]) -> list[dict]:
    torch.manual_seed(0)
    field = FIELDS[name](DEFAULT_VOLUME).to(device)
    if isinstance(field, HashGridSDF):
        roughen(field)
    params = list(field.parameters())
    n_params = sum(p.numel() for p in params)
    x = points(P, device)
    rows = []
    for mode in modes:
        vg = torch.compile(field.value_and_gradient) if "compile" in mode else field.value_and_gradient

        def fwd():
            with torch.no_grad():
                return vg(x)

        def fwd_bwd():
            f, g = vg(x)
            loss = ((g.norm(dim=-1) - 1.0) ** 2).mean() + f.abs().mean() / field.scale
            return torch.autograd.grad(loss, params)

        t0 = time.perf_counter()
        fwd_bwd()
        sync(device)
        first_s = time.perf_counter() - t0  # kernel builds and compilation (cached across runs)
        run_fwd, run_fb = fwd, fwd_bwd
        if "graph" in mode:
            run_fwd, run_fb = graphed(fwd, device), graphed(fwd_bwd, device)
        peak_mb = None
        if device.type == "cuda":
            sync(device)
            base = torch.cuda.memory_allocated(device)
            torch.cuda.reset_peak_memory_stats(device)
            fwd_bwd()
            sync(device)
            peak_mb = (torch.cuda.max_memory_allocated(device) - base) / 2**20
        t_f = timeit(run_fwd, device, reps, warmup=2)
        t_fb = timeit(run_fb, device, reps, warmup=2)
        rows.append({"field": name, "mode": mode, "points": P, "params": n_params, "fwd_ms": t_f * 1e3,
                     "fwd_bwd_ms": t_fb * 1e3, "peak_mb": peak_mb, "first_call_s": first_s})
        print(f"  {name:20s} {mode:14s} fwd {t_f * 1e3:9.3f} ms   fwd+bwd {t_fb * 1e3:9.3f} ms"
              + (f"   peak {peak_mb:8.1f} MB" if peak_mb is not None else ""), flush=True)
    del field
    if device.type == "cuda":
        torch.cuda.empty_cache()
    return rows


def markdown(doc: dict) -> str:
    lines = [f"# Field benchmark ({doc['device_name']}, {doc['points']} points)", "",
             f"`{doc['command']}` on {doc['date']} (torch {doc['torch']}, warp {doc['warp']}).", "",
             "| field | mode | params | fwd ms | fwd+bwd ms | peak MB | first call s |", "|---|---|---:|---:|---:|---:|---:|"]
    for r in doc["rows"]:
        peak = f"{r['peak_mb']:.0f}" if r["peak_mb"] is not None else "-"
        lines.append(f"| {r['field']} | {r['mode']} | {r['params']:,} | {r['fwd_ms']:.3f} | {r['fwd_bwd_ms']:.3f} | {peak} | "
                     f"{r['first_call_s']:.1f} |")
    ratio = doc.get("warp_over_twin")
    if ratio:
        lines += ["", "Time with the torch-twin encoding / with the Warp encoding (fwd+bwd): "
                  + ", ".join(f"{m}: {v:.2f}x" for m, v in ratio.items())]
    acc = doc.get("accuracy")
    if acc:
        lines += ["", f"Gradient accuracy against the float64 analytic gradient of a field fitted to a bumpy sphere "
                  f"({acc['fit_steps']} steps, value MAE {acc['fit_mae_mm']:.3f} mm; {acc['points']} points within 5 mm of the "
                  f"surface, {acc['active_levels']} levels, finite-difference step {acc['fd_step_mm']:.3f} mm, median |grad| "
                  f"{acc['ref_grad_norm_median']:.3f}); last column: against the bumpy sphere's own gradient:", "",
                  "| gradient | median rel. error | p99 rel. error | median abs. error of norm | median rel. error vs shape |",
                  "|---|---:|---:|---:|---:|"]
        for k in ("analytic_float32", "finite_difference_float32", "finite_difference_float64"):
            a = acc[k]
            lines.append(f"| {k} | {a['rel_err_median']:.2e} | {a['rel_err_p99']:.2e} | {a['abs_norm_err_median']:.2e} | "
                         f"{a['vs_shape_rel_err_median']:.2e} |")
        lines.append(f"| analytic_float64 (reference) | 0 | 0 | 0 | {acc['analytic_float64']['vs_shape_rel_err_median']:.2e} |")
    lines += ["", "Correctness (max error relative to the largest value): " + json.dumps(doc["checks"], default=lambda v: f"{v:.1e}")]
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default=None, help="cpu | cuda (default: cuda when present)")
    ap.add_argument("--points", type=int, default=None, help="P (default 131072 on CUDA, 4096 on the CPU)")
    ap.add_argument("--repeats", type=int, default=None, help="timed calls per row (default 20 on CUDA, 3 on the CPU)")
    ap.add_argument("--fields", nargs="+", default=DEFAULT_FIELDS, choices=sorted(FIELDS))
    ap.add_argument("--compile", action="store_true", help="also time torch.compile'd value_and_gradient")
    ap.add_argument("--accuracy-points", type=int, default=2048)
    ap.add_argument("--fit-steps", type=int, default=150, help="regression steps of the field the accuracy is measured on")
    ap.add_argument("--out", default=str(REPO / "bench" / "results"))
    args = ap.parse_args(argv)
    device = torch.device(args.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    if device.type == "cpu":
        torch.set_flush_denormal(True)
    P = args.points or (131072 if device.type == "cuda" else 4096)
    reps = args.repeats or (20 if device.type == "cuda" else 3)
    modes = ["eager"] + (["compile"] if args.compile else [])
    if device.type == "cuda":
        modes += ["graph"] + (["compile+graph"] if args.compile else [])
    import warp

    name = torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor() or "cpu"
    print(f"device {name}, {P} points, fields {args.fields}, modes {modes}", flush=True)
    print("correctness ...", flush=True)
    checks = check_correctness(device, min(P, 16384))
    print("  " + json.dumps(checks, default=lambda v: f"{v:.1e}"), flush=True)
    print(f"gradient accuracy (float64 reference; fitting a field for {args.fit_steps} steps) ...", flush=True)
    accuracy = gradient_accuracy(args.accuracy_points, args.fit_steps, device)
    for k in ("analytic_float32", "finite_difference_float32", "finite_difference_float64"):
        print(f"  {k:26s} median rel. error {accuracy[k]['rel_err_median']:.2e}  p99 {accuracy[k]['rel_err_p99']:.2e}  "
              f"vs shape {accuracy[k]['vs_shape_rel_err_median']:.2e}", flush=True)
    print("timings ...", flush=True)
    rows = []
    # everything on a side stream: autograd's per-parameter nodes made by eager calls on the legacy stream
    # would make a later graph capture depend on it (the trainer steps on its own stream for the same reason)
    with torch.cuda.stream(torch.cuda.Stream(device)) if device.type == "cuda" else contextlib.nullcontext():
        for f in args.fields:
            rows += time_field(f, device, P, reps, modes)
    by = {(r["field"], r["mode"]): r for r in rows}
    ratio = {f"{grad} {m}": by[(f"hashgrid-torch-{grad}", m)]["fwd_bwd_ms"] / by[(f"hashgrid-warp-{grad}", m)]["fwd_bwd_ms"]
             for grad in ("analytic", "fd") for m in modes
             if (f"hashgrid-torch-{grad}", m) in by and (f"hashgrid-warp-{grad}", m) in by}
    doc = {"command": "python -m bench.field " + " ".join(argv if argv is not None else sys.argv[1:]),
           "date": datetime.date.today().isoformat(), "device": device.type, "device_name": name, "points": P,
           "repeats": reps, "torch": torch.__version__, "warp": warp.__version__, "checks": checks,
           "accuracy": accuracy, "rows": rows, "warp_over_twin": ratio}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"field-{device.type}.json").write_text(json.dumps(doc, indent=1))
    md = markdown(doc)
    (out / f"field-{device.type}.md").write_text(md)
    print()
    print(md)


if __name__ == "__main__":
    main()
