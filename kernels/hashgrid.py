"""Multiresolution hash-grid encoding (Instant-NGP) with its spatial gradient, in Warp (CPU and CUDA).

Grid: L levels over the unit cube, level l with res_l cells per side (vertices 0..res_l per axis) and a
table slice of `size_l` entries at `offset_l` in one table T [E, F] (F features per entry). The per-level
description is meta [L, 4] int32 = (res, offset, size, hashed). A point x in [0, 1]^3 at level l:
    u = x res_l, clamped to [0, res_l] (a clamped coordinate has zero derivative: the features are
        constant outside the cube; NaN counts as clamped to 0, so no input indexes out of bounds)
    cell i = min(floor(u), res_l - 1) per axis, t = u - i in [0, 1]
    vertex v = i + c for the 8 corners c in {0, 1}^3, weight w_c = prod_d (c_d ? t_d : 1 - t_d)
    entry(v) = offset + v_x + (res+1) (v_y + (res+1) v_z)                     dense level (hashed = 0)
             = offset + (v_x ^ v_y 2654435761 ^ v_z 805459861) mod size        hashed level (uint32
               arithmetic, size a power of two: Instant-NGP's xor-of-primes spatial hash)
    feat_l = sum_c w_c T[entry(v_c)]  (trilinear interpolation)
The spatial derivative of a weight is closed form: d w_c / d x_d = res m_d s_d prod_{e != d} w_e with
s_d = +1 for an upper corner (c_d = 1) and -1 for a lower one, m_d = 0 where the coordinate is clamped;
its second derivatives are d2 w_c / dx_d dx_e = res^2 m_d m_e s_d s_e w_k (k the third axis) for d != e,
and zero on the diagonal (trilinear is linear along each axis).

Kernels (launched with dim (L, P): one thread per level and point, consecutive threads on consecutive
points of one level; levels l >= active[0] are switched off: zero features, zero gradients):
    encode             feat [P, L F]:  feat[p, l F + f] = sum_c w_c T[e_c, f]
    encode_backward    dT [E, F] +=    w_c g[p, l F + f]                                    (atomic)
                       launched with dim (L, ceil(P / run)): a thread takes `run` consecutive points and
                       sums their terms in registers while they stay in one cell (one atomic per corner
                       and cell instead of one per point)
    gradient           out [P, 3] +=   sum_c (sum_f g[p, l F + f] T[e_c, f]) grad w_c      (atomic over l)
                       = sum_j g_j d feat_j / dx: the feature Jacobian contracted with a cotangent g,
                       never materialising [P, L F, 3]
    gradient_backward  given H = dL/d out [P, 3]:
                       dg[p, l F + f] = sum_c T[e_c, f] (H . grad w_c)
                       dT[e_c, f]    += g[p, l F + f] (H . grad w_c)                          (atomic)
                       dx[p]         += sum_c (sum_f g T[e_c]) Hess(w_c) H   (only when need_x; atomic)
`gradient` is also the encoding's backward into x. The table gradients are atomic adds (many points hit
one entry; hash collisions add up by construction).

Kernels are specialised on F (a compile-time constant: a table row is one vector load).
"""

import functools

import warp as wp

PRIME_Y = wp.constant(wp.uint32(2654435761))
PRIME_Z = wp.constant(wp.uint32(805459861))


@wp.func
def axis_coord(x: float, res: int):
    """(cell, t, m) of one coordinate at a level of `res` cells: the lower vertex index, the fraction in
    [0, 1] and 1.0 where the coordinate is inside [0, 1] (0.0 where it is clamped or NaN)."""
    r = float(res)
    u = x * r
    m = float(1.0)
    if u >= 0.0:
        if u > r:
            u = r
            m = 0.0
    else:  # below zero, or NaN
        u = 0.0
        m = 0.0
    cell = wp.min(int(wp.floor(u)), res - 1)
    return cell, u - float(cell), m


