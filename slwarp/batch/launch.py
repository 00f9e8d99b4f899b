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

from .. import timeline
from ..driver import start_driver
from .discovery import ScanEntry, largest_first, scan_cost, shard
from .jobs import (BatchOptions, ScanJob, ScanResult, error_line, outputs_complete, result_from_outputs, run_scan,
                   run_scans)
from .summary import BatchSummary

__all__ = ["COLLECTIVE_TIMEOUT", "run_batch", "WorkerPool", "visible_device_count", "visible_device_ids",
           "launched_by_torchrun", "pin_torchrun_rank", "worker_devices", "worker_cores"]

# Ranks that finish their share wait at the gather for the slowest one: hours on a large batch (gloo's
# default of 30 minutes would abort a healthy run). A rank that dies is torchrun's to notice, not this timeout's.
COLLECTIVE_TIMEOUT = datetime.timedelta(days=7)


def launched_by_torchrun() -> bool:
    """Whether this process is one of several that torchrun (or another launcher setting its variables)
    started: WORLD_SIZE and RANK are set."""
    return "WORLD_SIZE" in os.environ and "RANK" in os.environ


# the device this process was pinned to (`_pin`): "cuda:N" as numbered among the GPUs its launcher saw, while
# this process itself sees only that GPU, as cuda:0
_PINNED: str | None = None


def worker_devices(device: str) -> list[str]:
    """The devices a batch's workers share out, for a config's resolved device: every visible CUDA device for
    'cuda' (no index), only that one for 'cuda:N', the CPU for 'cpu'. Worker k runs on devices[k % len]."""
    import torch

    dev = torch.device(device)
    if _PINNED is not None and dev.type == "cuda":
        return ["cuda:0"]
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
              single: bool = False, per_device: int | None = None, pool: WorkerPool | None = None,
              log: Callable[[str], None] = print) -> BatchSummary | int:
    """Reconstruct `scans` (from `find_scans`) with `config` into `out`: one after another in this process,
    over torchrun's processes when launched by it, or over `per_device` worker processes per device (see the
    docstring of slwarp.batch). single: write the one scan's outputs into `out` itself. pool: the WorkerPool to
    run them on (started early by the caller, with this config and `options`); closed here.

    Writes out/summary.json and out/summary.md and returns the BatchSummary in the process that holds it (this
    one, or rank 0 under torchrun); other ranks return the number of failed scans (rank 0 reports them).
    """
    out = Path(out)
    try:
        if per_device is not None:
            if per_device < 1:
                raise ValueError(f"per_device must be >= 1, got {per_device}")
            if launched_by_torchrun():
                raise ValueError("per_device starts its own worker processes: under torchrun give --nproc-per-node "
                                 "(K x GPUs for K scans per GPU) instead")
        if launched_by_torchrun() or per_device is not None or pool is not None:
            options = replace(options, progress=False)  # bars of several processes would interleave
        if launched_by_torchrun():
            return _run_torchrun(scans, config, out, options, single, log)
        t0 = time.perf_counter()
        jobs, skipped = _plan(scans, out, single, options.resume)
        if per_device is not None or pool is not None:
            devices = worker_devices(config.runtime.device)
            if pool is None and jobs:
                pool = WorkerPool(min(per_device * len(devices), len(jobs)), _Fixed(config), options, per_device,
                                  device=config.runtime.device)
            rows = pool.run(jobs) if jobs else []
            workers, mode = min(pool.active if pool else 0, len(jobs)), "per-device"
        else:
            devices, workers, mode = [config.runtime.device], 1, "sequential"
            rows = run_scans(jobs, config, options, log=log)
    finally:
        if pool is not None:
            pool.close()
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
                                               log=log, device_name=device_label(device))]
        gathered = [None] * world if rank == 0 else None
        dist.gather_object((device_label(device), rows), gathered, dst=0)
        failed = [0]
        try:
            if rank == 0:
                results = [ScanResult.from_dict(d) for _, part in gathered for d in part]
                summary = BatchSummary(_in_order(scans, results + skipped), "torchrun", world,
                                       time.perf_counter() - t0, [d for d, _ in gathered], config.to_dict())
                summary.write(out)
                failed = [len(summary.failed)]  # a count: the list would reach the other ranks as their "summary"
        finally:
            # every rank learns whether a scan failed, so that every process exits alike: over several hosts the
            # launchers whose processes succeed wait at torchrun's exit barrier (5 min) for those whose failed
            dist.broadcast_object_list(failed, src=0)
        return summary if rank == 0 else failed[0]
    finally:
        if owned:
            dist.destroy_process_group()


