"""The Warp helpers every kernel module shares (the only kernel module the others import):

- the camera and projector as kernel structs, OpenCV distortion and its inverse, pixel rays, the projection
  into the projector and its vector-Jacobian product;
- bilinear taps: one channel of a channel-first stack (`bilinear_channel`) and all N patterns of a
  pattern stack [H, W, N] with their gradient (`pattern_sampler(N)`);
- sigmoid, the inside-box test, and the constants the renderer and the sampler share.

Conventions follow `slwarp.scans.scanner`: mm, OpenCV axes, pixel centres at integer coordinates, X_p = R X_c + T.
The torch twin (slwarp.neural.ops.twin) imports the constants, so both compute with the same values.
"""

import functools

import warp as wp

ALPHA_EPS = 1.0e-5  # NeuS's alpha regulariser: (cdf_prev - cdf_next + eps) / (cdf_prev + eps)
TRANS_EPS = 1.0e-7  # NeuS's transmittance regulariser: T_k = prod_{j<k} (1 - alpha_j + eps)
MIN_PROJECTOR_Z = 1.0e-6  # mm: points with a smaller projector-frame z are behind (or on) the lens
FAR_AWAY_PX = -1.0e6  # projector pixel given to points that do not project: every tap falls outside


@wp.struct
class ProjectorParams:
    """A projector for kernels: pose, intrinsics, distortion and the image size (float px)."""

    R: wp.mat33
    T: wp.vec3
    f: wp.vec2  # fx, fy (px)
    c: wp.vec2  # cx, cy (px)
    k: wp.vec3  # k1, k2, k3
    p: wp.vec2  # p1, p2
    size: wp.vec2  # width, height (px)
    max_r2: float  # squared normalised radius beyond which OpenCV's polynomial is not trusted (it can fold)


def projector_params(projector) -> ProjectorParams:
    """A projector for kernels, from its 24 packed floats (`slwarp.scans.scanner.PackedProjector`) or a
    `slwarp.Projector` (which carries them as `.packed`)."""
    p = getattr(projector, "packed", projector)
    prm = ProjectorParams()
    prm.R = wp.mat33(*p.R)
    prm.T = wp.vec3(*p.T)
    prm.f = wp.vec2(p.fx, p.fy)
    prm.c = wp.vec2(p.cx, p.cy)
    prm.k = wp.vec3(p.k1, p.k2, p.k3)
    prm.p = wp.vec2(p.p1, p.p2)
    prm.size = wp.vec2(p.width, p.height)
    prm.max_r2 = p.max_r2
    return prm


@wp.func
def distort(x: float, y: float, k: wp.vec3, p: wp.vec2) -> wp.vec2:
    """OpenCV radial-tangential distortion of normalised coordinates."""
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k[0] + r2 * (k[1] + r2 * k[2]))
    xd = x * radial + 2.0 * p[0] * x * y + p[1] * (r2 + 2.0 * x * x)
    yd = y * radial + p[0] * (r2 + 2.0 * y * y) + 2.0 * p[1] * x * y
    return wp.vec2(xd, yd)


@wp.func
def distort_jacobian(x: float, y: float, k: wp.vec3, p: wp.vec2) -> wp.vec4:
    """d(xd, yd)/d(x, y) as (dxd/dx, dxd/dy, dyd/dx, dyd/dy)."""
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k[0] + r2 * (k[1] + r2 * k[2]))
    dradial = k[0] + r2 * (2.0 * k[1] + 3.0 * k[2] * r2)
    jxx = radial + 2.0 * x * x * dradial + 2.0 * p[0] * y + 6.0 * p[1] * x
    jxy = 2.0 * x * y * dradial + 2.0 * p[0] * x + 2.0 * p[1] * y
    jyy = radial + 2.0 * y * y * dradial + 6.0 * p[0] * y + 2.0 * p[1] * x
    return wp.vec4(jxx, jxy, jxy, jyy)


