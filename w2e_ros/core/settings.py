"""One source per setting: a dataclass field carries its default and its help text once, and the
command line (and the ROS parameters, ``w2e_ros.ros.params.setting_param``) are made from it.

    @dataclass
    class FinetuneConfig:
        finetune_lr: float = setting(1e-3, "fine-tuning learning rate")

    add_arguments(parser, ExploreConfig)          # --finetune-lr, ... one flag per field
    cfg = from_namespace(ExploreConfig, parser.parse_args())

The flag is the field's name with dashes (``similarity_bar`` -> ``--similarity-bar``); a bool
is ``--name`` / ``--no-name``; a field holding another settings dataclass adds that one's fields
(their names are unique across the two). ``from_dict`` rebuilds a config from its ``asdict``,
nested or flat (the flat form older results were written in).
"""

from __future__ import annotations

import argparse
import dataclasses
import typing
from collections.abc import Collection, Mapping, Sequence
from typing import Any, TypeVar

T = TypeVar("T")


def setting(default: Any, help: str, *, choices: Sequence[str] | None = None,  # noqa: A002
            min: float | None = None, max: float | None = None) -> Any:  # noqa: A002
    """A dataclass field for a setting: its default, its help text (the CLI flag's help and the
    ROS parameter's description) and optionally the values or the range it allows."""
    meta = {"help": help, "choices": tuple(choices) if choices else None, "min": min, "max": max}
    if isinstance(default, (list, dict, set)):
        raise TypeError("a mutable default: use a tuple")
    return dataclasses.field(default=default, metadata=meta)


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


def add_arguments(parser: argparse.ArgumentParser, cls: type,
                  skip: Collection[str] = ()) -> None:
    """One flag per setting of ``cls`` (nested dataclasses opened), but those in ``skip``:
    the type, default, choices and help of the field."""
    defaults = cls()
    for name, (f, tp) in leaf_fields(cls).items():
        if name in skip:
            continue
        default = _get(defaults, name)
        kw: dict[str, Any] = {"default": default, "help": f.metadata.get("help")}
        if tp is bool:
            kw["action"] = argparse.BooleanOptionalAction
        elif typing.get_origin(tp) is tuple:
            kw.update(type=typing.get_args(tp)[0], nargs="+")
        else:
            kw["type"] = _ranged(tp, f.metadata.get("min"), f.metadata.get("max"))
            if f.metadata.get("choices"):
                kw["choices"] = list(f.metadata["choices"])
        if kw["help"]:
            kw["help"] = kw["help"].replace("%", "%%")  # argparse formats help with %
            if tp is not bool:  # BooleanOptionalAction adds its own
                kw["help"] += " (default: %(default)s)"
        parser.add_argument(flag(name), **kw)


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


def _get(obj: Any, name: str) -> Any:
    """The value of setting ``name`` in ``obj`` or in one of its nested settings."""
    for f, tp in _fields(type(obj)):
        if f.name == name:
            return getattr(obj, name)
        if _nested(tp) and name in leaf_fields(tp):
            return _get(getattr(obj, f.name), name)
    raise AttributeError(name)


def _build(cls: type[T], values: Mapping[str, Any]) -> T:
    kw: dict[str, Any] = {}
    for f, tp in _fields(cls):
        if _nested(tp):
            kw[f.name] = _build(tp, values)
        elif f.name in values:
            v = values[f.name]
            kw[f.name] = tuple(v) if typing.get_origin(tp) is tuple else v
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


def from_dict(cls: type[T], d: Mapping[str, Any], renamed: Mapping[str, str] = {}) -> T:
    """``cls`` from its ``asdict``, nested or flat; ``renamed``: old name -> setting name for
    what older files stored under another name. Unknown keys are an error."""
    flat = {renamed.get(k, k): v for k, v in flatten(d, cls).items()}
    unknown = flat.keys() - leaf_fields(cls).keys()
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown settings {sorted(unknown)}")
    return _build(cls, flat)
