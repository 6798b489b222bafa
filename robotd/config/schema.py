"""Typed configuration schema: plain mappings in, frozen dataclasses out, every problem named by its dotted path.

Theory of operation: a configuration section is a frozen dataclass whose fields are declared with `setting()`,
which carries the field's documentation and an optional check. `build()` walks a parsed YAML mapping against the
dataclass's type hints, collecting every problem (unknown key with the nearest known key, wrong type, failed check)
instead of stopping at the first, so that one run of `robotd check-config` lists them all. `reference()` walks the
same schema to print the configuration reference, so the documentation cannot drift from the code.
"""

from __future__ import annotations

import dataclasses
import difflib
import ipaddress
import math
import re
import types
import typing
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any, Literal, TypeVar, get_args, get_origin

Check = Callable[[Any], str | None]
"""A check returns None when the value is acceptable, else the reason, as in "must be > 0"."""

T = TypeVar("T")


class ConfigError(Exception):
    """A configuration that cannot be used: one human-readable line per problem."""

    def __init__(self, problems: list[str]) -> None:
        super().__init__("\n".join(problems))
        self.problems = problems


def setting(default: T, doc: str, check: Check | None = None) -> T:
    """Declare a configuration field with its default, its one-line documentation and an optional check."""
    if isinstance(default, list | dict):
        raise TypeError("use a tuple or a dataclass for structured defaults")  # frozen configs hold no mutables
    return dataclasses.field(default=default, metadata={"doc": doc, "check": check})


def section(factory: Callable[[], T], doc: str) -> T:
    """Declare a nested configuration section (a dataclass) with its documentation."""
    return dataclasses.field(default_factory=factory, metadata={"doc": doc, "check": None})


# --- checks ---------------------------------------------------------------------------------------


def _show(value: Any) -> str:
    """A value as the user wrote it: -1 rather than -1.0 (YAML integers become floats before the check)."""
    if isinstance(value, float) and value.is_integer():
        return str(int(value))
    return repr(value)


def positive(value: float) -> str | None:
    """Strictly greater than zero."""
    return None if value > 0 else f"must be > 0, got {_show(value)}"


def non_negative(value: float) -> str | None:
    """Zero or more."""
    return None if value >= 0 else f"must be >= 0, got {_show(value)}"


def in_range(low: float, high: float, *, above_low: bool = False) -> Check:
    """Between low and high inclusive; with `above_low`, strictly above low (for limits that must not be zero)."""
    if above_low:

        def above(value: float) -> str | None:
            return (
                None if low < value <= high else f"must be > {_show(low)} and at most {_show(high)}, got {_show(value)}"
            )

        above.__doc__ = f"Above {_show(low)}, at most {_show(high)}."
        return above

    def check(value: float) -> str | None:
        return None if low <= value <= high else f"must be between {low} and {high}, got {_show(value)}"

    check.__doc__ = f"Between {low} and {high}."
    return check


def one_of(*choices: object) -> Check:
    """One of the listed values."""

    def check(value: object) -> str | None:
        return None if value in choices else f"must be one of {', '.join(map(str, choices))}, got {_show(value)}"

    return check


def each(inner: Check) -> Check:
    """Every element of a sequence passes `inner`."""

    def check(values: tuple[Any, ...]) -> str | None:
        for index, value in enumerate(values):
            problem = inner(value)
            if problem is not None:
                return f"element {index} {problem}"
        return None

    return check


def gpio_pin(value: int) -> str | None:
    """A Broadcom (BCM) GPIO number on the 40-pin header of a Raspberry Pi."""
    return None if 2 <= value <= 27 else f"must be a BCM GPIO number between 2 and 27, got {_show(value)}"


def port_number(value: int) -> str | None:
    """A TCP or UDP port."""
    return None if 1 <= value <= 65535 else f"must be a port between 1 and 65535, got {_show(value)}"


def ip_address(value: str) -> str | None:
    """An IPv4 or IPv6 address literal (host names are not resolved)."""
    try:
        ipaddress.ip_address(value)
    except ValueError:
        return f"must be an IP address such as 127.0.0.1, 0.0.0.0 or ::1, got {value!r}"
    return None


_HOST_LABEL = re.compile(r"(?!-)[A-Za-z0-9-]{1,63}(?<!-)")


