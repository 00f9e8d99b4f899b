"""Adam for the trainer, without torch.optim.

Why not torch.optim.Adam: its first call (constructor, step, zero_grad, state_dict) imports torch._dynamo, and with it
sympy and Inductor's modules: 1.1 s of a fresh `slwarp reconstruct` on 2 CPU cores, on the critical path before the
first step. This class does the same arithmetic with the same aten kernels and nothing else:
- on CUDA, torch's fused Adam kernel (`torch._fused_adam_`), which reads the step count and, under CUDA graphs, the
  learning rate from device tensors, so a captured step replays with no host sync;
- on the CPU, the element-wise sequence of torch's single-tensor Adam (bit-identical results, tests/test_adam.py).

`state_dict()` / `load_state_dict()` use torch.optim's layout, so checkpoints written by either load in the other.
Only what the trainer uses: betas, eps, no weight decay, no amsgrad.

Segments (a group's "segments" and "active_segments"): a parameter of one group (a hash grid's table, its levels'
rows stacked) whose row ranges switch on one after another. Each segment counts its own steps, from the step it is
switched on, so its bias correction is that of a new parameter; with one count for all, a level switched on at step
t would take its first steps with the correction of step t (1 - 0.999^t instead of 0.001 for the second moment):
2-4x the group's rate for tens of steps. Segments not switched on have zero gradient and stay where they are.
"""
from __future__ import annotations

import torch


