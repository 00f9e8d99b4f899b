"""Real captures: every preset on every capture of the procam-calibration rig, as a user runs it.

Five real captures of one camera + projector rig (1280x1024 camera, 1024x768 projector, vertical baseline: the
projector's rows carry depth) come with the MIT-licensed repository kamino410/procam-calibration
(`sample_data/capture_0` ... `capture_4`; the calibration of its first commit matches these images, the later
one does not). Captures 0-2 are for development; 3 and 4 are the acceptance set: prepare them only to check
a finished change (`--acceptance`), never to tune.

    python -m bench.real_captures prepare --repo PATH_TO_CLONE            # captures 0-2 into data/real/
    python -m bench.real_captures run --presets fast,accurate,tuned       # every preset on every prepared capture
    python -m bench.real_captures run --presets fast,fast:free_space=0 --captures 1,2 --stem real-fast-ablation
    python -m bench.real_captures run --presets fast,accurate --also-extract doubt_confidence=0.8
                                        # extraction variants of the same trained fields (labelled PRESET+VARIANT)

`prepare` reads a clone of the repository (a work tree or a bare git directory; its commit ccf1cd8 is used) and
writes, per capture, `data/real/capture_N/scan/` (a native scan of the 7 most significant row-code images, no
inverses, depth range 800-2600 mm: what a user with a 7-pattern rig has) and `reference.npz`: the full 40-image
Gray code decode with interpolation (every projector row and column), GC(7)-interp of the same 7 images, and the
chessboard plate's region (9x7 inner corners found in the white image). Nothing of it is committed (data/ is
ignored).

`run` reconstructs each capture with each preset as a fresh process of the command a user types
(`python -m slwarp reconstruct SCAN --config PRESET.yaml --out DIR --quiet`), spread over the visible GPUs, and
reports per capture: the plate's RMS distance to its fitted plane (mm; the calibration alone bends the plate by
about 0.4 mm RMS), the same about a quadric (local error), the plate's coverage, the agreement with the full decode
over the whole image (median |difference| and the share above 2 mm where both have depth; the share of the full
decode's pixels given a depth within 2 mm of it), the pixels with depth, the command's wall time, and what the extraction decided about the photometric refinement (refined or not, the misfit its gate saw, the
held-out check's word); beside the full decode, the pattern model's misfit of the 7 images at that depth (what the
gate compares with `refine_max_misfit`). The two classical references are reported the same way. Writes
<out>/<stem>.json and .md.

`--also-extract` compares extraction options without the noise of a second training: after each preset's run,
each variant copies that run's final checkpoint into its own folder and continues it with `--resume` and the
variant's options (only options marked 'may change on resume' may differ), so it extracts the same field again.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DEST = REPO / "data" / "real"
DATA_COMMIT = "ccf1cd8"  # the repository's first commit with data: its calibration matches the captures
DEV_CAPTURES = (0, 1, 2)
ACCEPTANCE_CAPTURES = (3, 4)
SEVEN_ROWS = "gray:row:bit=0-6:noinv"  # the 7 most significant row bits, no inverses (role selector)
DEPTH_RANGE = (800.0, 2600.0)  # mm: wide around the plate and the wall (about 1.1-1.7 m), as a user would set it
AGREE_MM = 2.0
EDGE_BAND_PX = 20  # a twin's pixels this close to a depth step count as the edges' (capture_metrics)


def _extract_repo(repo: Path, into: Path) -> Path:
    """The repository's sample_data at DATA_COMMIT, extracted under `into`; returns the sample_data folder."""
    git_dir = repo / ".git" if (repo / ".git").exists() else repo
    if not (git_dir / "HEAD").is_file():
        raise SystemExit(f"{repo}: not a git clone of kamino410/procam-calibration (no .git or HEAD)")
    archive = into / "sample_data.tar"
    with open(archive, "wb") as f:
        p = subprocess.run(["git", f"--git-dir={git_dir}", "archive", DATA_COMMIT, "sample_data", "LICENSE"],
                           stdout=f, stderr=subprocess.PIPE, text=False)
    if p.returncode:
        raise SystemExit(f"{repo}: git archive {DATA_COMMIT} failed: {p.stderr.decode().strip()}")
    with tarfile.open(archive) as t:
        t.extractall(into, filter="data")
    return into / "sample_data"


