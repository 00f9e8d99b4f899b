"""How the training step runs on its device: on CUDA on a stream of its own, captured once as a CUDA graph and
replayed; plain launches otherwise; and where each step's random draws come from.

    steps = GraphedStep(device, enabled, body=step_body, on_failure=plain_adam, rays=R)  # enabled: CUDA, cuda_graph
    pick, jitter = steps.draw(generator, draw, key=n_valid)   # drawn DRAW_AHEAD steps at a time under a graph
    vals = steps.replay(pick, jitter, weights, key)           # None: this step runs plain
    if vals is None:
        vals = steps.run_plain(pick, jitter, weights, cos_anneal_ratio, tensor_weights)

The captured step reads its inputs from device tensors that each replay fills: the draws (pick [R] long positions in
the valid-pixel list, jitter [R]) and the weights ("warmup", "lambda_sc": 0-d); the learning rates and the hash
grid's level count are device tensors too (schedule.configure_adam, HashGridSDF.set_active_levels), so neither
recaptures. A change of `key` (the renderer's frames_version, whether there is a starting map) drops the graph; it
is captured again after two plain steps, which compile kernels and create Adam's state. Warp is told of the capture
(kernels.runtime.torch_capture), so that an array it frees meanwhile does not break it. A failed capture warns and
leaves plain launches for good, with the stream that was current before it current again (torch.cuda.graph leaves
its capture stream current when the capture's end fails: the next run in the process then worked on it, and its
depth search found no pixel). Every random draw comes from one CPU generator in the same order with or without a
graph, so both give the same run and a checkpoint's generator state (`generator_state`) resumes it exactly.
"""
from __future__ import annotations

import warnings
from contextlib import nullcontext

import torch

from slwarp.kernels import runtime

__all__ = ["DRAW_AHEAD", "DrawAhead", "GraphedStep"]

# with a CUDA graph the steps' random draws are made and sent to the GPU this many steps at a time (GraphedStep.draw)
DRAW_AHEAD = 50


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


