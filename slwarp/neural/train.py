"""Training the neural SDF on a scan: the paper's schedule, incremental mode, checkpoints, progress.

    trainer = Trainer(scan, preset("paper"), out_dir="run")     # preset: slwarp.neural.config
    trainer.train()                 # resumable: Trainer(..., resume=True) continues from run/checkpoint.pt
    field = trainer.field           # x [..., 3] mm -> sdf mm

Schedule (paper; TrainConfig.schedule): lambda_sc = 0 for the first `sc_start` iterations, then `lambda_sc`;
lambda_reg throughout; Adam at a constant learning rate (or cosine decay). Before it (init.method "search", the
default), `init.iters` warm-up iterations pull the volume-rendered depth onto a depth-search map
(slwarp.neural.search): the photometric loss is not convex in depth, and NeuS's sphere initialisation leaves
surfaces hundreds of mm from the truth stuck in other minima (measured: 232 mm MAE on the small-rig bunny
without it). With init.surface_weight > 0 the warm-up also puts the field's zero level at the map's points
(`Trainer._surface_term`), and init.surface_after > 0 keeps that term after the warm-up where the field lost a
surface in front of the one it shows (thin parts: bench/thin_stages.py); init.free_space > 0 adds the opposite
after the warm-up: where the field shows a surface in front of the map's, its samples before the map's point are
pushed out of the solid (`Trainer._free_space_term`: gaps and background the field bridged). Incremental mode (paper Fig. 8): start
with `start_frames` frames and add the next one every `add_every` iterations without restarting;
`Trainer.add_frames` lets a caller add captured frames to a running optimisation.

Checkpoints (`out_dir/checkpoint.pt`) record the run's identity (`run_identity`: the frames by name and content
digest, the depth range, a digest of the calibration and every option that is not `resumable`); `resume=True`
refuses a checkpoint of another run (`RunMismatch`, naming each difference), and a new run refuses to replace an
existing checkpoint unless `overwrite=True` (`CheckpointExists`). SIGINT/SIGTERM during `train()` save a checkpoint at
the next step boundary and raise `TrainingInterrupted` (exit status 130/143 on the command line).

The hash-grid field (field.kind "hashgrid"): Adam groups for its tables (grid_table_lr_factor x lr), its MLP
and the NeuS variance (lr), all following the schedule's factor; its levels switch on coarse to fine
(`active_levels`) through a device-side count, so a captured CUDA graph is replayed unchanged.

Repeatability: every random draw (pixel batches, ray jitter) comes from one torch.Generator seeded by
`runtime.seed` and saved in checkpoints, so a resumed run continues exactly as an uninterrupted one would.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import signal
import threading
import time
from contextlib import nullcontext as _nullcontext
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..devices import torch_device
from ..scans.scan import ScanError
from .config import TrainConfig
from .field import Volume, make_field
from .confidence import pattern_model_inputs, photometric_confidence
from .pattern_model import blur_patterns, estimate_pattern_blur, lit_with_contrast, offset_and_modulation
from .progress import Progress
from . import ops
from .render import StructuredLightRenderer, compile_in_process
from .search import AGREE_MM, component_sizes, search_depth

MISSED_MM = 5.0  # after the warm-up, the surface term acts where the field's depth is this far behind the map's
# (and the free-space term where it is this far in front, on the samples this far before the map's point)
SURFACE_CONFIDENCE = 0.8  # the surface term's depths: the map's where the pixel's own codes fit this well ...
SURFACE_MIN_GROUP = 50  # ... inside a connected group of at least this many such pixels (search.AGREE_MM apart)
# with a CUDA graph the steps' random draws are made and sent to the GPU this many steps at a time (Trainer._draw)
DRAW_AHEAD = 50


def _off_the_map(target: torch.Tensor, rendered: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(has target, field behind, field in front) [R] bool: where the rendered depth [R] (mm) lies more than MISSED_MM
    behind or in front of the map's confirmed depth target [R] (mm, NaN: none)."""
    ok = torch.isfinite(target)
    target = torch.nan_to_num(target)
    return ok, ok & (target < rendered - MISSED_MM), ok & (target > rendered + MISSED_MM)


def surface_term_weights(target: torch.Tensor, rendered: torch.Tensor, warm, during: float, after: float,
                         in_front: bool = False) -> torch.Tensor:
    """Per-pixel weights [R] of the surface term (Trainer._surface_term): `during` on every pixel with a target
    in the warm-up (warm 1), and after it (warm 0) `after` only where the rendered depth [R] (mm) lies more than
    MISSED_MM behind the target [R] (mm, NaN: none): a thin part in front that the field lost; with `in_front` also
    where it lies more than MISSED_MM in front of the target (the field carried a surface over the pixel's own, e.g.
    a step's edge over the lower step). Elsewhere the photometric loss alone decides. warm: a float or a 0-d tensor
    in [0, 1]."""
    ok, behind, ahead = _off_the_map(target, rendered)
    missed = behind | ahead if in_front else behind
    return ok.to(rendered.dtype) * (warm * during) + missed.to(rendered.dtype) * ((1.0 - warm) * after)


def free_space_weights(target: torch.Tensor, rendered: torch.Tensor, warm, after: float) -> torch.Tensor:
    """Per-pixel weights [R] of the free-space term (Trainer._free_space_term): `after` (outside the warm-up: warm 0)
    where the rendered depth [R] (mm) lies more than MISSED_MM in front of the map's confirmed depth target [R]
    (mm, NaN: none), else 0. The pixel's own codes put its surface at the target, so the field's surface in front of
    it is one the field bridged across a gap or grew over the background (steps, boxes: notes/accuracy.md)."""
    _, _, bridged = _off_the_map(target, rendered)
    return bridged.to(rendered.dtype) * ((1.0 - warm) * after)


__all__ = ["Trainer", "surface_term_weights", "free_space_weights", "TrainingDiverged", "TrainingInterrupted", "CheckpointError",
           "CheckpointExists", "RunMismatch", "History", "run_identity"]


class TrainingDiverged(RuntimeError):
    """The loss became non-finite; the last good checkpoint is kept."""