def prepare(args) -> None:
    from slwarp.evaluation.metrics import chessboard_region
    from slwarp.scans.scan import load_scan

    captures = DEV_CAPTURES + (ACCEPTANCE_CAPTURES if args.acceptance else ())
    dest = Path(args.dest)
    dest.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        sample = _extract_repo(Path(args.repo), Path(tmp))
        shutil.copy(Path(tmp) / "LICENSE", dest / "LICENSE")
        for n in captures:
            t = time.perf_counter()
            full = load_scan(sample / f"capture_{n}")
            region = chessboard_region(full.images[full.frame_with("white")])
            out = dest / f"capture_{n}"
            ref = write_capture(full, region, out)
            print(f"capture_{n}: 7 frames -> {out / 'scan'}; full decode on "
                  f"{np.isfinite(ref).mean():.1%} of the image, plate {int(region.sum())} px "
                  f"({time.perf_counter() - t:.1f} s)", flush=True)


def write_capture(full, region: np.ndarray, out: Path) -> np.ndarray:
    """A prepared capture in `out`: scan/ (the 7 most significant row-code images of the full scan `full`, depth
    range DEPTH_RANGE) and reference.npz (the full decode, GC(7)-interp of the same 7 images, the plate's `region`).
    Shared with bench.real_twin, whose simulated twins are prepared the same way. Returns the full decode."""
    from slwarp.decode import reconstruct_depth

    ref, _, _ = reconstruct_depth(full, "gc-interp", depth_range=DEPTH_RANGE)
    seven = full.select(SEVEN_ROWS)
    gc7, _, _ = reconstruct_depth(seven, "gc-interp", depth_range=DEPTH_RANGE)
    seven.depth_range = DEPTH_RANGE
    shutil.rmtree(out, ignore_errors=True)
    seven.save(out / "scan")
    np.savez_compressed(out / "reference.npz", full_decode=ref.astype(np.float32), gc7=gc7.astype(np.float32),
                        region=region)
    return ref


def capture_metrics(depth: np.ndarray, ref: dict, camera) -> dict:
    """Plate RMS (plane, quadric), plate coverage and agreement with the full decode of one depth map [H, W] mm; on a
    twin (ref with gt_depth, gt_mask and, computed once per capture, gt_step_px) the exact depth's metrics too."""
    from slwarp.evaluation.metrics import plane_rms, quadric_rms
    from slwarp.neural.depth_maps import depth_to_points

    region = ref["region"]
    pts = depth_to_points(np.where(region, depth, np.nan), camera)
    rms, n = plane_rms(pts)
    both = np.isfinite(depth) & np.isfinite(ref["full_decode"])
    diff = np.abs(depth[both] - ref["full_decode"][both])
    exact = {}
    if "gt_depth" in ref:  # a twin's exact depth: MAE, RMSE and completeness over its mask
        from slwarp.evaluation.metrics import depth_metrics, depth_step_distance

        m = depth_metrics(depth, ref["gt_depth"], ref["gt_mask"])
        exact = {"gt_mae_mm": m["mae"], "gt_rmse_mm": m["rmse"], "gt_completeness": m["completeness"]}
        # what the depth edges cost: the MAE's part from pixels within EDGE_BAND_PX of a depth step, and the MAE
        # of the pixels beyond (a field draws small steps soft: docs/accuracy.md, section 34)
        err = np.abs(depth - ref["gt_depth"])
        ok = ref["gt_mask"] & np.isfinite(err)
        step_px = ref["gt_step_px"] if "gt_step_px" in ref else depth_step_distance(ref["gt_depth"])
        near = ok & (step_px < EDGE_BAND_PX)
        exact.update(gt_mae_edge_part_mm=float(err[near].sum() / max(ok.sum(), 1)),
                     gt_mae_interior_mm=float(err[ok & ~near].mean()) if (ok & ~near).any() else float("nan"))
    return {**exact, "plane_rms_mm": rms, "quadric_rms_mm": quadric_rms(pts), "plate_coverage": n / max(int(region.sum()), 1),
            "agree_median_mm": float(np.median(diff)) if diff.size else float("nan"),
            "agree_over_2mm": float((diff > AGREE_MM).mean()) if diff.size else float("nan"),
            "agree_coverage": float((diff <= AGREE_MM).sum()) / max(int(np.isfinite(ref["full_decode"]).sum()), 1),
            "pixels_with_depth": float(np.isfinite(depth).mean())}


