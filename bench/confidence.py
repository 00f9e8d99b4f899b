"""Does confidence predict the error? Sparsification curves and AUSE of every confidence map, neural and
classical, on the virtual scanner.

For each scene: one simulated scan (noise on) with the paper's 6 random patterns and the classical sets; the
neural SDF trained on the 6 random patterns (checkpoints cached in --work, so a second run only re-measures);
its depth extracted with no confidence filter (min_confidence 0), so every confidence kind ranks the same
pixels; the classical baselines decoded from their own frames. For every (method, confidence) pair: the
sparsification curve (MAE of the most confident x% of the compared pixels, x = 100 down to 50), the oracle's
(pixels sorted by true error) and the AUSE between them (`slwarp.evaluation.metrics.confidence_metrics`), and
the MAE, >5 mm share and completeness left after each kind's filter at the share of pixels the photometric
check (min_confidence 0.6 on photometric) keeps.

    python -m bench.confidence --work /tmp/confw   # small rig, cpu preset: neural on bunny, boxes; classical on six scenes
    python -m bench.confidence --scenes bunny,boxes --preset tiny --out /tmp/conf

Writes <out>.json (every number and curve), <out>.md (the tables) and <out>.png (the curves).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import sys
import time
from pathlib import Path

import numpy as np

from bench.classical_baselines import cpu_name

REPO = Path(__file__).resolve().parents[1]
DATE = "2026-11-22"
PATTERNS = "random6+gt+cgc7+hpmp6+npmp6"  # the neural method uses the random ones; gt holds GC(7) with inverses
BASELINES = [  # (label, method, frames)
    ("GC(7) interp", "gc-interp", "gray:col:bit=0-6:noinv"),
    ("GC(6) interp", "gc-interp", "gray:col:bit=0-5:noinv"),
    ("CGC(7)", "cgc", "gray:col:bit=0-3:noinv,phase:col:period={s8}"),
    ("H-PMP(6)", "hpmp", "phase:col:period={s},phase:col:period=80"),
    ("N-PMP(6)", "npmp", "phase:col:period=48,phase:col:period=70"),
]
PHOTOMETRIC_CHECK = 0.6  # the photometric check of old: min_confidence 0.6 on the photometric kind
# geometric means of terms, measured beside the library's kinds (gm:a+b rows)
PRODUCTS = [("photometric", "agreement"), ("photometric", "uniqueness"), ("photometric", "peak", "uniqueness")]


def trained(scan, config, work: Path, progress: bool):
    """A Trainer on the scan's random frames, trained (or resumed from work/train/checkpoint.pt)."""
    from slwarp.neural.training import Trainer

    resume = (work / "train" / "checkpoint.pt").is_file()
    trainer = Trainer(scan.select("random"), config, out_dir=work / "train", resume=resume, progress=progress,
                      progress_interval_s=30.0)
    trainer.train()
    return trainer


def neural_maps(trainer, kinds) -> tuple[np.ndarray, dict, float]:
    """(depth with no confidence filter, {kind: confidence}, seconds for the confidence maps)."""
    from slwarp.neural.extraction import ModelInputs, TrainedField, extract_depth
    from slwarp.neural.extraction.confidence import confidence_terms

    t = trainer
    keep = t.cfg
    t.cfg = keep.with_options(min_confidence=0.0, confidence="photometric")
    try:
        depth = extract_depth(t, t.renderer.valid_map.cpu().numpy()).depth
    finally:
        t.cfg = keep
    t0 = time.perf_counter()
    terms = confidence_terms(ModelInputs.from_trainer(t), depth, kinds, TrainedField.from_trainer(t))
    return depth, terms, time.perf_counter() - t0


def classical_variants(dec, depth) -> dict[str, np.ndarray]:
    """{variant: confidence} of a classical decoding: 'default' (`decoding_confidence`: certainty x swing) and
    its two factors alone, 'swing' and (Gray code methods) 'certainty'."""
    from slwarp.decode.confidence import decoding_confidence, signal_swing

    ex = dec.extra
    invalid = ~(dec.valid & np.isfinite(depth))
    out = {"default": decoding_confidence(dec, depth)}
    swings = [np.asarray(ex[k], np.float64) for k in ("amplitude_col", "amplitude_row", "amplitude", "modulation")
              if k in ex]
    out["swing"] = np.where(invalid, np.nan, signal_swing(np.minimum.reduce(swings)))
    certainties = [np.asarray(ex[k], np.float64) for k in ("certainty_col", "certainty_row", "certainty") if k in ex]
    if certainties:
        out["certainty"] = np.where(invalid, np.nan, np.fmin.reduce(certainties))
    return out


