"""Many scans in one command: find them, share them out over processes and GPUs, reconstruct each with
`slwarp.neural.reconstruct.reconstruct`, and summarise.

    found = find_scans(["scans/", "more/scan_0*"])          # scan folders, folders of scans, globs
    summary = run_batch(found.scans, preset("paper"), "out", single=found.single)
    print(summary.report())                                  # also out/summary.json and out/summary.md

How the scans run (the same per-scan work, `run_scan`, everywhere):
- in one process, one after another (the default);
- under `torchrun --nproc-per-node N` (any of torchrun's multi-node flags): the processes join a gloo process
  group, rank 0 plans (which scans are done already, what each costs) and broadcasts the plan, each rank takes
  the share `shard` gives it, on GPU LOCAL_RANK % device_count, and rank 0 gathers the results and writes the
  summary. Gloo carries only the plan and the summary (a few kB), so it works on CPUs and GPUs alike and needs
  no NCCL set-up. N = 2 x GPUs runs two scans per GPU at a time;
- with `per_device=K` (no torchrun): K worker processes per device (every visible GPU for device "cuda", the
  one given for "cuda:N", the CPU for "cpu"), started here, pulling scans largest first from a queue; a worker
  that dies loses only the scan it held.

Each scan writes into out/<name>/ (out/ itself for a single scan folder: `Discovery.single`). A scan that fails
is reported with a one-line error (and its traceback in summary.json); the others go on. With resume=True a
scan whose outputs are complete (`outputs_complete`) is skipped, one with a checkpoint continues from it, and
any other starts afresh.
"""
from __future__ import annotations

import datetime
import gc
import glob
import json
import math
import os
import sys
import time
import traceback
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Callable, Sequence

from .scans.scan import SCAN_FILE, ScanError

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
    "run_batch",
    "launched_by_torchrun",
    "worker_devices",
]

# The files by which `load_scan` recognises a scan folder's layout: native, NeSS, procam-calibration.
SCAN_MARKERS = (SCAN_FILE, "config.ini", "calibration_result.xml")
# Outputs `reconstruct` writes, config.yaml last: a folder holding all of them holds a finished run.
COMPLETE_OUTPUTS = ("depth.npy", "timings.json", "config.yaml")
# Where `reconstruct` keeps the resumable training state, relative to its output folder.
CHECKPOINT = Path("train") / "checkpoint.pt"
# Ranks that finish their share wait at the gather for the slowest one: hours on a large batch (gloo's
# default of 30 minutes would abort a healthy run). A rank that dies is torchrun's to notice, not this timeout's.
COLLECTIVE_TIMEOUT = datetime.timedelta(days=7)
SUMMARY_JSON, SUMMARY_MD = "summary.json", "summary.md"
_GLOB_CHARS = frozenset("*?[")


# ----------------------------------------------------------------------------------------------
# finding the scans


@dataclass(frozen=True)
class ScanEntry:
    """One scan of a batch: `name` (its output folder's name, unique in the batch) and `source` (the folder)."""

    name: str
    source: Path


@dataclass
class Discovery:
    """What `find_scans` found: the scans (sorted by name), whether the command named one scan folder (its
    outputs then go straight into --out, as for a lone scan always), and the folders it passed over (in a
    folder of scans or among a glob's matches, holding no scan)."""

    scans: list[ScanEntry]
    single: bool
    ignored: list[Path] = field(default_factory=list)


def is_scan_folder(path: str | os.PathLike) -> bool:
    """Whether `path` is a folder `load_scan` recognises (it holds one of SCAN_MARKERS)."""
    path = Path(path)
    return path.is_dir() and any((path / m).is_file() for m in SCAN_MARKERS)


def _has_glob(spec: str) -> bool:
    return any(c in _GLOB_CHARS for c in spec)


def _scans_in(folder: Path, ignored: list[Path]) -> list[Path]:
    """The scan folders among `folder`'s immediate subfolders (sorted); the other subfolders go to `ignored`."""
    found = []
    for sub in sorted(p for p in folder.iterdir() if p.is_dir()):
        (found if is_scan_folder(sub) else ignored).append(sub)
    return found


