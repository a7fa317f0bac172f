"""Typed access to an object's parameters. Each getter marks what it reads;
every plugin ends with `finish`, which rejects any parameter left unread
(Mitsuba's "unreferenced property" rule)."""
from __future__ import annotations

import numpy as np

from dosppm_core.scene.mitsuba.colour import prop_rgb
from dosppm_core.scene.mitsuba.objects import Obj


def get_float(obj: Obj, name: str, default=None):
    prop = obj.take(name, ("float", "integer"))
    return default if prop is None else float(prop.value)


def get_int(obj: Obj, name: str, default=None):
    prop = obj.take(name, ("integer",))
    return default if prop is None else prop.value


def get_bool(obj: Obj, name: str, default=None):
    prop = obj.take(name, ("boolean",))
    return default if prop is None else prop.value


def get_str(obj: Obj, name: str, default=None):
    prop = obj.take(name, ("string",))
    return default if prop is None else prop.value


def get_point(obj: Obj, name: str, default=None):
    prop = obj.take(name, ("point", "vector"))
    return default if prop is None else prop.value


def get_matrix(obj: Obj, name: str = "to_world") -> np.ndarray:
    prop = obj.take(name, ("transform",))
    return np.eye(4) if prop is None else prop.value


def get_rgb(obj: Obj, name: str, default: float) -> tuple:
    prop = obj.take(name, ("rgb", "spectrum", "float", "integer"))
    return (default,) * 3 if prop is None else tuple(float(c) for c in prop_rgb(prop))


def required(obj: Obj, name: str, getter):
    value = getter(obj, name)
    if value is None:
        obj.node.fail(f"missing parameter {name!r}")
    return value


def finish(obj: Obj) -> None:
    """Mitsuba's rule: a parameter no plugin read is an error."""
    for prop in obj.props.values():
        if not prop.used:
            prop.node.fail(f"unsupported parameter of {obj.node.label}")
