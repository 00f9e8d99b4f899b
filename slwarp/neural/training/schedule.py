"""The training schedule (TrainConfig.schedule, and the field's level schedule) and the Adam optimiser it drives.

Iteration `it` counts from the first step, the depth-search warm-up's `warmup_iters` included (0 without a starting
map). Through the warm-up the loss is the pull onto the map (weight "warmup" 1); after it the photometric loss, with
lambda_sc = 0 for its first `sc_start` iterations, then `lambda_sc`. The learning rate: each Adam group's base rate
times `lr_factor` (1, or a cosine decay to lr_final over the whole run). NeuS's cosine annealing ratio rises from 0
to 1 over `anneal_end` iterations. A hash grid's levels switch on coarse to fine (`active_levels`).

Adam's groups (`parameter_groups`): a hash grid's tables (grid_table_lr_factor x lr), the rest of the field (lr) and
NeuS's variance (variance_lr_factor x lr). Under a CUDA graph the learning rates are device tensors that each replay
reads, and Adam's step count lives on the GPU (`configure_adam`); `set_learning_rates` fills them (no recapture).
"""
from __future__ import annotations

import math

import torch

__all__ = ["lambda_sc", "lr_factor", "cos_anneal", "step_weights", "active_levels", "set_levels", "parameter_groups",
           "configure_adam", "set_learning_rates"]


def lambda_sc(schedule, it: int) -> float:
    """The surface-colour loss's weight `it` iterations after the warm-up. schedule: a ScheduleConfig."""
    return schedule.lambda_sc if it >= schedule.sc_start else 0.0


def lr_factor(schedule, it: int, warmup_iters: int) -> float:
    """The factor on every parameter group's base learning rate at iteration `it` (1: no decay)."""
    if schedule.lr_decay == "none":
        return 1.0
    total = max(1, schedule.iters + warmup_iters)
    progress = min(1.0, it / total)
    return schedule.lr_final + (1.0 - schedule.lr_final) * 0.5 * (1.0 + math.cos(math.pi * progress))


def cos_anneal(schedule, it: int) -> float:
    """NeuS's cosine annealing ratio at iteration `it`, in [0, 1] (1: none)."""
    return 1.0 if schedule.anneal_end <= 0 else min(1.0, it / schedule.anneal_end)


def step_weights(schedule, it: int, warmup_iters: int) -> dict:
    """The step's loss weights at iteration `it`: "warmup" (1 in the depth-search warm-up, else 0) and "lambda_sc"
    (0 in the warm-up), floats."""
    warm = it < warmup_iters
    return {"warmup": 1.0 if warm else 0.0, "lambda_sc": 0.0 if warm else lambda_sc(schedule, it - warmup_iters)}


def active_levels(field_config, field, it: int, warmup_iters: int) -> int | None:
    """Hash-grid levels switched on at iteration `it` (None for a field without levels): grid_start_levels through
    the warm-up, then one more every grid_level_every iterations (all at once when 0). field_config: a FieldConfig."""
    if field_config.kind != "hashgrid" or not hasattr(field, "set_active_levels"):
        return None
    after = it - warmup_iters
    if after < 0:
        return min(field_config.grid_start_levels, field.levels)
    added = field.levels if field_config.grid_level_every == 0 else after // field_config.grid_level_every
    return min(field.levels, field_config.grid_start_levels + added)


def set_levels(field_config, field, it: int, warmup_iters: int) -> None:
    """Apply the level schedule at iteration `it` (a device-side level count: no recapture, no host sync)."""
    n = active_levels(field_config, field, it, warmup_iters)
    if n is not None and n != field.n_active:
        field.set_active_levels(n)


def parameter_groups(config, field: torch.nn.Module, variance: torch.nn.Module) -> list[dict]:
    """Adam's groups, each with its base learning rate ("base_lr", scaled by the schedule's factor): the hash
    grid's tables (grid_table_lr_factor x lr; with level_adam_steps each level with its own step count), the rest
    of the field (lr) and the NeuS variance
    (variance_lr_factor x lr); for other fields one group of everything (as checkpoints of the MLP hold it)
    unless the variance has a rate of its own. config: a TrainConfig."""
    lr = config.schedule.lr
    variance = list(variance.parameters())
    variance_lr = lr * config.schedule.variance_lr_factor
    table = getattr(field, "table", None)
    if config.field.kind != "hashgrid" or not isinstance(table, torch.nn.Parameter):
        if variance_lr == lr:
            return [{"params": list(field.parameters()) + variance, "lr": lr, "base_lr": lr}]
        return [{"params": list(field.parameters()), "lr": lr, "base_lr": lr},
                {"params": variance, "lr": variance_lr, "base_lr": variance_lr}]
    rest = [p for p in field.parameters() if p is not table]
    table_lr = lr * config.field.grid_table_lr_factor
    tables = {"params": [table], "lr": table_lr, "base_lr": table_lr}
    if config.schedule.level_adam_steps:
        # each level's rows count their own steps from the iteration the level is switched on (training.adam)
        layout = field.layout
        tables.update(segments=[(o, o + n) for o, n in zip(layout.offsets, layout.sizes)], active_segments=field.active)
    return [tables,
            {"params": rest, "lr": lr, "base_lr": lr},
            {"params": variance, "lr": variance_lr, "base_lr": variance_lr}]


def configure_adam(optimizer, device: torch.device, use_graph: bool) -> None:
    """Adam (training.adam.Adam) as the step needs it: with CUDA graphs the learning rate a device tensor that each
    replay reads; otherwise a plain float. On CUDA it runs torch's fused Adam kernel: that took the `accurate`
    preset's step from 4.70 to 4.37 ms on an H100 (docs/hashgrid.md, phase 3)."""
    optimizer.configure(device, capturable=use_graph)


def set_learning_rates(optimizer, factor: float, lr: float) -> None:
    """Each group's learning rate: its base rate (else `lr`) times the schedule's factor (a device tensor's fill
    under CUDA graphs: no recapture, no host sync)."""
    for group in optimizer.param_groups:
        rate = group.get("base_lr", lr) * factor
        if torch.is_tensor(group["lr"]):
            group["lr"].fill_(rate)
        else:
            group["lr"] = rate
