"""The fused structured-light renderer: one thread per ray, all S samples and all N patterns, after a pass with one
thread per sample that samples the N patterns at it (`samples`: the per-ray passes are latency-bound, and the
projection and 4 x N bilinear taps of each sample in their loops made most of their time).

Forward, per ray r with samples x_k = o + z_k d (k = 0..S-1):
    dz_k      = z_{k+1} - z_k (last: `last_delta`, or the previous interval when last_delta < 0)
    cos_k     = d . g_k;  c_k = -(relu(0.5 - 0.5 cos_k) (1 - anneal) + relu(-cos_k) anneal)     (NeuS)
    alpha_k   = clamp((sig((f_k - c_k dz_k / 2) s) - sig((f_k + c_k dz_k / 2) s) + 1e-5)
                      / (sig((f_k - c_k dz_k / 2) s) + 1e-5), 0, 1)                              (NeuS)
    T_k       = prod_{j<k} (1 - alpha_j + 1e-7);  w_k = alpha_k T_k
    rendered_n = a sum_k w_k + b sum_k w_k P_n(pi(x_k))   (P_n bilinear, zero outside the projector image)
    surface   = sum_k w_k x_k / (sum_k w_k + 1e-6): the expected surface point under the weights (equal to
                sum_k w_k x_k for an opaque ray; normalised because in the camera frame a missing 1% of opacity
                would otherwise pull the point 1% of its depth toward the camera, about 9 mm at 900 mm)
    depth = surface_z;  surface_rendered_n = a + b P_n(pi(surface))
    eikonal_k = (|g_k| - 1)^2 inside the working volume (axis-aligned box), else 0; eikonal_sum = sum_k
    The forward also keeps T_k for the backward (one extra write per sample instead of a second pass).
Backward is written by hand: the transmittance product is a loop-carried dependency that Warp's
automatic adjoint does not replay. With G_k the total cotangent reaching w_k,
    dL/dalpha_k = T_k (G_k - U_k),  U_{k} = G_{k+1} alpha_{k+1} + (1 - alpha_{k+1} + 1e-7) U_{k+1},  U_{S-1} = 0,
a suffix recurrence: no division by (1 - alpha). The backward is one reverse pass per ray over the
saved T_k and the saved surface point (whose cotangent enters every G_k). Per-sample cotangents of
weights and Eikonal that no loss uses are skipped (flags), so they are never read.

Both loops are software-pipelined (the next sample's inputs load while this one is processed): with one
thread per ray the kernels are latency-bound, and sample-major inputs make each load coalesced.

Kernels are specialised on the pattern count N (a compile-time constant: per-pattern accumulators stay
in registers). Patterns are packed [H, W, N] so the N values of one projector pixel are contiguous; their
bilinear taps come from slwarp.kernels.geometry.pattern_sampler, shared with the depth search.
"""

import functools

import warp as wp

from slwarp.kernels.geometry import (ALPHA_EPS, TRANS_EPS, ProjectorParams, inside_box, pattern_sampler,
                                     project_to_projector, project_to_projector_grad, sigmoid)

NORM_EPS = 1.0e-12  # |g| = sqrt(g.g + eps): finite Eikonal gradient at g = 0
WSUM_EPS = 1.0e-6  # surface point = sum w x / (sum w + eps): defined for rays with no weight


@wp.func
def iter_cos(true_cos: float, anneal: float) -> float:
    return -(wp.max(-true_cos * 0.5 + 0.5, 0.0) * (1.0 - anneal) + wp.max(-true_cos, 0.0) * anneal)


@wp.func
def neus_alpha(sdf: float, true_cos: float, dz: float, inv_s: float, anneal: float) -> float:
    c = iter_cos(true_cos, anneal)
    prev_cdf = sigmoid((sdf - c * dz * 0.5) * inv_s)
    next_cdf = sigmoid((sdf + c * dz * 0.5) * inv_s)
    return wp.clamp((prev_cdf - next_cdf + ALPHA_EPS) / (prev_cdf + ALPHA_EPS), 0.0, 1.0)


