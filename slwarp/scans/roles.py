"""Frame roles: what each frame of a scan is (a Gray code bit, a phase-shift step, a white frame, ...).

A frame declares its role in scan.yaml (`role:` beside `name`, `image`, `pattern`), as a mapping or as a
role string (the selector grammar below, every field given):

    {kind: gray, axis: col, bit: 0, inverse: false}      Gray code bit (0 = most significant), or its inverse
    {kind: phase, axis: col, period: 40, step: 0, steps: 4}   step of an N-step phase shift, period in projector px
    white | black                                        full-on / full-off frame
    {kind: uniform, level: 0.78}                         uniform frame at another level (0 = black, 1 = white)
    random | {kind: random, size: 20, index: 0}          random binary pattern (square size in px when known;
                                                         index and inverse optional)
    {kind: designed, index: 0, count: 4}                 i-th pattern (0-based) of an optimised set of `count`
                                                         grey-level patterns (slwarp.scans.pattern_files);
                                                         window_step: 3 when designed for the depth search's
                                                         windows 3 camera px apart (the search then uses 3)

Without a declared role, slwarp's own frame names are the fallback (`role_from_name`):

    gc_{col|row}_b{k}[_inv]   ps_{col|row}_p{P}_s{k}of{N}   white   black   rand{size}_{i}   uniform_{level}
    design{K}_{i}

A frame with neither has no role: the neural method uses it, the decoders do not. Roles are resolved once,
when a Scan is built (`resolve_roles`); the decoders read roles, never names. A declared role that is
incomplete, malformed, contradicts the frame's slwarp-style name, or repeats another frame's role raises
`RoleError` naming the frame and the problem.

Selector grammar (`--frames`, `slwarp info`): KIND[:QUALIFIER]..., KIND one of gray, phase, white, black,
uniform, random, designed; a QUALIFIER is `col` or `row` (axis), `inv` or `noinv` (inverse or not), or
FIELD=VALUE or FIELD=LO-HI (an inclusive range) with FIELD one of bit, period, step, steps, size, index, count,
level, window_step:

    gray:col                  every column Gray code frame (bits and inverses)
    gray:col:bit=0-6:noinv    the 7 most significant column bits, no inverses (GC(7))
    phase:row:period=40       the steps of the 40 px row phase shift
    random:size=20            the random patterns of 20 px squares
    designed:count=4          the 4 patterns of a designed set of 4 (designed:index=0-2: its first 3)
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, fields

__all__ = ["KINDS", "FrameRole", "RoleError", "RoleSelector", "role_from_name", "parse_role", "resolve_roles",
           "parse_selector", "describe_roles", "role_groups"]

KINDS = ("gray", "phase", "white", "black", "uniform", "random", "designed")
AXES = ("col", "row")
# the fields each kind may have, and which of them it must have
_FIELDS = {
    "gray": ({"axis", "bit", "inverse"}, {"axis", "bit"}),
    "phase": ({"axis", "period", "step", "steps"}, {"axis", "period", "step", "steps"}),
    "white": (set(), set()),
    "black": (set(), set()),
    "uniform": ({"level"}, set()),
    "random": ({"size", "index", "inverse"}, set()),
    "designed": ({"index", "count", "window_step"}, {"index", "count"}),
}
_INT_FIELDS = ("bit", "step", "steps", "index", "count", "window_step")
_FLOAT_FIELDS = ("period", "size", "level")


class RoleError(ValueError):
    """A frame role that cannot be used: the message names the frame and the problem."""


@dataclass(frozen=True)
class FrameRole:
    """What a frame is. kind: one of KINDS; axis: 'col' or 'row' (gray, phase); bit: Gray code bit, 0 = most
    significant; inverse: the inverted pattern (gray, random); period: projector px, step and steps: k of N
    (phase); size: random square size px (None: unknown); index: i-th random or designed pattern (0-based);
    count: the designed set's size K; level: uniform level; window_step: camera px between the pixels of the depth
    search's windows a designed set was optimised for (design-patterns --window-step; None: 1, adjacent pixels)."""

    kind: str
    axis: str | None = None
    bit: int | None = None
    inverse: bool = False
    period: float | None = None
    step: int | None = None
    steps: int | None = None
    size: float | None = None
    index: int | None = None
    level: float | None = None
    count: int | None = None
    window_step: int | None = None

    @property
    def unique(self) -> bool:
        """True when no two frames of a scan may share this role (random patterns without an index and
        uniform frames without a level may repeat)."""
        if self.kind == "random":
            return self.index is not None and self.size is not None
        if self.kind == "uniform":
            return self.level is not None
        return True

    def label(self) -> str:
        """The role in the selector grammar, every field given: 'gray:col:bit=3:inv', 'white', ..."""
        parts = [self.kind]
        if self.axis:
            parts.append(self.axis)
        for f in ("bit", "period", "step", "steps", "size", "count", "index", "level", "window_step"):
            v = getattr(self, f)
            if v is not None:
                parts.append(f"{f}={_fmt(v)}")
        if self.inverse:
            parts.append("inv")
        return ":".join(parts)

    def to_yaml(self):
        """The role as scan.yaml writes it: a bare kind for white/black, else a mapping of the fields set."""
        if self.kind in ("white", "black"):
            return self.kind
        d = {"kind": self.kind}
        for f in ("axis", "bit", "inverse", "period", "step", "steps", "size", "index", "count", "level", "window_step"):
            v = getattr(self, f)
            if f == "inverse":
                if self.kind == "gray" or v:
                    d[f] = bool(v)
            elif v is not None:
                d[f] = v
        return d

    @property
    def name(self) -> str | None:
        """slwarp's frame name for this role (the fallback grammar), or None where it has none."""
        if self.kind == "gray":
            return f"gc_{self.axis}_b{self.bit}" + ("_inv" if self.inverse else "")
        if self.kind == "phase":
            return f"ps_{self.axis}_p{_fmt(self.period)}_s{self.step}of{self.steps}"
        if self.kind in ("white", "black"):
            return self.kind
        if self.kind == "uniform" and self.level is not None:
            return f"uniform_{_fmt(self.level)}"
        if self.kind == "random" and self.size is not None and self.index is not None:
            return f"rand{_fmt(self.size)}_{self.index}" + ("_inv" if self.inverse else "")
        if self.kind == "designed":
            return f"design{self.count}_{self.index}"
        return None


