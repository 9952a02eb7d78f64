"""Declare a node's parameters from a small dataclass and read them back into it.

Each node keeps its settings in one dataclass whose fields carry the type (annotation), the
default and a description (``field(metadata={"description": ...})`` or :func:`param`). The
parameters are declared once, with explicit types, and read into a new instance of the class.
An integer given for a float parameter (YAML ``rate_hz: 5``, ``-p rate_hz:=5``, ``[1, 2]`` for
a float list) is taken as the float it means; any other type, or a value out of range, raises
:class:`ParameterError`, one line naming the parameter, the value and the type expected, which
:func:`w2e_ros.ros.spin.run_node` reports without a traceback.

    @dataclass
    class BridgeSettings:
        rate_hz: float = param(5.0, "camera cloud publishing rate (Hz)")

    self.settings = declare_typed_parameters(self, BridgeSettings)
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Any, TypeVar

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node
from rclpy.parameter import Parameter

T = TypeVar("T")

_TYPES: dict[Any, Parameter.Type] = {
    bool: Parameter.Type.BOOL,
    int: Parameter.Type.INTEGER,
    float: Parameter.Type.DOUBLE,
    str: Parameter.Type.STRING,
    list[bool]: Parameter.Type.BOOL_ARRAY,
    list[int]: Parameter.Type.INTEGER_ARRAY,
    list[float]: Parameter.Type.DOUBLE_ARRAY,
    list[str]: Parameter.Type.STRING_ARRAY,
}

# what a user reads in an error: the Python / YAML words, not ROS's enum names
_TYPE_WORDS: dict[Parameter.Type, str] = {
    Parameter.Type.NOT_SET: "not set",
    Parameter.Type.BOOL: "a bool",
    Parameter.Type.INTEGER: "an integer",
    Parameter.Type.DOUBLE: "a float",
    Parameter.Type.STRING: "a string",
    Parameter.Type.BYTE_ARRAY: "a byte array",
    Parameter.Type.BOOL_ARRAY: "a list of bools",
    Parameter.Type.INTEGER_ARRAY: "a list of integers",
    Parameter.Type.DOUBLE_ARRAY: "a list of floats",
    Parameter.Type.STRING_ARRAY: "a list of strings",
}
# an override of the key type is taken for a parameter of the value type, converted
_WIDENED = {
    (Parameter.Type.INTEGER, Parameter.Type.DOUBLE): float,
    (Parameter.Type.INTEGER_ARRAY, Parameter.Type.DOUBLE_ARRAY): lambda v: [float(x) for x in v],
}


class ParameterError(ValueError):
    """A parameter override a node cannot start with; the message is the one line to show."""

    def __init__(self, node: str, message: str) -> None:
        super().__init__(f"{node}: {message}")
        self.node = node  # fully qualified name, e.g. /robot1/segmentation
        self.message = message


def param(default: Any, description: str, *, read_only: bool = False,
          min: float | None = None, max: float | None = None) -> Any:  # noqa: A002
    """A dataclass field for a parameter: default, description and an optional numeric range."""
    meta = {"description": description, "read_only": read_only, "min": min, "max": max}
    if isinstance(default, list):
        return dataclasses.field(default_factory=lambda: list(default), metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def setting_param(config_cls: type, name: str, *, also: str = "",
                  min: float | None = None, max: float | None = None) -> Any:  # noqa: A002
    """A parameter that mirrors setting ``name`` of a core config dataclass
    (``w2e_ros.core.infra.settings``): the same name, default and description (``also`` appended),
    so the node, the CLI and the core agree by construction. The field's annotation must be
    the setting's type (checked when the parameters are declared); ``min`` / ``max``: the
    range this node accepts."""
    from w2e_ros.core.infra.settings import leaf_fields

    f, tp = leaf_fields(config_cls)[name]
    meta = {"description": f.metadata["help"] + also, "read_only": False, "min": min,
            "max": max, "setting": (config_cls.__name__, name, tp)}
    return dataclasses.field(default=f.default, metadata=meta)


def _descriptor(name: str, ptype: Parameter.Type, meta: typing.Mapping) -> ParameterDescriptor:
    d = ParameterDescriptor(
        name=name,
        type=ptype.value,
        description=str(meta.get("description", "")),
        read_only=bool(meta.get("read_only", False)),
    )
    lo, hi = meta.get("min"), meta.get("max")
    if lo is not None or hi is not None:
        if ptype == Parameter.Type.INTEGER:
            d.integer_range = [IntegerRange(
                from_value=int(lo if lo is not None else -(2**62)),
                to_value=int(hi if hi is not None else 2**62), step=0)]
        elif ptype == Parameter.Type.DOUBLE:
            d.floating_point_range = [FloatingPointRange(
                from_value=float(lo if lo is not None else -1e300),
                to_value=float(hi if hi is not None else 1e300), step=0.0)]
    return d


def declare_typed_parameters(node: Node, settings_cls: type[T], prefix: str = "") -> T:
    """Declare one parameter per field of the dataclass ``settings_cls`` and return an instance
    holding the values in effect (the parameter overrides, e.g. from the YAML, or defaults).

    Raises TypeError for a field type ROS parameters cannot hold (a programming error) and
    :class:`ParameterError` for an override of the wrong type or out of range (a user's).
    """
    if not dataclasses.is_dataclass(settings_cls):
        raise TypeError(f"{settings_cls!r} is not a dataclass")
    hints = typing.get_type_hints(settings_cls)
    values: dict[str, Any] = {}
    for f in dataclasses.fields(settings_cls):
        mirrored = f.metadata.get("setting")
        if mirrored and (mirrored[1] != f.name or mirrored[2] != hints[f.name]):
            raise TypeError(f"parameter {f.name!r} mirrors {mirrored[0]}.{mirrored[1]} "
                            f"({mirrored[2]!r}): same name and type expected")
        ptype = _TYPES.get(hints[f.name])
        if ptype is None:
            raise TypeError(f"parameter {f.name!r}: type {hints[f.name]!r} is not supported")
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            raise TypeError(f"parameter {f.name!r} needs a default")
        name = f"{prefix}{f.name}"
        desc = _descriptor(name, ptype, f.metadata)
        # an empty list has no type of its own: declare by type, fall back to the default
        initial = ptype if isinstance(default, list) and not default else default
        if isinstance(default, float) and ptype == Parameter.Type.DOUBLE:
            initial = float(default)
        p = _declare(node, name, initial, desc, ptype)
        values[f.name] = default if p.type_ == Parameter.Type.NOT_SET else p.value
        if ptype in (Parameter.Type.BOOL_ARRAY, Parameter.Type.INTEGER_ARRAY,
                     Parameter.Type.DOUBLE_ARRAY, Parameter.Type.STRING_ARRAY):
            values[f.name] = list(values[f.name])
    return settings_cls(**values)


def _declare(node: Node, name: str, initial: Any, desc: ParameterDescriptor,
             ptype: Parameter.Type) -> Parameter:
    """``node.declare_parameter`` that widens an integer override for a float parameter and
    turns a refused override into a :class:`ParameterError`.

    rclpy refuses an integer for a DOUBLE parameter and its exception does not carry the value
    as data, so the override is read back by declaring the name once without a type
    (``dynamic_typing``), undeclared, and declared again, typed, with the converted value in
    place of the override (``ignore_override``): public API only, the declared type stays
    DOUBLE.
    """
    try:
        return node.declare_parameter(name, initial, desc)
    except (InvalidParameterTypeException, InvalidParameterValueException) as err:
        refused = err
    probe = node.declare_parameter(name, None, ParameterDescriptor(dynamic_typing=True))
    given, gtype = probe.value, probe.type_
    node.undeclare_parameter(name)
    if gtype == Parameter.Type.NOT_SET:  # no override: the default itself was refused
        raise refused
    who = node.get_fully_qualified_name()
    if gtype != ptype:
        convert = _WIDENED.get((gtype, ptype))
        if convert is None:
            raise ParameterError(who, f"parameter {name!r} is {given!r} "
                                      f"({_TYPE_WORDS[gtype]}); expected {_TYPE_WORDS[ptype]}")
        given = convert(given)
        try:
            return node.declare_parameter(name, given, desc, ignore_override=True)
        except InvalidParameterValueException:
            pass
    raise ParameterError(who, f"parameter {name!r} is {given!r}; expected {_range_words(desc)}")


def _range_words(desc: ParameterDescriptor) -> str:
    """The range a descriptor allows, in words (the open ends :func:`_descriptor` fills in
    left out)."""
    for r, huge in ((desc.floating_point_range, 1e300), (desc.integer_range, 2**62)):
        if r:
            lo, hi = r[0].from_value, r[0].to_value
            if lo <= -huge:
                return f"a value <= {hi}"
            if hi >= huge:
                return f"a value >= {lo}"
            return f"a value in [{lo}, {hi}]"
    return "a valid value"


def describe(settings: Any) -> str:
    """``name=value`` pairs of a settings instance, for one start-up log line."""
    fields = dataclasses.fields(settings)
    return ", ".join(f"{f.name}={getattr(settings, f.name)!r}" for f in fields)