class GraphedStep:
    """The training step's runs on `device` (see the module docstring).

    enabled: capture and replay (CUDA only; set off for good by a failed capture). body(pick, jitter, weights,
    cos_anneal_ratio=1.0) -> {name: 0-d tensor}: the step itself (render, losses, backward, Adam), on the device's
    draws; on_failure(): called after a failed capture has set `enabled` off (the trainer puts Adam back to plain
    float learning rates). rays: the batch size R."""

    def __init__(self, device: torch.device, enabled: bool, body, on_failure, rays: int):
        self.device, self.enabled, self.body, self.on_failure, self.rays = device, enabled, body, on_failure, rays
        self.stream = torch.cuda.Stream(device) if enabled else None
        self.graph = None  # the captured step: its graph, its input and output tensors and its key (`replay`)
        self.eager_since_change = 0  # plain steps since the key changed (capture needs warm kernels)
        self.ahead = None  # the draws made ahead for the coming steps (`draw`)

    # --- draws --------------------------------------------------------------------------------
    def draw(self, generator: torch.Generator, draw, key) -> tuple:
        """This step's draws `draw(generator)` (a tuple of CPU tensors): drawn now, or while `enabled` DRAW_AHEAD
        steps at a time and sent to the GPU in one copy (`DrawAhead`; key: what the draws depend on): a copy from
        pageable memory waits for the GPU to finish the steps before it, so each step's host work (draws, learning
        rate, levels, replay) added to its GPU time instead of overlapping it."""
        if not self.enabled:
            if self.ahead is not None:  # the capture failed: on from the steps taken, without drawing ahead
                self.ahead.rewind()
                self.ahead = None
            return draw(generator)
        if self.ahead is None:
            self.ahead = DrawAhead(generator, self.device, DRAW_AHEAD)
        return self.ahead.next(draw, key=key)

    def generator_state(self, generator: torch.Generator) -> torch.Tensor:
        """The generator's state after the draws of the steps taken (not those drawn ahead for later steps)."""
        return self.ahead.generator_state() if self.ahead is not None else generator.get_state()

    def forget_draws(self) -> None:
        """Drop the draws made ahead without rewinding (the generator is about to be set from a checkpoint)."""
        self.ahead = None

    # --- steps --------------------------------------------------------------------------------
    def run_plain(self, pick: torch.Tensor, jitter: torch.Tensor, weights: dict, cos_anneal_ratio: float,
                  tensor_weights: bool) -> dict:
        """The step as plain launches (on the step's stream when there is one). tensor_weights: pass the weights
        as 0-d device tensors, as the captured step does, so that one compiled graph of the map terms serves both."""
        stream = torch.cuda.stream(self.stream) if self.stream is not None else nullcontext()
        if self.stream is not None:
            self.stream.wait_stream(torch.cuda.current_stream(self.device))
        if tensor_weights:
            weights = {k: torch.full((), v, device=self.device) for k, v in weights.items()}  # a fill: no host copy
        with stream:
            vals = self.body(pick.to(self.device), jitter.to(self.device), weights, cos_anneal_ratio)
        if self.stream is not None:
            torch.cuda.current_stream(self.device).wait_stream(self.stream)
        self.eager_since_change += 1
        return vals

    def replay(self, pick: torch.Tensor, jitter: torch.Tensor, weights: dict, key) -> dict | None:
        """Replay the captured step on this iteration's draws and float weights (capturing it first when needed);
        None when this step must run plain (the first steps after a change of key, which compile kernels and
        create Adam's state, or after a failed capture)."""
        g = self.graph
        if g is not None and g["key"] != key:  # new frames or blur: recapture after plain steps warm them up
            self.graph = g = None
            self.eager_since_change = 0
        if g is None:
            if self.eager_since_change < 2:
                return None
            g = self._capture(key)
            if g is None:
                return None
        g["pick"].copy_(pick)
        g["jitter"].copy_(jitter)
        g["warmup"].fill_(weights["warmup"])
        g["lambda_sc"].fill_(weights["lambda_sc"])
        self.stream.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(self.stream):
            g["graph"].replay()
            vals = {k: v.clone() for k, v in g["out"].items()}  # the graph's outputs change with the next replay
        torch.cuda.current_stream(self.device).wait_stream(self.stream)
        return vals

    @property
    def captured(self) -> bool:
        """Whether the step is held as a captured CUDA graph now."""
        return self.graph is not None

    def reset(self) -> None:
        """Drop the captured step; the next replay captures it again."""
        self.graph = None

    def _capture(self, key) -> dict | None:
        R, dev = self.rays, self.device
        g = {"key": key, "pick": torch.zeros(R, dtype=torch.long, device=dev), "jitter": torch.zeros(R, device=dev),
             "warmup": torch.zeros((), device=dev), "lambda_sc": torch.zeros((), device=dev),
             "graph": torch.cuda.CUDAGraph()}
        current = torch.cuda.current_stream(dev)
        self.stream.wait_stream(current)
        try:
            # thread-local: another thread's CUDA work (a batch's extraction of the scan before) may go on meanwhile
            with (torch.cuda.graph(g["graph"], stream=self.stream, capture_error_mode="thread_local"),
                  runtime.torch_capture(self.stream)):
                g["out"] = self.body(g["pick"], g["jitter"], {"warmup": g["warmup"], "lambda_sc": g["lambda_sc"]})
        except Exception as e:  # noqa: BLE001 - any capture failure leaves plain launches, which always work
            torch.cuda.set_stream(current)
            warnings.warn(f"CUDA graph capture of the training step failed ({type(e).__name__}: {e}); "
                          "training continues without it (TrainConfig.cuda_graph=False silences this)", RuntimeWarning)
            self.enabled = False
            self.on_failure()  # back to plain Adam with a float learning rate
            torch.cuda.synchronize(dev)
            return None
        self.graph = g
        return g