def rate(depth, conf, scan, share: float | None) -> dict:
    """confidence_metrics of one map, and the MAE of its most confident `share` of the compared pixels."""
    from slwarp.evaluation.metrics import confidence_metrics, depth_metrics

    cm = confidence_metrics(depth, conf, scan.gt_depth, scan.mask)
    row = {k: cm[k] for k in ("mae_top90", "mae_top75", "ause", "ause_random")}
    row["mae"] = depth_metrics(depth, scan.gt_depth, scan.mask)["mae"]
    if share is not None:
        row["mae_at_check_share"] = confidence_metrics(depth, conf, scan.gt_depth, scan.mask,
                                                       fractions=[share])["sparsification"]["curve"][0]
    row["sparsification"] = cm["sparsification"]
    return row


def run_scene(scene: str, args, results: dict) -> None:
    from slwarp.decode import reconstruct_depth
    from slwarp.evaluation.metrics import depth_metrics
    from slwarp.neural.config import preset
    from slwarp.sim.simulate import SimOptions, simulate_scene

    torch_device = "cpu"
    scan = simulate_scene(scene, PATTERNS, args.rig, SimOptions(seed=0), device=torch_device)
    res = results.setdefault(scene, {})
    if scene in args.neural_scenes:
        from slwarp.neural.extraction.confidence import CONFIDENCE_KINDS, combine

        trainer = trained(scan, preset(args.preset, device=torch_device), Path(args.work) / scene, args.progress)
        depth, terms, conf_s = neural_maps(trainer, CONFIDENCE_KINDS)
        for pair in PRODUCTS:  # combinations beyond the library's 'combined', measured here only
            terms["gm:" + "+".join(pair)] = combine(terms, pair)
        np.savez_compressed(Path(args.work) / scene / "confidence-maps.npz", depth=depth, gt=scan.gt_depth,
                            mask=scan.mask, **{k.replace(":", "_").replace("+", "_"): v for k, v in terms.items()})
        compared = np.isfinite(depth) & np.isfinite(scan.gt_depth) & (scan.gt_depth > 0) & scan.mask
        check = (terms["photometric"] >= PHOTOMETRIC_CHECK)[compared]
        share = float(check.mean()) if check.size else None
        kept = np.where(terms["photometric"] >= PHOTOMETRIC_CHECK, depth, np.nan)
        res["neural"] = {"confidence_s": conf_s, "check_share": share,
                         "unfiltered": depth_metrics(depth, scan.gt_depth, scan.mask),
                         "photometric_check": depth_metrics(kept, scan.gt_depth, scan.mask),
                         "kinds": {k: rate(depth, v, scan, share) for k, v in terms.items()}}
        print(f"{scene} neural: check keeps {share:.3f}; confidence maps {conf_s:.1f} s", flush=True)
    P = scan.projector
    res["classical"] = {}
    for label, method, frames in BASELINES:
        frames = frames.format(s=f"{P.width:g}", s8=f"{P.width / 8:g}")
        depth, _, dec = reconstruct_depth(scan, method, frames=frames)
        res["classical"][label] = {k: rate(depth, v, scan, None) for k, v in classical_variants(dec, depth).items()}
    print(f"{scene} classical done", flush=True)


