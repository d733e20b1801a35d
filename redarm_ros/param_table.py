"""The cores' parameters, declared once as data (``parameters.yaml``), and the classes built from it.

Every parameter of the reaching controller and of the arm's capsule model has one entry in
``redarm_ros/parameters.yaml``: its default, unit, bound and one-line meaning, in a section per
parameter class. :func:`declared` turns a
class that holds only an explanation (its docstring) and methods into a frozen dataclass with the
table's fields and defaults; its ``__post_init__`` checks every field against its bound (then runs the
class's own ``__post_init__``, for checks that are not a bound), and its docstring lists the fields.
Nested groups (``ControllerParams.heading`` ...) are fields too, so :func:`from_mapping` reads the
YAML form of any class without a hand-kept list of them.

``python -m redarm_ros.param_table`` prints the table as Markdown.

numpy-free and ROS-free: PyYAML, the standard library and :mod:`redarm_ros.errors` only, so every
core may build its parameter classes from the table.
"""

from __future__ import annotations

import inspect
import math
import sys
import textwrap
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import cache
from importlib import resources
from typing import Any, TypeVar

from redarm_ros.errors import ConfigError, InvalidInputError
from redarm_ros.yaml_safe import safe_load

#: The table, a data file of this package.
TABLE_FILE = "parameters.yaml"

#: The exceptions a section may name under ``error``.
ERRORS: dict[str, type[InvalidInputError]] = {"InvalidInputError": InvalidInputError,
                                               "ConfigError": ConfigError}

LINK_COUNT = 4  # capsule links: base, upper arm, forearm, hand

T = TypeVar("T")
Check = Callable[[Any], tuple[bool, Any]]  # value -> (accepted, value as stored)


@dataclass(frozen=True)
class Bound:
    """What a parameter accepts.

    ``word``: the table's name for it (``positive``, ``int_at_least``, ``choice``, ``group`` ...);
    ``arg``: its argument (least integer, choices, section of a nested group), if any; ``phrase``: what
    it asks for, as error messages say it; ``check``: value -> (accepted, the value as stored, e.g. a
    list as a tuple); ``type``: the field's annotation.
    """

    word: str
    arg: Any
    phrase: str
    check: Check
    type: Any


@dataclass(frozen=True)
class Param:
    """One row of the table: ``name``, ``default`` (None for a nested group), ``unit`` ("" if none),
    ``bound``, ``doc``."""

    name: str
    default: Any
    unit: str
    bound: Bound
    doc: str

    @property
    def group(self) -> str | None:
        """Section of the nested group this field holds, or None for a plain value."""
        return self.bound.arg if self.bound.word == "group" else None


@dataclass(frozen=True)
class Group:
    """One section of the table: ``section`` name, ``class_name``, the ``error`` a bad value raises and
    the ``params`` in declaration order."""

    section: str
    class_name: str
    error: type[InvalidInputError]
    params: tuple[Param, ...]

    def param(self, name: str) -> Param:
        """The row of ``name``.

        Raises:
            ConfigError: no such parameter in this section.
        """
        for p in self.params:
            if p.name == name:
                return p
        raise ConfigError(f"no parameter {name!r} in section {self.section!r}", field=name)


# ----------------------------------------------------------------------------------------------
# The bound vocabulary
# ----------------------------------------------------------------------------------------------


def _number(v: Any) -> bool:
    # bool is an int: accepted where a number is, as the hand-written checks did
    return isinstance(v, int | float)