def _fmt(v) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


# ----------------------------------------------------------------------------------------------
# names (the fallback)

_NUM = r"([0-9]*\.?[0-9]+(?:e[+-]?\d+)?)"
_NAME_PATTERNS = [
    (re.compile(r"gc_(col|row)_b(\d+)(_inv)?"),
     lambda m: FrameRole("gray", axis=m[1], bit=int(m[2]), inverse=bool(m[3]))),
    (re.compile(rf"ps_(col|row)_p{_NUM}_s(\d+)of(\d+)"),
     lambda m: FrameRole("phase", axis=m[1], period=float(m[2]), step=int(m[3]), steps=int(m[4]))),
    (re.compile(r"white"), lambda m: FrameRole("white")),
    (re.compile(r"black"), lambda m: FrameRole("black")),
    (re.compile(rf"uniform_{_NUM}"), lambda m: FrameRole("uniform", level=float(m[1]))),
    (re.compile(rf"rand{_NUM}_(\d+)(_inv)?"),
     lambda m: FrameRole("random", size=float(m[1]), index=int(m[2]), inverse=bool(m[3]))),
    (re.compile(r"design(\d+)_(\d+)"), lambda m: FrameRole("designed", index=int(m[2]), count=int(m[1]))),
]


def role_from_name(name: str) -> FrameRole | None:
    """The role that slwarp's naming contract gives `name`, or None (the name follows no contract)."""
    for pattern, make in _NAME_PATTERNS:
        m = pattern.fullmatch(name)
        if m:
            role = make(m)
            try:
                _check(role)
            except RoleError:
                return None  # e.g. ps_col_p40_s5of4: not a valid role, so not a role name
            return role
    return None


