"""Pattern reprojection: the bilinear values of K projector patterns at given projector pixels, and the backward
into the pattern image (and into the pixels), for pattern design (optimising the patterns by gradient descent
through lookups at fixed projections of camera rays at depth hypotheses).

Patterns are packed [Hp, Wp, K] (the K values of a projector pixel side by side, as `pattern_sampler` reads them);
lookups are uv [M] vec2 in projector pixels (pixel centres at integer coordinates, taps outside the image count
as zero). One thread per lookup, the K patterns in a loop inside it: the four taps' addresses are computed once
and each tap's K values are adjacent in memory.

The backward into the patterns scatters: many lookups (millions per step, from neighbouring rays and depths)
land on the same projector pixels, so the threads add their bilinear weight x cotangent with wp.atomic_add into
a zero-initialised [Hp, Wp, K] gradient. A gather (one thread per pattern pixel) would need the inverse map
from pixels to lookups, which changes with every set of uv; atomics on float32 are cheap on GPUs and their
order only changes rounding.
"""

import functools

import warp as wp

from slwarp.kernels.geometry import bilinear_cell, bilinear_weight, inside_image, pattern_sampler


@wp.func
def lookup_position(uv: wp.vec2, width: int, height: int) -> wp.vec3:
    """(u, v, ok) as `pattern_sampler` takes it: ok = 0 unless some tap of (u, v) can be inside the image,
    i.e. -1 <= u < width and -1 <= v < height. NaN fails every comparison, so it is not ok; the range test also
    keeps int(floor(u)) away from float -> int overflow for uv far outside the image."""
    u = uv[0]
    v = uv[1]
    if u >= -1.0 and u < float(width) and v >= -1.0 and v < float(height):
        return wp.vec3(u, v, 1.0)
    return wp.vec3(0.0, 0.0, 0.0)


@functools.lru_cache(maxsize=None)
def reproject_kernels(K: int):
    """(forward, backward) for K patterns packed [Hp, Wp, K].

    forward(pat [Hp, Wp, K], uv [M] vec2, out [M, K]): out[i, k] = P_k(uv_i), zero where uv_i is not ok.
    backward(pat, uv, cot [M, K], need_patterns, need_uv, grad_patterns [Hp, Wp, K], grad_uv [M] vec2):
    grad_patterns += sum_i w_tap(uv_i) cot[i, k] at each tap (atomics; the caller zeroes it), and
    grad_uv[i] = d(sum_k cot[i, k] P_k(uv_i)) / d uv_i (zero where not ok). need_patterns / need_uv = 0 skip
    the scatter / the uv gradient (grad_uv is then left as it is).
    Any strides for out and cot (a broadcast cotangent, stride 0, is read without being materialised).
    """
    vecK, sample_all, sample_all_grad = pattern_sampler(K)

    @wp.kernel(module="unique")
    def forward(
        pat: wp.array3d(dtype=float),  # [Hp, Wp, K]
        uv: wp.array(dtype=wp.vec2),  # [M] projector pixels
        out: wp.array2d(dtype=float),  # [M, K]
    ):
        i = wp.tid()
        p = sample_all(pat, lookup_position(uv[i], pat.shape[1], pat.shape[0]))
        for k in range(K):
            out[i, k] = p[k]

    @wp.kernel(module="unique")
    def backward(
        pat: wp.array3d(dtype=float),  # [Hp, Wp, K]
        uv: wp.array(dtype=wp.vec2),  # [M]
        cot: wp.array2d(dtype=float),  # [M, K]
        need_patterns: int,
        need_uv: int,
        grad_patterns: wp.array3d(dtype=float),  # [Hp, Wp, K], zero-initialised
        grad_uv: wp.array(dtype=wp.vec2),  # [M]
    ):
        i = wp.tid()
        H = pat.shape[0]
        W = pat.shape[1]
        uvo = lookup_position(uv[i], W, H)
        c = vecK()
        for k in range(K):
            c[k] = cot[i, k]
        if need_uv != 0:
            grad_uv[i] = sample_all_grad(pat, uvo, c)
        if need_patterns == 0 or uvo[2] == 0.0:
            return
        iu, iv, fu, fv = bilinear_cell(uvo[0], uvo[1])
        for dy in range(2):
            for dx in range(2):
                x = iu + dx
                y = iv + dy
                wgt = bilinear_weight(fu, fv, dx, dy)
                # a zero weight adds nothing: skip its atomics (on a pixel row or column half the taps are such)
                if wgt != 0.0 and inside_image(x, y, W, H):
                    for k in range(K):
                        wp.atomic_add(grad_patterns, y, x, k, wgt * c[k])

    return forward, backward