def find_scans(specs: Sequence[str | os.PathLike]) -> Discovery:
    """The scans named by command-line words: each a scan folder, a folder of scan folders (its immediate
    subfolders that are scans) or a glob (`scans/day1_*`, `data/**/scan.yaml`; quote it so that the shell leaves
    it alone) whose matches are either. A `scan.yaml` file stands for its folder. The same folder named twice
    is one scan.

    Raises ScanError for a word that names no scan (a path that does not exist, a folder holding no scan, a
    glob matching none): a mistake in the command, reported before any work starts. A scan folder that exists
    but cannot be loaded is a scan of the batch: it fails alone when it runs.
    """
    if not specs:
        raise ScanError("no scan given")
    single = False
    paths: list[Path] = []
    ignored: list[Path] = []
    for spec in map(str, specs):
        if _has_glob(spec):
            matches = [Path(m) for m in sorted(glob.glob(spec, recursive=True))]
            matches = [m.parent if m.name == SCAN_FILE else m for m in matches]
            folders = [m for m in matches if m.is_dir()]
            added = 0
            for m in folders:
                if is_scan_folder(m):
                    paths.append(m)
                    added += 1
                    continue
                passed_over: list[Path] = []
                inside = _scans_in(m, passed_over)
                paths.extend(inside)
                added += len(inside)
                ignored.extend(passed_over if inside else [m])  # a match holding no scan is passed over whole
            if not added:
                raise ScanError(f"{spec}: no scan matches (a scan is a folder with one of {', '.join(SCAN_MARKERS)})")
            continue
        path = Path(spec)
        if path.is_file() and path.name == SCAN_FILE:
            path = path.parent
        if not path.exists():
            raise ScanError(f"scan not found: {spec}")
        if is_scan_folder(path):
            paths.append(path)
            single = len(specs) == 1
            continue
        if not path.is_dir():
            raise ScanError(f"{spec}: not a scan folder (a scan is a folder with one of {', '.join(SCAN_MARKERS)})")
        inside = _scans_in(path, ignored)
        if not inside:
            raise ScanError(f"{spec}: holds no scan (neither it nor its subfolders has one of {', '.join(SCAN_MARKERS)})")
        paths.extend(inside)
    unique: dict[Path, Path] = {}
    for p in paths:
        unique.setdefault(p.resolve(), Path(os.path.abspath(p)))
    folders = list(unique.values())
    names = unique_names(folders)
    scans = sorted((ScanEntry(n, p) for n, p in zip(names, folders)), key=lambda e: e.name)
    return Discovery(scans, single, ignored)


def unique_names(folders: Sequence[Path]) -> list[str]:
    """Output-folder names for scan folders: each folder's own name; folders that share a name take their
    parents' names in front, joined with '-', one level at a time until they differ (day1/bunny and
    day2/bunny: day1-bunny, day2-bunny); names still equal after that get -2, -3, ... in the given order."""
    parts = [tuple(p for p in Path(f).parts if p != Path(f).anchor) for f in folders]
    depth = [1] * len(folders)

    def name(i: int) -> str:
        return "-".join(parts[i][-depth[i]:]) or "scan"

    while True:
        groups: dict[str, list[int]] = {}
        for i in range(len(folders)):
            groups.setdefault(name(i), []).append(i)
        grew = False
        for members in groups.values():
            if len(members) > 1:
                for i in members:
                    if depth[i] < len(parts[i]):
                        depth[i] += 1
                        grew = True
        if not grew:
            break
    names, seen = [], {}
    for i in range(len(folders)):
        n = name(i)
        seen[n] = seen.get(n, 0) + 1
        names.append(n if seen[n] == 1 else f"{n}-{seen[n]}")
    return names


# ----------------------------------------------------------------------------------------------
# sharing the scans out


def scan_cost(folder: str | os.PathLike) -> float | None:
    """The relative cost of reconstructing a scan: camera pixels x frames, read from a native scan.yaml
    without loading images (the depth search and the extraction grow with both; training is the same for
    every scan of a config). None when it cannot be told cheaply (other layouts, an unreadable scan.yaml)."""
    import yaml

    try:
        doc = yaml.safe_load((Path(folder) / SCAN_FILE).read_text())
        cam = doc["camera"]
        return float(int(cam["width"]) * int(cam["height"]) * len(doc["frames"]))
    except Exception:  # any unreadable or malformed file: the scan itself reports it when it runs
        return None