class TrainingInterrupted(Exception):
    """SIGINT or SIGTERM stopped training at a step boundary after saving a checkpoint (when the run has an output
    folder). signum: the signal; checkpoint: the Path saved or None; exit_status: 128 + signum (130, 143)."""

    def __init__(self, signum: int, iteration: int, checkpoint: Path | None):
        self.signum, self.iteration, self.checkpoint = signum, iteration, checkpoint
        self.exit_status = 128 + int(signum)
        where = (f"checkpoint saved at {checkpoint}; continue with --resume (Python: resume=True)" if checkpoint
                 else "no checkpoint (no output folder)")
        super().__init__(f"interrupted by {signal.Signals(signum).name} at iteration {iteration}: {where}")


class CheckpointError(ValueError):
    """A checkpoint that cannot be used: missing, truncated, not a slwarp checkpoint, or of another run."""


class CheckpointExists(CheckpointError):
    """A new run would replace an existing checkpoint (pass resume=True to continue it, overwrite=True to replace it)."""


class RunMismatch(CheckpointError):
    """--resume with a checkpoint written by a different run; `differences` lists (what, old, new)."""

    def __init__(self, path, differences: list[tuple[str, object, object]]):
        self.differences = differences
        lines = "; ".join(f"{what}: {old} in the checkpoint, {new} now" for what, old, new in differences)
        super().__init__(f"{path}: --resume with a different run ({lines}); resume with the same scan, frames and "
                         "options, or start again with --overwrite (or another --out)")


def _digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def run_identity(scan, config: TrainConfig, depth_range) -> dict:
    """What defines a run's result, as its checkpoint records it: the frames (name and a digest of the image and
    pattern, in order), the depth range (mm), a digest of the calibration and every option a resumed run must
    keep (`TrainConfig.fixed_options`). Plain values (JSON-able)."""
    calib = json.dumps({"camera": scan.camera.to_dict(), "projector": scan.projector.to_dict(),
                        "R": np.asarray(scan.projector.R).tolist(), "T": np.asarray(scan.projector.T).tolist()},
                       sort_keys=True)
    return {"frames": [[name, _digest(scan.images[i], scan.patterns[i])] for i, name in enumerate(scan.names)],
            "depth_range": [float(x) for x in depth_range],
            "calibration": hashlib.sha256(calib.encode()).hexdigest()[:16],
            "options": config.fixed_options()}


def _short_list(names: list[str], limit: int = 6) -> str:
    return ", ".join(names[:limit]) + (f", ... ({len(names)} in all)" if len(names) > limit else "")


def identity_differences(old: dict, new: dict) -> list[tuple[str, object, object]]:
    """(what, old value, new value) for every difference between two `run_identity` records."""
    diffs = []
    old_frames, new_frames = [tuple(f) for f in old["frames"]], [tuple(f) for f in new["frames"]]
    if old_frames != new_frames:
        old_names, new_names = [f[0] for f in old_frames], [f[0] for f in new_frames]
        if old_names != new_names:
            diffs.append(("frames", f"{len(old_names)} ({_short_list(old_names)})",
                          f"{len(new_names)} ({_short_list(new_names)})"))
        else:
            changed = [o[0] for o, n in zip(old_frames, new_frames) if o[1] != n[1]]
            diffs.append(("frame content", "other images or patterns", f"changed in {_short_list(changed)}"))
    if [float(x) for x in old["depth_range"]] != [float(x) for x in new["depth_range"]]:
        diffs.append(("depth range (mm)", tuple(old["depth_range"]), tuple(new["depth_range"])))
    if old["calibration"] != new["calibration"]:
        diffs.append(("calibration", "digest " + old["calibration"], "digest " + new["calibration"]))
    for name in sorted(set(old["options"]) | set(new["options"])):
        a, b = old["options"].get(name, "(absent)"), new["options"].get(name, "(absent)")
        if a != b:
            diffs.append((f"option {name}", a, b))
    return diffs


def read_checkpoint(path, map_location="cpu") -> dict:
    """The checkpoint at `path`, or CheckpointError naming the path and the problem (missing, truncated, not a
    slwarp checkpoint)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no checkpoint to resume from (run without --resume to start)")
    try:
        ck = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as e:  # noqa: BLE001 - torch reports truncation and garbage as many types (zip, pickle, EOF)
        raise CheckpointError(f"{path}: not a readable checkpoint ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else 'truncated?'}); "
                              "start again with --overwrite") from None
    needed = ("iteration", "config", "field", "variance", "optimizer", "generator", "n_frames", "history")
    if not isinstance(ck, dict) or any(k not in ck for k in needed):
        raise CheckpointError(f"{path}: not a slwarp training checkpoint (missing "
                              f"{[k for k in needed if not isinstance(ck, dict) or k not in ck]}); start again with --overwrite")
    return ck


class _StopSignals:
    """While active (in the main thread only, where Python delivers signals), SIGINT and SIGTERM set `signum`
    instead of stopping the process, so that training stops at the next step boundary; a second signal stops at
    once. The previous handlers come back on exit."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self.signum = None
        self._previous = {}

    def _handle(self, signum, frame):
        if self.signum is not None:  # asked twice: stop now
            self.__exit__()
            signal.raise_signal(signum)
            return
        self.signum = signum

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for s in self.SIGNALS:
                self._previous[s] = signal.signal(s, self._handle)
        return self

    def __exit__(self, *exc):
        for s, h in self._previous.items():
            signal.signal(s, h)
        self._previous = {}


@dataclass
class History:
    iters: list = field(default_factory=list)
    loss: list = field(default_factory=list)
    color: list = field(default_factory=list)
    surface: list = field(default_factory=list)
    eikonal: list = field(default_factory=list)
    inv_s: list = field(default_factory=list)
    frames: list = field(default_factory=list)
    # seconds of training (wall clock, resumed runs included) at each logged iteration; the loss is read there,
    # which waits for the GPU, so the differences are the true time per step (older checkpoints: empty)
    elapsed_s: list = field(default_factory=list)


