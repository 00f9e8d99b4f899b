"""Warp kernels of slwarp, imported as `slwarp.kernels` (never as a top-level `kernels`).

- runtime:   lazy Warp initialisation, kernel cache, device and stream helpers
- geometry:  shared @wp.func helpers: OpenCV distortion, projection into the projector, bilinear taps
- simulate:  the virtual scanner's ray casting (BVH mesh queries) and pattern sampling
- sampling:  camera rays, stratified samples and NeuS hierarchical up-sampling (no gradients)
- render:    the fused structured-light renderer (NeuS weights, reprojection, surface point, Eikonal)
             with its hand-written backward

Importing this package does not initialise Warp; `runtime.init()` does, on first use.
"""
