"""Training-level ablation of image-model changes that the model-floor study (bench/model_floor.py) ranks
high, prototyped here around the library's trainer (subclass + replaced forward; nothing in slwarp/ changes).

Variants (comma-separated flags; "baseline" = today's pipeline of the preset):
    ls        offset and modulation solved per ray in closed form inside the loss: the fused op renders the
              codes R_i = sum_k w_k P_i(pi(x_k)) (a = 0, b = 1), then b = cov(R, I) / var(R) (a ridge toward the
              min/max modulation, clamped at >= 0) and a = mean(I) - b mean(R) per ray, in torch; the L1
              residual |a + b R_i - I_i| is L_rc (gradients flow through a and b). No host synchronisation.
    dblur     depth-dependent pattern blur: sigma fitted per projector-depth bin at the depth-search map (as the
              global sigma is today), each pixel's sigma read at its search depth, and the codes rendered with
              the patterns blurred at 3 levels spanning the fitted sigmas, blended per ray (3 op calls, one
              field evaluation).
    gamma     the images linearised by I ** gamma before training, gamma fitted at the depth-search map.
    sphere    depth by sphere tracing the SDF instead of the marching-cubes mesh.
Every variant's depth is also reported after the photometric refinement (image_model.refine_depth): per pixel,
the offset within +-3 mm of the filtered depth that minimises the least-squares model's cost over a 7x7 window,
with the blur fitted per projector-depth bin at that depth.
    gtinit    a diagnostic, not a method: the warm-up pulls the field onto the ground-truth depth instead of the
              depth-search map (what a perfect search would give).
The photometric filter uses each variant's own model (its a/b, blur and linearised images), threshold 0.4.

    python bench/train_ablation.py                         # the default sweep (small rig, `cpu` preset)
    python bench/train_ablation.py --scenes bunny --variants baseline,ls --preset tiny --out /tmp/abl  # quick

Fields are cached in --cache (a rerun only evaluates). Writes bench/results/train-ablation-cpu.{json,md}.
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))

from image_model import (PatternStack, fit_depth_sigma, fit_gamma, fit_model, fit_sigma, model_residual,  # noqa: E402
                         projector_uv_z, refine_depth)
from study_common import DATE, gray_code_yardstick, markdown_table, simulate_study_scan, train_cached  # noqa: E402

FLAGS = ("ls", "dblur", "gamma", "sphere", "gtinit")
LS_RIDGE = 0.02


def ls_color_loss(rendered: torch.Tensor, observed: torch.Tensor, b_prior: torch.Tensor, valid: torch.Tensor,
                  ridge: float = LS_RIDGE) -> torch.Tensor:
    """L1 colour loss with a, b solved per ray: rendered codes [R, N] (a = 0, b = 1), observed [R, N],
    b_prior [R] (max - min), valid [R]. Closed form, differentiable, no data-dependent control flow."""
    mr = rendered.mean(1, keepdim=True)
    mi = observed.mean(1, keepdim=True)
    cov = ((rendered - mr) * (observed - mi)).mean(1)
    var = ((rendered - mr) ** 2).mean(1)
    b = ((cov + ridge * b_prior) / (var + ridge)).clamp(min=0.0)
    a = mi[:, 0] - b * mr[:, 0]
    pred = a[:, None] + b[:, None] * rendered
    m = valid.to(rendered.dtype)[:, None]
    return ((pred - observed).abs() * m).sum() / (m.sum() * observed.shape[1]).clamp(min=1.0)


def search_map(trainer) -> np.ndarray | None:
    d = trainer.init_depth
    if d is None:
        return None
    return d.detach().cpu().numpy().reshape(trainer.scan.camera.height, trainer.scan.camera.width)


def make_trainer_cls(flags: set[str]):
    """A Trainer subclass implementing the variant's flags (see module docstring)."""
    from slwarp.neural import ops
    from slwarp.neural.pattern_model import blur_patterns
    from slwarp.neural.render import RenderLosses, structured_light_losses
    from slwarp.neural.train import Trainer

    class VariantTrainer(Trainer):
        def __init__(self, scan, cfg, **kw):
            if "gtinit" in flags and not kw.get("resume"):
                kw["init_depth"] = scan.gt_depth
            super().__init__(scan, cfg, **kw)
            r = self.renderer
            self.ab = "ls" if "ls" in flags else "minmax"
            H, W = scan.camera.height, scan.camera.width
            self.sigma_map = np.full((H, W), r.pattern_blur)  # per-pixel blur used by the filter
            self.levels = None
            if "dblur" in flags:
                self._fit_depth_blur()
            if "ls" in flags or "dblur" in flags:
                r.forward = self._forward  # instance attribute: nn.Module.__call__ finds it first

        def _fit_depth_blur(self):
            r, scan = self.renderer, self.scan
            depth = search_map(self)
            cam, prj = scan.camera, scan.projector
            images = scan.images[: self.n_frames].astype(np.float64)
            ok = np.isfinite(depth) & r.valid_map.cpu().numpy()
            rays = cam.pixel_to_ray(cam.pixel_grid())
            uv, zp = projector_uv_z(rays[ok], depth[ok].astype(np.float64), prj)
            obs = images[:, ok].T
            stack = PatternStack(scan.patterns[: self.n_frames])
            a0 = obs.min(1)
            b0 = obs.max(1) - a0
            zc, sc = fit_depth_sigma(stack, obs, uv, zp, self.ab, a0, b0)
            self.blur_bins = {"z_p": zc.tolist(), "sigma": sc.tolist()}
            # every pixel's sigma at its search depth (the global fit where there is none)
            _, zp_all = projector_uv_z(rays, np.where(np.isfinite(depth), depth, np.nan).astype(np.float64), prj)
            sig = np.where(np.isfinite(zp_all), np.interp(np.nan_to_num(zp_all, nan=0.0), zc, sc), r.pattern_blur)
            self.sigma_map = sig
            lv = np.linspace(sc.min(), sc.max(), 3)
            self.levels = lv
            pats = torch.as_tensor(np.asarray(scan.patterns[: self.n_frames], np.float32))
            self.level_patterns = [ops.pack_patterns(blur_patterns(pats, float(s))).to(self.device) for s in lv]
            # per-pixel blend weights [H*W, 3] of the levels (piecewise linear in sigma)
            s = np.clip(sig.reshape(-1), lv[0], lv[-1])
            w = np.zeros((s.size, 3), np.float32)
            step = max(lv[1] - lv[0], 1e-9)
            pos = (s - lv[0]) / step
            i0 = np.clip(np.floor(pos).astype(int), 0, 1)
            t = pos - i0
            w[np.arange(s.size), i0] = 1 - t
            w[np.arange(s.size), i0 + 1] += t
            self.level_weights = torch.as_tensor(w, device=self.device)

        def _forward(self, batch, *, cos_anneal_ratio=1.0, perturb=True, generator=None, jitter=None):
            r = self.renderer
            zeros, ones = torch.zeros_like(batch.a), torch.ones_like(batch.b)
            ab_batch = batch._replace(a=zeros, b=ones) if self.ab == "ls" else batch
            o, d, z = r.sample_rays(ab_batch, perturb, generator, jitter)
            z_sr = z.t().contiguous()
            x = o[None, :, :] + z_sr[..., None] * d[None, :, :]
            sdf, grad = r._field_fn("grad")(x)
            pattern_sets = self.level_patterns if self.levels is not None else [r.patterns_hwn]
            outs = [ops.render_structured_light(
                sdf.t(), grad.transpose(0, 1), z_sr.t(), o, d, ab_batch.a, ab_batch.b, p, r._projector_packed, r.inv_s(),
                cos_anneal_ratio=cos_anneal_ratio, backend=r.backend, bounds=r.volume.as_bounds(), patterns_layout="HWN")
                for p in pattern_sets]
            out = outs[0]
            if len(outs) > 1:
                w = self.level_weights[batch.index]
                out = out._replace(rendered=sum(w[:, k : k + 1] * o_.rendered for k, o_ in enumerate(outs)),
                                   surface_rendered=sum(w[:, k : k + 1] * o_.surface_rendered for k, o_ in enumerate(outs)))
            if self.ab == "ls":
                color = ls_color_loss(out.rendered, batch.observed, batch.b, batch.valid)
                _, surface, eikonal = structured_light_losses(out, batch.observed, batch.valid)
            else:
                color, surface, eikonal = structured_light_losses(out, batch.observed, batch.valid)
            return RenderLosses(color, surface, eikonal, out, z_sr.t(), batch.valid)

    return VariantTrainer


