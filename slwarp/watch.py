"""A scanning station: one long-lived process that reconstructs each scan folder that lands in an inbox.

    slwarp watch INBOX --out OUT --preset fast          # the command
    station = Station(preset("fast"), options)          # the same warm worker from Python
    row = station.reconstruct("inbox/part_017", "out/part_017")
    rows = station.run(jobs, on_row=print)              # many ScanJobs, loading and writing beside the training

The process keeps what a process pays once (imports, the device's start, kernel modules, compiled graphs of
the scans' size), so each scan after the first costs its reconstruction alone. As in a batch (slwarp.batch.run_scans),
a scan that is ready loads while the one before trains and, on a GPU, its depth map is extracted and its files written
while the next one trains (a `fast` scan every 2.7 s on an H100, bench/watch_station.py; a batch there took 3.6 s a
scan before it overlapped them); its line is printed as soon as its files are complete. A scan folder is taken once it
is complete: its scan.yaml parses and every file it names (frames' images and patterns, gt_depth, mask) is present,
and no file of the folder has changed size or time for `settle_s` (a scanner still copying frames is waited for).
A scan's files are read from inside its folder only (slwarp.scans.scan.load_scan with outside_paths=False).
Other layouts (NeSS config.ini, procam calibration_result.xml) are taken once their folder has settled. OUT/NAME
with complete outputs is skipped; OUT/NAME with a checkpoint continues from it. A broken scan is reported in one
line and not retried until its folder changes. Entries of the inbox that are links leading out of it are
ignored (said once). Ctrl-C or SIGTERM stops the station: between scans at once, during training at the next
step boundary with a checkpoint (the scan continues on the next start), during extraction or writing after the
scan's outputs are complete; a finished scan is never lost (its outputs appear together: staged_outputs).
"""
from __future__ import annotations

import math
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Iterable

from .batch import SCAN_MARKERS, BatchOptions, ScanJob, ScanResult, outputs_complete, run_scan, run_scans
from .scans.scan import SCAN_FILE, inside_folder

DEFAULT_POLL_S = 0.5
DEFAULT_SETTLE_S = 1.0


def _listed_files(folder: Path) -> list[Path] | str:
    """The files a native scan folder's scan.yaml names (frames, gt_depth, mask), or why they cannot be listed
    yet (an unreadable or half-written scan.yaml)."""
    import yaml

    try:
        doc = yaml.safe_load((folder / SCAN_FILE).read_text())
    except (OSError, yaml.YAMLError) as e:
        return f"{SCAN_FILE} not readable yet ({type(e).__name__})"
    if not isinstance(doc, dict) or not isinstance(doc.get("frames"), list):
        return f"{SCAN_FILE} has no frame list yet"
    files = []
    for fr in doc["frames"]:
        if isinstance(fr, dict):
            files += [folder / str(fr[k]) for k in ("image", "pattern") if fr.get(k)]
    files += [folder / str(doc[k]) for k in ("gt_depth", "mask") if doc.get(k)]
    return files


def _signature(folder: Path) -> tuple:
    """(name, size, mtime) of every file under `folder`: equal twice `settle_s` apart means nothing is being
    written there."""
    sig = []
    for root, _dirs, names in os.walk(folder):
        for n in names:
            try:
                st = os.stat(os.path.join(root, n))
            except OSError:  # removed meanwhile: the next poll sees the folder anew
                continue
            sig.append((os.path.join(root, n), st.st_size, st.st_mtime_ns))
    return tuple(sorted(sig))


def scan_complete(folder: str | os.PathLike) -> tuple[bool, str]:
    """(whether `folder` holds a complete scan, why not): a native scan when scan.yaml parses and every file it
    names exists; another layout when its marker file exists. Settling (no file still growing) is the
    Watcher's part."""
    folder = Path(folder)
    if (folder / SCAN_FILE).is_file():
        files = _listed_files(folder)
        if isinstance(files, str):
            return False, files
        missing = [f for f in files if not f.is_file()]
        if missing:
            return False, f"{len(missing)} listed file(s) missing, e.g. {missing[0].name}"
        return True, ""
    if any((folder / m).is_file() for m in SCAN_MARKERS):
        return True, ""
    return False, "no scan file yet"


