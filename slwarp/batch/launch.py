"""Running a batch (`run_batch`): one scan after another in this process, over torchrun's processes, or over
worker processes started here per device, each bound to its own share of the cores (`worker_cores`); see the
package docstring (slwarp.batch)."""
from __future__ import annotations

import datetime
import os
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Callable, Sequence

from .discovery import ScanEntry, largest_first, scan_cost, shard
from .jobs import (BatchOptions, ScanJob, ScanResult, error_line, outputs_complete, result_from_outputs, run_scan,
                   run_scans)
from .summary import BatchSummary

__all__ = ["COLLECTIVE_TIMEOUT", "run_batch", "launched_by_torchrun", "worker_devices", "worker_cores"]

# Ranks that finish their share wait at the gather for the slowest one: hours on a large batch (gloo's
# default of 30 minutes would abort a healthy run). A rank that dies is torchrun's to notice, not this timeout's.
COLLECTIVE_TIMEOUT = datetime.timedelta(days=7)


def launched_by_torchrun() -> bool:
    """Whether this process is one of several that torchrun (or another launcher setting its variables)
    started: WORLD_SIZE and RANK are set."""
    return "WORLD_SIZE" in os.environ and "RANK" in os.environ


def worker_devices(device: str) -> list[str]:
    """The devices a batch's workers share out, for a config's resolved device: every visible CUDA device for
    'cuda' (no index), only that one for 'cuda:N', the CPU for 'cpu'. Worker k runs on devices[k % len]."""
    import torch

    dev = torch.device(device)
    if dev.type == "cuda" and dev.index is None:
        return [f"cuda:{i}" for i in range(torch.cuda.device_count())]
    return [str(dev)]