def refinement_facts(timings: dict) -> dict:
    """What a run's extraction decided about the photometric refinement, from its timings.json: refined (bool),
    refine_misfit (the pattern model's misfit at the depth the gate saw; None without a gate) and refine_kept (the
    held-out check's decision; None without the check) and lens_halo (the halo's share the pattern model used, fitted
    or given; None when the run does not say)."""
    check = timings.get("refine_check")
    return {"refined": timings.get("refined"), "refine_misfit": timings.get("refine_misfit"),
            "refine_kept": check.get("keep") if isinstance(check, dict) else None,
            "lens_halo": timings.get("pattern_halo")}


def _gpus() -> list[str]:
    """The visible GPUs' indices as strings (nvidia-smi; no CUDA context in this process); [] without one."""
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None:
        return [g for g in visible.split(",") if g.strip()]
    try:
        out = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.TimeoutExpired):
        return []
    return [str(i) for i, line in enumerate(out.splitlines()) if line.startswith("GPU ")]


def _finished(job: dict) -> dict | None:
    """The result of a run an earlier call of the same command finished in --work (its run.json; or, without one, its
    depth.npy and timings.json, with the wall time unknown), so that an interrupted comparison goes on; else None.
    A run is known by its capture and preset label: give a new --work when the code or the scans change."""
    out = Path(job["out"])
    if (out / "run.json").is_file():
        return {**job, **json.loads((out / "run.json").read_text()), "out": out}
    if (out / "depth.npy").is_file() and (out / "timings.json").is_file():
        return {**job, "wall_s": None, "rc": 0}
    return None


def _run_one(job: dict, gpu: str | None) -> dict:
    """One reconstruction as a fresh process of the CLI; the job with wall_s, rc and (on failure) the output's tail.
    A variant job (job["base_out"]: the folder of its preset's finished run) starts from a copy of that run's final
    checkpoint and continues it with --resume: the same field, extracted with the variant's options."""
    env = dict(os.environ)
    if gpu is not None:
        env["CUDA_VISIBLE_DEVICES"] = gpu
    cmd = [sys.executable, "-m", "slwarp", "reconstruct", str(job["scan"]), "--config", str(job["config"]),
           "--out", str(job["out"]), "--quiet"]
    if job.get("base_out") is not None:
        out = Path(job["out"])
        shutil.rmtree(out, ignore_errors=True)
        shutil.copytree(Path(job["base_out"]) / "train", out / "train")
        cmd.append("--resume")
    else:
        cmd.append("--overwrite")
    if job.get("depth_range"):
        cmd += ["--depth-range", job["depth_range"]]
    t = time.perf_counter()
    p = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True)
    job = dict(job, wall_s=time.perf_counter() - t, rc=p.returncode, gpu=gpu)
    if p.returncode:
        job["tail"] = (p.stdout + p.stderr).strip()[-1500:]
    else:  # finished: a later call with the same --work takes it as it is (`_finished`)
        (Path(job["out"]) / "run.json").write_text(json.dumps({"wall_s": job["wall_s"], "rc": 0, "gpu": gpu}))
    return job