@wp.func
def project_to_projector(prm: ProjectorParams, xc: wp.vec3) -> wp.vec3:
    """Camera-frame point (mm) -> (u, v, ok) in projector pixels; ok = 1 in front of the lens and inside
    the trusted distortion radius, else 0 (and u = v = FAR_AWAY_PX, outside any image)."""
    xp = prm.R * xc + prm.T
    if xp[2] <= MIN_PROJECTOR_Z:
        return wp.vec3(FAR_AWAY_PX, FAR_AWAY_PX, 0.0)
    xn = xp[0] / xp[2]
    yn = xp[1] / xp[2]
    if xn * xn + yn * yn > prm.max_r2:
        return wp.vec3(FAR_AWAY_PX, FAR_AWAY_PX, 0.0)
    d = distort(xn, yn, prm.k, prm.p)
    return wp.vec3(prm.f[0] * d[0] + prm.c[0], prm.f[1] * d[1] + prm.c[1], 1.0)


@wp.func
def project_to_projector_grad(prm: ProjectorParams, xc: wp.vec3, du: float, dv: float) -> wp.vec3:
    """Vector-Jacobian product: d(du * u + dv * v)/d xc for the projection above (zero where not ok)."""
    xp = prm.R * xc + prm.T
    if xp[2] <= MIN_PROJECTOR_Z:
        return wp.vec3(0.0, 0.0, 0.0)
    inv_z = 1.0 / xp[2]
    xn = xp[0] * inv_z
    yn = xp[1] * inv_z
    if xn * xn + yn * yn > prm.max_r2:
        return wp.vec3(0.0, 0.0, 0.0)
    J = distort_jacobian(xn, yn, prm.k, prm.p)
    gxd = du * prm.f[0]
    gyd = dv * prm.f[1]
    gxn = gxd * J[0] + gyd * J[2]
    gyn = gxd * J[1] + gyd * J[3]
    gxp = wp.vec3(gxn * inv_z, gyn * inv_z, -(gxn * xn + gyn * yn) * inv_z)
    return wp.transpose(prm.R) * gxp


@wp.struct
class CameraParams:
    """A camera for kernels: intrinsics and distortion."""

    f: wp.vec2
    c: wp.vec2
    k: wp.vec3  # k1, k2, k3
    p: wp.vec2  # p1, p2


def camera_params(camera) -> CameraParams:
    """Pack a `slwarp.Camera` for kernels."""
    prm = CameraParams()
    prm.f = wp.vec2(camera.fx, camera.fy)
    prm.c = wp.vec2(camera.cx, camera.cy)
    d = camera.dist
    prm.k = wp.vec3(float(d[0]), float(d[1]), float(d[4]))
    prm.p = wp.vec2(float(d[2]), float(d[3]))
    return prm


@wp.func
def undistort(xd: float, yd: float, k: wp.vec3, p: wp.vec2) -> wp.vec2:
    """Inverse of `distort` by Newton's method (12 steps, as slwarp.scans.scanner.undistort_normalized)."""
    x = xd
    y = yd
    for _ in range(12):
        dd = distort(x, y, k, p)
        J = distort_jacobian(x, y, k, p)
        fx = dd[0] - xd
        fy = dd[1] - yd
        det = J[0] * J[3] - J[1] * J[2]
        x = x - (J[3] * fx - J[1] * fy) / det
        y = y - (J[0] * fy - J[2] * fx) / det
    return wp.vec2(x, y)


@wp.func
def pixel_ray(cam: CameraParams, uv: wp.vec2) -> wp.vec3:
    """Unit camera-frame ray through the (distorted) pixel uv."""
    n = undistort((uv[0] - cam.c[0]) / cam.f[0], (uv[1] - cam.c[1]) / cam.f[1], cam.k, cam.p)
    return wp.normalize(wp.vec3(n[0], n[1], 1.0))


# ----------------------------------------------------------------------------------------------
# small shared functions


@wp.func
def sigmoid(x: float) -> float:
    return 1.0 / (1.0 + wp.exp(-x))