def worker_cores(index: int, count: int, allowed) -> list[int]:
    """The CPU cores of host-local worker `index` of `count`: a contiguous share of `allowed` (the cores this
    process may use), disjoint from the other workers' shares, sizes differing by at most one; all of `allowed`
    for a single worker or when there are fewer cores than workers."""
    cores = sorted(allowed)
    if count <= 1 or len(cores) < count:
        return cores
    index %= count
    return cores[index * len(cores) // count:(index + 1) * len(cores) // count]


def _enter_worker(device: str, index: int = 0, count: int = 1) -> None:
    """Set up host-local worker `index` of `count` for its device: with more than one worker, bound to its share of
    the cores (`worker_cores`, within any affinity the launcher gave) and torch's CPU threads to that share unless
    OMP_NUM_THREADS is set; then the current CUDA device.
    Why bind the workers slwarp starts itself (`per_device`): two plain processes on two GPUs of one host, each with
    torch's default of a thread per core, trained a scan in 1.82-1.83 s each against 1.56 s alone; bound to half of
    the 32 cores each, in 1.53 s (two H200s, bench/results/batch-concurrency-cuda-h200x2-20.md). torchrun's ranks
    enter as one worker each (no binding): torchrun sets OMP_NUM_THREADS=1, and their scans after the first already
    trained in 1.53 s unbound."""
    import torch

    if count > 1 and hasattr(os, "sched_setaffinity"):  # before CUDA starts its threads, which inherit it
        share = worker_cores(index, count, os.sched_getaffinity(0))
        os.sched_setaffinity(0, share)
        if "OMP_NUM_THREADS" not in os.environ:
            torch.set_num_threads(len(share))
    if device.startswith("cuda"):
        torch.cuda.set_device(torch.device(device))


def _plan(scans: Sequence[ScanEntry], out: Path, single: bool, resume: bool) -> tuple[list[ScanJob], list[ScanResult]]:
    """(jobs to run, summary lines of the scans skipped as complete), in the order of `scans`."""
    jobs, skipped = [], []
    for e in scans:
        job = ScanJob(e.name, str(e.source), str(out if single else out / e.name), scan_cost(e.source))
        if resume and outputs_complete(job.out_dir):
            skipped.append(result_from_outputs(job))
        else:
            jobs.append(job)
    return jobs, skipped


def _in_order(scans: Sequence[ScanEntry], rows: Sequence[ScanResult]) -> list[ScanResult]:
    by_name = {r.name: r for r in rows}
    return [by_name[e.name] for e in scans if e.name in by_name]


def run_batch(scans: Sequence[ScanEntry], config, out: str | os.PathLike, options: BatchOptions = BatchOptions(), *,
              single: bool = False, per_device: int | None = None, log: Callable[[str], None] = print
              ) -> BatchSummary | int:
    """Reconstruct `scans` (from `find_scans`) with `config` into `out`: one after another in this process,
    over torchrun's processes when launched by it, or over `per_device` worker processes per device (see the
    docstring of slwarp.batch). single: write the one scan's outputs into `out` itself.

    Writes out/summary.json and out/summary.md and returns the BatchSummary in the process that holds it (this
    one, or rank 0 under torchrun); other ranks return the number of failed scans (rank 0 reports them).
    """
    out = Path(out)
    if per_device is not None:
        if per_device < 1:
            raise ValueError(f"per_device must be >= 1, got {per_device}")
        if launched_by_torchrun():
            raise ValueError("per_device starts its own worker processes: under torchrun give --nproc-per-node "
                             "(K x GPUs for K scans per GPU) instead")
    if launched_by_torchrun() or per_device is not None:
        options = replace(options, progress=False)  # bars of several processes would interleave
    if launched_by_torchrun():
        return _run_torchrun(scans, config, out, options, single, log)
    t0 = time.perf_counter()
    jobs, skipped = _plan(scans, out, single, options.resume)
    if per_device is not None:
        devices = worker_devices(config.runtime.device)
        rows, workers = _run_spawned(jobs, config, options, devices, per_device, log), min(per_device * len(devices), len(jobs))
        mode = "per-device"
    else:
        devices, workers, mode = [config.runtime.device], 1, "sequential"
        rows = run_scans(jobs, config, options, log=log)
    summary = BatchSummary(_in_order(scans, rows + skipped), mode, workers, time.perf_counter() - t0, devices,
                           config.to_dict())
    summary.write(out)
    return summary


def _run_torchrun(scans, config, out: Path, options: BatchOptions, single: bool, log) -> BatchSummary | int:
    """This process's part of a batch under torchrun (see the docstring of slwarp.batch)."""
    import torch.distributed as dist

    owned = not dist.is_initialized()
    if owned:  # env:// rendezvous: MASTER_ADDR, MASTER_PORT, RANK, WORLD_SIZE as torchrun sets them
        dist.init_process_group("gloo", timeout=COLLECTIVE_TIMEOUT)
    try:
        rank, world = dist.get_rank(), dist.get_world_size()
        local_rank = int(os.environ.get("LOCAL_RANK", rank))
        t0 = time.perf_counter()
        box: list = [None]
        if rank == 0:  # one process decides, so that every rank sees the same plan however the files change
            try:
                box[0] = _plan(scans, out, single, options.resume)
            except Exception as e:  # the other ranks must hear of it, not wait at the broadcast
                box[0] = e
        dist.broadcast_object_list(box, src=0)
        if isinstance(box[0], Exception):
            if rank == 0:
                raise box[0]
            raise RuntimeError(f"rank 0 could not plan the batch: {error_line(box[0])}")
        jobs, skipped = box[0]
        devices = worker_devices(config.runtime.device)
        device = devices[local_rank % len(devices)]
        _enter_worker(device)
        cfg = config.with_options(device=device)
        mine = shard([j.cost for j in jobs], world)[rank]
        rows = [r.to_dict() for r in run_scans([jobs[i] for i in mine], cfg, options, worker=f"rank {rank}",
                                               log=log)]
        gathered = [None] * world if rank == 0 else None
        dist.gather_object((device, rows), gathered, dst=0)
        failed = [0]
        try:
            if rank == 0:
                results = [ScanResult.from_dict(d) for _, part in gathered for d in part]
                summary = BatchSummary(_in_order(scans, results + skipped), "torchrun", world,
                                       time.perf_counter() - t0, [d for d, _ in gathered], config.to_dict())
                summary.write(out)
                failed = [summary.failed]
        finally:
            # every rank learns whether a scan failed, so that every process exits alike: over several hosts the
            # launchers whose processes succeed wait at torchrun's exit barrier (5 min) for those whose failed
            dist.broadcast_object_list(failed, src=0)
        return summary if rank == 0 else failed[0]
    finally:
        if owned:
            dist.destroy_process_group()


def _run_spawned(jobs: list[ScanJob], config, options: BatchOptions, devices: list[str], per_device: int,
                 log) -> list[ScanResult]:
    """Run `jobs` on per_device worker processes per device; each worker pulls the next scan (largest first)
    from a queue. A worker that dies (killed, out of host memory) fails the scan it held; the others go on."""
    import multiprocessing as mp
    import queue

    n = min(per_device * len(devices), len(jobs))
    if n == 0:
        return []
    ctx = mp.get_context("spawn")  # CUDA cannot be used in forked children
    todo, events = ctx.Queue(), ctx.Queue()
    for i in largest_first([j.cost for j in jobs]):
        todo.put(i)
    for _ in range(n):
        todo.put(None)  # one stop sign per worker
    procs = [ctx.Process(target=_queue_worker, name=f"slwarp-worker-{w}",
                         args=(w, devices[w % len(devices)], n, jobs, config, options, todo, events))
             for w in range(n)]
    for p in procs:
        p.start()
    results: dict[int, ScanResult] = {}
    held: dict[int, int] = {}  # worker -> the job it runs

    def handle(event) -> None:
        kind, w, payload = event
        if kind == "start":
            held[w] = payload
        else:
            results[held.pop(w)] = ScanResult.from_dict(payload)

    try:
        while any(p.is_alive() for p in procs):
            try:
                handle(events.get(timeout=0.5))
            except queue.Empty:
                pass
        while True:  # what the last workers sent before they ended
            try:
                handle(events.get(timeout=0.1))
            except queue.Empty:
                break
    except KeyboardInterrupt:  # the workers got the same interrupt and stop at their next step
        for p in procs:
            p.join(timeout=60)
            if p.is_alive():
                p.terminate()
        raise
    finally:
        todo.cancel_join_thread()  # stop signs left by a dead worker must not hold this process at exit
    for w, p in enumerate(procs):
        p.join()
        if w in held:
            job = jobs[held[w]]
            results[held[w]] = ScanResult(job.name, job.source, job.out_dir, "failed", worker=f"worker {w}",
                                          device=devices[w % len(devices)],
                                          error=f"the worker process ended (exit code {p.exitcode}) during this scan")
    for i, job in enumerate(jobs):
        if i not in results:
            results[i] = ScanResult(job.name, job.source, job.out_dir, "failed",
                                    error="not run: every worker process ended before it")
    return [results[i] for i in range(len(jobs))]


def _queue_worker(w: int, device: str, workers: int, jobs, config, options, todo, events) -> None:
    """Worker w of the `workers` processes of `_run_spawned`: scans from `todo` until a stop sign, each reported
    to `events`."""
    try:
        _enter_worker(device, w, workers)
        cfg = config.with_options(device=device)
        while (i := todo.get()) is not None:
            events.put(("start", w, i))
            events.put(("done", w, run_scan(jobs[i], cfg, options, worker=f"worker {w}").to_dict()))
    except KeyboardInterrupt:
        sys.exit(130)
    except Exception as e:  # TrainingInterrupted (a signal during training, checkpoint saved): stop as asked
        if hasattr(e, "exit_status"):
            sys.exit(e.exit_status)
        raise