def run(args) -> None:
    from slwarp.neural.config import parse_assignments, preset, save_config
    from slwarp.neural.pattern_model import model_misfit
    from slwarp.scans.scan import load_scan

    data, work = Path(args.data), Path(args.work)
    neural_range = [float(x) for x in args.depth_range.split(",")] if args.depth_range else list(DEPTH_RANGE)
    captures = [int(c) for c in args.captures.split(",")] if args.captures else sorted(
        int(p.name.split("_")[1]) for p in data.glob("capture_*") if (p / "reference.npz").is_file())
    if not captures:
        raise SystemExit(f"{data}: no prepared captures (run `python -m bench.real_captures prepare` first)")
    acceptance = [c for c in captures if c in ACCEPTANCE_CAPTURES]
    if acceptance:
        print(f"note: captures {acceptance} are the acceptance set: report them, never tune on them", flush=True)
    work.mkdir(parents=True, exist_ok=True)
    presets = args.presets.split(",")
    variants = args.also_extract.split(",") if args.also_extract else []
    labels = [lab for name in presets for lab in [name] + [f"{name}+{v}" for v in variants]]
    jobs = []
    for label in presets:
        name, *items = label.split(":")
        configs = {}
        for variant in [None] + variants:
            lab = label if variant is None else f"{label}+{variant}"
            configs[lab] = work / f"config-{_folder_name(lab)}.yaml"
            extra = parse_assignments(variant.split(":")) if variant else {}
            save_config(configs[lab], preset(name, **{**parse_assignments(items), **extra}))
        for c in captures:
            base = {"label": label, "capture": c, "scan": data / f"capture_{c}" / "scan", "config": configs[label],
                    "out": work / f"capture_{c}" / _folder_name(label), "depth_range": args.depth_range}
            # the variants run after their preset's run, on the same worker, from its checkpoint
            base["variants"] = [dict(base, label=lab, config=configs[lab], out=work / f"capture_{c}" / _folder_name(lab),
                                     base_out=base["out"]) for lab in configs if lab != label]
            jobs.append(base)
    slots = [g for g in _gpus() for _ in range(args.workers_per_gpu)] or [None]
    queue, done, lock = list(jobs), [], threading.Lock()

    def worker(gpu):
        while True:
            with lock:
                if not queue:
                    return
                job = queue.pop(0)
            base = _finished(job) or _run_one(job, gpu)
            for res in [base] + [_finished(v) or _run_one(v, gpu) for v in (job["variants"] if base["rc"] == 0 else [])]:
                with lock:
                    done.append(res)
                    print(f"capture_{res['capture']} {res['label']}: "
                          + (f"{res['wall_s']:.1f} s" if res["wall_s"] is not None else "done before")
                          + ("" if res["rc"] == 0 else f" FAILED rc={res['rc']}\n{res['tail']}"), flush=True)

    threads = [threading.Thread(target=worker, args=(g,)) for g in slots]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    rows = []
    for c in captures:
        ref = dict(np.load(data / f"capture_{c}" / "reference.npz"))
        seven = load_scan(data / f"capture_{c}" / "scan").select(SEVEN_ROWS)
        camera = seven.camera
        if seven.gt_depth is not None:  # a simulated twin (bench.real_twin): the exact depth too
            from slwarp.evaluation.metrics import depth_step_distance

            # the exact depth's steps, once per capture for every method's row
            ref["gt_depth"], ref["gt_mask"] = seven.gt_depth, seven.mask
            ref["gt_step_px"] = depth_step_distance(seven.gt_depth)
        # the refinement's gate compares this kind of number with refine_max_misfit: the model's misfit of the
        # 7 images at the full decode, a depth close to the truth
        misfit = model_misfit(ref["full_decode"], camera, seven.projector, seven.images, seven.patterns)
        rows.append({"capture": c, "method": "full 40-image gc-interp", "model_misfit": misfit,
                     **capture_metrics(ref["full_decode"], ref, camera)})
        rows.append({"capture": c, "method": "GC(7)-interp, same 7 images", **capture_metrics(ref["gc7"], ref, camera)})
        for res in sorted((r for r in done if r["capture"] == c), key=lambda r: labels.index(r["label"])):
            row = {"capture": c, "method": res["label"], "wall_s": res["wall_s"], "rc": res["rc"]}
            if res["rc"] == 0:
                depth = np.load(res["out"] / "depth.npy")
                timings = json.loads((res["out"] / "timings.json").read_text())
                row.update(capture_metrics(depth, ref, camera), depth_map_s=timings.get("depth_map_s"),
                           **refinement_facts(timings))
            else:
                row["error"] = res.get("tail", "")[-300:]
            rows.append(row)
    doc = {"date": str(datetime.date.today()), "device": args.device_name or _device_name(),
           "command": "python -m bench.real_captures " + " ".join(sys.argv[1:]), "depth_range_mm": neural_range,
           "frames": SEVEN_ROWS, "rows": rows}
    md = markdown(doc, captures, ["full 40-image gc-interp", "GC(7)-interp, same 7 images"] + labels)
    print(md)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{args.stem}.json").write_text(json.dumps(doc, indent=1, default=str))
    (out / f"{args.stem}.md").write_text(md + "\n")


