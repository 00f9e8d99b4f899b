"""The paper's experiments on the virtual scanner: Table 1, the loss ablation (Table 2), Fig. 7 and Fig. 8.

    python -m bench.paper_experiments all --out bench/results            # on a GPU machine
    python -m bench.paper_experiments table1 --preset tuned --iters 4000
    python -m bench.paper_experiments fig7 --ks 3,5,7,9 --iters 2000

- table1: ours (6 random patterns) on the six built-in scenes, next to the classical rows of
  bench/results/classical-cpu.json (GC(6), GC(7) with interpolation, CGC(6), CGC(7), H-PMP(6), N-PMP(6);
  the same rig, noise model and noise seed): MAE and the share of pixels above 1, 2 and 5 mm.
- ablation: the paper's Table 2 on one scene: L_rc; L_rc + L_reg; L_sc; L_sc + L_reg; all three.
- fig7: ours against Gray code decoding (gc-interp) of the same K most significant Gray code patterns,
  without and with their inverses (2K images), on one scene; the classical rows decode the very same
  simulated images (same pattern set and noise seed).
- fig8: batch against incremental training (start with 3 patterns, one more every `add_every` iterations)
  with the 9 random patterns (3 per scale), on one scene.

Each experiment runs its trainings through bench/train_variants.py (one process per run, `--parallel` at
a time) and writes <out>/<name>-<device>.json (every number), .md (the table, naming the device, the date
and any cut in scenes or iterations) and .png (a plot).
"""
from __future__ import annotations

import argparse
import datetime
import json
import sys
from pathlib import Path

import numpy as np
from bench.train_variants import run_variants

REPO = Path(__file__).resolve().parents[1]

SCENES = ("spheres", "torus", "boxes", "bunny", "vase", "steps")
CLASSICAL_ROWS = [("GC(6) interp", "GC(6)"), ("GC(7) interp", "GC(7)"), ("CGC(6): 3 GC + 3-step W/4", "CGC(6)"),
                  ("CGC(7): 4 GC + 3-step W/8", "CGC(7)"), ("H-PMP(6): 3-step W + 80 px", "H-PMP(6)"),
                  ("N-PMP(6): 3-step 48 + 70 px", "N-PMP(6)")]
ABLATION = [("L_rc", "lambda_sc=0,lambda_reg=0"), ("L_rc + L_reg", "lambda_sc=0,lambda_reg=0.1"),
            ("L_sc", "lambda_rc=0,lambda_sc=1,sc_start=0,lambda_reg=0"),
            ("L_sc + L_reg", "lambda_rc=0,lambda_sc=1,sc_start=0,lambda_reg=0.1"),
            ("L_rc + L_sc + L_reg", "lambda_sc=1,lambda_reg=0.1")]  # L_sc from iteration sc_start (1000), as in the paper


def device_name() -> str:
    import torch

    return torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu"


def slug(name: str) -> str:
    return "cuda" if name != "cpu" else "cpu"


def spec(name: str, *parts: str) -> str:
    return f"{name}:" + ",".join(p for p in parts if p)


def pct(x) -> str:
    return "n/a" if x is None or not np.isfinite(x) else f"{100 * x:.2f}%"


def num(x, fmt="{:.3f}") -> str:
    return "n/a" if x is None or not np.isfinite(x) else fmt.format(x)


def write(out: Path, stem: str, doc: dict, md: str, fig=None) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{stem}.json").write_text(json.dumps(doc, indent=1, default=float) + "\n")
    (out / f"{stem}.md").write_text(md + "\n")
    if fig is not None:
        fig.savefig(out / f"{stem}.png", dpi=110, bbox_inches="tight")
    print(md, flush=True)


def finish_log_plot(ax, xlabel: str, ylabel: str, title: str) -> None:
    """Log y axis, labels, legend and a title naming the device."""
    ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.legend()
    ax.set_title(f"{title} ({device_name()})", fontsize=9)


def plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as p

    return p


def iters_run(docs: dict, args):
    """The training iterations the runs used (the preset's unless --iters)."""
    return next(iter(docs.values()))["config"]["schedule"]["iters"] if docs else args.iters


