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
`TrainingInterrupted` after saving a checkpoint (see slwarp.neural.training).
"""
from __future__ import annotations

import importlib
import json
import os
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import torch

from ..evaluation.outputs import (check_output_folder, staged_outputs, write_confidence, write_depth, write_mesh_ply,
                                  write_points_ply)
from ..scans.prefetch import rays_ahead
from .config import TrainConfig, save_config
from .depth_maps import depth_to_points
from .extraction import build_stages, extract_depth, fate_counts, pixel_fates
from .training import Trainer


# the field "lost the surface" when over this share of the lit pixels end without a depth inside the depth range
# (no surface, or one out of range) while the depth search, which looks only inside it, had found one on over this
# share of them; healthy runs lose under 3%. The losses seen on simulated scans (`fast`, 2026-11-27: 2 of 96 and 3 of 64
# runs of two sweeps) came from a failed CUDA-graph capture that broke the process's later runs, fixed in
# training.graph_step (bench/results/capture-failure-cuda.md); the rule stays for what else may make a field lose it.
LOST_SURFACE_SHARE = 0.5


def surface_shares(counts: dict, start_depth: np.ndarray | None) -> dict | None:
    """{"lost": share of the lit pixels without a depth in range, "searched": share of them the depth search gave a
    depth (None without a search)}, what lost_surface reads (None without lit pixels). counts: fate_counts of the
    depth map; start_depth: the depth search's map [H*W] or [H, W] (NaN: none), or None."""
    lit = sum(counts.values()) - counts.get("no_contrast", 0)
    if lit <= 0:
        return None
    lost = (counts.get("no_surface", 0) + counts.get("out_of_range", 0)) / lit
    searched = None
    if start_depth is not None:
        found = (torch.isfinite(start_depth).sum().item() if isinstance(start_depth, torch.Tensor)
                 else np.isfinite(np.asarray(start_depth)).sum())
        searched = float(found) / lit
    return {"lost": lost, "searched": searched}


def surface_is_lost(shares: dict | None) -> bool:
    """Whether surface_shares' `shares` say the field lost the surface: over LOST_SURFACE_SHARE of the lit pixels
    lost while the search, if there was one, had found a depth on over that share of them."""
    if shares is None:
        return False
    searched = shares["searched"]
    return shares["lost"] > LOST_SURFACE_SHARE and (searched is None or searched > LOST_SURFACE_SHARE)


def lost_surface(counts: dict, start_depth: np.ndarray | None) -> dict | None:
    """surface_shares' {"lost", "searched"} when the field lost the surface (surface_is_lost), else None."""
    shares = surface_shares(counts, start_depth)
    return shares if surface_is_lost(shares) else None


# the scene seems to lie outside the depth range when the depth search, which looks only inside it, found a depth on
# under this share of the lit pixels (healthy runs: 90% and more) and under half of them end with one in the map (a field
# trained there draws surfaces the confidence check mostly drops); lost_surface does not blame the field then, and
# without this rule nothing said why the map was empty
FEW_FOUND_SHARE = 0.25


def range_missed(counts: dict, shares: dict | None, with_depth: int) -> dict | None:
    """{"searched": share of the lit pixels the depth search gave a depth, "with_depth": share of them with a depth in
    the map} when the scene seems to lie outside the depth range (see FEW_FOUND_SHARE), else None. counts: fate_counts
    of the depth map; shares: surface_shares of it (None, or "searched" None without a search: nothing to say);
    with_depth: the map's pixels with a depth."""
    if shares is None or shares["searched"] is None:
        return None
    share = with_depth / (sum(counts.values()) - counts.get("no_contrast", 0))
    if shares["searched"] < FEW_FOUND_SHARE and share < 0.5:
        return {"searched": shares["searched"], "with_depth": share}
    return None


def range_missed_message(info: dict, depth_range) -> str:
    """One line for a user: what range_missed found and what to do."""
    near, far = depth_range
    return (f"the depth search found a depth inside the depth range {near:g}-{far:g} mm on only {info['searched']:.0%} "
            f"of the lit pixels, and {info['with_depth']:.0%} of them have one in the map: the scene seems to lie "
            "outside that range (give --depth-range NEAR,FAR in mm, or correct the scan's depth_range)")