@wp.func
def vertex_entry(vx: int, vy: int, vz: int, res: int, offset: int, size: int, hashed: int) -> int:
    """Row of the table holding vertex (vx, vy, vz) of a level."""
    if hashed != 0:
        h = wp.uint32(vx) ^ (wp.uint32(vy) * PRIME_Y) ^ (wp.uint32(vz) * PRIME_Z)
        return offset + int(h & wp.uint32(size - 1))
    n = res + 1
    return offset + vx + n * (vy + n * vz)


@wp.func
def corner_factors(bit: int, t: float):
    """(weight factor, its derivative sign) of one axis for the lower (bit 0) or upper (bit 1) corner."""
    if bit == 1:
        return t, 1.0
    return 1.0 - t, -1.0


# Adding a table row's gradient: one vector reduction (PTX red.global.add.v2/v4.f32, sm_90 and newer) instead of
# F scalar atomics. The backward is bound by its atomics into L2: on one H100 at the trained state of `accurate`
# (bunny, 524288 points, 8 levels) the encoding's backward took 1.33 ms with scalar atomics, 0.78 with CUDA's
# float2 atomicAdd (which returns the old value) and 0.69 with the reduction that returns nothing. Elsewhere (the
# CPU, older GPUs, or PTX built for an older target) the scalar atomics.
_ADD_ROW_SNIPPET = """
#if defined(__CUDA_ARCH__) && (__CUDA_ARCH__ >= 900)
    float* p = reinterpret_cast<float*>(&d[e]);
    asm volatile("red.relaxed.gpu.global.add.v{n}.f32 [%0], {{{regs}}};" :: "l"(p), {values} : "memory");
#else
    for (int i = 0; i < {n}; ++i) wp::atomic_add(&d[e].c[i], v.c[i]);
#endif
"""


def _add_row_snippet(n: int) -> str:
    regs = ", ".join(f"%{i + 1}" for i in range(n))
    values = ", ".join(f'"f"(v.c[{i}])' for i in range(n))
    return _ADD_ROW_SNIPPET.replace("{n}", str(n)).replace("{{{regs}}}", "{" + regs + "}").replace("{values}", values)


@wp.func_native(_add_row_snippet(2))
def add_row2(d: wp.array(dtype=wp.vec2), e: int, v: wp.vec2):
    """d[e] += v (atomic; one vector reduction on sm_90+)."""
    ...


@wp.func_native(_add_row_snippet(4))
def add_row4(d: wp.array(dtype=wp.vec4), e: int, v: wp.vec4):
    """d[e] += v (atomic; one vector reduction on sm_90+)."""
    ...


