"""StructuredLightRenderer: sampling + any torch SDF + the fused renderer -> the paper's three losses.

A drop-in loss for SDF training in a calibrated camera + projector rig:

    renderer = StructuredLightRenderer.from_scan(scan, sdf_module)   # sdf_module: x [..., 3] mm -> sdf [...] mm
    batch = renderer.sample_pixels(2048)
    losses = renderer(batch)                                           # .color, .surface, .eikonal
    (losses.color + lambda_sc * losses.surface + lambda_reg * losses.eikonal).backward()

Per batch of camera pixels: rays (undistorted) between the near and far depth; stratified samples
with per-ray jitter; NeuS hierarchical up-sampling (the SDF at new samples from the field without
gradient, between kernel launches); the field and its gradient (double-backward ready) at the final
samples; the fused render; and the losses
    L_rc  = mean |I'_i(r) - I_i(r)|            rendered colour, over valid pixels and patterns
    L_sc  = mean |a + b P_i(pi(s(r))) - I_i(r)| surface colour
    L_reg = mean (|grad f| - 1)^2               Eikonal, over samples inside the working volume
with a(r) = min_i I_i(r), b(r) = max_i I_i(r) - a(r) (the pattern model, slwarp.neural.pattern_model); a pixel
is valid (used by L_rc and L_sc) when it is lit with enough contrast: b(r) > contrast_threshold.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
import torch.nn as nn

from . import ops
from .fields import LearnedVariance, Volume, sdf_and_gradient
from .pattern_model import CONTRAST_THRESHOLD, blur_patterns, lit_with_contrast, offset_and_modulation


def compile_in_process(fn):
    """torch.compile(fn, dynamic=False) with Inductor compiling in this process (its `compile_threads` set to 1 for
    the process, unless the environment sets TORCHINDUCTOR_COMPILE_THREADS).

    Why: Inductor's default is a pool of compile workers (on a 16-core host 16 Python processes) started by the
    first compile. With a warm on-disk cache, as in any run after the first on a machine, `fast` on one H100 trained
    at 555 and 564 it/s against 634-645 it/s with the pool off, started by fork, or the cache cold (2.97-2.99 s
    against 2.62-2.69 s to the depth map; its steps in the bench's microbenchmark, same process, unchanged:
    bench/results/train-speed-cuda-fast-compile-workers.md). The likely reading, not measured directly: with every
    graph from the cache nothing waits for the pool, and its start-up runs during training, on the CPU that
    launches the steps. Compiling in this process warmed up no slower there (1.48-1.55 s against 1.45-2.1 s)."""
    import os

    compiled = torch.compile(fn, dynamic=False)
    if "TORCHINDUCTOR_COMPILE_THREADS" not in os.environ:
        import torch._inductor.config as inductor_config

        inductor_config.compile_threads = 1  # read at the first call, which compiles
    return compiled


class RenderLosses(NamedTuple):
    """color (L_rc), surface (L_sc), eikonal (L_reg): scalar tensors; output: the RenderOutput;
    z_vals [R, S]: the sample distances used; valid [R]: pixels the colour losses counted; sdf [R, S]: the
    field's SDF (mm) at the samples, differentiable (for terms on the samples, e.g. the trainer's free space)."""

    color: torch.Tensor
    surface: torch.Tensor
    eikonal: torch.Tensor
    output: ops.RenderOutput
    z_vals: torch.Tensor
    valid: torch.Tensor
    sdf: torch.Tensor


class PixelBatch(NamedTuple):
    """A batch of camera pixels: flat indices [R] (long), uv [R, 2], observed intensities [R, N],
    a [R], b [R], valid [R] (bool)."""

    index: torch.Tensor
    uv: torch.Tensor
    observed: torch.Tensor
    a: torch.Tensor
    b: torch.Tensor
    valid: torch.Tensor


class StructuredLightRenderer(nn.Module):
    """Sampling, field evaluation and the fused renderer for one rig and its captured frames.

    sdf: torch module x [..., 3] (camera frame, mm) -> signed distance [...] (mm).
    camera, projector: the rig; patterns [N, Hp, Wp] and images [N, H, W] in [0, 1].
    depth_range: (near, far) camera z (mm) sampled along each ray. volume: the working volume where the
    Eikonal term counts and up-sampling trusts the SDF (default: the frustum box of the valid pixels).
    variance: a module returning inv_s (1/mm); default a NeuS LearnedVariance scaled to the volume.
    n_samples coarse + n_importance up-sampled samples in up_sample_steps steps; backend "warp" | "torch".
    pattern_blur: Gaussian sigma (projector px) applied to the patterns before they are sampled, so that a
    sample sees the pattern as the camera does (projector defocus, the camera pixel's footprint); 0 = sharp.
    """

    def __init__(self, sdf: nn.Module, camera, projector, patterns, images, *, depth_range, volume: Volume | None = None,
                 variance: nn.Module | None = None, n_samples: int = 32, n_importance: int = 32, up_sample_steps: int = 4,
                 contrast_threshold: float = CONTRAST_THRESHOLD, backend: str = "warp", device=None, compile_field: bool = False,
                 pattern_blur: float = 0.0):
        super().__init__()
        if not pattern_blur >= 0:
            raise ValueError(f"pattern_blur must be >= 0 projector px, got {pattern_blur}")
        self.pattern_blur = float(pattern_blur)
        if backend not in ops.BACKENDS:
            raise ValueError(f"backend must be one of {ops.BACKENDS}, got {backend!r}")
        if up_sample_steps > 0 and n_importance % up_sample_steps:
            raise ValueError(f"n_importance ({n_importance}) must be a multiple of up_sample_steps ({up_sample_steps})")
        self.sdf = sdf
        self.camera = camera
        self.projector = projector
        self.depth_range = (float(depth_range[0]), float(depth_range[1]))
        self.n_samples, self.n_importance, self.up_sample_steps = n_samples, n_importance, up_sample_steps
        self.contrast_threshold = float(contrast_threshold)
        self.backend = backend
        self.compile_field = compile_field
        self._compiled = {}
        self.phase_hook = None  # callable(name) told when each phase of a step starts (see mark_phase)
        self._frames_version = 0
        self._emphasis = None  # (pixels [H*W] bool, share) of `emphasise`, kept across new frames
        device = torch.device(device) if device is not None else next(sdf.parameters(), torch.empty(0)).device
        self._projector_packed = ops.pack_projector(projector)
        self.set_frames(images, patterns, device=device)
        if volume is None:
            volume = Volume.from_frustum(camera, self.valid_map.cpu().numpy(), self.depth_range)
        self.volume = volume
        self.variance = variance if variance is not None else LearnedVariance(0.3, volume.scale)
        self.to(device)
        uv = camera.pixel_grid().reshape(-1, 2)
        self.register_buffer("pixel_uv", torch.as_tensor(uv, dtype=torch.float32, device=device), persistent=False)

    @classmethod
    def from_scan(cls, scan, sdf: nn.Module, **kw) -> "StructuredLightRenderer":
        """A renderer for a `slwarp.Scan` (depth range from the scan unless given)."""
        depth_range = kw.pop("depth_range", None) or scan.depth_range
        if depth_range is None:
            raise ValueError(f"{scan.source or 'scan'}: no depth range: give depth_range=(near, far) in mm")
        return cls(sdf, scan.camera, scan.projector, scan.patterns, scan.images, depth_range=depth_range, **kw)

    # --- frames -------------------------------------------------------------------------------
    def set_frames(self, images, patterns, device=None):
        """(Re)set the captured frames, e.g. to add a pattern during incremental training.

        images [N, H, W], patterns [N, Hp, Wp]; recomputes a, b and the valid-pixel map.
        """
        device = device if device is not None else self.pixel_uv.device
        images = torch.as_tensor(np.asarray(images) if not isinstance(images, torch.Tensor) else images, dtype=torch.float32).to(device)
        patterns = torch.as_tensor(np.asarray(patterns) if not isinstance(patterns, torch.Tensor) else patterns, dtype=torch.float32).to(device)
        if images.shape[0] != patterns.shape[0]:
            raise ValueError(f"{images.shape[0]} images for {patterns.shape[0]} patterns")
        if tuple(images.shape[1:]) != (self.camera.height, self.camera.width):
            raise ValueError(f"images are {tuple(images.shape[1:])}, camera is {self.camera.height}x{self.camera.width}")
        if tuple(patterns.shape[1:]) != (self.projector.height, self.projector.width):
            raise ValueError(f"patterns are {tuple(patterns.shape[1:])}, projector is {self.projector.height}x{self.projector.width}")
        self._frames_version += 1
        a, b = offset_and_modulation(images)
        self.images_flat = images.reshape(images.shape[0], -1).t().contiguous()  # [H*W, N]: one gather per batch
        self.a_flat, self.b_flat = a.reshape(-1), b.reshape(-1)
        self.valid_map = lit_with_contrast(b, self.contrast_threshold)
        self._valid_index = torch.nonzero(self.valid_map.reshape(-1)).squeeze(1)  # flat indices of the valid pixels
        self._set_draw_list()
        self.patterns = patterns
        self.patterns_hwn = ops.pack_patterns(blur_patterns(patterns, self.pattern_blur))

    def set_pattern_blur(self, sigma: float) -> None:
        """Change the Gaussian blur (projector px) of the patterns as sampled."""
        if not sigma >= 0:
            raise ValueError(f"pattern_blur must be >= 0 projector px, got {sigma}")
        self.pattern_blur = float(sigma)
        self._frames_version += 1
        self.patterns_hwn = ops.pack_patterns(blur_patterns(self.patterns, self.pattern_blur))

    @property
    def frames_version(self) -> int:
        """A number that changes whenever the frames or the pattern blur change, i.e. whenever the tensors a
        render reads are replaced: a captured CUDA graph of a step is stale once it differs."""
        return self._frames_version

    @property
    def rendered_patterns(self) -> torch.Tensor:
        """[N, Hp, Wp]: the patterns as the renderer samples them (blurred by pattern_blur)."""
        return self.patterns_hwn.permute(2, 0, 1)

    @property
    def n_frames(self) -> int:
        return int(self.patterns.shape[0])

    # --- batches ------------------------------------------------------------------------------
    def batch(self, index: torch.Tensor) -> PixelBatch:
        """The pixel batch for flat pixel indices [R] (row-major over the camera image)."""
        index = index.to(self.pixel_uv.device)
        return PixelBatch(index, self.pixel_uv[index], self.images_flat[index], self.a_flat[index], self.b_flat[index],
                          self.valid_map.reshape(-1)[index])

    def sample_pixels(self, n: int, generator: torch.Generator | None = None) -> PixelBatch:
        """n random valid pixels (uniform, with replacement)."""
        return self.valid_batch(self.draw_valid(n, generator))

    @property
    def n_valid(self) -> int:
        """The number of valid pixels (lit with contrast)."""
        return int(self._valid_index.numel())

    @property
    def n_draw(self) -> int:
        """The length of the list the draws index: the valid pixels, then the emphasised ones repeated (`emphasise`)."""
        return int(self._draw_index.numel())

    def emphasise(self, pixels: torch.Tensor | np.ndarray | None, share: float) -> int:
        """Draw about `share` (0 <= share < 1) of each batch from the valid pixels among `pixels` ([H, W] bool; None:
        none) and the rest from every valid pixel, for as long as the renderer lives (`set_frames` keeps the choice);
        returns the number of emphasised valid pixels. One uniform draw over one list, the valid pixels followed by
        the emphasised ones repeated to share / (1 - share) of the valid count: the draws stay one randint and one
        gather, as a captured step needs."""
        if not 0.0 <= share < 1.0:
            raise ValueError(f"share must be in [0, 1), got {share}")
        self._emphasis = None
        if pixels is not None and share > 0:
            mask = torch.as_tensor(np.asarray(pixels) if not isinstance(pixels, torch.Tensor) else pixels)
            if tuple(mask.shape) != (self.camera.height, self.camera.width):
                raise ValueError(f"emphasised pixels are {tuple(mask.shape)}, camera is "
                                 f"{self.camera.height}x{self.camera.width}")
            self._emphasis = (mask.to(torch.bool).reshape(-1), float(share))
        return self._set_draw_list()

    def _set_draw_list(self) -> int:
        """Build the list the draws index (`n_draw`) from the valid pixels and the emphasis; the emphasised count."""
        self._draw_index = self._valid_index
        if self._emphasis is None:
            return 0
        mask, share = self._emphasis
        chosen = self._valid_index[mask.to(self._valid_index.device)[self._valid_index]]
        if chosen.numel() == 0:
            return 0
        extra = round(share / (1.0 - share) * self.n_valid)
        repeats = -(-extra // chosen.numel())
        self._draw_index = torch.cat([self._valid_index, chosen.repeat(repeats)[:extra]])
        return int(chosen.numel())

    def draw_valid(self, n: int, generator: torch.Generator | None = None, emphasised: bool = False) -> torch.Tensor:
        """n random positions [n] (long) in the draw list, with replacement, on the generator's device: what
        `valid_batch` takes. The list's head, the valid pixels once each (uniform), or with emphasised=True the whole
        list (`n_draw`: the `emphasise`d pixels more often); the gather reads the same list either way, so a captured
        step serves both. Drawing and gathering apart lets a captured step gather on the device what was drawn on the
        host."""
        if self.n_valid == 0:
            raise ValueError("no valid pixel (lit with enough contrast) in the frames")
        dev = generator.device if generator is not None else "cpu"
        return torch.randint(0, self.n_draw if emphasised else self.n_valid, (n,), generator=generator, device=dev)

    def valid_batch(self, positions: torch.Tensor) -> PixelBatch:
        """The batch of the pixels at `positions` [R] in the draw list (long, from `draw_valid`; any device)."""
        return self.batch(self._draw_index[positions.to(self._draw_index.device)])

    # --- sampling -----------------------------------------------------------------------------
    def inv_s(self) -> torch.Tensor:
        return self.variance()

    def _field_fn(self, kind: str):
        """The field's SDF (kind 'sdf') or SDF + gradient ('grad'), torch.compile'd when asked: compiling
        fuses the MLP's element-wise work (softplus, its derivative, the explicit gradient) into few kernels."""
        fn = self._compiled.get(kind)
        if fn is None:
            base = self.sdf if kind == "sdf" else (lambda x: sdf_and_gradient(self.sdf, x))
            fn = compile_in_process(base) if self.compile_field else base
            self._compiled[kind] = fn
        return fn

    def mark_phase(self, name: str) -> None:
        """Tell `phase_hook` (when set) that a phase of a training step starts: the renderer marks "rays",
        "field" and "render"; the trainer its own phases around them. Benchmarks time the phases with it."""
        if self.phase_hook is not None:
            self.phase_hook(name)

    def draw_jitter(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """Per-ray stratification offsets [n] in [-0.5, 0.5), on the generator's device."""
        dev = generator.device if generator is not None else "cpu"
        return torch.rand(n, generator=generator, device=dev) - 0.5

    @torch.no_grad()
    def sample_rays(self, batch: PixelBatch, perturb: bool = True, generator: torch.Generator | None = None,
                    jitter: torch.Tensor | None = None):
        """(rays_o, rays_d, z_vals [R, n_samples + n_importance]) with NeuS up-sampling. jitter [R]: the
        stratification offsets to use (default: drawn from `generator` when perturb, else 0)."""
        self.mark_phase("rays")
        be = self.backend
        o, d, near, far = ops.camera_rays(batch.uv, self.camera, self.depth_range, backend=be)
        R = batch.uv.shape[0]
        if jitter is None:
            jitter = self.draw_jitter(R, generator).to(o.device) if perturb else torch.zeros(R, device=o.device)
        z = ops.stratified_samples(near, far, self.n_samples, jitter, backend=be)
        if self.n_importance > 0 and self.up_sample_steps > 0:
            bounds = self.volume.as_bounds()
            field = self._field_fn("sdf")
            sdf = field(o[:, None, :] + z[..., None] * d[:, None, :])
            per_step = self.n_importance // self.up_sample_steps
            for i in range(self.up_sample_steps):
                inv_s = 64.0 * 2**i / self.volume.scale  # NeuS's schedule, in 1/mm
                z_new = ops.upsample_samples(z, sdf, o, d, per_step, inv_s, bounds=bounds, backend=be)
                sdf_new = field(o[:, None, :] + z_new[..., None] * d[:, None, :])
                z, sdf = ops.merge_samples(z, sdf, z_new, sdf_new, backend=be)
        return o, d, z

    # --- forward ------------------------------------------------------------------------------
    def render(self, batch: PixelBatch, *, cos_anneal_ratio: float = 1.0, perturb: bool = True,
               generator: torch.Generator | None = None, jitter: torch.Tensor | None = None
               ) -> tuple[ops.RenderOutput, torch.Tensor, torch.Tensor]:
        """(RenderOutput, z_vals [R, S], sdf [R, S] mm at the samples) for a batch: gradients reach the SDF module
        and the variance."""
        o, d, z = self.sample_rays(batch, perturb, generator, jitter)
        self.mark_phase("field")
        # sample-major memory ([S, R] viewed as [R, S]): consecutive rays are adjacent, so the kernels'
        # one-thread-per-ray loads coalesce; the field does not care about the order of its points
        z_sr = z.t().contiguous()
        x = o[None, :, :] + z_sr[..., None] * d[None, :, :]
        sdf, grad = self._field_fn("grad")(x)
        self.mark_phase("render")
        out = ops.render_structured_light(
            sdf.t(), grad.transpose(0, 1), z_sr.t(), o, d, batch.a, batch.b, self.patterns_hwn, self._projector_packed, self.inv_s(),
            cos_anneal_ratio=cos_anneal_ratio, backend=self.backend, bounds=self.volume.as_bounds(),
            patterns_layout="HWN",
        )
        return out, z_sr.t(), sdf.t()

    def forward(self, batch: PixelBatch, *, cos_anneal_ratio: float = 1.0, perturb: bool = True,
                generator: torch.Generator | None = None, jitter: torch.Tensor | None = None) -> RenderLosses:
        out, z, sdf = self.render(batch, cos_anneal_ratio=cos_anneal_ratio, perturb=perturb, generator=generator,
                                  jitter=jitter)
        color, surface, eikonal = structured_light_losses(out, batch.observed, batch.valid)
        return RenderLosses(color, surface, eikonal, out, z, batch.valid, sdf)


def structured_light_losses(out: ops.RenderOutput, observed: torch.Tensor, valid: torch.Tensor):
    """(L_rc, L_sc, L_reg): L1 colour losses over valid pixels and all patterns, Eikonal mean over the
    samples inside the working volume. An empty mask gives zero colour losses (never NaN)."""
    m = valid.to(out.rendered.dtype)[:, None]
    denom = (m.sum() * observed.shape[1]).clamp(min=1.0)
    color = ((out.rendered - observed).abs() * m).sum() / denom
    surface = ((out.surface_rendered - observed).abs() * m).sum() / denom
    eikonal = out.eikonal_sum.sum() / out.eikonal_count.sum().clamp(min=1.0)
    return color, surface, eikonal
