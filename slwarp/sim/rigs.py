"""Built-in camera + projector rigs of the virtual scanner.

Both rigs share one geometry (the camera at the origin looking down +z; the projector 150 mm to its
right, toed in toward a point 750 mm ahead), modelled on a desktop structured-light setup measuring
objects 500 to 1000 mm away:

- `default`: camera 1280x1024 (fx 1800 px, about 39 deg horizontal field of view), projector 1280x800
  (fx 1600 px), mild lens distortion on both.
- `small`: the same lenses at camera 320x256 and projector 640x400, for fast CPU tests and demos.
"""
from __future__ import annotations

import numpy as np

from ..scans.scanner import Camera, Projector, look_at_rotation

RIG_NAMES = ("default", "small")
BASELINE_MM = 150.0
CONVERGENCE_MM = 750.0
DEPTH_RANGE_MM = (450.0, 1100.0)


def _rig(cam_scale: float, proj_scale: float) -> tuple[Camera, Projector]:
    camera = Camera(
        1280,
        1024,
        [[1800.0, 0.0, 641.3], [0.0, 1800.0, 509.6], [0.0, 0.0, 1.0]],
        [-0.06, 0.09, 2e-4, -3e-4, 0.0],
    )
    center = np.array([BASELINE_MM, 0.0, 0.0])
    R = look_at_rotation(center, np.array([0.0, 0.0, CONVERGENCE_MM]))
    projector = Projector(
        1280,
        800,
        [[1600.0, 0.0, 639.5], [0.0, 1600.0, 399.5], [0.0, 0.0, 1.0]],
        [0.03, -0.02, 0.0, 0.0, 0.0],
        R=R,
        T=-R @ center,
    )
    if cam_scale != 1.0:
        camera = camera.scaled(cam_scale)
    if proj_scale != 1.0:
        projector = projector.scaled(proj_scale)
    return camera, projector


def make_rig(name: str = "default") -> tuple[Camera, Projector]:
    """(camera, projector) of a built-in rig: 'default' or 'small'."""
    if name == "default":
        return _rig(1.0, 1.0)
    if name == "small":
        return _rig(0.25, 0.5)
    raise ValueError(f"unknown rig {name!r}; built-in rigs: {', '.join(RIG_NAMES)}")