def linearise(scan, preset_name: str):
    """(scan with images ** gamma, gamma): gamma fitted at a depth-search map of the raw images (blur 1 px,
    the trainer's search setting), with the least-squares model at the blur fitted there."""
    import dataclasses

    from slwarp.neural.pattern_model import blur_patterns
    from slwarp.neural.search import search_depth
    from slwarp.neural.config import preset

    cfg = preset(preset_name)
    images = scan.images.astype(np.float32)
    b = images.max(0) - images.min(0)
    valid = b > cfg.get("contrast_threshold")
    depth, _ = search_depth(scan.camera, scan.projector, images,
                            blur_patterns(torch.as_tensor(scan.patterns), 1.0).numpy(), scan.depth_range,
                            valid=valid, step_mm=cfg.get("search_step_mm"), stride=cfg.get("search_stride"), device="cpu")
    ok = np.isfinite(depth) & valid
    rays = scan.camera.pixel_to_ray(scan.camera.pixel_grid())
    uv, _ = projector_uv_z(rays[ok], depth[ok].astype(np.float64), scan.projector)
    obs = images[:, ok].T.astype(np.float64)
    stack = PatternStack(scan.patterns)
    s = fit_sigma(stack, obs, uv, "ls", obs.min(1), obs.max(1) - obs.min(1))
    gamma = fit_gamma(obs, stack.sample(uv, s), "ls")
    return dataclasses.replace(scan, images=(images ** gamma).astype(np.float32)), gamma