class Station:
    """A warm worker for library users: reconstructs scan after scan in this process with one config (see the
    module docstring); `reconstruct` returns the scan's summary line (slwarp.batch.ScanResult, never raises for
    a broken scan: status 'failed' with a one-line error)."""

    def __init__(self, config, options: BatchOptions = BatchOptions(log=False)):
        self.config = config.validate()
        self.options = options
        self.results: list[ScanResult] = []

    def reconstruct(self, source: str | os.PathLike, out_dir: str | os.PathLike, name: str | None = None) -> ScanResult:
        """Reconstruct the scan folder `source` into `out_dir`; its files are complete when this returns."""
        job = ScanJob(name or Path(source).name, str(source), str(out_dir))
        row = run_scan(job, self.config, self.options, worker="station")
        self.results.append(row)
        return row

    def run(self, jobs: Iterable[ScanJob], on_row: Callable[[ScanResult], None] | None = None,
            should_stop: Callable[[], bool] | None = None) -> list[ScanResult]:
        """Reconstruct `jobs` (any iterable, drawn one ahead) one after another, each loading while the one before
        trains and writing its files while the next one trains (slwarp.batch.run_scans): on_row(row) as soon as a
        scan's files are complete; should_stop() is asked before each scan starts."""
        def final(row: ScanResult) -> None:
            self.results.append(row)  # also the rows finished before a stop during a later scan's training
            if on_row is not None:
                on_row(row)

        return run_scans(jobs, self.config, self.options, worker="station", on_row=final, should_stop=should_stop)


@dataclass
class _Seen:
    """What the watcher knows of one inbox entry: its last signature and when it last changed; the signature
    of its last failure (not retried until the folder changes)."""

    signature: tuple = ()
    since: float = 0.0
    failed: tuple | None = None


def line(row: ScanResult) -> str:
    """One line per scan: name, seconds, pixels with depth, MAE when the scan has ground truth (or the error)."""
    if row.status == "failed":
        return f"{row.name}: failed after {row.seconds or 0:.1f} s: {row.error}"
    if row.status == "skipped":
        return f"{row.name}: skipped (outputs complete in {row.out_dir})"
    text = f"{row.name}: {row.seconds:.1f} s, depth on {row.valid_share:.1%} of {row.pixels} pixels"
    if row.mae is not None and math.isfinite(row.mae):
        text += f", MAE {row.mae:.3f} mm"
    return text


