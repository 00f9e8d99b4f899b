"""One scan of a batch: what it runs with (`BatchOptions`), what it is (`ScanJob`), its line of the summary
(`ScanResult`), and `run_scan`, the same per-scan work under every launcher (slwarp.batch.launch) and the scanning
station (slwarp.watch)."""
from __future__ import annotations

import gc
import json
import math
import os
import sys
import time
import traceback
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Callable, Iterable

from .. import timeline

__all__ = ["COMPLETE_OUTPUTS", "CHECKPOINT", "BatchOptions", "ScanJob", "ScanResult", "outputs_complete",
           "result_from_outputs", "error_line", "run_scan", "run_scans"]

# Outputs `reconstruct` writes, config.yaml last: a folder holding all of them holds a finished run.
COMPLETE_OUTPUTS = ("depth.npy", "timings.json", "config.yaml")
# Where `reconstruct` keeps the resumable training state, relative to its output folder.
CHECKPOINT = Path("train") / "checkpoint.pt"


@dataclass(frozen=True)
class BatchOptions:
    """What every scan of a batch is reconstructed with besides the TrainConfig (see `reconstruct`): frames
    (a selection, see `Scan.frame_indices`), depth_range (near, far) mm for scans that declare none, use_mask,
    resume (see the docstring of slwarp.batch), overwrite (start each scan afresh over a checkpoint in its folder),
    progress (training progress of each scan; only when one process runs the batch), log (per-scan start and
    end lines), outside_paths (files outside a scan's folder: see `load_scan`), patterns (a pattern-set file,
    slwarp.scans.pattern_files, whose patterns replace those of each scan's frames of the same names:
    `Scan.with_patterns`; a path, read per scan, so that the options stay small to send to worker processes),
    overlap (a scan's extraction and files made in a thread while the next scan trains, `run_scans`; None: on a GPU,
    where the training leaves the host idle)."""

    frames: str | None = None
    depth_range: tuple[float, float] | None = None
    use_mask: bool = False
    resume: bool = False
    overwrite: bool = False
    progress: bool = False
    log: bool = True
    outside_paths: bool | None = None
    patterns: str | None = None
    overlap: bool | None = None


@dataclass(frozen=True)
class ScanJob:
    """A scan to reconstruct: its name, source folder, output folder and estimated cost (`scan_cost`)."""

    name: str
    source: str
    out_dir: str
    cost: float | None = None


@dataclass
class ScanResult:
    """One scan's line of the summary.

    status: done (reconstructed now), skipped (its outputs were complete: numbers from them), failed.
    seconds: wall time of the scan (skipped: of the run that wrote its outputs); valid_share: pixels with a
    depth / all pixels; mae (mm) and completeness when the scan has ground truth; error: one line;
    traceback: of a failure.
    """

    name: str
    source: str
    out_dir: str
    status: str
    worker: str = ""
    device: str = ""
    seconds: float | None = None
    frames: int | None = None
    pixels: int | None = None
    iterations: int | None = None
    valid_share: float | None = None
    mae: float | None = None
    completeness: float | None = None
    error: str | None = None
    traceback: str | None = None

    def to_dict(self) -> dict:
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, doc: dict) -> "ScanResult":
        return cls(**{f.name: doc.get(f.name) for f in fields(cls)})


def outputs_complete(out_dir: str | os.PathLike) -> bool:
    """Whether `out_dir` holds a finished reconstruction (every file of COMPLETE_OUTPUTS)."""
    return all((Path(out_dir) / f).is_file() for f in COMPLETE_OUTPUTS)