def rig_of(args) -> str:
    extra = dict(kv.split("=", 1) for kv in args.extra.split(",") if "=" in kv)
    return extra.get("rig", "default")


def header(title: str, args, runs_note: str) -> str:
    return (f"# {title}\n\n{device_name()}, {datetime.date.today().isoformat()}; {rig_of(args)} rig, SimOptions() noise "
            f"(seed 0); preset `{args.preset}`, {runs_note}.\n")


# --- Table 1 --------------------------------------------------------------------------------------------
def table1(args, out: Path, work: Path) -> None:
    scenes = args.scenes.split(",") if args.scenes else list(SCENES)
    it = f",iters={args.iters}" if args.iters else ""
    specs = [spec(f"t1_{s}", f"scene={s}", f"preset={args.preset}{it}", args.extra) for s in scenes]
    docs = run_variants(specs, work / "table1", args.parallel)
    classical = json.loads(Path(args.classical).read_text())["per_scene"]
    rows = [(f"ours, 6 random ({args.preset})", {s: docs.get(f"t1_{s}", {}).get("metrics") for s in scenes})]
    rows += [(short, {s: classical[label].get(s) for s in scenes}) for label, short in CLASSICAL_ROWS if label in classical]
    iters = iters_run(docs, args)
    md = [header("Table 1: the six built-in scenes", args, f"{iters} iterations (+ the depth-search warm-up)"),
          "Classical rows: bench/results/classical-cpu.json (same rig, noise model and seed; decoded on the CPU).", "",
          "| method | " + " | ".join(scenes) + " | mean MAE | >1 mm | >2 mm | >5 mm |",
          "|---|" + "---|" * (len(scenes) + 4)]
    summary = {}
    for label, per in rows:
        ok = [per[s] for s in scenes if per.get(s)]
        mean = {k: float(np.mean([m[k] for m in ok])) if len(ok) == len(scenes) else float("nan")
                for k in ("mae", "over_1mm", "over_2mm", "over_5mm", "median", "completeness")}
        summary[label] = mean
        md.append(f"| {label} | " + " | ".join(num(per[s]["mae"]) if per.get(s) else "failed" for s in scenes)
                  + f" | {num(mean['mae'])} | {pct(mean['over_1mm'])} | {pct(mean['over_2mm'])} | {pct(mean['over_5mm'])} |")
    ours = summary[rows[0][0]]["mae"]
    for short in ("GC(7)", "GC(6)"):
        if short in summary:
            md.append(f"\nours / {short} mean MAE: {ours / summary[short]['mae']:.2f}x")
    p = plt()
    fig, ax = p.subplots(figsize=(9, 4))
    width = 0.8 / len(rows)
    for j, (label, per) in enumerate(rows):
        ax.bar(np.arange(len(scenes)) + j * width, [per[s]["mae"] if per.get(s) else np.nan for s in scenes], width, label=label)
    ax.set_xticks(np.arange(len(scenes)) + 0.4 - width / 2, scenes)
    ax.set_yscale("log")
    ax.set_ylabel("MAE (mm, log)")
    ax.legend(fontsize=7, ncol=2)
    ax.set_title(f"Table 1 on the virtual scanner ({device_name()})")
    write(out, f"table1-{slug(device_name())}", {"device": device_name(), "date": datetime.date.today().isoformat(),
          "preset": args.preset, "runs": docs, "classical": {short: classical.get(label) for label, short in CLASSICAL_ROWS},
          "summary": summary}, "\n".join(md), fig)


