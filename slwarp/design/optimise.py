"""Pattern design by gradient descent: K projector images that minimise the expected miss of `objective.miss_loss`.

Parameterisation: a code along the rig's epipolar direction, theta [K, L] (L samples one projector px apart on the
coordinate t = (u, v) . e, e the mean direction of the epipolar lines in the projector image); the pattern image is
that code sampled at each projector pixel's t (linear in t), so every projector row that an epipolar line crosses
carries the same code, as a Gray code's columns do. Why not a free image [K, Hp, Wp]: a batch's gradient reaches each
of its million values a few times, and two batches' gradients were nearly orthogonal (cosine 0.01 on the small rig):
the descent random-walked and the design got worse; along the lines, every pixel of a batch informs the same L
values. Each code sample is s = sigmoid(theta) rescaled over the K frames to span exactly 0..1,
P = (s - min_k s) / (max_k s - min_k s). Why: the pattern model reads each camera pixel's offset and modulation as the
min and max of its K intensities, which is exact only where the code reaches both 0 and 1; it also gives every pixel
the projector's full contrast. The camera sees P blurred (`blur_px`), so the design spends no effort on detail the
optics remove.

Start: smooth random codes (white noise blurred by `init_scale_px`), so that the codes vary on the scale of a few px
from the first step. Adam on theta; each step draws a new batch of pixels, depths, offsets, modulations and noise
(the design is for the rig, never for a scene). A fixed validation batch measures the loss and the miss rate (the
share of pixels whose most probable hypothesis is off by more than `tol_px`) every `report_every` steps; the best
patterns by that measure are the result.

Binary output (DLP projectors that show 1-bit frames fastest): each value rounded at 0.5, and a pixel whose K bits
came out all equal gets its highest value set to 1 and its lowest to 0.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np
import torch

from ..neural.pattern_model import blur_patterns
from ..scans.patterns import PatternSet
from ..scans.roles import FrameRole
from .objective import CodeModel, NoiseModel, code_image, miss_loss

__all__ = ["DesignOptions", "DesignResult", "design_patterns", "normalised_codes", "binarise", "evaluate_patterns"]


@dataclass
class DesignOptions:
    """How to design K patterns. iterations: Adam steps; pixels: camera pixels per step; lr: Adam's learning rate on
    theta; tol_px: a miss is a hypothesis farther than this (projector px) from the truth; step_px: the spacing of the
    depth hypotheses along the line (projector px); softness: scales the posterior's noise; init_scale_px: smoothness
    of the start (projector px); binary: sharpened towards 0/1 over the descent's last two thirds (BINARY_START),
    scored as rounded, rounded at the end; seed: every random draw; validation_pixels: the fixed batch that picks
    the best patterns; report_every: steps between validations; window: the radius (camera px) of the window whose
    pixels share a depth hypothesis, as the depth search's (2), 0: each pixel alone (a window of (2 window + 1)^2
    pixels costs as many reprojections, so each batch then holds that many times fewer windows); window_step: the
    camera px between a window's pixels (1: every pixel; 2: a window of the same count spans twice as far); backend: "warp" (the
    reprojection's Warp kernels), "torch" (its twin) or "auto": Warp on CUDA, the twin on the CPU (Warp's CPU kernels run
    on one core, torch's on all of them: 3x faster on 2 cores)."""

    count: int = 4
    iterations: int = 1500
    pixels: int = 4096
    lr: float = 0.05
    tol_px: float = 2.0
    step_px: float = 0.5
    softness: float = 1.0
    init_scale_px: float = 3.0
    binary: bool = False
    seed: int = 0
    validation_pixels: int = 8192
    report_every: int = 100
    window: int = 0
    window_step: int = 1
    backend: str = "auto"
    noise: NoiseModel = field(default_factory=NoiseModel)

    def __post_init__(self):
        if self.count < 2:
            raise ValueError(f"a design needs at least 2 patterns, got --count {self.count}")
        if self.iterations < 0 or self.pixels < 1 or self.validation_pixels < 1 or self.report_every < 1:
            raise ValueError("iterations must be >= 0; pixels, validation pixels and report_every >= 1")
        if not (self.lr > 0 and self.tol_px > 0 and self.step_px > 0 and self.softness > 0):
            raise ValueError("lr, tol_px, step_px and softness must be > 0")
        if self.window < 0:
            raise ValueError(f"the window's radius must be >= 0 camera px, got --window {self.window}")
        if self.window_step < 1:
            raise ValueError(f"the window's step must be >= 1 camera px, got --window-step {self.window_step}")
        if self.window_step > 1 and self.window == 0:  # the step would reach the roles, and the search, for nothing
            raise ValueError(f"--window-step {self.window_step} spaces a window's pixels: give the window too "
                             "(--window 2, the depth search's)")

    def windows(self, pixels: int) -> int:
        """How many windows a batch of `pixels` camera pixels' worth of reprojections holds."""
        return max(1, pixels // (2 * self.window + 1) ** 2)


@dataclass
class DesignResult:
    """patterns: the designed PatternSet (names design{K}_{i}); history: {"iteration", "loss", "miss_rate"} lists of
    the validations; baselines: {set name: {"loss", "miss_rate"}} of classical sets of the same rig on the same
    validation batch; timings (s); hypotheses per pixel; interrupted: stopped early (Ctrl-C), the best so far kept."""

    patterns: PatternSet
    options: DesignOptions
    history: dict
    final: dict
    baselines: dict
    timings: dict
    hypotheses: int
    span_px: float
    interrupted: bool = False

    def to_json(self) -> dict:
        """Plain JSON / YAML types (tuples as lists)."""
        opts = asdict(self.options)
        opts["noise"] = {k: list(v) if isinstance(v, tuple) else v for k, v in opts["noise"].items()}
        return {"options": opts, "history": self.history, "final": self.final, "baselines": self.baselines,
                "timings": self.timings, "hypotheses": self.hypotheses, "epipolar_span_px": self.span_px,
                "interrupted": self.interrupted}


def normalised_codes(theta: torch.Tensor) -> torch.Tensor:
    """theta [K, ...] -> codes in [0, 1] whose K values span exactly 0..1 at every position."""
    return _span_unit(torch.sigmoid(theta))


def _span_unit(s: torch.Tensor) -> torch.Tensor:
    """s [K, ...] rescaled over the K values to span 0..1 at every position."""
    lo = s.min(0, keepdim=True).values
    hi = s.max(0, keepdim=True).values
    return (s - lo) / (hi - lo).clamp_min(1.0e-6)


def binarise(patterns):
    """[K, Hp, Wp] in [0, 1] -> 0/1 with each pixel's highest value 1 and lowest 0 (every pixel keeps a code);
    a numpy array or a torch tensor, returned as the same kind."""
    t = torch.as_tensor(np.asarray(patterns, np.float32)) if isinstance(patterns, np.ndarray) else patterns
    out = (t >= 0.5).to(t.dtype)
    out.scatter_(0, t.argmax(0, keepdim=True), 1.0)
    out.scatter_(0, t.argmin(0, keepdim=True), 0.0)
    return out.numpy() if isinstance(patterns, np.ndarray) else out


# binary designs: the descent sharpens the patterns towards black and white over its last part, so that the
# rounding at the end changes little (rounding a grey design of 4 afterwards took the small rig's misses from 8.6%
# to 23.6%, worse than 6 random patterns' 16.4%)
BINARY_START = 1.0 / 3.0  # the share of the descent before the sharpening starts
BINARY_BETA = (2.0, 40.0)  # the sharpening's slope: sigmoid(beta (p - 0.5)), from the first to the last step


def _sharpness(it: int, iterations: int) -> float:
    """beta of step `it` (0: none) for a binary design, rising geometrically over the descent's last part."""
    start = BINARY_START * iterations
    if it < start:
        return 0.0
    f = (it - start) / max(iterations - start, 1.0)
    return BINARY_BETA[0] * (BINARY_BETA[1] / BINARY_BETA[0]) ** f


def _smooth_start(K: int, L: int, scale_px: float, generator: torch.Generator, device) -> torch.Tensor:
    """theta [K, L]: white noise blurred by `scale_px`, rescaled to std 2 (codes that vary over a few px)."""
    x = torch.randn(K, 1, L, generator=generator, device=device)
    x = blur_patterns(x, scale_px)[:, 0]
    return 2.0 * x / x.std(dim=1, keepdim=True).clamp_min(1e-6)


def evaluate_patterns(model: CodeModel, patterns: torch.Tensor, batch, opts: DesignOptions) -> dict:
    """{"loss", "miss_rate"} of patterns [K, Hp, Wp] (unblurred, as projected) on a batch: the mean over the blurs
    the camera may see (NoiseModel.observed_blurs), decoded with the modelled one."""
    losses, misses = [], []
    with torch.no_grad():
        modelled = blur_patterns(patterns, opts.noise.blur_px)
        for sigma in opts.noise.observed_blurs():
            loss, info = miss_loss(modelled, batch, opts.noise, tol_px=opts.tol_px, softness=opts.softness,
                                   backend=_backend(opts.backend, patterns.device), details=True,
                                   observed=blur_patterns(patterns, sigma))
            losses.append(float(loss))
            misses.append(info["miss_rate"])
    return {"loss": float(np.mean(losses)), "miss_rate": float(np.mean(misses))}


def design_patterns(camera, projector, depth_range, opts: DesignOptions, *, device="cpu", baselines=("random6",),
                    progress=None) -> DesignResult:
    """Design opts.count patterns for the rig (camera, projector; depth_range camera z in mm) on `device`.

    baselines: named pattern sets (slwarp.scans.patterns.named_set) scored on the same validation batch for
    comparison. progress(text): called with one line per validation (None: silent). Ctrl-C stops the descent and
    returns the best patterns so far (interrupted=True)."""
    from ..scans.patterns import designed_names, named_set

    t0 = time.perf_counter()
    device = torch.device(device)
    opts = replace(opts, backend=_backend(opts.backend, device))
    K, H, W = opts.count, projector.height, projector.width
    model = CodeModel(camera, projector, depth_range, opts.noise, step_px=opts.step_px, device=device)
    g = torch.Generator(device=device)
    g.manual_seed(opts.seed)
    # the validation batch: fixed, drawn from its own seed so that it does not depend on the training draws
    gv = torch.Generator(device=device)
    gv.manual_seed(opts.seed + 7919)
    val = model.batch(opts.windows(opts.validation_pixels), K, gv, opts.window, opts.window_step)
    base = {}
    for name in baselines:
        pset = named_set(name, W, H)
        pv = model.batch(opts.windows(opts.validation_pixels), len(pset), _seeded(device, opts.seed + 7919), opts.window,
                         opts.window_step)
        base[name] = evaluate_patterns(model, torch.as_tensor(pset.patterns, device=device), pv, opts)
    theta = _smooth_start(K, model.code_length, opts.init_scale_px, g, device).requires_grad_(True)

    def patterns_of(th: torch.Tensor) -> torch.Tensor:
        # rescaled again per projector pixel: between two code samples of different order the interpolation
        # would span less than 0..1
        return _span_unit(code_image(normalised_codes(th), model.coords))

    adam = GlobalAdam(theta, lr=opts.lr)
    t1 = time.perf_counter()
    history = {"iteration": [], "loss": [], "miss_rate": [], "seconds": []}
    best = (math.inf, theta.detach().clone())
    interrupted = False

    def validate(it: int):
        nonlocal best
        pats = patterns_of(theta.detach())
        m = evaluate_patterns(model, binarise(pats) if opts.binary else pats, val, opts)  # as they will be shown
        history["iteration"].append(it)
        history["loss"].append(m["loss"])
        history["miss_rate"].append(m["miss_rate"])
        history["seconds"].append(time.perf_counter() - t1)
        if m["loss"] < best[0]:
            best = (m["loss"], theta.detach().clone())
        if progress:
            progress(f"step {it:5d}/{opts.iterations}  loss {m['loss']:.4f}  misses {100 * m['miss_rate']:5.2f}%  "
                     f"{time.perf_counter() - t1:6.1f} s")

    try:
        validate(0)
        for it in range(1, opts.iterations + 1):
            batch = model.batch(opts.windows(opts.pixels), K, g, opts.window, opts.window_step)
            pats = patterns_of(theta)
            beta = _sharpness(it, opts.iterations) if opts.binary else 0.0
            if beta > 0.0:
                pats = torch.sigmoid(beta * (pats - 0.5))
            seen = blur_patterns(pats, opts.noise.blur_px)
            # the camera's blur drawn anew each step: codes that only the modelled blur reads right are misses
            observed = None
            if opts.noise.blur_spread > 1.0:
                u = 2.0 * float(torch.rand((), generator=g, device=device)) - 1.0
                observed = blur_patterns(pats, opts.noise.observed_blurs(u)[0])
            loss = miss_loss(seen, batch, opts.noise, tol_px=opts.tol_px, softness=opts.softness, backend=opts.backend,
                             observed=observed)
            theta.grad = None
            loss.backward()
            adam.step()
            if it % opts.report_every == 0 or it == opts.iterations:
                validate(it)
    except KeyboardInterrupt:
        interrupted = True
    t2 = time.perf_counter()
    pats = patterns_of(best[1]).cpu().numpy()
    if opts.binary:
        pats = binarise(pats)
    pats = np.round(pats * 255.0) / 255.0  # what an 8-bit projector shows (and the pattern-set file holds)
    final = evaluate_patterns(model, torch.as_tensor(pats, device=device), val, opts)
    names = designed_names(K)
    # a set designed for spaced windows says so in its roles: the depth search then sums the same windows
    roles = ({n: FrameRole("designed", index=i, count=K, window_step=opts.window_step) for i, n in enumerate(names)}
             if opts.window_step > 1 else None)
    pset = PatternSet(pats.astype(np.float32), names, roles)
    timings = {"setup_s": t1 - t0, "descent_s": t2 - t1, "total_s": time.perf_counter() - t0}
    return DesignResult(pset, opts, history, final, base, timings, model.hypotheses, model.span_px, interrupted)


class GlobalAdam:
    """Adam with one second moment for the whole tensor: steps of lr x m / rms(g).

    Why not torch's Adam: each step's batch reaches a different part of the projector image, and a per-value second
    moment turns the tiny gradients of a rarely seen pixel into full-size steps: the values random-walk and the
    design got worse while the loss on any fixed batch fell. One shared scale keeps the steps in proportion to the
    gradients."""

    def __init__(self, param: torch.Tensor, lr: float, betas=(0.9, 0.999), eps: float = 1e-12):
        self.param, self.lr, self.betas, self.eps = param, lr, betas, eps
        self.m = torch.zeros_like(param)
        self.v = torch.zeros((), dtype=param.dtype, device=param.device)
        self.t = 0

    @torch.no_grad()
    def step(self) -> None:
        b1, b2 = self.betas
        g = self.param.grad
        self.t += 1
        self.m.mul_(b1).add_(g, alpha=1 - b1)
        self.v.mul_(b2).add_((g * g).mean(), alpha=1 - b2)
        m_hat = self.m / (1 - b1 ** self.t)
        v_hat = self.v / (1 - b2 ** self.t)
        self.param.sub_(self.lr * m_hat / (v_hat.sqrt() + self.eps))


def _backend(backend: str, device: torch.device) -> str:
    """The reprojection's backend: "auto" is Warp on CUDA and the torch twin on the CPU."""
    return ("warp" if device.type == "cuda" else "torch") if backend == "auto" else backend


def _seeded(device, seed: int) -> torch.Generator:
    g = torch.Generator(device=device)
    g.manual_seed(seed)
    return g