@wp.func
def neus_alpha_vjp(sdf: float, true_cos: float, dz: float, inv_s: float, anneal: float, g_alpha: float) -> wp.vec3:
    """(dL/dsdf, dL/dtrue_cos, dL/dinv_s) given dL/dalpha; zero where the clamp is active (as torch)."""
    c = iter_cos(true_cos, anneal)
    prev = sdf - c * dz * 0.5
    nxt = sdf + c * dz * 0.5
    prev_cdf = sigmoid(prev * inv_s)
    next_cdf = sigmoid(nxt * inv_s)
    raw = (prev_cdf - next_cdf + ALPHA_EPS) / (prev_cdf + ALPHA_EPS)
    if raw < 0.0 or raw > 1.0:
        return wp.vec3(0.0, 0.0, 0.0)
    inv = 1.0 / (prev_cdf + ALPHA_EPS)
    g_prev_arg = g_alpha * next_cdf * inv * inv * prev_cdf * (1.0 - prev_cdf)
    g_next_arg = -g_alpha * inv * next_cdf * (1.0 - next_cdf)
    g_prev = g_prev_arg * inv_s
    g_next = g_next_arg * inv_s
    g_c = (g_next - g_prev) * dz * 0.5
    dc_dcos = wp.where(true_cos < 1.0, 0.5 * (1.0 - anneal), 0.0) + wp.where(true_cos < 0.0, anneal, 0.0)
    return wp.vec3(g_prev + g_next, g_c * dc_dcos, g_prev_arg * prev + g_next_arg * nxt)


# The kernels' arguments in the groups that travel together (R rays, S samples, N patterns; mm). Field names are
# those of the torch side (slwarp.neural.ops.render_ops), which fills each struct by name in one place.


@wp.struct
class RaySamples:
    """The rays and the field at their samples: what both passes read per ray and per sample."""

    sdf: wp.array2d(dtype=float)  # [R, S] f_k (mm)
    sdf_grad: wp.array2d(dtype=wp.vec3)  # [R, S] g_k
    z_vals: wp.array2d(dtype=float)  # [R, S] z_k (mm along the ray)
    rays_o: wp.array(dtype=wp.vec3)  # [R] o (mm)
    rays_d: wp.array(dtype=wp.vec3)  # [R] d (unit)
    a: wp.array(dtype=float)  # [R] offset of I = a + b P
    b: wp.array(dtype=float)  # [R] modulation


@wp.struct
class RenderParams:
    """The patterns, the projector and the scalars of a render."""

    patterns: wp.array3d(dtype=float)  # [H, W, N]
    projector: ProjectorParams
    inv_s: wp.array(dtype=float)  # [1] NeuS's s (1/mm)
    cos_anneal_ratio: float
    last_delta: float  # the last sample's interval (mm); < 0: the previous interval
    bmin: wp.vec3  # the working volume's box (mm), where the Eikonal term counts
    bmax: wp.vec3


@wp.struct
class ForwardOutputs:
    """What the forward writes (the T_k in `trans` are kept for the backward)."""

    weights: wp.array2d(dtype=float)  # [R, S]
    rendered: wp.array2d(dtype=float)  # [R, N]
    surface: wp.array(dtype=wp.vec3)  # [R]
    surface_rendered: wp.array2d(dtype=float)  # [R, N]
    depth: wp.array(dtype=float)  # [R]
    weight_sum: wp.array(dtype=float)  # [R]
    eikonal: wp.array2d(dtype=float)  # [R, S]
    eikonal_sum: wp.array(dtype=float)  # [R]
    eikonal_count: wp.array(dtype=float)  # [R]
    trans: wp.array2d(dtype=float)  # [R, S] T_k


@wp.struct
class ForwardSaved:
    """The forward's outputs the backward reads."""

    trans: wp.array2d(dtype=float)  # [R, S]
    surface: wp.array(dtype=wp.vec3)  # [R]
    weight_sum: wp.array(dtype=float)  # [R]


