"""Neural reconstruction: the SDF field (field), the pattern model I = a + b P(pi(x)) with its blur and
photometric checks (pattern_model, confidence), the fused Warp renderer as torch ops with their torch twins (ops,
twin), sampling and losses (render), the depth-search start (search), training (train), the extraction from the
trained field to a depth map as a list of stages (extraction) and the end-to-end pipeline (reconstruct)."""
