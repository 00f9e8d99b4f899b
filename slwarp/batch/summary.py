"""The summary of a batch: `BatchSummary`, its per-scan table and totals, written as summary.json and summary.md."""
from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

from .jobs import ScanResult

__all__ = ["SUMMARY_JSON", "SUMMARY_MD", "BatchSummary"]

SUMMARY_JSON, SUMMARY_MD = "summary.json", "summary.md"
_TABLE_COLUMNS = [("status", "status", "{}"), ("worker", "worker", "{}"), ("seconds", "time s", "{:.1f}"),
                  ("iterations", "iters", "{:d}"), ("valid_share", "valid", "{:.1%}"), ("mae", "MAE mm", "{:.3f}"),
                  ("completeness", "complete", "{:.1%}")]


@dataclass
class BatchSummary:
    """The results of a batch, in the order of its scans; mode (sequential, torchrun, per-device), workers (the
    processes that ran scans), wall_s (the batch's wall time, from planning to the last result)."""

    results: list[ScanResult]
    mode: str
    workers: int
    wall_s: float
    devices: list[str] = field(default_factory=list)
    config: dict | None = None

    @property
    def failed(self) -> list[ScanResult]:
        return [r for r in self.results if r.status == "failed"]

    def totals(self) -> dict:
        """Counts by status; wall time; throughput (scans reconstructed now per hour of wall time); the mean
        MAE over the scans that have a finite one, the mean completeness over those that have ground truth."""
        done = [r for r in self.results if r.status == "done"]
        with_gt = [r for r in self.results if r.mae is not None and math.isfinite(r.mae)]
        # a scan with ground truth but no valid depth has no MAE yet a completeness of 0: it counts there
        complete = [r.completeness for r in self.results if r.completeness is not None and math.isfinite(r.completeness)]
        return {
            "scans": len(self.results), "done": len(done), "skipped": sum(r.status == "skipped" for r in self.results),
            "failed": len(self.failed), "workers": self.workers, "wall_s": self.wall_s,
            "scan_s": sum(r.seconds or 0.0 for r in done),
            "scans_per_hour": len(done) / self.wall_s * 3600.0 if self.wall_s > 0 and done else 0.0,
            "with_ground_truth": len(with_gt),
            "mean_mae": sum(r.mae for r in with_gt) / len(with_gt) if with_gt else None,
            "mean_completeness": sum(complete) / len(complete) if complete else None,
        }

    def table(self) -> str:
        """The per-scan markdown table (a '-' where a number does not apply)."""
        from ..evaluation.metrics import format_table

        return format_table([(r.name, asdict(r)) for r in self.results], columns=_TABLE_COLUMNS, title_header="scan")

    def report(self) -> str:
        """The table, the totals in a line, and each failure with its one-line error."""
        t = self.totals()
        lines = [self.table(), "",
                 f"{t['scans']} scans: {t['done']} done, {t['skipped']} skipped (complete before), {t['failed']} failed; "
                 f"{self.mode}, {self.workers} worker(s); wall {t['wall_s']:.1f} s, {t['scans_per_hour']:.1f} scans/h"
                 + (f"; mean MAE {t['mean_mae']:.3f} mm over {t['with_ground_truth']} scans with ground truth"
                    if t["mean_mae"] is not None else "")]
        lines += [f"failed: {r.name} ({r.source}): {r.error}" for r in self.failed]
        return "\n".join(lines)

    def to_dict(self) -> dict:
        totals = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in self.totals().items()}
        return {"mode": self.mode, "workers": self.workers, "devices": self.devices, "totals": totals,
                "scans": [r.to_dict() for r in self.results], "config": self.config}

    def write(self, out: str | os.PathLike) -> tuple[Path, Path]:
        """summary.json (everything, tracebacks included) and summary.md (the report) in `out`."""
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        (out / SUMMARY_JSON).write_text(json.dumps(self.to_dict(), indent=1) + "\n")
        (out / SUMMARY_MD).write_text(self.report() + "\n")
        return out / SUMMARY_JSON, out / SUMMARY_MD