def variant_photometric_filter(depth, trainer, threshold: float) -> np.ndarray:
    """Depth with pixels dropped whose relative RMS residual under the variant's own model (a/b, per-pixel
    blur) reaches `threshold` (as slwarp.neural.pattern_model.photometric_filter, which is the baseline's model)."""
    scan = trainer.scan
    images = scan.images[: trainer.n_frames].astype(np.float64)
    ok = np.isfinite(depth)
    rays = scan.camera.pixel_to_ray(scan.camera.pixel_grid())
    uv, _ = projector_uv_z(rays[ok], depth[ok].astype(np.float64), scan.projector)
    stack = PatternStack(scan.patterns[: trainer.n_frames])
    obs = images[:, ok].T
    a0 = obs.min(1)
    b0 = obs.max(1) - a0
    r = model_residual(obs, stack.sample(uv, trainer.sigma_map[ok]), trainer.ab, a0, b0)
    rel = np.sqrt(np.mean(r**2, -1)) / np.maximum(b0, 1e-3)
    out = np.full(depth.shape, np.nan, np.float32)
    out[ok] = np.where(rel < threshold, depth[ok], np.nan)
    return out


def extract(trainer, cfg, flags: set[str]) -> dict:
    """Depth maps of the trained field: raw (mesh or sphere), after the flying-pixel filter, after the
    variant's photometric filter."""
    from slwarp.neural.extraction.surface import extract_mesh, flying_pixel_filter, mesh_depth, sphere_trace_depth
    from slwarp.neural.pattern_model import photometric_filter

    cam = trainer.scan.camera
    valid = trainer.renderer.valid_map.cpu().numpy()
    field = trainer.field.eval()
    if "sphere" in flags:
        d = sphere_trace_depth(field, cam, trainer.depth_range, trainer.device, valid=valid)
    else:
        d = mesh_depth(extract_mesh(field, trainer.volume, cfg.get("mc_resolution"), trainer.device, depth_range=trainer.depth_range), cam, "cpu")
    field.train()
    near, far = trainer.depth_range
    d = np.where(valid & (d >= near) & (d <= far), d, np.nan).astype(np.float32)
    f1 = flying_pixel_filter(d, cam, cfg.get("edge_filter"))
    # the library's filter: the baseline's model exactly (min/max a, b; the global blur applied at its sigma)
    f_lib = photometric_filter(f1, cam, trainer.scan.projector, trainer.scan.images[: trainer.n_frames],
                               trainer.renderer.rendered_patterns.cpu().numpy(), (1.0 - cfg.get("min_confidence")))
    f2 = variant_photometric_filter(f1, trainer, (1.0 - cfg.get("min_confidence"))) if flags & {"ls", "dblur"} else f_lib
    # photometric refinement of the filtered depth: least-squares a, b and the blur per projector-depth bin,
    # both fitted at that depth; a 7x7 window, +-3 mm
    scan = trainer.scan
    sigma_fn, _ = fit_model(scan, f_lib, "ls", "depth")
    refined = refine_depth(scan, f_lib, sigma_fn, "ls", radius=3)
    return {"raw": d, "flying": f1, "final": f2, "final_minmax_filter": f_lib, "refined": refined}


