"""A real capture's twin for the virtual scanner: the capture's planes, chessboard, albedos and noise, fitted to its
depth map and its white and black frames, so that the simulator renders the same scene through the same
calibration with exact ground truth.

    twin = fit_twin(depth, region, white, black, pairs, camera, projector)   # from a real capture (see bench.real_twin)
    twin.to_dict() / Twin.from_dict(d)                                      # kept as JSON beside the capture
    objects, options = twin.scene_objects(), twin.sim_options("procam")     # then sim.simulate(objects, ...)

The scene is what the capture of a chessboard plate shows: the plate (the plane of the chessboard's region), the
sheet of paper on it and its printed squares (the region between the outermost inner corners, widened by a square
each side; each layer 0.2 mm in front of the one below), the wall (the plane holding most of the other decoded
points) and a third plane where one holds enough of the rest (the desk). Albedos are the white frame minus the black one, divided by each pixel's shading (the cosine toward the
projector and the fall-off from it). The noise is fitted to pattern + inverse pairs, whose sum is the white and
black frames' but for noise. The projector is focused on the board, as a user focuses it.

Why: the built-in scenes are objects before a wall at 0.6-1 m seen by an invented rig, and the simulator did not
rank the methods as the real captures do once a halo was added (docs/accuracy.md, section 23). A twin holds the real
geometry, calibration and radiometry fixed, so what is left to differ is the optics and what the real images have
beyond them.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from ..scans.scanner import Camera, Projector, camera_rays
from .scenes import SceneObject
from .simulate import SimOptions, camera_model

__all__ = ["Twin", "TwinBox", "fit_plane", "fit_noise", "fit_twin"]

PAPER_LIFT_MM = 0.2  # the paper and its print each stand this far in front of what they lie on
BOX_DEPTH_MM = 2.0  # thickness of a twin's boxes (only their front faces are seen)
MIN_SECOND_PLANE = 0.02  # share of the image a second plane must hold to enter the twin


@dataclass
class TwinBox:
    """A thin box whose front face lies on a plane: centre (mm, camera frame) of that face, its in-plane axes u, v
    (unit), extents (mm) along them, the normal n (unit, away from the camera) and its albedo."""

    name: str
    center: list
    u: list
    v: list
    extents: list
    normal: list
    albedo: float

    def scene_object(self) -> SceneObject:
        import trimesh

        u, v, n = (np.asarray(a, np.float64) for a in (self.u, self.v, self.normal))
        T = np.eye(4)
        T[:3, 0], T[:3, 1], T[:3, 2] = u, v, n
        T[:3, 3] = np.asarray(self.center, np.float64) + n * BOX_DEPTH_MM / 2  # the box lies behind its face
        mesh = trimesh.creation.box(extents=(*self.extents, BOX_DEPTH_MM), transform=T)
        # flat faces: each face its own vertices, so that the simulator's smooth normal (the vertex normals
        # interpolated) is the face's; a box's 8 shared corners would give the diagonals of three faces
        mesh.unmerge_vertices()
        return SceneObject(self.name, mesh, float(self.albedo))


@dataclass
class Twin:
    """A capture's twin: camera and projector (scan.yaml dicts; the projector's with its R and T), boxes, radiometry (SimOptions fields: gain,
    ambient, ref_dist, focus_dist, full_well, read_noise, black_level), depth_range (mm) and what the fit saw
    (`report`: plane inliers, albedos, square size, noise)."""

    camera: dict
    projector: dict
    boxes: list[TwinBox]
    radiometry: dict
    depth_range: tuple
    report: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["depth_range"] = list(self.depth_range)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "Twin":
        return cls(d["camera"], d["projector"], [TwinBox(**b) for b in d["boxes"]], dict(d["radiometry"]),
                   tuple(d["depth_range"]), dict(d.get("report") or {}))

    def rig(self) -> tuple[Camera, Projector]:
        return Camera.from_dict(self.camera), Projector.from_dicts(self.projector, self.projector)

    def scene_objects(self) -> list[SceneObject]:
        return [b.scene_object() for b in self.boxes]

    def sim_options(self, model: str = "procam", seed: int = 0) -> SimOptions:
        """SimOptions of a named camera model (simulate.CAMERA_MODELS) with this capture's radiometry and noise,
        the projector focused on the board."""
        return camera_model(model, seed=seed, **self.radiometry)


def fit_plane(points: np.ndarray, inlier_mm: float = 4.0, iterations: int = 300, seed: int = 0):
    """The plane holding most of `points` [P, 3] (mm): (n unit away from the camera at the origin, d > 0) with
    n . x = d (n_z > 0 would turn a desk seen from above toward the camera), and the inlier mask
    (|n . x - d| <= inlier_mm). Three-point samples, then least squares over the inliers twice."""
    P = np.asarray(points, np.float64)
    if len(P) < 3:
        raise ValueError(f"a plane needs 3 points, got {len(P)}")
    rng = np.random.default_rng(seed)
    best, best_count = None, -1
    probe = P[rng.choice(len(P), min(len(P), 20000), replace=False)]
    for _ in range(iterations):
        a, b, c = P[rng.choice(len(P), 3, replace=False)]
        n = np.cross(b - a, c - a)
        if np.linalg.norm(n) < 1e-9:
            continue
        n /= np.linalg.norm(n)
        count = int((np.abs(probe @ n - n @ a) <= inlier_mm).sum())
        if count > best_count:
            best, best_count = (n, float(n @ a)), count
    n, d = best
    for _ in range(2):
        inl = np.abs(P @ n - d) <= inlier_mm
        c = P[inl].mean(0)
        n = np.linalg.svd(P[inl] - c, full_matrices=False)[2][2]
        d = float(n @ c)
    if d < 0:
        n, d = -n, -d
    return n, d, np.abs(P @ n - d) <= inlier_mm


def fit_noise(pairs, white: np.ndarray, black: np.ndarray, bins: int = 12, quantum: float = 1.0 / 255.0) -> dict:
    """The camera's noise from pattern + inverse pairs [(I, J), ...] (float [0, 1]): I + J - white - black is noise
    alone, of variance 2 (W + B) / full_well + 4 read^2 for shot noise at full_well electrons per full scale and a
    read noise `read`. Fitted by least squares over bins of the white level; quantum: the frames' grey level (8-bit:
    1 / 255). Returns full_well, read_noise and the measured per-image standard deviations (sigma_at: level ->
    sigma)."""
    W, B = np.asarray(white, np.float64), np.asarray(black, np.float64)
    s = np.concatenate([(np.asarray(i, np.float64) + np.asarray(j, np.float64) - W - B).ravel() for i, j in pairs])
    lev = np.tile((2 * (W + B)).ravel(), len(pairs))  # I + J's shot noise is W + B's, W and B's their own
    edges = np.quantile(lev, np.linspace(0.02, 0.98, bins + 1))
    x, y = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (lev >= lo) & (lev < hi)
        if m.sum() > 100:
            # the variance of the values within 4 robust sigmas: the pairs' few edge pixels (a stripe edge moved by
            # noise) are not sensor noise; the bound is at least 2 grey levels, since on 8-bit frames the median
            # absolute deviation itself counts whole levels. The four frames' quantisation (1 / 12 level^2 each)
            # comes off: the simulator quantises its own.
            med = np.median(s[m])
            bound = 4.0 * max(1.4826 * np.median(np.abs(s[m] - med)), 2.0 * quantum)
            kept = s[m][np.abs(s[m] - med) <= bound]
            x.append(lev[m].mean())
            y.append(max(kept.var() - 4.0 * quantum ** 2 / 12.0, 0.0))
    A = np.stack([np.asarray(x), np.full(len(x), 4.0)], 1)
    (inv_fw, read2), *_ = np.linalg.lstsq(A, np.asarray(y), rcond=None)
    inv_fw, read2 = max(inv_fw, 1e-6), max(read2, 0.0)
    return {"full_well": float(1.0 / inv_fw), "read_noise": float(np.sqrt(read2)),
            "sigma_at": {f"{xi / 4:.3f}": float(np.sqrt(yi / 4)) for xi, yi in zip(x, y)}}


def _plane_axes(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """u along the camera's x projected onto the plane, v = n x u (the camera's y, roughly)."""
    u = np.array([1.0, 0.0, 0.0]) - n * n[0]
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


def _rectangle(points: np.ndarray, n: np.ndarray, d: float, q: float = 0.002):
    """The rectangle on plane (n, d) that holds `points` [P, 3] (mm) but their q and 1 - q quantiles along its axes:
    centre [3] on the plane, axes u, v [3] (u the points' principal direction, toward the camera's +x) and extents
    (mm)."""
    u0, v0 = _plane_axes(n)
    uv = np.stack([points @ u0, points @ v0], 1)
    c = uv.mean(0)
    w, vecs = np.linalg.eigh(np.cov((uv - c).T))
    a = vecs[:, 1] if vecs[0, 1] >= 0 else -vecs[:, 1]  # the major axis, pointing to +u0
    u = a[0] * u0 + a[1] * v0
    v = np.cross(n, u)
    pu, pv = points @ u, points @ v
    (lu, hu), (lv, hv) = np.quantile(pu, [q, 1 - q]), np.quantile(pv, [q, 1 - q])
    centre = n * d + u * ((lu + hu) / 2) + v * ((lv + hv) / 2)
    return centre, u, v, (float(hu - lu), float(hv - lv))


def _shading(points: np.ndarray, n: np.ndarray, projector_center: np.ndarray, ref_dist: float) -> np.ndarray:
    """cos(n, to projector) x (ref_dist / distance)^2 at points [P, 3]: what the simulator multiplies albedo by."""
    to_p = projector_center[None, :] - points
    dist = np.linalg.norm(to_p, axis=1)
    return np.clip(-(to_p @ n) / dist, 0.0, 1.0) * (ref_dist / dist) ** 2


def fit_twin(depth: np.ndarray, region: np.ndarray, white: np.ndarray, black: np.ndarray, pairs, camera: Camera,
             projector: Projector, depth_range, squares=(10, 8), paper_margin: float = 1.0,
             plate_margin: float = 1.0, plate_mm: float = 6.0, wall_reach: float = 0.25) -> Twin:
    """A capture's twin from its full decode `depth` [H, W] (mm, NaN where none), the chessboard's `region` [H, W]
    (between its outermost inner corners: (squares - 2) squares across), its white and black frames [H, W] (float
    [0, 1]) and pattern + inverse pairs (for the noise). squares: the print's squares across and down;
    paper_margin, plate_margin: the white paper around them and the plate around the paper, in squares; plate_mm:
    how far from the plate's plane a decoded point may lie and still count as the plate; wall_reach: how far the
    wall reaches past its decoded points, a share of its size each side.

    The scene: the plate (the plane of the region's points), the paper and the print on it, all rectangles in the
    region's principal axes, then the wall (the plane holding most of the other points) and, where enough points are
    left, a third plane (the desk)."""
    H, W = depth.shape
    rays = camera_rays(camera)
    ok = np.isfinite(depth)
    P = np.where(ok[..., None], rays * (depth / np.where(ok, rays[..., 2], 1.0))[..., None], np.nan)
    proj_c = np.asarray(projector.center, np.float64)
    signal = np.asarray(white, np.float64) - np.asarray(black, np.float64)
    reg = region & ok
    n, d, _ = fit_plane(P[reg], inlier_mm=3.0)
    # every pixel's ray on the plate's plane, the rectangles in the region's frame (its principal axes)
    on_plane = rays * (d / (rays @ n))[..., None]
    # the whole quad, its dark squares included: the decoded (light) squares alone lean their axes by their parity
    c_reg, u, v, (ext_u, ext_v) = _rectangle(on_plane[region], n, d)
    square = float(np.mean([ext_u / (squares[0] - 2), ext_v / (squares[1] - 2)]))
    du, dv = np.abs((on_plane - c_reg) @ u), np.abs((on_plane - c_reg) @ v)
    exts = {}
    for name, margin in (("print", 1.0), ("paper", 1.0 + paper_margin), ("plate", 1.0 + paper_margin + plate_margin)):
        exts[name] = (ext_u + 2 * margin * square, ext_v + 2 * margin * square)
    inside = {k: (du <= e[0] / 2) & (dv <= e[1] / 2) for k, e in exts.items()}
    with np.errstate(invalid="ignore"):
        off_plate = ok & ~(inside["plate"] & (np.abs(P @ n - d) <= plate_mm))
    ref_dist = float(np.median(np.linalg.norm(on_plane[inside["plate"]] - proj_c, axis=1)))

    def albedo_at(mask_px: np.ndarray, q: float, normal: np.ndarray, offset: float) -> float:
        """The q-quantile albedo of the pixels `mask_px`, each at its ray's point on the plane (normal, offset):
        the dark squares, which no decoder gives a depth, are measured too."""
        r = rays[mask_px]
        X = r * (offset / (r @ normal))[:, None]
        return float(np.clip(np.quantile(signal[mask_px] / np.maximum(_shading(X, normal, proj_c, ref_dist), 1e-3), q),
                             0.0, 1.0))

    white_sq, black_sq = albedo_at(region, 0.75, n, d), albedo_at(region, 0.10, n, d)
    ring_paper = inside["paper"] & ~inside["print"] & ~off_plate
    ring_plate = inside["plate"] & ~inside["paper"] & ~off_plate
    paper_albedo = albedo_at(ring_paper, 0.5, n, d) if ring_paper.sum() > 100 else white_sq
    plate_albedo = albedo_at(ring_plate, 0.5, n, d) if ring_plate.sum() > 100 else paper_albedo
    boxes = [
        TwinBox("plate", list(c_reg), list(u), list(v), list(exts["plate"]), list(n), plate_albedo),
        TwinBox("paper", list(c_reg - n * PAPER_LIFT_MM), list(u), list(v), list(exts["paper"]), list(n), paper_albedo),
    ]
    # the print: one box per square in the plate's own axes (the simulator's checker texture runs along the camera's
    # x and y, which on a plate turned 57 deg away would stretch its squares 1.8x)
    size_u, size_v = exts["print"][0] / squares[0], exts["print"][1] / squares[1]
    for i in range(squares[0]):
        for j in range(squares[1]):
            centre = c_reg - n * 2 * PAPER_LIFT_MM + u * (i + 0.5 - squares[0] / 2) * size_u \
                + v * (j + 0.5 - squares[1] / 2) * size_v
            boxes.append(TwinBox(f"square_{i}_{j}", list(centre), list(u), list(v), [size_u, size_v], list(n),
                                 black_sq if (i + j) % 2 == 0 else white_sq))
    report = {"plate_distance_mm": float(c_reg[2]), "plate_normal": n.tolist(), "square_mm": square,
              "albedo": {"plate": plate_albedo, "paper": paper_albedo, "white_squares": white_sq,
                         "black_squares": black_sq}}
    # the wall (reaching past the view: its rectangle widened by `wall_reach` each side), then a third plane (the
    # desk, as far as its points reach), from the decoded points off the plate
    rest = off_plate.copy()
    for name, reach in (("wall", wall_reach), ("desk", 0.0)):
        if rest.sum() < MIN_SECOND_PLANE * H * W:
            break
        n2, d2, inl = fit_plane(P[rest], inlier_mm=5.0, seed=len(boxes))
        if inl.sum() < MIN_SECOND_PLANE * H * W:
            break
        # a desk is no wall's leftover (a plane nearly parallel to it) and has the projector on the camera's side
        if name == "desk" and (abs(n2 @ np.asarray(boxes[-1].normal)) > np.cos(np.radians(20.0)) or n2 @ proj_c >= d2):
            report["desk_refused"] = {"normal": n2.tolist(), "share": float(inl.sum() / (H * W))}
            break
        px = np.zeros_like(rest)
        px[rest] = inl
        c2, u2, v2, (e2u, e2v) = _rectangle(P[px], n2, d2)
        a2 = albedo_at(px, 0.5, n2, d2)
        boxes.append(TwinBox(name, list(c2), list(u2), list(v2), [e2u * (1 + 2 * reach), e2v * (1 + 2 * reach)],
                             list(n2), a2))
        report[f"{name}_share"] = float(px.mean())
        report[f"{name}_distance_mm"] = float(np.median(P[px][:, 2]))
        report["albedo"][name] = a2
        rest &= ~px
    noise = fit_noise(pairs, white, black)
    # the projector's z of the print's middle: where a user focuses it
    focus = float((np.asarray(projector.R, np.float64) @ c_reg + np.asarray(projector.T, np.float64))[2])
    radiometry = {"gain": 1.0, "ambient": 0.0, "ref_dist": ref_dist, "focus_dist": focus,
                  "full_well": noise["full_well"], "read_noise": noise["read_noise"],
                  "black_level": float(np.median(np.asarray(black, np.float64)[ok]))}
    report["noise_sigma_at"] = noise["sigma_at"]
    return Twin(camera.to_dict(), {**projector.to_dict(), **projector.extrinsics_dict()}, boxes, radiometry,
                tuple(float(x) for x in depth_range), report)
