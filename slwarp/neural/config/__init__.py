"""TrainConfig: everything that defines a neural reconstruction run, in six typed sections.

    field       the SDF network: kind mlp (NeuS's MLP: width, depth, skip, encoding) or hashgrid (its grid_* options)
    sampling    what a training step renders: rays, samples per ray, pixels with contrast, pattern blur
    schedule    iterations, Adam's learning rate and its decay, loss weights, incremental mode
    init        where the field starts: depth-search map + warm-up, NeuS's sphere, or a far surface
    runtime     how and where it runs (seed, backend, device, precision, compile, CUDA graph, logs)
    extraction  from the trained field to a depth map (marching cubes, ray casting, filters)

Every option has one flat name, unique across sections (`OPTIONS`): the CLI flag (--name with dashes, generated
from this package with its type, choices and help), the keyword of `preset(name, **options)` and
`TrainConfig.with_options`, and the key of bench specs (key=value). On disk a config is YAML with the sections
as mappings (`load_config`, `save_config`). `TrainConfig.validate` checks every value against its type and
range and raises ConfigError naming the option, the value and what is allowed.

Resuming: a run's checkpoint records its `fixed_options()` (every option but the resumable ones) and a resumed run
must keep them; the options marked `resumable` (`RESUMABLE`: more iterations, logging and checkpoint intervals,
where and how the same computation runs, and the whole extraction section, which acts after training) may change.

PRESETS: paper (the paper's recipe, unchanged), tuned, fast and accurate (the hash-grid field, GPU), cpu and
cpu-hashgrid (small rig, two CPU cores), tiny (tests); `PRESET_SUMMARIES` says what each is for, docs/presets.md
why each holds its values. `default_preset_name(device)` reads DEFAULT_PRESET (one entry per device type).

The modules: `options` (the option machinery: `option()`, `Option`, `ConfigError`), `switches` (the extraction's
stage list and the options that switch its stages), `sections` (the six sections, `OPTIONS`), `train_config`
(`TrainConfig`), `presets`, `files` (YAML and key=value). The config is where its defaults live: it imports no
implementation module (nor torch), and those that need a default import it from here (`CONTRAST_THRESHOLD`,
`REFINE_MAX_MISFIT`, `DEVICE_PATTERN`).
"""
from .files import load_config, parse_assignments, save_config
from .options import DEVICE_PATTERN, ConfigError, Option, StageList, option
from .presets import DEFAULT_PRESET, PRESET_SUMMARIES, PRESETS, REFINE_MAX_MISFIT, default_preset_name, preset
from .sections import (CONTRAST_THRESHOLD, OPTIONS, REMOVED_OPTIONS, RESUMABLE, SECTIONS, ExtractionConfig, FieldConfig,
                       InitConfig, RuntimeConfig, SamplingConfig, ScheduleConfig)
from .switches import DEFAULT_STAGES, STAGE_ORDER, STAGE_SWITCHES
from .train_config import TrainConfig

__all__ = [
    "ConfigError",
    "FieldConfig",
    "SamplingConfig",
    "ScheduleConfig",
    "InitConfig",
    "RuntimeConfig",
    "ExtractionConfig",
    "TrainConfig",
    "Option",
    "OPTIONS",
    "RESUMABLE",
    "SECTIONS",
    "PRESETS",
    "PRESET_SUMMARIES",
    "preset",
    "parse_assignments",
    "default_preset_name",
    "DEFAULT_PRESET",
    "load_config",
    "save_config",
]
