"""Training the neural SDF on a scan: the paper's schedule, incremental mode, checkpoints, progress.

    trainer = Trainer(scan, preset("paper"), out_dir="run")     # preset: slwarp.neural.config
    trainer.train()                 # resumable: Trainer(..., resume=True) continues from run/checkpoint.pt
    field = trainer.field           # x [..., 3] mm -> sdf mm

`Trainer` orchestrates; the parts live beside it in slwarp.neural.training. The start (slwarp.neural.start): the
working volume of the pixels lit with contrast, the field and renderer, the depth search's starting map and the
fitted pattern blur. Schedule (training.schedule; TrainConfig.schedule): lambda_sc = 0 for the first `sc_start`
iterations, then `lambda_sc`; lambda_reg throughout; Adam at a constant learning rate (or cosine decay). Before it
(init.method "search", the default), `init.iters` warm-up iterations pull the volume-rendered depth onto a
depth-search map (slwarp.neural.start.search): the photometric loss is not convex in depth, and NeuS's sphere
initialisation leaves surfaces hundreds of mm from the truth stuck in other minima (measured: 232 mm MAE on the
small-rig bunny without it). The loss (training.terms): with init.surface_weight > 0 the warm-up also puts the
field's zero level at the map's points (`MapTerms.surface_term`), and init.surface_after > 0 keeps that term after
the warm-up where the field lost a surface in front of the one it shows (thin parts: bench/thin_stages.py);
init.free_space > 0 adds the opposite after the warm-up: where the field shows a surface in front of the map's, its
samples before the map's point are pushed out of the solid (`MapTerms.free_space_term`: gaps and background the field
bridged). Incremental mode (paper Fig. 8): start with `start_frames` frames and add the next one every `add_every`
iterations without restarting; `Trainer.add_frames` lets a caller add captured frames to a running optimisation.

Checkpoints (`out_dir/checkpoint.pt`; training.checkpoint: tensors and plain data, read without unpickling
anything else) record the run's identity (`run_identity`: the frames by name and content digest, the depth range, a
digest of the calibration and every option that is not `resumable`); `resume=True` refuses a checkpoint of another
run (`RunMismatch`, naming each difference), and a new run refuses to replace an existing checkpoint unless
`overwrite=True` (`CheckpointExists`). SIGINT/SIGTERM during `train()` save a checkpoint at the next step boundary and
raise `TrainingInterrupted` (exit status 130/143 on the command line; training.stops).

The hash-grid field (field.kind "hashgrid"): Adam groups for its tables (grid_table_lr_factor x lr), its MLP
and the NeuS variance (lr), all following the schedule's factor; its levels switch on coarse to fine
(`active_levels`) through a device-side count, so a captured CUDA graph is replayed unchanged
(training.graph_step: the step captured once and replayed on CUDA).

Repeatability: every random draw (pixel batches, ray jitter) comes from one torch.Generator seeded by
`runtime.seed` and saved in checkpoints, so a resumed run continues exactly as an uninterrupted one would.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import os
import threading
import time
from pathlib import Path

import numpy as np
import torch

from ...devices import torch_device, with_index
from ...scans.scanner import with_halo
from ..config import TrainConfig
from ..fields import Volume
from ..pattern_model import fit_halo, halo_light
from ..start import (checked_depth_range, doubtful_pixels, fit_blur, frames_at_start, narrowed_range, search_start,
                     searches, set_process_flags, start_field, start_renderer, surface_depth, surface_terms_on,
                     working_volume)
from . import schedule
from .checkpoint import (CheckpointError, CheckpointExists, RunMismatch, check_field, identity_differences,
                         make_state, read_checkpoint, restore, run_identity, write_checkpoint)
from .adam import Adam
from .graph_step import GraphedStep
from .history import History
from .progress import Progress
from .stops import StopSignals, TrainingDiverged, TrainingInterrupted
from .terms import MapTerms, free_space_weights, step_loss, surface_term_weights

__all__ = ["Trainer", "surface_term_weights", "free_space_weights", "TrainingDiverged", "TrainingInterrupted",
           "CheckpointError", "CheckpointExists", "RunMismatch", "History", "run_identity", "pattern_model_inputs"]


def _with_frames(scan, n: int, images, patterns) -> tuple:
    """(the scan with images [k, H, W] and patterns [k, Hp, Wp] inserted after its first n frames, named
    "added<i>"; k); ValueError when they do not fit the camera and projector."""
    cam, prj = scan.camera, scan.projector
    images = np.asarray(images, np.float32).reshape(-1, cam.height, cam.width)
    patterns = np.asarray(patterns, np.float32)
    if patterns.shape[1:] != (prj.height, prj.width) or len(patterns) != len(images):
        raise ValueError(f"add_frames: {len(images)} images need as many patterns of {prj.width}x{prj.height} px, "
                         f"got {patterns.shape}")
    names = [f"added{len(scan) + i}" for i in range(len(images))]
    return dataclasses.replace(scan, images=np.concatenate([scan.images[:n], images, scan.images[n:]]),
                               patterns=np.concatenate([scan.patterns[:n], patterns, scan.patterns[n:]]),
                               names=scan.names[:n] + names + scan.names[n:]), len(images)


def _held_by_terms(name: str, doc: str) -> property:
    """A Trainer attribute that lives in its MapTerms (`Trainer.terms`)."""
    return property(lambda self: getattr(self.terms, name), lambda self, value: setattr(self.terms, name, value),
                    doc=doc)


def pattern_model_inputs(trainer) -> tuple:
    """(images [N, H, W], patterns as rendered [N, Hp, Wp]) of a trainer's frames for the pattern model
    (photometric_confidence, the depth searches): on a GPU the renderer's own tensors, so that the model runs
    there (pattern_model.residual._residual_on_device); else numpy, on the host."""
    patterns = trainer.renderer.rendered_patterns.detach()
    if trainer.device.type == "cuda":
        cam = trainer.scan.camera
        return trainer.renderer.images_flat.t().reshape(-1, cam.height, cam.width), patterns
    return trainer.scan.images[: trainer.n_frames], patterns.cpu().numpy()


FIRST_STEPS = 4  # steps whose host time a run records (Trainer.first_steps): two plain steps, the capture, a replay


def _on_host(state):
    """A copy of a checkpoint's state with every tensor in host memory (a snapshot a thread may write)."""
    if isinstance(state, torch.Tensor):
        return state.detach().to("cpu", copy=True)
    if isinstance(state, dict):
        return {k: _on_host(v) for k, v in state.items()}
    if isinstance(state, (list, tuple)):
        return type(state)(_on_host(v) for v in state)
    return state


