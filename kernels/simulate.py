"""Virtual scanner kernels: camera rays against a triangle-mesh BVH, shadows toward the projector, and
bilinear sampling of (defocused) patterns at the projected hit points.

cast_camera_rays: one thread per camera pixel.
    first hit along the (unit) camera ray -> depth z (mm), smooth normal, albedo (with a sinusoidal or
    checkerboard texture);
    lit = facing the projector, not shadowed (second ray toward the projector centre), and inside the
    projector image; shade = albedo * cos(angle to projector) * (ref_dist / dist_to_projector)^2.
sample_patterns: one thread per (frame, pixel): the defocused pattern value at the projector pixel.
first_hit_depth, mesh_hits: camera z of the first (K) hit(s) of each camera ray on a mesh (also used
    to turn a reconstructed mesh into a depth map).
"""

import warp as wp

from slwarp.kernels.geometry import ProjectorParams, bilinear_channel, project_to_projector


TEXTURE_SINE = wp.constant(0)  # smooth 3-D sinusoid (texture_value)
TEXTURE_CHECKER = wp.constant(1)  # hard-edged checkerboard in the camera's x-y (checker_value)


@wp.func
def texture_value(x: wp.vec3, period: float) -> float:
    """Smooth 3-D sinusoidal texture in [0, 1] with the given period (mm)."""
    w = 6.283185307 / period
    return 0.5 + 0.5 * wp.sin(w * x[0]) * wp.sin(w * x[1] + 1.3) * wp.sin(w * x[2] + 0.7)


@wp.func
def checker_value(x: wp.vec3, period: float) -> float:
    """Checkerboard in {0, 1} over the camera frame's x and y (squares of period / 2 mm, edges at multiples
    of it): a print seen face-on, with albedo steps inside camera pixels (the case that mixes codes)."""
    cell = 0.5 * period
    k = int(wp.floor(x[0] / cell)) + int(wp.floor(x[1] / cell))
    return float(k & 1)


@wp.func
def albedo_texture(x: wp.vec3, kind: int, period: float) -> float:
    """The texture in [0, 1] of kind TEXTURE_SINE or TEXTURE_CHECKER at x (mm)."""
    if kind == TEXTURE_CHECKER:
        return checker_value(x, period)
    return texture_value(x, period)


@wp.kernel
def cast_camera_rays(
    mesh: wp.uint64,
    dirs: wp.array(dtype=wp.vec3),
    face_object: wp.array(dtype=wp.int32),
    obj_albedo: wp.array(dtype=float),
    obj_texture: wp.array(dtype=float),
    obj_texture_kind: wp.array(dtype=wp.int32),
    obj_period: wp.array(dtype=float),
    prm: ProjectorParams,
    proj_center: wp.vec3,
    ref_dist: float,
    shadow_eps: float,
    depth: wp.array(dtype=float),
    normal: wp.array(dtype=wp.vec3),
    uv_proj: wp.array(dtype=wp.vec2),
    z_proj: wp.array(dtype=float),
    lit: wp.array(dtype=wp.int32),
    shade: wp.array(dtype=float),
    albedo: wp.array(dtype=float),
):
    i = wp.tid()
    d = dirs[i]
    nan = wp.nan
    q = wp.mesh_query_ray(mesh, wp.vec3(0.0, 0.0, 0.0), d, 1.0e7)
    lit[i] = 0
    shade[i] = 0.0
    uv_proj[i] = wp.vec2(-1.0e6, -1.0e6)
    z_proj[i] = 0.0
    if not q.result:
        depth[i] = nan
        normal[i] = wp.vec3(nan, nan, nan)
        albedo[i] = 0.0
        return
    x = d * q.t
    depth[i] = x[2]
    fn = q.normal
    if wp.dot(fn, d) > 0.0:  # face normal toward the camera (meshes may be open or inverted)
        fn = -fn
    n = wp.normalize(wp.mesh_eval_velocity(mesh, q.face, q.u, q.v))  # smooth normal (vertex normals)
    if wp.dot(n, fn) < 0.0:
        n = -n
    normal[i] = n
    o = face_object[q.face]
    a = obj_albedo[o]
    if obj_texture[o] > 0.0:
        a = a * (1.0 - obj_texture[o] + obj_texture[o] * albedo_texture(x, obj_texture_kind[o], obj_period[o]))
    albedo[i] = a

    to_p = proj_center - x
    dist = wp.length(to_p)
    l = to_p / dist
    cos_p = wp.dot(n, l)
    if cos_p <= 0.0 or wp.dot(fn, l) <= 0.0:
        return
    start = x + fn * shadow_eps
    qs = wp.mesh_query_ray(mesh, start, l, dist - shadow_eps)
    if qs.result:
        return
    uvo = project_to_projector(prm, x)
    if uvo[2] == 0.0:
        return
    if uvo[0] < -0.5 or uvo[0] > prm.size[0] - 0.5 or uvo[1] < -0.5 or uvo[1] > prm.size[1] - 0.5:
        return
    xp = prm.R * x + prm.T
    lit[i] = 1
    uv_proj[i] = wp.vec2(uvo[0], uvo[1])
    z_proj[i] = xp[2]
    falloff = ref_dist / dist
    shade[i] = a * cos_p * falloff * falloff


