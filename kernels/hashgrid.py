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

Every kernel starts with the same per-level decode (`level`, then `locate`: the point's cell, t and m) and
walks the 8 corners with `corner` (table row, weight factors, derivative signs); the points x [P, 3], the
table, meta and active travel together in one struct (`Grid`). Kernels (launched with dim (L, P): one
thread per level and point, consecutive threads on consecutive points of one level; levels l >= active[0]
are switched off: zero features, zero gradients):
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
from typing import NamedTuple

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


@wp.struct
class Level:
    """One level of the grid (its row of meta) and, once located, a point's cell there (see the module doc)."""

    res: int  # cells per side
    offset: int  # first table row of the level
    size: int  # table rows of the level (a power of two where hashed)
    hashed: int  # 1: hashed, 0: dense
    cell: wp.vec3i  # lower vertex of the point's cell
    t: wp.vec3  # the point's fraction in the cell per axis, in [0, 1]
    m: wp.vec3  # 1 where the coordinate is inside [0, 1], 0 where it is clamped (or NaN)


@wp.func
def level(meta: wp.array2d(dtype=int), l: int) -> Level:
    """Level l's description from meta [L, 4] (no point located yet)."""
    lv = Level()
    lv.res = meta[l, 0]
    lv.offset = meta[l, 1]
    lv.size = meta[l, 2]
    lv.hashed = meta[l, 3]
    return lv


@wp.func
def locate(lv: Level, x: wp.vec3) -> Level:
    """Level lv with unit-cube point x located in it: its cell, fractions and clamp masks."""
    ix, tx, mx = axis_coord(x[0], lv.res)
    iy, ty, my = axis_coord(x[1], lv.res)
    iz, tz, mz = axis_coord(x[2], lv.res)
    return Level(lv.res, lv.offset, lv.size, lv.hashed, wp.vec3i(ix, iy, iz), wp.vec3(tx, ty, tz), wp.vec3(mx, my, mz))


@wp.func
def vertex_entry(lv: Level, vx: int, vy: int, vz: int) -> int:
    """Row of the table holding vertex (vx, vy, vz) of level lv."""
    if lv.hashed != 0:
        h = wp.uint32(vx) ^ (wp.uint32(vy) * PRIME_Y) ^ (wp.uint32(vz) * PRIME_Z)
        return lv.offset + int(h & wp.uint32(lv.size - 1))
    n = lv.res + 1
    return lv.offset + vx + n * (vy + n * vz)


@wp.func
def corner_factors(bit: int, t: float):
    """(weight factor, its derivative sign) of one axis for the lower (bit 0) or upper (bit 1) corner."""
    if bit == 1:
        return t, 1.0
    return 1.0 - t, -1.0


@wp.func
def corner(lv: Level, c: int):
    """Corner c = b_x + 2 b_y + 4 b_z of the point's cell: (its table row, the weight factors (w_x, w_y, w_z)
    whose product is w_c, their derivative signs (s_x, s_y, s_z))."""
    bx = c & 1
    by = (c >> 1) & 1
    bz = (c >> 2) & 1
    wx, sx = corner_factors(bx, lv.t[0])
    wy, sy = corner_factors(by, lv.t[1])
    wz, sz = corner_factors(bz, lv.t[2])
    e = vertex_entry(lv, lv.cell[0] + bx, lv.cell[1] + by, lv.cell[2] + bz)
    return e, wp.vec3(wx, wy, wz), wp.vec3(sx, sy, sz)


@wp.func
def weight(w: wp.vec3) -> float:
    """w_c = w_x w_y w_z."""
    return w[0] * w[1] * w[2]


@wp.func
def weight_gradient(w: wp.vec3, s: wp.vec3) -> wp.vec3:
    """grad w_c without the chain factors res m_d: (s_x w_y w_z, w_x s_y w_z, w_x w_y s_z)."""
    return wp.vec3(s[0] * w[1] * w[2], w[0] * s[1] * w[2], w[0] * w[1] * s[2])


@wp.func
def weight_hessian_dot(w: wp.vec3, s: wp.vec3, h: wp.vec3) -> wp.vec3:
    """Hess(w_c) h without the chain factors: d2 w_c / dx_d dx_e = s_d s_e w_k (k the third axis), zero diagonal."""
    hxy = s[0] * s[1] * w[2]
    hxz = s[0] * s[2] * w[1]
    hyz = s[1] * s[2] * w[0]
    return wp.vec3(hxy * h[1] + hxz * h[2], hxy * h[0] + hyz * h[2], hxz * h[0] + hyz * h[1])


@wp.func
def chain(v: wp.vec3, lv: Level) -> wp.vec3:
    """v times the chain factor res m_d of each axis (d u_d / d x_d: zero where the coordinate is clamped)."""
    r = float(lv.res)
    return wp.vec3(v[0] * lv.m[0] * r, v[1] * lv.m[1] * r, v[2] * lv.m[2] * r)


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


class HashGridKernels(NamedTuple):
    """The kernels of one feature count F and the struct they take (see the module doc)."""

    Grid: type
    encode: wp.Kernel
    encode_backward: wp.Kernel
    gradient: wp.Kernel
    gradient_backward: wp.Kernel


@functools.lru_cache(maxsize=None)
def hashgrid_kernels(F: int) -> HashGridKernels:
    """The hash-grid kernels for F features per entry (see module doc)."""
    vecF = wp.types.vector(length=F, dtype=wp.float32)
    matF = wp.types.matrix(shape=(8, F), dtype=wp.float32)  # one row per cell corner

    @wp.struct
    class Grid:
        """The points and the grid every kernel reads (P points, L levels, E table rows)."""

        x: wp.array(dtype=wp.vec3)  # [P] unit-cube points
        table: wp.array(dtype=vecF)  # [E] rows of F features
        meta: wp.array2d(dtype=int)  # [L, 4] (res, offset, size, hashed)
        active: wp.array(dtype=int)  # [1] levels switched on

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
    def encode(grid: Grid, feat: wp.array2d(dtype=float)):
        l, p = wp.tid()
        acc = vecF()
        if l < grid.active[0]:
            table = grid.table
            lv = locate(level(grid.meta, l), grid.x[p])
            for c in range(8):
                e, w, s = corner(lv, c)
                acc += weight(w) * table[e]
        for f in range(F):
            feat[p, l * F + f] = acc[f]

    @wp.func
    def scatter_cell(d_table: wp.array(dtype=vecF), acc: matF, lv: Level, cell: wp.vec3i):
        """Add the 8 corner rows of `acc` to the table rows of the corners of level lv's cell `cell` (atomic)."""
        for c in range(8):
            e = vertex_entry(lv, cell[0] + (c & 1), cell[1] + ((c >> 1) & 1), cell[2] + ((c >> 2) & 1))
            add_row(d_table, e, acc[c])

    @wp.kernel(enable_backward=False, module="unique")
    def encode_backward(grid: Grid, g_feat: wp.array2d(dtype=float), run: int, d_table: wp.array(dtype=vecF)):
        # one thread per level and run of `run` consecutive points: while the points stay in one cell (samples
        # along a ray at the coarse levels) their weighted cotangents add up in registers and reach the table
        # in one atomic per corner when the cell changes. Same-address atomics serialise, and at the coarse
        # levels whole warps hit the same 8 rows (1.11 -> 0.92 ms for this kernel in an accurate step, H100)
        l, q = wp.tid()
        if l >= grid.active[0]:
            return
        x = grid.x
        n = x.shape[0]
        lv = level(grid.meta, l)
        acc = matF()
        cur = wp.vec3i(-1, -1, -1)  # the cell whose corners acc holds
        for k in range(run):
            p = q * run + k
            if p < n:
                gv = load_cotangent(g_feat, p, l)
                pt = locate(lv, x[p])
                if pt.cell[0] != cur[0] or pt.cell[1] != cur[1] or pt.cell[2] != cur[2]:
                    if cur[0] >= 0:
                        scatter_cell(d_table, acc, lv, cur)
                    acc = matF()
                    cur = pt.cell
                for c in range(8):
                    e, w, s = corner(pt, c)
                    acc[c] = acc[c] + weight(w) * gv
        if cur[0] >= 0:
            scatter_cell(d_table, acc, lv, cur)

    @wp.kernel(enable_backward=False, module="unique")
    def gradient(grid: Grid, g: wp.array2d(dtype=float), out: wp.array(dtype=wp.vec3)):
        l, p = wp.tid()
        if l >= grid.active[0]:
            return
        gv = load_cotangent(g, p, l)
        table = grid.table
        lv = locate(level(grid.meta, l), grid.x[p])
        acc = wp.vec3(0.0, 0.0, 0.0)
        for c in range(8):
            e, w, s = corner(lv, c)
            acc += wp.dot(gv, table[e]) * weight_gradient(w, s)
        wp.atomic_add(out, p, chain(acc, lv))

    @wp.kernel(enable_backward=False, module="unique")
    def gradient_backward(
        grid: Grid,
        g: wp.array2d(dtype=float),
        h_out: wp.array(dtype=wp.vec3),
        need_x: int,
        d_table: wp.array(dtype=vecF),
        d_g: wp.array2d(dtype=float),
        d_x: wp.array(dtype=wp.vec3),
    ):
        l, p = wp.tid()
        dg = vecF()
        if l < grid.active[0]:
            gv = load_cotangent(g, p, l)
            table = grid.table
            lv = locate(level(grid.meta, l), grid.x[p])
            # H with the chain factors res m_d folded in: H . grad w_c = hm . weight_gradient(w, s)
            hm = chain(h_out[p], lv)
            dx = wp.vec3(0.0, 0.0, 0.0)
            for c in range(8):
                e, w, s = corner(lv, c)
                tv = table[e]
                hdot = wp.dot(hm, weight_gradient(w, s))
                dg += hdot * tv
                add_row(d_table, e, hdot * gv)
                if need_x != 0:
                    # Hess(w_c) H with the res m factors of both axes
                    dx += wp.dot(gv, tv) * chain(weight_hessian_dot(w, s, hm), lv)
            if need_x != 0:
                wp.atomic_add(d_x, p, dx)
        for f in range(F):
            d_g[p, l * F + f] = dg[f]

    return HashGridKernels(Grid, encode, encode_backward, gradient, gradient_backward)