# --- Table 2: loss ablation -----------------------------------------------------------------------------
def ablation(args, out: Path, work: Path) -> None:
    it = f",iters={args.iters}" if args.iters else ""
    specs = [spec(f"ab{j}", f"scene={args.scene}", f"preset={args.preset}{it}", s, args.extra)
             for j, (_, s) in enumerate(ABLATION)]
    docs = run_variants(specs, work / "ablation", args.parallel)
    iters = iters_run(docs, args)
    md = [header(f"Table 2: loss ablation ({args.scene})", args, f"{iters} iterations"),
          "| losses | settings | MAE mm | median mm | >1 mm | >2 mm | >5 mm | complete |", "|---|---|---|---|---|---|---|---|"]
    for j, (label, s) in enumerate(ABLATION):
        m = docs.get(f"ab{j}", {}).get("metrics")
        md.append(f"| {label} | {s or 'preset'} | " + (" | ".join([num(m["mae"]), num(m["median"]), pct(m["over_1mm"]),
                  pct(m["over_2mm"]), pct(m["over_5mm"]), pct(m["completeness"])]) if m else "failed | | | | | ") + " |")
    p = plt()
    fig, ax = p.subplots(figsize=(7, 3.5))
    ax.bar([l for l, _ in ABLATION], [docs.get(f"ab{j}", {}).get("metrics", {}).get("mae", np.nan) for j in range(len(ABLATION))])
    ax.set_ylabel("MAE (mm)")
    ax.set_title(f"loss ablation, {args.scene} ({device_name()})")
    p.setp(ax.get_xticklabels(), fontsize=8)
    write(out, f"ablation-{slug(device_name())}", {"device": device_name(), "date": datetime.date.today().isoformat(),
          "scene": args.scene, "variants": dict(ABLATION), "runs": docs}, "\n".join(md), fig)


# --- Fig. 7: ours vs Gray code with the same patterns ----------------------------------------------------
def fig7(args, out: Path, work: Path) -> None:
    import torch

    from slwarp.decode import reconstruct_depth
    from slwarp.evaluation.metrics import depth_metrics
    from slwarp.sim.simulate import SimOptions, simulate_scene

    ks = [int(k) for k in args.ks.split(",")]
    kmax = max(ks)
    pats = f"gray{kmax}inv"
    it = f",iters={args.iters}" if args.iters else ""

    def frames(k, inv):
        sel = f"gc_col_b[0-{k - 1}]"
        return sel + (f";{sel}_inv" if inv else "")

    specs = [spec(f"f7_k{k}{'inv' if inv else ''}", f"scene={args.scene}", f"patterns={pats}", f"frames={frames(k, inv)}",
                  f"preset={args.preset}{it}", args.extra) for inv in (False, True) for k in ks]
    docs = run_variants(specs, work / "fig7", args.parallel)
    scan = simulate_scene(args.scene, pats, rig=rig_of(args), options=SimOptions(seed=0),
                          device="cuda:0" if torch.cuda.is_available() else "cpu")
    gc = {}
    for inv in (False, True):
        for k in ks:
            depth, _, _ = reconstruct_depth(scan, "gc-interp", frames=frames(k, inv).replace(";", ","))
            gc[f"k{k}{'inv' if inv else ''}"] = depth_metrics(depth, scan.gt_depth, scan.mask)
    iters = iters_run(docs, args)
    md = [header(f"Fig. 7: ours vs Gray code with the same patterns ({args.scene})", args, f"{iters} iterations"),
          "K most significant column Gray code patterns; 'with inverses' uses 2K images. MAE in mm (>5 mm share).", "",
          "| K | ours | GC interp | ours, with inverses | GC interp, with inverses |", "|---|---|---|---|---|"]
    series = {name: [] for name in ("ours", "gc", "ours_inv", "gc_inv")}
    for k in ks:
        cells = []
        for inv in (False, True):
            key = f"k{k}{'inv' if inv else ''}"
            m_o = docs.get(f"f7_{key}", {}).get("metrics")
            m_g = gc[key]
            series["ours_inv" if inv else "ours"].append(m_o["mae"] if m_o else np.nan)
            series["gc_inv" if inv else "gc"].append(m_g["mae"])
            cells += [f"{num(m_o['mae'])} ({pct(m_o['over_5mm'])})" if m_o else "failed",
                      f"{num(m_g['mae'])} ({pct(m_g['over_5mm'])})"]
        md.append(f"| {k} | " + " | ".join(cells) + " |")
    p = plt()
    fig, ax = p.subplots(figsize=(6, 4))
    for name, style, label in (("ours", "o-", "ours"), ("gc", "s-", "GC interp"), ("ours_inv", "o--", "ours, with inverses"),
                               ("gc_inv", "s--", "GC interp, with inverses")):
        ax.plot(ks, series[name], style, label=label)
    finish_log_plot(ax, "Gray code patterns K", "MAE (mm, log)", f"Fig. 7 on the virtual scanner, {args.scene}")
    write(out, f"fig7-{slug(device_name())}", {"device": device_name(), "date": datetime.date.today().isoformat(),
          "scene": args.scene, "ks": ks, "runs": docs, "gc_interp": gc}, "\n".join(md), fig)