class Watcher:
    """Watches `inbox` and reconstructs each complete scan folder into out/NAME with `station` (see the module
    docstring). `run()` returns when stopped (a signal, `stop()`, `max_scans` reconstructed, or, with
    `until_idle`, when no folder is pending)."""

    def __init__(self, inbox: str | os.PathLike, out: str | os.PathLike, station: Station,
                 poll_s: float = DEFAULT_POLL_S, settle_s: float = DEFAULT_SETTLE_S, say: Callable[[str], None] = print):
        self.inbox = Path(inbox)
        self.out = Path(out)
        self.station = station
        self.poll_s, self.settle_s = poll_s, settle_s
        self.say = say
        self.seen: dict[str, _Seen] = {}
        self.ignored: set[str] = set()
        self.stopping = threading.Event()
        self.stop_signal: int | None = None

    def stop(self, signum: int | None = None) -> None:
        self.stop_signal = self.stop_signal or signum
        self.stopping.set()

    def _entries(self) -> list[Path]:
        """The inbox's folders in name order; a link leading out of the inbox is ignored (said once)."""
        found = []
        for p in sorted(self.inbox.iterdir(), key=lambda p: p.name):
            if not p.is_dir() or p.name.startswith("."):
                continue
            if not inside_folder(p, self.inbox):
                if p.name not in self.ignored:
                    self.ignored.add(p.name)
                    self.say(f"{p.name}: ignored (a link leading out of {self.inbox})")
                continue
            found.append(p)
        return found

    def ready(self, now: float | None = None) -> list[Path]:
        """The inbox's scan folders to reconstruct now: complete, settled, not done in out/, not failed as they are."""
        now = time.monotonic() if now is None else now
        todo = []
        for folder in self._entries():
            seen = self.seen.setdefault(folder.name, _Seen())
            sig = _signature(folder)
            if sig != seen.signature:
                seen.signature, seen.since = sig, now
                continue
            if now - seen.since < self.settle_s or seen.failed == sig:
                continue
            if outputs_complete(self.out / folder.name):
                continue
            if scan_complete(folder)[0]:
                todo.append(folder)
        return todo

    def run(self, max_scans: int | None = None, until_idle: bool = False) -> list[ScanResult]:
        """Reconstruct scans as they come until stopped; the rows of the scans reconstructed (or failed)."""
        from .neural.training import TrainingInterrupted

        if not self.inbox.is_dir():
            raise FileNotFoundError(f"{self.inbox}: the inbox is not a folder")
        with _StopOn(self):
            for folder in self._entries():
                if outputs_complete(self.out / folder.name):
                    self.say(f"{folder.name}: done before (outputs in {self.out / folder.name})")
            rows: list[ScanResult] = []
            lock = threading.Lock()
            drawn: list[str] = []  # the scans handed to the station, in order

            def report(row: ScanResult) -> None:  # the scan's files are complete (or it failed): its line
                with lock:
                    rows.append(row)
                    self.say(line(row))
                    if row.status == "failed":
                        seen = self.seen[row.name]
                        seen.failed = seen.signature

            def jobs(todo):
                for folder in todo:
                    if max_scans is not None and len(drawn) >= max_scans:
                        return
                    drawn.append(folder.name)
                    yield ScanJob(folder.name, str(folder), str(self.out / folder.name))

            while not self.stopping.is_set():
                todo = self.ready()
                if not todo and until_idle and not self._pending():
                    break
                try:  # the next scan loads while one trains, its files are written while the next one trains
                    self.station.run(jobs(todo), on_row=report, should_stop=self.stopping.is_set)
                except TrainingInterrupted as e:  # a signal during training: its checkpoint is saved
                    done = {r.name for r in rows}
                    name = next((n for n in drawn if n not in done), "the scan")
                    with lock:
                        self.say(f"{name}: interrupted; it continues from its checkpoint on the next start")
                    self.stop(e.signum)
                    break
                if max_scans is not None and len(drawn) >= max_scans:
                    self.stop()
                    break
                self.stopping.wait(self.poll_s)
            return rows

    def _pending(self) -> bool:
        """Whether some inbox folder may still be reconstructed: not settled yet, or a complete scan neither done
        nor failed as it is (a settled folder that holds no complete scan is not waited for)."""
        now = time.monotonic()
        for folder in self._entries():
            seen = self.seen.get(folder.name)
            if seen is None or now - seen.since < self.settle_s:
                return True
            if outputs_complete(self.out / folder.name) or seen.failed == seen.signature:
                continue
            if scan_complete(folder)[0]:
                return True
        return False


class _StopOn:
    """SIGINT and SIGTERM stop the watcher (between scans; during training the trainer's own handling takes over
    and saves a checkpoint); the previous handlers come back on exit. Main thread only."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self, watcher: Watcher):
        self.watcher = watcher
        self.previous = {}

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for s in self.SIGNALS:
                self.previous[s] = signal.signal(s, lambda signum, _frame: self.watcher.stop(signum))
        return self

    def __exit__(self, *exc):
        for s, h in self.previous.items():
            signal.signal(s, h)


def watch(inbox, out, config, options: BatchOptions, poll_s: float = DEFAULT_POLL_S,
          settle_s: float = DEFAULT_SETTLE_S, max_scans: int | None = None, until_idle: bool = False,
          say: Callable[[str], None] = print) -> int:
    """The `slwarp watch` command's body: 0 when stopped by request or done, 130/143 when stopped by a signal."""
    # a station continues what it started, prints one line a scan, and reads a scan's files from inside its folder
    # only, whatever its scan.yaml says (docs/inputs.md: folders that others wrote)
    options = replace(options, resume=True, log=False, outside_paths=False)
    watcher = Watcher(inbox, out, Station(config, options), poll_s=poll_s, settle_s=settle_s, say=say)
    say(f"watching {inbox} -> {out} ({config.runtime.device}); Ctrl-C stops")
    rows = watcher.run(max_scans=max_scans, until_idle=until_idle)
    done = sum(r.status == "done" for r in rows)
    failed = sum(r.status == "failed" for r in rows)
    say(f"stopped: {done} scan(s) reconstructed, {failed} failed")
    sys.stdout.flush()
    return 128 + watcher.stop_signal if watcher.stop_signal else 0
