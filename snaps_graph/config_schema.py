"""The config's checks and its TOML: a field's range, the check of a value against its type and
range, the walk over nested sections, and a value written as TOML. ``config.py`` declares the
sections with these; nothing here knows a particular setting."""

from __future__ import annotations

import dataclasses
import difflib
import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, Literal, get_args, get_origin, get_type_hints

from .errors import SnapsGraphError


@dataclass(frozen=True)
class Range:
    """Allowed values of a number: bounds (open or closed), odd, a multiple of ``multiple``."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    odd: bool = False
    multiple: int | None = None

    def describe(self) -> str:
        if self.lo is not None and self.hi is not None:
            text = f"in {'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}{')' if self.hi_open else ']'}"
        elif self.lo is not None:
            text = f"{'>' if self.lo_open else '>='} {self.lo:g}"
        elif self.hi is not None:
            text = f"{'<' if self.hi_open else '<='} {self.hi:g}"
        else:
            text = "a number"
        if self.odd:
            text = "odd and " + text
        if self.multiple:
            text = f"a multiple of {self.multiple} and " + text
        return text

    def ok(self, v: float) -> bool:
        if self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo):
            return False
        if self.hi is not None and (v >= self.hi if self.hi_open else v > self.hi):
            return False
        if self.odd and int(v) % 2 == 0:
            return False
        return not (self.multiple and int(v) % self.multiple)


class Section:
    """Validation shared by the config sections: every field is checked against its type (a
    ``Literal`` is an enumeration) and its range (the field's metadata), a nested section in turn,
    at construction and on demand. ``_name`` is the section's dotted name ("frontend")."""

    _name = "config"

    def __post_init__(self) -> None:
        self.validate()

    def validate(self, source: str = "config") -> None:
        """A one-line SnapsGraphError naming ``source`` and the key for the first bad value."""
        hints = hints_of(type(self))
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            value = getattr(self, f.name)
            if isinstance(value, Section):
                value.validate(source)
            else:
                check_value(value, hints[f.name], f.metadata.get("range"), f"{source}: {self._name}.{f.name}")
        self._cross_checks(source)

    def _cross_checks(self, source: str) -> None:
        pass


def is_section(obj: Any) -> bool:
    return dataclasses.is_dataclass(obj) and not isinstance(obj, type)


def settings(obj: Any, prefix: str = "") -> Iterator[tuple[str, dataclasses.Field, Any]]:
    """Every setting under ``obj`` as ("frontend.mode", its field, its type), nested
    sections walked in place; the sections themselves are not settings."""
    hints = hints_of(type(obj))
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if is_section(value):
            yield from settings(value, f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", f, hints[f.name]


_HINTS: dict[type, dict[str, Any]] = {}


def hints_of(cls: type) -> dict[str, Any]:
    if cls not in _HINTS:
        _HINTS[cls] = get_type_hints(cls)
    return _HINTS[cls]


def choices(hint: Any) -> tuple | None:
    """The allowed values of a ``Literal`` type, else None."""
    return get_args(hint) if get_origin(hint) is Literal else None


def check_value(value: Any, hint: Any, rule: Range | None, where: str) -> None:
    allowed = choices(hint)
    if allowed is not None:
        if isinstance(value, bool) or value not in allowed:
            raise SnapsGraphError(f"{where} must be one of {', '.join(repr(a) for a in allowed)}, got {value!r}")
        return
    if hint is bool:
        if not isinstance(value, bool):
            raise SnapsGraphError(f"{where}: expected true/false, got {value!r}")
        return
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise SnapsGraphError(f"{where}: expected an integer, got {value!r}")
    elif hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise SnapsGraphError(f"{where}: expected a finite number, got {value!r}")
    else:
        return  # a string
    if rule is not None and not rule.ok(value):
        shown = f"{value:.10g}" if isinstance(value, float) else repr(value)
        raise SnapsGraphError(f"{where} must be {rule.describe()}, got {shown}")


def coerce(current: Any, value: Any, where: str) -> Any:
    """A value read from TOML as the type of the field's ``current`` value, or a one-line error."""
    if isinstance(current, bool):
        if not isinstance(value, bool):
            raise SnapsGraphError(f"{where}: expected true/false, got {value!r}")
        return value
    if isinstance(current, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise SnapsGraphError(f"{where}: expected an integer, got {value!r}")
        return value
    if isinstance(current, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise SnapsGraphError(f"{where}: expected a finite number, got {value!r}")
        return float(value)
    if isinstance(current, str):
        if not isinstance(value, str):
            raise SnapsGraphError(f"{where}: expected a string, got {value!r}")
        return value
    return value


def toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    raise TypeError(f"cannot write {value!r} to TOML")


def describe(f: dataclasses.Field, hint: Any) -> str:
    """A field's comment in ``snaps-graph config``: its help, then its range or choices."""
    text = f.metadata.get("help", "")
    allowed = choices(hint)
    if allowed is not None:
        return f"{text}; one of {', '.join(toml_value(a) for a in allowed)}"
    if "range" in f.metadata:
        return f"{text}; {f.metadata['range'].describe()}"
    return text


def did_you_mean(name: str, obj: Any, prefix: str = "") -> str:
    """ " (did you mean 'loop.min_similarity'?)" for a misspelled key, else "". A key of a nested
    section counts too, so a prefix left off ("section.key") finds "section.part.key"."""
    names = {f.name: f.name for f in dataclasses.fields(obj)}
    for key, _, _ in settings(obj):
        names.setdefault(key.rpartition(".")[2], key)
    close = difflib.get_close_matches(name, list(names), n=1, cutoff=0.7)
    return f" (did you mean '{prefix}{names[close[0]]}'?)" if close else ""


def dumps_section(obj: Any, name: str, comments: bool) -> list[str]:
    """``obj``'s settings as TOML lines under ``[name]`` (no header for the root), then each nested
    section as its own ``[name.sub]`` table."""
    lines = [f"[{name}]"] if name else []
    hints = hints_of(type(obj))
    nested = []
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if is_section(value):
            nested.append((f"{name}.{f.name}" if name else f.name, value))
            continue
        line = f"{f.name} = {toml_value(value)}"
        lines.append(f"{line}  # {describe(f, hints[f.name])}" if comments else line)
    for sub, value in nested:
        lines += ["", *dumps_section(value, sub, comments)]
    return lines