def _known_costs(costs: Sequence[float | None]) -> list[float]:
    """Costs with the unknown ones set to the mean of the known ones (1 when none is known)."""
    known = [c for c in costs if c is not None]
    fill = sum(known) / len(known) if known else 1.0
    return [fill if c is None else float(c) for c in costs]


def largest_first(costs: Sequence[float | None]) -> list[int]:
    """Indices of the scans by decreasing cost; equal costs keep their order (unknown costs: see
    `_known_costs`)."""
    full = _known_costs(costs)
    return sorted(range(len(full)), key=lambda i: (-full[i], i))


def shard(costs: Sequence[float | None], n_workers: int) -> list[list[int]]:
    """Deterministic shares of the scans for `n_workers` workers (longest processing time first): scans by
    decreasing cost, each to the worker with the least total cost so far (the lowest-numbered one on a tie).
    Returns, per worker, the indices of its scans in the order it runs them. Equal costs deal round-robin."""
    if n_workers < 1:
        raise ValueError(f"n_workers must be >= 1, got {n_workers}")
    full = _known_costs(costs)
    shares: list[list[int]] = [[] for _ in range(n_workers)]
    load = [0.0] * n_workers
    for i in largest_first(full):
        w = min(range(n_workers), key=lambda k: (load[k], k))
        shares[w].append(i)
        load[w] += full[i]
    return shares


# ----------------------------------------------------------------------------------------------
# one scan


@dataclass(frozen=True)
class BatchOptions:
    """What every scan of a batch is reconstructed with besides the TrainConfig (see `reconstruct`): frames
    (a selection, see `Scan.frame_indices`), depth_range (near, far) mm for scans that declare none, use_mask,
    resume (see the module docstring), overwrite (start each scan afresh over a checkpoint in its folder),
    progress (training progress of each scan; only when one process runs the batch), log (per-scan start and
    end lines), outside_paths (files outside a scan's folder: see `load_scan`)."""

    frames: str | None = None
    depth_range: tuple[float, float] | None = None
    use_mask: bool = False
    resume: bool = False
    overwrite: bool = False
    progress: bool = False
    log: bool = True
    outside_paths: bool | None = None


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


def _result_from_outputs(job: ScanJob) -> ScanResult:
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


def _one_line(error: BaseException) -> str:
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
    reaches them as tensors: field.register_volume_buffers), so the scans of one rig after the first compile
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


def run_scan(job: ScanJob, config, options: BatchOptions = BatchOptions(), worker: str = "main",
             log: Callable[[str], None] = print) -> ScanResult:
    """Reconstruct one scan into job.out_dir with `config` (whose runtime.device it runs on) and return its
    summary line; any error of the scan (loading, training, writing) is caught and reported in the line; a stop
    asked for (KeyboardInterrupt, SystemExit, TrainingInterrupted: Ctrl-C or SIGTERM during training, after its
    checkpoint) passes, so that the batch stops instead of going on with the next scan."""
    from .neural.reconstruct import reconstruct
    from .neural.train import TrainingInterrupted
    from .scans.scan import load_scan

    import numpy as np

    device = config.runtime.device
    row = ScanResult(job.name, job.source, job.out_dir, "failed", worker=worker, device=device)
    say = log if options.log else (lambda _msg: None)
    t0 = time.perf_counter()
    try:
        scan = load_scan(job.source, frames=options.frames, outside_paths=options.outside_paths)
        row.frames, row.pixels = len(scan), scan.camera.width * scan.camera.height
        _fit_compiled(scan, config)
        resume = options.resume and (Path(job.out_dir) / CHECKPOINT).is_file()
        say(f"[{worker} {device}] {job.name}: {'resuming' if resume else 'starting'} ({len(scan)} frames) -> {job.out_dir}")
        res = reconstruct(scan, config, out_dir=job.out_dir, resume=resume, depth_range=options.depth_range,
                          use_mask=options.use_mask, progress=options.progress, overwrite=options.overwrite and not resume)
        row.status = "done"
        row.iterations = res.timings.get("iterations")
        row.valid_share = float(np.isfinite(res.depth).mean())
        if res.metrics is not None:
            row.mae, row.completeness = res.metrics.get("mae"), res.metrics.get("completeness")
        del res, scan
    except TrainingInterrupted:
        raise
    except Exception as e:  # one scan's failure, whatever it is, must not stop the others
        row.error, row.traceback = _one_line(e), traceback.format_exc()
    row.seconds = time.perf_counter() - t0
    _release_memory()
    if row.status == "done":
        say(f"[{worker} {device}] {job.name}: done in {row.seconds:.1f} s, valid {row.valid_share:.1%}"
            + (f", MAE {row.mae:.3f} mm" if row.mae is not None and math.isfinite(row.mae) else ""))
    else:
        say(f"[{worker} {device}] {job.name}: failed after {row.seconds:.1f} s: {row.error}")
    return row