class Adam:
    """Adam over parameter groups (dicts with "params" and "lr"; other keys, e.g. "base_lr", are kept).

    configure(device, capturable): the step count lives on the device (fused kernel) on CUDA and on the CPU
    otherwise; with capturable=True each group's learning rate is a 0-d device tensor that a CUDA-graph replay
    reads (set it with fill_).

    A group of one parameter may carry "segments", [(start, stop)] row ranges of it, and "active_segments", an int
    tensor [1] on the parameter's device: segments [0, n) take steps, each with its own step count (module
    docstring). Without them every parameter has one count."""

    def __init__(self, groups: list[dict], lr: float, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        self.param_groups = []
        for g in groups:
            group = dict(g)
            group["params"] = list(group["params"])
            group.setdefault("lr", lr)
            group.setdefault("betas", tuple(betas))
            group.setdefault("eps", eps)
            if "segments" in group:
                if len(group["params"]) != 1 or "active_segments" not in group:
                    raise ValueError("Adam: a group with segments holds one parameter and its active_segments")
                rows = group["params"][0].shape[0]
                group["segments"] = [(int(a), int(b)) for a, b in group["segments"]]
                if any(not 0 <= a < b <= rows for a, b in group["segments"]):
                    raise ValueError(f"Adam: segments {group['segments']} do not lie in the parameter's {rows} rows")
            self.param_groups.append(group)
        self.state: dict[torch.nn.Parameter, dict] = {}
        self.capturable = False

    def _params(self) -> list[torch.nn.Parameter]:
        return [p for g in self.param_groups for p in g["params"]]

    # --- set-up ---------------------------------------------------------------------------------

    def configure(self, device: torch.device, capturable: bool) -> None:
        """Learning rates as device tensors (capturable) or floats; step counts where the step reads them."""
        self.capturable = bool(capturable)
        for group in self.param_groups:
            lr = float(group["lr"])
            group["lr"] = torch.tensor(lr, device=device) if self.capturable else lr
        for p, st in self.state.items():
            st["step"] = st["step"].to(self._step_device(p), torch.float32)
            if "segment_steps" in st:
                st["segment_steps"] = st["segment_steps"].to(p.device, torch.float32)

    @staticmethod
    def _step_device(p: torch.Tensor) -> torch.device:
        return p.device if p.device.type == "cuda" else torch.device("cpu")

    def _state(self, p: torch.nn.Parameter, segments: int = 0) -> dict:
        st = self.state.get(p)
        if st is None:
            st = self.state[p] = {"step": torch.zeros((), dtype=torch.float32, device=self._step_device(p)),
                                  "exp_avg": torch.zeros_like(p, memory_format=torch.preserve_format),
                                  "exp_avg_sq": torch.zeros_like(p, memory_format=torch.preserve_format)}
        if segments and "segment_steps" not in st:
            # steps each segment has taken, on the parameter's device (read there by the fused kernel, and
            # counted there under a CUDA graph)
            st["segment_steps"] = torch.zeros(segments, dtype=torch.float32, device=p.device)
        return st

    # --- the step -----------------------------------------------------------------------------

    def zero_grad(self, set_to_none: bool = True) -> None:
        for p in self._params():
            if p.grad is None:
                continue
            if set_to_none:
                p.grad = None
            else:
                p.grad.detach_().zero_()

    @torch.no_grad()
    def step(self) -> None:
        """One Adam update of every parameter that has a gradient (state created at its first gradient)."""
        for group in self.param_groups:
            params = [p for p in group["params"] if p.grad is not None]
            if not params:
                continue
            if "segments" in group:
                self._segmented(group, params[0])
                continue
            states = [self._state(p) for p in params]
            grads = [p.grad for p in params]
            if params[0].device.type == "cuda":
                self._fused(group, params, grads, states)
            else:
                self._elementwise(group, params, grads, states)

    def _segmented(self, group: dict, p: torch.nn.Parameter) -> None:
        """One step of a segmented parameter: the switched-on segments count a step, and each row range updates
        with its own count (at least 1, so a segment not yet on, whose moments are 0, does not move). Everything
        stays on the device: a CUDA graph replays it with the segment count of the moment."""
        segments = group["segments"]
        st = self._state(p, len(segments))
        st["step"] += 1
        counts = st["segment_steps"]
        index = group.get("segment_index")
        if index is None or index.device != counts.device:  # made once, not on every step
            index = group["segment_index"] = torch.arange(len(segments), device=counts.device)
        counts.add_((index < group["active_segments"].to(counts.device)).to(counts.dtype))
        steps = counts.clamp(min=1.0)
        rows = [slice(a, b) for a, b in segments]
        views = [(p[r], p.grad[r], st["exp_avg"][r], st["exp_avg_sq"][r]) for r in rows]
        if p.device.type == "cuda":
            beta1, beta2 = group["betas"]
            torch._fused_adam_([v[0] for v in views], [v[1] for v in views], [v[2] for v in views],
                               [v[3] for v in views], [], list(steps.unbind(0)), amsgrad=False, lr=group["lr"],
                               beta1=beta1, beta2=beta2, weight_decay=0.0, eps=group["eps"], maximize=False,
                               grad_scale=None, found_inf=None)
            return
        for (param, grad, exp_avg, exp_avg_sq), step in zip(views, steps.tolist()):
            self._update(group, param, grad, exp_avg, exp_avg_sq, step)

    @staticmethod
    def _update(group: dict, p, grad, exp_avg, exp_avg_sq, step: float) -> None:
        """torch's single-tensor Adam update of one tensor at step count `step` (the CPU path)."""
        beta1, beta2 = group["betas"]
        lr, eps = float(group["lr"]), group["eps"]
        exp_avg.lerp_(grad, 1 - beta1)
        exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
        step_size = lr / (1 - beta1 ** step)
        denom = (exp_avg_sq.sqrt() / (1 - beta2 ** step) ** 0.5).add_(eps)
        p.addcdiv_(exp_avg, denom, value=-step_size)

    @staticmethod
    def _fused(group: dict, params, grads, states) -> None:
        beta1, beta2 = group["betas"]
        steps = [s["step"] for s in states]
        torch._foreach_add_(steps, 1)
        torch._fused_adam_(params, grads, [s["exp_avg"] for s in states], [s["exp_avg_sq"] for s in states], [],
                           steps, amsgrad=False, lr=group["lr"], beta1=beta1, beta2=beta2, weight_decay=0.0,
                           eps=group["eps"], maximize=False, grad_scale=None, found_inf=None)

    @classmethod
    def _elementwise(cls, group: dict, params, grads, states) -> None:
        for p, grad, st in zip(params, grads, states):
            st["step"] += 1
            cls._update(group, p, grad, st["exp_avg"], st["exp_avg_sq"], st["step"].item())

    # --- torch.optim's state layout -----------------------------------------------------------

    def state_dict(self) -> dict:
        """{"state": {index: {"step", "exp_avg", "exp_avg_sq"}}, "param_groups": [{..., "params": [index]}]}, the
        parameters numbered in group order as torch.optim numbers them."""
        index = {p: i for i, p in enumerate(self._params())}
        groups = []
        for g in self.param_groups:
            # active_segments is the field's own count (its buffer) and segment_index a constant: no state
            d = {k: v for k, v in g.items() if k not in ("params", "active_segments", "segment_index")}
            d.update(weight_decay=0.0, amsgrad=False, maximize=False, capturable=self.capturable,
                     params=[index[p] for p in g["params"]])
            groups.append(d)
        return {"state": {index[p]: dict(st) for p, st in self.state.items()}, "param_groups": groups}

    def load_state_dict(self, state: dict) -> None:
        """Load a state from state_dict() (ours or torch.optim.Adam's); ValueError when the groups or the parameter
        shapes differ."""
        groups = state["param_groups"]
        if len(groups) != len(self.param_groups):
            raise ValueError(f"loaded state has {len(groups)} parameter groups, this optimiser {len(self.param_groups)}")
        for saved, group in zip(groups, self.param_groups):
            if len(saved["params"]) != len(group["params"]):
                raise ValueError("loaded state has a parameter group of a different size")
        params = {i: p for g_saved, g in zip(groups, self.param_groups) for i, p in zip(g_saved["params"], g["params"])}
        self.state = {}
        for i, st in state["state"].items():
            p = params[int(i)]
            for key in ("exp_avg", "exp_avg_sq"):
                if st[key].shape != p.shape:
                    raise ValueError(f"loaded state of a parameter of shape {tuple(st[key].shape)} for one of "
                                     f"{tuple(p.shape)}")
            self.state[p] = {"step": torch.as_tensor(st["step"], dtype=torch.float32).to(self._step_device(p)).clone(),
                             "exp_avg": st["exp_avg"].to(p.device, p.dtype).clone(),
                             "exp_avg_sq": st["exp_avg_sq"].to(p.device, p.dtype).clone()}
            if "segment_steps" in st:
                self.state[p]["segment_steps"] = torch.as_tensor(st["segment_steps"]).to(p.device, torch.float32).clone()
        for saved, group in zip(groups, self.param_groups):
            group["lr"] = float(saved["lr"])
            group["betas"] = tuple(saved.get("betas", group["betas"]))
            group["eps"] = saved.get("eps", group["eps"])
            if "base_lr" in saved:
                group["base_lr"] = saved["base_lr"]
