"""Built-in camera + projector rigs of the virtual scanner.

Every rig has the same camera (1280x1024, fx 1800 px: about 39 x 32 deg) at the origin looking down +z, and a
1280x800 projector toed in toward a point 750 mm ahead, both with mild lens distortion. They frame the same
working volume (objects 550 to 900 mm away, a wall at about 950 mm, depth range 450 to 1100 mm), so every
built-in scene is lit on most of the camera image on every rig. They differ in where the projector sits and how
it is turned (the geometries):

- `default`: projector 150 mm to the right of the camera (horizontal baseline): its column codes carry depth.
- `vertical`: projector 150 mm below the camera (vertical baseline, like the real capture in shared/data):
  its row codes carry depth.
- `oblique`: projector 150 mm right of and 150 mm below the camera (a 45 deg baseline of 212 mm): column and
  row codes both carry depth, each as much as the column codes of `default`.
- `rolled`: projector 200 mm below the camera and rolled 90 deg about its optical axis, so that its columns run
  along the vertical baseline and its column codes carry depth. Its lens is wider (fx 1200 px) so that its
  800-pixel side covers the camera's width; the longer baseline keeps the depth resolution of `default`
  (baseline x projector focal length along the baseline: 200 x 1200 = 150 x 1600 mm px).

Each geometry exists at full resolution (its name) and at a small resolution for fast CPU tests and demos
(camera 320x256, projector 640x400, the same lenses): `small` for `default`, `small-<geometry>` for the others.
`default` and `small` are the rigs of every result measured before the other geometries existed.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..scans.scanner import Camera, Projector, look_at_rotation

BASELINE_MM = 150.0  # the default rig's baseline
CONVERGENCE_MM = 750.0  # every projector is toed in toward (0, 0, CONVERGENCE_MM)
DEPTH_RANGE_MM = (450.0, 1100.0)
SMALL_CAMERA_SCALE, SMALL_PROJECTOR_SCALE = 0.25, 0.5


@dataclass(frozen=True)
class RigGeometry:
    """Where the projector sits and how it is turned, at full resolution.

    projector_center: (x, y, z) mm in the camera frame (x right, y down); roll_deg: rotation of the projector
    about its optical axis after toeing in (90: its columns run along the camera's y axis);
    projector_focal: fx = fy of the projector, px; summary: one line for listings.
    """

    name: str
    projector_center: tuple[float, float, float]
    roll_deg: float
    projector_focal: float
    summary: str

    @property
    def baseline_direction(self) -> np.ndarray:
        """Unit vector [3] from the camera centre to the projector centre (camera frame)."""
        c = np.asarray(self.projector_center, np.float64)
        return c / np.linalg.norm(c)


GEOMETRIES: dict[str, RigGeometry] = {
    g.name: g
    for g in [
        RigGeometry("default", (BASELINE_MM, 0.0, 0.0), 0.0, 1600.0,
                    "horizontal baseline: projector 150 mm right of the camera; column codes carry depth"),
        RigGeometry("vertical", (0.0, BASELINE_MM, 0.0), 0.0, 1600.0,
                    "vertical baseline: projector 150 mm below the camera; row codes carry depth"),
        RigGeometry("oblique", (BASELINE_MM, BASELINE_MM, 0.0), 0.0, 1600.0,
                    "45 deg baseline: projector 150 mm right of and 150 mm below the camera; column and row "
                    "codes both carry depth"),
        RigGeometry("rolled", (0.0, 200.0, 0.0), 90.0, 1200.0,
                    "vertical baseline, projector 200 mm below the camera rolled 90 deg (fx 1200 px); column "
                    "codes carry depth"),
    ]
}


def rig_name(geometry: str, small: bool = False) -> str:
    """The rig name of a geometry at full or small resolution ('default', True -> 'small')."""
    if geometry not in GEOMETRIES:
        raise ValueError(f"unknown rig geometry {geometry!r}; geometries: {', '.join(GEOMETRIES)}")
    if not small:
        return geometry
    return "small" if geometry == "default" else f"small-{geometry}"


RIG_NAMES = tuple(rig_name(g, small) for small in (False, True) for g in GEOMETRIES)


def parse_rig_name(name: str) -> tuple[RigGeometry, bool]:
    """(geometry, small) of a rig name; ValueError naming the built-in rigs for an unknown one."""
    for g in GEOMETRIES:
        for small in (False, True):
            if rig_name(g, small) == name:
                return GEOMETRIES[g], small
    raise ValueError(f"unknown rig {name!r}; built-in rigs: {', '.join(RIG_NAMES)}")


def _roll(deg: float) -> np.ndarray:
    """Rotation of a device frame about its own z (optical) axis by `deg`: new x = cos x + sin y."""
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


def _build(geometry: RigGeometry, small: bool) -> tuple[Camera, Projector]:
    camera = Camera(
        1280,
        1024,
        [[1800.0, 0.0, 641.3], [0.0, 1800.0, 509.6], [0.0, 0.0, 1.0]],
        [-0.06, 0.09, 2e-4, -3e-4, 0.0],
    )
    center = np.array(geometry.projector_center, np.float64)
    R = look_at_rotation(center, np.array([0.0, 0.0, CONVERGENCE_MM]))
    if geometry.roll_deg != 0.0:  # no product with the identity: `default` keeps its exact rotation
        R = _roll(geometry.roll_deg) @ R
    f = geometry.projector_focal
    projector = Projector(
        1280,
        800,
        [[f, 0.0, 639.5], [0.0, f, 399.5], [0.0, 0.0, 1.0]],
        [0.03, -0.02, 0.0, 0.0, 0.0],
        R=R,
        T=-R @ center,
    )
    if small:
        camera, projector = camera.scaled(SMALL_CAMERA_SCALE), projector.scaled(SMALL_PROJECTOR_SCALE)
    return camera, projector


def make_rig(name: str = "default") -> tuple[Camera, Projector]:
    """(camera, projector) of a built-in rig (see RIG_NAMES: 'default', 'vertical', ..., 'small', 'small-vertical', ...)."""
    geometry, small = parse_rig_name(name)
    return _build(geometry, small)


def describe_rigs() -> list[str]:
    """One line per geometry with its rig names, for listings (`slwarp simulate --list`)."""
    return [f"{g.name} / {rig_name(g.name, True)}: {g.summary}" for g in GEOMETRIES.values()]
