"""Ray generation and sample placement (no gradients flow through these).

camera_rays:        pixels -> unit camera-frame rays and [near, far] distances from a camera-z depth range
stratified:         S samples per ray at near + (far - near) (k + 0.5 + jitter_r) / S (one jitter per ray)
upsample_*:         one NeuS hierarchical up-sampling step (NeuS's sample_pdf with det=True) in two launches,
                    parallel over samples instead of one serial thread per ray:
  upsample_intervals  one thread per (ray, interval): NeuS's "estimated" alpha from the SDF at the current
                      samples with a fixed inv_s (needs only the interval's neighbours)
  upsample_place      one thread per (ray, new sample): the weights' total, then the normalised CDF until it
                      passes the thread's quantile (j + 0.5) / n, and the inverse-CDF distance there (the serial
                      part: a few flops per interval)
merge_sorted:       merge two per-ray sorted sample lists (z and SDF) into one, stable (a before b on ties):
                    one thread per input element, which computes its output rank by binary search
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


# The up-sampling step used to be one thread per ray walking its S samples twice: with ~1000 rays per training step
# that is a few warps on a GPU of 132 SMs, latency-bound on the per-interval sigmoids. Split in two launches, the
# sigmoids run one thread per interval, and what stays serial is a chain of a few flops per interval, which each
# new sample's thread runs for itself (its ray's threads read the same alphas, so the copies cost no memory
# traffic) while watching for its own quantile: no CDF buffer and no third launch. The arithmetic is the per-ray
# walk's (the same alpha, the same products and sums in the same order): the results were bit-identical to it on
# the CPU and on an H100.


@wp.kernel
def upsample_intervals(
    z: wp.array2d(dtype=float),
    sdf: wp.array2d(dtype=float),
    rays_o: wp.array(dtype=wp.vec3),
    rays_d: wp.array(dtype=wp.vec3),
    inv_s: float,
    bmin: wp.vec3,
    bmax: wp.vec3,
    alpha: wp.array2d(dtype=float),
):
    """alpha [R, S-1]: NeuS's estimated alpha of interval [z_i, z_{i+1}] (launch dim (R, S-1)); the cosine
    counts where either end is inside the box [bmin, bmax]."""
    r, i = wp.tid()
    o = rays_o[r]
    d = rays_d[r]
    inside = inside_box(o + d * z[r, i], bmin, bmax) or inside_box(o + d * z[r, i + 1], bmin, bmax)
    alpha[r, i] = upsample_alpha(z, sdf, r, i, inside, inv_s)


@wp.func
def upsample_total(alpha: wp.array2d(dtype=float), r: int) -> float:
    """sum_i w_i, w_i = alpha_i T_i + PDF_EPS, T_i = prod_{k<i} (1 - alpha_k + TRANS_EPS), summed in order."""
    n = alpha.shape[1]
    n4 = n - n % 4
    total = float(0.0)
    trans = float(1.0)
    # 4 intervals a step: their loads issue together instead of each stalling the chain (Warp does not unroll
    # loops of a run-time length); the same operations in the same order as one at a time
    for i in range(0, n4, 4):
        a0 = alpha[r, i]
        a1 = alpha[r, i + 1]
        a2 = alpha[r, i + 2]
        a3 = alpha[r, i + 3]
        total += a0 * trans + PDF_EPS
        trans = trans * (1.0 - a0 + TRANS_EPS)
        total += a1 * trans + PDF_EPS
        trans = trans * (1.0 - a1 + TRANS_EPS)
        total += a2 * trans + PDF_EPS
        trans = trans * (1.0 - a2 + TRANS_EPS)
        total += a3 * trans + PDF_EPS
        trans = trans * (1.0 - a3 + TRANS_EPS)
    for i in range(n4, n):
        a = alpha[r, i]
        total += a * trans + PDF_EPS
        trans = trans * (1.0 - a + TRANS_EPS)
    return total


@wp.func
def upsample_cdf_step(a: float, trans: float, c: float, total: float, u: float, i: int, k: int, c0: float, c1: float):
    """One interval of the CDF walk: (T_{i+1}, cdf_{i+1}, k, c0, c1). k, the first CDF index above u, and the CDF at
    its interval's ends c0, c1 are set at the first interval whose CDF passes u (k = -1 until then)."""
    c_next = c + (a * trans + PDF_EPS) / total
    hit = k < 0 and u < c_next
    return (trans * (1.0 - a + TRANS_EPS), c_next, wp.where(hit, i + 1, k), wp.where(hit, c, c0),
            wp.where(hit, c_next, c1))


