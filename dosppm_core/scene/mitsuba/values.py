"""Property values as Mitsuba reads them: numbers, points, colours, spectra
and transforms (each operation left-multiplies the ones before it)."""
from __future__ import annotations

import math
import re

import numpy as np

from dosppm_core.scene.mitsuba.xmltree import Node, check_attrs


def tokens(text: str) -> list:
    return [t for t in re.split(r"[,\s]+", text.strip()) if t]


def to_float(node: Node, text: str) -> float:
    try:
        return float(text)
    except ValueError:
        node.fail(f"not a number: {text!r}")


def numbers(node: Node, text: str, counts) -> np.ndarray:
    values = np.array([to_float(node, t) for t in tokens(text)])
    if values.size not in counts:
        node.fail(f"expected {' or '.join(map(str, counts))} numbers, got {text!r}")
    return values


def xyz(node: Node, default: float, extra=()) -> np.ndarray:
    """x/y/z attributes, or one `value` of 1 or 3 numbers, as Mitsuba reads
    points, vectors, translate, scale and rotate axes."""
    check_attrs(node, {"value", "x", "y", "z", *extra})
    attrib = node.attrib
    if "value" in attrib:
        if any(k in attrib for k in "xyz"):
            node.fail("cannot mix 'value' with 'x'/'y'/'z'")
        return np.broadcast_to(numbers(node, attrib["value"], (1, 3)), (3,)).copy()
    return np.array([to_float(node, attrib[k]) if k in attrib else default for k in "xyz"])


def read_spectrum(node: Node, text: str):
    """('constant', v) or ('pairs', wavelengths, values)."""
    parts = tokens(text)
    if len(parts) == 1 and ":" not in parts[0]:
        return ("constant", to_float(node, parts[0]))
    pairs = [t.split(":") for t in parts]
    if len(pairs) < 2 or any(len(p) != 2 for p in pairs):
        node.fail("expected one number or at least two wavelength:value pairs")
    wavelengths = np.array([to_float(node, p[0]) for p in pairs])
    if np.any(np.diff(wavelengths) <= 0):
        node.fail("wavelengths must increase")
    return ("pairs", wavelengths, np.array([to_float(node, p[1]) for p in pairs]))


def read_value(node: Node):
    """The value of a <float>, <integer>, <boolean>, <string>, <point>,
    <vector>, <rgb> or <spectrum> element."""
    if node.tag in ("point", "vector"):
        check_attrs(node, {"name", "value", "x", "y", "z"}, required=("name",))
        return xyz(node, 0.0, extra=("name",))
    check_attrs(node, {"name", "value"}, required=("name", "value"))
    text = node.attrib["value"]
    if node.tag == "float":
        return to_float(node, text)
    if node.tag == "integer":
        try:
            return int(text)
        except ValueError:
            node.fail(f"not an integer: {text!r}")
    if node.tag == "boolean":
        if text.strip().lower() not in ("true", "false"):
            node.fail(f"expected true or false, got {text!r}")
        return text.strip().lower() == "true"
    if node.tag == "rgb":
        return np.broadcast_to(numbers(node, text, (1, 3)), (3,)).copy()
    if node.tag == "spectrum":
        return read_spectrum(node, text)
    return text                                  # string


# -- transforms ------------------------------------------------------------------

def rotation(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    """Mitsuba 3's `Transform4f::rotate`, which does not normalise the axis:
    a non-unit axis skews, in Mitsuba and here alike."""
    x, y, z = axis
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    cross = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    m = np.eye(4)
    m[:3, :3] = c * np.eye(3) + s * cross + (1 - c) * np.outer((x, y, z), (x, y, z))
    return m


def coordinate_system(n: np.ndarray) -> np.ndarray:
    """Mitsuba's `coordinate_system` (Duff et al. 2017): the up vector a
    lookat without `up` gets."""
    sign = math.copysign(1.0, n[2])
    a = -1.0 / (sign + n[2])
    return np.array([n[0] * n[0] * a * sign + 1, n[0] * n[1] * a * sign, -n[0] * sign])


def lookat(op: Node) -> np.ndarray:
    check_attrs(op, {"origin", "target", "up"}, required=("origin", "target"))
    origin, target = (numbers(op, op.attrib[k], (3,)) for k in ("origin", "target"))
    up = numbers(op, op.attrib["up"], (3,)) if "up" in op.attrib else np.zeros(3)
    forward = target - origin
    if not np.any(forward):
        op.fail("target equals origin")
    forward /= np.linalg.norm(forward)
    if not np.any(up):
        up = coordinate_system(forward)
    left = np.cross(up, forward)
    if np.linalg.norm(left) < 1e-12:
        op.fail("up is parallel to the viewing direction")
    left /= np.linalg.norm(left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, np.cross(forward, left), forward, origin
    return m


def matrix_op(op: Node) -> np.ndarray:
    check_attrs(op, {"value"}, required=("value",))
    values = numbers(op, op.attrib["value"], (9, 16))
    if values.size == 16:
        return values.reshape(4, 4)
    m = np.eye(4)
    m[:3, :3] = values.reshape(3, 3)
    return m


def transform_op(op: Node) -> np.ndarray:
    """The 4x4 matrix of one operation inside a <transform>."""
    m = np.eye(4)
    if op.tag == "translate":
        m[:3, 3] = xyz(op, 0.0)
    elif op.tag == "scale":
        m[:3, :3] = np.diag(xyz(op, 1.0))
    elif op.tag == "rotate":
        axis = xyz(op, 0.0, extra=("angle",))
        if "angle" not in op.attrib or not np.any(axis):
            op.fail("needs an angle and a non-zero axis")
        m = rotation(axis, to_float(op, op.attrib["angle"]))
    elif op.tag == "matrix":
        m = matrix_op(op)
    elif op.tag == "lookat":
        m = lookat(op)
    else:
        op.fail("a <transform> holds only translate, rotate, scale, matrix and lookat")
    if not np.all(np.isfinite(m)):
        op.fail("transform is not finite")
    return m
