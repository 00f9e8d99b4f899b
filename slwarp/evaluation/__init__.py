"""Evaluation and outputs: depth metrics (metrics), the output writers of every method (outputs: depth maps,
PLY point clouds and meshes) and pictures (viz)."""
