"""The virtual scanner: renders a Scan with exact ground truth from triangle meshes (Warp BVH ray queries).

Image formation per camera pixel (ray through the pixel centre):
    first hit x (GT depth = x_z, mm), smooth normal n, albedo rho (optionally textured);
    lit = facing the projector, not shadowed, inside the projector image; GT mask = hit and lit;
    radiance = gain * rho * cos(n, to projector) * (ref_dist / |x - c_p|)^2 * P_blur(pi(x)) + ambient * rho
    where P_blur is the pattern (with the lens's halos `halo` and `near_halo`, halo_patterns) blurred by a Gaussian of
    sigma = defocus_sigma + defocus_slope * |z_p - focus_dist| / focus_dist projector px, sampled bilinearly at the
    projection pi(x) (projector distortion applied);
    optics and pixels (off by default): with `supersample` k > 1 (odd) each camera pixel is k x k rays
    whose radiances are averaged (pixel integration: albedo steps, pattern edges and depth edges inside a
    pixel mix, as on a real sensor); `camera_blur` > 0 convolves the radiance with a Gaussian lens PSF of
    that sigma (camera px) before the pixels integrate it; ground truth (depth, mask) is the ray through
    the pixel centre (the middle one of the k x k);
    camera: I = response(clip(radiance + black_level, 0, 1)) with response I ** (1 / gamma) or the sRGB curve, then
    Poisson shot noise (full_well electrons at I = 1) plus Gaussian read noise, then quantisation to `bits`.
Every effect can be switched off (`SimOptions`); all randomness comes from `seed`. Named camera models
(`CAMERA_MODELS`, `camera_model`) give the settings that benchmark sweeps use as one dimension.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np

from ..devices import warp_device
from ..scans.patterns import PatternSet, named_set
from .rigs import DEPTH_RANGE_MM, make_rig
from ..scans.scan import Scan
from ..scans.scanner import Camera, Projector, with_halo
from .scenes import SceneObject, build_scene

__all__ = ["SimOptions", "simulate", "simulate_scene", "RenderedGeometry", "CAMERA_MODELS", "camera_model"]

RESPONSES = ("gamma", "srgb")


@dataclass
class SimOptions:
    """Virtual scanner settings (intensities in [0, 1] of the camera's full scale)."""

    noise: bool = True
    full_well: float = 6000.0  # electrons at full scale (shot noise)
    read_noise: float = 0.004  # Gaussian read noise std, full-scale units
    bits: int = 8  # quantisation: 8 or 16; 0 keeps float (saved as 16-bit)
    gamma: float = 1.0  # camera response I ** (1 / gamma); 1 = linear (machine-vision cameras)
    # "gamma": I ** (1 / gamma); "srgb": the sRGB encoding curve (a linear toe below 0.0031308, then
    # 1.055 I ** (1 / 2.4) - 0.055: not a power law; needs gamma = 1), as consumer cameras and webcams write
    response: str = "gamma"
    supersample: int = 1  # k x k rays per camera pixel, averaged (pixel integration); odd, 1 = one ray
    camera_blur: float = 0.0  # Gaussian lens PSF sigma (camera px) applied before pixel integration; 0 = none
    defocus: bool = True
    defocus_sigma: float = 0.6  # projector defocus at the focus plane (projector px)
    defocus_slope: float = 2.0  # extra sigma per unit of relative distance from the focus plane
    # a lens halo around the projected patterns (scans.scanner.with_halo): this share of the light spread by a
    # Gaussian of halo_sigma projector px; the real capture's edges show about 0.1 at 40 px (bench.edge_profile)
    halo: float = 0.0
    halo_sigma: float = 40.0
    # a second, nearer scale of the same tail: the real capture's edges fit 0.15 at 3 px beside 0.085 at 49 px
    # (bench.real_twin: a core, a near and a far halo fitted to every bit's edge profile at once)
    near_halo: float = 0.0
    near_halo_sigma: float = 3.0
    focus_dist: float = 750.0  # projector focus distance (mm, projector z)
    shading: bool = True  # cosine and inverse-square fall-off toward the projector
    ambient: float = 0.03  # ambient light (times albedo)
    gain: float = 0.8  # projector power: white on albedo 1 facing the projector at ref_dist
    ref_dist: float = 750.0  # mm
    texture: bool = True  # per-object albedo textures where the scene defines them
    # the camera's offset (full scale) added to every pixel before the response: the real capture's black frame
    # reads about 0.02 on the white and the black squares alike, a dark level rather than light
    black_level: float = 0.0
    seed: int = 0

    def __post_init__(self):
        if self.response not in RESPONSES:
            raise ValueError(f"SimOptions.response must be one of {RESPONSES}, got {self.response!r}")
        if not self.gamma > 0:
            raise ValueError(f"SimOptions.gamma must be > 0, got {self.gamma}")
        if self.response == "srgb" and self.gamma != 1.0:
            raise ValueError(f"SimOptions: response 'srgb' is its own curve; gamma must stay 1, got {self.gamma}")
        if int(self.supersample) != self.supersample or self.supersample < 1 or self.supersample % 2 == 0:
            raise ValueError(f"SimOptions.supersample must be an odd integer >= 1 (the middle ray is the pixel "
                             f"centre), got {self.supersample}")
        if not self.camera_blur >= 0:
            raise ValueError(f"SimOptions.camera_blur must be >= 0 camera px, got {self.camera_blur}")
        if not 0 <= self.halo < 1 or not self.halo_sigma > 0:
            raise ValueError(f"SimOptions: halo must be in [0, 1) and halo_sigma > 0, got {self.halo}, {self.halo_sigma}")
        if not 0 <= self.near_halo < 1 - self.halo or not self.near_halo_sigma > 0:
            raise ValueError(f"SimOptions: near_halo must be in [0, 1 - halo) and near_halo_sigma > 0, got "
                             f"{self.near_halo}, {self.near_halo_sigma}")
        if not 0 <= self.black_level < 1:
            raise ValueError(f"SimOptions.black_level must be in [0, 1), got {self.black_level}")
        if self.bits not in (0, 8, 16):
            raise ValueError(f"SimOptions.bits must be 0, 8 or 16, got {self.bits}")


# Named camera models: one sweep dimension of the benchmarks. "linear" is the scanner the six-scene
# results were measured with (one ray per pixel, linear response); the others add what real cameras do.
CAMERA_MODELS = {
    "linear": {},
    # pixel integration (3 x 3 rays) and a lens PSF of 0.5 px: albedo and depth steps mix inside a pixel
    "optics": {"supersample": 3, "camera_blur": 0.5},
    # the same optics with a power-law response of gamma 2.2
    "gamma": {"supersample": 3, "camera_blur": 0.5, "gamma": 2.2},
    # the same optics with the sRGB curve (linear toe + power 1/2.4), not a power law
    "srgb": {"supersample": 3, "camera_blur": 0.5, "response": "srgb"},
    # the same optics with the real capture's lens halo: 10% of the light spread over 40 projector px
    "halo": {"supersample": 3, "camera_blur": 0.5, "halo": 0.1, "halo_sigma": 40.0},
    # the real capture's optics as measured (bench.real_twin): its edge profile's core (0.59 projector px in all,
    # so the projector's own 0.49 beside the pixel and the lens blur) in focus at every depth, a near and a far
    # halo, and the camera's black level
    "procam": {"supersample": 3, "camera_blur": 0.5, "defocus_sigma": 0.49, "defocus_slope": 0.0, "near_halo": 0.146,
               "near_halo_sigma": 3.1, "halo": 0.085, "halo_sigma": 49.0, "black_level": 0.02},
}


def camera_model(name: str, **overrides) -> SimOptions:
    """SimOptions of a named camera model (`CAMERA_MODELS`), with any field overridden."""
    if name not in CAMERA_MODELS:
        raise ValueError(f"unknown camera model {name!r}; camera models: {', '.join(CAMERA_MODELS)}")
    return SimOptions(**{**CAMERA_MODELS[name], **overrides})


@dataclass
class RenderedGeometry:
    """Per camera pixel (flattened [P]): depth (mm, NaN no hit), normal [P, 3], albedo, lit (bool),
    shade (albedo * cos * fall-off), projector pixel [P, 2] and projector-frame z (mm)."""

    depth: np.ndarray
    normal: np.ndarray
    albedo: np.ndarray
    lit: np.ndarray
    shade: np.ndarray
    uv_proj: np.ndarray
    z_proj: np.ndarray
    timings: dict = field(default_factory=dict)


def _merge_objects(objects: list[SceneObject]):
    verts, faces, face_obj, normals = [], [], [], []
    offset = 0
    for i, o in enumerate(objects):
        m = o.mesh
        verts.append(np.asarray(m.vertices, np.float64))
        faces.append(np.asarray(m.faces, np.int64) + offset)
        normals.append(np.asarray(m.vertex_normals, np.float64))
        face_obj.append(np.full(len(m.faces), i, np.int32))
        offset += len(m.vertices)
    return np.concatenate(verts), np.concatenate(faces), np.concatenate(face_obj), np.concatenate(normals)


def render_geometry(objects: list[SceneObject], camera: Camera, projector: Projector, options: SimOptions,
                    device: str | None = None) -> RenderedGeometry:
    """Ray-cast the scene for every camera pixel (see module docstring)."""
    from slwarp.kernels import runtime
    from slwarp.kernels.geometry import projector_params
    from slwarp.kernels.simulate import TEXTURE_CHECKER, TEXTURE_SINE, cast_camera_rays

    wp = runtime.init()
    device = warp_device(device)
    t0 = time.perf_counter()
    verts, faces, face_obj, vnormals = _merge_objects(objects)
    with wp.ScopedDevice(device):
        mesh = wp.Mesh(
            points=wp.array(verts.astype(np.float32), dtype=wp.vec3),
            indices=wp.array(faces.astype(np.int32).ravel(), dtype=wp.int32),
            velocities=wp.array(vnormals.astype(np.float32), dtype=wp.vec3),
        )
        t_bvh = time.perf_counter()
        dirs = camera.pixel_to_ray(camera.pixel_grid()).reshape(-1, 3).astype(np.float32)
        P = dirs.shape[0]
        albedo = np.array([o.albedo for o in objects], np.float32)
        tex = np.array([o.texture if options.texture else 0.0 for o in objects], np.float32)
        codes = {"sine": int(TEXTURE_SINE), "checker": int(TEXTURE_CHECKER)}
        tex_kind = np.array([codes[o.texture_kind] for o in objects], np.int32)
        period = np.array([o.texture_period for o in objects], np.float32)
        out = {
            "depth": wp.empty(P, dtype=float), "normal": wp.empty(P, dtype=wp.vec3), "uv_proj": wp.empty(P, dtype=wp.vec2),
            "z_proj": wp.empty(P, dtype=float), "lit": wp.empty(P, dtype=wp.int32), "shade": wp.empty(P, dtype=float),
            "albedo": wp.empty(P, dtype=float),
        }
        wp.launch(
            cast_camera_rays, dim=P,
            inputs=[mesh.id, wp.array(dirs, dtype=wp.vec3), wp.array(face_obj, dtype=wp.int32), wp.array(albedo),
                    wp.array(tex), wp.array(tex_kind, dtype=wp.int32), wp.array(period), projector_params(projector),
                    wp.vec3(*projector.center.astype(np.float32)), float(options.ref_dist), 0.05],
            outputs=[out["depth"], out["normal"], out["uv_proj"], out["z_proj"], out["lit"], out["shade"], out["albedo"]],
        )
        res = {k: v.numpy() for k, v in out.items()}
    t1 = time.perf_counter()
    shade = res["shade"] if options.shading else np.where(res["lit"] > 0, res["albedo"], 0.0).astype(np.float32)
    return RenderedGeometry(
        depth=res["depth"], normal=res["normal"], albedo=res["albedo"], lit=res["lit"] > 0, shade=shade,
        uv_proj=res["uv_proj"], z_proj=res["z_proj"],
        timings={"bvh_s": t_bvh - t0, "raycast_s": t1 - t_bvh},
    )


def _blur_levels(patterns: np.ndarray, sigmas: np.ndarray) -> np.ndarray:
    """[L, N, H, W]: the patterns Gaussian-blurred at each sigma (projector px; 0 = sharp)."""
    import cv2

    out = np.empty((len(sigmas), *patterns.shape), np.float32)
    for li, s in enumerate(sigmas):
        for n in range(patterns.shape[0]):
            out[li, n] = patterns[n] if s <= 1e-6 else cv2.GaussianBlur(
                patterns[n], (0, 0), sigmaX=float(s), borderType=cv2.BORDER_REPLICATE)
    return out


def halo_patterns(patterns: np.ndarray, options: SimOptions) -> np.ndarray:
    """patterns [N, Hp, Wp] through the lens's tail: (1 - halo - near_halo) P + halo G(halo_sigma) P + near_halo
    G(near_halo_sigma) P (scans.scanner.with_halo per scale; the defocus applies on top)."""
    far = with_halo(patterns, options.halo, options.halo_sigma)
    if options.near_halo <= 0:
        return far
    near = with_halo(patterns, 1.0, options.near_halo_sigma)  # the near blur alone
    return (far + options.near_halo * (near - np.asarray(patterns, np.float32))).astype(np.float32)


def sample_projected_patterns(geom: RenderedGeometry, patterns: np.ndarray, options: SimOptions, device: str | None = None) -> np.ndarray:
    """[N, P]: (defocused) pattern value seen at each camera pixel; 0 where not lit."""
    from slwarp.kernels import runtime
    from slwarp.kernels.simulate import sample_patterns

    wp = runtime.init()
    device = warp_device(device)
    if options.defocus:
        zl = geom.z_proj[geom.lit]
        rel = np.abs(zl - options.focus_dist).max() / options.focus_dist if zl.size else 0.0
        s_lo, s_hi = options.defocus_sigma, options.defocus_sigma + options.defocus_slope * rel
        n_levels = int(np.clip(np.ceil((s_hi - s_lo) / 0.15), 0, 12)) + 1
        sigmas = np.linspace(s_lo, s_hi, n_levels).astype(np.float32)
        sigma0, slope = options.defocus_sigma, options.defocus_slope
    else:
        sigmas = np.zeros(1, np.float32)
        sigma0, slope = 0.0, 0.0
    levels = _blur_levels(halo_patterns(patterns, options), sigmas)
    N, P = patterns.shape[0], geom.depth.shape[0]
    with wp.ScopedDevice(device):
        out = wp.empty((N, P), dtype=float)
        wp.launch(
            sample_patterns, dim=(N, P),
            inputs=[wp.array(levels, dtype=wp.float32), wp.array(sigmas), wp.array(geom.uv_proj, dtype=wp.vec2),
                    wp.array(geom.z_proj), wp.array(geom.lit.astype(np.int32)), float(sigma0), float(slope),
                    float(options.focus_dist)],
            outputs=[out],
        )
        return out.numpy()


def radiance(geom: RenderedGeometry, values: np.ndarray, options: SimOptions) -> np.ndarray:
    """[N, P] scene radiance (camera full-scale units, before clipping) from pattern values [N, P]."""
    hit = np.isfinite(geom.depth)
    return options.gain * geom.shade[None, :] * values + options.ambient * np.where(hit, geom.albedo, 0.0)[None, :]


def camera_response(radiance: np.ndarray, options: SimOptions) -> np.ndarray:
    """The camera's response curve applied to radiance plus the camera's black level, clipped to [0, 1] (full
    scale)."""
    img = np.clip(radiance + options.black_level, 0.0, 1.0)
    if options.response == "srgb":
        return np.where(img <= 0.0031308, 12.92 * img, 1.055 * img ** (1.0 / 2.4) - 0.055)
    if options.gamma != 1.0:
        img = img ** (1.0 / options.gamma)
    return img


def sensor_images(radiance: np.ndarray, options: SimOptions) -> np.ndarray:
    """Camera images [N, P] in [0, 1] from the radiance each pixel collected: response, noise, quantisation."""
    img = camera_response(radiance, options)
    if options.noise:
        rng = np.random.default_rng(options.seed + 7919)
        img = rng.poisson(img * options.full_well) / options.full_well + rng.normal(0.0, options.read_noise, img.shape)
        img = np.clip(img, 0.0, 1.0)
    if options.bits:
        levels = (1 << options.bits) - 1
        img = np.rint(img * levels) / levels
    return img.astype(np.float32)


def form_images(geom: RenderedGeometry, values: np.ndarray, options: SimOptions) -> np.ndarray:
    """Camera images [N, P] in [0, 1] from pattern values, one ray per pixel: radiometry, response, noise,
    quantisation."""
    return sensor_images(radiance(geom, values, options), options)


def pixel_radiance(geom_fine: RenderedGeometry, patterns: np.ndarray, camera: Camera, options: SimOptions,
                   device: str | None = None, chunk_frames: int = 4) -> np.ndarray:
    """[N, H * W] radiance collected by each camera pixel from a geometry rendered with k x k rays per pixel
    (k = options.supersample, on `camera.scaled(k)`): the lens PSF (camera_blur, a Gaussian) applied to the
    fine radiance, then the k x k box of each pixel averaged. Frames are processed `chunk_frames` at a time
    (the fine values of all frames at once would need N x k^2 x H x W floats)."""
    import cv2

    k, H, W = options.supersample, camera.height, camera.width
    out = np.empty((len(patterns), H * W), np.float64)
    for f0 in range(0, len(patterns), chunk_frames):
        values = sample_projected_patterns(geom_fine, patterns[f0 : f0 + chunk_frames], options, device)
        rad = radiance(geom_fine, values, options).reshape(-1, H * k, W * k)
        for j, img in enumerate(rad):
            if options.camera_blur > 0:
                img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), sigmaX=options.camera_blur * k,
                                       borderType=cv2.BORDER_REFLECT)
            out[f0 + j] = img.reshape(H, k, W, k).mean(axis=(1, 3), dtype=np.float64).ravel()
    return out