@wp.func
def upsample_inverse_cdf(z: wp.array2d(dtype=float), alpha: wp.array2d(dtype=float), r: int, total: float,
                         u: float) -> float:
    """The distance at quantile u of ray r: walk the CDF (running sum of w_i / total) to the first interval whose
    end passes u, then interpolate in it. A CDF that rises by less than CDF_EPS over the interval puts u at its
    start; u beyond the last CDF value (rounding) sits on the last sample."""
    n = alpha.shape[1]
    n4 = n - n % 4
    k = int(-1)
    c0 = float(0.0)
    c1 = float(0.0)
    c = float(0.0)
    trans = float(1.0)
    for i in range(0, n4, 4):
        a0 = alpha[r, i]
        a1 = alpha[r, i + 1]
        a2 = alpha[r, i + 2]
        a3 = alpha[r, i + 3]
        trans, c, k, c0, c1 = upsample_cdf_step(a0, trans, c, total, u, i, k, c0, c1)
        trans, c, k, c0, c1 = upsample_cdf_step(a1, trans, c, total, u, i + 1, k, c0, c1)
        trans, c, k, c0, c1 = upsample_cdf_step(a2, trans, c, total, u, i + 2, k, c0, c1)
        trans, c, k, c0, c1 = upsample_cdf_step(a3, trans, c, total, u, i + 3, k, c0, c1)
        if k >= 0:  # found: the rest of the CDF does not matter to this quantile
            break
    if k < 0:
        for i in range(n4, n):
            trans, c, k, c0, c1 = upsample_cdf_step(alpha[r, i], trans, c, total, u, i, k, c0, c1)
    if k < 0:
        return z[r, z.shape[1] - 1]
    denom = c1 - c0
    if denom < CDF_EPS:
        denom = 1.0
    return z[r, k - 1] + (u - c0) / denom * (z[r, k] - z[r, k - 1])


@wp.kernel
def upsample_place(
    z: wp.array2d(dtype=float),
    alpha: wp.array2d(dtype=float),
    z_new: wp.array2d(dtype=float),
):
    """z_new [R, n]: the distance at quantile u_j = (j + 0.5) / n by inverse CDF of the weights of alpha [R, S-1]
    (launch dim (R, n); z [R, S]). The CDF is normalised by the total, so the total comes first."""
    r, j = wp.tid()
    u = (float(j) + 0.5) / float(z_new.shape[1])
    z_new[r, j] = upsample_inverse_cdf(z, alpha, r, upsample_total(alpha, r), u)


@wp.func
def count_below(z: wp.array2d(dtype=float), r: int, v: float, or_equal: bool) -> int:
    """Number of entries of the sorted row z[r] below v (at or below v when or_equal), by binary search."""
    lo = int(0)
    hi = z.shape[1]
    while lo < hi:
        mid = (lo + hi) // 2
        x = z[r, mid]
        if x < v or (or_equal and x == v):
            lo = mid + 1
        else:
            hi = mid
    return lo


@wp.kernel
def merge_sorted(
    z_a: wp.array2d(dtype=float),
    f_a: wp.array2d(dtype=float),
    z_b: wp.array2d(dtype=float),
    f_b: wp.array2d(dtype=float),
    z_out: wp.array2d(dtype=float),
    f_out: wp.array2d(dtype=float),
):
    """Stable merge of sorted rows z_a [R, na] and z_b [R, nb] (values f_a, f_b alongside) into z_out, f_out
    [R, na + nb]; launch dim (R, na + nb), one thread per input element. a_k lands at k + #{b < a_k} and b_j at
    j + #{a <= b_j}: on ties a goes first, as in the sequential merge (and a stable sort of [a, b])."""
    r, k = wp.tid()
    na = z_a.shape[1]
    if k < na:
        v = z_a[r, k]
        dst = k + count_below(z_b, r, v, False)
        z_out[r, dst] = v
        f_out[r, dst] = f_a[r, k]
    else:
        j = k - na
        v = z_b[r, j]
        dst = j + count_below(z_a, r, v, True)
        z_out[r, dst] = v
        f_out[r, dst] = f_b[r, j]