@wp.func
def inside_box(x: wp.vec3, bmin: wp.vec3, bmax: wp.vec3) -> bool:
    """x inside the axis-aligned box [bmin, bmax] (bounds included)."""
    return x[0] >= bmin[0] and x[0] <= bmax[0] and x[1] >= bmin[1] and x[1] <= bmax[1] and x[2] >= bmin[2] and x[2] <= bmax[2]


# ----------------------------------------------------------------------------------------------
# bilinear taps: pixel centres at integer coordinates, taps outside the image count as zero


@wp.func
def bilinear_cell(u: float, v: float):
    """(iu, iv, fu, fv): the top-left tap (iu, iv) of the 2x2 taps around (u, v) and the fractions."""
    u0 = wp.floor(u)
    v0 = wp.floor(v)
    return int(u0), int(v0), u - u0, v - v0


@wp.func
def bilinear_weight(fu: float, fv: float, dx: int, dy: int) -> float:
    """Weight of tap (iu + dx, iv + dy), dx, dy in {0, 1}."""
    return wp.where(dx == 0, 1.0 - fu, fu) * wp.where(dy == 0, 1.0 - fv, fv)


@wp.func
def inside_image(x: int, y: int, width: int, height: int) -> bool:
    return x >= 0 and x < width and y >= 0 and y < height


@wp.func
def bilinear_channel(img: wp.array3d(dtype=float), c: int, u: float, v: float) -> float:
    """Bilinear value of channel c of img [C, H, W] at continuous (u, v)."""
    h = img.shape[1]
    w = img.shape[2]
    iu, iv, fu, fv = bilinear_cell(u, v)
    acc = float(0.0)
    for dy in range(2):
        for dx in range(2):
            x = iu + dx
            y = iv + dy
            if inside_image(x, y, w, h):
                acc += bilinear_weight(fu, fv, dx, dy) * img[c, y, x]
    return acc


@functools.lru_cache(maxsize=None)
def pattern_sampler(N: int):
    """(vecN, sample_all, sample_all_grad) for N patterns packed [H, W, N] (the N values of a projector pixel
    side by side): the Warp vector type of N values, the bilinear values of all N patterns at a projector
    position (u, v, ok) (zero when not ok), and the gradient d(sum_n cot_n P_n(u, v)) / d(u, v)."""
    vecN = wp.types.vector(length=N, dtype=wp.float32)

    @wp.func
    def sample_all(pat: wp.array3d(dtype=float), uvo: wp.vec3) -> vecN:
        out = vecN()
        if uvo[2] == 0.0:
            return out
        H = pat.shape[0]
        W = pat.shape[1]
        iu, iv, fu, fv = bilinear_cell(uvo[0], uvo[1])
        for dy in range(2):
            for dx in range(2):
                x = iu + dx
                y = iv + dy
                if inside_image(x, y, W, H):
                    wgt = bilinear_weight(fu, fv, dx, dy)
                    for n in range(N):
                        out[n] += wgt * pat[y, x, n]
        return out

    @wp.func
    def sample_all_grad(pat: wp.array3d(dtype=float), uvo: wp.vec3, cot: vecN) -> wp.vec2:
        if uvo[2] == 0.0:
            return wp.vec2(0.0, 0.0)
        H = pat.shape[0]
        W = pat.shape[1]
        iu, iv, fu, fv = bilinear_cell(uvo[0], uvo[1])
        gu = float(0.0)
        gv = float(0.0)
        for dy in range(2):
            for dx in range(2):
                x = iu + dx
                y = iv + dy
                if inside_image(x, y, W, H):
                    val = float(0.0)
                    for n in range(N):
                        val += cot[n] * pat[y, x, n]
                    # d weight / du and d weight / dv of this tap
                    wu = wp.where(dy == 0, 1.0 - fv, fv) * wp.where(dx == 0, -1.0, 1.0)
                    wv = wp.where(dx == 0, 1.0 - fu, fu) * wp.where(dy == 0, -1.0, 1.0)
                    gu += wu * val
                    gv += wv * val
        return wp.vec2(gu, gv)

    return vecN, sample_all, sample_all_grad
