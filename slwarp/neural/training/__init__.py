"""Training the neural SDF on a scan (`Trainer`), from the start that slwarp.neural.start computes.

- `trainer`: `Trainer`, which orchestrates the parts below, and `pattern_model_inputs` (a trainer's frames as the
  pattern model holds them, for the extraction).
- `terms`: the loss: the renderer's losses weighted by the schedule and the terms that use the depth-search map.
- `schedule`: the schedule (warm-up, lambda_sc, learning rate, annealing, hash-grid levels) and the Adam it drives.
- `graph_step`: the step captured once as a CUDA graph and replayed, and the random draws it reads.
- `checkpoint`: what a checkpoint holds, writing and reading it, the run identity a resumed run must match.
- `stops`: stopping at a signal or a non-finite loss; `history`: the logged losses; `progress`: progress lines.
"""
from .checkpoint import CheckpointError, CheckpointExists, RunMismatch, run_identity
from .history import History
from .stops import TrainingDiverged, TrainingInterrupted
from .terms import free_space_weights, surface_term_weights
from .trainer import Trainer, pattern_model_inputs

__all__ = ["Trainer", "surface_term_weights", "free_space_weights", "TrainingDiverged", "TrainingInterrupted",
           "CheckpointError", "CheckpointExists", "RunMismatch", "History", "run_identity", "pattern_model_inputs"]
