"""From a trained field to a depth map: the extraction.

- `surface`: marching cubes, the mesh's depth by ray casting or the field's by sphere tracing, the flying-pixel
  filter and its edge readmission, the edge-aware denoising, point clouds.
- `confidence`: per-pixel confidence maps of a depth map (the photometric term, which the training shares, is
  `slwarp.neural.confidence`'s).
"""
