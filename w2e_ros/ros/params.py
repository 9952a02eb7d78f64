"""Declare a node's parameters from a small dataclass and read them back into it.

Each node keeps its settings in one dataclass whose fields carry the type (annotation), the
default and a description (``field(metadata={"description": ...})`` or :func:`param`). The
parameters are declared once, with explicit types (a YAML ``5`` for a float parameter is an
error that names the parameter, not a silent int), and read into a new instance of the class.

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


def param(default: Any, description: str, *, read_only: bool = False,
          min: float | None = None, max: float | None = None) -> Any:  # noqa: A002
    """A dataclass field for a parameter: default, description and an optional numeric range."""
    meta = {"description": description, "read_only": read_only, "min": min, "max": max}
    if isinstance(default, list):
        return dataclasses.field(default_factory=lambda: list(default), metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


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

    Raises TypeError for a field type ROS parameters cannot hold, and rclpy's
    ``InvalidParameterTypeException`` / ``InvalidParameterValueException`` (which name the
    parameter) for an override of the wrong type or out of range.
    """
    if not dataclasses.is_dataclass(settings_cls):
        raise TypeError(f"{settings_cls!r} is not a dataclass")
    hints = typing.get_type_hints(settings_cls)
    values: dict[str, Any] = {}
    for f in dataclasses.fields(settings_cls):
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
        p = node.declare_parameter(name, initial, desc)
        values[f.name] = default if p.type_ == Parameter.Type.NOT_SET else p.value
        if ptype in (Parameter.Type.BOOL_ARRAY, Parameter.Type.INTEGER_ARRAY,
                     Parameter.Type.DOUBLE_ARRAY, Parameter.Type.STRING_ARRAY):
            values[f.name] = list(values[f.name])
    return settings_cls(**values)


def describe(settings: Any) -> str:
    """``name=value`` pairs of a settings instance, for one start-up log line."""
    fields = dataclasses.fields(settings)
    return ", ".join(f"{f.name}={getattr(settings, f.name)!r}" for f in fields)
