"""Configs in and out of text: YAML files of sections (`load_config`, `save_config`) and KEY=VALUE assignments
(`parse_assignments`: the key=value specs of the benchmarks)."""
from __future__ import annotations

from pathlib import Path

from .options import ConfigError
from .sections import OPTIONS
from .train_config import TrainConfig

__all__ = ["load_config", "parse_assignments", "save_config"]


def parse_assignments(items) -> dict:
    """['iters=300', 'field=hashgrid'] -> {flat option name: value}, each value parsed and checked as on the
    command line; ConfigError naming the item when it is not KEY=VALUE with KEY an option (see OPTIONS)."""
    options = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or key not in OPTIONS:
            raise ConfigError(f"{item!r}: expected KEY=VALUE with KEY an option of slwarp.neural.config")
        options[key] = OPTIONS[key].parse(value)
    return options


def load_config(path, base: TrainConfig | None = None) -> TrainConfig:
    """A config from a YAML file of sections (field, sampling, ...: mappings of options; any may be left out and
    keeps `base`'s values, default TrainConfig()). A `fitted` section (values a run fitted, written by
    `save_config`) is read past, so a run's config.yaml can be passed back."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    try:
        doc = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: not valid YAML ({e})") from None
    if isinstance(doc, dict):
        doc = {k: v for k, v in doc.items() if k != "fitted"}
    return TrainConfig.from_dict(doc if doc is not None else {}, base, source=str(path))


def save_config(path, config: TrainConfig, fitted: dict | None = None) -> None:
    """Write the config as YAML (every section and option) and, when given, the values the run fitted in a
    `fitted` section."""
    import yaml

    doc = config.to_dict()
    if fitted is not None:
        doc["fitted"] = _plain(fitted)
    Path(path).write_text(yaml.safe_dump(doc, sort_keys=False, default_flow_style=False, width=120))


def _plain(x):
    """Nested dicts/lists with numpy scalars turned into Python numbers (YAML's safe dumper needs them)."""
    if isinstance(x, dict):
        return {_plain(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if hasattr(x, "item") and callable(x.item):
        return x.item()
    return x
