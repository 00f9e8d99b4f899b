"""How training stops before its last iteration: a signal at a step boundary, or a non-finite loss.

    stop = StopSignals()          # in the main thread: SIGINT / SIGTERM set stop.signum instead of stopping
    with stop: ... if stop.signum is not None: raise TrainingInterrupted(stop.signum, iteration, saved_checkpoint)
    raise TrainingDiverged.at(iteration, losses, out_dir)

`TrainingInterrupted` carries the exit status the command line returns (128 + signum: 130, 143).
"""
from __future__ import annotations

import signal
import threading
from pathlib import Path

__all__ = ["TrainingDiverged", "TrainingInterrupted", "StopSignals"]


class TrainingDiverged(RuntimeError):
    """The loss became non-finite; the last good checkpoint is kept."""

    @classmethod
    def at(cls, iteration: int, losses: dict, out_dir: Path | None) -> "TrainingDiverged":
        """The error for non-finite `losses` ({name: float}) at `iteration`, naming the checkpoint kept in out_dir."""
        kept = f"is kept at {out_dir / 'checkpoint.pt'}" if out_dir else "was not written (no output folder)"
        return cls(f"non-finite loss at iteration {iteration} ({losses}); the last good checkpoint {kept}; "
                   "try a lower learning rate")


class TrainingInterrupted(Exception):
    """SIGINT or SIGTERM stopped training at a step boundary after saving a checkpoint (when the run has an output
    folder). signum: the signal; checkpoint: the Path saved or None; exit_status: 128 + signum (130, 143)."""

    def __init__(self, signum: int, iteration: int, checkpoint: Path | None):
        self.signum, self.iteration, self.checkpoint = signum, iteration, checkpoint
        self.exit_status = 128 + int(signum)
        where = (f"checkpoint saved at {checkpoint}; continue with --resume (Python: resume=True)" if checkpoint
                 else "no checkpoint (no output folder)")
        super().__init__(f"interrupted by {signal.Signals(signum).name} at iteration {iteration}: {where}")


class StopSignals:
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
