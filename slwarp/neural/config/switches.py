"""The extraction's stage list and the options of old that switch its stages on and off: the order a stage takes
when a switch adds it, and the rules that keep `stages` and the switches in step (`sync_stages`, `check_stages`)."""
from __future__ import annotations

import typing

from .options import ConfigError, StageList

if typing.TYPE_CHECKING:
    from .sections import ExtractionConfig

__all__ = ["DEFAULT_STAGES", "STAGE_ORDER", "STAGE_SWITCHES", "check_stages", "sync_stages"]

# the extraction's stages (slwarp.neural.extraction.stages) in the order a preset lists them: an option that switches
# a stage on (STAGE_SWITCHES) puts it at its place in this order, after the stages that come before it here
STAGE_ORDER = ("marching_cubes", "depth", "depth_range", "flying_pixel", "confidence", "search_repair", "search_doubt",
               "refine", "uniform_fill", "repair_grow", "step_split", "edge_side", "denoise", "hole_fill", "edge_band")
# the stages of an extraction that names none: the mesh, its depth, the depth range, the flying-pixel filter and the
# confidence map with its filter
DEFAULT_STAGES = ("marching_cubes", "depth", "depth_range", "flying_pixel", "confidence")
# the options that switch a stage on (true, or a number above 0) and off (false, 0), by their flat names of old:
# `stages` and they always agree. search_repair and search_doubt share one place (the repair includes the doubt
# rule; while it runs, search_doubt says whether the doubt rule stays when the repair is switched off: sync_stages)
STAGE_SWITCHES = {"edge_filter": "flying_pixel", "search_repair": "search_repair", "search_doubt": "search_doubt",
                  "refine_range": "refine", "uniform_fill": "uniform_fill", "repair_grow": "repair_grow",
                  "step_split_radius": "step_split", "edge_side_radius": "edge_side", "denoise_radius": "denoise",
                  "hole_fill": "hole_fill",
                  "edge_band_radius": "edge_band"}
_SEARCH_STAGES = ("search_repair", "search_doubt")


def _place(stages: list[str], name: str) -> None:
    """Insert stage `name` into `stages` after the last of them that STAGE_ORDER puts before it (stages it does not
    know are passed over)."""
    rank = STAGE_ORDER.index(name)
    at = max((i + 1 for i, s in enumerate(stages) if s in STAGE_ORDER and STAGE_ORDER.index(s) < rank), default=0)
    stages.insert(at, name)


def sync_stages(ex: ExtractionConfig, given) -> None:
    """Make `stages` and the stage switches agree, in place: each switch in `given` (the options set just now) adds
    or removes its stage, then every switch reads from the list (a number switch keeps its value while its stage
    runs, 0 when it does not).

    search_repair and search_doubt share one place in the list: the repair (which includes the doubt rule), else the
    doubt rule alone, else neither. While the repair runs, search_doubt keeps its own value: whether the doubt rule
    stays when the repair is switched off (as the two options always behaved)."""
    stages = list(ex.stages)
    on = {opt: bool(getattr(ex, opt)) if opt in given else stage in stages for opt, stage in STAGE_SWITCHES.items()}
    if "search_doubt" not in given and "search_repair" in stages:
        on["search_doubt"] = bool(ex.search_doubt)
    if "search_doubt" not in given and "search_doubt" in stages:
        on["search_doubt"] = True
    if {"search_repair", "search_doubt"} & set(given):
        slot = "search_repair" if on["search_repair"] else "search_doubt" if on["search_doubt"] else None
        stages = [s for s in stages if s not in _SEARCH_STAGES or s == slot]
        if slot is not None and slot not in stages:
            _place(stages, slot)
    for opt in set(given) & STAGE_SWITCHES.keys() - {"search_repair", "search_doubt"}:
        stage = STAGE_SWITCHES[opt]
        if on[opt] and stage not in stages:
            _place(stages, stage)
        elif not on[opt] and stage in stages:
            stages.remove(stage)
    for opt, stage in STAGE_SWITCHES.items():
        value = getattr(ex, opt)
        if opt == "search_doubt":
            setattr(ex, opt, on[opt] if "search_repair" in stages else "search_doubt" in stages)
        elif isinstance(value, bool):
            setattr(ex, opt, stage in stages)
        elif stage not in stages:
            setattr(ex, opt, type(value)(0))
        elif not value > 0:
            raise ConfigError(f"option stages: {stage} runs with {opt} above 0, got {value}: give {opt} (or leave "
                              f"{stage} out)")
    ex.stages = StageList(stages)


def check_stages(ex: ExtractionConfig) -> None:
    """ConfigError unless `stages` names each stage once, at most one of the search repair and its doubt rule, and
    agrees with the stage switches (which with_options, presets and config files keep in step with it)."""
    stages = list(ex.stages)
    twice = sorted({s for s in stages if stages.count(s) > 1})
    if twice:
        raise ConfigError(f"option stages: {', '.join(twice)} named more than once in {StageList(stages)}")
    if set(_SEARCH_STAGES) <= set(stages):
        raise ConfigError("option stages: names both search_repair and search_doubt; the repair includes the doubt "
                          "rule, so name one")
    for opt, stage in STAGE_SWITCHES.items():
        if opt == "search_doubt" and "search_repair" in stages:
            continue  # the repair's own setting: whether the doubt rule stays without it
        if bool(getattr(ex, opt)) != (stage in stages):
            raise ConfigError(f"option {opt}: {getattr(ex, opt)!r} disagrees with stages ({StageList(stages)}), "
                              f"which {'names' if stage in stages else 'does not name'} {stage}; set options through "
                              "with_options, a preset or a config file, which keep them in step")

