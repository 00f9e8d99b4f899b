"""TrainConfig: the six sections of a run together, set by flat option names, checked as a whole, and turned
into and out of plain dicts (YAML, checkpoints)."""
from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass

from .options import ConfigError
from .sections import (OPTIONS, REMOVED_OPTIONS, SECTIONS, ExtractionConfig, FieldConfig, InitConfig, RuntimeConfig,
                       SamplingConfig, ScheduleConfig, option_named)
from .switches import check_stages, sync_stages

__all__ = ["TrainConfig"]


@dataclass
class TrainConfig:
    """Everything that defines a run, in six sections (see slwarp.neural.config and its PRESETS)."""

    field: FieldConfig = dataclasses.field(default_factory=FieldConfig)
    sampling: SamplingConfig = dataclasses.field(default_factory=SamplingConfig)
    schedule: ScheduleConfig = dataclasses.field(default_factory=ScheduleConfig)
    init: InitConfig = dataclasses.field(default_factory=InitConfig)
    runtime: RuntimeConfig = dataclasses.field(default_factory=RuntimeConfig)
    extraction: ExtractionConfig = dataclasses.field(default_factory=ExtractionConfig)

    def get(self, name: str):
        """The value of an option by its flat name."""
        opt = option_named(name)
        return getattr(getattr(self, opt.section), opt.key)

    def with_options(self, **options) -> "TrainConfig":
        """A copy with options set by flat name (e.g. iters=300, init_iters=100, device="cpu"), validated."""
        sections = {name: dataclasses.replace(getattr(self, name)) for name in SECTIONS}
        for name, value in options.items():
            opt = option_named(name)
            opt.check(value)
            setattr(sections[opt.section], opt.key, value)
        sync_stages(sections["extraction"], options)
        return TrainConfig(**sections).validate()

    def validate(self) -> "TrainConfig":
        """Check every option's type and range and the rules between options; raise ConfigError naming the
        option, its value and what is allowed. Returns self."""
        for name, cls in SECTIONS.items():
            if not isinstance(getattr(self, name), cls):
                raise ConfigError(f"TrainConfig.{name} must be a {cls.__name__}, got {type(getattr(self, name)).__name__}")
        for opt in OPTIONS.values():
            opt.check(self.get(opt.name))
        s, f = self.sampling, self.field
        if s.up_sample_steps > 0 and s.n_importance % s.up_sample_steps:
            raise ConfigError(f"option n_importance: {s.n_importance} is not a multiple of up_sample_steps "
                              f"({s.up_sample_steps})")
        if f.skip is not None and not f.skip < f.layers:
            raise ConfigError(f"option skip: {f.skip} must be below layers ({f.layers}), or none")
        if f.grid_start_levels > f.grid_levels:
            raise ConfigError(f"option grid_start_levels: {f.grid_start_levels} must not exceed grid_levels "
                              f"({f.grid_levels})")
        if f.grid_finest != "auto" and f.grid_finest < f.grid_base:
            raise ConfigError(f"option grid_finest: {f.grid_finest} must not be below grid_base ({f.grid_base}), or auto")
        check_stages(self.extraction)
        if self.extraction.edge_readmit and not self.extraction.edge_filter > 0:
            raise ConfigError("option edge_readmit: true needs edge_filter > 0 (it gives back what that filter dropped)")
        if self.extraction.repair_grow and not self.extraction.search_repair:
            raise ConfigError("option repair_grow: true needs search_repair: true (it spreads the repair's changes)")
        return self

    def lens_options(self) -> dict:
        """{option: value} a lens with a halo sets in place of this config's own: variance_lr_factor from
        lens_variance_lr_factor, lambda_reg from lens_lambda_reg, each where set (none: not replaced)."""
        s = self.schedule
        return {k: v for k, v in (("variance_lr_factor", s.lens_variance_lr_factor),
                                  ("lambda_reg", s.lens_lambda_reg)) if v is not None}

    def through_lens(self, halo_share: float) -> "TrainConfig":
        """The config a run trains with when its lens halo's share is `halo_share`: with a halo (share > 0) the
        `lens_options` in place of the config's own; otherwise (or without lens options) self."""
        swap = self.lens_options()
        return self.with_options(**swap) if halo_share > 0 and swap else self

    def fixed_options(self) -> dict:
        """{flat name: value} of every option a resumed run must keep: all but the `RESUMABLE` ones."""
        return {name: self.get(name) for name, opt in OPTIONS.items() if not opt.resumable}

    def to_dict(self) -> dict:
        """{section: {key: value}}: plain values, as YAML and checkpoints hold them (the stages as a list)."""
        doc = dataclasses.asdict(self)
        doc["extraction"]["stages"] = list(self.extraction.stages)
        return doc

    @classmethod
    def from_dict(cls, doc: dict, base: "TrainConfig | None" = None, source: str = "config") -> "TrainConfig":
        """`base` (default: TrainConfig()) with the values of doc {section: {key: value}} (all optional),
        validated. Unknown sections or keys raise ConfigError naming `source`."""
        if not isinstance(doc, dict):
            raise ConfigError(f"{source}: expected a mapping of sections ({', '.join(SECTIONS)}), got {type(doc).__name__}")
        sections = {name: dataclasses.replace(getattr(base or cls(), name)) for name in SECTIONS}
        for name, values in doc.items():
            if name not in SECTIONS:
                raise ConfigError(f"{source}: unknown section {name!r}; sections: {', '.join(SECTIONS)}")
            if not isinstance(values, dict):
                raise ConfigError(f"{source}: section {name} must be a mapping of options, got {values!r}")
            keys = {f.name: f for f in dataclasses.fields(SECTIONS[name])}
            for key, value in values.items():
                if (name, key) in REMOVED_OPTIONS:
                    if value:
                        warnings.warn(f"{source}: option {name}.{key} was removed ({REMOVED_OPTIONS[name, key]}); "
                                      f"its value {value!r} is ignored", stacklevel=2)
                    continue
                if key not in keys:
                    raise ConfigError(f"{source}: unknown option {name}.{key}; {name} has {', '.join(keys)}")
                opt = OPTIONS[keys[key].metadata.get("name") or key]
                try:
                    setattr(sections[name], key, opt.coerce(value))
                except ConfigError as e:
                    raise ConfigError(f"{source}: {e}") from None
        try:
            # a file of before `stages` (or one that sets a switch) has its switches add or remove their stages
            sync_stages(sections["extraction"], doc.get("extraction") or {})
        except ConfigError as e:
            raise ConfigError(f"{source}: {e}") from None
        return cls(**sections).validate()