def lost_surface_message(info: dict, depth_range) -> str:
    """One line for a user: what lost_surface found and what to do."""
    near, far = depth_range
    found = f", where the depth search had found one on {info['searched']:.0%}" if info["searched"] is not None else ""
    return (f"the field lost the surface: {info['lost']:.0%} of the lit pixels got no depth inside the depth range "
            f"{near:g}-{far:g} mm{found}; the depth map is not usable (a training failure: train again with another "
            "--seed, or with --preset accurate)")


@dataclass
class Reconstruction:
    """depth [H, W] mm (NaN invalid); mesh (extraction.surface.SurfaceMesh, mm: vertices, faces, and trimesh's
    attributes on first use, `.to_trimesh()`) or None; points [P, 3] mm; metrics (dict or
    None); timings (seconds per stage); trainer (the trained state); confidence [H, W] in [0, 1] (NaN where
    depth is; slwarp.neural.extraction.confidence); fate [H, W] uint8 (extraction.pixel_fates()'s index per pixel)."""

    depth: np.ndarray
    mesh: object
    points: np.ndarray
    metrics: dict | None
    timings: dict = field(default_factory=dict)
    trainer: Trainer | None = None
    confidence: np.ndarray | None = None
    fate: np.ndarray | None = None
    writer: "Finishing | None" = field(default=None, repr=False)  # write_in_background's, until wait_written

    def wait_written(self) -> None:
        """Wait for the output files being written in the background (reconstruct(write_in_background=True)); the
        write's error (OSError) when it failed, in which case none of this run's files appeared."""
        writer, self.writer = self.writer, None
        if writer is not None:
            writer.result()


def reconstruct(scan, config: TrainConfig, out_dir=None, resume: bool = False, depth_range=None,
                use_mask: bool = False, progress: bool = True, log_every_s: float | None = None,
                overwrite: bool = False, write_in_background: bool = False) -> Reconstruction:
    """Train the neural SDF on `scan` and extract its depth map (see module docstring).

    use_mask: also restrict the depth map to the scan's mask (by default only to the pixels lit with
    enough contrast in the images, the same information the classical decoders use). progress: a bar on a
    terminal, else a line every few seconds; log_every_s: progress lines every this many seconds in any case.
    resume / overwrite: continue out_dir's checkpoint / replace it (neither: a checkpoint there is refused).
    Errors a caller may handle per scan: ScanError, ConfigError, CheckpointError (RunMismatch, CheckpointExists),
    TrainingInterrupted, TrainingDiverged, OSError.

    write_in_background: return as soon as the depth map and its metrics are known, the files (and the final
    checkpoint) written and moved into out_dir by a thread; `Reconstruction.wait_written()` waits for them (a batch
    trains its next scan meanwhile: slwarp.batch.run_scans). The thread is not a daemon: an interpreter that exits
    finishes the files first.
    """
    out = check_output_folder(out_dir) if out_dir is not None else None
    args = (scan, config, out, resume, depth_range, use_mask, progress, log_every_s, overwrite)
    if out is None:
        return _reconstruct(*args)[0]
    if not write_in_background:
        with staged_outputs(out) as staging:
            res, jobs = _reconstruct(*args, staging)
            _write_files(res, jobs)
        return res
    (res, jobs), res.writer = _staged_in_background(out, lambda staging: _reconstruct(*args, staging),
                                                    lambda done: _write_files(*done))
    return res


class Finishing:
    """The rest of a reconstruction, going on in a thread: its depth map, metrics and files (reconstruct_in_background)
    or its files alone (reconstruct(write_in_background=True)). result() waits for it: what it returns (the
    Reconstruction, its files written, and its checkpoint), or the error that stopped it, in which case none of its
    files appeared."""

    def __init__(self, work):
        self._res, self._error = None, None

        def run():
            try:
                self._res = work()
            except BaseException as e:  # noqa: BLE001 - raised by result(), in the caller's thread
                self._error = e

        self._thread = threading.Thread(target=run, name="slwarp-finish")  # not a daemon: the files get written
        self._thread.start()

    def wait(self) -> None:
        """Wait for the thread to end, whatever its outcome (result() tells it)."""
        self._thread.join()

    def result(self):
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self._res


