"""Phase shifting: wrapped phase and modulation, and the temporal unwrapping schemes of the baselines.

Image model of step k of an N-step set with period P (projector px) and shift d_k:

    I_k = A + B cos(phi - d_k),   phi = 2 pi u / P

where the pattern of step k is a + b cos(2 pi u / P - d_k). slwarp's patterns have d_k = 2 pi k / N
(`slwarp.scans.patterns`); other conventions decode too, since the decoders measure each d_k from its pattern
(`slwarp.decode.frames.measure_phase_shifts`). A, B cos phi and B sin phi are the least-squares solution of the
N equations (for equally spaced shifts: S = sum_k I_k sin d_k, C = sum_k I_k cos d_k, phi = atan2(S, C),
B = (2 / N) sqrt(S^2 + C^2), A = mean_k I_k). The wrapped position is u_w = P phi / (2 pi) in [0, P); the
absolute one is u = u_w + m P for an integer period order m that the unwrapping finds.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = [
    "wrapped_phase",
    "wrapped_position",
    "unwrap_with_reference",
    "coarse_position",
    "NumberTheoreticTable",
    "unwrap_number_theoretic",
]


def wrapped_phase(images: np.ndarray, shifts: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """images [N, H, W] -> (phi [H, W] in [0, 2 pi), offset A [H, W], modulation B [H, W]).

    shifts [N] rad: the shift d_k of each step (I_k = A + B cos(phi - d_k)); default 2 pi k / N. The three
    unknowns A, B cos phi, B sin phi are the least-squares solution of the N equations; for equally spaced
    shifts that is the classical S = sum I_k sin d_k, C = sum I_k cos d_k, phi = atan2(S, C)."""
    imgs = np.asarray(images, np.float64)
    n = imgs.shape[0]
    if n < 3:
        raise ValueError(f"phase shifting needs at least 3 steps, got {n}")
    d = 2 * np.pi * np.arange(n) / n if shifts is None else np.asarray(shifts, np.float64)
    if d.shape != (n,):
        raise ValueError(f"{n} phase-shift images need {n} shifts, got {d.shape}")
    M = np.stack([np.ones(n), np.cos(d), np.sin(d)], 1)  # [N, 3]
    A, C, S = np.tensordot(np.linalg.pinv(M), imgs, axes=1)
    phi = np.mod(np.arctan2(S, C), 2 * np.pi)
    return phi, A, np.hypot(S, C)


def wrapped_position(phi: np.ndarray, period: float) -> np.ndarray:
    """Wrapped phase -> position within the period, u_w in [0, P) projector px."""
    u = phi * (period / (2 * np.pi))
    return np.where(u >= period, u - period, u)  # phi rounding can give exactly 2 pi


def unwrap_with_reference(u_wrapped: np.ndarray, u_ref: np.ndarray, period: float) -> np.ndarray:
    """u = u_w + P round((u_ref - u_w) / P): the period order that puts u nearest to a coarse estimate.

    Correct whenever the coarse estimate is within P / 2 of the true position. For CGC the reference is
    the centre of a Gray code stripe half a period wide, so the true position is within P / 4 of it,
    which leaves a margin of P / 4 for decoding errors: in particular, the period edges (where phi wraps
    and a noisy wrapped phase can land on either side) need no special care, and a pixel decoded into the
    wrong one of two neighbouring stripes is still unwrapped correctly while it lies within P / 4 of
    their boundary. NaN in either input gives NaN.
    """
    return u_wrapped + period * np.round((u_ref - u_wrapped) / period)


def coarse_position(phi: np.ndarray, period: float) -> np.ndarray:
    """Absolute position from a phase whose period covers the whole axis: in [-0.5, P - 0.5).

    The projector's pixel area spans [-0.5, size - 0.5]; a period of exactly `size` cannot tell its two
    edges apart, so the half pixel left of 0 is mapped there and not to the far edge.
    """
    return np.mod(phi * (period / (2 * np.pi)) + 0.5, period) - 0.5


class NumberTheoreticTable:
    """Lookup for number-theoretic (co-prime period) unwrapping of two phase sets.

    With integer periods P1, P2 of greatest common divisor g and the true position u = u1 + m1 P1 =
    u2 + m2 P2, the difference of the wrapped positions u2 - u1 = m1 P1 - m2 P2 is a multiple of g, and
    over one least common multiple of positions the pair (m1, m2) is unique for each multiple. The table
    maps round((u2 - u1) / g) to the pair, for every pair that occurs over the axis [-0.5, size - 0.5]
    (with `slack` px of tolerance at the ends of each period, where noise can flip the order of one set).
    A difference whose index has no pair in the table is inconsistent: that pixel is invalid. Noise of
    more than g / 2 in the difference picks a wrong pair: N-PMP's known weakness (g = 2 px for 48/70).
    """

    def __init__(self, p1: float, p2: float, size: int, slack: float = 1.0):
        if abs(p1 - round(p1)) > 1e-9 or abs(p2 - round(p2)) > 1e-9:
            raise ValueError(f"number-theoretic unwrapping needs integer periods, got {p1:g} and {p2:g}")
        self.p1, self.p2 = int(round(p1)), int(round(p2))
        self.g = math.gcd(self.p1, self.p2)
        lcm = self.p1 * self.p2 // self.g
        if lcm < size:
            raise ValueError(f"periods {self.p1} and {self.p2} are unambiguous over only {lcm} px < {size} px")
        lo, hi = -0.5 - slack, size - 0.5 + slack
        pairs = []
        for m1 in range(math.floor(lo / self.p1), math.floor(hi / self.p1) + 1):
            a0, a1 = m1 * self.p1 - slack, (m1 + 1) * self.p1 + slack
            for m2 in range(math.floor(lo / self.p2), math.floor(hi / self.p2) + 1):
                b0, b1 = m2 * self.p2 - slack, (m2 + 1) * self.p2 + slack
                if max(a0, b0, lo) < min(a1, b1, hi):
                    pairs.append((m1, m2))
        pairs = np.array(pairs, np.int64)
        key = (pairs[:, 0] * self.p1 - pairs[:, 1] * self.p2) // self.g
        if len(np.unique(key)) != len(key):  # cannot happen within one lcm; guards the slack
            raise ValueError(f"periods {self.p1} and {self.p2}: ambiguous orders over {size} px")
        self.offset = int(-key.min())
        self.m1 = np.full(int(key.max() - key.min()) + 1, np.iinfo(np.int64).min, np.int64)
        self.m2 = self.m1.copy()
        self.m1[key + self.offset] = pairs[:, 0]
        self.m2[key + self.offset] = pairs[:, 1]

    def lookup(self, u1: np.ndarray, u2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Wrapped positions [...] -> (m1, m2 as float with NaN where no pair, found [...] bool)."""
        finite = np.isfinite(u1) & np.isfinite(u2)
        k = np.round(np.where(finite, u2 - u1, 0.0) / self.g).astype(np.int64) + self.offset
        inside = finite & (k >= 0) & (k < self.m1.size)
        kk = np.clip(k, 0, self.m1.size - 1)
        found = inside & (self.m1[kk] != np.iinfo(np.int64).min)
        m1 = np.where(found, self.m1[kk], 0).astype(np.float64)
        m2 = np.where(found, self.m2[kk], 0).astype(np.float64)
        m1[~found] = np.nan
        m2[~found] = np.nan
        return m1, m2, found


def unwrap_number_theoretic(u1: np.ndarray, u2: np.ndarray, p1: float, p2: float, size: int,
                            table: NumberTheoreticTable | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Absolute position from two wrapped positions with co-prime periods (N-PMP).

    The two unwrapped estimates are averaged with weights 1 / P^2: the position noise of a phase set
    grows in proportion to its period, so this is the minimum-variance combination.
    Returns (u [...] with NaN where the pair is inconsistent, the disagreement |U1 - U2| [...] px).
    """
    table = table or NumberTheoreticTable(p1, p2, size)
    m1, m2, _ = table.lookup(u1, u2)
    a = u1 + m1 * table.p1
    b = u2 + m2 * table.p2
    w1, w2 = 1.0 / table.p1**2, 1.0 / table.p2**2
    return (w1 * a + w2 * b) / (w1 + w2), np.abs(a - b)
