"""Classical structured-light baselines: decoders, triangulation, depth reconstruction.

    decode(scan, method, frames=None, **params) -> Decoding (col, row [H, W] projector px, NaN invalid; valid)
    reconstruct_depth(scan, method, ...) -> (depth [H, W] mm NaN invalid, points [H, W, 3], Decoding)
    METHODS: gc, gc-interp, ps, cgc, hpmp, npmp, gt

Modules: frames (which frames a method uses, from the scan's frame roles), gray (Gray code tables,
binarisation, stripe interpolation along the code gradient), phase (wrapped phase, unwrapping), cgc (Gray
code + phase: CGC and the GT pipeline), triangulate (plane, both-coordinate and ray-ray midpoint
triangulation chosen from the rig), methods (the registry). Point clouds are written by slwarp.evaluation.outputs.
"""
from .frames import MissingFrames
from .methods import METHODS, Decoding, decode, finalize_positions, reconstruct_depth
from .triangulate import (baseline_alignment, choose_plane_axis, choose_triangulation, triangulate, triangulate_midpoint,
                          triangulate_plane, triangulate_rays)

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
    "triangulate_rays",
    "baseline_alignment",
    "choose_plane_axis",
    "choose_triangulation",
]
