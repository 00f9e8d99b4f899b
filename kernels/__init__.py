"""Warp kernels of slwarp, imported as `slwarp.kernels` (never as a top-level `kernels`).

- runtime:   lazy Warp initialisation, the kernel cache, array descriptors of torch tensors, struct values
             filled from them, cached launches
- geometry:  the helpers every kernel module shares (the only one they import): camera and projector structs,
             OpenCV distortion, projection into the projector, bilinear taps of one channel or N patterns,
             sigmoid, inside-box, the constants the twin shares
- simulate:  the virtual scanner's ray casting (BVH mesh queries) and pattern sampling
- sampling:  camera rays, stratified samples and NeuS hierarchical up-sampling (no gradients)
- render:    the fused structured-light renderer (NeuS weights, reprojection, surface point, Eikonal)
             with its hand-written backward
- search:    the exhaustive depth search (the neural SDF's starting depth map)
- hashgrid:  the multiresolution hash-grid encoding, its spatial gradient and their backward passes
- reproject: bilinear lookups of K patterns at projector pixels, backward into patterns (atomics) and pixels

Importing a kernel module defines its kernels without initialising Warp; `runtime.init()` does, on first use.
Nothing here imports torch or slwarp's other packages: the slwarp modules that launch kernels import them.
"""