# ----------------------------------------------------------------------------------------------
# declared roles


def _check(role: FrameRole) -> FrameRole:
    """Validate the values of a role (RoleError without the frame; the caller adds it)."""
    allowed, required = _FIELDS[role.kind]
    missing = sorted(f for f in required if getattr(role, f) is None)
    if missing:
        raise RoleError(f"a {role.kind} role needs {', '.join(missing)}")
    if role.axis is not None and role.axis not in AXES:
        raise RoleError(f"axis must be 'col' or 'row', got {role.axis!r}")
    if role.bit is not None and role.bit < 0:
        raise RoleError(f"bit must be >= 0, got {role.bit}")
    if role.steps is not None and role.steps < 3:
        raise RoleError(f"a phase shift needs at least 3 steps, got steps={role.steps}")
    if role.step is not None and not 0 <= role.step < (role.steps or 0):
        raise RoleError(f"step must be in 0..steps-1 ({(role.steps or 0) - 1}), got step={role.step}")
    for f in ("period", "size"):
        v = getattr(role, f)
        if v is not None and not (math.isfinite(v) and v > 0):
            raise RoleError(f"{f} must be a positive number of projector px, got {v}")
    if role.level is not None and not 0.0 <= role.level <= 1.0:
        raise RoleError(f"level must be in [0, 1] (0 = black, 1 = white), got {role.level}")
    if role.index is not None and role.index < 0:
        raise RoleError(f"index must be >= 0, got {role.index}")
    if role.count is not None:
        if role.count < 1:
            raise RoleError(f"count must be >= 1 (the designed set's size), got {role.count}")
        if role.index is not None and role.index >= role.count:
            raise RoleError(f"index must be in 0..count-1 ({role.count - 1}), got index={role.index}")
    if role.window_step is not None and role.window_step < 1:
        raise RoleError(f"window_step must be >= 1 camera px, got window_step={role.window_step}")
    return role


def _convert(key: str, value, kind: str):
    """A yaml value as the field's type (RoleError naming the field when it is not)."""
    if key == "axis":
        if value not in AXES:
            raise RoleError(f"axis must be 'col' or 'row', got {value!r}")
        return value
    if key == "inverse":
        if not isinstance(value, bool):
            raise RoleError(f"inverse must be true or false, got {value!r}")
        return value
    try:
        if key in _INT_FIELDS:
            if isinstance(value, bool) or float(value) != int(float(value)):
                raise ValueError
            return int(float(value))
        if isinstance(value, bool):
            raise ValueError
        return float(value)
    except (TypeError, ValueError):
        kind_of = "an integer" if key in _INT_FIELDS else "a number"
        raise RoleError(f"{key} must be {kind_of}, got {value!r}") from None


def parse_role(value) -> FrameRole:
    """A declared role (a scan.yaml mapping, a kind, or a full role string such as 'gray:col:bit=0') as a
    FrameRole. Raises RoleError (without the frame: `resolve_roles` adds it)."""
    if isinstance(value, FrameRole):
        return _check(value)
    if isinstance(value, str):
        sel = parse_selector(value)
        if sel is None:
            raise RoleError(f"unknown role {value!r}; a role is a mapping with 'kind' ({', '.join(KINDS)}) "
                            "or a role string such as 'gray:col:bit=0'")
        return sel.exact_role()
    if not isinstance(value, dict):
        raise RoleError(f"a role is a mapping such as {{kind: gray, axis: col, bit: 0}} or a kind, got {value!r}")
    if "kind" not in value:
        raise RoleError(f"the role {value!r} has no 'kind' ({', '.join(KINDS)})")
    kind = value["kind"]
    if kind not in KINDS:
        raise RoleError(f"unknown role kind {kind!r}; kinds: {', '.join(KINDS)}")
    allowed, _ = _FIELDS[kind]
    kw = {}
    for key, v in value.items():
        if key == "kind":
            continue
        if key not in allowed:
            what = f"fields: {', '.join(sorted(allowed))}" if allowed else "it has no fields"
            raise RoleError(f"{key!r} is not a field of a {kind} role ({what})")
        kw[key] = _convert(key, v, kind)
    return _check(FrameRole(kind, **kw))


