"""Many scans in one command: find them, share them out over processes and GPUs, reconstruct each with
`slwarp.neural.reconstruct.reconstruct`, and summarise.

    found = find_scans(["scans/", "more/scan_0*"])          # scan folders, folders of scans, globs
    summary = run_batch(found.scans, preset("paper"), "out", single=found.single)
    print(summary.report())                                  # also out/summary.json and out/summary.md

How the scans run (the same per-scan work, `run_scan`, everywhere):
- in one process, one after another (run_batch's default; the command line's on the CPU, and with --per-device 0);
- under `torchrun --nproc-per-node N` (any of torchrun's multi-node flags): the processes join a gloo process
  group, rank 0 plans (which scans are done already, what each costs) and broadcasts the plan, each rank takes
  the share `shard` gives it, on GPU LOCAL_RANK % device_count, and rank 0 gathers the results and writes the
  summary. Gloo carries only the plan and the summary (a few kB), so it works on CPUs and GPUs alike and needs
  no NCCL set-up. N = 2 x GPUs runs two scans per GPU at a time;
- with `per_device=K` (no torchrun): K worker processes per device (every visible GPU for device "cuda", the
  one given for "cuda:N", the CPU for "cpu"), started here (a WorkerPool; the command line starts it before it
  imports torch), pulling scans largest first from a queue, each loading its next scan and writing its last one
  while it trains; a worker that dies loses only the scans it held. The command line's default for several scans on
  GPUs of 20 GiB or more: K = 2 (cli.neural._per_device).

Each scan writes into out/<name>/ (out/ itself for a single scan folder: `Discovery.single`). A scan that fails
is reported with a one-line error (and its traceback in summary.json); the others go on. With resume=True a
scan whose outputs are complete (`outputs_complete`) is skipped, one with a checkpoint continues from it, and
any other starts afresh.

Modules: `discovery` (find_scans, names, costs, shares), `jobs` (BatchOptions, ScanJob, ScanResult, run_scan),
`summary` (BatchSummary), `launch` (run_batch: one after another, torchrun, worker processes per device).
"""
from __future__ import annotations

from .discovery import (SCAN_MARKERS, Discovery, ScanEntry, find_scans, is_scan_folder, largest_first, scan_cost,
                        shard, unique_names)
from .jobs import BatchOptions, ScanJob, ScanResult, outputs_complete, run_scan, run_scans
from .launch import WorkerPool, launched_by_torchrun, run_batch, visible_device_count, worker_cores, worker_devices
from .summary import BatchSummary

__all__ = [
    "SCAN_MARKERS",
    "ScanEntry",
    "Discovery",
    "find_scans",
    "is_scan_folder",
    "unique_names",
    "scan_cost",
    "largest_first",
    "shard",
    "outputs_complete",
    "BatchOptions",
    "ScanJob",
    "ScanResult",
    "BatchSummary",
    "run_scan",
    "run_scans",
    "run_batch",
    "WorkerPool",
    "visible_device_count",
    "launched_by_torchrun",
    "worker_devices",
    "worker_cores",
]
