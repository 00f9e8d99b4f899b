"""Loading ahead (slwarp.scans.prefetch) and what it relies on: a scan loads without torch, the prefetched scan is
the scan load_scan gives, its errors arrive where the scan is asked for, and a batch loads each scan while the one
before it trains (slwarp.batch.run_scans) without changing what any scan gives."""
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from slwarp.batch import BatchOptions, ScanJob, run_scans
from slwarp.scans import scanner
from slwarp.scans.errors import ScanError
from slwarp.scans.prefetch import ScanPrefetch
from slwarp.scans.scan import load_scan
from slwarp.sim.simulate import SimOptions, simulate_scene


@pytest.fixture(scope="module")
def saved_scan(tmp_path_factory):
    folder = tmp_path_factory.mktemp("prefetch") / "spheres"
    simulate_scene("spheres", "random6", rig="small", options=SimOptions(seed=5)).save(folder)
    return folder


def test_a_scan_loads_without_importing_torch(saved_scan):
    """The point of loading ahead: the thread decodes frames while the main thread imports torch, which it could
    not do if loading imported torch itself (its import lock)."""
    code = ("import sys\nfrom slwarp.scans.prefetch import ScanPrefetch\n"
            f"s = ScanPrefetch({str(saved_scan)!r}).result()\n"
            "print(len(s), 'torch' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["6", "False"]


def test_prefetched_scan_is_the_loaded_scan_with_its_rays_cached(saved_scan):
    scanner._RAYS_CACHE.clear()
    ahead = ScanPrefetch(saved_scan, frames="0:4")
    scan, plain = ahead.result(), load_scan(saved_scan, frames="0:4")
    assert scan.names == plain.names and len(scan) == 4
    np.testing.assert_array_equal(scan.images, plain.images)
    np.testing.assert_array_equal(scan.gt_depth, plain.gt_depth)
    assert scan.camera.cache_key in scanner._RAYS_CACHE  # computed beside the caller's work, read by the search
    np.testing.assert_array_equal(scanner.camera_rays(scan.camera), scan.camera.pixel_to_ray(scan.camera.pixel_grid()))


def test_prefetch_errors_are_raised_by_result(tmp_path):
    ahead = ScanPrefetch(tmp_path / "missing")
    with pytest.raises(ScanError, match="scan not found"):
        ahead.result()


def test_batch_loads_ahead_and_a_broken_scan_fails_alone(saved_scan, tmp_path, monkeypatch):
    """Three scans, the middle one broken: run_scans gives the first and the last as run_scan alone does, each scan
    loaded once (the next one while the one before runs), and the broken one reported in its line."""
    from slwarp.batch import jobs as jobs_module

    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "scan.yaml").write_text("units: mm\nframes: [missing.png]\n")
    loads = []
    real = jobs_module.run_scan

    def recording(job, *a, loaded=None, **kw):
        loads.append((job.name, loaded is not None))
        return real(job, *a, loaded=loaded, **kw)

    monkeypatch.setattr(jobs_module, "run_scan", recording)
    from slwarp.neural.config import preset

    cfg = preset("tiny", device="cpu", iters=3, init_iters=2, mc_resolution=32, rays=64)
    jobs = [ScanJob(name, src, tmp_path / "out" / name, 1) for name, src in
            (("a", saved_scan), ("broken", broken), ("c", saved_scan))]
    drawn, final = [], []

    def queue():  # a worker's queue: each job drawn once the scan before it is in memory
        for job in jobs:
            drawn.append((job.name, len(loads)))
            yield job

    rows = run_scans(queue(), cfg, BatchOptions(progress=False, log=False),
                     on_row=lambda row: final.append((row.name, row.status, (Path(row.out_dir) / "depth.npy").is_file())))
    assert [r.status for r in rows] == ["done", "failed", "done"]
    assert "broken" in rows[1].error or "missing.png" in rows[1].error
    assert loads == [("a", True), ("broken", True), ("c", True)]
    assert drawn == [("a", 0), ("broken", 1), ("c", 2)]  # one ahead: during the scan before
    # each row reported once final, in order, with its files on disk
    assert final == [("a", "done", True), ("broken", "failed", False), ("c", "done", True)]
    for r in (rows[0], rows[2]):
        out = Path(r.out_dir)
        assert (out / "depth.npy").is_file() and (out / "train" / "checkpoint.pt").is_file()


def test_rays_ahead_fills_the_cache_and_a_second_caller_waits_for_it(saved_scan, monkeypatch):
    """camera_rays computes a grid once however many threads ask: the one that comes second waits."""
    import threading

    from slwarp.scans.prefetch import rays_ahead

    scanner._RAYS_CACHE.clear()
    cam = load_scan(saved_scan).camera
    calls, gate = [], threading.Event()
    real = type(cam).pixel_to_ray

    def slow(self, uv):
        calls.append(threading.current_thread().name)
        gate.wait(5)
        return real(self, uv)

    monkeypatch.setattr(type(cam), "pixel_to_ray", slow)
    thread = rays_ahead(cam)
    for _ in range(5000):  # until the thread computes (it holds the lock), then a second caller
        if calls:
            break
        threading.Event().wait(0.001)
    waiter = threading.Thread(target=scanner.camera_rays, args=(cam,), name="waiter")
    waiter.start()
    gate.set()
    thread.join(10), waiter.join(10)
    # one computation, its bands of rows in threads of its own; a second one would have doubled the calls
    bands = min(os.cpu_count() or 1, scanner.RAY_BANDS, cam.height)
    assert len(calls) == (bands if bands > 1 else 1) and "waiter" not in calls
    assert cam.cache_key in scanner._RAYS_CACHE