@wp.kernel
def sample_patterns(
    blurred: wp.array(dtype=wp.float32, ndim=4),  # [L, N, Hp, Wp]: the patterns blurred at L sigmas
    level_sigma: wp.array(dtype=float),  # [L] ascending
    uv_proj: wp.array(dtype=wp.vec2),
    z_proj: wp.array(dtype=float),
    lit: wp.array(dtype=wp.int32),
    sigma0: float,
    sigma_slope: float,
    focus_dist: float,
    out: wp.array2d(dtype=float),  # [N, P]: pattern value seen at each pixel (0 where unlit)
):
    n, i = wp.tid()
    if lit[i] == 0:
        out[n, i] = 0.0
        return
    sigma = sigma0 + sigma_slope * wp.abs(z_proj[i] - focus_dist) / focus_dist
    L = level_sigma.shape[0]
    lo = int(0)
    for j in range(L - 1):
        if level_sigma[j + 1] <= sigma:
            lo = j + 1
    hi = wp.min(lo + 1, L - 1)
    t = float(0.0)
    if hi != lo:
        t = wp.clamp((sigma - level_sigma[lo]) / (level_sigma[hi] - level_sigma[lo]), 0.0, 1.0)
    uv = uv_proj[i]
    a = bilinear_channel(blurred[lo], n, uv[0], uv[1])
    b = a
    if hi != lo:
        b = bilinear_channel(blurred[hi], n, uv[0], uv[1])
    out[n, i] = (1.0 - t) * a + t * b


@wp.kernel
def first_hit_depth(mesh: wp.uint64, dirs: wp.array(dtype=wp.vec3), depth: wp.array(dtype=float)):
    """Camera z (mm) of the first hit of each unit ray from the camera centre; NaN where none (used to
    turn a reconstructed mesh into a depth map)."""
    i = wp.tid()
    d = dirs[i]
    q = wp.mesh_query_ray(mesh, wp.vec3(0.0, 0.0, 0.0), d, 1.0e7)
    if q.result:
        depth[i] = q.t * d[2]
    else:
        depth[i] = wp.nan


@wp.kernel
def mesh_hits(mesh: wp.uint64, dirs: wp.array(dtype=wp.vec3), eps: float, depth: wp.array2d(dtype=float)):
    """Camera z (mm) of the first K hits of each unit camera ray on a mesh (depth [P, K]; NaN past the
    last hit): candidate surfaces when a reconstructed surface bleeds over a depth edge."""
    i = wp.tid()
    d = dirs[i]
    K = depth.shape[1]
    t0 = float(0.0)
    done = bool(False)
    for k in range(K):
        depth[i, k] = wp.nan
        if not done:
            q = wp.mesh_query_ray(mesh, d * t0, d, 1.0e7)
            if q.result:
                t0 = t0 + q.t
                depth[i, k] = t0 * d[2]
                t0 = t0 + eps
            else:
                done = True
