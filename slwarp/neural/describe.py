"""A run's configuration in words, for the line a command prints before training (cli, demo, batch).

    describe(config)   "hash grid 8 levels x 2^15 + MLP 1x64, 1800 iterations (300 warm-up), 384 rays, 24+16 samples"
"""
from __future__ import annotations

__all__ = ["describe", "describe_field", "describe_iterations", "total_iterations"]


def describe_field(config) -> str:
    """The field that trains: 'MLP 8x256' (hidden layers x width) or 'hash grid 8 levels x 2^15 + MLP 1x64'."""
    f = config.field
    if f.kind == "hashgrid":
        finest = "" if f.grid_finest == "auto" else f", finest {f.grid_finest}"
        return f"hash grid {f.grid_levels} levels x 2^{f.grid_log2_table}{finest} + MLP {f.grid_layers}x{f.grid_hidden}"
    return f"MLP {f.layers}x{f.hidden}"


def total_iterations(config) -> tuple[int, int]:
    """(iterations the progress bar counts, of which warm-up): the warm-up runs only after a depth search."""
    warm = config.init.iters if config.init.method == "search" else 0
    return config.schedule.iters + warm, warm


def describe_iterations(config) -> str:
    """'1800 iterations (300 warm-up)', or '4000 iterations' without a warm-up."""
    total, warm = total_iterations(config)
    return f"{total} iterations" + (f" ({warm} warm-up)" if warm else "")


def describe(config) -> str:
    """The field, the iterations as the progress bar counts them, rays per iteration and samples per ray."""
    s = config.sampling
    return f"{describe_field(config)}, {describe_iterations(config)}, {s.rays} rays, {s.n_samples}+{s.n_importance} samples"