def _agree(declared: FrameRole, named: FrameRole) -> bool:
    """Whether a declared role and the role of the frame's slwarp-style name can be the same role: the same
    kind, and equal fields wherever both set them."""
    if declared.kind != named.kind:
        return False
    for f in fields(FrameRole):
        a, b = getattr(declared, f.name), getattr(named, f.name)
        if f.name == "inverse":
            if a != b:
                return False
        elif a is not None and b is not None and a != b:
            return False
    return True


def resolve_roles(names: list[str], declared: dict | None = None) -> list[FrameRole | None]:
    """The role of every frame: declared (name -> role as `parse_role` reads it) or from the frame's name.

    Raises RoleError naming the frame when a declared role is malformed or incomplete, when it contradicts
    the frame's slwarp-style name, or when two frames have the same role."""
    declared = declared or {}
    roles: list[FrameRole | None] = []
    for name in names:
        named = role_from_name(name)
        if name in declared and declared[name] is not None:
            try:
                role = parse_role(declared[name])
            except RoleError as e:
                raise RoleError(f"frame {name!r}: {e}") from None
            if named is not None and not _agree(role, named):
                raise RoleError(f"frame {name!r}: its role {role.label()} contradicts its name, which means "
                                f"{named.label()} (rename the frame or fix the role)")
        else:
            role = named
        roles.append(role)
    seen: dict[FrameRole, str] = {}
    for name, role in zip(names, roles):
        if role is None or not role.unique:
            continue
        if role in seen:
            raise RoleError(f"frames {seen[role]!r} and {name!r} both have the role {role.label()}")
        seen[role] = name
    return roles


# ----------------------------------------------------------------------------------------------
# selectors


@dataclass(frozen=True)
class RoleSelector:
    """A role selector: kind, and constraints on fields (a value, or an inclusive (lo, hi) range)."""

    kind: str
    constraints: tuple = ()  # ((field, lo, hi), ...); axis and inverse as (field, value, value)

    def matches(self, role: FrameRole | None) -> bool:
        if role is None or role.kind != self.kind:
            return False
        for f, lo, hi in self.constraints:
            v = getattr(role, f)
            if f in ("axis", "inverse"):
                if v != lo:
                    return False
            elif v is None or not (lo - 1e-9 <= v <= hi + 1e-9):
                return False
        return True

    def exact_role(self) -> FrameRole:
        """The one role this selector names (every constraint a single value), validated."""
        kw = {}
        for f, lo, hi in self.constraints:
            if lo != hi:
                raise RoleError(f"a role has one value per field, got the range {f}={_fmt(lo)}-{_fmt(hi)}")
            kw[f] = lo
        allowed, _ = _FIELDS[self.kind]
        for f in kw:
            if f not in allowed:
                raise RoleError(f"{f!r} is not a field of a {self.kind} role")
        return _check(FrameRole(self.kind, **kw))


def parse_selector(token: str) -> RoleSelector | None:
    """A selector token (see the module docstring) -> RoleSelector; None when the token does not start with
    a role kind (it is then a frame name or glob). RoleError for a malformed qualifier."""
    parts = token.strip().split(":")
    kind = parts[0]
    if kind not in KINDS:
        return None
    allowed, _ = _FIELDS[kind]
    cons = []
    for q in parts[1:]:
        if q in AXES:
            key, lo, hi = "axis", q, q
        elif q in ("inv", "noinv"):
            key, lo, hi = "inverse", q == "inv", q == "inv"
        elif "=" in q:
            key, val = q.split("=", 1)
            if key not in _INT_FIELDS + _FLOAT_FIELDS:
                raise RoleError(f"selector {token!r}: unknown field {key!r} (fields: bit, period, step, steps, size, "
                                "index, count, level, window_step)")
            m = re.fullmatch(rf"{_NUM}(?:-{_NUM})?", val)
            if not m:
                raise RoleError(f"selector {token!r}: {key}= needs a number or a range LO-HI, got {val!r}")
            lo = float(m[1])
            hi = float(m[2]) if m[2] is not None else lo
            if key in _INT_FIELDS:
                lo, hi = int(lo), int(hi)
        else:
            raise RoleError(f"selector {token!r}: cannot read {q!r} (use col, row, inv, noinv or FIELD=VALUE)")
        if key not in allowed:
            raise RoleError(f"selector {token!r}: {kind} frames have no {key}")
        cons.append((key, lo, hi))
    return RoleSelector(kind, tuple(cons))


