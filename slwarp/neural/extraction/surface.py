"""From a trained SDF to a mesh, a depth map and a point cloud (all in mm, camera frame).

- `sdf_grid`: the field on a regular grid over the working volume, evaluated in chunks.
- `extract_mesh`: marching cubes at level 0 (Warp's on a GPU, scikit-image's on the CPU) -> SurfaceMesh (trimesh on
  demand).
- `mesh_depth`: camera rays (through pixel centres, undistorted) cast at the mesh with Warp's BVH:
  depth = camera z of the first hit (or the first K hits), NaN where no hit.
- `flying_pixel_filter`: removes the pixels on depth edges, where a smooth SDF bends from the foreground
  to the background over a few pixels.
- `edge_band_masks`: the pixels a few pixels from a depth edge of the field (in front of it and behind it), where
  an outline it drew a pixel or two off leaves them with the other surface's depth.
- `denoise_depth`: an edge-aware local plane fit of the final depth map (the field's fine-scale noise).
- `sphere_trace_depth`: the alternative without a mesh: march each ray with steps of the SDF value,
  then refine the first sign change by the secant method.
"""
from __future__ import annotations

import numpy as np
import torch

from ...devices import warp_device
from ...scans.scanner import camera_rays
from ..depth_maps import NEIGHBOUR_OFFSETS, neighbour_stack, neighbours_at
from ..fields import Volume
from ..training.progress import Progress
from slwarp.kernels import runtime
from slwarp.kernels.simulate import first_hit_depth, mesh_hits