def host(value: str) -> str | None:
    """An IP address, or a host name (which must not look like a dotted number)."""
    if ":" in value or re.fullmatch(r"[0-9.]+", value):  # written as an address: it must be a valid one
        try:
            ipaddress.ip_address(value)
        except ValueError:
            return f"must be a valid IP address or a host name, got {value!r}"
        return None
    labels = value.removesuffix(".").split(".")
    if len(value) > 253 or not all(_HOST_LABEL.fullmatch(label) for label in labels):
        return f"must be a valid IP address or a host name, got {value!r}"
    return None


def file_mode(value: str) -> str | None:
    """Octal permissions (3 or 4 digits) without setuid, setgid or sticky bits, not writable by every user."""
    if not re.fullmatch(r"[0-7]{3,4}", value):
        return f"must be octal permissions such as '0660', got {value!r}"
    mode = int(value, 8)
    if mode & 0o7000:
        return f"must not set the setuid, setgid or sticky bits, got {value!r}"
    if mode & 0o002:
        return f"must not be writable by every user (the last digit must be 0, 1, 4 or 5), got {value!r}"
    return None


# --- building -------------------------------------------------------------------------------------


def _type_name(tp: Any) -> str:
    origin = get_origin(tp)
    if tp is float:
        return "number"
    if tp is int:
        return "integer"
    if tp is bool:
        return "true or false"
    if tp is str:
        return "string"
    if origin is Literal:
        return " or ".join(repr(a) for a in get_args(tp))
    if origin in (types.UnionType, typing.Union):
        return " or ".join(_type_name(a) for a in get_args(tp))
    if origin is tuple:
        args = get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"list of {_type_name(args[0])}"
        return f"list of {len(args)} {_type_name(args[0])}s"
    if dataclasses.is_dataclass(tp):
        return "mapping"
    return str(tp)


def _convert(tp: Any, value: Any, path: str, problems: list[str]) -> Any:
    """Convert one YAML value to `tp`, appending problems; returns the value or None after a problem."""
    origin = get_origin(tp)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, Mapping):
            problems.append(f"{path}: expected a mapping, got {_describe(value)}")
            return None
        return _build(typing.cast(type[Any], tp), value, path, problems)
    if origin in (types.UnionType, typing.Union):
        for member in get_args(tp):
            trial: list[str] = []
            converted = _convert(member, value, path, trial)
            if not trial:
                return converted
        problems.append(f"{path}: expected {_type_name(tp)}, got {_describe(value)}")
        return None
    if origin is Literal:
        if value in get_args(tp) and type(value) is type(get_args(tp)[0]):
            return value
        problems.append(f"{path}: expected {_type_name(tp)}, got {_describe(value)}")
        return None
    if origin is tuple:
        args = get_args(tp)
        if not isinstance(value, list | tuple):
            problems.append(f"{path}: expected a {_type_name(tp)}, got {_describe(value)}")
            return None
        if len(args) == 2 and args[1] is Ellipsis:
            element_types = [args[0]] * len(value)
        elif len(value) != len(args):
            problems.append(f"{path}: expected a {_type_name(tp)}, got {len(value)} elements")
            return None
        else:
            element_types = list(args)
        start = len(problems)
        items = [
            _convert(t, v, f"{path}[{i}]", problems) for i, (t, v) in enumerate(zip(element_types, value, strict=True))
        ]
        return None if len(problems) > start else tuple(items)  # a bad element spoils the list: no check sees None
    if tp is bool:
        if isinstance(value, bool):
            return value
    elif tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif tp is float:
        if isinstance(value, int | float) and not isinstance(value, bool):
            if math.isfinite(value):
                return float(value)
            problems.append(f"{path}: must be a finite number, got {_show(value)}")
            return None
    elif tp is str and isinstance(value, str):
        return value
    problems.append(f"{path}: expected a {_type_name(tp)}, got {_describe(value)}")
    return None


def _describe(value: Any) -> str:
    if value is None:
        return "nothing (null)"
    kind = {bool: "boolean", int: "integer", float: "number", str: "string", list: "list", dict: "mapping"}
    return f"{kind.get(type(value), type(value).__name__)} {value!r}"