# ----------------------------------------------------------------------------------------------
# the summary

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
        from .evaluation.metrics import format_table

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


# ----------------------------------------------------------------------------------------------
# running a batch


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
            skipped.append(_result_from_outputs(job))
        else:
            jobs.append(job)
    return jobs, skipped


def _in_order(scans: Sequence[ScanEntry], rows: Sequence[ScanResult]) -> list[ScanResult]:
    by_name = {r.name: r for r in rows}
    return [by_name[e.name] for e in scans if e.name in by_name]


def run_batch(scans: Sequence[ScanEntry], config, out: str | os.PathLike, options: BatchOptions = BatchOptions(), *,
              single: bool = False, per_device: int | None = None, log: Callable[[str], None] = print
              ) -> BatchSummary | None:
    """Reconstruct `scans` (from `find_scans`) with `config` into `out`: one after another in this process,
    over torchrun's processes when launched by it, or over `per_device` worker processes per device (see the
    module docstring). single: write the one scan's outputs into `out` itself.

    Writes out/summary.json and out/summary.md and returns the BatchSummary in the process that holds it (this
    one, or rank 0 under torchrun); other ranks return None.
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
        rows = [run_scan(job, config, options, log=log) for job in jobs]
    summary = BatchSummary(_in_order(scans, rows + skipped), mode, workers, time.perf_counter() - t0, devices,
                           config.to_dict())
    summary.write(out)
    return summary


def _run_torchrun(scans, config, out: Path, options: BatchOptions, single: bool, log) -> BatchSummary | None:
    """This process's part of a batch under torchrun (see the module docstring)."""
    import torch.distributed as dist

    owned = not dist.is_initialized()
    if owned:  # env:// rendezvous: MASTER_ADDR, MASTER_PORT, RANK, WORLD_SIZE as torchrun sets them
        dist.init_process_group("gloo", timeout=COLLECTIVE_TIMEOUT)
    try:
        rank, world = dist.get_rank(), dist.get_world_size()
        local_rank = int(os.environ.get("LOCAL_RANK", rank))
        local_world = int(os.environ.get("LOCAL_WORLD_SIZE", world))
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
            raise RuntimeError(f"rank 0 could not plan the batch: {_one_line(box[0])}")
        jobs, skipped = box[0]
        devices = worker_devices(config.runtime.device)
        device = devices[local_rank % len(devices)]
        _enter_worker(device)
        cfg = config.with_options(device=device)
        mine = shard([j.cost for j in jobs], world)[rank]
        rows = [run_scan(jobs[i], cfg, options, worker=f"rank {rank}", log=log).to_dict() for i in mine]
        gathered = [None] * world if rank == 0 else None
        dist.gather_object((device, rows), gathered, dst=0)
        if rank != 0:
            return None
        results = [ScanResult.from_dict(d) for _, part in gathered for d in part]
        summary = BatchSummary(_in_order(scans, results + skipped), "torchrun", world, time.perf_counter() - t0,
                               [d for d, _ in gathered], config.to_dict())
        summary.write(out)
        return summary
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