@torch.no_grad()
def sdf_grid(field, volume: Volume, resolution: int, device, chunk: int | None = None, progress: bool = False,
             as_tensor: bool = False):
    """SDF values [nx, ny, nz] (float32, mm) on a grid with `resolution` cells along the volume's largest side;
    returns (values, origin [3] mm, spacing mm). values: numpy, or with as_tensor a tensor on `device`.
    chunk: points per field call (default 2^18 on the CPU, 2^21 on a GPU, where each call is a launch)."""
    lo, hi = np.asarray(volume.lo), np.asarray(volume.hi)
    h = float((hi - lo).max() / resolution)
    n = np.maximum(np.ceil((hi - lo) / h).astype(int) + 1, 2)
    device = torch.device(device)
    chunk = chunk or (1 << 21 if device.type == "cuda" else 1 << 18)
    axes = [torch.arange(n[i], device=device, dtype=torch.float32) * h + float(lo[i]) for i in range(3)]
    out = torch.empty((int(n[0]), int(n[1]), int(n[2])), dtype=torch.float32, device=device)
    plane = n[1] * n[2]
    yz = torch.stack(torch.meshgrid(axes[1], axes[2], indexing="ij"), -1).reshape(-1, 2)
    step = max(1, chunk // plane)
    with Progress(len(range(0, n[0], step)), "SDF grid", unit="slab", enabled=progress, leave=False) as bar:
        for i0 in range(0, n[0], step):
            xs = axes[0][i0 : i0 + step]
            pts = torch.cat([xs[:, None, None].expand(-1, plane, 1), yz[None].expand(len(xs), -1, -1)], -1)
            out[i0 : i0 + len(xs)] = field(pts.reshape(-1, 3)).reshape(len(xs), n[1], n[2]).float()
            bar.update()
    return (out if as_tensor else out.cpu().numpy()), lo, h


class SurfaceMesh:
    """A triangle mesh in mm as marching cubes gives it: vertices [V, 3] (float64), faces [F, 3] (int64, wound outward,
    towards positive SDF) and, when the extraction has them, vertex normals [V, 3] (outward).

    Anything else (volume, export, area, ...) is trimesh.Trimesh's, built on first use (`to_trimesh`): trimesh takes
    a fresh process about 1 s of interpreter time to import (H100 host, cProfile), which the depth map, the PLY
    writer and the ray cast do not need; imported in a thread beside the training it slowed the first steps."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, vertex_normals: np.ndarray | None = None):
        self.vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
        self.faces = np.asarray(faces, np.int64).reshape(-1, 3)
        self._normals = None if vertex_normals is None else np.asarray(vertex_normals, np.float64).reshape(-1, 3)
        self._trimesh = None

    def to_trimesh(self):
        """The same mesh as a trimesh.Trimesh (made once; process=False: vertices and faces as they are)."""
        if self._trimesh is None:
            import trimesh

            self._trimesh = trimesh.Trimesh(self.vertices, self.faces, vertex_normals=self._normals, process=False)
        return self._trimesh

    @property
    def vertex_normals(self) -> np.ndarray:
        return self._normals if self._normals is not None else self.to_trimesh().vertex_normals

    def __getattr__(self, name):  # only for what the class lacks: trimesh's
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(self.to_trimesh(), name)

    def __repr__(self) -> str:
        return f"SurfaceMesh({len(self.vertices)} vertices, {len(self.faces)} faces)"


def extract_mesh(field, volume: Volume, resolution: int = 384, device="cpu", progress: bool = False,
                 depth_range=None):
    """Marching cubes of the zero level set -> a SurfaceMesh in mm (None if the SDF never crosses 0), faces wound
    outward (towards positive SDF) and vertex normals outward; `.to_trimesh()` (or any trimesh attribute) for trimesh.

    On a GPU the grid stays there and Warp's marching cubes runs on it (default-rig fast, 256 cells: 0.23 s of
    scikit-image on the host saved); on the CPU scikit-image's is faster than Warp's. Both interpolate each
    crossing linearly along the cell edge: the same vertices, the ambiguous cells triangulated alike or nearly.

    depth_range (near, far) in mm of camera z: the grid's planes nearer than `near` are set empty (SDF +h)
    first. Training samples rays only beyond the near plane, so the field is unconstrained in the volume's
    margin before it, and a negative region there hides what lies behind (`tuned`, H100/H200 sweeps: 1.5 to 12%
    of the pixels of default-rig boxes and torus, vertical-rig torus and rolled-rig boxes had their first hit out of range, most
    likely on that side: beyond `far` lies the wall that every ray renders). Beyond `far` nothing is cut: there the field is the inside of the farthest surfaces, and a cut
    would close them with a cap that rays never reach."""
    on_gpu = torch.device(device).type == "cuda"
    values, origin, h = sdf_grid(field, volume, resolution, device, progress=progress, as_tensor=True)
    if depth_range is not None:
        z = origin[2] + h * np.arange(values.shape[2])
        values[:, :, torch.as_tensor(z < float(depth_range[0]), device=values.device)] = h
    lo_hi = torch.stack([values.min(), values.max()]).cpu()
    if not (lo_hi[0] < 0.0 < lo_hi[1]):
        return None
    if on_gpu:
        verts, faces = _marching_cubes_warp(values, origin, h)
        # normals from the faces (wound outward), when asked for: the SDF's gradient direction at the surface
        return SurfaceMesh(verts, faces)
    from skimage.measure import marching_cubes

    verts, faces, normals, _ = marching_cubes(values.numpy(), level=0.0, spacing=(h, h, h))
    # scikit-image winds its faces towards increasing values here (outward, as the SDF grows outside) and its
    # normals point the other way
    return SurfaceMesh(verts + origin, faces, vertex_normals=-normals)


def _marching_cubes_warp(values: torch.Tensor, origin: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """(vertices [V, 3] mm, faces [F, 3]) of the zero level of a CUDA tensor [nx, ny, nz] by Warp's marching
    cubes, faces wound outward (towards positive values)."""
    wp = runtime.init()
    from warp.geometry import IsoSurfaceMarchingCubes

    n = np.asarray(values.shape)
    lo = tuple(float(x) for x in origin)
    hi = tuple(float(x) for x in np.asarray(origin) + h * (n - 1))
    device = warp_device(values.device)
    with wp.ScopedDevice(device):
        # after the field's evaluation of the grid on torch's stream, with no host synchronisation between them: Warp's
        # stream waits for torch's (not a ScopedStream, which would switch the device's stream for every thread)
        if values.is_cuda:
            wp.get_stream(device).wait_stream(wp.stream_from_torch(values.device))
        verts, tris = IsoSurfaceMarchingCubes.extract(wp.from_torch(values.contiguous()), 0.0, lower=lo, upper=hi)
        return verts.numpy().astype(np.float64), tris.numpy().reshape(-1, 3).astype(np.int64)


def mesh_depth(mesh, camera, device=None, hits: int = 1, eps_mm: float = 1.0) -> np.ndarray:
    """Depth [H, W] (camera z, mm) of the first hit of each pixel's ray on `mesh` (NaN where none), or
    with hits = K > 1 the first K hits [H, W, K] (NaN past the last), `eps_mm` apart at least (for
    users who want every surface along a ray). device: a torch device or device string (None: auto)."""
    wp = runtime.init()
    device = warp_device(device)
    H, W = camera.height, camera.width
    shape = (H, W) if hits == 1 else (H, W, hits)
    if mesh is None or len(mesh.faces) == 0:
        return np.full(shape, np.nan, np.float32)
    dirs = camera_rays(camera).reshape(-1, 3).astype(np.float32)
    with wp.ScopedDevice(device):
        m = wp.Mesh(points=wp.array(np.asarray(mesh.vertices, np.float32), dtype=wp.vec3),
                    indices=wp.array(np.asarray(mesh.faces, np.int32).ravel(), dtype=wp.int32))
        if hits == 1:
            depth = wp.empty(dirs.shape[0], dtype=float)
            wp.launch(first_hit_depth, dim=dirs.shape[0], inputs=[m.id, wp.array(dirs, dtype=wp.vec3)], outputs=[depth])
        else:
            depth = wp.empty((dirs.shape[0], hits), dtype=float)
            wp.launch(mesh_hits, dim=dirs.shape[0], inputs=[m.id, wp.array(dirs, dtype=wp.vec3), float(eps_mm)],
                      outputs=[depth])
        return depth.numpy().reshape(shape)


def flying_pixel_filter(depth: np.ndarray, camera, footprints: float = 10.0, device=None) -> np.ndarray:
    """Depth with "flying pixels" removed (NaN): pixels whose depth differs from one of their 8 neighbours
    by more than `footprints` pixel footprints (z / f mm each) lie on a depth edge.

    A neural SDF is smooth: where a foreground object ends in front of the background, its surface bends
    over a few pixels toward the background instead of stopping, and those pixels get depths in between
    (measured on the small-rig bunny: 76% of the pixels wrong by more than 5 mm were within 3 px of a depth
    edge). A slanted surface changes depth by a few footprints per pixel at most, so it is kept.
    Computed by torch on `device` (default the CPU; the GPU extraction's takes 0.02 s where numpy took 0.2 s).
    """
    d = torch.as_tensor(np.asarray(depth, np.float64), device=device)
    limit = footprints * d / min(camera.fx, camera.fy)
    jump = torch.nan_to_num(torch.abs(neighbour_stack(d) - d), nan=0.0).amax(0)
    out = torch.where(jump > limit, torch.full_like(d, float("nan")), d)
    return out.float().cpu().numpy()


def edge_band_masks(field_depth: np.ndarray, camera, near_radius: int, far_radius: int, footprints: float = 10.0,
                    device=None) -> tuple[np.ndarray, np.ndarray]:
    """(near [H, W] bool, far [H, W] bool): the pixels of `field_depth` ([H, W] mm, NaN: none) in front of a depth edge
    (some depth of their (2 near_radius + 1)^2 window lies farther than theirs by more than `footprints` pixel
    footprints, z / f mm each, z their own depth) and behind one (a depth of their (2 far_radius + 1)^2 window lies
    nearer by that much). A radius of 0: that side's mask is empty.

    Why: a smooth field draws an outline a pixel or two off. Where it draws a silhouette too small, the outline's
    pixels carry the background's depth (fast, default rig, H200: the spheres' gross errors lay 2 pixels from the
    field's edge, 18 of 24): they are behind the field's edge. Where it draws a thin part too thick, the background
    beside it carries the part's depth (rods, steps: 2 pixels on the near side). The flying-pixel filter drops only the
    pixel beside the edge, so those one or two further out keep the wrong depth wherever the codes fit it by chance.
    Computed by torch on `device` (window extremes: max-pools)."""
    d = torch.as_tensor(np.asarray(field_depth, np.float32), device=device)
    has = torch.isfinite(d)
    limit = footprints * d / min(camera.fx, camera.fy)

    def window_max(x, radius):
        return torch.nn.functional.max_pool2d(x[None, None], 2 * radius + 1, stride=1, padding=radius)[0, 0]

    none = torch.zeros_like(has)
    far = has & (d + window_max(-torch.where(has, d, torch.inf), far_radius) > limit) if far_radius > 0 else none
    near = has & (window_max(torch.where(has, d, -torch.inf), near_radius) - d > limit) if near_radius > 0 else none
    return near.cpu().numpy(), far.cpu().numpy()


def readmit_edge_pixels(before: np.ndarray, after: np.ndarray, camera, footprints: float, confidence_of,
                        *, min_support: int, min_confidence: float, device=None) -> np.ndarray:
    """[H, W] bool: the pixels the flying-pixel filter dropped (finite in `before`, NaN in `after`, both [H, W]
    mm) that lie on one side of the edge rather than in between: at least `min_support` of their 8 neighbours
    kept a depth in `after` within `footprints` pixel footprints of theirs, and `confidence_of(map)` (a map [H, W]
    of the candidates' depths, NaN elsewhere -> confidence [H, W]) is at least `min_confidence` there.

    The filter drops both sides of every depth edge, so a true occlusion edge costs a pixel on the foreground and
    one on the background, which a Gray code decoder keeps. A pixel the field bent toward the other surface is
    over the limit from its own neighbours and stays dropped; a mixed pixel's codes blend two projector columns
    and fail the confidence. The bars are the options edge_readmit_support and edge_readmit_confidence (0.9: at
    the surface term's 0.8 the readmitted rod edges cost the vertical rig's MAE target, config.py's tuned).
    The neighbour counts by torch on `device` (default the CPU; numpy's took 0.13 s of a GPU extraction)."""
    dropped = np.isfinite(before) & ~np.isfinite(after)
    if not dropped.any():
        return dropped
    b = torch.as_tensor(np.asarray(before, np.float64), device=device)
    limit = footprints * b / min(camera.fx, camera.fy)
    a = torch.as_tensor(np.asarray(after, np.float64), device=device)
    support = (torch.abs(neighbour_stack(a) - b) <= limit).sum(0)  # NaN neighbours compare False
    candidates = dropped & (support >= min_support).cpu().numpy()
    if not candidates.any():
        return candidates
    confidence = np.asarray(confidence_of(np.where(candidates, before, np.nan).astype(np.float32)))
    return candidates & (np.nan_to_num(confidence, nan=0.0) >= min_confidence)


def fill_pinholes(depth: np.ndarray, camera, region: np.ndarray | None, min_neighbours: int,
                  footprints: float) -> tuple[np.ndarray, np.ndarray]:
    """(depth [H, W] float32 mm, filled [H, W] bool): each pixel without depth inside `region` ([H, W] bool; None:
    anywhere) at least `min_neighbours` of whose 8 neighbours have a depth takes the depth at its centre of the plane
    d = c0 + c1 u + c2 v fitted to them by least squares (u, v: their pixel offsets), when every one of them lies
    within `footprints` pixel footprints (z / f mm each) of that plane. Only the input's depths take part: a hole of
    one or two pixels closes, a larger one does not grow shut.

    Why: the filters drop single pixels inside smooth surfaces (a confidence just below its threshold, a doubt), and
    a depth map with scattered pinholes on a flat wall is less complete than a decoder's without being more right.
    A hole beside a depth edge or on a crease fails the plane check and stays; neighbours on a line (a degenerate
    fit) fill nothing."""
    d = np.asarray(depth, np.float64)
    hole = ~np.isfinite(d)
    if region is not None:
        hole &= np.asarray(region, bool)
    filled = np.zeros(d.shape, bool)
    out = np.asarray(depth, np.float32).copy()
    index = np.flatnonzero(hole)
    z = neighbours_at(d, index).T  # [P, 8]: the holes' neighbours only
    enough = np.isfinite(z).sum(1) >= min_neighbours
    index, z = index[enough], z[enough]
    if not index.size:
        return out, filled
    ys, xs = np.divmod(index, d.shape[1])
    has = np.isfinite(z)
    w = has.astype(np.float64)
    X = np.array([(1.0, dx, dy) for dy, dx in NEIGHBOUR_OFFSETS])  # [8, 3]: 1, u, v of each neighbour
    A = np.einsum("pk,ki,kj->pij", w, X, X)
    b = np.einsum("pk,ki->pi", w * np.nan_to_num(z), X)
    solvable = np.abs(np.linalg.det(A)) > 1e-9
    coef = np.zeros_like(b)
    coef[solvable] = np.linalg.solve(A[solvable], b[solvable, :, None])[..., 0]
    residual = np.where(has, np.abs(z - coef @ X.T), 0.0).max(1)
    ok = solvable & (coef[:, 0] > 0) & (residual <= footprints * coef[:, 0] / min(camera.fx, camera.fy))
    out[ys[ok], xs[ok]] = coef[ok, 0]
    filled[ys[ok], xs[ok]] = True
    return out, filled


@torch.no_grad()
def denoise_depth(depth: np.ndarray, camera, radius: int, footprints: float = 4.0, device=None) -> np.ndarray:
    """Depth [H, W] (mm, NaN kept NaN) with each finite pixel replaced by the value at the pixel of the plane
    d = c0 + c1 u + c2 v fitted by least squares to the depths of its (2 radius + 1)^2 window (u, v in pixels from
    the centre, the centre included) that lie within `footprints` pixel footprints (z / f mm each) of its own depth.

    Why: the field's surface carries noise at the scale of a few pixels (a hash grid's finest cells are about one
    pixel footprint and fit the images' noise; the refinement moves windows, not single pixels). A smooth surface
    is locally a plane; the tolerance keeps other surfaces out (a depth edge jumps by more: the flying-pixel filter
    drops jumps of 10 footprints), and a slanted surface whose far window pixels leave the tolerance is fitted on
    the part that stays. On a curved surface of radius R the fit's bias is about mean(u^2 + v^2) fp^2 / (2 R), fp
    the footprint in mm: 0.02 mm for R = 50 mm, radius 4 and the default rig's 0.39 mm at 700 mm.
    Computed by torch in float64 on `device` (default the CPU)."""
    d = torch.as_tensor(np.asarray(depth, np.float64), device=device)
    if radius <= 0 or not torch.isfinite(d).any():
        return np.asarray(depth, np.float32).copy()
    H, W = d.shape
    tol = footprints * d / min(camera.fx, camera.fy)
    pad = torch.nn.functional.pad(d, (radius, radius, radius, radius), value=float("nan"))
    # normal equations of the fit to the offsets n - d: sums over the window's accepted pixels
    n0 = torch.zeros_like(d)
    su, sv, suu, suv, svv = (torch.zeros_like(d) for _ in range(5))
    b0, bu, bv = (torch.zeros_like(d) for _ in range(3))
    for dy in range(2 * radius + 1):
        for dx in range(2 * radius + 1):
            n = pad[dy : dy + H, dx : dx + W]
            ok = (torch.abs(n - d) <= tol).to(d.dtype)  # NaN on either side compares False
            off = torch.nan_to_num(n - d) * ok
            u, v = float(dx - radius), float(dy - radius)
            n0 += ok
            su += u * ok
            sv += v * ok
            suu += u * u * ok
            suv += u * v * ok
            svv += v * v * ok
            b0 += off
            bu += u * off
            bv += v * off
    A = torch.stack([torch.stack([n0, su, sv], -1), torch.stack([su, suu, suv], -1),
                     torch.stack([sv, suv, svv], -1)], -2)  # [H, W, 3, 3]
    # a tiny ridge: a window whose accepted pixels lie on one line leaves the slope across it at 0
    A = A + 1e-6 * torch.eye(3, dtype=d.dtype, device=d.device)
    c0 = torch.linalg.solve(A, torch.stack([b0, bu, bv], -1)[..., None])[..., 0, 0]
    out = torch.where(torch.isfinite(d), d + c0, d)
    return out.float().cpu().numpy()


@torch.no_grad()
def sphere_trace_depth(field, camera, depth_range, device, valid: np.ndarray | None = None, max_steps: int = 128,
                       chunk: int = 1 << 16, refine: int = 8) -> np.ndarray:
    """Depth [H, W] by sphere tracing each pixel's ray from the near to the far depth (steps of the SDF
    value, at least 1/512 of the range), then secant refinement of the first sign change. Pixels with no
    crossing (or outside `valid`) are NaN."""
    H, W = camera.height, camera.width
    dirs = torch.as_tensor(camera_rays(camera).reshape(-1, 3).astype(np.float32), device=device)  # a writable copy
    sel = torch.arange(H * W, device=device)
    if valid is not None:
        sel = sel[torch.as_tensor(valid.reshape(-1), device=device)]
    depth = torch.full((H * W,), float("nan"), device=device)
    near, far = depth_range
    min_step = (far - near) / 512.0
    for s0 in range(0, sel.numel(), chunk):
        idx = sel[s0 : s0 + chunk]
        d = dirs[idx]
        t_far = far / d[:, 2]
        t = near / d[:, 2]
        f = field(d * t[:, None])
        a, fa, b, fb = t.clone(), f.clone(), t.clone(), f.clone()  # bracket of the first crossing
        found = f <= 0  # inside at the near plane: the surface is there
        live = torch.nonzero(~found).squeeze(1)
        for _ in range(max_steps):
            if live.numel() == 0:
                break
            t_new = t[live] + torch.clamp(f[live], min=min_step)
            f_new = field(d[live] * t_new[:, None])
            crossed = f_new <= 0
            c = live[crossed]
            a[c], fa[c], b[c], fb[c] = t[c], f[c], t_new[crossed], f_new[crossed]
            found[c] = True
            t[live], f[live] = t_new, f_new
            live = live[~crossed & (t_new < t_far[live])]
        for _ in range(refine):  # secant steps, keeping the bracket [a (f > 0), b (f <= 0)]
            den = fb - fa
            m = torch.where(den.abs() > 1e-12, b - fb * (b - a) / torch.where(den.abs() > 1e-12, den, torch.ones_like(den)), b)
            m = torch.minimum(torch.maximum(m, torch.minimum(a, b)), torch.maximum(a, b))
            fm = field(d * m[:, None])
            pos = fm > 0
            a, fa = torch.where(pos, m, a), torch.where(pos, fm, fa)
            b, fb = torch.where(pos, b, m), torch.where(pos, fb, fm)
        t_hit = torch.where(fb.abs() <= fa.abs(), b, a)
        ok = found & (t_hit <= t_far)
        depth[idx] = torch.where(ok, t_hit * d[:, 2], torch.full_like(t_hit, float("nan")))
    return depth.reshape(H, W).cpu().numpy()