def result_from_outputs(job: ScanJob) -> ScanResult:
    """The summary line of a scan whose outputs are complete, read from them."""
    import numpy as np

    out = Path(job.out_dir)
    row = ScanResult(job.name, job.source, job.out_dir, "skipped")
    try:
        timings = json.loads((out / "timings.json").read_text())
        row.seconds, row.iterations = timings.get("total_s"), timings.get("iterations")
        depth = np.load(out / "depth.npy", allow_pickle=False)
        row.valid_share, row.pixels = float(np.isfinite(depth).mean()), int(depth.size)
        if (out / "metrics.json").is_file():
            m = json.loads((out / "metrics.json").read_text())["metrics"]
            row.mae, row.completeness = m.get("mae"), m.get("completeness")
    except (OSError, ValueError, KeyError) as e:  # outputs present but unreadable: say so, numbers stay empty
        row.error = f"outputs unreadable: {' '.join(str(e).split())}"
    return row


def error_line(error: BaseException) -> str:
    """An error as one line: its type and its message with the whitespace collapsed."""
    text = " ".join(str(error).split())
    return f"{type(error).__name__}: {text}" if text else type(error).__name__


def _release_memory() -> None:
    """Free what a finished scan left behind before the next one starts in this process (the CUDA cache)."""
    import torch

    gc.collect()
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        torch.cuda.empty_cache()


# the sizes and settings of the scan whose training graphs torch.compile holds in this process (see _fit_compiled)
_compiled_for: tuple | None = None


def _fit_compiled(scan, config) -> None:
    """Keep torch.compile's graphs for a scan of the sizes and settings they were compiled for, else drop them.

    The compiled graphs depend on the settings and the scan's image size and frame count only (the working volume
    reaches them as tensors: fields.register_volume_buffers), so the scans of one rig after the first compile
    nothing (one H100, 8 `fast` scans one after another: 22.9 -> 8.0 s a scan, bench/results/
    batch-throughput-cuda-h100x2-before.md and -cold.md). Each other size adds
    compiled versions, and past torch._dynamo's recompile limit (8) the field would run uncompiled: a new size
    starts from empty caches."""
    global _compiled_for
    import torch

    key = (scan.camera.height, scan.camera.width, len(scan), json.dumps(config.to_dict(), sort_keys=True, default=str))
    if _compiled_for is not None and key != _compiled_for and "torch._dynamo" in sys.modules:
        torch._dynamo.reset()
    _compiled_for = key


def run_scans(jobs: Iterable[ScanJob], config, options: BatchOptions = BatchOptions(), worker: str = "main",
              log: Callable[[str], None] = print, on_row: Callable[[ScanResult], None] | None = None,
              should_stop: Callable[[], bool] | None = None, device_name: str | None = None) -> list[ScanResult]:
    """run_scan over `jobs` in order, each scan loading (frames decoded, camera rays computed: scans.prefetch) in a
    thread while the scan before it trains, and its files written in a thread while the next one trains
    (reconstruct's write_in_background; a scan whose files fail is marked failed when they do). Why: a `fast` scan
    after the first took 3.6-3.9 s in a batch on an H100, of which loading was about 0.3 s and the files 0.4 s.
    With options.overlap (default: on a GPU) a scan's extraction, metrics and files are made in a thread while the
    next scan sets up and trains (reconstruct_in_background; one such thread at a time, in order): the extraction is
    mostly host work (0.75 s of a `fast` scan's 3.3 s on an H100) and the training mostly waits on the GPU.
    A row's `seconds` ends when its depth map and metrics are known; the batch's wall time counts everything.

    jobs: any iterable, drawn one ahead (the next job is taken once the current scan is in memory: a worker of a
    queue, slwarp.batch.launch, holds at most two). on_row: called with each row as soon as it is final (its files
    written, or failed), in order, from a thread of this call's own. should_stop: asked before each scan starts;
    True ends the run there (a job drawn ahead is left). Every row is final, and reported, when this returns or
    raises (a stop during training: TrainingInterrupted). device_name: how the rows and log lines name the device
    (default: the config's; a worker pinned to one GPU names it as its launcher numbered it)."""
    import queue
    import threading

    from ..scans.prefetch import ScanPrefetch

    def load(job):
        return ScanPrefetch(job.source, frames=options.frames, outside_paths=options.outside_paths,
                            patterns=options.patterns)

    finals: queue.Queue = queue.Queue()  # (row, wait for its files or None), in order; None ends
    errors: list[BaseException] = []

    def reporter() -> None:
        final = 0
        while (item := finals.get()) is not None:
            row, wait = item
            try:
                if wait is not None:
                    _settle_written(row, wait)
                final += 1
                timeline.mark(f"scan {final}")  # the row is final: its depth map and files are there
                if on_row is not None:
                    on_row(row)
            except BaseException as e:  # noqa: BLE001 - raised in the caller's thread once all are reported
                errors.append(e)

    thread = threading.Thread(target=reporter, name="slwarp-scan-rows")
    thread.start()
    todo = iter(jobs)
    rows: list[ScanResult] = []
    overlap = options.overlap if options.overlap is not None else _on_gpu(config)
    previous = [None]  # the Finishing of the scan before, when it extracts in a thread (overlap)
    try:
        job = next(todo, None)
        ahead = load(job) if job is not None else None
        while job is not None and not (should_stop is not None and should_stop()):
            current, ahead, following = ahead, None, [None]

            def load_next():
                nonlocal ahead
                following[0] = next(todo, None)
                ahead = load(following[0]) if following[0] is not None else None

            writing: list = []
            row = run_scan(job, config, options, worker, log, loaded=current, on_loaded=load_next, writing=writing,
                           device_name=device_name, overlap=overlap, after=previous[0])
            if writing and len(writing[0]) > 2:  # the next scan's extraction waits for this one's
                previous[0] = writing[0][2]
            rows.append(row)
            timeline.mark(f"scan {len(rows)} trained")
            finals.put(writing[0][:2] if writing else (row, None))
            job = following[0]
    finally:
        finals.put(None)
        thread.join()
    if errors:
        raise errors[0]
    return rows


