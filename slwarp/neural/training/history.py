"""A training run's logged losses (`History`): what a checkpoint keeps, history.json and loss.png."""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["History"]


@dataclass
class History:
    """Lists, one entry per logged iteration: the iteration, the step's losses (loss, color: L_rc, surface: L_sc,
    eikonal: L_reg; dimensionless), NeuS's inv_s, the frames in use and the training's wall time (s)."""

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

    def record(self, iteration: int, losses: dict, inv_s: float, frames: int, elapsed_s: float) -> None:
        """Log an iteration: losses {"loss", "color", "surface", "eikonal": float}."""
        self.iters.append(iteration)
        self.loss.append(losses["loss"])
        self.color.append(losses["color"])
        self.surface.append(losses["surface"])
        self.eikonal.append(losses["eikonal"])
        self.inv_s.append(inv_s)
        self.frames.append(frames)
        self.elapsed_s.append(elapsed_s)

    def save(self, folder) -> None:
        """The loss curves into `folder`: history.json and (once anything is logged) loss.png."""
        from ...evaluation.viz import save_loss_curves

        folder = Path(folder)
        (folder / "history.json").write_text(json.dumps(dataclasses.asdict(self)))
        if self.iters:
            save_loss_curves(folder / "loss.png", self.iters, {"L_rc (rendered colour)": self.color,
                                                               "L_sc (surface colour)": self.surface,
                                                               "L_reg (Eikonal)": self.eikonal}, self.inv_s)
