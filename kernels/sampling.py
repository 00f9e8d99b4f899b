"""Ray generation and sample placement (no gradients flow through these).

camera_rays:    pixels -> unit camera-frame rays and [near, far] distances from a camera-z depth range
stratified:     S samples per ray at near + (far - near) (k + 0.5 + jitter_r) / S (one jitter per ray)
upsample:       one NeuS hierarchical up-sampling step: NeuS's "estimated" alpha from the SDF at the
                current samples with a fixed inv_s, then inverse-CDF placement of n new samples at
                deterministic quantiles (k + 0.5) / n (NeuS's sample_pdf with det=True)
merge_sorted:   merge two per-ray sorted sample lists (z and SDF) into one, stable
"""

import warp as wp

from slwarp.kernels.geometry import ALPHA_EPS, TRANS_EPS, CameraParams, inside_box, pixel_ray, sigmoid

# NeuS's up-sampling regularisers (all 1e-5 in NeuS's renderer): the SDF slope over an interval divides by its
# length + SLOPE_EPS and is clamped to [MIN_SLOPE, 0]; every interval's weight gets PDF_EPS so the CDF rises
# everywhere; an interval whose CDF rises by less than CDF_EPS places its quantiles at its start
SLOPE_EPS = 1.0e-5
MIN_SLOPE = -1.0e3
PDF_EPS = 1.0e-5
CDF_EPS = 1.0e-5


@wp.kernel
def camera_rays(
    pixels: wp.array(dtype=wp.vec2),
    cam: CameraParams,
    z_near: float,
    z_far: float,
    rays_d: wp.array(dtype=wp.vec3),
    near: wp.array(dtype=float),
    far: wp.array(dtype=float),
):
    i = wp.tid()
    d = pixel_ray(cam, pixels[i])
    rays_d[i] = d
    near[i] = z_near / d[2]  # depth is camera z: distance along the unit ray = z / d_z
    far[i] = z_far / d[2]


@wp.kernel
def stratified(
    near: wp.array(dtype=float),
    far: wp.array(dtype=float),
    jitter: wp.array(dtype=float),
    z: wp.array2d(dtype=float),
):
    r, k = wp.tid()
    S = z.shape[1]
    z[r, k] = near[r] + (far[r] - near[r]) * (float(k) + 0.5 + jitter[r]) / float(S)


@wp.func
def upsample_alpha(z: wp.array2d(dtype=float), sdf: wp.array2d(dtype=float), r: int, i: int, inside_i: bool,
                   inv_s: float) -> float:
    """NeuS's estimated alpha of interval [z_i, z_{i+1}] (the cosine from SDF differences)."""
    dist = z[r, i + 1] - z[r, i]
    c = (sdf[r, i + 1] - sdf[r, i]) / (dist + SLOPE_EPS)
    if i > 0:
        c = wp.min(c, (sdf[r, i] - sdf[r, i - 1]) / (z[r, i] - z[r, i - 1] + SLOPE_EPS))
    else:
        c = wp.min(c, 0.0)
    c = wp.clamp(c, MIN_SLOPE, 0.0)
    if not inside_i:
        c = 0.0
    mid = (sdf[r, i] + sdf[r, i + 1]) * 0.5
    prev_cdf = sigmoid((mid - c * dist * 0.5) * inv_s)
    next_cdf = sigmoid((mid + c * dist * 0.5) * inv_s)
    return (prev_cdf - next_cdf + ALPHA_EPS) / (prev_cdf + ALPHA_EPS)


@wp.kernel
def upsample(
    z: wp.array2d(dtype=float),
    sdf: wp.array2d(dtype=float),
    rays_o: wp.array(dtype=wp.vec3),
    rays_d: wp.array(dtype=wp.vec3),
    inv_s: float,
    bmin: wp.vec3,
    bmax: wp.vec3,
    z_new: wp.array2d(dtype=float),
):
    r = wp.tid()
    S = z.shape[1]
    n_new = z_new.shape[1]
    o = rays_o[r]
    d = rays_d[r]
    # pass 1: total of the (regularised) weights
    total = float(0.0)
    trans = float(1.0)
    in_prev = inside_box(o + d * z[r, 0], bmin, bmax)
    for i in range(S - 1):
        in_next = inside_box(o + d * z[r, i + 1], bmin, bmax)
        alpha = upsample_alpha(z, sdf, r, i, in_prev or in_next, inv_s)
        total += alpha * trans + PDF_EPS
        trans = trans * (1.0 - alpha + TRANS_EPS)
        in_prev = in_next
    # pass 2: walk the CDF and place quantiles (j + 0.5) / n_new in order
    j = int(0)
    cdf_lo = float(0.0)
    trans = float(1.0)
    in_prev = inside_box(o + d * z[r, 0], bmin, bmax)
    for i in range(S - 1):
        in_next = inside_box(o + d * z[r, i + 1], bmin, bmax)
        alpha = upsample_alpha(z, sdf, r, i, in_prev or in_next, inv_s)
        cdf_hi = cdf_lo + (alpha * trans + PDF_EPS) / total
        trans = trans * (1.0 - alpha + TRANS_EPS)
        in_prev = in_next
        denom = cdf_hi - cdf_lo
        if denom < CDF_EPS:
            denom = 1.0
        while j < n_new and (float(j) + 0.5) / float(n_new) < cdf_hi:
            u = (float(j) + 0.5) / float(n_new)
            z_new[r, j] = z[r, i] + (u - cdf_lo) / denom * (z[r, i + 1] - z[r, i])
            j += 1
        cdf_lo = cdf_hi
    while j < n_new:  # quantiles beyond the (rounded) last CDF value sit on the last sample
        z_new[r, j] = z[r, S - 1]
        j += 1


@wp.kernel
def merge_sorted(
    z_a: wp.array2d(dtype=float),
    f_a: wp.array2d(dtype=float),
    z_b: wp.array2d(dtype=float),
    f_b: wp.array2d(dtype=float),
    z_out: wp.array2d(dtype=float),
    f_out: wp.array2d(dtype=float),
):
    r = wp.tid()
    na = z_a.shape[1]
    nb = z_b.shape[1]
    i = int(0)
    j = int(0)
    for k in range(na + nb):
        take_a = j >= nb or (i < na and z_a[r, i] <= z_b[r, j])
        if take_a:
            z_out[r, k] = z_a[r, i]
            f_out[r, k] = f_a[r, i]
            i += 1
        else:
            z_out[r, k] = z_b[r, j]
            f_out[r, k] = f_b[r, j]
            j += 1
