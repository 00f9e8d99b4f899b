"""The option machinery: `option()` declares a section's field, `Option` describes one option by its flat name
(type, range, help) and parses, coerces and checks its values; `ConfigError` names what is wrong."""
from __future__ import annotations

import dataclasses
import math
import re
import typing
from dataclasses import dataclass
from typing import Literal

__all__ = ["ConfigError", "DEVICE_PATTERN", "Option", "StageList", "collect_options", "option"]

# the device names a user may give (CLI --device, TrainConfig.runtime.device; slwarp.devices resolves them)
DEVICE_PATTERN = re.compile(r"auto|cpu|cuda(:\d+)?")
# the type of an annotation such as `int | None` (types.UnionType), beside typing.Union
_UnionType = type(int | None)


class ConfigError(ValueError):
    """An unknown option or a value an option cannot take; the message names the option, the value and
    what is allowed."""


def option(default, help: str, *, min=None, max=None, above=None, name: str | None = None, resumable: bool = False):
    """A config field: its default, a one-line help (CLI --help and docs), the allowed range (min <= value <=
    max, value > above), its flat name when it differs from the field's (it must be unique across sections) and
    whether a resumed run may change it (`resumable`: it does not define what the run computes)."""
    return dataclasses.field(default=default, metadata={"help": help, "min": min, "max": max, "above": above, "name": name,
                                                        "resumable": resumable})


class StageList(tuple):
    """The extraction's stage names in order (a tuple; written comma-separated, as the command line takes them)."""

    def __str__(self) -> str:
        return ",".join(self)


@dataclass(frozen=True)
class Option:
    """One option: its flat name, where it lives (section, key), its type and allowed values."""

    name: str
    section: str
    key: str
    type: object
    help: str
    min: float | None = None
    max: float | None = None
    above: float | None = None
    resumable: bool = False  # a resumed run may change it (see slwarp.neural.config's docstring)

    @property
    def choices(self) -> tuple | None:
        """The allowed words of a Literal option (with a number alternative: the words besides the number)."""
        words = [a for t in self._alternatives() if typing.get_origin(t) is Literal for a in typing.get_args(t)]
        return tuple(words) if words else None

    @property
    def is_bool(self) -> bool:
        return self.type is bool

    @property
    def is_list(self) -> bool:
        """A list of names (the extraction's stages): comma-separated on the command line, a list in YAML."""
        return typing.get_origin(self.type) is tuple

    def _alternatives(self) -> tuple:
        return typing.get_args(self.type) if typing.get_origin(self.type) in (typing.Union, _UnionType) else (self.type,)

    def _numeric(self):
        """int or float when the option takes a number (besides words or None), else None."""
        for t in self._alternatives():
            if t in (int, float):
                return t
        return None

    def allowed(self) -> str:
        """What the option takes, in words."""
        if self.is_list:
            return "a comma-separated list of names"
        parts = []
        num = self._numeric()
        if num is not None:
            rng = []
            if self.min is not None:
                rng.append(f">= {self.min:g}")
            if self.above is not None:
                rng.append(f"> {self.above:g}")
            if self.max is not None:
                rng.append(f"<= {self.max:g}")
            parts.append(("an integer" if num is int else "a number") + (" " + " and ".join(rng) if rng else ""))
        if self.choices:
            parts.append(("" if parts else "one of ") + ", ".join(map(str, self.choices)))
        if type(None) in self._alternatives():
            parts.append("none")
        if self.is_bool:
            parts.append("true or false")
        if self.type is str and self.key == "device":
            parts.append("auto, cpu, cuda or cuda:N")
        return " or ".join(parts)

    def metavar(self) -> str:
        """How --help shows the value: {a,b} for a choice of words, N (an integer) or X (a number) with the
        words it also takes, the key in capitals for text."""
        if self.is_list:
            return "NAME,..."
        if self.choices and self._numeric() is None:
            return "{" + ",".join(self.choices) + "}"
        word = {int: "N", float: "X"}.get(self._numeric(), self.key.upper())
        return "|".join([word, *(self.choices or ()), *(["none"] if type(None) in self._alternatives() else [])])

    def _fail(self, value):
        raise ConfigError(f"option {self.name} ({self.section}.{self.key}): {value!r} is not allowed; it takes {self.allowed()}")

    def check(self, value) -> None:
        """Raise ConfigError unless `value` is of the option's type and in its range."""
        if value is None:
            if type(None) not in self._alternatives():
                self._fail(value)
            return
        if self.is_list:
            if not (isinstance(value, (list, tuple)) and value and all(isinstance(v, str) and v.isidentifier()
                                                                      for v in value)):
                self._fail(value)
            return
        if self.choices and value in self.choices and not isinstance(value, bool):
            return
        if self.is_bool:
            if not isinstance(value, bool):
                self._fail(value)
            return
        num = self._numeric()
        if num is not None and isinstance(value, (int, float)) and not isinstance(value, bool):
            if (num is int and not isinstance(value, int)) or not math.isfinite(value):
                self._fail(value)
            if ((self.min is not None and value < self.min) or (self.max is not None and value > self.max)
                    or (self.above is not None and not value > self.above)):
                self._fail(value)
            return
        if self.type is str and isinstance(value, str) and (self.key != "device" or DEVICE_PATTERN.fullmatch(value)):
            return
        self._fail(value)

    def parse(self, text: str):
        """The value of `text` (a command-line word, a key=value spec, a YAML string), checked."""
        word = text.strip()
        if self.is_list:
            value = StageList(w.strip() for w in word.split(","))
            self.check(value)
            return value
        if self.is_bool:
            low = word.lower()
            if low not in ("true", "false", "1", "0", "yes", "no", "on", "off"):
                self._fail(text)
            value = low in ("true", "1", "yes", "on")
        elif self.choices and word in self.choices:
            value = word
        elif type(None) in self._alternatives() and word.lower() in ("none", "null"):
            value = None
        elif self._numeric() is not None:
            try:
                value = int(word) if self._numeric() is int else float(word)
            except ValueError:
                self._fail(text)
        else:
            value = word
        self.check(value)
        return value

    def coerce(self, value):
        """A value read from YAML: strings are parsed as on the command line (YAML reads 1e-4 as a string), an
        integer is accepted for a number; checked."""
        if isinstance(value, str):
            return self.parse(value)
        if self.is_list and isinstance(value, (list, tuple)):
            value = StageList(value)
        if isinstance(value, int) and not isinstance(value, bool) and self._numeric() is float:
            value = float(value)
        self.check(value)
        return value



def collect_options(sections: dict) -> dict[str, Option]:
    """{flat name: Option} of every field of the section classes {section: dataclass}; RuntimeError when a flat
    name is not unique."""
    options: dict[str, Option] = {}
    for section, cls in sections.items():
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            md = f.metadata
            name = md.get("name") or f.name
            if name in options:
                raise RuntimeError(f"option name {name!r} ({section}.{f.name}) is not unique")
            options[name] = Option(name, section, f.name, hints[f.name], md["help"], md.get("min"), md.get("max"),
                                   md.get("above"), bool(md.get("resumable")))
    return options

