"""Per-pixel confidence of a neural depth map, from what the method knows about each pixel.

Each term is a map [H, W] float32 in [0, 1] (1 = trustworthy), NaN where the depth map has no depth:

- `photometric`: 1 - r, r the relative RMS residual of the pattern model at the pixel's depth
  (`pattern_model.photometric_residual`: how much of the modulation b the predicted codes leave unexplained).
  The extraction's photometric filter of old ("drop r >= 0.4") is min_confidence 0.6 on this term.
- `peak`: the share of the volume-rendering weight of the pixel's ray within `PEAK_WINDOW` coarse sample
  spacings of the extracted surface (1: the NeuS weights sit on the surface; low where they spread over a
  second surface, as at occlusion edges, or over nothing).
- `agreement`: exp(-|z_rendered - z| / `AGREEMENT_SCALE_MM`): the rendered (expected) depth of the ray against
  the extracted one.
- `uniqueness`: 1 - (residual at the depth) / (lowest residual elsewhere on the ray): how much better the pixel's
  depth explains its codes than any other depth along its ray more than `UNIQUE_EXCLUDE_PX` projector px away
  (0 where another depth explains them as well: the code is ambiguous, the few-pattern failure).
- `combined`: the geometric mean of photometric and peak.

Measured (bench/confidence.py, small rig, cpu preset, bunny and boxes; AUSE in mm, lower is better): combined
ranks the errors best (0.180 / 0.264), then photometric (0.194 / 0.285); agreement (0.281 / 0.269) and peak
(0.711 / 0.255) help on one scene only; uniqueness (0.307 / 0.446) is 0 on about a quarter of the pixels (with 6
random patterns another depth a few projector px away fits the codes as well even where the field's depth is
right) and pulls any product down. As a filter at min_confidence 0.6, photometric is better (combined's values
sit higher), so photometric stays the extraction's default.

`photometric_confidence` is slwarp.neural.pattern_model's (the training uses it too). `depth_confidence(inputs, depth,
kind, field)` is the one entry point the extraction uses: the pattern model's inputs (`state.ModelInputs`) and the
trained field where a term renders it (`state.TrainedField`), not the trainer.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from ...scans.scanner import camera_rays
from .. import ops
from ..depth_maps import on_depth
from ..ops.twin import bilinear_patterns, project_to_projector
from ..pattern_model import MIN_MODULATION, offset_and_modulation, photometric_confidence
from .state import ModelInputs, TrainedField, evaluating

__all__ = [
    "CONFIDENCE_KINDS",
    "COMBINED_TERMS",
    "ray_confidence",
    "uniqueness_confidence",
    "combine",
    "depth_confidence",
    "confidence_terms",
]

CONFIDENCE_KINDS = ("photometric", "peak", "agreement", "uniqueness", "combined")
COMBINED_TERMS = ("photometric", "peak")
# half-width of the window around the surface that `peak` counts, in coarse sample spacings along the ray
PEAK_WINDOW = 1.0
# depth difference (mm) at which `agreement` falls to 1/e
AGREEMENT_SCALE_MM = 1.0
# hypotheses whose projector pixel lies within this many projector px of the depth's own are the same basin
UNIQUE_EXCLUDE_PX = 3.0
# spacing of the hypotheses along the ray, in projector px (uniform in inverse depth)
UNIQUE_STEP_PX = 0.5


def _pixel_index(depth: np.ndarray, device) -> torch.Tensor:
    return torch.as_tensor(np.flatnonzero(np.isfinite(depth)), dtype=torch.long, device=device)


@torch.no_grad()
def ray_confidence(renderer, depth: np.ndarray, rays_per_chunk: int = 4096, window: float = PEAK_WINDOW,
                   scale_mm: float = AGREEMENT_SCALE_MM) -> tuple[np.ndarray, np.ndarray]:
    """(peak [H, W], agreement [H, W]) from volume-rendering each pixel with depth (mm, NaN invalid) through
    `renderer` (a StructuredLightRenderer with its trained field) without jitter.

    peak: sum of the weights w_k of samples within `window` coarse spacings ((far - near) / n_samples along the
    ray) of the surface at `depth`, over sum_k w_k. agreement: exp(-|rendered depth - depth| / scale_mm).
    Chunks of `rays_per_chunk` rays (the last one padded): keep it the training batch when the field is
    torch.compile'd, so no new shape is compiled."""
    H, W = depth.shape
    peak = np.full(H * W, np.nan, np.float32)
    agree = np.full(H * W, np.nan, np.float32)
    dev = renderer.pixel_uv.device
    index = _pixel_index(depth, dev)
    flat_depth = torch.as_tensor(np.asarray(depth, np.float32).reshape(-1), device=dev)
    for s0 in range(0, index.numel(), rays_per_chunk):
        idx = index[s0 : s0 + rays_per_chunk]
        n = idx.numel()
        if n < rays_per_chunk:  # pad with the last pixel: the same shape for every chunk
            idx = torch.cat([idx, idx[-1:].expand(rays_per_chunk - n)])
        batch = renderer.batch(idx)
        out, z, _ = renderer.render(batch, perturb=False)
        _, d, t_near, t_far = ops.camera_rays(batch.uv, renderer.camera, renderer.depth_range, backend=renderer.backend)
        t_surf = flat_depth[idx] / d[:, 2]
        half = window * (t_far - t_near) / renderer.n_samples
        w = out.weights
        inside = (z - t_surf[:, None]).abs() <= half[:, None]
        total = w.sum(1)
        p = torch.where(total > 0, (w * inside).sum(1) / total.clamp(min=1e-12), torch.zeros_like(total))
        a = torch.exp(-(out.depth - flat_depth[idx]).abs() / scale_mm)
        a = torch.where(torch.isfinite(a), a, torch.zeros_like(a))
        peak[idx[:n].cpu().numpy()] = p[:n].float().cpu().numpy()
        agree[idx[:n].cpu().numpy()] = a[:n].float().cpu().numpy()
    return on_depth(peak.reshape(H, W), depth), on_depth(agree.reshape(H, W), depth)