def _integer(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _plain(test: Callable[[Any], bool]) -> Check:
    return lambda v: (test(v), v)


def _floats(n: int, least: float) -> Check:
    def check(v: Any) -> tuple[bool, Any]:
        try:
            out = tuple(float(x) for x in v)
        except (TypeError, ValueError):
            return False, v
        return len(out) == n and all(math.isfinite(x) and x >= least for x in out), out

    return check


def _links(v: Any) -> tuple[bool, Any]:
    try:
        out = tuple(v)
    except TypeError:
        return False, v
    return all(_integer(i) and 0 <= i < LINK_COUNT for i in out), out


_FIXED: dict[str, tuple[str, Check, Any]] = {
    "positive": ("finite and > 0", _plain(lambda v: _number(v) and math.isfinite(v) and v > 0), float),
    "nonnegative": ("finite and >= 0", _plain(lambda v: _number(v) and math.isfinite(v) and v >= 0), float),
    "finite": ("finite", _plain(lambda v: _number(v) and math.isfinite(v)), float),
    "unit_interval": ("in [0, 1]", _plain(lambda v: _number(v) and 0 <= v <= 1), float),
    "share": ("in (0, 1]", _plain(lambda v: _number(v) and 0 < v <= 1), float),
    "bool": ("a bool", _plain(lambda v: isinstance(v, bool)), bool),
    "integer": ("an integer", _plain(_integer), int),
    "int_positive": ("an integer >= 1", _plain(lambda v: _integer(v) and v >= 1), int),
    "int_nonnegative": ("an integer >= 0", _plain(lambda v: _integer(v) and v >= 0), int),
    "angles3": ("3 finite angles (rad)", _floats(3, -math.inf), tuple[float, float, float]),
    "lengths4": ("4 finite numbers >= 0", _floats(4, 0.0), tuple[float, float, float, float]),
    "links": (f"a sequence of link indices 0..{LINK_COUNT - 1}", _links, tuple[int, ...]),
}

#: Every word a bound may use; ``int_at_least``, ``range`` (two floats, a closed interval), ``choice``
#: and ``group`` take an argument.
BOUND_WORDS = (*_FIXED, "int_at_least", "range", "choice", "group")


def make_bound(spec: Any) -> Bound:
    """The bound of a table entry: a word (``positive``) or a one-key mapping (``{choice: [a, b]}``).

    Raises:
        ConfigError: unknown word or bad argument.
    """
    if isinstance(spec, str) and spec in _FIXED:
        phrase, check, typ = _FIXED[spec]
        return Bound(spec, None, phrase, check, typ)
    if isinstance(spec, Mapping) and len(spec) == 1:
        ((word, arg),) = spec.items()
        if word == "int_at_least" and _integer(arg):
            return Bound(word, arg, f"an integer >= {arg}", _plain(lambda v: _integer(v) and v >= arg), int)
        if word == "choice" and isinstance(arg, list) and arg and all(isinstance(c, str) for c in arg):
            choices = tuple(arg)
            return Bound(word, choices, f"one of {choices}", _plain(lambda v: v in choices), str)
        if word == "range" and isinstance(arg, list) and len(arg) == 2 and all(
                isinstance(x, float) and math.isfinite(x) for x in arg) and arg[0] < arg[1]:
            lo, hi = arg
            return Bound(word, (lo, hi), f"in [{lo:g}, {hi:g}]",
                         _plain(lambda v: _number(v) and lo <= v <= hi), float)
        if word == "group" and isinstance(arg, str):
            return Bound(word, arg, "a parameter group", lambda v: (True, v), Any)
    raise ConfigError(f"unknown bound {spec!r}; known: {list(BOUND_WORDS)}", value=spec)


# ----------------------------------------------------------------------------------------------
# Loading the table
# ----------------------------------------------------------------------------------------------

_ROW_KEYS = {"default", "unit", "bound", "doc"}
_GROUP_ROW_KEYS = {"bound", "doc"}


def _row(section: str, name: str, entry: Any) -> Param:
    where = f"{section}.{name}"
    if not isinstance(entry, Mapping) or "bound" not in entry:
        raise ConfigError(f"parameter table: {where} must be a mapping with a bound", field=where)
    bound = make_bound(entry["bound"])
    keys = _GROUP_ROW_KEYS if bound.word == "group" else _ROW_KEYS
    if set(entry) != keys:
        raise ConfigError(f"parameter table: {where} must have exactly the keys {sorted(keys)}, has "
                          f"{sorted(entry)}", field=where)
    if not isinstance(entry["doc"], str) or not entry["doc"].strip():
        raise ConfigError(f"parameter table: {where} needs a doc string", field=where)
    if bound.word == "group":
        return Param(name, None, "", bound, entry["doc"])
    default = entry["default"]
    ok, default = bound.check(default)
    # a float bound's default must be a float (YAML reads 1e-6 as a string and 30 as an int)
    if not ok or (bound.type is float and not isinstance(default, float)):
        raise ConfigError(f"parameter table: default of {where} ({entry['default']!r}) is not "
                          f"{bound.phrase}" + (" (write floats with a dot)" if bound.type is float else ""),
                          field=where, value=entry["default"])
    if not isinstance(entry["unit"], str):
        raise ConfigError(f"parameter table: unit of {where} must be a string", field=where)
    return Param(name, default, entry["unit"], bound, entry["doc"])


def load_table(text: str) -> dict[str, Group]:
    """Parse a parameter table (the YAML text of ``parameters.yaml``) into its sections.

    Raises:
        ConfigError: malformed table (the message names the entry).
    """
    raw = safe_load(text)
    if not isinstance(raw, Mapping):
        raise ConfigError("parameter table must be a mapping of sections")
    groups: dict[str, Group] = {}
    for section, body in raw.items():
        if not isinstance(body, Mapping) or not {"class", "params"} <= set(body) or \
                not set(body) <= {"class", "params", "error"} or not isinstance(body["params"], Mapping):
            raise ConfigError(f"parameter table: section {section!r} needs class and params (error optional)",
                              field=str(section))
        error = body.get("error", "InvalidInputError")
        if error not in ERRORS:
            raise ConfigError(f"parameter table: {section}.error must be one of {sorted(ERRORS)}",
                              field=f"{section}.error", value=error)
        params = tuple(_row(section, name, entry) for name, entry in body["params"].items())
        groups[section] = Group(section, str(body["class"]), ERRORS[error], params)
    for g in groups.values():
        for p in g.params:
            if p.group is not None and p.group not in groups:
                raise ConfigError(f"parameter table: {g.section}.{p.name} names an unknown section "
                                  f"{p.group!r}", field=f"{g.section}.{p.name}")
    return groups


@cache
def table() -> dict[str, Group]:
    """The package's parameter table (read once)."""
    return load_table(resources.files(__package__).joinpath(TABLE_FILE).read_text(encoding="utf-8"))


# ----------------------------------------------------------------------------------------------
# Classes from the table
# ----------------------------------------------------------------------------------------------

_CLASSES: dict[str, type] = {}


def group_class(section: str) -> type:
    """The class built from ``section`` (its module must have been imported).

    Raises:
        ConfigError: no class built from that section yet.
    """
    try:
        return _CLASSES[section]
    except KeyError:
        raise ConfigError(f"no parameter class built from section {section!r} yet (import its module "
                          "first)", field=section) from None


def group_of(cls: type) -> Group:
    """The table section a class was built from.

    Raises:
        ConfigError: ``cls`` was not built by :func:`declared`.
    """
    for section, c in _CLASSES.items():
        if c is cls:
            return table()[section]
    raise ConfigError(f"{getattr(cls, '__name__', cls)!r} is not built from the parameter table")


def validate(obj: Any, group: Group) -> None:
    """Check every field of ``obj`` against its bound and store it normalised (lists as tuples).

    Raises:
        InvalidInputError: (or the section's ``error``) naming class, field, bound and value.
    """
    for p in group.params:
        v = getattr(obj, p.name)
        ok, stored = p.bound.check(v)
        if not ok:
            raise group.error(f"{type(obj).__name__}.{p.name} must be {p.bound.phrase}, got {v!r}",
                              field=p.name, value=v)
        if stored is not v:
            object.__setattr__(obj, p.name, stored)


def _field_line(p: Param) -> str:
    if p.group is not None:
        return f"``{p.name}``: {p.doc}."
    unit = f" [{p.unit}]" if p.unit else ""
    return f"``{p.name}``{unit} = {p.default!r} ({p.bound.phrase}): {p.doc}."


def docstring(header: str | None, group: Group) -> str:
    """A class docstring: ``header`` followed by one line per field (name [unit] = default (bound): doc)."""
    lines = [inspect.cleandoc(header or group.class_name), "",
             f"Fields (declared in ``redarm_ros/{TABLE_FILE}``, section ``{group.section}``):", ""]
    lines += [textwrap.fill(f"- {_field_line(p)}", width=100, subsequent_indent="  ") for p in group.params]
    return "\n".join(lines) + "\n"


def declared(section: str) -> Callable[[type[T]], type[T]]:
    """Class decorator: make the class a frozen dataclass with the fields of table section ``section``.

    The class keeps its name, module, methods and explanation; it must not declare fields itself. A
    ``__post_init__`` it defines runs after the bound checks (for checks that are not a bound).

    Raises:
        ConfigError: the section names another class, or the class declares a field of its own.
    """

    def build(cls: type[T]) -> type[T]:
        group = table()[section]
        if cls.__name__ != group.class_name:
            raise ConfigError(f"section {section!r} declares {group.class_name}, not {cls.__name__}")
        own = cls.__dict__.get("__annotations__") or {}
        clash = [p.name for p in group.params if p.name in cls.__dict__] + list(own)
        if clash:
            raise ConfigError(f"{cls.__name__} declares {clash} itself; its fields come from the parameter "
                              "table", field=clash[0])
        annotations: dict[str, Any] = {}
        for p in group.params:
            if p.group is not None:
                annotations[p.name] = group_class(p.group)
                setattr(cls, p.name, field(default_factory=group_class(p.group)))
            else:
                annotations[p.name] = p.bound.type
                setattr(cls, p.name, p.default)
        cls.__annotations__ = annotations
        extra = cls.__dict__.get("__post_init__")

        def post_init(self: Any) -> None:
            validate(self, group)
            if extra is not None:
                extra(self)

        post_init.__name__ = "__post_init__"
        post_init.__qualname__ = f"{cls.__qualname__}.__post_init__"
        cls.__post_init__ = post_init  # type: ignore[attr-defined]
        cls.__doc__ = docstring(cls.__doc__, group)
        made = dataclass(frozen=True)(cls)
        _CLASSES[section] = made
        return made

    return build


def from_mapping(cls: type[T], d: Mapping[str, Any] | None, label: str) -> T:
    """An instance of a table-built class from its (YAML-like) mapping; nested mappings for nested
    groups; missing keys keep their defaults; lists become tuples. ``label`` names the mapping in
    messages (``"controller"``).

    Raises:
        ConfigError: not a mapping, an unknown key (at any depth) or a bad value; ``field`` is the
            dotted path of the offending key (``"speed.v_max"``).
    """
    if not d:
        return cls()
    if not isinstance(d, Mapping):
        raise ConfigError(f"{label} parameters must be a mapping", value=d)
    group = group_of(cls)
    known = [p.name for p in group.params]
    bad = sorted(str(k) for k in d if k not in known)
    if bad:
        raise ConfigError(f"unknown {label} parameter(s) {bad}; known: {sorted(known)}", field=bad[0])
    kwargs: dict[str, Any] = {}
    for key, value in d.items():
        sub = group.param(key).group
        if sub is None:
            kwargs[key] = tuple(value) if isinstance(value, list) else value
            continue
        if not isinstance(value, Mapping):
            raise ConfigError(f"{key} must be a mapping", field=key, value=value)
        try:
            kwargs[key] = from_mapping(group_class(sub), value, key)
        except ConfigError as exc:
            raise ConfigError(f"{key}: {exc}", field=f"{key}.{exc.field}", value=exc.value) from exc
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except InvalidInputError as exc:
        raise ConfigError(str(exc), field=exc.field, value=exc.value) from exc


# ----------------------------------------------------------------------------------------------
# The table as Markdown
# ----------------------------------------------------------------------------------------------


def markdown() -> str:
    """Every section of the table as a Markdown table (name, default, unit, bound, meaning)."""
    out: list[str] = []
    for g in table().values():
        out += [f"### `{g.section}` (`{g.class_name}`)", "", "| name | default | unit | bound | meaning |",
                "|---|---|---|---|---|"]
        for p in g.params:
            default = f"section `{p.group}`" if p.group else f"`{p.default!r}`"
            doc = p.doc.replace("|", "\\|")  # |x| in a meaning is not a column
            out.append(f"| `{p.name}` | {default} | {p.unit} | {p.bound.phrase} | {doc} |")
        out.append("")
    return "\n".join(out)


def main() -> int:
    """Print the table as Markdown (``python -m redarm_ros.param_table``)."""
    sys.stdout.write(markdown())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
