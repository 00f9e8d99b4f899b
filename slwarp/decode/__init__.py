"""Classical structured-light baselines: decoders, triangulation, depth reconstruction.

    decode(scan, method, frames=None, **params) -> Decoding (col, row [H, W] projector px, NaN invalid; valid)
    reconstruct_depth(scan, method, ...) -> (depth [H, W] mm NaN invalid, points [H, W, 3], Decoding)
    METHODS: gc, gc-interp, ps, cgc, hpmp, npmp, gt

Modules: frames (which frame is what, from its name), gray (Gray code tables, binarisation, stripe
interpolation), phase (wrapped phase, unwrapping), cgc (Gray code + phase: CGC and the GT pipeline),
triangulate (plane and ray-ray midpoint triangulation), methods (the registry). Point clouds are written by
slwarp.evaluation.outputs.
"""
from .frames import MissingFrames
from .methods import METHODS, Decoding, decode, finalize_positions, reconstruct_depth
from .triangulate import choose_plane_axis, triangulate, triangulate_midpoint, triangulate_plane

__all__ = [
    "METHODS",
    "Decoding",
    "MissingFrames",
    "decode",
    "reconstruct_depth",
    "finalize_positions",
    "triangulate",
    "triangulate_plane",
    "triangulate_midpoint",
    "choose_plane_axis",
]