def markdown(results: dict, meta: dict) -> str:
    lines = [f"# Confidence: does ranking by confidence predict the error? ({meta['date']}, {meta['cpu']}, "
             f"torch {meta['device']})", "",
             f"Command: `{meta['command']}`. Small rig, {meta['preset']} preset, one simulated scan per scene "
             "(noise on, seed 0). Over the compared pixels (scan mask, finite depth): MAE of the 90% / 75% most "
             "confident pixels, AUSE (mean excess MAE of the most confident x% over the oracle's, x = 100..50; 0 = "
             "perfect ranking), AUSE random (a confidence that ranks nothing). Neural depth is extracted with no "
             "confidence filter, so every kind ranks the same pixels; 'MAE at check share': the MAE of each kind's "
             "most confident pixels in the number the photometric check (photometric >= 0.6, the default) keeps.", ""]
    for scene, res in results.items():
        if "neural" in res:
            n = res["neural"]
            lines += [f"## {scene}: neural SDF (6 random patterns)", "",
                      f"Unfiltered MAE {n['unfiltered']['mae']:.3f} mm, completeness {n['unfiltered']['completeness']:.3f}; "
                      f"the photometric check keeps {n['check_share']:.1%} of the compared pixels: MAE "
                      f"{n['photometric_check']['mae']:.3f} mm, >5 mm {n['photometric_check']['over_5mm']:.4f}, "
                      f"completeness {n['photometric_check']['completeness']:.3f}. Confidence maps: {n['confidence_s']:.1f} s.", "",
                      "| confidence | MAE top 90% | MAE top 75% | MAE at check share | AUSE | AUSE random |",
                      "|---|---|---|---|---|---|"]
            for k, r in n["kinds"].items():
                lines.append(f"| {k} | {r['mae_top90']:.3f} | {r['mae_top75']:.3f} | {r['mae_at_check_share']:.3f} | "
                             f"{r['ause']:.3f} | {r['ause_random']:.3f} |")
            lines.append("")
        lines += [f"## {scene}: classical decoders", "",
                  "| method | confidence | MAE | MAE top 90% | MAE top 75% | AUSE | AUSE random |",
                  "|---|---|---|---|---|---|---|"]
        for label, variants in res["classical"].items():
            for k, r in variants.items():
                lines.append(f"| {label} | {k} | {r['mae']:.3f} | {r['mae_top90']:.3f} | {r['mae_top75']:.3f} | "
                             f"{r['ause']:.3f} | {r['ause_random']:.3f} |")
        lines.append("")
    return "\n".join(lines)


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(results)
    fig, axes = plt.subplots(2, len(scenes), figsize=(4.2 * len(scenes), 7.5), squeeze=False)
    for j, scene in enumerate(scenes):
        res = results[scene]
        ax = axes[0, j]
        if "neural" in res:
            for k, r in res["neural"]["kinds"].items():
                sp = r["sparsification"]
                ax.plot(np.multiply(sp["fractions"], 100), sp["curve"], label=k)
            ax.plot(np.multiply(sp["fractions"], 100), sp["oracle"], "k--", label="oracle")
            ax.set_title(f"{scene}: neural SDF")
            ax.legend(fontsize=7)
        else:
            ax.set_axis_off()
        ax = axes[1, j]
        for i, (label, variants) in enumerate(res["classical"].items()):
            sp = variants["default"]["sparsification"]
            line, = ax.plot(np.multiply(sp["fractions"], 100), sp["curve"], label=label)
            ax.plot(np.multiply(sp["fractions"], 100), sp["oracle"], "--", color=line.get_color(), lw=0.8)
        ax.set_title(f"{scene}: classical (dashed: oracle)")
        ax.set_yscale("log")
        ax.legend(fontsize=7)
        for ax in axes[:, j]:
            ax.set_xlabel("most confident pixels kept (%)")
            ax.set_ylabel("MAE (mm)")
            ax.invert_xaxis()
    fig.tight_layout()
    fig.savefig(path, dpi=72)
    plt.close(fig)


def dump_json(doc) -> str:
    """The results as JSON, numbers to 5 significant digits and each curve on one line (the file stays small)."""
    def compact(x):
        if isinstance(x, dict):
            return {k: compact(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [compact(v) for v in x]
        if isinstance(x, (float, np.floating)):
            return float(f"{float(x):.5g}")
        return x

    text = json.dumps(compact(doc), indent=1)
    # join the lines of number lists (the curves) into one line each
    return re.sub(r"\[\s*([-0-9.eE+,\sNaInfity]+?)\s*\]", lambda m: "[" + ", ".join(m.group(1).split()).replace(",,", ",") + "]",
                  text) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", default="bunny,boxes,spheres,torus,vase,steps", help="scenes for the classical decoders")
    p.add_argument("--neural-scenes", default="bunny,boxes", help="scenes (among --scenes) the neural SDF is trained on")
    p.add_argument("--rig", default="small")
    p.add_argument("--preset", default="cpu")
    p.add_argument("--work", default=str(REPO / "out" / "confidence"), help="checkpoints (cached between runs)")
    p.add_argument("--out", default=str(REPO / "bench" / "results" / "confidence-cpu"))
    p.add_argument("--progress", action="store_true")
    args = p.parse_args(argv)
    args.neural_scenes = [s for s in args.neural_scenes.split(",") if s]
    import torch

    t0 = time.perf_counter()
    results = {}
    for scene in args.scenes.split(","):
        run_scene(scene, args, results)
    meta = {"date": DATE, "cpu": cpu_name(), "device": "cpu", "torch": torch.__version__, "preset": args.preset,
            "rig": args.rig, "threads": os.environ.get("OMP_NUM_THREADS"), "wall_s": time.perf_counter() - t0,
            "command": "python -m bench.confidence " + " ".join(sys.argv[1:] if argv is None else argv)}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(dump_json({"meta": meta, "results": results}))
    md = markdown(results, meta)
    out.with_suffix(".md").write_text(md + "\n")
    plot(results, out.with_suffix(".png"))
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