def visible_device_count(device: str) -> int | None:
    """How many devices `worker_devices` will give for the device a user asked for ('auto', 'cpu', 'cuda',
    'cuda:N'), found without importing torch: 1 for the CPU or one named GPU; for 'cuda' and 'auto' the GPUs
    CUDA_VISIBLE_DEVICES lists, else those the NVIDIA driver lists in /proc ('auto' with none: the CPU, 1).
    None when it cannot tell (no driver listing: another platform or a sandbox). Why: `WorkerPool` starts its
    workers before the command imports torch (about 2 s), so that their own imports overlap the command's."""
    if device == "cpu" or device.startswith("cuda:"):
        return 1
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None:
        count = 0
        for entry in visible.split(","):  # CUDA stops at the first invalid entry ("-1" hides every GPU)
            entry = entry.strip()
            if not entry or entry.startswith("-"):
                break
            count += 1
    else:
        listing = Path("/proc/driver/nvidia/gpus")
        if not listing.is_dir():
            return 1 if device == "auto" and not Path("/dev/nvidiactl").exists() else None
        count = sum(1 for _ in listing.iterdir())
    if count == 0:
        return 1 if device == "auto" else None  # 'cuda' with no GPU: the command's own check says so
    return count


def visible_device_ids(device: str) -> list[str] | None:
    """The CUDA_VISIBLE_DEVICES entries of the GPUs `worker_devices` will give for the device asked for ('auto',
    'cuda', 'cuda:N'), found without starting CUDA: the variable's own entries, else the driver's indices. None
    for the CPU, or when the GPUs cannot be told (see visible_device_count)."""
    if device == "cpu":
        return None
    count = visible_device_count("cuda")
    if count is None:
        return None
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    ids = [e.strip() for e in visible.split(",")][:count] if visible is not None else [str(i) for i in range(count)]
    if device.startswith("cuda:"):
        index = int(device.split(":", 1)[1])
        return [ids[index]] if index < len(ids) else None
    return ids


def _pin(entry: str, label: str) -> None:
    """Make this process see one GPU only (CUDA_VISIBLE_DEVICES=entry), before anything starts CUDA here.
    Why: every process that starts CUDA with all of a host's GPUs visible initialises the driver for each of them;
    with four H200s the command's config step took 1.07 s against 0.27 s with one visible, and five processes doing
    it at once (a pool's workers and the command) were the slowest part of a batch's start."""
    global _PINNED
    os.environ["CUDA_VISIBLE_DEVICES"] = entry
    _PINNED = label


def pin_torchrun_rank(device: str) -> None:
    """Under torchrun, pin this rank to the GPU its LOCAL_RANK picks (`_pin`) when the device asked for is 'auto'
    or 'cuda' and several GPUs are visible; nothing otherwise. Call it before torch starts CUDA."""
    if not launched_by_torchrun() or device not in ("auto", "cuda"):
        return
    ids = visible_device_ids(device)
    if not ids or len(ids) < 2:
        return
    local = int(os.environ.get("LOCAL_RANK", os.environ.get("RANK", "0")))
    _pin(ids[local % len(ids)], f"cuda:{local % len(ids)}")
    start_driver(0)  # the rank's GPU context beside its imports (slwarp.driver)


def device_label(device: str) -> str:
    """How a batch's rows name `device`: the GPU as its launcher numbered it when this process is pinned."""
    return _PINNED if _PINNED is not None and device.startswith("cuda") else device


