"""One source per setting: a dataclass field carries its default and its help text once, and the
command line (and the ROS parameters, ``w2e_ros.ros.params.setting_param``) are made from it.

    @dataclass
    class FinetuneConfig:
        finetune_lr: float = setting(1e-3, "fine-tuning learning rate")

    add_arguments(parser, ExploreConfig)          # --finetune-lr, ... one flag per field
    cfg = from_namespace(ExploreConfig, parser.parse_args())

The flag is the field's name with dashes (``similarity_bar`` -> ``--similarity-bar``); a bool
is ``--name`` / ``--no-name``; a tuple or a list takes one value or more; a setting whose default
is ``REQUIRED`` is a required flag; a field holding another settings dataclass adds that one's
fields (their names are unique across the two). ``from_dict`` rebuilds a config from its
``asdict``, nested or flat (the flat form older results were written in).
"""

from __future__ import annotations

import argparse
import dataclasses
import types
import typing
from collections.abc import Callable, Collection, Mapping, Sequence
from typing import Any, TypeVar

T = TypeVar("T")

REQUIRED: Any = dataclasses.MISSING
"""The default of a setting that has none: the dataclass needs it, the flag is required."""


def setting(default: Any, help: str, *,  # noqa: A002
            choices: Sequence[str] | Callable[[], Sequence[str]] | None = None,
            min: float | None = None, max: float | None = None) -> Any:  # noqa: A002
    """A dataclass field for a setting: its default (or ``REQUIRED``), its help text (the CLI
    flag's help and the ROS parameter's description) and optionally the values or the range it
    allows. ``choices`` may be a function returning them, called when the flags are made (for
    values read from a file)."""
    if choices is not None and not callable(choices):
        choices = tuple(choices)
    meta = {"help": help, "choices": choices or None, "min": min, "max": max}
    if isinstance(default, (list, dict, set)):
        raise TypeError("a mutable default: use a tuple")
    return dataclasses.field(default=default, metadata=meta)


def choices_of(f: dataclasses.Field) -> tuple[str, ...] | None:
    """The values setting ``f`` allows (None: any)."""
    c = f.metadata.get("choices")
    return tuple(c() if callable(c) else c) if c else None


def flag(name: str) -> str:
    """The command-line flag of a field: its name with dashes."""
    return "--" + name.replace("_", "-")


def _fields(cls: type) -> list[tuple[dataclasses.Field, Any]]:
    hints = typing.get_type_hints(cls)
    return [(f, hints[f.name]) for f in dataclasses.fields(cls)]


def _nested(tp: Any) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def leaf_fields(cls: type) -> dict[str, tuple[dataclasses.Field, Any]]:
    """Every setting of ``cls`` by name, nested settings dataclasses opened (one level or
    more); a name used twice is an error, as it would be two flags of one name."""
    out: dict[str, tuple[dataclasses.Field, Any]] = {}
    for f, tp in _fields(cls):
        found = leaf_fields(tp) if _nested(tp) else {f.name: (f, tp)}
        twice = out.keys() & found.keys()
        if twice:
            raise TypeError(f"{cls.__name__}: setting {sorted(twice)} appears twice")
        out.update(found)
    return out


def _optional(tp: Any) -> Any:
    """``X`` of ``X | None``; other types as they are."""
    args = typing.get_args(tp)
    if typing.get_origin(tp) in (typing.Union, types.UnionType) and type(None) in args:
        rest = [a for a in args if a is not type(None)]
        if len(rest) == 1:
            return rest[0]
    return tp