@wp.struct
class Cotangents:
    """The cotangents of the forward's outputs; the per-sample ones of weights and Eikonal only where a flag is
    set (a loss that does not use them leaves them unread)."""

    g_weights: wp.array2d(dtype=float)  # [R, S], read when has_g_weights
    has_g_weights: int
    g_rendered: wp.array2d(dtype=float)  # [R, N]
    g_surface: wp.array(dtype=wp.vec3)  # [R]
    g_surface_rendered: wp.array2d(dtype=float)  # [R, N]
    g_depth: wp.array(dtype=float)  # [R]
    g_weight_sum: wp.array(dtype=float)  # [R]
    g_eikonal: wp.array2d(dtype=float)  # [R, S], read when has_g_eikonal
    has_g_eikonal: int
    g_eikonal_sum: wp.array(dtype=float)  # [R]


@wp.struct
class InputGrads:
    """What the backward writes: the gradients of the differentiable inputs."""

    d_sdf: wp.array2d(dtype=float)  # [R, S]
    d_grad: wp.array2d(dtype=wp.vec3)  # [R, S]
    d_inv_s: wp.array(dtype=float)  # [R]: one term per ray (summed by the caller)


@functools.lru_cache(maxsize=None)
def render_kernels(N: int):
    """(samples, forward, backward) kernels for N patterns: `samples` writes P_n(pi(x_k)) of every sample, one
    thread per sample, which both per-ray passes then read (the samples' distances carry no gradient, so their
    pattern values are constants of the backward)."""
    vecN, sample_all, sample_all_grad = pattern_sampler(N)

    @wp.kernel(module="unique")
    def samples(
        rays: RaySamples,
        params: RenderParams,
        values: wp.array2d(dtype=vecN),  # [R, S]: the N patterns' bilinear values at sample k of ray r
    ):
        r, k = wp.tid()
        x = rays.rays_o[r] + rays.rays_d[r] * rays.z_vals[r, k]
        values[r, k] = sample_all(params.patterns, project_to_projector(params.projector, x))

    @wp.kernel(module="unique")
    def forward(rays: RaySamples, params: RenderParams, pvals: wp.array2d(dtype=vecN), out: ForwardOutputs):
        r = wp.tid()
        sdf = rays.sdf
        grad = rays.sdf_grad
        z = rays.z_vals
        S = z.shape[1]
        inv_s = params.inv_s[0]
        anneal = params.cos_anneal_ratio
        last_delta = params.last_delta
        o = rays.rays_o[r]
        d = rays.rays_d[r]
        trans = float(1.0)
        wsum = float(0.0)
        sp = wp.vec3(0.0, 0.0, 0.0)
        acc = vecN()
        esum = float(0.0)
        count = float(0.0)
        # software pipelining: the next sample's inputs are loaded while this one is processed
        f_next = sdf[r, 0]
        g_next = grad[r, 0]
        z_next = z[r, 0]
        p_next = pvals[r, 0]
        z_prev = z_next
        for k in range(S):
            f = f_next
            g = g_next
            zk = z_next
            pk = p_next
            if k + 1 < S:
                f_next = sdf[r, k + 1]
                g_next = grad[r, k + 1]
                z_next = z[r, k + 1]
                p_next = pvals[r, k + 1]
            dz = z_next - zk
            if k + 1 == S:
                dz = wp.where(last_delta >= 0.0, last_delta, wp.where(S > 1, zk - z_prev, 0.0))
            z_prev = zk
            alpha = neus_alpha(f, wp.dot(d, g), dz, inv_s, anneal)
            w = alpha * trans
            out.trans[r, k] = trans
            trans = trans * (1.0 - alpha + TRANS_EPS)
            out.weights[r, k] = w
            wsum += w
            x = o + d * zk
            sp += w * x
            acc += w * pk
            e = float(0.0)
            if inside_box(x, params.bmin, params.bmax):
                nrm = wp.sqrt(wp.dot(g, g) + NORM_EPS)
                e = (nrm - 1.0) * (nrm - 1.0)
                count += 1.0
            out.eikonal[r, k] = e
            esum += e
        sp = sp / (wsum + WSUM_EPS)
        ps = sample_all(params.patterns, project_to_projector(params.projector, sp))
        ar = rays.a[r]
        br = rays.b[r]
        for n in range(N):
            out.rendered[r, n] = ar * wsum + br * acc[n]
            out.surface_rendered[r, n] = ar + br * ps[n]
        out.surface[r] = sp
        out.depth[r] = sp[2]
        out.weight_sum[r] = wsum
        out.eikonal_sum[r] = esum
        out.eikonal_count[r] = count

    @wp.kernel(module="unique")
    def backward(
        rays: RaySamples,
        params: RenderParams,
        pvals: wp.array2d(dtype=vecN),
        saved: ForwardSaved,
        cot: Cotangents,
        grads: InputGrads,
    ):
        r = wp.tid()
        sdf = rays.sdf
        grad = rays.sdf_grad
        z = rays.z_vals
        trans_saved = saved.trans
        S = z.shape[1]
        inv_s = params.inv_s[0]
        anneal = params.cos_anneal_ratio
        last_delta = params.last_delta
        o = rays.rays_o[r]
        d = rays.rays_d[r]
        br = rays.b[r]
        gr = vecN()
        gsr = vecN()
        sum_gr = float(0.0)
        for n in range(N):
            gr[n] = cot.g_rendered[r, n]
            gsr[n] = cot.g_surface_rendered[r, n] * br
            sum_gr += gr[n]
        common = cot.g_weight_sum[r] + rays.a[r] * sum_gr
        g_eik_ray = cot.g_eikonal_sum[r]

        # cotangent of the surface point (saved by the forward): direct, through depth, and through the
        # surface intensities
        sp = saved.surface[r]
        g_s = cot.g_surface[r] + wp.vec3(0.0, 0.0, cot.g_depth[r])
        duv = sample_all_grad(params.patterns, project_to_projector(params.projector, sp), gsr)
        g_s += project_to_projector_grad(params.projector, sp, duv[0], duv[1])
        # s = sum w x / (W + eps): ds/dw_k = (x_k - s) / (W + eps)
        g_s = g_s / (saved.weight_sum[r] + WSUM_EPS)

        # one pass in reverse: G_k (the total cotangent of w_k), the U recurrence with the saved
        # transmittance T_k, then the NeuS alpha and Eikonal adjoints. Inputs of the next (lower) sample
        # are loaded while this one is processed.
        u_suffix = float(0.0)
        g_inv_s = float(0.0)
        k0 = S - 1
        f_next = sdf[r, k0]
        g_next = grad[r, k0]
        z_next = z[r, k0]
        t_next = trans_saved[r, k0]
        p_next = pvals[r, k0]
        z_after = z_next  # z of sample k + 1
        for kk in range(S):
            k = S - 1 - kk
            f = f_next
            g = g_next
            zk = z_next
            t_k = t_next
            pk = p_next
            if k > 0:
                f_next = sdf[r, k - 1]
                g_next = grad[r, k - 1]
                z_next = z[r, k - 1]
                t_next = trans_saved[r, k - 1]
                p_next = pvals[r, k - 1]
            dz = z_after - zk
            if k + 1 == S:
                dz = wp.where(last_delta >= 0.0, last_delta, wp.where(S > 1, zk - z_next, 0.0))
            z_after = zk
            cos_k = wp.dot(d, g)
            alpha = neus_alpha(f, cos_k, dz, inv_s, anneal)
            x = o + d * zk
            gw = common + br * wp.dot(gr, pk) + wp.dot(g_s, x - sp)
            if cot.has_g_weights != 0:
                gw += cot.g_weights[r, k]
            g_alpha = t_k * (gw - u_suffix)
            u_suffix = gw * alpha + (1.0 - alpha + TRANS_EPS) * u_suffix
            v = neus_alpha_vjp(f, cos_k, dz, inv_s, anneal, g_alpha)
            dg = d * v[1]
            if inside_box(x, params.bmin, params.bmax):
                g_e = g_eik_ray
                if cot.has_g_eikonal != 0:
                    g_e += cot.g_eikonal[r, k]
                if g_e != 0.0:
                    nrm = wp.sqrt(wp.dot(g, g) + NORM_EPS)
                    dg += g * (g_e * 2.0 * (nrm - 1.0) / nrm)
            grads.d_sdf[r, k] = v[0]
            grads.d_grad[r, k] = dg
            g_inv_s += v[2]
        grads.d_inv_s[r] = g_inv_s

    return samples, forward, backward