class DrawAhead:
    """A step's random draws made `ahead` steps at a time from a CPU generator and sent to `device` in one copy.

    The draws and the generator's order are those of drawing step by step: `next` gives each step's draws,
    `generator_state` the state after the steps taken so far (for a checkpoint), `rewind` sets the generator
    there. A change of `key` (what the draws depend on, e.g. the count of valid pixels) rewinds and draws anew.
    Why: the training step's draws, copied to the GPU from pageable memory each step, made the host wait for the
    GPU's previous step (`fast`, H100: 2.57 ms per iteration in reconstruct against 2.18 ms in
    bench/train_speed.py's steady state)."""

    def __init__(self, generator: torch.Generator, device, ahead: int):
        self.generator, self.device, self.ahead = generator, torch.device(device), int(ahead)
        self.state, self.used, self.key, self.drawn = None, 0, None, None
        self._shapes = self._host = self._dev = self._copied = None  # the pinned and device buffers (`_send`)

    def next(self, draw, key=None) -> tuple:
        """This step's draws: `draw(generator)` -> a tuple of CPU tensors, here on `device`."""
        if self.drawn is None or self.used == self.ahead or key != self.key:
            self.rewind()
            self.state, self.used, self.key, self._draw = self.generator.get_state(), 0, key, draw
            steps = [draw(self.generator) for _ in range(self.ahead)]
            self.drawn = self._send([torch.stack(x) for x in zip(*steps)])
        i = self.used
        self.used += 1
        return tuple(x[i] for x in self.drawn)

    def _send(self, blocks: list) -> tuple:
        """The blocks of draws on `device`. To a GPU: through pinned buffers allocated once (a fresh pinned
        allocation for each block made that block's 20 profiled steps 10-18 ms slower in all), reused once their last
        copy is done."""
        if self.device.type != "cuda":
            return tuple(b.to(self.device) for b in blocks)
        shapes = [(b.shape, b.dtype) for b in blocks]
        if self._shapes != shapes:
            self._shapes = shapes
            self._host = [torch.empty(sh, dtype=dt, pin_memory=True) for sh, dt in shapes]
            self._dev = [torch.empty(sh, dtype=dt, device=self.device) for sh, dt in shapes]
            self._copied = None
        if self._copied is not None:
            self._copied.synchronize()  # the previous block's copy out of the host buffers (long done: ahead steps ago)
        for h, d, b in zip(self._host, self._dev, blocks):
            h.copy_(b)
            d.copy_(h, non_blocking=True)
        self._copied = torch.cuda.Event()
        self._copied.record(torch.cuda.current_stream(self.device))
        return tuple(self._dev)

    def generator_state(self) -> torch.Tensor:
        """The generator's state after the draws of the steps taken."""
        if self.drawn is None or self.used == self.ahead:
            return self.generator.get_state()
        g = torch.Generator(device="cpu")
        g.set_state(self.state)
        for _ in range(self.used):
            self._draw(g)
        return g.get_state()

    def rewind(self) -> None:
        """Set the generator to `generator_state` and forget the draws made ahead."""
        if self.drawn is not None:
            self.generator.set_state(self.generator_state())
        self.drawn, self.used = None, 0


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
        self.scan = scan
        self.cfg = config.validate()
        self.device = torch_device(config.runtime.device)
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.progress = progress
        self.progress_interval_s = progress_interval_s
        depth_range = depth_range or scan.depth_range
        if depth_range is None:
            raise ScanError(f"{scan.source or 'scan'}: no depth range in the scan: give one (near, far) in mm "
                            "(CLI: --depth-range NEAR,FAR)")
        self.depth_range = tuple(float(x) for x in depth_range)
        if not (len(self.depth_range) == 2 and all(map(math.isfinite, self.depth_range))
                and 0 < self.depth_range[0] < self.depth_range[1]):
            raise ScanError(f"{scan.source or 'scan'}: depth range {depth_range} must be two finite numbers "
                            "0 < near < far (mm)")
        # what this run is (`identity`), and the checkpoint it continues (checked first: a refusal costs nothing).
        # Only a checkpoint needs the identity, whose frame digests take 0.15 s for 42 default-rig frames: without
        # an output folder it is never computed, with one it is hashed beside the training (hashlib releases the GIL)
        self._identity, self._identity_thread = None, None
        if out_dir is not None and not resume:
            self._identity_thread = threading.Thread(target=self._compute_identity, daemon=True)
            self._identity_thread.start()
        checkpoint = None
        ck_path = self.out_dir / "checkpoint.pt" if self.out_dir is not None else None
        if resume:
            if ck_path is None:
                raise CheckpointError("resume: no output folder to resume from")
            checkpoint = read_checkpoint(ck_path, map_location=self.device)
            if "identity" in checkpoint:
                diffs = identity_differences(checkpoint["identity"], self.identity)
                if diffs:
                    raise RunMismatch(ck_path, diffs)
        elif ck_path is not None and ck_path.exists() and not overwrite:
            raise CheckpointExists(f"{ck_path}: holds the checkpoint of an earlier run; --resume continues it, "
                                   "--overwrite starts again and replaces it (Python: resume=True / overwrite=True)")
        if self.device.type == "cpu":
            # transmittance products and sigmoids of a sharpening SDF underflow into denormal floats, which
            # x86 CPUs process ~100x slower (measured: 50 iterations in 46 s instead of 1.4 s)
            torch.set_flush_denormal(True)
        if config.runtime.matmul == "tf32":
            torch.backends.cuda.matmul.allow_tf32 = True
            torch.backends.cudnn.allow_tf32 = True
        torch.manual_seed(config.runtime.seed)
        self.generator = torch.Generator(device="cpu").manual_seed(config.runtime.seed)
        self._ahead = None  # the draws made ahead for the coming steps (see _draw)
        n_all = len(scan)
        if n_all < 2:
            raise ScanError(f"{scan.source or 'scan'}: {'; '.join(scan.problems(config.sampling.contrast_threshold))}")
        self.n_frames = min(config.schedule.start_frames, n_all) if config.schedule.incremental else n_all
        # the working volume (the frustum box of the pixels lit with contrast) sizes the field, which the
        # renderer then samples
        images = scan.images[: self.n_frames]
        lit = lit_with_contrast(offset_and_modulation(images)[1], config.sampling.contrast_threshold)
        if not lit.any():
            why = scan.problems(config.sampling.contrast_threshold)
            raise ScanError(f"{scan.source or 'scan'}: no pixel is lit with contrast (modulation above "
                            f"{config.sampling.contrast_threshold}) in the frames used" + (f": {'; '.join(why)}" if why else ""))
        self.volume = Volume.from_frustum(scan.camera, lit, self.depth_range)
        # the camera's pixel footprint at the middle of the depth range sizes a hash grid's finest cells
        pixel_mm = 0.5 * sum(self.depth_range) / (0.5 * (scan.camera.fx + scan.camera.fy))
        self.field = sdf if sdf is not None else make_field(
            config.field, self.volume, init="camera" if config.init.method == "camera" else "sphere",
            far=self.depth_range[1], pixel_mm=pixel_mm)
        self.renderer = StructuredLightRenderer(
            self.field, scan.camera, scan.projector, scan.patterns[: self.n_frames], images, depth_range=self.depth_range,
            volume=self.volume, n_samples=config.sampling.n_samples, n_importance=config.sampling.n_importance,
            up_sample_steps=config.sampling.up_sample_steps, contrast_threshold=config.sampling.contrast_threshold,
            backend=config.runtime.backend, device=self.device, compile_field=config.runtime.compile and self.device.type == "cuda",
            pattern_blur=0.0 if config.sampling.pattern_blur == "auto" else float(config.sampling.pattern_blur),
        )
        # a captured step reads the learning rate from a device tensor and keeps Adam's step count on the GPU
        self.use_graph = bool(config.runtime.cuda_graph) and self.device.type == "cuda"
        self.optimizer = torch.optim.Adam(self._parameter_groups(), lr=config.schedule.lr)
        self._configure_optimizer()
        self._graph = None  # the captured step (see _graph_step)
        self._map_terms_compiled = None  # _map_terms, compiled on first use (see _map_terms_fn)
        # the map terms' unit (mm), a device tensor: an input of their compiled graph, which so serves every scan
        # of the same sizes (field.register_volume_buffers)
        self._scale_mm = torch.tensor(self.volume.scale, dtype=torch.float32, device=self.device)
        self._eager_since_change = 0  # plain steps since the frames changed (capture needs warm kernels)
        self._stream = torch.cuda.Stream(self.device) if self.use_graph else None
        self.init_depth = None
        self.search_info = None
        self.blur_fit = None
        if init_depth is None and config.init.method == "search" and config.init.iters > 0 and not resume:
            search_blur = 1.0 if config.sampling.pattern_blur == "auto" else float(config.sampling.pattern_blur)
            # on a GPU the search reads the frames where they are: the renderer's images, the patterns blurred there
            search_patterns = blur_patterns(torch.as_tensor(scan.patterns[: self.n_frames], device=self.device), search_blur)
            if self.device.type != "cuda":
                search_patterns = search_patterns.numpy()
            init_depth, self.search_info = search_depth(
                scan.camera, scan.projector, pattern_model_inputs(self)[0], search_patterns, self.depth_range,
                valid=lit, step_mm=config.init.search_step_mm, stride=config.init.search_stride, device=self.device)
        if config.sampling.pattern_blur == "auto" and not resume:
            sigma, fit = 1.0, None
            if init_depth is not None:
                try:
                    sigma, fit = estimate_pattern_blur(scan.camera, scan.projector, images, scan.patterns[: self.n_frames],
                                                       np.asarray(init_depth, np.float32).reshape(scan.camera.height,
                                                                                                  scan.camera.width),
                                                       device=self.device)
                except ValueError as e:  # too few pixels with a starting depth: the scan does not fit its model
                    why = scan.problems(config.sampling.contrast_threshold)
                    raise ScanError(f"{scan.source or 'scan'}: " + (f"{'; '.join(why)} (so the pattern blur cannot be "
                                    f"fitted: {e})" if why else f"cannot fit the pattern blur ({e}); check the depth "
                                    "range and the patterns, or give a fixed pattern_blur (--pattern-blur)")) from None
            self.renderer.set_pattern_blur(sigma)
            self.blur_fit = fit
        if init_depth is not None:
            self.init_depth = torch.as_tensor(np.asarray(init_depth, np.float32).reshape(-1), device=self.device)
        self.iteration = 0
        self.history = History()
        self.elapsed = 0.0
        if checkpoint is not None:
            self.load_checkpoint(ck_path, checkpoint)
        self.surface_depth = self._surface_depth()

    def _surface_depth(self) -> torch.Tensor | None:
        """[H W] (mm, NaN: none) the initial map's depths that the surface term pulls the field onto: those that
        their own pixel's codes confirm (photometric confidence >= SURFACE_CONFIDENCE, patterns as rendered)
        inside a connected group of at least SURFACE_MIN_GROUP of them (8 neighbours, each within AGREE_MM of the
        next); None when the term is off or there is no map. Why: its gradient does not vanish far from the
        field's surface, so a wrong depth of the map raises a wrong surface. A 5x5 window's foreground depth
        spread over the background beside a depth edge fits the pixel's own codes poorly; a chance match of the
        codes may fit them well but comes in small scattered groups (rolled-rig spheres: 3224 targets more than
        20 mm in front of the truth, down to the near plane, raised floaters; none lies in a group of 50)."""
        init = self.cfg.init
        if self.init_depth is None or not (init.surface_weight > 0 or init.surface_after > 0 or init.free_space > 0):
            return None
        cam = self.scan.camera
        d = self.init_depth.reshape(cam.height, cam.width).cpu().numpy()
        conf = photometric_confidence(d, cam, self.scan.projector, *pattern_model_inputs(self))
        kept = np.where(conf >= SURFACE_CONFIDENCE, d, np.nan).astype(np.float32)
        kept[component_sizes(kept, AGREE_MM) < SURFACE_MIN_GROUP] = np.nan
        return torch.as_tensor(kept.reshape(-1), device=self.device)

    # --- frames -------------------------------------------------------------------------------
    def add_frames(self, images=None, patterns=None, count: int = 1):
        """Add frames to the running optimisation: the next `count` frames of the scan, or the given images
        [k, H, W] and patterns [k, Hp, Wp] (inserted right after the frames in use, so they count now)."""
        if images is not None:
            _ = self.identity  # the run's identity stays that of the scan it started with
            cam, prj = self.scan.camera, self.scan.projector
            images = np.asarray(images, np.float32).reshape(-1, cam.height, cam.width)
            patterns = np.asarray(patterns, np.float32)
            if patterns.shape[1:] != (prj.height, prj.width) or len(patterns) != len(images):
                raise ValueError(f"add_frames: {len(images)} images need as many patterns of {prj.width}x{prj.height} px, "
                                 f"got {patterns.shape}")
            n = self.n_frames
            names = [f"added{len(self.scan) + i}" for i in range(len(images))]
            self.scan = dataclasses.replace(
                self.scan, images=np.concatenate([self.scan.images[:n], images, self.scan.images[n:]]),
                patterns=np.concatenate([self.scan.patterns[:n], patterns, self.scan.patterns[n:]]),
                names=self.scan.names[:n] + names + self.scan.names[n:])
            count = len(images)
        self.n_frames = min(self.n_frames + count, len(self.scan))
        self.renderer.set_frames(self.scan.images[: self.n_frames], self.scan.patterns[: self.n_frames])

    # --- schedule -----------------------------------------------------------------------------
    def lambda_sc(self, it: int) -> float:
        return self.cfg.schedule.lambda_sc if it >= self.cfg.schedule.sc_start else 0.0

    def lr_factor(self, it: int) -> float:
        """The schedule's factor on every parameter group's base learning rate at iteration `it` (1: none)."""
        if self.cfg.schedule.lr_decay == "none":
            return 1.0
        total = max(1, self.cfg.schedule.iters + self.warmup_iters)
        progress = min(1.0, it / total)
        return self.cfg.schedule.lr_final + (1.0 - self.cfg.schedule.lr_final) * 0.5 * (1.0 + math.cos(math.pi * progress))

    def learning_rate(self, it: int) -> float:
        """The learning rate of the field's MLP (config lr times the schedule factor)."""
        return self.cfg.schedule.lr * self.lr_factor(it)

    def _compute_identity(self) -> None:
        self._identity = run_identity(self.scan, self.cfg, self.depth_range)

    @property
    def identity(self) -> dict:
        """This run's `run_identity` (what a checkpoint records and a resumed run must match)."""
        if self._identity_thread is not None:
            self._identity_thread.join()
            self._identity_thread = None
        if self._identity is None:
            self._compute_identity()
        return self._identity

    def active_levels(self, it: int) -> int | None:
        """Hash-grid levels switched on at iteration `it` (None for a field without levels): grid_start_levels
        through the warm-up, then one more every grid_level_every iterations (all at once when 0)."""
        if self.cfg.field.kind != "hashgrid" or not hasattr(self.field, "set_active_levels"):
            return None
        f = self.cfg.field
        after = it - self.warmup_iters
        if after < 0:
            return min(f.grid_start_levels, self.field.levels)
        added = self.field.levels if f.grid_level_every == 0 else after // f.grid_level_every
        return min(self.field.levels, f.grid_start_levels + added)

    def _parameter_groups(self) -> list[dict]:
        """Adam's groups, each with its base learning rate ("base_lr", scaled by the schedule's factor): the
        hash grid's tables (grid_table_lr_factor x lr), the rest of the field (lr) and the NeuS variance
        (variance_lr_factor x lr); for other fields one group of everything (as checkpoints of the MLP hold it)
        unless the variance has a rate of its own."""
        lr = self.cfg.schedule.lr
        variance = list(self.renderer.variance.parameters())
        variance_lr = lr * self.cfg.schedule.variance_lr_factor
        table = getattr(self.field, "table", None)
        if self.cfg.field.kind != "hashgrid" or not isinstance(table, torch.nn.Parameter):
            if variance_lr == lr:
                return [{"params": list(self.field.parameters()) + variance, "lr": lr, "base_lr": lr}]
            return [{"params": list(self.field.parameters()), "lr": lr, "base_lr": lr},
                    {"params": variance, "lr": variance_lr, "base_lr": variance_lr}]
        rest = [p for p in self.field.parameters() if p is not table]
        table_lr = lr * self.cfg.field.grid_table_lr_factor
        return [{"params": [table], "lr": table_lr, "base_lr": table_lr},
                {"params": rest, "lr": lr, "base_lr": lr},
                {"params": variance, "lr": variance_lr, "base_lr": variance_lr}]

    def cos_anneal(self, it: int) -> float:
        return 1.0 if self.cfg.schedule.anneal_end <= 0 else min(1.0, it / self.cfg.schedule.anneal_end)

    # --- checkpoints --------------------------------------------------------------------------
    def state(self) -> dict:
        return {
            "iteration": self.iteration,
            "config": self.cfg.to_dict(),
            "field": self.field.state_dict(),
            "variance": self.renderer.variance.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "generator": self._generator_state(),
            "n_frames": self.n_frames,
            "volume": dataclasses.asdict(self.volume),
            "depth_range": self.depth_range,
            "history": dataclasses.asdict(self.history),
            "elapsed": self.elapsed,
            "init_depth": self.init_depth,
            "pattern_blur": self.renderer.pattern_blur,
            "identity": self.identity,
        }

    def save_checkpoint(self, path=None) -> Path | None:
        """Atomically write the checkpoint (write to a temporary file, then rename)."""
        if self.out_dir is None and path is None:
            return None
        path = Path(path) if path is not None else self.out_dir / "checkpoint.pt"
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        try:
            torch.save(self.state(), tmp)
            os.replace(tmp, path)
        except (OSError, RuntimeError) as e:  # torch reports a full disk as a RuntimeError of its zip writer
            tmp.unlink(missing_ok=True)
            if isinstance(e, OSError):
                raise
            raise OSError(f"{path}: could not write the checkpoint ({str(e).splitlines()[0]}); is the disk full?") from None
        return path

    def load_checkpoint(self, path, ck: dict | None = None):
        """Continue from the checkpoint at `path` (or its already read contents `ck`)."""
        ck = ck if ck is not None else read_checkpoint(path, map_location=self.device)
        saved = ck["config"].get("field", ck["config"])  # flat in checkpoints written before the config had sections
        field_now = self.cfg.field.network()
        saved_kind = saved.get("kind", "mlp")  # written before the hash grid: the MLP
        if saved_kind != field_now["kind"]:
            raise CheckpointError(f"{path}: checkpoint was trained with the {saved_kind} field, the config asks for the "
                             f"{field_now['kind']} field (--field); resume with --field {saved_kind} and the same preset")
        differ = {k: (saved.get(k), v) for k, v in field_now.items() if saved.get(k) != v}
        if differ:
            raise CheckpointError(f"{path}: checkpoint was trained with a different {saved_kind} field (checkpoint, config: "
                             + ", ".join(f"{k} {a!r} vs {b!r}" for k, (a, b) in differ.items())
                             + "); use the same preset/options to resume")
        if ck["n_frames"] != self.n_frames:
            self.n_frames = ck["n_frames"]
            self.renderer.set_frames(self.scan.images[: self.n_frames], self.scan.patterns[: self.n_frames])
        self.field.load_state_dict(ck["field"])
        self.renderer.variance.load_state_dict(ck["variance"])
        self.optimizer.load_state_dict(ck["optimizer"])
        self._configure_optimizer()
        self._ahead = None  # before the generator: the draws made ahead belong to the run replaced
        self.generator.set_state(ck["generator"])
        self.iteration = ck["iteration"]
        self.history = History(**ck["history"])
        self.elapsed = ck.get("elapsed", 0.0)
        self.init_depth = ck.get("init_depth")
        self.renderer.set_pattern_blur(ck.get("pattern_blur", 0.0))

    # --- training -----------------------------------------------------------------------------
    @property
    def warmup_iters(self) -> int:
        return self.cfg.init.iters if self.init_depth is not None else 0

    def in_warmup(self, it: int) -> bool:
        return it < self.warmup_iters

    def _configure_optimizer(self) -> None:
        """Adam as the step needs it: with CUDA graphs, capturable (step count on the GPU) and the learning
        rate a device tensor that each replay reads; otherwise a plain float learning rate. On CUDA Adam's fused
        kernel: it took the `accurate` preset's step from 4.70 to 4.37 ms on an H100 (notes/hashgrid.md, phase 3)."""
        fused = self.device.type == "cuda"
        for group in self.optimizer.param_groups:
            lr = float(group["lr"])
            group["fused"] = fused
            group["foreach"] = None if fused else group.get("foreach")
            group["capturable"] = self.use_graph
            group["lr"] = torch.tensor(lr, device=self.device) if self.use_graph else lr
        for st in self.optimizer.state.values():
            if "step" in st and torch.is_tensor(st["step"]):
                st["step"] = st["step"].to(self.device if self.use_graph else "cpu", torch.float32)

    def _set_lr(self, factor: float) -> None:
        """Each group's learning rate: its base rate times the schedule's factor (a device tensor's fill under
        CUDA graphs: no recapture, no host sync)."""
        for group in self.optimizer.param_groups:
            lr = group.get("base_lr", self.cfg.schedule.lr) * factor
            if torch.is_tensor(group["lr"]):
                group["lr"].fill_(lr)
            else:
                group["lr"] = lr

    def _set_levels(self, it: int) -> None:
        """Apply the hash grid's level schedule (a device-side level count: no recapture, no host sync)."""
        n = self.active_levels(it)
        if n is not None and n != self.field.n_active:
            self.field.set_active_levels(n)

    def step(self) -> dict:
        """One optimisation step; returns the scalar losses (0-d tensors: reading them synchronises)."""
        it = self.iteration
        pick, jitter = self._draw()
        weights = {"warmup": 1.0 if self.in_warmup(it) else 0.0,
                   "lambda_sc": 0.0 if self.in_warmup(it) else self.lambda_sc(it - self.warmup_iters)}
        self._set_lr(self.lr_factor(it))
        self._set_levels(it)
        vals = None
        if self.use_graph and self.cos_anneal(it) == 1.0:
            vals = self._graph_step(pick, jitter, weights)
        if vals is None:
            stream = torch.cuda.stream(self._stream) if self._stream is not None else _nullcontext()
            if self._stream is not None:
                self._stream.wait_stream(torch.cuda.current_stream(self.device))
            if self.renderer.compile_field:  # as the captured step passes them: one compiled graph of the map terms
                weights = {k: torch.full((), v, device=self.device) for k, v in weights.items()}  # a fill: no host copy
            with stream:
                vals = self._step_body(pick.to(self.device), jitter.to(self.device), weights, self.cos_anneal(it))
            if self._stream is not None:
                torch.cuda.current_stream(self.device).wait_stream(self._stream)
            self._eager_since_change += 1
        self.iteration += 1
        return vals

    def _draw(self) -> tuple[torch.Tensor, torch.Tensor]:
        """This step's pixel positions [R] (long) and ray jitter [R].

        They come from the CPU generator in the same order with or without a CUDA graph, so both give the same
        run and a resumed run continues an interrupted one exactly. With a graph they are drawn DRAW_AHEAD steps
        at a time and sent to the GPU in one copy (`DrawAhead`): a copy from pageable memory waits for the GPU to
        finish the steps before it, so each step's host work (draws, learning rate, levels, replay) added to its
        GPU time instead of overlapping it."""
        R, r = self.cfg.sampling.rays, self.renderer

        def draw(g):
            return r.draw_valid(R, g), r.draw_jitter(R, g)

        if not self.use_graph:
            if self._ahead is not None:  # the capture failed: on from the steps taken, without drawing ahead
                self._ahead.rewind()
                self._ahead = None
            return draw(self.generator)
        if self._ahead is None:
            self._ahead = DrawAhead(self.generator, self.device, DRAW_AHEAD)
        return self._ahead.next(draw, key=r.n_valid)

    def _generator_state(self) -> torch.Tensor:
        """The generator's state after the draws of the steps taken (not those drawn ahead for later steps)."""
        return self._ahead.generator_state() if self._ahead is not None else self.generator.get_state()

    def _step_body(self, pick: torch.Tensor, jitter: torch.Tensor, weights: dict, cos_anneal_ratio: float = 1.0) -> dict:
        """Render a batch, the losses, backward and Adam. pick [R] positions in the valid-pixel list and
        jitter [R] on the device; weights "warmup" (1 in the depth-search warm-up, else 0) and "lambda_sc":
        floats, or 0-d device tensors inside a captured graph (then every term is computed, weighted)."""
        r = self.renderer
        r.mark_phase("batch")
        batch = r.valid_batch(pick)
        losses = r(batch, cos_anneal_ratio=cos_anneal_ratio, jitter=jitter)
        warm, w_sc = weights["warmup"], weights["lambda_sc"]
        captured = torch.is_tensor(warm)
        loss = self.cfg.schedule.lambda_reg * losses.eikonal
        init = self.cfg.init
        if self.init_depth is not None and (captured or warm != 0.0 or init.surface_after > 0 or init.free_space > 0):
            _, d, _, _ = ops.camera_rays(batch.uv, self.scan.camera, self.depth_range, backend=self.cfg.runtime.backend)
            loss = loss + self._map_terms_fn()(d, batch.index, losses.output.depth, losses.output.weight_sum,
                                               losses.z_vals, losses.sdf, warm)
        if captured or warm != 1.0:
            photometric = self.cfg.schedule.lambda_rc * losses.color
            if captured or w_sc != 0.0:
                photometric = photometric + w_sc * losses.surface
            loss = loss + (1.0 - warm) * photometric
        r.mark_phase("backward")
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        r.mark_phase("optimizer")
        self.optimizer.step()
        r.mark_phase("end")
        return {"loss": loss.detach(), "color": losses.color.detach(), "surface": losses.surface.detach(),
                "eikonal": losses.eikonal.detach()}

    def _map_terms_fn(self):
        """`_map_terms`, torch.compile'd where the renderer compiles its field (CUDA with runtime.compile): the terms
        are some 90 small element-wise kernels and one more field evaluation, which compiling fuses (on an H100 `fast`'s
        step took 1.93 ms with them, bench/results/train-speed-cuda-fast-17a.md, and 1.61 ms timed without them,
        -fast-e2e-16c.md; compiled, with the sampling kernels parallel over samples, 1.63 ms: -fast-17b.md). Compiled, the
        weights come as 0-d tensors in every step (`step`), so that one compiled graph serves the plain steps before
        the capture and the captured one."""
        fn = self._map_terms_compiled
        if fn is None:
            fn = compile_in_process(self._map_terms) if self.renderer.compile_field else self._map_terms
            self._map_terms_compiled = fn
        return fn

    def _map_terms(self, d: torch.Tensor, index: torch.Tensor, depth: torch.Tensor, weight_sum: torch.Tensor,
                   z_vals: torch.Tensor, sdf: torch.Tensor, warm) -> torch.Tensor:
        """The loss terms that use the depth-search map (dimensionless), for a batch of R pixels: unit ray
        directions d [R, 3], flat pixel indices [R], the rendered depth [R] (mm) and opacity [R], the samples'
        distances z_vals [R, S] (mm) and SDF [R, S] (mm, differentiable). In the warm-up (warm 1) the rendered depth
        and full opacity are pulled onto the map; the surface term (`_surface_term`) and the free-space term
        (`_free_space_term`) act at the confirmed depths. warm: a float, or a 0-d tensor (then every term is
        computed, weighted)."""
        init = self.cfg.init
        captured = torch.is_tensor(warm)
        target = self.init_depth[index]
        ok = torch.isfinite(target).to(target.dtype)
        n = ok.sum().clamp(min=1.0)
        loss = torch.zeros((), device=depth.device)
        if captured or warm != 0.0:
            # warm-up: pull the rendered depth (and full opacity) onto the initial depth map
            depth_err = ((depth - torch.nan_to_num(target)).abs() * ok).sum() / n
            opacity = ((1.0 - weight_sum).abs() * ok).sum() / n
            loss = loss + warm * (depth_err / self._scale_mm + opacity)
        if self.surface_depth is not None:
            surface = self.surface_depth[index]
            t = torch.nan_to_num(surface) / d[:, 2]  # distance along the unit ray to camera depth surface
            per_pixel = surface_term_weights(surface, depth.detach(), warm, init.surface_weight, init.surface_after,
                                             init.surface_in_front)
            loss = loss + self._surface_term(d, t, per_pixel, n)
            if init.free_space > 0:
                bridged = free_space_weights(surface, depth.detach(), warm, init.free_space)
                loss = loss + self._free_space_term(t, bridged, z_vals, sdf, n)
        return loss

    def _surface_term(self, d: torch.Tensor, t: torch.Tensor, weight: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
        """The SDF term at the initial map's points (dimensionless: mm over the volume's scale), summed over the
        batch's pixels with per-pixel weights [R] (0 where no target) over n: |f(p)| at the point p at distance t [R]
        (mm) along each pixel's unit ray d [R, 3], plus relu(-f) at band mm before it and relu(f) at band mm
        behind it along the ray. The rendered depth's gradient reaches the SDF only through NeuS weights near
        the field's current surface, so it cannot raise a surface far in front of it (a 2.5 mm rod 100 mm in
        front of the background: bench/thin_stages.py); this term acts on the field at the point itself."""
        band = self.cfg.init.surface_band_mm
        along = torch.stack([t - band, t, t + band])  # [3, R]
        f = self.field(along[..., None] * d[None])  # [3, R] mm
        term = f[1].abs() + torch.relu(-f[0]) + torch.relu(f[2])
        return (term * weight).sum() / n / self._scale_mm

    def _free_space_term(self, t: torch.Tensor, weight: torch.Tensor, z_vals: torch.Tensor, sdf: torch.Tensor,
                         n: torch.Tensor) -> torch.Tensor:
        """The free-space term (dimensionless: mm over the volume's scale), summed over the batch's pixels with
        per-pixel weights [R] (0 where none) over n: the sum of relu(-f) over the ray's samples (z_vals [R, S] along
        the unit ray, sdf [R, S] mm, differentiable) more than MISSED_MM in front of the map's point at distance t [R]
        (mm) along the ray. The pixel sees its surface there, so the ray is empty before it; the samples
        there are the ones NeuS's up-sampling put on the field's wrong surface, so the term acts where that
        surface is, at no extra field evaluation."""
        before = (z_vals < (t - MISSED_MM)[:, None]).to(sdf.dtype)
        per_ray = (torch.relu(-sdf) * before).sum(1)
        return (per_ray * weight).sum() / n / self._scale_mm

    def _graph_step(self, pick: torch.Tensor, jitter: torch.Tensor, weights: dict) -> dict | None:
        """Replay the captured step on this iteration's draws and weights (capturing it first when needed);
        None when this step must run without the graph (the first steps after a change of frames, which
        compile kernels and create Adam's state, or after a failed capture)."""
        r = self.renderer
        key = (r.frames_version, self.init_depth is not None)
        g = self._graph
        if g is not None and g["key"] != key:  # new frames or blur: recapture after plain steps warm them up
            self._graph = g = None
            self._eager_since_change = 0
        if g is None:
            if self._eager_since_change < 2:
                return None
            g = self._capture(key)
            if g is None:
                return None
        g["pick"].copy_(pick)
        g["jitter"].copy_(jitter)
        g["warmup"].fill_(weights["warmup"])
        g["lambda_sc"].fill_(weights["lambda_sc"])
        self._stream.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(self._stream):
            g["graph"].replay()
            vals = {k: v.clone() for k, v in g["out"].items()}  # the graph's outputs change with the next replay
        torch.cuda.current_stream(self.device).wait_stream(self._stream)
        return vals

    @property
    def graph_captured(self) -> bool:
        """Whether the step is held as a captured CUDA graph now (see TrainConfig.runtime.cuda_graph)."""
        return self._graph is not None

    def reset_graph(self) -> None:
        """Drop the captured step; the next step captures it again (e.g. after setting the renderer's
        phase_hook, so that the hook's work is part of the graph)."""
        self._graph = None

    def _capture(self, key) -> dict | None:
        import warnings

        R, dev = self.cfg.sampling.rays, self.device
        g = {"key": key, "pick": torch.zeros(R, dtype=torch.long, device=dev), "jitter": torch.zeros(R, device=dev),
             "warmup": torch.zeros((), device=dev), "lambda_sc": torch.zeros((), device=dev),
             "graph": torch.cuda.CUDAGraph()}
        self._stream.wait_stream(torch.cuda.current_stream(dev))
        try:
            with torch.cuda.graph(g["graph"], stream=self._stream):
                g["out"] = self._step_body(g["pick"], g["jitter"], {"warmup": g["warmup"], "lambda_sc": g["lambda_sc"]})
        except Exception as e:  # noqa: BLE001 - any capture failure leaves plain launches, which always work
            warnings.warn(f"CUDA graph capture of the training step failed ({type(e).__name__}: {e}); "
                          "training continues without it (TrainConfig.cuda_graph=False silences this)", RuntimeWarning)
            self.use_graph = False
            self._configure_optimizer()  # back to plain Adam with a float learning rate
            torch.cuda.synchronize(dev)
            return None
        self._graph = g
        return g

    def train(self, iters: int | None = None, callback=None) -> History:
        """Run to `iters` (default: the config's) iterations, checkpointing as configured.

        Raises TrainingDiverged on a non-finite loss, keeping the last good checkpoint."""
        total = iters if iters is not None else self.cfg.schedule.iters + self.warmup_iters
        bar = Progress(total, "training", initial=self.iteration, enabled=self.progress,
                       interval_s=self.progress_interval_s)
        t_start = time.perf_counter() - self.elapsed
        stop = _StopSignals()
        try:
            stop.__enter__()
            while self.iteration < total:
                if stop.signum is not None:  # between two steps: never inside a captured graph's replay
                    bar.close()
                    self.elapsed = time.perf_counter() - t_start
                    saved = self.save_checkpoint() if self.out_dir is not None else None
                    raise TrainingInterrupted(stop.signum, self.iteration, saved)
                if (self.cfg.schedule.incremental and self.iteration > 0 and self.iteration % self.cfg.schedule.add_every == 0
                        and self.n_frames < len(self.scan)):
                    self.add_frames(count=1)
                vals = self.step()
                log_now = self.iteration % self.cfg.runtime.log_every == 0 or self.iteration == total
                if log_now:
                    v = {k: float(x) for k, x in vals.items()}
                    if not all(math.isfinite(x) for x in v.values()):
                        bar.close()
                        raise TrainingDiverged(
                            f"non-finite loss at iteration {self.iteration} ({v}); the last good checkpoint "
                            f"{'is kept at ' + str(self.out_dir / 'checkpoint.pt') if self.out_dir else 'was not written (no output folder)'}"
                            "; try a lower learning rate")
                    h = self.history
                    h.iters.append(self.iteration)
                    h.loss.append(v["loss"])
                    h.color.append(v["color"])
                    h.surface.append(v["surface"])
                    h.eikonal.append(v["eikonal"])
                    h.inv_s.append(float(self.renderer.inv_s().detach()))
                    h.frames.append(self.n_frames)
                    h.elapsed_s.append(time.perf_counter() - t_start)
                    bar.set_postfix(loss=f"{v['loss']:.4f}", rc=f"{v['color']:.4f}", sc=f"{v['surface']:.4f}",
                                    eik=f"{v['eikonal']:.3f}", inv_s=f"{h.inv_s[-1]:.3g}", frames=self.n_frames)
                    if callback is not None:
                        callback(self)
                bar.update()
                if self.out_dir is not None and self.iteration % self.cfg.runtime.checkpoint_every == 0:
                    self.elapsed = time.perf_counter() - t_start
                    self.save_checkpoint()
        finally:
            stop.__exit__()
            bar.close()
            self.elapsed = time.perf_counter() - t_start
        if self.out_dir is not None:
            self.save_checkpoint()
        return self.history

    def save_history(self, folder) -> None:
        """loss curves: history.json and loss.png."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        folder = Path(folder)
        (folder / "history.json").write_text(json.dumps(dataclasses.asdict(self.history)))
        h = self.history
        if not h.iters:
            return
        fig, ax = plt.subplots(1, 2, figsize=(10, 3.5), dpi=100)
        ax[0].semilogy(h.iters, h.color, label="L_rc (rendered colour)")
        ax[0].semilogy(h.iters, h.surface, label="L_sc (surface colour)")
        ax[0].semilogy(h.iters, h.eikonal, label="L_reg (Eikonal)")
        ax[0].set_xlabel("iteration")
        ax[0].legend(fontsize=8)
        ax[1].semilogy(h.iters, h.inv_s)
        ax[1].set_xlabel("iteration")
        ax[1].set_ylabel("inv_s (1/mm)")
        fig.tight_layout()
        fig.savefig(folder / "loss.png")
        plt.close(fig)