def _settle_written(row: ScanResult, wait: Callable[[], None]) -> None:
    """Wait for a scan's files (Reconstruction.wait_written); a failure makes its row failed."""
    try:
        wait()
    except Exception as e:  # noqa: BLE001 - one scan's files, reported in its line
        row.status, row.error, row.traceback = "failed", error_line(e), traceback.format_exc()


def _on_gpu(config) -> bool:
    """Whether a run of `config` trains on a CUDA device."""
    from ..devices import torch_device

    try:
        return torch_device(config.runtime.device).type == "cuda"
    except Exception:  # noqa: BLE001 - a bad device is each scan's own error, reported in its line
        return False


def run_scan(job: ScanJob, config, options: BatchOptions = BatchOptions(), worker: str = "main",
             log: Callable[[str], None] = print, loaded=None, on_loaded: Callable[[], None] | None = None,
             writing: list | None = None, device_name: str | None = None, overlap: bool = False,
             after=None) -> ScanResult:
    """Reconstruct one scan into job.out_dir with `config` (whose runtime.device it runs on) and return its
    summary line; any error of the scan (loading, training, writing) is caught and reported in the line; a stop
    asked for (KeyboardInterrupt, SystemExit, TrainingInterrupted: Ctrl-C or SIGTERM during training, after its
    checkpoint) passes, so that the batch stops instead of going on with the next scan. loaded: a ScanPrefetch of
    job.source (else it is loaded here); on_loaded: called once the scan is in memory (run_scans loads the next);
    writing: a list to which (row, wait) is appended when the files are being written in the background (else they
    are written before this returns). overlap (with writing): return once the field is trained, the extraction and
    files made in a thread (reconstruct_in_background) that first waits for `after` (the Finishing of the scan before,
    or None); then (row, wait, finishing) is appended and wait() completes the row. device_name: how the row and the
    log lines name the device (default: the config's)."""
    from ..neural.reconstruct import reconstruct, reconstruct_in_background
    from ..neural.training import TrainingInterrupted
    from ..scans.scan import load_scan

    device = device_name or config.runtime.device
    row = ScanResult(job.name, job.source, job.out_dir, "failed", worker=worker, device=device)
    say = log if options.log else (lambda _msg: None)
    t0 = time.perf_counter()
    try:
        try:
            scan = (loaded.result() if loaded is not None
                    else load_scan(job.source, frames=options.frames, outside_paths=options.outside_paths,
                                   patterns=options.patterns))
            timeline.mark("scan in memory")
        finally:
            if on_loaded is not None:
                on_loaded()
        row.frames, row.pixels = len(scan), scan.camera.width * scan.camera.height
        _fit_compiled(scan, config)
        resume = options.resume and (Path(job.out_dir) / CHECKPOINT).is_file()
        say(f"[{worker} {device}] {job.name}: {'resuming' if resume else 'starting'} ({len(scan)} frames) -> {job.out_dir}")
        kwargs = dict(resume=resume, depth_range=options.depth_range, use_mask=options.use_mask,
                      progress=options.progress, overwrite=options.overwrite and not resume)
        if overlap and writing is not None:
            started = time.perf_counter() - t0  # loading, until the reconstruction begins
            finishing = reconstruct_in_background(scan, config, job.out_dir,
                                                  after=after.wait if after is not None else None, **kwargs)
            tag = f"[{worker} {device}] {job.name}"

            def complete() -> None:
                try:
                    res = finishing.result()
                except Exception as e:
                    row.seconds = time.perf_counter() - t0
                    _say_outcome(row, say, tag, failed=e)
                    raise
                _record(row, res, say, tag)
                row.seconds = started + res.timings["total_s"]  # until its depth map and metrics were known
                _say_outcome(row, say, tag)

            row.status = "done"
            writing.append((row, complete, finishing))
            del scan
            _release_memory()
            return row
        res = reconstruct(scan, config, out_dir=job.out_dir, write_in_background=writing is not None, **kwargs)
        if writing is not None:
            writing.append((row, res.wait_written))
        _record(row, res, say, f"[{worker} {device}] {job.name}")
        del res, scan
    except TrainingInterrupted:
        raise
    except Exception as e:  # one scan's failure, whatever it is, must not stop the others
        row.status = "failed"
        row.error, row.traceback = error_line(e), traceback.format_exc()
    row.seconds = time.perf_counter() - t0
    _release_memory()
    _say_outcome(row, say, f"[{worker} {device}] {job.name}")
    return row