# ----------------------------------------------------------------------------------------------
# descriptions


def _ranges(values: list[int]) -> str:
    """[0, 1, 2, 5] -> '0-2,5'."""
    vals = sorted(set(values))
    out, start = [], vals[0]
    for a, b in zip(vals, vals[1:] + [None]):
        if b != a + 1:
            out.append(f"{start}" if start == a else f"{start}-{a}")
            start = b
    return ",".join(out)


def role_groups(names: list[str], roles: list[FrameRole | None]) -> list[tuple[str, list[str]]]:
    """Frames grouped by role family, in order of first appearance: [(label, frame names)]. A label is a
    selector of the group with a summary of its members, e.g. 'gray:col:bit=0-6 (+inv)'; frames without a
    role form the group 'no role'."""
    groups: dict[tuple, list[int]] = {}
    for i, r in enumerate(roles):
        if r is None:
            key = ("none",)
        elif r.kind == "gray":
            key = ("gray", r.axis)
        elif r.kind == "phase":
            key = ("phase", r.axis, r.period, r.steps)
        elif r.kind == "random":
            key = ("random", r.size)
        elif r.kind == "designed":
            key = ("designed", r.count)
        else:
            key = (r.kind, r.level)
        groups.setdefault(key, []).append(i)
    out = []
    for key, idx in groups.items():
        members = [roles[i] for i in idx]
        kind = key[0]
        if kind == "none":
            label = "no role"
        elif kind == "gray":
            bits = [r.bit for r in members if not r.inverse]
            inv = [r.bit for r in members if r.inverse]
            label = f"gray:{key[1]}:bit={_ranges(bits or inv)}"
            if inv and bits:
                label += " (+inv)" if sorted(inv) == sorted(bits) else f" (inverses of bit={_ranges(inv)})"
            elif inv:
                label += ":inv"
        elif kind == "phase":
            steps = [r.step for r in members]
            label = f"phase:{key[1]}:period={_fmt(key[2])}:steps={key[3]} (step={_ranges(steps)})"
        elif kind == "random":
            label = "random" + (f":size={_fmt(key[1])}" if key[1] is not None else "")
            n_inv = sum(r.inverse for r in members)
            if n_inv:
                label += f" ({n_inv} inverse{'s' if n_inv > 1 else ''})"
        elif kind == "designed":
            label = f"designed:count={key[1]} (index={_ranges([r.index for r in members])})"
        else:
            label = kind + (f":level={_fmt(key[1])}" if kind == "uniform" and key[1] is not None else "")
        out.append((label, [names[i] for i in idx]))
    return out


def describe_roles(names: list[str], roles: list[FrameRole | None], limit: int = 12) -> str:
    """A compact one-line listing of a scan's frames by role, e.g. 'gray:col:bit=0-6 (+inv), white, black,
    no role (3 frames: a, b, c)'."""
    if not names:
        return "(no frames)"
    parts = []
    for label, members in role_groups(names, roles):
        if label == "no role":
            shown = ", ".join(members[:4]) + (", ..." if len(members) > 4 else "")
            parts.append(f"no role ({len(members)} frame{'s' if len(members) > 1 else ''}: {shown})")
        elif label.startswith("random") and len(members) > 1:
            parts.append(f"{label} x{len(members)}")
        else:
            parts.append(label)
    if len(parts) > limit:
        parts = parts[:limit] + [f"... ({len(names)} frames in all)"]
    return ", ".join(parts)

