"""The neural SDF method end to end: train on a scan, extract the surface, write the depth map and friends.

    result = reconstruct(scan, preset("paper"), out_dir="out")
    result.depth      # [H, W] mm, NaN where no surface
    result.metrics    # when the scan has ground truth

Outputs written to out_dir: depth.npy, depth.png (uint16, 0.1 mm), depth_color.png, confidence.npy (float32 in
[0, 1], NaN where no depth) + confidence.png, pixel_fate.png (what became of each pixel: measured, repaired,
filled, or the stage that left it without depth; counts in timings.json "pixels"), mesh.ply, points.ply,
history.json + loss.png, timings.json, config.yaml (the run's TrainConfig and the values it fitted; `--config`
reads it back), and metrics.json + error_map.png when the scan has ground truth;
train/checkpoint.pt holds the resumable training state. The outputs appear together or not at all
(`evaluation.outputs.staged_outputs`); `resume` continues the checkpoint of the same run (else RunMismatch), and a
new run into a folder with a checkpoint needs `overwrite=True` (else CheckpointExists). SIGINT/SIGTERM raise
`TrainingInterrupted` after saving a checkpoint (see slwarp.neural.train).
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from ..evaluation.outputs import (check_output_folder, staged_outputs, write_confidence, write_depth, write_mesh_ply,
                                  write_points_ply)
from .extraction.surface import (denoise_depth, depth_to_points, extract_mesh, flying_pixel_filter, mesh_depth, readmit_edge_pixels,
                      sphere_trace_depth)
from .confidence import pattern_model_inputs
from .extraction.confidence import depth_confidence
from .pattern_model import fill_uniform_codes, refine_where_model_fits, refinement_generalises
from .search import doubt_by_search, grow_repair, repair_by_search
from .config import TrainConfig, save_config
from .train import Trainer


@dataclass
class Reconstruction:
    """depth [H, W] mm (NaN invalid); mesh (trimesh, mm) or None; points [P, 3] mm; metrics (dict or
    None); timings (seconds per stage); trainer (the trained state); confidence [H, W] in [0, 1] (NaN where
    depth is; slwarp.neural.confidence)."""

    depth: np.ndarray
    mesh: object
    points: np.ndarray
    metrics: dict | None
    timings: dict = field(default_factory=dict)
    trainer: Trainer | None = None
    confidence: np.ndarray | None = None
    fate: np.ndarray | None = None


# what became of each camera pixel at extraction (the values of Extraction.fate): with a depth, "measured" (the
# field's, refined), "repaired" (a depth search's, slwarp.neural.search) or "filled" (the uniform-code fill); without,
# the stage that left it without one: "no_contrast" (outside the lit-with-contrast map the decoders also use:
# shadows, dark albedo, codes that never change), "no_surface" (no mesh hit), then the filters in their order
PIXEL_FATES = ("measured", "repaired", "filled", "no_contrast", "no_surface", "out_of_range", "flying_pixel",
               "low_confidence", "search_doubt")
FATE = {name: i for i, name in enumerate(PIXEL_FATES)}


def fate_counts(fate: np.ndarray) -> dict:
    """{fate name: pixels} of a fate map [H, W] (indices into PIXEL_FATES), every fate named."""
    counts = np.bincount(np.asarray(fate).ravel(), minlength=len(PIXEL_FATES))
    return {name: int(c) for name, c in zip(PIXEL_FATES, counts)}


class Extraction(NamedTuple):
    """extract_depth's result: depth [H, W] mm and confidence [H, W] in [0, 1] (NaN where no depth), the mesh
    (trimesh, mm), timings (seconds per stage and counts, JSON-safe) and fate [H, W] uint8 (the index in
    PIXEL_FATES of what became of each pixel)."""

    depth: np.ndarray
    confidence: np.ndarray
    mesh: object
    timings: dict
    fate: np.ndarray


def extract_depth(trainer: Trainer, valid: np.ndarray | None = None, progress: bool = False,
                  region: np.ndarray | None = None) -> Extraction:
    """An Extraction (depth [H, W], confidence [H, W], mesh, timings, fate [H, W]) from a trained field as its
    config's extraction section says: marching cubes, then the mesh ray-cast (or sphere tracing when depth_method
    is 'sphere'), the depth range, the flying-pixel filter (with `edge_readmit` the edge pixels on one side of their
    edge given back: extract.readmit_edge_pixels; timings["edge_readmitted"]), the confidence map
    (`extraction.confidence`) and the pixels below
    `extraction.min_confidence` dropped, the search repair when `search_repair` is on (holes filled, contradicted
    depths replaced: slwarp.neural.search.repair_by_search) or else its doubt rule alone when `search_doubt` is on
    (slwarp.neural.search.doubt_by_search), then the photometric refinement of the depth when refine_range > 0
    (the confidence is that of the depth before refinement), skipped when `refine_max_misfit` > 0 and the pattern
    model's misfit there is above it (`pattern_model.refine_where_model_fits`; timings["refine_misfit"],
    timings["refined"]), kept with `refine_check` only if it explains held-out frames better (`pattern_model.refinement_generalises`; timings["refine_check"]), and with `uniform_fill` the lit
    pixels without contrast inside `region` (default: all) that the field's predicted codes explain
    (`pattern_model.fill_uniform_codes`), with `repair_grow` the repair's changes spread to neighbours that kept
    another surface's depth (`search.grow_repair`; timings["repair_grown"]), and last, with denoise_radius > 0, an
    edge-aware plane fit over each pixel's window (`extract.denoise_depth`; depth changes, no pixel added or lost);
    depth is otherwise kept only inside `valid`. Both maps are NaN where no depth. timings["dropped"] counts the
    pixels each stage left without depth (no_surface inside `valid`, out_of_range, flying_pixel, low_confidence,
    search_doubt); timings["filled_uniform"] the pixels the uniform-code fill added; `fate` says the same per pixel
    (PIXEL_FATES)."""
    ex = trainer.cfg.extraction
    t0 = time.perf_counter()
    cam = trainer.scan.camera
    field_ = trainer.field.eval()
    mesh = extract_mesh(field_, trainer.volume, ex.mc_resolution, trainer.device, progress=progress,
                        depth_range=trainer.depth_range)
    t1 = time.perf_counter()
    if ex.depth_method == "sphere":
        depth = sphere_trace_depth(field_, cam, trainer.depth_range, trainer.device, valid=valid)
    else:
        depth = mesh_depth(mesh, cam, trainer.device)
    field_depth = depth.copy() if ex.uniform_fill else None  # for the pixels without contrast
    if valid is not None:
        depth = np.where(valid, depth, np.nan).astype(np.float32)
    # why pixels end without depth: per pixel (fate) and counted per stage over the pixels that still had one before it
    fate = np.full(depth.shape, FATE["measured"], np.uint8)
    if valid is not None:
        fate[~valid] = FATE["no_contrast"]
    fate[(fate == FATE["measured"]) & ~np.isfinite(depth)] = FATE["no_surface"]
    dropped = {"no_surface": int((fate == FATE["no_surface"]).sum())}

    def lost(stage: str, before: np.ndarray) -> None:
        """The pixels with depth in `before` that have none now: their fate and the stage's count."""
        gone = np.isfinite(before) & ~np.isfinite(depth)
        fate[gone] = FATE[stage]
        dropped[stage] = int(gone.sum())

    def rescored(changed: np.ndarray, depth: np.ndarray, confidence: np.ndarray) -> np.ndarray:
        """The confidence map with the pixels whose depth a stage changed scored again at their new depth."""
        if not changed.any():
            return confidence
        new = depth_confidence(trainer, np.where(changed, depth, np.nan).astype(np.float32), ex.confidence)
        return np.where(changed, new, confidence).astype(np.float32)

    # the frames for the pattern model's confidences and the depth searches: on a GPU its own tensors
    model_inputs = pattern_model_inputs(trainer)
    near, far = trainer.depth_range
    before = depth.copy()
    depth[(depth < near) | (depth > far)] = np.nan
    lost("out_of_range", before)
    readmitted = 0
    if ex.edge_filter > 0:
        before = depth
        depth = flying_pixel_filter(depth, cam, ex.edge_filter, device=trainer.device)
        if ex.edge_readmit:
            # the edge pixels on one side of the edge, whose own codes confirm them (extract.readmit_edge_pixels)
            back = readmit_edge_pixels(before, depth, cam, ex.edge_filter,
                                       lambda d: depth_confidence(trainer, d, "photometric"),
                                       min_support=ex.edge_readmit_support,
                                       min_confidence=ex.edge_readmit_confidence)
            depth = np.where(back, before, depth).astype(np.float32)
            readmitted = int(back.sum())
        lost("flying_pixel", before)
    field_.train()
    t2 = time.perf_counter()
    # confidence (slwarp.neural.confidence): the map beside the depth, and the filter of the pixels below min_confidence
    confidence = depth_confidence(trainer, depth, ex.confidence)
    if ex.min_confidence > 0:
        drop = ~(confidence >= ex.min_confidence)
        before = depth.copy()
        depth[drop] = np.nan
        confidence[drop] = np.nan
        lost("low_confidence", before)
    t3 = time.perf_counter()
    repair_s, repair = 0.0, None
    if (ex.search_repair or ex.search_doubt) and valid is not None:
        search_inputs = (cam, trainer.scan.projector, *model_inputs, trainer.depth_range, valid)
        search_options = dict(step_mm=trainer.cfg.init.search_step_mm, device=trainer.device)
        if ex.search_repair:
            # where a per-pixel depth search contradicts the field or fills its holes (thin parts it missed):
            # slwarp.neural.search.repair_by_search
            before = depth
            depth, repair = repair_by_search(depth, *search_inputs, ex.min_confidence,
                                             min_component=ex.repair_min_component, **search_options)
            # no flying-pixel filter on the changed pixels: a search has no smoothness to bend it across a depth
            # edge, and a thin part is all edge
            changed = np.isfinite(depth) & ~(depth == before)
            fate[changed] = FATE["repaired"]
            confidence = rescored(changed, depth, confidence)
            repair["kept"] = int(changed.sum())
        else:
            # only the repair's doubt rule: drop what a search contradicts and the codes do not support
            before = depth
            depth, repair = doubt_by_search(depth, *search_inputs, **search_options)
        confidence[~np.isfinite(depth)] = np.nan
        dropped["search_doubt"] = repair.get("dropped", 0)
        fate[np.isfinite(before) & ~np.isfinite(depth)] = FATE["search_doubt"]
        repair_s = time.perf_counter() - t3
        t3 = time.perf_counter()
    check, misfit, refined_applied = None, None, False
    if ex.refine_range > 0:
        # the images as the pattern model's inputs hold them (on a GPU the renderer's tensors: no upload per use)
        refine_inputs = (cam, trainer.scan.projector, model_inputs[0], trainer.scan.patterns[: trainer.n_frames],
                         ex.refine_range)
        # with refine_max_misfit: not where the model misses part of the optics (a camera response, real lenses),
        # whose errors the refinement would fit instead of the surface
        refined, misfit = refine_where_model_fits(depth, *refine_inputs, ex.refine_max_misfit, device=trainer.device)
    if ex.refine_range > 0 and not (misfit is not None and misfit > ex.refine_max_misfit):
        if ex.refine_check:
            # a refinement that fits the model's errors explains a held-out frame worse: keep the depth then
            check = refinement_generalises(depth, *refine_inputs, device=trainer.device)
        refined_applied = check is None or check["keep"]
        depth = refined if refined_applied else depth
    t4 = time.perf_counter()
    filled = None
    if ex.uniform_fill:
        depth, fill_confidence, filled = fill_uniform_codes(
            depth, field_depth, trainer.renderer.valid_map.cpu().numpy(), cam, trainer.scan.projector,
            trainer.scan.images[: trainer.n_frames], trainer.renderer.rendered_patterns.detach().cpu().numpy(),
            trainer.depth_range, ex.min_confidence, region=region)
        confidence = np.where(filled, fill_confidence, confidence).astype(np.float32)
        fate[filled] = FATE["filled"]
    t5 = time.perf_counter()
    grown = None
    if ex.repair_grow and ex.search_repair and valid is not None:
        # pixels beside the repaired ones that kept another surface's depth by a chance fit of their codes:
        # slwarp.neural.search.grow_repair (after the refinement, so that the repaired depths it spreads are refined)
        depth, grown = grow_repair(depth, fate == FATE["repaired"], cam, trainer.scan.projector, *model_inputs)
        if grown.any():
            fate[grown] = FATE["repaired"]
            confidence = rescored(grown, depth, confidence)
    t6 = time.perf_counter()
    if ex.denoise_radius > 0:
        # last: the field's fine-scale noise, as a plane fit over each pixel's window of one surface (extract.denoise_depth)
        depth = denoise_depth(depth, cam, ex.denoise_radius, ex.denoise_footprints, device=trainer.device)
    return Extraction(depth, confidence, mesh, {"marching_cubes_s": t1 - t0, "depth_s": t2 - t1,
                                     "confidence_s": t3 - t2 - repair_s, "repair_s": repair_s, "repair": repair,
                                     "refine_s": t4 - t3, "refine_misfit": misfit,
                                     "refined": refined_applied,
                                     "refine_check": check, "fill_s": t5 - t4,
                                     "filled_uniform": int(filled.sum()) if filled is not None else 0,
                                     "grow_s": t6 - t5, "denoise_s": time.perf_counter() - t6,
                                     "repair_grown": int(grown.sum()) if grown is not None else 0,
                                     "edge_readmitted": readmitted, "dropped": dropped}, fate)