def _folder_name(label: str) -> str:
    """A preset label as a folder or file name: fast:free_space=0+doubt_confidence=0.8 -> fast_free_space-0+doubt..."""
    return label.replace(":", "_").replace("=", "-")


def _device_name() -> str:
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True,
                             text=True, timeout=30).stdout.strip().splitlines()
        return f"{len(out)} x {out[0]}" if out else "CPU"
    except (OSError, subprocess.TimeoutExpired):
        return "CPU"


def markdown(doc: dict, captures: list[int], methods: list[str]) -> str:
    """Tables: plate RMS per capture and method with the mean; then every metric per capture."""
    by = {(r["capture"], r["method"]): r for r in doc["rows"]}
    head = " | ".join(f"capture {c}" for c in captures)
    twin = any("gt_mae_mm" in r for r in doc["rows"])
    title = ("Twins of the real captures (simulated by bench.real_twin): plate planarity, agreement with the full "
             "decode and the exact depth" if twin else "Real captures: plate planarity and agreement with the full decode")
    floor = ("the twin's plate is flat and its calibration exact, so no floor but the method's" if twin else
             "the calibration bends the plate by about 0.4 mm, the floor of every method")
    lines = [f"# {title} ({doc['device']}, {doc['date']})",
             "", f"`{doc['command']}`", "",
             f"Frames `{doc['frames']}` (7 row-code images), the neural runs' depth range {doc['depth_range_mm'][0]:.0f}-"
             f"{doc['depth_range_mm'][1]:.0f} mm. Plate RMS: distance (mm) of the plate's points to their fitted plane; "
             f"{floor}.", "",
             "## Plate RMS (mm)", "", f"| method | {head} | mean |", "|---|" + "---:|" * (len(captures) + 1)]
    for m in methods:
        vals = [by.get((c, m), {}).get("plane_rms_mm", float("nan")) for c in captures]
        lines.append(f"| {m} | " + " | ".join(f"{v:.3f}" for v in vals) + f" | {np.mean(vals):.3f} |")
    # completeness that counts right depths only: GC(7)'s extra pixels on the real captures are mostly wrong (capture
    # 0: of the 46,900 pixels it has and `fast` drops, 13% lie within 2 mm of the full decode; docs/accuracy.md, section 36)
    if any("agree_coverage" in r for r in doc["rows"]):
        lines += ["", f"## The full decode's pixels with a depth within {AGREE_MM:g} mm of it", "",
                  f"| method | {head} | mean |", "|---|" + "---:|" * (len(captures) + 1)]
        for m in methods:
            vals = [by.get((c, m), {}).get("agree_coverage", float("nan")) for c in captures]
            lines.append(f"| {m} | " + " | ".join(f"{v:.1%}" for v in vals) + f" | {np.mean(vals):.1%} |")
    if twin:  # twins: the exact depth's verdict beside the plate's
        for key, title, fmt in (("gt_mae_mm", "MAE against the exact depth (mm)", "{:.3f}"),
                                ("gt_rmse_mm", "RMSE against the exact depth (mm)", "{:.3f}"),
                                ("gt_completeness", "Completeness (share of the exact depth's pixels)", "{:.1%}"),
                                ("gt_mae_edge_part_mm", f"The MAE's part from pixels within {EDGE_BAND_PX} px of a "
                                 "depth step (mm)", "{:.3f}"),
                                ("gt_mae_interior_mm", f"MAE of the pixels farther than {EDGE_BAND_PX} px from a depth "
                                 "step (mm)", "{:.3f}")):
            if not any(key in r for r in doc["rows"]):  # results written before the metric
                continue
            lines += ["", f"## {title}", "", f"| method | {head} | mean |", "|---|" + "---:|" * (len(captures) + 1)]
            for m in methods:
                vals = [by.get((c, m), {}).get(key, float("nan")) for c in captures]
                lines.append(f"| {m} | " + " | ".join(fmt.format(v) for v in vals) + f" | {fmt.format(np.mean(vals))} |")
    lines += ["", "## Every metric", "", "| capture | method | plate RMS mm | quadric RMS mm | plate covered | "
              "agreement median mm | agreement > 2 mm | pixels with depth | command wall s | in-run depth map s | "
              "refined (misfit, lens halo) |", "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for c in captures:
        for m in methods:
            r = by.get((c, m))
            if r is None:
                continue
            if r.get("error"):
                lines.append(f"| {c} | {m} | failed: {r['error'][-120:]!r} ||||||||")
                continue
            wall = f"{r['wall_s']:.1f}" if r.get("wall_s") is not None else "-"
            dm = f"{r['depth_map_s']:.1f}" if r.get("depth_map_s") is not None else "-"
            lines.append(f"| {c} | {m} | {r['plane_rms_mm']:.3f} | {r['quadric_rms_mm']:.3f} | {r['plate_coverage']:.1%} | "
                         f"{r['agree_median_mm']:.3f} | {r['agree_over_2mm']:.2%} | {r['pixels_with_depth']:.1%} | "
                         f"{wall} | {dm} | {_refinement_cell(r)} |")
    return "\n".join(lines)


def _refinement_cell(row: dict) -> str:
    """'yes' / 'no' with the misfit the gate saw and the held-out check's word; for the full decode its misfit."""
    if row.get("model_misfit") is not None:
        return f"({row['model_misfit']:.4f} at this depth)"
    if row.get("refined") is None:
        return "-"
    cell = "yes" if row["refined"] else "no"
    notes = ([f"misfit {row['refine_misfit']:.4f}"] if row.get("refine_misfit") is not None else []) + \
        ([f"check {'kept' if row['refine_kept'] else 'refused'}"] if row.get("refine_kept") is not None else []) + \
        ([f"halo {row['lens_halo']:.3f}"] if row.get("lens_halo") else [])
    return cell + (f" ({', '.join(notes)})" if notes else "")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    pp = sub.add_parser("prepare", help="extract and prepare the captures from a clone of the repository")
    pp.add_argument("--repo", required=True, help="a clone of kamino410/procam-calibration (work tree or bare)")
    pp.add_argument("--dest", default=str(DEFAULT_DEST))
    pp.add_argument("--acceptance", action="store_true", help="also captures 3 and 4 (the acceptance set)")
    pr = sub.add_parser("run", help="reconstruct the prepared captures with each preset")
    pr.add_argument("--presets", required=True, help="comma-separated, each PRESET or PRESET:key=value:key=value")
    pr.add_argument("--captures", default=None, help="comma-separated capture numbers (default: every prepared one)")
    pr.add_argument("--data", default=str(DEFAULT_DEST))
    pr.add_argument("--work", default="/tmp/slwarp-real-captures", help="each run's output folder")
    pr.add_argument("--also-extract", default=None, metavar="VARIANTS",
                    help="comma-separated extraction variants, each key=value:key=value, run on each preset's trained "
                    "field (its checkpoint continued with --resume), e.g. doubt_confidence=0.8")
    pr.add_argument("--workers-per-gpu", type=int, default=2)
    pr.add_argument("--depth-range", default=None, metavar="NEAR,FAR",
                    help="the neural runs' depth range in mm (default: the scans' own, 800-2600)")
    pr.add_argument("--device-name", default=None)
    pr.add_argument("--out", default=str(REPO / "bench" / "results"))
    pr.add_argument("--stem", default="real-captures")
    args = p.parse_args(argv)
    (prepare if args.cmd == "prepare" else run)(args)


if __name__ == "__main__":
    main()