def seen_through_lens(scan, share: float, sigma: float, halo: np.ndarray | None = None):
    """The scan with its patterns as a lens with a halo of `share` over `sigma` projector px shows them
    (scans.scanner.with_halo; halo: the patterns' blur when the caller has it); the scan itself without a halo."""
    if share <= 0:
        return scan
    return dataclasses.replace(scan, patterns=with_halo(scan.patterns, share, sigma, halo=halo))


class _SetupClock:
    """Seconds between successive marks of the trainer's set-up (Trainer.setup_phases, in timings.json): host time,
    which is where a fresh process pays its first calls (Warp module loads, CUDA start, lazy imports)."""

    def __init__(self):
        self.phases: dict[str, float] = {}
        self._last = time.perf_counter()

    def mark(self, name: str) -> None:
        now = time.perf_counter()
        self.phases[name] = now - self._last
        self._last = now


_SETUP_LOCK = threading.Lock()


class Trainer:
    """Trains the config's field (make_field: NeuS's MLP or the hash grid) or a given SDF module on a scan with
    the structured-light renderer.

    scan: a slwarp.Scan (its depth_range is required unless depth_range (near, far) mm is given); config: a
    TrainConfig (validated here). out_dir: where checkpoints go (None: no checkpoints). resume: continue from
    out_dir/checkpoint.pt. sdf: an SDF module to train instead of the config's field. init_depth [H, W] (mm):
    a starting depth map for the warm-up instead of the depth search. progress: a bar on a terminal, else a
    line every progress_interval_s seconds (default 10; given: lines in any case). overwrite: a new run may replace
    an existing checkpoint in out_dir (else CheckpointExists). Raises CheckpointError / RunMismatch on resume.
    """

    def __init__(self, scan, config: TrainConfig, out_dir: str | os.PathLike | None = None, resume: bool = False,
                 sdf: torch.nn.Module | None = None, depth_range=None, progress: bool = True, init_depth=None,
                 progress_interval_s: float | None = None, overwrite: bool = False):
        # one set-up at a time in a process: it seeds torch's global generator, from which the field draws its
        # initial values (a batch's retry of a lost surface sets up in the thread that extracts, beside the next scan)
        with _SETUP_LOCK:
            self._set_up(scan, config, out_dir, resume, sdf, depth_range, progress, init_depth, progress_interval_s,
                         overwrite)

    def _set_up(self, scan, config, out_dir, resume, sdf, depth_range, progress, init_depth, progress_interval_s,
                overwrite):
        # declared_cfg: the run as asked for (its identity, its checkpoints); cfg: as it trains, which a lens with a
        # halo may change (TrainConfig.through_lens, applied once the halo is known)
        self.cfg = self.declared_cfg = config = config.validate()
        # every part of the run (blur fit, renderer, refinement, added frames) sees the patterns through one lens: a
        # given halo from the start (the search included), a fitted one ("auto") from the fit after the search on
        halo = config.sampling.pattern_halo
        self.halo_share, self.halo_fit = (0.0 if halo == "auto" else float(halo)), None
        self.scan = scan = seen_through_lens(scan, self.halo_share, config.sampling.pattern_halo_sigma)
        self.device = with_index(torch_device(config.runtime.device))
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.progress = progress
        self.progress_interval_s = progress_interval_s
        # the range the run was given (its identity) and the range it trains in: the same, or narrowed to the depth
        # search's depths (init.auto_range; a resumed run takes its checkpoint's)
        self.depth_range = self._declared_range = checked_depth_range(scan, depth_range)
        clock = _SetupClock()
        checkpoint, ck_path = self._open_checkpoint(resume, overwrite)
        if checkpoint is not None:
            self.depth_range = tuple(float(x) for x in checkpoint["depth_range"])
        set_process_flags(self.device, config.runtime.matmul)
        torch.manual_seed(config.runtime.seed)
        self.generator = torch.Generator(device="cpu").manual_seed(config.runtime.seed)
        clock.mark("device")
        self.n_frames = frames_at_start(scan, config)
        lit, self.volume = working_volume(scan, config, self.n_frames, self.depth_range)
        self.search_info, self.blur_fit = None, None
        if init_depth is None and searches(config) and not resume:
            init_depth, self.search_info = search_start(scan, config, self.n_frames, self.depth_range, lit,
                                                        self._search_images(), self.device)
            if config.init.auto_range and sdf is None:
                self.depth_range, init_depth = narrowed_range(init_depth, self.depth_range,
                                                              config.init.auto_range_margin_mm)
                self.search_info["depth_range"] = list(self.depth_range)
                self.volume = Volume.from_frustum(scan.camera, lit, self.depth_range)
        clock.mark("depth search")
        if halo == "auto":
            self.scan = scan = self._fit_lens(scan, checkpoint, init_depth)
            clock.mark("halo fit")
        self.cfg = config = self.declared_cfg.through_lens(self.halo_share)
        self.field = sdf if sdf is not None else start_field(config, self.volume, self.depth_range, scan.camera)
        clock.mark("field")
        self.renderer = start_renderer(self.field, scan, config, self.n_frames, self.volume, self.depth_range,
                                       self.device)
        clock.mark("renderer")
        # a captured step reads the learning rate from a device tensor and keeps Adam's step count on the GPU
        use_graph = bool(config.runtime.cuda_graph) and self.device.type == "cuda"
        self.optimizer = Adam(schedule.parameter_groups(config, self.field, self.renderer.variance),
                              lr=config.schedule.lr)
        schedule.configure_adam(self.optimizer, self.device, use_graph)
        self.terms = MapTerms(self.field, config.init, self.volume.scale, self.device, scan.camera,
                              self.depth_range, config.runtime.backend)
        self._steps = GraphedStep(self.device, use_graph, self._step_body, self._configure_optimizer,
                                  config.sampling.rays)
        clock.mark("optimiser")
        self._start_map(init_depth, resume, clock)
        self.iteration, self.history, self.elapsed = 0, History(), 0.0
        if checkpoint is not None:
            self.load_checkpoint(ck_path, checkpoint)
        if self.init_depth is not None and surface_terms_on(config.init):
            self.surface_depth = surface_depth(self.init_depth, scan.camera, scan.projector,
                                               *pattern_model_inputs(self), self.device)
        self.doubt_pixels = self._emphasise_doubt()
        clock.mark("surface depth")
        self.setup_phases = clock.phases
        self.first_steps: list[float] = []
        # train()'s final checkpoint written in a thread (reconstruct sets it, then calls wait_checkpoint)
        self.checkpoint_in_background = False

    def _emphasise_doubt(self) -> int:
        """With sampling.doubt_rays, the renderer draws that share of each batch from the start's doubtful pixels
        (start.doubtful_pixels: lit, of fair modulation, without a surface-term depth, or without the search's depth
        when the surface term is off, and their neighbours) until doubt_rays_until of the iterations; their count (0:
        off, or no starting map)."""
        s = self.cfg.sampling
        self._doubt_until = round(s.doubt_rays_until * (self.cfg.schedule.iters + self.warmup_iters))
        confirmed = self.surface_depth if self.surface_depth is not None else self.init_depth
        if s.doubt_rays <= 0 or confirmed is None:
            return 0
        cam = self.scan.camera
        r = self.renderer
        doubt = doubtful_pixels(confirmed.reshape(cam.height, cam.width), r.valid_map,
                                r.b_flat.reshape(cam.height, cam.width), s.doubt_rays_radius)
        return r.emphasise(doubt, s.doubt_rays)

    def _open_checkpoint(self, resume: bool, overwrite: bool) -> tuple[dict | None, Path | None]:
        """(the checkpoint this run continues or None, its path): checked first, as a refusal costs nothing.
        Starts hashing the run's identity beside the rest when a new run will write checkpoints."""
        # only a checkpoint needs the identity, whose frame digests take 0.15 s for 42 default-rig frames: without
        # an output folder it is never computed, with one it is hashed beside the training (hashlib releases the GIL)
        self._identity, self._identity_thread = None, None
        if self.out_dir is not None and not resume:
            self._identity_thread = threading.Thread(target=self._compute_identity, daemon=True)
            self._identity_thread.start()
        ck_path = self.out_dir / "checkpoint.pt" if self.out_dir is not None else None
        if resume:
            if ck_path is None:
                raise CheckpointError("resume: no output folder to resume from")
            checkpoint = read_checkpoint(ck_path, map_location=self.device)
            if "identity" in checkpoint:
                diffs = identity_differences(checkpoint["identity"], self.identity)
                if diffs:
                    raise RunMismatch(ck_path, diffs)
            return checkpoint, ck_path
        if ck_path is not None and ck_path.exists() and not overwrite:
            raise CheckpointExists(f"{ck_path}: holds the checkpoint of an earlier run; --resume continues it, "
                                   "--overwrite starts again and replaces it (Python: resume=True / overwrite=True)")
        return None, ck_path

    def _fit_lens(self, scan, checkpoint: dict | None, init_depth):
        """The scan through the lens halo fitted at the starting map (pattern_model.fit_halo; a resumed run takes its
        checkpoint's share); sets halo_share and halo_fit. Without a map: no halo."""
        sigma = self.cfg.sampling.pattern_halo_sigma
        halo = None
        if checkpoint is not None:
            self.halo_share = float(checkpoint.get("pattern_halo", 0.0))
        elif init_depth is not None:
            cam = scan.camera
            # the halo's blur once, for the fit and for the patterns through the fitted lens
            halo = halo_light(scan.patterns, sigma, self.device)
            self.halo_share, self.halo_fit = fit_halo(
                np.asarray(init_depth, np.float32).reshape(cam.height, cam.width), cam, scan.projector,
                self._search_images(), scan.patterns[: self.n_frames], sigma=sigma, device=self.device,
                halo=halo[: self.n_frames])
        return seen_through_lens(scan, self.halo_share, sigma,
                                 None if halo is None or self.halo_share <= 0 else halo.cpu().numpy())

    def _search_images(self):
        """The frames in use as the depth search reads them: on a GPU a device tensor [N, H, W], else numpy."""
        images = self.scan.images[: self.n_frames]
        return torch.as_tensor(images, device=self.device) if self.device.type == "cuda" else images

    def _start_map(self, init_depth, resume: bool, clock: _SetupClock) -> None:
        """The starting map (the given one, else the new run's depth search) and a new run's fitted pattern blur."""
        cfg = self.cfg
        if cfg.sampling.pattern_blur == "auto" and not resume:
            sigma, self.blur_fit = fit_blur(self.scan, cfg, self.n_frames, init_depth, self.device)
            self.renderer.set_pattern_blur(sigma)
        clock.mark("blur fit")
        if init_depth is not None:
            self.init_depth = torch.as_tensor(np.asarray(init_depth, np.float32).reshape(-1), device=self.device)

    # the maps the loss terms read (held by `terms`, whose compiled graph reads them there)
    init_depth = _held_by_terms("init_depth", "[H*W] (mm, NaN: none) the warm-up's starting map, or None (no warm-up)")
    surface_depth = _held_by_terms("surface_depth", "[H*W] (mm, NaN: none) the starting map's depths the surface term "
                                   "pulls onto (start.surface_depth), or None (the surface and free-space terms off)")

    # --- frames -------------------------------------------------------------------------------
    def add_frames(self, images=None, patterns=None, count: int = 1):
        """Add frames to the running optimisation: the next `count` frames of the scan, or the given images
        [k, H, W] and patterns [k, Hp, Wp] (inserted right after the frames in use, so they count now)."""
        if images is not None:
            _ = self.identity  # the run's identity stays that of the scan it started with
            # the added patterns through the run's lens, as the scan's are
            self.scan, count = _with_frames(self.scan, self.n_frames, images, with_halo(
                patterns, self.halo_share, self.cfg.sampling.pattern_halo_sigma))
        self.n_frames = min(self.n_frames + count, len(self.scan))
        self.renderer.set_frames(self.scan.images[: self.n_frames], self.scan.patterns[: self.n_frames])

    # --- schedule (training.schedule) ----------------------------------------------------
    @property
    def warmup_iters(self) -> int:
        return self.cfg.init.iters if self.init_depth is not None else 0

    def in_warmup(self, it: int) -> bool:
        return it < self.warmup_iters

    def lambda_sc(self, it: int) -> float:
        return schedule.lambda_sc(self.cfg.schedule, it)

    def lr_factor(self, it: int) -> float:
        """The schedule's factor on every parameter group's base learning rate at iteration `it` (1: none)."""
        return schedule.lr_factor(self.cfg.schedule, it, self.warmup_iters)

    def learning_rate(self, it: int) -> float:
        """The learning rate of the field's MLP (config lr times the schedule factor)."""
        return self.cfg.schedule.lr * self.lr_factor(it)

    def cos_anneal(self, it: int) -> float:
        return schedule.cos_anneal(self.cfg.schedule, it)

    def active_levels(self, it: int) -> int | None:
        """Hash-grid levels switched on at iteration `it` (None for a field without levels)."""
        return schedule.active_levels(self.cfg.field, self.field, it, self.warmup_iters)

    @property
    def lens_schedule(self) -> dict | None:
        """{flat option: value} of what the scan's lens halo changed in the training (TrainConfig.through_lens), or
        None where it changed nothing."""
        if self.cfg is self.declared_cfg:
            return None
        return {n: v for n, v in self.declared_cfg.lens_options().items() if v != self.declared_cfg.get(n)} or None

    # --- checkpoints --------------------------------------------------------------------------
    def _compute_identity(self) -> None:
        self._identity = run_identity(self.scan, self.declared_cfg, self._declared_range)

    @property
    def identity(self) -> dict:
        """This run's `run_identity` (what a checkpoint records and a resumed run must match)."""
        if self._identity_thread is not None:
            self._identity_thread.join()
            self._identity_thread = None
        if self._identity is None:
            self._compute_identity()
        return self._identity

    def state(self) -> dict:
        """The checkpoint's contents (training.checkpoint.make_state): tensors and plain data only."""
        return make_state(iteration=self.iteration, config=self.declared_cfg.to_dict(), field=self.field,
                          variance=self.renderer.variance, optimizer=self.optimizer,
                          generator_state=self._steps.generator_state(self.generator), n_frames=self.n_frames,
                          volume=dataclasses.asdict(self.volume), depth_range=self.depth_range,
                          history=dataclasses.asdict(self.history), elapsed=self.elapsed, init_depth=self.init_depth,
                          pattern_blur=self.renderer.pattern_blur, pattern_halo=self.halo_share,
                          identity=self.identity)

    def save_checkpoint(self, path=None, background: bool = False) -> Path | None:
        """Atomically write the checkpoint (out_dir/checkpoint.pt unless `path`); None without either. background:
        snapshot the state to host memory now and write it in a thread (`wait_checkpoint` joins it): the final
        checkpoint of `fast` is about 70 MB, which the depth map need not wait for."""
        if self.out_dir is None and path is None:
            return None
        target = Path(path) if path is not None else self.out_dir / "checkpoint.pt"
        self.wait_checkpoint()
        if not background:
            return write_checkpoint(self.state(), target)
        state = _on_host(self.state())
        errors: list[BaseException] = []

        def write():
            try:
                write_checkpoint(state, target)
            except BaseException as e:  # noqa: BLE001 - re-raised in the thread that waits for it
                errors.append(e)

        # not a daemon: an interpreter that exits (Ctrl-C during the extraction included) finishes the file first
        self._writer = (threading.Thread(target=write, name="slwarp-checkpoint"), errors, target)
        self._writer[0].start()
        return target

    def wait_checkpoint(self) -> Path | None:
        """Wait for the checkpoint being written in the background, if any: its path, or the write's OSError."""
        writer, self._writer = getattr(self, "_writer", None), None
        if writer is None:
            return None
        thread, errors, target = writer
        thread.join()
        if errors:
            raise errors[0]
        return target

    def load_checkpoint(self, path, ck: dict | None = None):
        """Continue from the checkpoint at `path` (or its already read contents `ck`)."""
        ck = ck if ck is not None else read_checkpoint(path, map_location=self.device)
        check_field(ck, self.cfg.field.network(), path)
        if not 1 <= ck["n_frames"] <= len(self.scan):
            raise CheckpointError(f"{path}: trained on {ck['n_frames']} frames, the scan has {len(self.scan)}; "
                                  "start again with --overwrite")
        try:
            history = History(**ck["history"])
        except TypeError:
            raise CheckpointError(f"{path}: not a slwarp training checkpoint (its history holds "
                                  f"{sorted(ck['history'])}); start again with --overwrite") from None
        if ck["n_frames"] != self.n_frames:
            self.n_frames = ck["n_frames"]
            self.renderer.set_frames(self.scan.images[: self.n_frames], self.scan.patterns[: self.n_frames])
        self._steps.forget_draws()  # before the generator: the draws made ahead belong to the run replaced
        restore(ck, path, field=self.field, variance=self.renderer.variance, optimizer=self.optimizer,
                generator=self.generator, pixels=self.scan.camera.width * self.scan.camera.height)
        self._configure_optimizer()
        self.iteration = ck["iteration"]
        self.history = history
        self.elapsed = float(ck.get("elapsed", 0.0))
        self.init_depth = ck.get("init_depth")
        self.renderer.set_pattern_blur(ck.get("pattern_blur", 0.0))

    def _configure_optimizer(self) -> None:
        """Adam for plain steps or a captured graph, as the step runs now (schedule.configure_adam)."""
        schedule.configure_adam(self.optimizer, self.device, self._steps.enabled)

    # --- training -----------------------------------------------------------------------------

    def step(self) -> dict:
        """One optimisation step; returns the scalar losses (0-d tensors: reading them synchronises)."""
        it = self.iteration
        # the draws depend on the list's length and on whether this step draws from the emphasis (doubt_rays_until);
        # the phase goes with the draw function, which the draws made ahead replay when they rewind
        emphasised = self.doubt_pixels > 0 and it < self._doubt_until
        pick, jitter = self._steps.draw(self.generator, functools.partial(self._draw, emphasised=emphasised),
                                        key=(self.renderer.n_draw, emphasised))
        weights = schedule.step_weights(self.cfg.schedule, it, self.warmup_iters)
        schedule.set_learning_rates(self.optimizer, self.lr_factor(it), self.cfg.schedule.lr)
        schedule.set_levels(self.cfg.field, self.field, it, self.warmup_iters)
        vals = None
        if self._steps.enabled and self.cos_anneal(it) == 1.0:
            vals = self._steps.replay(pick, jitter, weights, key=(self.renderer.frames_version,
                                                                  self.init_depth is not None))
        if vals is None:
            vals = self._steps.run_plain(pick, jitter, weights, self.cos_anneal(it), self.renderer.compile_field)
        self.iteration += 1
        return vals

    def _draw(self, generator: torch.Generator, emphasised: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """A step's pixel positions [R] (long; from the whole draw list when `emphasised`, else from the valid pixels
        alone) and ray jitter [R] from `generator` (on the CPU: GraphedStep.draw makes them in the same order with or
        without a CUDA graph, so a resumed run continues an interrupted one exactly)."""
        R = self.cfg.sampling.rays
        return self.renderer.draw_valid(R, generator, emphasised=emphasised), self.renderer.draw_jitter(R, generator)

    def _step_body(self, pick: torch.Tensor, jitter: torch.Tensor, weights: dict,
                   cos_anneal_ratio: float = 1.0) -> dict:
        """Render a batch, the losses (terms.step_loss), backward and Adam. pick [R] positions in the valid-pixel
        list and jitter [R] on the device; weights "warmup" and "lambda_sc": floats, or 0-d device tensors inside
        a captured graph (schedule.step_weights)."""
        r = self.renderer
        r.mark_phase("batch")
        batch = r.valid_batch(pick)
        losses = r(batch, cos_anneal_ratio=cos_anneal_ratio, jitter=jitter)
        loss = step_loss(losses, batch, weights, self.cfg.schedule, self.terms, r.compile_field)
        r.mark_phase("backward")
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        r.mark_phase("optimizer")
        self.optimizer.step()
        r.mark_phase("end")
        return {"loss": loss.detach(), "color": losses.color.detach(), "surface": losses.surface.detach(),
                "eikonal": losses.eikonal.detach()}

    @property
    def graph_captured(self) -> bool:
        """Whether the step is held as a captured CUDA graph now (see TrainConfig.runtime.cuda_graph)."""
        return self._steps.captured

    def reset_graph(self) -> None:
        """Drop the captured step; the next step captures it again (e.g. after setting the renderer's
        phase_hook, so that the hook's work is part of the graph)."""
        self._steps.reset()

    def train(self, iters: int | None = None, callback=None) -> History:
        """Run to `iters` (default: the config's) iterations, checkpointing as configured.

        Raises TrainingDiverged on a non-finite loss, keeping the last good checkpoint."""
        total = iters if iters is not None else self.cfg.schedule.iters + self.warmup_iters
        bar = Progress(total, "training", initial=self.iteration, enabled=self.progress,
                       interval_s=self.progress_interval_s)
        t_start = time.perf_counter() - self.elapsed
        stop = StopSignals()
        try:
            stop.__enter__()
            while self.iteration < total:
                if stop.signum is not None:  # between two steps: never inside a captured graph's replay
                    bar.close()
                    self.elapsed = time.perf_counter() - t_start
                    saved = self.save_checkpoint() if self.out_dir is not None else None
                    raise TrainingInterrupted(stop.signum, self.iteration, saved)
                sched = self.cfg.schedule
                if (sched.incremental and self.iteration > 0 and self.iteration % sched.add_every == 0
                        and self.n_frames < len(self.scan)):
                    self.add_frames(count=1)
                t_step = time.perf_counter()
                vals = self.step()
                if len(self.first_steps) < FIRST_STEPS:  # host time: module loads, compilation, graph capture
                    self.first_steps.append(time.perf_counter() - t_step)
                if self.iteration % self.cfg.runtime.log_every == 0 or self.iteration == total:
                    self._log(vals, bar, t_start)
                    if callback is not None:
                        callback(self)
                bar.update()
                if (self.out_dir is not None and self.iteration % self.cfg.runtime.checkpoint_every == 0
                        and self.iteration < total):  # the last one follows the loop
                    self.elapsed = time.perf_counter() - t_start
                    # snapshot now, file in a thread (the next save, an interruption's included, waits for it): a
                    # written checkpoint cost `accurate` 0.13 s of training each, 4 of them per run on an H100
                    self.save_checkpoint(background=True)
        finally:
            stop.__exit__()
            bar.close()
            self.elapsed = time.perf_counter() - t_start
        if self.out_dir is not None:
            self.save_checkpoint(background=self.checkpoint_in_background)
        return self.history

    def _log(self, vals: dict, bar: Progress, t_start: float) -> None:
        """Log the step's losses (0-d tensors: reading them waits for the step) in the history and on the bar;
        TrainingDiverged when one is not finite."""
        v = {k: float(x) for k, x in vals.items()}
        if not all(math.isfinite(x) for x in v.values()):
            bar.close()
            raise TrainingDiverged.at(self.iteration, v, self.out_dir)
        h = self.history
        h.record(self.iteration, v, float(self.renderer.inv_s().detach()), self.n_frames, time.perf_counter() - t_start)
        bar.set_postfix(loss=f"{v['loss']:.4f}", rc=f"{v['color']:.4f}", sc=f"{v['surface']:.4f}",
                        eik=f"{v['eikonal']:.3f}", inv_s=f"{h.inv_s[-1]:.3g}", frames=self.n_frames)

    def save_history(self, folder) -> None:
        """loss curves: history.json and loss.png (History.save)."""
        self.history.save(folder)