def main(argv=None) -> int:
    from slwarp.evaluation.metrics import depth_metrics

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default="bunny,torus,checker,rods")
    ap.add_argument("--rig", default="small")
    ap.add_argument("--cameras", default="linear", help="camera models (slwarp.sim.simulate.CAMERA_MODELS)")
    ap.add_argument("--variants", default="baseline,ls,dblur,ls+dblur,ls+dblur+sphere",
                    help=f"comma-separated; each 'baseline' or flags joined by '+' from {FLAGS}")
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--cache", default="/tmp/slwarp-study-fields")
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "train-ablation-cpu"))
    ap.add_argument("--markdown-only", action="store_true", help="rewrite <out>.md from <out>.json and stop")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    out = Path(args.out)
    if args.markdown_only:
        out.with_suffix(".md").write_text(render_markdown(json.loads(out.with_suffix(".json").read_text())))
        return 0
    out.parent.mkdir(parents=True, exist_ok=True)
    doc = {"date": DATE, "machine": platform.processor() or platform.machine(), "args": vars(args), "runs": []}
    if out.with_suffix(".json").is_file():  # keep rows of other (camera, scene, variant) combinations
        old = json.loads(out.with_suffix(".json").read_text())
        doc["runs"] = old.get("runs", [])
    for camera in args.cameras.split(","):
        for scene in args.scenes.split(","):
            scan, _ = simulate_study_scan(scene, args.rig, camera)
            gray = gray_code_yardstick(scan)
            rand = scan.select("rand*")
            for variant in args.variants.split(","):
                flags = set() if variant == "baseline" else set(variant.split("+"))
                if not flags <= set(FLAGS):
                    raise SystemExit(f"unknown variant {variant!r}: flags are {FLAGS}")
                t0 = time.perf_counter()
                train_scan, gamma = (linearise(rand, args.preset) if "gamma" in flags else (rand, 1.0))
                train_flags = flags - {"sphere"}  # extraction-only flag: the field is the one without it
                tv = "baseline" if not train_flags else "+".join(sorted(train_flags))
                trainer, cfg, train_s = train_cached(train_scan, args.preset, tv, Path(args.cache),
                                                     key=f"{args.rig}-{camera}-{scene}",
                                                     trainer_cls=make_trainer_cls(train_flags))
                depths = extract(trainer, cfg, flags)
                m = {k: depth_metrics(v, scan.gt_depth, scan.mask) for k, v in depths.items()}
                row = {"camera": camera, "scene": scene, "variant": variant, "metrics": m, "gamma": gamma,
                       "pattern_blur": trainer.renderer.pattern_blur, "blur_bins": getattr(trainer, "blur_bins", None),
                       "train_s": train_s, "seconds": time.perf_counter() - t0, "gray": gray}
                doc["runs"] = [r for r in doc["runs"] if (r["camera"], r["scene"], r["variant"]) != (camera, scene, variant)]
                doc["runs"].append(row)
                f = m["final"]
                print(f"{camera:7s} {scene:8s} {variant:22s} MAE {f['mae']:.3f} median {f['median']:.3f} >5mm "
                      f"{f['over_5mm']:.2%} complete {f['completeness']:.1%} (raw MAE {m['raw']['mae']:.3f}; "
                      f"GC7 {gray['GC(7) interp']['mae']:.3f}) {row['seconds']:.0f} s", flush=True)
                out.with_suffix(".json").write_text(json.dumps(doc, indent=1, default=float))
    md = render_markdown(doc)
    out.with_suffix(".md").write_text(md)
    print(md)
    return 0