def reconstruct_in_background(scan, config: TrainConfig, out_dir, resume: bool = False, depth_range=None,
                              use_mask: bool = False, progress: bool = True, log_every_s: float | None = None,
                              overwrite: bool = False, after=None) -> Finishing:
    """reconstruct(...) into out_dir, returning as soon as the field is trained (here, on this thread): the depth map
    is extracted, measured and written into out_dir by a thread of its own (Finishing.result() waits for it). Why:
    on a GPU the extraction is mostly host work while the training keeps the GPU busy and the host idle, so a batch
    trains its next scan beside it. after: called first by that thread (a batch: the scan before has finished, so
    that one extraction at most runs beside a training). Errors of the training are raised here, the others by
    result()."""
    def finish(trained: _Trained) -> Reconstruction:
        if after is not None:
            t = time.perf_counter()
            after()
            trained.waited = time.perf_counter() - t
        res, jobs = _finish(trained)
        _write_files(res, jobs)
        return res

    args = (scan, config, check_output_folder(out_dir), resume, depth_range, use_mask, progress, log_every_s, overwrite)
    return _staged_in_background(args[2], lambda staging: _train(*args, staging), finish)[1]


def _staged_in_background(out, first, rest):
    """(first(staging), a Finishing of rest(that)): `first` runs here and `rest` in a thread, inside out's staged
    outputs (evaluation.outputs.staged_outputs), which appear once `rest` has returned; when either fails the staging
    folder goes (first's error raised here, rest's by Finishing.result())."""
    outputs = staged_outputs(out)
    staging = outputs.__enter__()
    try:
        done = first(staging)
    except BaseException:
        outputs.__exit__(*sys.exc_info())  # removes the staging folder (and re-raises a wrapped OSError)
        raise

    def work():
        try:
            value = rest(done)
        except BaseException as e:
            try:
                outputs.__exit__(type(e), e, e.__traceback__)  # removes the staging folder, re-raises (wrapped)
            except BaseException as wrapped:  # noqa: BLE001
                raise wrapped from None
            raise
        outputs.__exit__(None, None, None)
        return value

    return done, Finishing(work)


def _import_in_background(*modules) -> None:
    """Import these modules (None: skipped) in a daemon thread: scikit-image's marching cubes, which the CPU's
    extraction needs, while the CPU trains (on a GPU host trimesh imported so beside the training slowed its first
    steps: the mesh no longer needs it, extraction.surface.SurfaceMesh). An import the main thread starts
    meanwhile waits for this one on the module's lock."""
    names = [m for m in modules if m is not None and m not in sys.modules]

    def run():
        for name in names:
            try:
                importlib.import_module(name)
            except Exception:  # noqa: BLE001 - the main thread's own import reports it, where it is needed
                pass

    if names:
        threading.Thread(target=run, name="slwarp-imports", daemon=True).start()


def _reconstruct(scan, config, out, resume, depth_range, use_mask, progress, log_every_s, overwrite, staging=None,
                 retry=True):
    """reconstruct's work: (the Reconstruction, the jobs that write its files into `staging`: _output_jobs; None
    without a staging folder); the final checkpoint goes to out/train in a thread (Trainer.wait_checkpoint). Where
    the field lost the surface (lost_surface) and config.runtime.retry_lost_surface, it trains once more from the
    start with the next seed and returns that run, its timings' "lost_surface_retry" saying what the first found."""
    return _finish(_train(scan, config, out, resume, depth_range, use_mask, progress, log_every_s, overwrite, staging,
                          retry))


@dataclass
class _Trained:
    """A trained field before its extraction (_train's result, _finish's input): the run's arguments, its stages
    and its clock (t0 start, t1 set up, t2 trained; perf_counter seconds)."""

    scan: object
    config: TrainConfig
    out: object
    depth_range: object
    use_mask: bool
    progress: bool
    log_every_s: float | None
    staging: object
    retry: bool
    trainer: Trainer
    stages: list
    t0: float
    t1: float
    t2: float
    waited: float = 0.0  # seconds between t2 and the extraction's start spent waiting (for a batch's scan before)