def simulate(objects: list[SceneObject], camera: Camera, projector: Projector, patterns: PatternSet,
             options: SimOptions | None = None, depth_range=None, device: str | None = None, meta: dict | None = None) -> Scan:
    """Render a Scan of `objects` (camera frame, mm) with exact ground truth.

    Returns a Scan with images, patterns, gt_depth (NaN where no hit) and mask (hit and lit);
    scan.meta['timings'] holds the stage timings in seconds.
    """
    options = options or SimOptions()
    if patterns.patterns.shape[1:] != (projector.height, projector.width):
        raise ValueError(f"patterns are {patterns.width}x{patterns.height}, projector is {projector.width}x{projector.height}")
    t0 = time.perf_counter()
    k = options.supersample
    H, W = camera.height, camera.width
    if k == 1 and options.camera_blur == 0:
        geom = render_geometry(objects, camera, projector, options, device)
        t1 = time.perf_counter()
        values = sample_projected_patterns(geom, patterns.patterns, options, device)
        t2 = time.perf_counter()
        images = form_images(geom, values, options)
        depth = geom.depth.reshape(H, W)
        lit = geom.lit.reshape(H, W)
    else:
        geom = render_geometry(objects, camera.scaled(k), projector, options, device)
        t1 = time.perf_counter()
        rad = pixel_radiance(geom, patterns.patterns, camera, options, device)
        t2 = time.perf_counter()
        images = sensor_images(rad, options)
        c = k // 2  # the middle ray of each pixel's k x k is its centre: the ground truth
        depth = geom.depth.reshape(H, k, W, k)[:, c, :, c]
        lit = geom.lit.reshape(H, k, W, k)[:, c, :, c]
    images = images.reshape(len(patterns), H, W)
    t3 = time.perf_counter()
    depth = np.ascontiguousarray(depth, np.float32)
    mask = lit & np.isfinite(depth)
    if depth_range is None:
        valid = depth[np.isfinite(depth)]
        depth_range = (float(valid.min()) * 0.9, float(valid.max()) * 1.1) if valid.size else DEPTH_RANGE_MM
    timings = {**geom.timings, "patterns_s": t2 - t1, "imaging_s": t3 - t2, "total_s": t3 - t0}
    info = {"simulator": asdict(options), "timings": timings, **(meta or {})}
    return Scan(camera, projector, images, patterns.patterns, patterns.names, depth_range=tuple(depth_range),
                gt_depth=depth, mask=mask, meta=info, declared_roles=patterns.roles)


def simulate_scene(scene: str = "bunny", patterns: str | PatternSet = "random6", rig: str = "default",
                   options: SimOptions | str | None = None, device: str | None = None, pattern_seed: int = 0) -> Scan:
    """A built-in scene on a built-in rig with a named pattern set (see `slwarp.scans.patterns.named_set`);
    options: SimOptions, or the name of a camera model (`CAMERA_MODELS`); default: SimOptions()."""
    camera_name = options if isinstance(options, str) else None
    if camera_name is not None:
        options = camera_model(camera_name)
    camera, projector = make_rig(rig)
    if isinstance(patterns, str):
        pset = named_set(patterns, projector.width, projector.height, seed=pattern_seed)
        pname = patterns
    else:
        pset, pname = patterns, "custom"
    return simulate(build_scene(scene), camera, projector, pset, options, depth_range=DEPTH_RANGE_MM, device=device,
                    meta={"scene": scene, "rig": rig, "patterns": pname,
                          **({"camera_model": camera_name} if camera_name else {})})