def _record(row: ScanResult, res, say: Callable[[str], None], tag: str) -> None:
    """A finished Reconstruction's figures in its row: done, or failed where the field lost the surface."""
    import numpy as np

    row.status = "done"
    if res.timings.get("surface_lost"):  # its files are written, for a look; the scan counts as failed
        from ..neural.reconstruct import lost_surface_message

        row.status, row.error = "failed", lost_surface_message(res.timings["surface_lost"], res.trainer.depth_range)
    if res.timings.get("range_missed"):  # not failed: a range kept narrow on purpose leaves the rest out
        from ..neural.reconstruct import range_missed_message

        say(f"{tag}: warning: {range_missed_message(res.timings['range_missed'], res.trainer.depth_range)}")
    row.iterations = res.timings.get("iterations")
    row.valid_share = float(np.isfinite(res.depth).mean())
    if res.metrics is not None:
        row.mae, row.completeness = res.metrics.get("mae"), res.metrics.get("completeness")


def _say_outcome(row: ScanResult, say: Callable[[str], None], tag: str, failed: BaseException | None = None) -> None:
    """The row's log line: done in its seconds, or failed (`failed`: the error that ends a row being completed)."""
    if failed is not None:
        say(f"{tag}: failed after {row.seconds:.1f} s: {error_line(failed)}")
    elif row.status == "done":
        say(f"{tag}: done in {row.seconds:.1f} s, valid {row.valid_share:.1%}"
            + (f", MAE {row.mae:.3f} mm" if row.mae is not None and math.isfinite(row.mae) else ""))
    else:
        say(f"{tag}: failed after {row.seconds:.1f} s: {row.error}")