def _train(scan, config, out, resume, depth_range, use_mask, progress, log_every_s, overwrite, staging=None,
           retry=True) -> _Trained:
    """The first half of _reconstruct: the trainer set up and trained, on this thread."""
    t0 = time.perf_counter()
    stages = build_stages(config.extraction)  # a stage list that cannot run fails before training
    rays_ahead(scan.camera)  # the depth search's ray grid, computed while the trainer sets up
    trainer = Trainer(scan, config, out_dir=out / "train" if out is not None else None, resume=resume,
                      depth_range=depth_range, progress=progress or bool(log_every_s), progress_interval_s=log_every_s,
                      overwrite=overwrite)
    t1 = time.perf_counter()
    if trainer.device.type == "cpu":  # the CPU's marching cubes (the mesh needs no trimesh: SurfaceMesh)
        _import_in_background("skimage.measure")
    trainer.checkpoint_in_background = True  # the final checkpoint is written beside the extraction
    trainer.train()
    if trainer.device.type == "cuda":  # this thread's stream: the training's work (another thread may extract)
        torch.cuda.current_stream(trainer.device).synchronize()
    return _Trained(scan, config, out, depth_range, use_mask, progress, log_every_s, staging, retry, trainer, stages,
                    t0, t1, time.perf_counter())


def _finish(trained: _Trained):
    """The second half of _reconstruct: the depth map extracted from the trained field, its metrics and the jobs that
    write its files (or, where the field lost the surface, the retry's); on any thread."""
    from ..evaluation.metrics import depth_metrics

    scan, config, trainer, use_mask = trained.scan, trained.config, trained.trainer, trained.use_mask
    t0, t1, t2 = trained.t0, trained.t1, trained.t2
    valid = trainer.renderer.valid_map.cpu().numpy()
    if use_mask and scan.mask is not None:
        valid &= scan.mask
    try:
        depth, confidence, mesh, ext_t, fate = extract_depth(
            trainer, valid, progress=trained.progress, stages=trained.stages,
            region=scan.mask if use_mask and scan.mask is not None else None)
    except BaseException:
        _settle_checkpoint(trainer)
        raise
    t3 = time.perf_counter()  # the depth map is done: what follows is outputs and, with ground truth, its metrics
    points = depth_to_points(depth, scan.camera)
    metrics = None
    if scan.gt_depth is not None:
        metrics = depth_metrics(depth, scan.gt_depth, scan.mask)
    waited = trained.waited  # not this scan's work: left out of its depth map's and its total time
    timings = {"setup_s": t1 - t0, "train_s": t2 - t1, "depth_map_s": t3 - t0 - waited,
               "train_wall_s_total": trainer.elapsed,
               "iterations": trainer.iteration, "setup_phases_s": trainer.setup_phases,
               "first_steps_s": trainer.first_steps, "pattern_halo": trainer.halo_share,
               "pattern_halo_fit": trainer.halo_fit, "lens_schedule": trainer.lens_schedule, **ext_t,
               "pixels": fate_counts(fate), "total_s": time.perf_counter() - t0 - waited,
               "waited_before_extraction_s": waited}
    # what the lost-surface rule read, and whether the step ran as a CUDA graph (both for study: bench.accuracy_sweep)
    shares = timings["surface_shares"] = surface_shares(timings["pixels"], trainer.init_depth)
    timings["graph_captured"] = trainer.graph_captured
    timings["surface_lost"] = shares if surface_is_lost(shares) else None
    timings["range_missed"] = range_missed(timings["pixels"], shares, int(np.isfinite(depth).sum()))
    if timings["surface_lost"] and trained.retry and config.runtime.retry_lost_surface:
        _settle_checkpoint(trainer)  # the next run replaces it
        seed = config.runtime.seed
        res, jobs = _reconstruct(scan, config.with_options(seed=seed + 1), trained.out, False, trained.depth_range,
                                 use_mask, trained.progress, trained.log_every_s, True, trained.staging, retry=False)
        res.timings["lost_surface_retry"] = {"seed": seed, **timings["surface_lost"], "total_s": timings["total_s"]}
        return res, jobs
    jobs = None
    if trained.staging is not None:
        jobs = _output_jobs(trained.staging, scan, config, trainer, depth, confidence, mesh, points, metrics, fate,
                            timings)
    return Reconstruction(depth, mesh, points, metrics, timings, trainer, confidence, fate), jobs