def _build(cls: type[T], raw: Mapping[Any, Any], path: str, problems: list[str], base: Any = None) -> T | None:
    """Build `cls` from `raw`; keys absent from `raw` keep their value in `base` (the section's real default)."""
    hints = typing.get_type_hints(cls)
    base = cls() if base is None else base
    fields = {f.name: f for f in dataclasses.fields(typing.cast(Any, cls)) if f.init}
    prefix = f"{path}." if path else ""
    start = len(problems)
    for key in raw:
        if not isinstance(key, str) or key not in fields:
            near = difflib.get_close_matches(str(key), fields, n=1, cutoff=0.6)
            hint = f" (did you mean '{near[0]}'?)" if near else f" (known keys: {', '.join(fields)})"
            problems.append(f"{prefix}{key}: unknown key{hint}")
    values: dict[str, Any] = {}
    for name, fld in fields.items():
        if name not in raw:
            continue
        tp = hints[name]
        if dataclasses.is_dataclass(tp) and isinstance(raw[name], Mapping):
            # a nested section starts from its own default (a wheel's pins), not from its class defaults
            converted = _build(typing.cast(type[Any], tp), raw[name], prefix + name, problems, getattr(base, name))
        else:
            converted = _convert(tp, raw[name], prefix + name, problems)
        if converted is None:
            continue
        check: Check | None = fld.metadata.get("check")
        problem = check(converted) if check is not None else None
        if problem is not None:
            problems.append(f"{prefix}{name}: {problem}")
            continue
        values[name] = converted
    if len(problems) > start:
        return None
    try:
        return dataclasses.replace(typing.cast(Any, base), **values)  # type: ignore[no-any-return]
    except ValueError as error:  # a section's __post_init__ cross-checks its fields
        problems.append(f"{path or '(top level)'}: {error}")
        return None


def build(cls: type[T], raw: Mapping[Any, Any]) -> T:
    """Build the dataclass `cls` from a parsed mapping, or raise ConfigError listing every problem."""
    problems: list[str] = []
    result = _build(cls, raw, "", problems)
    if result is None or problems:
        raise ConfigError(problems)
    return result


def build_fields(
    cls: type[T], raw: Mapping[Any, Any], path: str, base: T, names: tuple[str, ...]
) -> tuple[T, dict[str, str]]:
    """`base` with each of `names` found in `raw` that is valid on its own; the others keep `base`'s value.

    Returns the section and, per field that could not be used, its problem line. Keys outside `names` are not read
    at all, so a mistake elsewhere in the section cannot spoil the fields asked for.
    """
    values: dict[str, Any] = {}
    refused: dict[str, str] = {}
    for name in names:
        if name not in raw:
            continue
        problems: list[str] = []
        built = _build(cls, {name: raw[name]}, path, problems, base)
        if built is None or problems:
            refused[name] = problems[0] if problems else f"{path}.{name}: unusable"
        else:
            values[name] = getattr(built, name)
    return dataclasses.replace(typing.cast(Any, base), **values), refused


# --- documentation --------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Entry:
    """One documented key of the schema."""

    path: str
    type_name: str
    default: str
    doc: str


def entries(cls: type[Any], path: str = "", defaults: Any = None) -> Iterator[Entry | tuple[str, str]]:
    """Walk the schema: yields (path, doc) for a section, then an Entry per leaf key with its real default."""
    hints = typing.get_type_hints(cls)
    defaults = cls() if defaults is None else defaults  # a section's factory may override its class defaults
    for fld in dataclasses.fields(cls):
        dotted = f"{path}.{fld.name}" if path else fld.name
        tp = hints[fld.name]
        doc = fld.metadata.get("doc", "")
        if dataclasses.is_dataclass(tp):
            yield (dotted, doc)
            yield from entries(typing.cast(type[Any], tp), dotted, getattr(defaults, fld.name))
        else:
            default = getattr(defaults, fld.name)
            shown = "[" + ", ".join(map(str, default)) + "]" if isinstance(default, tuple) else repr(default)
            check = fld.metadata.get("check")
            rule = check.__doc__.strip() if check is not None and check.__doc__ else ""
            text = f"{doc} {rule}".strip() if rule and rule not in doc else doc
            yield Entry(dotted, _type_name(tp), shown, text)


def reference(cls: type[Any]) -> str:
    """The Markdown configuration reference of a schema: one table per section."""
    lines: list[str] = []
    table_open = False
    for item in entries(cls):
        if isinstance(item, tuple):
            lines += ["", f"### `{item[0]}`", "", item[1]]
            table_open = False
            continue
        if not table_open:  # a section holding only sub-sections gets no empty table
            lines += ["", "| key | type | default | meaning |", "|---|---|---|---|"]
            table_open = True
        doc = item.doc.replace("|", "\\|")
        lines.append(f"| `{item.path}` | {item.type_name} | `{item.default}` | {doc} |")
    return "\n".join(lines).strip() + "\n"
