"""Exhaustive depth search: for each (strided) camera pixel, the camera depth among n hypotheses whose
predicted intensities a + b P_n(pi(x)) best match the observed ones over a (2r+1)^2 window of pixels
that share the hypothesis depth (L1 cost, per pixel per pattern). It is a classical decoder for any
pattern set, used to start the neural SDF in the right basin of its non-convex photometric loss.
"""

import functools

import warp as wp

from slwarp.kernels.geometry import ProjectorParams, pattern_sampler, project_to_projector

NO_COST = 1.0e30  # the cost of "no hypothesis yet": above any mean L1 cost of intensities in [0, 1]


@functools.lru_cache(maxsize=None)
def search_kernel(N: int):
    """The search kernel for N patterns (see module docstring)."""
    _, patterns_at, _ = pattern_sampler(N)

    @wp.kernel(module="unique")
    def search(
        rays: wp.array2d(dtype=wp.vec3),  # [H, W] unit camera rays
        observed: wp.array3d(dtype=float),  # [H, W, N]
        a: wp.array2d(dtype=float),
        b: wp.array2d(dtype=float),
        valid: wp.array2d(dtype=wp.int32),  # the pixels a window counts
        centre: wp.array2d(dtype=wp.int32),  # the pixels to search (a window centred elsewhere is skipped: NaN)
        pat: wp.array3d(dtype=float),  # [Hp, Wp, N]
        prm: ProjectorParams,
        z_near: float,
        z_far: float,
        n_hyp: int,
        radius: int,
        stride: int,
        exclude: int,  # hypotheses within this many cells of the best do not count as a rival
        depth: wp.array2d(dtype=float),  # [H / stride, W / stride]: best camera z (mm), NaN if no valid pixel
        best_cost: wp.array2d(dtype=float),  # its mean L1 cost
        second_cost: wp.array2d(dtype=float),  # the best cost farther than `exclude` cells from the best
    ):
        i, j = wp.tid()
        H = rays.shape[0]
        W = rays.shape[1]
        v = i * stride
        u = j * stride
        if centre[v, u] == 0:  # v < H and u < W: the grid is ceil(H / stride) x ceil(W / stride)
            depth[i, j] = wp.nan
            best_cost[i, j] = wp.nan
            second_cost[i, j] = wp.nan
            return
        best = float(NO_COST)
        best_h = int(-1)
        costs_far = float(NO_COST)
        for h in range(n_hyp):
            z = z_near + (z_far - z_near) * (float(h) + 0.5) / float(n_hyp)
            cost = float(0.0)
            count = float(0.0)
            for dv in range(-radius, radius + 1):
                for du in range(-radius, radius + 1):
                    y = v + dv
                    x = u + du
                    if y >= 0 and y < H and x >= 0 and x < W:
                        if valid[y, x] != 0:
                            d = rays[y, x]
                            p = patterns_at(pat, project_to_projector(prm, d * (z / d[2])))
                            ay = a[y, x]
                            by = b[y, x]
                            for n in range(N):
                                cost += wp.abs(ay + by * p[n] - observed[y, x, n])
                            count += float(N)
            if count > 0.0:
                cost = cost / count
                if cost < best:
                    if best_h >= 0 and wp.abs(h - best_h) > exclude:
                        costs_far = wp.min(costs_far, best)
                    best = cost
                    best_h = h
                elif wp.abs(h - best_h) > exclude:
                    costs_far = wp.min(costs_far, cost)
        if best_h < 0:
            depth[i, j] = wp.nan
            best_cost[i, j] = wp.nan
            second_cost[i, j] = wp.nan
            return
        depth[i, j] = z_near + (z_far - z_near) * (float(best_h) + 0.5) / float(n_hyp)
        best_cost[i, j] = best
        second_cost[i, j] = costs_far

    return search