def _write_files(res: Reconstruction, jobs: list) -> None:
    """The run's files (_output_jobs), then its final checkpoint (Trainer.wait_checkpoint); when a file fails, the
    checkpoint settles before the error goes on."""
    try:
        _write_outputs(jobs)
    except BaseException:
        _settle_checkpoint(res.trainer)
        raise
    res.trainer.wait_checkpoint()


def _settle_checkpoint(trainer) -> None:
    """Wait for the trainer's checkpoint being written, its own error aside (the caller raises the first failure): a
    failed run returns with its checkpoint on disk, never half-written."""
    try:
        trainer.wait_checkpoint()
    except Exception:  # noqa: BLE001 - the error being raised matters more; the write left the last good file
        pass


def _write_outputs(jobs: list) -> None:
    """Run the jobs of _output_jobs concurrently. Each file is independent, and the PNG encoders, numpy and the file
    writes leave the interpreter free most of the time, so the pictures, the point cloud and the metrics overlap
    instead of queuing; this returns when all are written (the first failure raised)."""
    with ThreadPoolExecutor(max_workers=min(len(jobs), os.cpu_count() or 1)) as pool:
        for done in [pool.submit(job) for job in jobs]:
            done.result()


def _output_jobs(out, scan, config, trainer, depth, confidence, mesh, points, metrics, fate, timings) -> list:
    """The callables that write every output file of a reconstruction into the folder `out`."""
    from ..evaluation.metrics import confidence_metrics, error_map, metrics_document
    from ..evaluation.viz import save_confidence_map, save_depth_color, save_fate_map, save_map_with_colorbar

    has_gt = scan.gt_depth is not None and np.isfinite(scan.gt_depth).any()
    rng = (np.nanpercentile(scan.gt_depth, 1), np.nanpercentile(scan.gt_depth, 99)) if has_gt else None

    def metrics_file():
        doc = metrics_document(metrics, method="neural-sdf", scan=scan.source,
                               frames=list(scan.names[: trainer.n_frames]),
                               mask="scan mask" if scan.mask is not None else "none",
                               confidence={"kind": config.extraction.confidence,
                                           **confidence_metrics(depth, confidence, scan.gt_depth, scan.mask)})
        (out / "metrics.json").write_text(json.dumps(doc, indent=2, default=float) + "\n")

    def error_picture():  # a job of its own: with metrics.json it was the longest job (0.35 s, one H200 host)
        save_map_with_colorbar(out / "error_map.png", error_map(depth, scan.gt_depth, scan.mask),
                               f"|depth error|, MAE {metrics['mae']:.3f} mm", "mm", value_range=(0.0, 5.0), cmap="inferno")

    def config_file():
        fitted = {"pattern_blur_px": trainer.renderer.pattern_blur, "pattern_blur_fit_mse": trainer.blur_fit,
                  "pattern_halo": trainer.halo_share, "pattern_halo_fit": trainer.halo_fit,
                  "lens_schedule": trainer.lens_schedule,
                  "depth_search": {k: v for k, v in (trainer.search_info or {}).items() if k != "pattern_blur_fit"}}
        save_config(out / "config.yaml", config, fitted)

    # the longest first (the pool may have fewer workers than jobs): the metrics' sorts, then the pictures
    jobs = [metrics_file, error_picture] if metrics is not None else []
    jobs += [lambda: write_depth(out, depth),
             lambda: save_depth_color(out / "depth_color.png", depth, rng),
             lambda: write_points_ply(out / "points.ply", points, scan.images.max(0)[np.isfinite(depth)]),
             lambda: trainer.save_history(out),
             # the confidence map beside the depth map
             lambda: write_confidence(out, confidence),
             lambda: save_confidence_map(out / "confidence.png", confidence, f"confidence ({config.extraction.confidence})"),
             # why pixels have no depth (or a repaired / filled one), as a picture
             lambda: save_fate_map(out / "pixel_fate.png", fate, pixel_fates()),
             lambda: (out / "timings.json").write_text(json.dumps(timings, indent=1)),
             config_file]
    if mesh is not None:
        jobs.append(lambda: write_mesh_ply(out / "mesh.ply", mesh))
    return jobs