def add_arguments(parser: argparse.ArgumentParser, cls: type, skip: Collection[str] = (),
                  only: Collection[str] | None = None) -> None:
    """One flag per setting of ``cls`` (nested dataclasses opened), but those in ``skip`` (and,
    given ``only``, those not in it): the type, default, choices and help of the field."""
    for name, (f, tp) in leaf_fields(cls).items():
        if name in skip or (only is not None and name not in only):
            continue
        tp = _optional(tp)
        kw: dict[str, Any] = {"help": f.metadata.get("help")}
        if f.default is REQUIRED:
            kw["required"] = True
        else:
            kw["default"] = f.default
        if tp is bool:
            kw["action"] = argparse.BooleanOptionalAction
        else:
            many = typing.get_origin(tp) in (tuple, list)  # one value or more, each checked
            kw["type"] = _ranged(typing.get_args(tp)[0] if many else tp,
                                 f.metadata.get("min"), f.metadata.get("max"))
            if many:
                kw["nargs"] = "+"
            if choices_of(f):
                kw["choices"] = list(choices_of(f))
        if kw["help"]:
            # BooleanOptionalAction adds its own; None: the help says what it means. The
            # field's default, not the parser's (a verb may set the parser's to None)
            if tp is not bool and kw.get("default") is not None:
                kw["help"] += f" (default: {_shown(kw['default'])})"
            kw["help"] = kw["help"].replace("%", "%%")  # argparse formats help with %
        parser.add_argument(flag(name), **kw)


def _shown(value: Any) -> str:
    """A default as it is typed on the command line."""
    if isinstance(value, (tuple, list)):
        return " ".join(map(str, value))
    return str(value)


def _ranged(tp: Any, lo: float | None, hi: float | None) -> Any:
    """``tp`` for argparse, refusing a value outside [lo, hi] with a one-line message."""
    if lo is None and hi is None:
        return tp

    def parse(text: str) -> Any:
        v = tp(text)
        if lo is not None and v < lo:
            raise argparse.ArgumentTypeError(f"must be at least {lo}, got {v}")
        if hi is not None and v > hi:
            raise argparse.ArgumentTypeError(f"must be at most {hi}, got {v}")
        return v

    parse.__name__ = tp.__name__  # argparse names the type in its "invalid ..." message
    return parse


def _build(cls: type[T], values: Mapping[str, Any]) -> T:
    kw: dict[str, Any] = {}
    for f, tp in _fields(cls):
        if _nested(tp):
            kw[f.name] = _build(tp, values)
        elif f.name in values:
            v = values[f.name]
            many = typing.get_origin(_optional(tp)) is tuple and v is not None
            kw[f.name] = tuple(v) if many else v
    return cls(**kw)


def from_namespace(cls: type[T], ns: argparse.Namespace, **overrides: Any) -> T:
    """``cls`` from parsed flags (a setting without a flag keeps its default); ``overrides``
    by setting name win over the flags."""
    names = leaf_fields(cls)
    unknown = overrides.keys() - names.keys()
    if unknown:
        raise TypeError(f"{cls.__name__} has no setting {sorted(unknown)}")
    values = {k: getattr(ns, k) for k in names if hasattr(ns, k)}
    return _build(cls, {**values, **overrides})


def flatten(d: Mapping[str, Any], cls: type) -> dict[str, Any]:
    """The settings of ``asdict(cls(...))`` (nested or flat) as one flat mapping by name."""
    out: dict[str, Any] = {}
    for f, tp in _fields(cls):
        if _nested(tp) and isinstance(d.get(f.name), Mapping):
            out.update(flatten(d[f.name], tp))
    out.update({k: v for k, v in d.items() if not isinstance(v, Mapping)})
    return out


def nest(flat: Mapping[str, Any], cls: type) -> dict[str, Any]:
    """``flat`` in the nesting of ``asdict(cls(...))``, holding only the settings it gives (no
    defaults filled in: an older file's record stays what it said); names ``cls`` lacks stay
    at the top."""
    def build(c: type) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for f, tp in _fields(c):
            if _nested(tp):
                if sub := build(tp):
                    out[f.name] = sub
            elif f.name in flat:
                out[f.name] = flat[f.name]
        return out

    known = leaf_fields(cls)
    return {**build(cls), **{k: v for k, v in flat.items() if k not in known}}


def from_dict(cls: type[T], d: Mapping[str, Any], renamed: Mapping[str, str] = {}) -> T:
    """``cls`` from its ``asdict``, nested or flat; ``renamed``: old name -> setting name for
    what older files stored under another name. Unknown keys are an error."""
    flat = {renamed.get(k, k): v for k, v in flatten(d, cls).items()}
    unknown = flat.keys() - leaf_fields(cls).keys()
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown settings {sorted(unknown)}")
    return _build(cls, flat)