def reconstruct(scan, config: TrainConfig, out_dir=None, resume: bool = False, depth_range=None,
                use_mask: bool = False, progress: bool = True, log_every_s: float | None = None,
                overwrite: bool = False) -> Reconstruction:
    """Train the neural SDF on `scan` and extract its depth map (see module docstring).

    use_mask: also restrict the depth map to the scan's mask (by default only to the pixels lit with
    enough contrast in the images, the same information the classical decoders use). progress: a bar on a
    terminal, else a line every few seconds; log_every_s: progress lines every this many seconds in any case.
    resume / overwrite: continue out_dir's checkpoint / replace it (neither: a checkpoint there is refused).
    Errors a caller may handle per scan: ScanError, ConfigError, CheckpointError (RunMismatch, CheckpointExists),
    TrainingInterrupted, TrainingDiverged, OSError.
    """
    out = check_output_folder(out_dir) if out_dir is not None else None
    if out is None:
        return _reconstruct(scan, config, None, resume, depth_range, use_mask, progress, log_every_s, overwrite)
    with staged_outputs(out) as staging:
        return _reconstruct(scan, config, out, resume, depth_range, use_mask, progress, log_every_s, overwrite, staging)


def _reconstruct(scan, config, out, resume, depth_range, use_mask, progress, log_every_s, overwrite, staging=None):
    """reconstruct's work: the checkpoint in out/train, the other outputs written into `staging`."""
    from ..evaluation.metrics import confidence_metrics, depth_metrics, error_map, metrics_document
    from ..evaluation.viz import save_confidence_map, save_depth_color, save_fate_map, save_map_with_colorbar

    t0 = time.perf_counter()
    trainer = Trainer(scan, config, out_dir=out / "train" if out is not None else None, resume=resume,
                      depth_range=depth_range, progress=progress or bool(log_every_s), progress_interval_s=log_every_s,
                      overwrite=overwrite)
    t1 = time.perf_counter()
    trainer.train()
    if trainer.device.type == "cuda":
        torch.cuda.synchronize(trainer.device)
    t2 = time.perf_counter()
    valid = trainer.renderer.valid_map.cpu().numpy()
    if use_mask and scan.mask is not None:
        valid &= scan.mask
    depth, confidence, mesh, ext_t, fate = extract_depth(trainer, valid, progress=progress,
                                                         region=scan.mask if use_mask and scan.mask is not None else None)
    t3 = time.perf_counter()  # the depth map is done: what follows is outputs and, with ground truth, its metrics
    points = depth_to_points(depth, scan.camera)
    metrics = None
    if scan.gt_depth is not None:
        metrics = depth_metrics(depth, scan.gt_depth, scan.mask)
    timings = {"setup_s": t1 - t0, "train_s": t2 - t1, "depth_map_s": t3 - t0, "train_wall_s_total": trainer.elapsed,
               "iterations": trainer.iteration, **ext_t, "pixels": fate_counts(fate), "total_s": time.perf_counter() - t0}
    if staging is not None:
        out = staging
        write_depth(out, depth)
        rng = (np.nanpercentile(scan.gt_depth, 1), np.nanpercentile(scan.gt_depth, 99)) if scan.gt_depth is not None and np.isfinite(scan.gt_depth).any() else None
        save_depth_color(out / "depth_color.png", depth, rng)
        if mesh is not None:
            write_mesh_ply(out / "mesh.ply", mesh)
        write_points_ply(out / "points.ply", points, scan.images.max(0)[np.isfinite(depth)])
        trainer.save_history(out)
        if metrics is not None:
            doc = metrics_document(metrics, method="neural-sdf", scan=scan.source,
                                   frames=list(scan.names[: trainer.n_frames]), mask="scan mask" if scan.mask is not None else "none",
                                   confidence={"kind": config.extraction.confidence,
                                               **confidence_metrics(depth, confidence, scan.gt_depth, scan.mask)})
            (out / "metrics.json").write_text(json.dumps(doc, indent=2, default=float) + "\n")
            save_map_with_colorbar(out / "error_map.png", error_map(depth, scan.gt_depth, scan.mask),
                                   f"|depth error|, MAE {metrics['mae']:.3f} mm", "mm", value_range=(0.0, 5.0), cmap="inferno")
        # the confidence map beside the depth map
        write_confidence(out, confidence)
        save_confidence_map(out / "confidence.png", confidence, f"confidence ({config.extraction.confidence})")
        # why pixels have no depth (or a repaired / filled one), as a picture
        save_fate_map(out / "pixel_fate.png", fate, PIXEL_FATES)
        (out / "timings.json").write_text(json.dumps(timings, indent=1))
        fitted = {"pattern_blur_px": trainer.renderer.pattern_blur, "pattern_blur_fit_mse": trainer.blur_fit,
                  "depth_search": {k: v for k, v in (trainer.search_info or {}).items() if k != "pattern_blur_fit"}}
        save_config(out / "config.yaml", config, fitted)
    return Reconstruction(depth, mesh, points, metrics, timings, trainer, confidence, fate)
