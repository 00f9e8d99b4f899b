"""Built-in scenes of the virtual scanner: procedural objects in front of a wall, in the camera frame (mm).

Modelled on the paper's setup: objects 550 to 900 mm from the camera in front of a wall at about 950 mm.
Everything is generated here (trimesh primitives, surfaces of revolution, an implicit blobby shape
through marching cubes); nothing is downloaded.

    spheres   three spheres of different sizes and albedos
    torus     a tilted torus and a small sphere
    boxes     three rotated boxes with textured faces (sharp edges, planes)
    bunny     a smooth blobby "bunny-like" shape (body, head, ears) built as an implicit surface
    vase      a textured surface of revolution and a lying cylinder
    steps     a staircase receding in depth, a cone and a capsule
    checker   a wall printed with a high-contrast checkerboard (20 mm squares, albedo 0.16 to 0.8) and
              objects with strong textures (a checkered sphere, a box with a fine sinusoid)
    rods      thin rods (2.5 mm diameter, 560 to 680 mm away: about 2 camera pixels wide on the small rig,
              7 on the default rig) in front of two spheres and the wall: thin structures, the shadows
              they cast and their occlusion edges
    waves     a sheet 700 mm away rippled in both image directions (15 and 10 mm deep, 120 and 90 mm
              periods; slopes up to 45 deg) before the wall: a smooth surface whose depth changes
              everywhere, along and across the epipolar lines of every rig

The first six (`SIX_SCENES`) are the original benchmark set and never change (published results depend
on them); `checker`, `rods` and `waves` cover what users meet beyond it. Means over "the 8 scenes" in results
before 2026-11-29 are over the first eight (`waves` came later).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SIX_SCENES = ("spheres", "torus", "boxes", "bunny", "vase", "steps")
SCENE_NAMES = SIX_SCENES + ("checker", "rods", "waves")
TEXTURE_KINDS = ("sine", "checker")
DEFAULT_SCENE = "bunny"


@dataclass
class SceneObject:
    """A mesh (camera frame, mm, outward normals) with its reflectance.

    albedo: Lambertian albedo in [0, 1]; texture: amplitude t in [0, 1] of an albedo texture T(x) in [0, 1]
    (the albedo is albedo * (1 - t + t T(x)); 0 = uniform); texture_period: its period in mm;
    texture_kind: "sine" (a smooth 3-D sinusoid) or "checker" (a hard-edged checkerboard over the camera
    frame's x and y, squares of texture_period / 2).
    """

    name: str
    mesh: "object"  # trimesh.Trimesh
    albedo: float = 0.7
    texture: float = 0.0
    texture_period: float = 40.0
    texture_kind: str = "sine"

    def __post_init__(self):
        if self.texture_kind not in TEXTURE_KINDS:
            raise ValueError(f"scene object {self.name!r}: texture_kind must be one of {TEXTURE_KINDS}, "
                             f"got {self.texture_kind!r}")
        if not 0.0 <= self.texture <= 1.0 or not 0.0 <= self.albedo <= 1.0:
            raise ValueError(f"scene object {self.name!r}: albedo and texture must lie in [0, 1], "
                             f"got {self.albedo} and {self.texture}")
        if not self.texture_period > 0.0:
            raise ValueError(f"scene object {self.name!r}: texture_period must be > 0 mm, got {self.texture_period}")


def _transform(translation=(0, 0, 0), rx=0.0, ry=0.0, rz=0.0) -> np.ndarray:
    """4x4 rigid transform: rotations about x, y, z (degrees, applied in that order), then translation."""
    import trimesh

    T = trimesh.transformations.euler_matrix(np.radians(rx), np.radians(ry), np.radians(rz), "sxyz")
    T[:3, 3] = translation
    return T


def _wall(z: float = 950.0, tilt_deg: float = 8.0, albedo: float = 0.65, **texture) -> SceneObject:
    import trimesh

    wall = trimesh.creation.box(extents=(1800.0, 1500.0, 20.0), transform=_transform((0, 0, z + 10.0), ry=tilt_deg))
    return SceneObject("wall", wall, albedo, **texture)


def _rod(start, end, diameter: float = 2.5, sections: int = 24):
    """A closed cylinder of `diameter` mm from `start` to `end` (mm)."""
    import trimesh

    return trimesh.creation.cylinder(radius=0.5 * diameter, segment=np.array([start, end], float), sections=sections)


def _sphere(center, radius, subdivisions=6):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    m.apply_translation(center)
    return m


def _blobby_bunny(center=(0.0, 20.0, 730.0), voxel=2.0):
    """A smooth bunny-like implicit shape: union of ellipsoids blended by a smooth minimum."""
    import trimesh
    from skimage.measure import marching_cubes

    # ellipsoids: centre (mm, object frame with y down), radii
    parts = [
        ((0.0, 40.0, 0.0), (105.0, 80.0, 85.0)),  # body
        ((-85.0, -45.0, -15.0), (58.0, 52.0, 55.0)),  # head
        ((-105.0, -135.0, -5.0), (16.0, 60.0, 14.0)),  # ear 1
        ((-65.0, -140.0, -25.0), (16.0, 58.0, 14.0)),  # ear 2
        ((105.0, 30.0, 10.0), (28.0, 26.0, 26.0)),  # tail
        ((-40.0, 110.0, -35.0), (40.0, 22.0, 35.0)),  # front paw
        ((60.0, 110.0, -30.0), (50.0, 24.0, 40.0)),  # back paw
    ]
    lo = np.array([-180.0, -210.0, -130.0])
    hi = np.array([150.0, 150.0, 130.0])
    axes = [np.arange(lo[i], hi[i] + voxel, voxel) for i in range(3)]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    k = 12.0  # smooth-min blending width (mm)
    acc = np.zeros_like(X)
    for c, r in parts:
        # approximate signed distance of an ellipsoid (scaled by the smallest radius)
        q = np.sqrt(((X - c[0]) / r[0]) ** 2 + ((Y - c[1]) / r[1]) ** 2 + ((Z - c[2]) / r[2]) ** 2)
        d = (q - 1.0) * min(r)
        acc += np.exp(-d / k)
    sdf = -k * np.log(acc)
    verts, faces, _, _ = marching_cubes(sdf, level=0.0, spacing=(voxel, voxel, voxel))
    verts += lo
    mesh = trimesh.Trimesh(verts, faces[:, ::-1], process=True)  # marching cubes winds inward here
    if mesh.volume < 0:
        mesh.invert()
    trimesh.smoothing.filter_taubin(mesh, iterations=10)
    mesh.apply_transform(_transform(center, ry=-20.0))
    return mesh


def _vase(center, height=300.0, sections=256):
    import trimesh

    y = np.linspace(-height / 2, height / 2, 121)
    t = (y + height / 2) / height
    r = 55.0 + 45.0 * np.sin(np.pi * t * 1.2) ** 2 - 20.0 * t
    # profile in the (radius, height) plane; revolve about the object's z, then stand it up along y
    line = np.stack([r, y], axis=1)
    mesh = trimesh.creation.revolve(line, sections=sections, cap=True)
    mesh.apply_transform(_transform(center, rx=90.0))
    return mesh


def _waves(z0: float = 700.0, half=(280.0, 220.0), depth=(15.0, 10.0), period=(120.0, 90.0), thickness=10.0,
           n=(281, 221)):
    """A closed slab (mm) whose face toward the camera is z = z0 + depth[0] sin(2 pi x / period[0]) + depth[1]
    sin(2 pi y / period[1]) over |x| <= half[0], |y| <= half[1] (n[0] x n[1] vertices); its back is flat, `thickness`
    mm behind the front's farthest point."""
    import trimesh

    x, y = np.linspace(-half[0], half[0], n[0]), np.linspace(-half[1], half[1], n[1])
    X, Y = np.meshgrid(x, y)  # [ny, nx]
    Z = z0 + depth[0] * np.sin(2 * np.pi * X / period[0]) + depth[1] * np.sin(2 * np.pi * Y / period[1])
    front = np.stack([X, Y, Z], -1).reshape(-1, 3)
    back = np.stack([X, Y, np.full_like(Z, z0 + max(depth[0] + depth[1], 0.0) + thickness)], -1).reshape(-1, 3)
    ny, nx = X.shape
    idx = np.arange(ny * nx).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = [np.stack([a, b, d], 1), np.stack([a, d, c], 1)]  # the front face's triangles
    off = ny * nx
    faces += [np.stack([a, d, b], 1) + off, np.stack([a, c, d], 1) + off]  # the back, the other way round
    ring = np.concatenate([idx[0, :], idx[1:, -1], idx[-1, -2::-1], idx[-2:0:-1, 0]])  # the border, once round
    r0, r1 = ring, np.roll(ring, -1)
    faces += [np.stack([r0, r0 + off, r1], 1), np.stack([r1, r0 + off, r1 + off], 1)]
    mesh = trimesh.Trimesh(np.concatenate([front, back]), np.concatenate(faces), process=True)
    mesh.fix_normals()  # outward, whichever way the border ran
    return mesh


def build_scene(name: str) -> list[SceneObject]:
    """The objects of a built-in scene (camera frame, mm)."""
    import trimesh

    if name == "spheres":
        return [
            _wall(),
            SceneObject("sphere_large", _sphere((-110.0, 10.0, 760.0), 95.0), 0.8),
            SceneObject("sphere_medium", _sphere((125.0, -85.0, 650.0), 60.0), 0.55),
            SceneObject("sphere_small", _sphere((75.0, 125.0, 840.0), 45.0), 0.75),
        ]
    if name == "torus":
        torus = trimesh.creation.torus(110.0, 38.0, major_sections=256, minor_sections=96,
                                       transform=_transform((-30.0, -10.0, 720.0), rx=55.0, ry=25.0))
        return [_wall(tilt_deg=-6.0), SceneObject("torus", torus, 0.75),
                SceneObject("sphere", _sphere((165.0, 120.0, 790.0), 42.0), 0.6)]
    if name == "boxes":
        return [
            _wall(tilt_deg=12.0),
            SceneObject("box_a", trimesh.creation.box((160.0, 160.0, 160.0), transform=_transform((-125.0, 40.0, 800.0), rx=20.0, ry=30.0)), 0.7, 0.35, 60.0),
            SceneObject("box_b", trimesh.creation.box((100.0, 230.0, 90.0), transform=_transform((125.0, -30.0, 690.0), ry=-28.0, rz=8.0)), 0.6, 0.35, 45.0),
            SceneObject("box_c", trimesh.creation.box((80.0, 60.0, 80.0), transform=_transform((10.0, 150.0, 600.0), rx=-15.0, ry=40.0)), 0.8),
        ]
    if name == "bunny":
        return [_wall(tilt_deg=-10.0), SceneObject("bunny", _blobby_bunny(), 0.8)]
    if name == "vase":
        cyl = trimesh.creation.cylinder(radius=40.0, height=220.0, sections=192,
                                        transform=_transform((150.0, 120.0, 690.0), ry=70.0, rx=10.0))
        return [_wall(tilt_deg=5.0), SceneObject("vase", _vase((-80.0, 0.0, 760.0)), 0.7, 0.4, 35.0),
                SceneObject("cylinder", cyl, 0.65)]
    if name == "steps":
        objs = [_wall(tilt_deg=0.0)]
        for i in range(4):
            z = 620.0 + 70.0 * i
            step = trimesh.creation.box((260.0, 70.0, 60.0), transform=_transform((-110.0, 120.0 - 75.0 * i, z), ry=10.0))
            objs.append(SceneObject(f"step_{i}", step, 0.7 - 0.05 * i))
        cone = trimesh.creation.cone(radius=70.0, height=150.0, sections=192, transform=_transform((140.0, 20.0, 760.0), rx=-90.0))
        capsule = trimesh.creation.capsule(height=160.0, radius=35.0, count=[96, 96],
                                           transform=_transform((120.0, -150.0, 680.0), ry=90.0, rz=15.0))
        objs += [SceneObject("cone", cone, 0.75), SceneObject("capsule", capsule, 0.6)]
        return objs
    if name == "checker":
        # albedo 0.8 x (1 - 0.8 + 0.8 T): squares of 0.16 and 0.8, a 5:1 contrast whose dark squares stay above
        # the decoders' contrast thresholds (a 10:1 print leaves them unlit for every method alike)
        box = trimesh.creation.box((150.0, 150.0, 150.0), transform=_transform((140.0, 30.0, 760.0), rx=15.0, ry=-35.0))
        return [
            _wall(tilt_deg=8.0, albedo=0.8, texture=0.8, texture_period=40.0, texture_kind="checker"),
            SceneObject("sphere_checker", _sphere((-120.0, -20.0, 720.0), 90.0), 0.8, 0.8, 30.0, "checker"),
            SceneObject("box_fine_sine", box, 0.7, 0.9, 12.0, "sine"),
        ]
    if name == "rods":
        objs = [
            _wall(tilt_deg=-5.0),
            SceneObject("sphere_left", _sphere((-120.0, 20.0, 800.0), 90.0), 0.75),
            SceneObject("sphere_right", _sphere((130.0, -40.0, 760.0), 70.0), 0.6),
        ]
        # vertical, horizontal and slanted rods 560 to 680 mm away, crossing in front of the spheres
        rods = [
            ((-160.0, -260.0, 600.0), (-160.0, 260.0, 600.0)),
            ((-60.0, -260.0, 640.0), (-60.0, 260.0, 660.0)),
            ((60.0, -260.0, 620.0), (60.0, 260.0, 620.0)),
            ((170.0, -260.0, 680.0), (170.0, 260.0, 665.0)),
            ((-300.0, -120.0, 580.0), (300.0, -120.0, 600.0)),
            ((-300.0, 150.0, 650.0), (300.0, 90.0, 650.0)),
            ((-280.0, -250.0, 560.0), (260.0, 250.0, 680.0)),
        ]
        objs += [SceneObject(f"rod_{i}", _rod(p0, p1), 0.7) for i, (p0, p1) in enumerate(rods)]
        return objs
    if name == "waves":
        return [_wall(tilt_deg=4.0), SceneObject("waves", _waves(), 0.7)]
    raise ValueError(f"unknown scene {name!r}; built-in scenes: {', '.join(SCENE_NAMES)}")


def load_mesh_objects(paths, albedo: float = 0.7) -> list[SceneObject]:
    """User meshes (any format trimesh reads; camera frame, mm) as scene objects."""
    import trimesh

    objs = []
    for p in paths:
        try:
            m = trimesh.load(p, force="mesh")
        except Exception as e:  # noqa: BLE001 - trimesh raises many types; report the file
            raise ValueError(f"cannot read mesh {p}: {e}") from None
        if not isinstance(m, trimesh.Trimesh) or len(m.faces) == 0:
            raise ValueError(f"mesh {p} has no triangles")
        if not np.all(np.isfinite(m.vertices)):
            raise ValueError(f"mesh {p} has non-finite vertices")
        objs.append(SceneObject(str(p), m, albedo))
    return objs
