"""Work on a scan started in a thread while the process does something else.

    ahead = ScanPrefetch(path, frames=..., outside_paths=...)   # load_scan and the camera's rays, starting now
    ...                                                         # e.g. train the scan before (slwarp.batch.run_scans)
    scan = ahead.result()                                       # the Scan, or load_scan's ScanError raised here

    rays_ahead(scan.camera)                                     # camera_rays in a thread (reconstruct does this)

Why it pays: decoding the PNG frames (OpenCV) and undistorting every camera pixel for its ray (numpy on 1.3 M
float64 pixels, `camera_rays`: 0.35-0.44 s of the first depth search of a fresh `slwarp reconstruct` on an H100
host, cProfile) leave the interpreter lock free most of the time, so they overlap the caller's work; a batch's
next scan loads while the GPU trains the one before. The rays land in `camera_rays`' cache, which the search and
the extraction read (a caller that comes first waits for them). Not during the imports of a fresh process: loading
the scan beside torch's import made both slower (imports 2.0 -> 2.4-3.2 s, H100 host).
"""
from __future__ import annotations

import threading

from .scan import load_scan
from .scanner import camera_rays


class ScanPrefetch:
    """load_scan(path, frames, outside_paths=..., patterns=...) and the camera's ray grid, in a daemon thread started
    here."""

    def __init__(self, path, frames=None, outside_paths: bool | None = None, patterns=None):
        self.path = path
        self._scan, self._error = None, None
        self._thread = threading.Thread(target=self._run, args=(path, frames, outside_paths, patterns),
                                        name="slwarp-scan", daemon=True)
        self._thread.start()

    def _run(self, path, frames, outside_paths, patterns) -> None:
        try:
            self._scan = load_scan(path, frames=frames, outside_paths=outside_paths, patterns=patterns)
        except BaseException as e:  # noqa: BLE001 - raised in the thread that asks for the scan
            self._error = e
            return
        try:
            camera_rays(self._scan.camera)
        except Exception:  # noqa: BLE001 - the rays are computed again where needed, and fail there if they must
            pass

    def result(self):
        """The loaded Scan (waits for it); load_scan's error when it failed."""
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self._scan


def rays_ahead(camera) -> threading.Thread:
    """camera_rays(camera) computed in a daemon thread (a no-op when cached); returns the thread."""
    thread = threading.Thread(target=camera_rays, args=(camera,), name="slwarp-rays", daemon=True)
    thread.start()
    return thread