@functools.lru_cache(maxsize=None)
def hashgrid_kernels(F: int):
    """(encode, encode_backward, gradient, gradient_backward) for F features per entry (see module doc)."""
    vecF = wp.types.vector(length=F, dtype=wp.float32)
    matF = wp.types.matrix(shape=(8, F), dtype=wp.float32)  # one row per cell corner

    @wp.func
    def add_row(d: wp.array(dtype=vecF), e: int, v: vecF):
        """d[e] += v, atomic: a table row's gradient in one reduction where F is 2 or 4 (see _ADD_ROW_SNIPPET)."""
        if wp.static(F == 2):
            add_row2(d, e, v)
        elif wp.static(F == 4):
            add_row4(d, e, v)
        else:
            wp.atomic_add(d, e, v)

    @wp.func
    def load_cotangent(g: wp.array2d(dtype=float), p: int, l: int) -> vecF:
        out = vecF()
        for f in range(F):
            out[f] = g[p, l * F + f]
        return out

    @wp.kernel(enable_backward=False, module="unique")
    def encode(
        x: wp.array(dtype=wp.vec3),
        table: wp.array(dtype=vecF),
        meta: wp.array2d(dtype=int),
        active: wp.array(dtype=int),
        feat: wp.array2d(dtype=float),
    ):
        l, p = wp.tid()
        acc = vecF()
        if l < active[0]:
            res = meta[l, 0]
            offset = meta[l, 1]
            size = meta[l, 2]
            hashed = meta[l, 3]
            xp = x[p]
            ix, tx, mx = axis_coord(xp[0], res)
            iy, ty, my = axis_coord(xp[1], res)
            iz, tz, mz = axis_coord(xp[2], res)
            for c in range(8):
                bx = c & 1
                by = (c >> 1) & 1
                bz = (c >> 2) & 1
                wx, sx = corner_factors(bx, tx)
                wy, sy = corner_factors(by, ty)
                wz, sz = corner_factors(bz, tz)
                e = vertex_entry(ix + bx, iy + by, iz + bz, res, offset, size, hashed)
                acc += (wx * wy * wz) * table[e]
        for f in range(F):
            feat[p, l * F + f] = acc[f]

    @wp.func
    def scatter_cell(d_table: wp.array(dtype=vecF), acc: matF, ix: int, iy: int, iz: int, res: int, offset: int,
                     size: int, hashed: int):
        """Add the 8 corner rows of `acc` to the table rows of cell (ix, iy, iz)'s corners (atomic)."""
        for c in range(8):
            e = vertex_entry(ix + (c & 1), iy + ((c >> 1) & 1), iz + ((c >> 2) & 1), res, offset, size, hashed)
            add_row(d_table, e, acc[c])

    @wp.kernel(enable_backward=False, module="unique")
    def encode_backward(
        x: wp.array(dtype=wp.vec3),
        meta: wp.array2d(dtype=int),
        active: wp.array(dtype=int),
        g_feat: wp.array2d(dtype=float),
        run: int,
        d_table: wp.array(dtype=vecF),
    ):
        # one thread per level and run of `run` consecutive points: while the points stay in one cell (samples
        # along a ray at the coarse levels) their weighted cotangents add up in registers and reach the table
        # in one atomic per corner when the cell changes. Same-address atomics serialise, and at the coarse
        # levels whole warps hit the same 8 rows (1.11 -> 0.92 ms for this kernel in an accurate step, H100)
        l, q = wp.tid()
        if l >= active[0]:
            return
        res = meta[l, 0]
        offset = meta[l, 1]
        size = meta[l, 2]
        hashed = meta[l, 3]
        n = x.shape[0]
        acc = matF()
        cx = int(-1)
        cy = int(-1)
        cz = int(-1)
        for k in range(run):
            p = q * run + k
            if p < n:
                gv = load_cotangent(g_feat, p, l)
                xp = x[p]
                ix, tx, mx = axis_coord(xp[0], res)
                iy, ty, my = axis_coord(xp[1], res)
                iz, tz, mz = axis_coord(xp[2], res)
                if ix != cx or iy != cy or iz != cz:
                    if cx >= 0:
                        scatter_cell(d_table, acc, cx, cy, cz, res, offset, size, hashed)
                    acc = matF()
                    cx = ix
                    cy = iy
                    cz = iz
                for c in range(8):
                    wx, sx = corner_factors(c & 1, tx)
                    wy, sy = corner_factors((c >> 1) & 1, ty)
                    wz, sz = corner_factors((c >> 2) & 1, tz)
                    acc[c] = acc[c] + (wx * wy * wz) * gv
        if cx >= 0:
            scatter_cell(d_table, acc, cx, cy, cz, res, offset, size, hashed)

    @wp.kernel(enable_backward=False, module="unique")
    def gradient(
        x: wp.array(dtype=wp.vec3),
        table: wp.array(dtype=vecF),
        meta: wp.array2d(dtype=int),
        active: wp.array(dtype=int),
        g: wp.array2d(dtype=float),
        out: wp.array(dtype=wp.vec3),
    ):
        l, p = wp.tid()
        if l >= active[0]:
            return
        gv = load_cotangent(g, p, l)
        res = meta[l, 0]
        offset = meta[l, 1]
        size = meta[l, 2]
        hashed = meta[l, 3]
        xp = x[p]
        ix, tx, mx = axis_coord(xp[0], res)
        iy, ty, my = axis_coord(xp[1], res)
        iz, tz, mz = axis_coord(xp[2], res)
        acc = wp.vec3(0.0, 0.0, 0.0)
        for c in range(8):
            bx = c & 1
            by = (c >> 1) & 1
            bz = (c >> 2) & 1
            wx, sx = corner_factors(bx, tx)
            wy, sy = corner_factors(by, ty)
            wz, sz = corner_factors(bz, tz)
            e = vertex_entry(ix + bx, iy + by, iz + bz, res, offset, size, hashed)
            a = wp.dot(gv, table[e])
            acc += a * wp.vec3(sx * wy * wz, wx * sy * wz, wx * wy * sz)
        r = float(res)
        wp.atomic_add(out, p, wp.vec3(acc[0] * mx * r, acc[1] * my * r, acc[2] * mz * r))

    @wp.kernel(enable_backward=False, module="unique")
    def gradient_backward(
        x: wp.array(dtype=wp.vec3),
        table: wp.array(dtype=vecF),
        meta: wp.array2d(dtype=int),
        active: wp.array(dtype=int),
        g: wp.array2d(dtype=float),
        h_out: wp.array(dtype=wp.vec3),
        need_x: int,
        d_table: wp.array(dtype=vecF),
        d_g: wp.array2d(dtype=float),
        d_x: wp.array(dtype=wp.vec3),
    ):
        l, p = wp.tid()
        dg = vecF()
        if l < active[0]:
            gv = load_cotangent(g, p, l)
            res = meta[l, 0]
            offset = meta[l, 1]
            size = meta[l, 2]
            hashed = meta[l, 3]
            r = float(res)
            xp = x[p]
            ix, tx, mx = axis_coord(xp[0], res)
            iy, ty, my = axis_coord(xp[1], res)
            iz, tz, mz = axis_coord(xp[2], res)
            hp = h_out[p]
            # H with the chain factors res m_d folded in: H . grad w_c = hm . (s_x w_y w_z, w_x s_y w_z, w_x w_y s_z)
            hm = wp.vec3(hp[0] * mx * r, hp[1] * my * r, hp[2] * mz * r)
            dx = wp.vec3(0.0, 0.0, 0.0)
            for c in range(8):
                bx = c & 1
                by = (c >> 1) & 1
                bz = (c >> 2) & 1
                wx, sx = corner_factors(bx, tx)
                wy, sy = corner_factors(by, ty)
                wz, sz = corner_factors(bz, tz)
                e = vertex_entry(ix + bx, iy + by, iz + bz, res, offset, size, hashed)
                tv = table[e]
                hdot = wp.dot(hm, wp.vec3(sx * wy * wz, wx * sy * wz, wx * wy * sz))
                dg += hdot * tv
                add_row(d_table, e, hdot * gv)
                if need_x != 0:
                    a = wp.dot(gv, tv)
                    # Hess(w_c) H with the res m factors of both axes: (hm_y s_x s_y w_z + hm_z s_x s_z w_y, ...)
                    hxy = sx * sy * wz
                    hxz = sx * sz * wy
                    hyz = sy * sz * wx
                    dx += a * wp.vec3((hxy * hm[1] + hxz * hm[2]) * mx * r, (hxy * hm[0] + hyz * hm[2]) * my * r,
                                      (hxz * hm[0] + hyz * hm[1]) * mz * r)
            if need_x != 0:
                wp.atomic_add(d_x, p, dx)
        for f in range(F):
            d_g[p, l * F + f] = dg[f]

    return encode, encode_backward, gradient, gradient_backward