class WorkerPool:
    """Worker processes (spawned) that reconstruct scans pulled from a queue, largest first: `count` of them,
    worker w on devices[w % len(devices)] of `worker_devices(config.runtime.device)`, bound to its share of the
    cores (`_enter_worker`). Each builds its TrainConfig with `make_config()` (a picklable callable) and starts its
    runtimes as soon as it starts, so a pool made before the batch is planned (the command line makes it before
    importing torch) pays the workers' start-up while this process imports and plans. `run(jobs)` hands out
    the scans and returns their rows; a worker that dies (killed, out of host memory) fails the scans it held,
    the others go on. `close()` (also on leaving a `with`) stops workers that got no scans."""

    def __init__(self, count: int, make_config: Callable, options: BatchOptions, per_device: int | None = None,
                 device: str | None = None):
        """count: workers to start; per_device: at most this many per device of the config (a worker beyond it,
        when the count read without torch was more than torch sees, ends at once); device: the device asked for
        ('auto', 'cuda', 'cuda:N'; None: the workers find it from their config), whose GPUs, when they can be told
        without CUDA (`visible_device_ids`), are dealt out before the workers start: each worker sees only its own
        (`_pin`)."""
        import multiprocessing as mp

        ctx = mp.get_context("spawn")  # CUDA cannot be used in forked children
        self.count = count
        self.active = 0  # the workers that took part (known after run)
        self._todo, self._events = ctx.Queue(), ctx.Queue()
        slots = _worker_slots(device, count, per_device)
        self._procs = [ctx.Process(target=_queue_worker, name=f"slwarp-worker-{w}",
                                   args=(w, count, per_device, make_config, options, self._todo, self._events,
                                         slots[w]))
                       for w in range(count)]
        self._closed = False
        for p in self._procs:
            p.start()

    def __enter__(self) -> "WorkerPool":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Stop the workers of a pool that is not running scans (`run` closes the pool it ran): they hold no scan,
        so they are terminated at once (a bad command line is reported without waiting for their start-up)."""
        if self._closed:
            return
        self._closed = True
        for p in self._procs:
            p.terminate()
        for p in self._procs:
            p.join()
        self._release()

    def _release(self) -> None:
        """Let go of the queues, so that their semaphores are unlinked now: the command ends with os._exit, which
        runs no exit handler (multiprocessing's resource tracker then warned of leaked semaphores)."""
        for q in (self._todo, self._events):
            if q is not None:
                q.cancel_join_thread()  # stop signs left by a dead worker must not hold this process at exit
                q.close()
        self._todo = self._events = None

    def run(self, jobs: list[ScanJob]) -> list[ScanResult]:
        """Reconstruct `jobs` on the workers (one run per pool); their rows, in the order of `jobs`."""
        import queue

        if self._closed:
            raise RuntimeError("this WorkerPool is closed")
        for i in largest_first([j.cost for j in jobs]):
            self._todo.put((i, jobs[i]))
        for _ in self._procs:
            self._todo.put(None)  # one stop sign per worker
        results: dict[int, ScanResult] = {}
        held: dict[int, set[int]] = {w: set() for w in range(self.count)}  # worker -> the jobs it took
        devices: dict[int, str] = {}

        finished: set[int] = set()  # workers done with the queue, their rows sent

        def handle(event) -> None:
            kind, w, payload = event
            if kind == "bye":
                finished.add(w)
            elif kind == "device":
                devices[w] = payload
            elif kind == "start":
                held[w].add(payload)
            else:
                i, row = payload
                held[w].discard(i)
                results[i] = ScanResult.from_dict(row)

        procs = self._procs
        try:
            while len(finished) < len(procs) and any(p.is_alive() for p in procs):
                try:
                    handle(self._events.get(timeout=0.5))
                except queue.Empty:
                    pass
            while True:  # what the last workers sent before they ended
                try:
                    handle(self._events.get(timeout=0.1))
                except queue.Empty:
                    break
        except KeyboardInterrupt:  # the workers got the same interrupt and stop at their next step
            for p in procs:
                p.join(timeout=60)
                if p.is_alive():
                    p.terminate()
            raise
        finally:
            self._closed = True
        for w, p in enumerate(procs):
            p.join()
            for i in sorted(held[w]):
                job = jobs[i]
                results[i] = ScanResult(job.name, job.source, job.out_dir, "failed", worker=f"worker {w}",
                                        device=devices.get(w, ""),
                                        error=f"the worker process ended (exit code {p.exitcode}) during this scan")
        for i, job in enumerate(jobs):
            if i not in results:
                results[i] = ScanResult(job.name, job.source, job.out_dir, "failed",
                                        error="not run: every worker process ended before it")
        self.active = len(devices)
        self._release()
        return [results[i] for i in range(len(jobs))]


class _Fixed:
    """make_config for a TrainConfig known when the pool starts (picklable, unlike a lambda)."""

    def __init__(self, config):
        self.config = config

    def __call__(self):
        return self.config


def _worker_slots(device: str | None, count: int, per_device: int | None) -> list:
    """Each of `count` pool workers' GPU, dealt out before they start: (CUDA_VISIBLE_DEVICES entry, the GPU's name as
    this process numbers it, the pool's active workers) for worker w on GPU w % GPUs, "idle" for a worker beyond
    per_device x GPUs; None for every worker when the GPUs cannot be told without CUDA (the workers then share out
    what torch sees)."""
    ids = visible_device_ids(device) if device is not None else None
    if not ids:
        return [None] * count
    first = int(device.split(":", 1)[1]) if device.startswith("cuda:") else 0
    active = count if per_device is None else min(count, per_device * len(ids))
    return [(ids[w % len(ids)], f"cuda:{first + w % len(ids)}", active) if w < active else "idle"
            for w in range(count)]


def _queue_worker(w: int, workers: int, per_device: int | None, make_config: Callable, options: BatchOptions, todo,
                  events, slot=None) -> None:
    """Worker w of the `workers` processes of a WorkerPool: scans from `todo` ((index, ScanJob), None to stop),
    loaded one ahead and written in the background as `run_scans` does; each scan's taking and final row reported
    to `events`. slot: its GPU (`_worker_slots`): seen alone, "idle" to take nothing, None to take devices[w %
    len(devices)] of those torch sees. A worker beyond per_device x the devices takes nothing."""
    timeline.mark("worker started")
    if isinstance(slot, tuple):
        _pin(slot[0], slot[1])  # before make_config, which may start CUDA (the device 'auto')
        start_driver(0)  # its GPU's context beside the imports (slwarp.driver): 4 workers' starts queue in the driver
    try:
        config = make_config()
        timeline.mark("worker config")
        devices = worker_devices(config.runtime.device)
        timeline.mark("worker devices")
        if slot is None:
            active = workers if per_device is None else min(workers, per_device * len(devices))
        else:  # the parent dealt the GPUs: this worker is active with its own one, or idle
            active = slot[2] if isinstance(slot, tuple) else 0
        if w < active:
            device = devices[0] if isinstance(slot, tuple) else devices[w % len(devices)]
            _enter_worker(device, w, active)
            timeline.mark("worker entered")
            events.put(("device", w, device_label(device)))
            cfg = config.with_options(device=device)
            _warm_up(device)

            def taken():
                while (item := todo.get()) is not None:
                    i, job = item
                    timeline.mark("job taken")
                    index[job.out_dir] = i
                    events.put(("start", w, i))
                    yield job

            index: dict[str, int] = {}
            timeline.mark("worker ready")
            run_scans(taken(), cfg, options, worker=f"worker {w}", device_name=device_label(device),
                      on_row=lambda row: events.put(("done", w, (index[row.out_dir], row.to_dict()))))
            timeline.mark("worker done")
    except KeyboardInterrupt:
        sys.exit(130)
    except Exception as e:  # TrainingInterrupted (a signal during training, checkpoint saved): stop as asked
        if hasattr(e, "exit_status"):
            sys.exit(e.exit_status)
        raise
    finally:
        timeline.write()
    # Every file is written and every row sent (run_scans waits for the last scan's files). Why not a plain return:
    # the interpreter's teardown (torch's, Warp's and CUDA's exit handlers) took 1-2 s, which the batch waited for.
    events.put(("bye", w, None))
    events.close()
    events.join_thread()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


def _warm_up(device: str) -> None:
    """What a worker's first scan needs, started before it has one: the runtimes (Warp, the CUDA context) in a
    thread, and the reconstruction's modules imported here."""
    import torch

    from ..devices import start_runtimes

    start_runtimes(torch.device(device))
    from ..neural import reconstruct  # noqa: F401 - the first scan's imports, while the batch is being planned