# --- Fig. 8: batch vs incremental ----------------------------------------------------------------------
def fig8(args, out: Path, work: Path) -> None:
    it = f",iters={args.iters}" if args.iters else ""
    base = [f"scene={args.scene}", "patterns=random9", f"preset={args.preset}{it}", args.extra]
    specs = [spec("f8_batch", *base), spec("f8_incremental", *base, f"incremental=true,start_frames=3,add_every={args.add_every}")]
    docs = run_variants(specs, work / "fig8", args.parallel)
    iters = iters_run(docs, args)
    md = [header(f"Fig. 8: batch vs incremental training, 9 random patterns ({args.scene})", args, f"{iters} iterations"),
          f"Incremental: 3 patterns (the 20 px scale) at the start, one more every {args.add_every} iterations.", "",
          "| training | MAE mm | median mm | >1 mm | >5 mm | complete | train s |", "|---|---|---|---|---|---|---|"]
    p = plt()
    fig, ax = p.subplots(figsize=(6.5, 4))
    for name in ("f8_batch", "f8_incremental"):
        d = docs.get(name)
        if not d:
            md.append(f"| {name[3:]} | failed | | | | | |")
            continue
        m = d["metrics"]
        md.append(f"| {name[3:]} | {num(m['mae'])} | {num(m['median'])} | {pct(m['over_1mm'])} | {pct(m['over_5mm'])} | "
                  f"{pct(m['completeness'])} | {d['timings']['train_s']:.1f} |")
        hist = work / "fig8" / name / "history.json"
        if hist.is_file():
            h = json.loads(hist.read_text())
            ax.plot(h["iters"], h["color"], label=f"{name[3:]}: rendered-colour loss")
            d["history"] = {k: h[k] for k in ("iters", "color", "frames") if k in h}
    finish_log_plot(ax, "iteration", "L_rc", f"Fig. 8 on the virtual scanner, {args.scene}")
    write(out, f"fig8-{slug(device_name())}", {"device": device_name(), "date": datetime.date.today().isoformat(),
          "scene": args.scene, "add_every": args.add_every, "runs": docs}, "\n".join(md), fig)


EXPERIMENTS = {"table1": table1, "ablation": ablation, "fig7": fig7, "fig8": fig8}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("experiments", help="comma-separated: table1, ablation, fig7, fig8, or all")
    ap.add_argument("--out", default=str(REPO / "bench" / "results"))
    ap.add_argument("--work", default=None, help="per-run folders and logs (default: <out>/runs)")
    ap.add_argument("--preset", default="tuned")
    ap.add_argument("--iters", type=int, default=None, help="training iterations (default: the preset's)")
    ap.add_argument("--scenes", default=None, help="table1: comma-separated scenes (default: all six)")
    ap.add_argument("--scene", default="bunny", help="ablation, fig7, fig8: the scene")
    ap.add_argument("--ks", default="3,4,5,6,7,8,9", help="fig7: Gray code pattern counts")
    ap.add_argument("--add-every", type=int, default=500, help="fig8: iterations between added patterns")
    ap.add_argument("--extra", default="", help="extra TrainConfig overrides for every run, key=value,...")
    ap.add_argument("--parallel", type=int, default=4)
    ap.add_argument("--classical", default=str(REPO / "bench/results/classical-cpu.json"))
    args = ap.parse_args(argv)
    names = list(EXPERIMENTS) if args.experiments == "all" else args.experiments.split(",")
    unknown = [n for n in names if n not in EXPERIMENTS]
    if unknown:
        ap.error(f"unknown experiment(s) {unknown}; choose from {', '.join(EXPERIMENTS)} or all")
    out = Path(args.out)
    work = Path(args.work) if args.work else out / "runs"
    for n in names:
        EXPERIMENTS[n](args, out, work)
    return 0


if __name__ == "__main__":
    sys.exit(main())
