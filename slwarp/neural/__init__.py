"""Neural reconstruction, one package or module per step of the pipeline, in the order a reconstruction runs:

- `reconstruct`: the end-to-end pipeline, composed of the steps below; `describe`: a run's configuration in words;
- `config`: the typed run configuration and its presets (imports no implementation module);
- `start`: what training starts from: working volume, field, renderer, the depth search (`start.search`), blur fit;
- `training`: `Trainer`, its loss terms, schedule, graphed CUDA step, checkpoints, stops, history and progress;
- `extraction`: from the trained field to a depth map, as a list of stages;
and what the steps are built of:
- `render`: `StructuredLightRenderer`, sampling + any SDF module + the fused render + losses (a drop-in loss);
- `fields`: the SDF fields (the working volume, NeuS's MLP, the hash grid) and `make_field`;
- `pattern_model`: the pattern model I = a + b P(pi(x)), its blur, photometric residual, confidence and refinement;
- `ops`: the Warp kernels as torch ops with their pure-torch twins;
- `depth_maps`: helpers on depth maps (neighbours, connected groups, points).
This module imports nothing, so that `import slwarp.neural.config` stays light."""