def _residual_torch(observed, a, b, pred):
    """RMS over frames of (I - a - b P) / max(b, MIN_MODULATION): observed [P, N], a, b [P], pred [P, ..., N]."""
    shape = (-1,) + (1,) * (pred.dim() - 2) + (observed.shape[1],)
    diff = observed.reshape(shape) - a.reshape(shape[:-1] + (1,)) - b.reshape(shape[:-1] + (1,)) * pred
    return torch.sqrt((diff * diff).mean(-1)) / b.clamp(min=MIN_MODULATION).reshape(shape[:-1])


@torch.no_grad()
def uniqueness_confidence(depth: np.ndarray, camera, projector, images, patterns, depth_range, *,
                          exclude_px: float = UNIQUE_EXCLUDE_PX, step_px: float = UNIQUE_STEP_PX, device="cpu",
                          points_per_chunk: int = 1 << 22) -> np.ndarray:
    """[H, W]: 1 - r(depth) / min r(z) over the depths z of the pixel's ray whose projector pixel is more than
    `exclude_px` from the depth's own (r: the relative RMS residual of `photometric_residual`).

    Hypotheses z between the near and far depth, uniform in inverse depth (so uniform in projector px along the
    epipolar line), `step_px` projector px apart at the pixel that moves most. images [N, H, W], patterns
    [N, Hp, Wp] as rendered (blurred). Computed with the torch twin's projection and bilinear sampling on `device`.
    """
    device = torch.device(device)
    H, W = depth.shape
    near, far = (float(x) for x in depth_range)
    out = np.full(H * W, np.nan, np.float32)
    index = np.flatnonzero(np.isfinite(depth))
    if index.size == 0:
        return out.reshape(H, W)
    imgs = np.asarray(images, np.float32).reshape(len(images), -1)
    a, b = offset_and_modulation(imgs)
    packed = ops.pack_projector(projector)
    pats = torch.as_tensor(np.asarray(patterns, np.float32), device=device)
    rays = torch.as_tensor(camera_rays(camera).reshape(-1, 3)[index], dtype=torch.float32, device=device)
    z0 = torch.as_tensor(np.asarray(depth, np.float32).reshape(-1)[index], device=device)
    obs = torch.as_tensor(np.ascontiguousarray(imgs[:, index].T), device=device)
    a_t = torch.as_tensor(a[index], device=device)
    b_t = torch.as_tensor(b[index], device=device)
    # the number of hypotheses: the largest projector travel from near to far over the pixels, in steps
    uv_near, _ = project_to_projector(rays * (near / rays[:, 2:3]), packed)
    uv_far, _ = project_to_projector(rays * (far / rays[:, 2:3]), packed)
    travel = float((uv_near - uv_far).norm(dim=1).max())
    n_hyp = int(min(4096, max(16, math.ceil(travel / step_px) + 1)))
    inv_z = torch.linspace(1.0 / near, 1.0 / far, n_hyp, device=device)
    per_chunk = max(1, points_per_chunk // n_hyp)
    for s0 in range(0, index.size, per_chunk):
        sl = slice(s0, s0 + per_chunk)
        r, zs = rays[sl], z0[sl]
        o, aa, bb = obs[sl], a_t[sl], b_t[sl]
        uv0, _ = project_to_projector(r * (zs / r[:, 2])[:, None], packed)  # [P, 2]
        res0 = _residual_torch(o, aa, bb, bilinear_patterns(pats, uv0))  # [P]
        x = r[:, None, :] / (r[:, None, 2:3] * inv_z[None, :, None])  # [P, n_hyp, 3]: camera z = 1 / inv_z
        uv, _ = project_to_projector(x, packed)
        res = _residual_torch(o, aa, bb, bilinear_patterns(pats, uv))  # [P, n_hyp]
        far_away = (uv - uv0[:, None, :]).norm(dim=-1) > exclude_px
        rival = torch.where(far_away, res, torch.full_like(res, float("inf"))).min(1).values
        conf = torch.where(rival > 0, 1.0 - res0 / rival, torch.zeros_like(res0))  # rival 0: a perfect other fit
        conf = torch.where(torch.isfinite(rival), conf, torch.ones_like(conf))  # no other depth on the ray
        out[index[sl]] = conf.clamp(0.0, 1.0).cpu().numpy()
    return on_depth(out.reshape(H, W), depth)


def combine(terms: dict, names=COMBINED_TERMS) -> np.ndarray:
    """The geometric mean of the named terms [H, W] (NaN where any is NaN): a pixel is trusted only as far
    as every term trusts it."""
    stack = np.stack([np.asarray(terms[n], np.float64) for n in names])
    with np.errstate(divide="ignore"):
        g = np.exp(np.mean(np.log(np.clip(stack, 0.0, 1.0)), axis=0))
    return np.where(np.isfinite(stack).all(0), g, np.nan).astype(np.float32)


def confidence_terms(inputs: ModelInputs, depth: np.ndarray, kinds=CONFIDENCE_KINDS,
                     field: TrainedField | None = None) -> dict[str, np.ndarray]:
    """{kind: [H, W] confidence} of a depth map [H, W] (mm, NaN: none) for the kinds asked (see the module docstring;
    'combined' computes the terms it needs), from the pattern model's inputs and, for peak and agreement, the
    trained field they render."""
    kinds = tuple(kinds)
    unknown = [k for k in kinds if k not in CONFIDENCE_KINDS]
    if unknown:
        raise ValueError(f"unknown confidence kind(s) {unknown}; kinds: {', '.join(CONFIDENCE_KINDS)}")
    need = set(kinds) | (set(COMBINED_TERMS) if "combined" in kinds else set())
    terms = {}
    if "photometric" in need:
        terms["photometric"] = photometric_confidence(depth, *inputs.model)
    if need & {"peak", "agreement"}:
        if field is None:
            raise ValueError("confidence kinds peak and agreement render the trained field: give `field`")
        with evaluating(field.sdf):
            terms["peak"], terms["agreement"] = ray_confidence(field.renderer, depth, field.rays)
    if "uniqueness" in need:
        # the host's arrays (uniqueness_confidence uploads what it needs itself)
        terms["uniqueness"] = uniqueness_confidence(depth, inputs.camera, inputs.projector, inputs.host_images,
                                                    inputs.host_patterns, inputs.depth_range, device=inputs.device)
    if "combined" in kinds:
        terms["combined"] = combine(terms)
    return {k: terms[k] for k in kinds}


def depth_confidence(inputs: ModelInputs, depth: np.ndarray, kind: str = "combined",
                     field: TrainedField | None = None) -> np.ndarray:
    """[H, W] float32 confidence in [0, 1] of `depth` (NaN where depth is NaN): the term `kind`
    (`confidence_terms`)."""
    return confidence_terms(inputs, depth, (kind,), field)[kind]
