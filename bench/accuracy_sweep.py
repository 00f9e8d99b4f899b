"""Accuracy sweep: the neural SDF's presets against Gray code on every rig geometry and scene of the virtual
scanner, with the paper's 6 random patterns.

One simulated scan per rig and scene (noise on, `SimOptions(seed=SEED)`), holding the paper's 6 random
patterns and the 7-bit Gray code along the projector axis that carries depth on that rig (columns on
`default`, `oblique` and `rolled`, rows on `vertical`). The neural presets train on the 6 random patterns
only (`--frames 'rand*'`), or with `--neural-frames gray7` on the 7 Gray code images GC(7) decodes (what the real
captures give: bench.real_captures); GC(7)-interp and GC(6)-interp decode 7 and 6 of the Gray code images (no
inverses), triangulated as `slwarp decode` does by default. Metrics over the scan's GT mask: MAE, RMSE, median,
shares above 1, 2 and 5 mm, completeness; means over scenes per rig, as papers report, and the targets
(mean MAE <= 0.5x GC(7) and <= 0.3x GC(6), completeness within 1 point of GC(7), >5 mm share and RMSE no higher).

Runs are spread over every GPU, K processes per GPU (`--workers-per-gpu`), or K processes on the CPU. Each
finished run is kept in --state (one JSON per run), so an interrupted sweep continues where it stopped.

    python -m bench.accuracy_sweep --presets accurate,tuned               # GPU: every rig and scene
    python -m bench.accuracy_sweep --small --presets tiny --scenes bunny,steps --rigs default,rolled \\
        --workers 2 --out /tmp/sweep                                      # CPU smoke run
    python -m bench.accuracy_sweep --presets tuned --also-extract refine_range=0,search_doubt=true
                                          # extraction variants on the same trained fields (one training each)
    python -m bench.accuracy_sweep --report --device-name "NVIDIA H200" --presets tuned --state merged/ \\
        --stem accuracy-cuda-merged                                       # tables from runs made elsewhere

Writes <out>/accuracy-<cpu|cuda>.json and .md (the tables) and prints the markdown.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import signal
import sys
import time
import traceback
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
CLASSICAL = (("GC(7) interp", "bit=0-6"), ("GC(6) interp", "bit=0-5"))
KEYS = ("mae", "rmse", "median", "over_1mm", "over_2mm", "over_5mm", "completeness", "mae_within_5mm", "outlier_mae")
LOST = ("unlit", "no_surface", "out_of_range", "flying_pixel", "low_confidence", "search_doubt")  # the `lost` keys of a neural run

_DEVICE = None  # this worker process's device, set by _init_worker
_KEEP = None  # the folder for error maps (--keep), set by _init_worker


def _init_worker(devices, threads: int, keep: str | None = None) -> None:
    global _DEVICE, _KEEP
    import torch

    _DEVICE = devices.get()
    _KEEP = keep
    torch.set_num_threads(threads)
    # a worker runs several presets, whose ray counts give the compiled field other shapes: at dynamo's default
    # limit of 8 compiled versions a worker ran its later fields uncompiled (slower, the same results)
    import torch._dynamo

    torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, 64)
    if _DEVICE.startswith("cuda"):
        torch.cuda.set_device(torch.device(_DEVICE))


def _scan(rig: str, scene: str, seed: int, designs: str | None = None, camera: str = "linear",
          device: str | None = None):
    """(scan, depth axis): random6 + gray7 along the depth axis, and with `designs` (a folder of
    <rig>/design<K>/patterns.yaml, bench.designed_patterns) every design of the rig after them; seen through the
    named camera model (slwarp.sim.simulate.CAMERA_MODELS); simulated on `device` (default: the worker's)."""
    from slwarp.decode import choose_plane_axis
    from slwarp.sim.rigs import make_rig
    from slwarp.sim.simulate import camera_model, simulate_scene

    _, projector = make_rig(rig)
    axis = choose_plane_axis(projector)
    gray = "gray7" if axis == "col" else "gray7_row"
    spec = f"random6+{gray}" + "".join(f"+{p}" for p in rig_designs(designs, rig))
    device = _DEVICE if device is None else device
    sim_device = device if device and device.startswith("cuda") else None
    return simulate_scene(scene, spec, rig, camera_model(camera, seed=seed), device=sim_device), axis


def rig_designs(designs: str | None, rig: str) -> list[str]:
    """The pattern-set files <designs>/<rig>/design<K>/patterns.yaml, by K."""
    if not designs:
        return []
    found = sorted(Path(designs, rig).glob("design*/patterns.yaml"), key=lambda p: int(p.parent.name[6:] or 0))
    return [str(p) for p in found]


def error_split(depth: np.ndarray, scan) -> dict:
    """Where a mean error comes from: mae_within_5mm (MAE of the compared pixels off by <= 5 mm) and outlier_mae
    (the part of the MAE, mm, that the pixels off by > 5 mm contribute: MAE = inliers' share + outlier_mae)."""
    ref = np.isfinite(scan.gt_depth) & (scan.gt_depth > 0) & scan.mask & np.isfinite(depth)
    err = np.abs(depth[ref] - scan.gt_depth[ref])
    if err.size == 0:
        return {"mae_within_5mm": float("nan"), "outlier_mae": float("nan")}
    small = err <= 5.0
    return {"mae_within_5mm": float(err[small].mean()) if small.any() else float("nan"),
            "outlier_mae": float(err[~small].sum() / err.size)}


def lost_pixels(mask: np.ndarray, valid: np.ndarray, timings: dict) -> dict:
    """Where a run's missing pixels went, as shares of the GT mask: unlit (outside the decoders' valid map) and
    each extraction stage's drops (`extract_depth` timings["dropped"])."""
    n_mask = max(int(mask.sum()), 1)
    return {"unlit": float((mask & ~valid).sum() / n_mask),
            **{k: v / n_mask for k, v in timings.get("dropped", {}).items()}}


def refine_facts(timings: dict) -> dict:
    """What an extraction decided, for study: the model's misfit, whether it refined, the held-out check's decision
    and per-fold residuals when it ran, the pixels the repair's growth changed, the edge pixels given back and the
    lens halo's share the pattern model used (fitted or given), and where the field lost the surface, what the run
    (surface_lost) or its first training (lost_surface_retry, reconstruct.lost_surface) found, the shares that rule
    read (surface_shares) and whether the training step ran as a CUDA graph (graph_captured)."""
    return {k: timings[k] for k in ("refine_misfit", "refined", "refine_check", "repair_grown", "edge_readmitted",
                                    "pattern_halo", "surface_lost", "lost_surface_retry", "surface_shares",
                                    "graph_captured")
            if timings.get(k) is not None}


def keep_error_map(job: dict, label: str, depth: np.ndarray, scan, fate: np.ndarray | None = None) -> None:
    """Save the absolute error map of one run as <--keep>/<job key>__<method>.png (0-5 mm colour scale) and, for
    study without the device, <...>.npz: "error" (depth - gt in mm as float16, NaN outside the GT mask or without
    depth) and for the neural runs "fate" (uint8, slwarp.neural.extraction.PIXEL_FATES, named in "fates")."""
    keep = _KEEP
    if not keep:
        return
    from slwarp.evaluation.viz import save_error_map

    Path(keep).mkdir(parents=True, exist_ok=True)
    name = f"{job_key(job)}__{label}".replace("/", "_").replace(":", "_").replace("=", "-").replace(" ", "")
    name = name.replace("(", "").replace(")", "")
    save_error_map(Path(keep) / f"{name}.png", depth, np.where(scan.mask, scan.gt_depth, np.nan),
                   title=f"{label}: {job['scene']} on {job['rig']}")
    arrays = {"error": np.where(scan.mask, depth - scan.gt_depth, np.nan).astype(np.float16)}
    if fate is not None:
        from slwarp.neural.extraction import PIXEL_FATES

        arrays.update(fate=fate.astype(np.uint8), fates=np.array(PIXEL_FATES))
    np.savez_compressed(Path(keep) / f"{name}.npz", **arrays)


def _interrupt(signum, frame):
    """SIGTERM handled as Ctrl-C: the sweep stops its workers and keeps what finished (`main`)."""
    raise KeyboardInterrupt


def _stop_workers(pool: ProcessPoolExecutor) -> None:
    """Terminate `pool`'s worker processes now and drop the runs not started. Why: shutting a pool down waits for
    every running run (minutes each), and a sweep stopped without it left its workers training on, two of them
    slowing the next command on a 2-core machine threefold (`slwarp demo`: 133.8 -> 441.7 s)."""
    for proc in list((getattr(pool, "_processes", None) or {}).values()):  # the executor's only handle on them
        proc.terminate()
    pool.shutdown(wait=False, cancel_futures=True)


def run_job(job: dict) -> dict:
    """One run: {"kind": "classical" | "neural", rig, scene, seed, preset, overrides} -> metrics per method
    (and the error maps in the --keep folder when one is given)."""
    t0 = time.perf_counter()
    try:
        scan, axis = _scan(job["rig"], job["scene"], job["seed"], job.get("designs"), job.get("camera", "linear"))
        out = {"job": job, "device": _DEVICE, "axis": axis, "methods": {}}
        if job["kind"] == "classical":
            from slwarp.decode import reconstruct_depth
            from slwarp.evaluation.metrics import depth_metrics

            for label, bits in CLASSICAL:
                depth, _, dec = reconstruct_depth(scan, "gc-interp", frames=f"gray:{axis}:{bits}:noinv")
                m = depth_metrics(depth, scan.gt_depth, scan.mask)
                m["frames"] = len(dec.frames)
                m.update(error_split(depth, scan))
                out["methods"][label] = m
                keep_error_map(job, label, depth, scan)
        else:
            from slwarp.evaluation.metrics import depth_metrics
            from slwarp.neural.config import preset
            from slwarp.neural.extraction import extract_depth
            from slwarp.neural.reconstruct import reconstruct

            cfg = preset(job["preset"], device=_DEVICE, **job["overrides"])
            rec = reconstruct(scan.select(neural_frames(job, axis)), cfg, progress=False)
            m = dict(rec.metrics)
            m.update(error_split(rec.depth, scan))
            keep_error_map(job, method_label(job), rec.depth, scan, rec.fate)
            m.update(train_s=rec.timings.get("train_s"), total_s=rec.timings.get("total_s"),
                     iterations=rec.timings.get("iterations"), extract_s=rec.timings.get("total_s", 0.0)
                     - rec.timings.get("train_s", 0.0) - rec.timings.get("setup_s", 0.0))
            # where the missing pixels went: share of the GT mask unlit (outside the decoders' valid map) and
            # dropped by each extraction stage
            valid = rec.trainer.renderer.valid_map.cpu().numpy()
            m["lost"] = lost_pixels(scan.mask, valid, rec.timings)
            m.update(refine_facts(rec.timings))
            m["search_window_step"] = (rec.trainer.search_info or {}).get("window_step")  # a designed set's, or 1
            out["methods"][method_label(job)] = m
            # the same trained field extracted again with other extraction options (--also-extract)
            trainer = rec.trainer
            for variant in job.get("also_extract", []):
                trainer.cfg = cfg.with_options(**parse_overrides(variant.replace(":", ",")))
                t1 = time.perf_counter()
                depth, _, _, ext_t, fate = extract_depth(trainer, valid)
                label = f"{method_label(job)}+{variant}"
                m = {**depth_metrics(depth, scan.gt_depth, scan.mask), **error_split(depth, scan),
                     "train_s": rec.timings.get("train_s"), "extract_s": time.perf_counter() - t1,
                     "lost": lost_pixels(scan.mask, valid, ext_t)}
                m.update(refine_facts(ext_t))
                keep_error_map(job, label, depth, scan, fate)
                out["methods"][label] = m
        out["wall_s"] = time.perf_counter() - t0
        return out
    except Exception as e:  # noqa: BLE001 - one failed run is reported, the sweep goes on
        return {"job": job, "device": _DEVICE, "error": f"{type(e).__name__}: {e}", "traceback": traceback.format_exc(),
                "wall_s": time.perf_counter() - t0}


def neural_frames(job: dict, axis: str) -> str:
    """The frame selector a neural run trains on: the 6 random patterns, (job["frames"] == "gray7") the 7 most
    significant Gray code images along the depth axis, no inverses: what the real captures give (bench.real_captures),
    or ("design<K>") the rig's designed set of K patterns."""
    frames = job.get("frames") or "random6"
    if frames == "gray7":
        return f"gray:{axis}:bit=0-6:noinv"
    if frames.startswith("design"):
        return f"designed:count={int(frames[6:])}"
    return "rand*"


def method_label(job: dict) -> str:
    """A neural run's name in the tables: the preset label, and the frames when a sweep trains on several sets."""
    return job.get("tag") or job["label"]


def job_key(job: dict) -> str:
    name = job["label"] if job["kind"] == "neural" else "classical"
    frames = f"__{job['frames']}" if job.get("frames") else ""
    camera = f"__{job['camera']}" if job.get("camera", "linear") != "linear" else ""
    return (f"{name}{frames}{camera}__{job['rig']}__{job['scene']}__s{job['seed']}").replace("/", "_").replace(":", "_") \
        .replace("=", "-")


def _camera_prose(camera: str) -> str:
    """The camera model in the header's prose (nothing for the linear scanner of the earlier tables)."""
    if camera == "linear":
        return ""
    from slwarp.sim.simulate import CAMERA_MODELS

    return f" through the `{camera}` camera model ({', '.join(f'{k} {v}' for k, v in CAMERA_MODELS[camera].items())})"


def _without_note(argv: list[str]) -> list[str]:
    """The command's arguments less --note and its text (the header prints the note once, as prose)."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a == "--note":
            skip = True
        elif not a.startswith("--note="):
            out.append(a)
    return out


def parse_overrides(text: str | None) -> dict:
    """'iters=200,rays=512,compile=false' -> {"iters": 200, "rays": 512, "compile": False} (numbers and
    true/false parsed, the rest kept as text)."""
    out = {}
    for item in filter(None, (text or "").split(",")):
        k, _, v = item.partition("=")
        if v.lower() in ("true", "false"):
            out[k.strip()] = v.lower() == "true"
            continue
        for cast in (int, float):
            try:
                v = cast(v)
                break
            except ValueError:
                pass
        out[k.strip()] = v
    return out


def summarise(results: list[dict], rigs: list[str], scenes: list[str], labels: list[str]) -> dict:
    """{rig: {label: {"per_scene": {scene: metrics}, "mean": {...}}}} and the targets per rig and preset."""
    table: dict = {r: {} for r in rigs}
    for res in results:
        if "error" in res:
            continue
        r, s = res["job"]["rig"], res["job"]["scene"]
        for label, m in res["methods"].items():
            table[r].setdefault(label, {"per_scene": {}})["per_scene"][s] = m
    for r in rigs:
        for label, d in table[r].items():
            done = [s for s in scenes if s in d["per_scene"]]
            d["scenes"] = done
            if len(done) == len(scenes):
                d["mean"] = {k: float(np.mean([d["per_scene"][s].get(k, np.nan) for s in scenes])) for k in KEYS}
                for k in ("train_s", "total_s"):
                    vals = [d["per_scene"][s].get(k) for s in scenes]
                    if all(v is not None for v in vals):
                        d["mean"][k] = float(np.mean(vals))
        g7, g6 = (table[r].get(lab, {}).get("mean") for lab, _ in CLASSICAL)
        for label in labels:
            ours = table[r].get(label, {}).get("mean")
            if ours and g7 and g6:
                table[r][label]["targets"] = {
                    "mae_over_gc7": ours["mae"] / g7["mae"], "mae_over_gc6": ours["mae"] / g6["mae"],
                    "completeness_minus_gc7": ours["completeness"] - g7["completeness"],
                    "over_5mm_minus_gc7": ours["over_5mm"] - g7["over_5mm"],
                    "rmse_minus_gc7": ours["rmse"] - g7["rmse"]}
                t = table[r][label]["targets"]
                # a sweep stored before RMSE was recorded has NaN there: judged on the other four
                rmse_ok = not t["rmse_minus_gc7"] > 0
                t["met"] = bool(t["mae_over_gc7"] <= 0.5 and t["mae_over_gc6"] <= 0.3
                                and t["completeness_minus_gc7"] >= -0.01 and t["over_5mm_minus_gc7"] <= 0 and rmse_ok)
    return table


def _frames_prose(frames: str | None) -> str:
    sets = (frames or "random6").split(",")
    prose = {"random6": "the 6 random patterns",
             "gray7": "the 7 most significant Gray code images (no inverses), as on the real captures"}
    names = [prose.get(f, f"the rig's designed set of {f[6:]} patterns (bench.designed_patterns)") for f in sets]
    designed = any(f.startswith("design") for f in sets)
    return names[0] if len(names) == 1 else "each of: " + "; ".join(names) + \
        (" (one design per rig, from no scene)" if designed else "")


def markdown(doc: dict) -> str:
    from slwarp.evaluation.metrics import format_table

    rigs, scenes, labels = doc["rigs"], doc["scenes"], doc["labels"]
    methods = [lab for lab, _ in CLASSICAL] + labels
    t = doc["table"]
    md = [f"# Accuracy sweep: presets against Gray code on every rig ({doc['device_name']}, {doc['date']})", "",
          (f"`{doc['command']}`: the tables of the finished runs in its --state. " if doc.get("report") else
           f"`{doc['command']}`; {doc['workers']} runs at a time on {max(doc['gpus'], 1)} device(s); {doc['wall_s'] / 60:.1f} min. ")
          + (f"{doc['note']} " if doc.get("note") else "") + "Scans: `random6+gray7` (rows on the vertical rig), "
          f"SimOptions(seed={doc['seed']})" + _camera_prose(doc.get("camera", "linear")) + "; ours trains on " + _frames_prose(doc.get("neural_frames")) + "; GC(k) interp decodes k Gray code "
          "images without inverses. Metrics over the GT mask, means over the scenes "
          f"({', '.join(scenes)}).", ""]
    if doc["overrides"]:
        md += [f"Preset overrides: `{doc['overrides']}`.", ""]

    def mean(r, lab, k):
        return t[r].get(lab, {}).get("mean", {}).get(k, float("nan"))

    md += ["## Mean MAE (mm) per rig", ""]
    md.append(format_table([(lab, {r: mean(r, lab, "mae") for r in rigs}) for lab in methods],
                           [(r, r, "{:.3f}") for r in rigs], "method"))
    md += ["", "## Every metric, mean over the scenes", ""]
    full = [("mae", "MAE mm", "{:.3f}"), ("rmse", "RMSE mm", "{:.3f}"), ("median", "median mm", "{:.3f}"),
            ("over_1mm", "> 1 mm", "{:.2%}"), ("over_2mm", "> 2 mm", "{:.2%}"), ("over_5mm", "> 5 mm", "{:.2%}"),
            ("completeness", "complete", "{:.2%}")]
    md.append(format_table([(f"{lab} on {r}", {k: mean(r, lab, k) for k, _, _ in full}) for r in rigs for lab in methods],
                           full, "method, rig"))
    md += ["", "## Targets per rig (ours / GC(7), ours / GC(6), completeness, >5 mm share and RMSE against GC(7))", ""]
    rows = []
    for lab in labels:
        for r in rigs:
            tg = t[r].get(lab, {}).get("targets")
            if tg:
                rows.append((f"{lab} on {r}", {"a": tg["mae_over_gc7"], "b": tg["mae_over_gc6"],
                                               "c": 100 * tg["completeness_minus_gc7"],
                                               "d": 100 * tg["over_5mm_minus_gc7"], "f": tg.get("rmse_minus_gc7", float("nan")),
                                               "e": "yes" if tg["met"] else "no"}))
    md.append(format_table(rows, [("a", "MAE / GC(7) (<= 0.5)", "{:.2f}"), ("b", "MAE / GC(6) (<= 0.3)", "{:.2f}"),
                                  ("c", "completeness - GC(7) (pt, >= -1)", "{:+.2f}"),
                                  ("d", ">5 mm - GC(7) (pt, <= 0)", "{:+.2f}"),
                                  ("f", "RMSE - GC(7) (mm, <= 0)", "{:+.3f}"), ("e", "all met", "{}")], "preset, rig"))
    for r in rigs:
        md += ["", f"## {r}", ""]
        cols = [(s, s, "{:.3f}") for s in scenes] + [("mean", "mean", "{:.3f}")]
        for k, title, fmt in (("mae", "MAE mm", "{:.3f}"), ("rmse", "RMSE mm", "{:.3f}"),
                              ("completeness", "completeness", "{:.1%}"),
                              ("over_5mm", "share > 5 mm", "{:.2%}"),
                              ("mae_within_5mm", "MAE of the pixels off by <= 5 mm", "{:.3f}"),
                              ("outlier_mae", "part of the MAE from the pixels off by > 5 mm (mm)", "{:.3f}")):
            md += [f"{title} per scene:", ""]
            md.append(format_table([(lab, {**{s: t[r].get(lab, {}).get("per_scene", {}).get(s, {}).get(k, float("nan"))
                                              for s in scenes}, "mean": mean(r, lab, k)}) for lab in methods],
                                   [(c[0], c[1], fmt) for c in cols], "method"))
            md.append("")
        lost = []
        for lab in labels:
            per = [t[r].get(lab, {}).get("per_scene", {}).get(s, {}).get("lost") for s in scenes]
            if any(per):
                lost.append((lab, {k: 100 * float(np.mean([p.get(k, 0.0) for p in per if p])) for k in LOST}))
        if lost:
            md += ["Where the missing pixels went (% of the GT mask, mean over the scenes; a dropped pixel may be "
                   "outside the mask, so these bound the loss from above):", "",
                   format_table(lost, [(k, k.replace("_", " "), "{:.2f}") for k in LOST], "method"), ""]
        secs = [(lab, {"train": mean(r, lab, "train_s"), "total": mean(r, lab, "total_s")}) for lab in labels]
        md += ["Time per scan (s, mean; runs shared the device, see the header):", "",
               format_table(secs, [("train", "training", "{:.1f}"), ("total", "scan to depth map", "{:.1f}")], "preset")]
    if doc["errors"]:
        md += ["", "## Failed runs", ""] + [f"- {e['key']}: {e['error']}" for e in doc["errors"]]
    return "\n".join(md) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--presets", default=None, help="comma-separated presets, each PRESET or PRESET:key=value:key=value "
                    "(a variant, e.g. accurate:refine_range=3; default: the device's default preset)")
    ap.add_argument("--set", default=None, help="option overrides for every preset, e.g. 'iters=300,rays=512'")
    ap.add_argument("--rigs", default=None, help="comma-separated rig geometries (default: all)")
    ap.add_argument("--small", action="store_true", help="each geometry's small-resolution rig")
    ap.add_argument("--scenes", default=None, help="comma-separated scenes (default: every built-in scene)")
    ap.add_argument("--seed", type=int, default=0, help="simulator noise seed")
    ap.add_argument("--camera", default="linear", help="the simulator's camera model (slwarp.sim.simulate.CAMERA_MODELS:"
                    " linear, optics, gamma, srgb, halo; default linear, the scanner of the tables so far)")
    ap.add_argument("--designs", default=None, help="a folder of designed pattern sets, <rig>/design<K>/patterns.yaml "
                    "(bench.designed_patterns): the scans carry them too, and --neural-frames may name design<K>")
    ap.add_argument("--neural-frames", default="random6",
                    help="what the neural presets train on, comma-separated: random6 (the paper's 6 random patterns), "
                         "gray7 (the 7 Gray code images the classical GC(7) decodes: the real captures' case) or "
                         "design<K> (with --designs); several: every preset on each, named 'PRESET on SET'")
    ap.add_argument("--workers-per-gpu", type=int, default=4, help="processes per GPU (CUDA)")
    ap.add_argument("--workers", type=int, default=None, help="processes on the CPU (default 1)")
    ap.add_argument("--state", default=None, help="folder of finished runs (default <out>/accuracy-state)")
    ap.add_argument("--max-minutes", type=float, default=None,
                    help="stop starting runs after this many minutes (the runs under way finish; every finished run is kept: "
                         "run again to go on)")
    ap.add_argument("--out", default=str(REPO / "bench" / "results"))
    ap.add_argument("--keep", default=None, help="folder for each run's absolute error map (PNG, 0-5 mm) and its "
                    "signed error and pixel fates (npz, for study elsewhere)")
    ap.add_argument("--also-extract", default=None,
                    help="extraction variants, comma-separated, each key=value:key=value, applied to each neural run's "
                    "trained field after its own extraction and reported as PRESET+VARIANT (e.g. 'search_repair=true': "
                    "the repair's effect on the very same fields, at the cost of one extraction)")
    ap.add_argument("--report", action="store_true", help="run nothing: write the tables from the finished runs in "
                    "--state (e.g. states merged from several machines)")
    ap.add_argument("--device-name", default=None, help="with --report: the device the runs ran on (for the header)")
    ap.add_argument("--note", default=None, help="a sentence for the tables' header (e.g. how the runs were made)")
    ap.add_argument("--stem", default=None, help="output file name without suffix (default accuracy-<cpu|cuda>)")
    args = ap.parse_args(argv)

    import multiprocessing as mp

    import torch

    from slwarp.neural.config import default_preset_name
    from slwarp.sim.rigs import GEOMETRIES, rig_name
    from slwarp.sim.scenes import SCENE_NAMES

    cuda = torch.cuda.is_available()
    n_gpu = torch.cuda.device_count() if cuda else 0
    devices = [f"cuda:{i}" for i in range(n_gpu) for _ in range(args.workers_per_gpu)] if cuda else \
        ["cpu"] * (args.workers or 1)
    labels = args.presets.split(",") if args.presets else [default_preset_name("cuda" if cuda else "cpu")]
    also = args.also_extract.split(",") if args.also_extract else []
    overrides = parse_overrides(args.set)
    rigs = [rig_name(g, args.small) for g in (args.rigs.split(",") if args.rigs else GEOMETRIES)]
    scenes = args.scenes.split(",") if args.scenes else list(SCENE_NAMES)
    out = Path(args.out)
    state = Path(args.state) if args.state else out / "accuracy-state"
    state.mkdir(parents=True, exist_ok=True)

    frame_sets = args.neural_frames.split(",")
    for fs in frame_sets:
        if fs not in ("random6", "gray7") and not (fs.startswith("design") and fs[6:].isdigit() and args.designs):
            ap.error(f"--neural-frames {fs!r}: random6, gray7 or design<K> (design<K> needs --designs)")
    # runs are named by their set when there are several, or a design (bench.designed_patterns reads them so)
    several = len(frame_sets) > 1 or any(fs.startswith("design") for fs in frame_sets)
    from slwarp.sim.simulate import CAMERA_MODELS

    if args.camera not in CAMERA_MODELS:
        ap.error(f"--camera {args.camera!r}: one of {', '.join(CAMERA_MODELS)}")
    camera = {"camera": args.camera} if args.camera != "linear" else {}
    designs = {"designs": str(Path(args.designs).resolve())} if args.designs else {}
    jobs = []
    for r in rigs:
        for s in scenes:
            for fs in frame_sets:
                for label in labels:  # neural runs first: they are the long ones
                    name, *variant = label.split(":")
                    jobs.append({"kind": "neural", "label": label, "preset": name,
                                 "overrides": {**overrides, **parse_overrides(",".join(variant))}, "rig": r, "scene": s,
                                 "seed": args.seed, **({"also_extract": also} if also else {}),
                                 **({"frames": fs} if fs != "random6" or several else {}),
                                 **({"tag": f"{label} on {fs}"} if several else {}), **designs, **camera})
            jobs.append({"kind": "classical", "rig": r, "scene": s, "seed": args.seed, **designs, **camera})
    results, todo = [], []
    for j in jobs:
        f = state / (job_key(j) + ".json")
        if f.is_file():
            prev = json.loads(f.read_text())
            if prev["job"] == j:
                results.append(prev)
                continue
        todo.append(j)
    name = args.device_name or (torch.cuda.get_device_name(0) if n_gpu else "CPU")
    if args.report:
        todo = []
        cuda = any(str(r.get("device", "")).startswith("cuda") for r in results)  # where the runs ran
    print(f"{len(jobs)} runs ({len(jobs) - len(todo)} already done in {state}); {len(devices)} workers on "
          f"{n_gpu or 'no'} GPU ({name})", flush=True)
    t0 = time.perf_counter()
    threads = 1 if not cuda else 2
    ctx = mp.get_context("spawn")
    queue = ctx.Manager().Queue()
    for d in devices:
        queue.put(d)
    if todo:
        pool = ProcessPoolExecutor(max_workers=len(devices), mp_context=ctx, initializer=_init_worker,
                                   initargs=(queue, threads, args.keep))
        previous = signal.signal(signal.SIGTERM, _interrupt)
        kept_before = len(results)
        try:
            futures = {pool.submit(run_job, j): j for j in todo}
            stopping = False
            for i, fut in enumerate(as_completed(futures), 1):
                if fut.cancelled():  # not started before --max-minutes
                    continue
                res = fut.result()
                key = job_key(res["job"])
                results.append(res)
                if "error" in res:
                    print(f"[{i}/{len(todo)}] {key}: FAILED {res['error']}", flush=True)
                    continue
                (state / (key + ".json")).write_text(json.dumps(res, default=float))
                line = ", ".join(f"{lab} MAE {m['mae']:.3f} complete {m['completeness']:.3f}"
                                 for lab, m in res["methods"].items())
                print(f"[{i}/{len(todo)}] {key} ({res['wall_s']:.0f} s, {time.perf_counter() - t0:.0f} s so far): "
                      f"{line}", flush=True)
                if not stopping and args.max_minutes and time.perf_counter() - t0 > 60 * args.max_minutes:
                    # the runs under way finish and are kept like the others (they were lost before: waited for by
                    # the pool's shutdown, never saved)
                    print(f"--max-minutes {args.max_minutes} reached: cancelling the runs not started, keeping those "
                          "under way", flush=True)
                    for f in futures:
                        f.cancel()
                    stopping = True
        except KeyboardInterrupt:
            _stop_workers(pool)
            print(f"interrupted: the {len(results) - kept_before} runs this call finished are kept in {state}; the "
                  "same command goes on from there", file=sys.stderr, flush=True)
            return 130
        finally:
            signal.signal(signal.SIGTERM, previous)
        pool.shutdown()
    errors = [{"key": job_key(r["job"]), "error": r["error"]} for r in results if "error" in r]
    if several:
        labels = [f"{lab} on {fs}" for fs in frame_sets for lab in labels]
    all_labels = labels + [f"{lab}+{v}" for lab in labels for v in also]
    command = " ".join(["python -m bench.accuracy_sweep"] + _without_note(list(sys.argv[1:] if argv is None else argv)))
    doc = {"date": datetime.date.today().isoformat(), "device": "cuda" if cuda else "cpu", "device_name": name,
           "gpus": n_gpu, "workers": len(devices), "command": command, "seed": args.seed, "rigs": rigs,
           "scenes": scenes, "labels": all_labels, "overrides": overrides, "wall_s": time.perf_counter() - t0,
           "table": summarise(results, rigs, scenes, all_labels), "errors": errors, "report": args.report,
           "note": args.note, "neural_frames": args.neural_frames, "camera": args.camera}
    out.mkdir(parents=True, exist_ok=True)
    stem = args.stem or f"accuracy-{doc['device']}"
    (out / f"{stem}.json").write_text(json.dumps(doc, indent=1, default=float) + "\n")
    text = markdown(doc)
    (out / f"{stem}.md").write_text(text)
    print(text)
    missing = len(jobs) - sum(1 for r in results if "error" not in r)
    if missing:
        print(f"{missing} runs missing or failed: run the same command again to go on", file=sys.stderr)
    return 0 if not errors else 1


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main())