def render_markdown(doc: dict) -> str:
    a = doc["args"]
    lines = ["# Training-level ablation of image-model changes (small rig, CPU)", "",
             "Rows accumulate over runs (each run replaces its own camera/scene/variant rows); the last run was "
             f"`python bench/train_ablation.py --scenes {a['scenes']} --cameras {a['cameras']} --variants {a['variants']} "
             f"--preset {a['preset']}` ({doc['date']}, CPU, one thread). Ours: the 6 random patterns of a random6+gray7 "
             "scan (pattern and noise seed 0); GC rows: gc-interp of the same scan's 7 and 6 most significant column "
             "bits. 'final': after the flying-pixel and photometric filters (each variant's own model); 'raw': the "
             "extracted depth inside the valid mask and depth range.", ""]
    runs = doc["runs"]
    for camera in dict.fromkeys(r["camera"] for r in runs):
        sel = [r for r in runs if r["camera"] == camera]
        scenes = list(dict.fromkeys(r["scene"] for r in sel))
        variants = list(dict.fromkeys(r["variant"] for r in sel))
        for key, stage, fmt, title in [("mae", "final", "{:.3f}", "MAE mm (the variant's own photometric filter)"), ("median", "final", "{:.3f}", "median |error| mm"),
                                       ("over_5mm", "final", "{:.2%}", "share > 5 mm"),
                                       ("completeness", "final", "{:.1%}", "completeness"),
                                       ("mae", "final_minmax_filter", "{:.3f}", "MAE mm with the baseline's photometric filter (min/max a, b, global blur)"),
                                       ("completeness", "final_minmax_filter", "{:.1%}", "completeness with the baseline's photometric filter"),
                                       ("mae", "raw", "{:.3f}", "raw MAE mm (before the filters)"),
                                       ("mae", "refined", "{:.3f}", "MAE mm after the photometric refinement (ls, depth blur, 7x7, +-3 mm) of the min/max-filtered depth"),
                                       ("median", "refined", "{:.3f}", "median |error| mm after the refinement"),
                                       ("over_5mm", "refined", "{:.2%}", "share > 5 mm after the refinement")]:
            if not any(stage in r["metrics"] for r in sel):
                continue
            rows = []
            for v in variants:
                vals = []
                for s in scenes:
                    hit = [r for r in sel if r["scene"] == s and r["variant"] == v]
                    # runs from before a stage existed (e.g. 'refined') show as nan
                    vals.append(hit[0]["metrics"].get(stage, {}).get(key, float("nan")) if hit else float("nan"))
                rows.append([v] + [fmt.format(x) for x in vals] + [fmt.format(float(np.nanmean(vals)))])
            if stage in ("final", "refined"):
                for g in ("GC(7) interp", "GC(6) interp"):
                    vals = [next(r for r in sel if r["scene"] == s)["gray"][g][key] for s in scenes]
                    rows.append([f"*{g}*"] + [fmt.format(x) for x in vals] + [fmt.format(float(np.mean(vals)))])
            lines += [f"## camera model `{camera}`: {title}", ""]
            lines += markdown_table(["variant"] + scenes + ["mean"], rows) + [""]
        fits = [[r["scene"], r["variant"], f"{r['pattern_blur']:.3f}", json.dumps([round(x, 2) for x in r["blur_bins"]["sigma"]]) if r["blur_bins"] else "-",
                 f"{r['gamma']:.2f}", f"{r['train_s']:.0f}"] for r in sel]
        lines += [f"## camera model `{camera}`: fitted blur, gamma, training time", ""]
        lines += markdown_table(["scene", "variant", "global sigma px", "depth-bin sigmas px", "gamma", "train s"], fits) + [""]
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
