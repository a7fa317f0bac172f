"""Import a subset of Mitsuba 3's scene XML (and Nori's dialect of it).

`load_mitsuba_xml(path, **defaults)` reads a scene file and its includes and
feeds `SceneBuilder`. Anything outside the subset below is a `SceneError`
whose one line names ``file:line`` and the element, for example
``cbox.xml:42: <bsdf type="plastic">: unsupported plugin``: nothing is
silently dropped, in the spirit of Mitsuba's "unreferenced property" errors.

==========  ================================================================
element     plugins and parameters understood
==========  ================================================================
scene       ``version``; ``<default name value>`` and ``$name`` (keyword
            arguments override defaults; an unused keyword is an error);
            ``<include filename>``; ``id`` on any object, ``<ref id>``
shape       obj, ply (filename, face_normals); rectangle; cube; sphere
            (center, radius; an icosphere of 20,480 triangles); all take
            to_world and flip_normals
bsdf        diffuse (reflectance); twosided (one nested BSDF);
            conductor (material="none", specular_reflectance) -> mirror;
            roughconductor (distribution="ggx", alpha or alpha_u = alpha_v,
            material="none", specular_reflectance, sample_visible) -> glossy;
            dielectric (int_ior, ext_ior as numbers or Mitsuba's names;
            specular_reflectance equal to specular_transmittance) -> glass
emitter     area (radiance) in a shape or referenced by one; point (position
            or to_world, intensity); spot (to_world, intensity,
            cutoff_angle, beam_width)
sensor      perspective, thinlens (fov or focal_length, fov_axis, to_world,
            near_clip, far_clip, focus_distance, aperture_radius); film
            hdrfilm (width, height, pixel_format, rfilter); sampler
            (sample_count, seed)
integrator  path, volpath, volpathmis, ptracer, direct (max_depth, rr_depth,
            hide_emitters)
values      float, integer, boolean, string, point, vector, rgb, spectrum
            (constant or wavelength:value pairs); transform of translate,
            rotate, scale, matrix, lookat (each applied after the previous)
==========  ================================================================

What `Scene` cannot hold (integrator, max_depth, spp, far_clip, film filter,
pixel format) lands in ``scene.render_settings``, a dict with only the keys
the file sets.

Decisions:

* Colours are converted exactly as Mitsuba 3's RGB variants (`scalar_rgb`)
  do (xml.cpp, ``create_texture_from_spectrum``): wavelength:value pairs are
  integrated against the CIE 1931 curves (1,000 samples over 360-830 nm) and
  mapped to linear sRGB; reflectances are weighted by the D65 illuminant and
  clamped to [0, 1], emission is not weighted and only clamped at 0. A
  constant spectrum is grey for a reflectance but ``value * xyz_to_srgb(1,
  1, 1)`` (slightly purple) for an emitter; RGB is taken as is.
* roughconductor accepts only GGX. Mitsuba's default is Beckmann, so a file
  must say ``<string name="distribution" value="ggx"/>``: swapping the lobe
  silently would make comparisons against Mitsuba disagree.
* The front of a surface is its triangle winding (counter-clockwise), which
  emission and one-sided BSDFs use, and flip_normals reverses. Under a
  mirroring to_world Mitsuba keeps the front of rectangles and cubes outward
  (so we rewind them) while spheres and meshes turn. Per-vertex normals in
  OBJ/PLY files are ignored: Mitsuba would orient by them, and every shared
  scene has them agreeing with the winding.
* Nori's XML (no ``version``, ``<mesh>``, ``<camera>``, ``<color>``) is
  cheap to support and is: it is rewritten to the Mitsuba elements it means
  (camelCase names, albedo, mirror, a film for width/height, the top-level
  sampler) and read by the same code. Nori's image x axis runs opposite to
  Mitsuba's, so a Nori camera gets ``scale(-1, 1, 1)`` applied first; Nori's
  defaults (fov 30, 1280x720, grey BSDF on emitters) are kept.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import os
import re
import warnings
from dataclasses import dataclass, field
from typing import NoReturn
from xml.parsers import expat

import numpy as np

from dosppm_core.scene.model import Camera, Material, Scene, SceneBuilder, SceneError

# ---------------------------------------------------------------------------
# XML elements with their source location


@dataclass(eq=False)
class _Node:
    """One XML element and where it was written."""
    tag: str
    attrib: dict
    file: str
    line: int
    label: str                      # the start tag as written, for messages
    children: list = field(default_factory=list)

    def fail(self, message: str) -> NoReturn:
        raise SceneError(f"{self.file}:{self.line}: {self.label}: {message}")


def _start_tag(tag: str, attrib: dict) -> str:
    shown = "".join(f' {k}="{attrib[k]}"' for k in ("type", "name", "id", "filename") if k in attrib)
    return f"<{tag}{shown}>"


def _synthetic(tag: str, attrib: dict, origin: _Node) -> _Node:
    """An element the Nori rewrite adds; errors point at `origin`."""
    return _Node(tag, attrib, origin.file, origin.line, origin.label)


def _parse_xml(path: str) -> _Node:
    """Parse one file; expat gives the line of every start tag."""
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError as exc:
        raise SceneError(f"{path}: cannot read: {exc.strerror}") from None
    parser = expat.ParserCreate()
    stack = [_Node("#document", {}, path, 0, "")]

    def start(tag, attrib):
        node = _Node(tag, dict(attrib), path, parser.CurrentLineNumber, _start_tag(tag, attrib))
        stack[-1].children.append(node)
        stack.append(node)

    def text(data):
        if data.strip():
            raise SceneError(f"{path}:{parser.CurrentLineNumber}: {stack[-1].label}: "
                             f"unexpected text {data.strip()[:30]!r}")

    parser.StartElementHandler = start
    parser.EndElementHandler = lambda tag: stack.pop()
    parser.CharacterDataHandler = text
    try:
        parser.Parse(data, True)
    except expat.ExpatError as exc:
        raise SceneError(f"{path}:{exc.lineno}: malformed XML: {expat.ErrorString(exc.code)}") from None
    return stack[0].children[0]


def _walk(node: _Node):
    yield node
    for child in node.children:
        yield from _walk(child)


def _no_children(node: _Node) -> None:
    if node.children:
        node.children[0].fail(f"cannot occur inside {node.label}")


def _check_attrs(node: _Node, allowed, required=()) -> None:
    for key in node.attrib:
        if key not in allowed:
            node.fail(f"unsupported attribute {key!r}")
    for key in required:
        if key not in node.attrib:
            node.fail(f"missing attribute {key!r}")


def _resolve(node: _Node, filename: str, root_dir: str) -> str:
    """A relative name is looked up beside the file that names it, then beside
    the main file (Mitsuba's resolver: cbox-rgb.xml's fragments name meshes/
    relative to the main file)."""
    candidates = [filename] if os.path.isabs(filename) else [
        os.path.join(os.path.dirname(node.file), filename), os.path.join(root_dir, filename)]
    for path in candidates:
        if os.path.isfile(path):
            return path
    node.fail(f"file {filename!r} not found")


# ---------------------------------------------------------------------------
# Values


def _tokens(text: str) -> list:
    return [t for t in re.split(r"[,\s]+", text.strip()) if t]


def _to_float(node: _Node, text: str) -> float:
    try:
        return float(text)
    except ValueError:
        node.fail(f"not a number: {text!r}")


def _numbers(node: _Node, text: str, counts) -> np.ndarray:
    values = np.array([_to_float(node, t) for t in _tokens(text)])
    if values.size not in counts:
        node.fail(f"expected {' or '.join(map(str, counts))} numbers, got {text!r}")
    return values


def _xyz(node: _Node, default: float, extra=()) -> np.ndarray:
    """x/y/z attributes, or one `value` of 1 or 3 numbers, as Mitsuba reads
    points, vectors, translate, scale and rotate axes."""
    _check_attrs(node, {"value", "x", "y", "z", *extra})
    attrib = node.attrib
    if "value" in attrib:
        if any(k in attrib for k in "xyz"):
            node.fail("cannot mix 'value' with 'x'/'y'/'z'")
        return np.broadcast_to(_numbers(node, attrib["value"], (1, 3)), (3,)).copy()
    return np.array([_to_float(node, attrib[k]) if k in attrib else default for k in "xyz"])


def _read_spectrum(node: _Node, text: str):
    """('constant', v) or ('pairs', wavelengths, values)."""
    tokens = _tokens(text)
    if len(tokens) == 1 and ":" not in tokens[0]:
        return ("constant", _to_float(node, tokens[0]))
    pairs = [t.split(":") for t in tokens]
    if len(pairs) < 2 or any(len(p) != 2 for p in pairs):
        node.fail("expected one number or at least two wavelength:value pairs")
    wavelengths = np.array([_to_float(node, p[0]) for p in pairs])
    if np.any(np.diff(wavelengths) <= 0):
        node.fail("wavelengths must increase")
    return ("pairs", wavelengths, np.array([_to_float(node, p[1]) for p in pairs]))


def _read_value(node: _Node):
    if node.tag in ("point", "vector"):
        _check_attrs(node, {"name", "value", "x", "y", "z"}, required=("name",))
        return _xyz(node, 0.0, extra=("name",))
    _check_attrs(node, {"name", "value"}, required=("name", "value"))
    text = node.attrib["value"]
    if node.tag == "float":
        return _to_float(node, text)
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
        return np.broadcast_to(_numbers(node, text, (1, 3)), (3,)).copy()
    if node.tag == "spectrum":
        return _read_spectrum(node, text)
    return text                                  # string


# ---------------------------------------------------------------------------
# Transforms: each operation left-multiplies the ones before it, as in Mitsuba


def _rotation(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    """Mitsuba 3's `Transform4f::rotate`, which does not normalise the axis:
    a non-unit axis skews, in Mitsuba and here alike."""
    x, y, z = axis
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    cross = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    m = np.eye(4)
    m[:3, :3] = c * np.eye(3) + s * cross + (1 - c) * np.outer((x, y, z), (x, y, z))
    return m


def _coordinate_system(n: np.ndarray) -> np.ndarray:
    """Mitsuba's `coordinate_system` (Duff et al. 2017): the up vector a
    lookat without `up` gets."""
    sign = math.copysign(1.0, n[2])
    a = -1.0 / (sign + n[2])
    return np.array([n[0] * n[0] * a * sign + 1, n[0] * n[1] * a * sign, -n[0] * sign])


def _lookat(op: _Node) -> np.ndarray:
    _check_attrs(op, {"origin", "target", "up"}, required=("origin", "target"))
    origin, target = (_numbers(op, op.attrib[k], (3,)) for k in ("origin", "target"))
    up = _numbers(op, op.attrib["up"], (3,)) if "up" in op.attrib else np.zeros(3)
    forward = target - origin
    if not np.any(forward):
        op.fail("target equals origin")
    forward /= np.linalg.norm(forward)
    if not np.any(up):
        up = _coordinate_system(forward)
    left = np.cross(up, forward)
    if np.linalg.norm(left) < 1e-12:
        op.fail("up is parallel to the viewing direction")
    left /= np.linalg.norm(left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, np.cross(forward, left), forward, origin
    return m


def _matrix_op(op: _Node) -> np.ndarray:
    _check_attrs(op, {"value"}, required=("value",))
    values = _numbers(op, op.attrib["value"], (9, 16))
    if values.size == 16:
        return values.reshape(4, 4)
    m = np.eye(4)
    m[:3, :3] = values.reshape(3, 3)
    return m


def _transform_op(op: _Node) -> np.ndarray:
    m = np.eye(4)
    if op.tag == "translate":
        m[:3, 3] = _xyz(op, 0.0)
    elif op.tag == "scale":
        m[:3, :3] = np.diag(_xyz(op, 1.0))
    elif op.tag == "rotate":
        axis = _xyz(op, 0.0, extra=("angle",))
        if "angle" not in op.attrib or not np.any(axis):
            op.fail("needs an angle and a non-zero axis")
        m = _rotation(axis, _to_float(op, op.attrib["angle"]))
    elif op.tag == "matrix":
        m = _matrix_op(op)
    elif op.tag == "lookat":
        m = _lookat(op)
    else:
        op.fail("a <transform> holds only translate, rotate, scale, matrix and lookat")
    if not np.all(np.isfinite(m)):
        op.fail("transform is not finite")
    return m


# ---------------------------------------------------------------------------
# Spectra to linear sRGB, as Mitsuba 3's RGB variants do

# CIE 1931 2-degree colour matching functions and the D65 illuminant, 360 to
# 830 nm every 5 nm (the tables Mitsuba 3 interpolates linearly).
_CIE_X = """
    1.299e-04 2.321e-04 4.149e-04 7.416e-04 0.001368 0.002236 0.004243 0.00765 0.01431
    0.02319 0.04351 0.07763 0.13438 0.21477 0.2839 0.3285 0.34828 0.34806 0.3362 0.3187
    0.2908 0.2511 0.19536 0.1421 0.09564 0.05795001 0.03201 0.0147 0.0049 0.0024 0.0093
    0.0291 0.06327 0.1096 0.1655 0.2257499 0.2904 0.3597 0.4334499 0.5120501 0.5945
    0.6784 0.7621 0.8425 0.9163 0.9786 1.0263 1.0567 1.0622 1.0456 1.0026 0.9384
    0.8544499 0.7514 0.6424 0.5419 0.4479 0.3608 0.2835 0.2187 0.1649 0.1212 0.0874
    0.0636 0.04677 0.0329 0.0227 0.01584 0.01135916 0.008110916 0.005790346 0.004109457
    0.002899327 0.00204919 0.001439971 9.999493e-04 6.900786e-04 4.760213e-04
    3.323011e-04 2.348261e-04 1.661505e-04 1.17413e-04 8.307527e-05 5.870652e-05
    4.150994e-05 2.935326e-05 2.067383e-05 1.455977e-05 1.025398e-05 7.221456e-06
    5.085868e-06 3.581652e-06 2.522525e-06 1.776509e-06 1.251141e-06
"""
_CIE_Y = """
    3.917e-06 6.965e-06 1.239e-05 2.202e-05 3.9e-05 6.4e-05 1.2e-04 2.17e-04 3.96e-04
    6.4e-04 0.00121 0.00218 0.004 0.0073 0.0116 0.01684 0.023 0.0298 0.038 0.048 0.06
    0.0739 0.09098 0.1126 0.13902 0.1693 0.20802 0.2586 0.323 0.4073 0.503 0.6082 0.71
    0.7932 0.862 0.9148501 0.954 0.9803 0.9949501 1 0.995 0.9786 0.952 0.9154 0.87
    0.8163 0.757 0.6949 0.631 0.5668 0.503 0.4412 0.381 0.321 0.265 0.217 0.175 0.1382
    0.107 0.0816 0.061 0.04458 0.032 0.0232 0.017 0.01192 0.00821 0.005723 0.004102
    0.002929 0.002091 0.001484 0.001047 7.4e-04 5.2e-04 3.611e-04 2.492e-04 1.719e-04
    1.2e-04 8.48e-05 6e-05 4.24e-05 3e-05 2.12e-05 1.499e-05 1.06e-05 7.4657e-06
    5.2578e-06 3.7029e-06 2.6078e-06 1.8366e-06 1.2934e-06 9.1093e-07 6.4153e-07
    4.5181e-07
"""
_CIE_Z = """
    6.061e-04 0.001086 0.001946 0.003486 0.006450001 0.01054999 0.02005001 0.03621
    0.06785001 0.1102 0.2074 0.3713 0.6456 1.0390501 1.3856 1.62296 1.74706 1.7826
    1.77211 1.7441 1.6692 1.5281 1.28764 1.0419 0.8129501 0.6162 0.46518 0.3533 0.272
    0.2123 0.1582 0.1117 0.07824999 0.05725001 0.04216 0.02984 0.0203 0.0134 0.008749999
    0.005749999 0.0039 0.002749999 0.0021 0.0018 0.001650001 0.0014 0.0011 0.001 8e-04
    6e-04 3.4e-04 2.4e-04 1.9e-04 1e-04 4.999999e-05 3e-05 2e-05 1e-05
""" + " 0" * 37
_D65 = """
    46.6383 49.3637 52.0891 51.0323 49.9755 52.3118 54.6482 68.7015 82.7549 87.1204
    91.486 92.4589 93.4318 90.057 86.6823 95.7736 104.865 110.936 117.008 117.41 117.812
    116.336 114.861 115.392 115.923 112.367 108.811 109.082 109.354 108.578 107.802
    106.296 104.79 106.239 107.689 106.047 104.405 104.225 104.046 102.023 100 98.1671
    96.3342 96.0611 95.788 92.2368 88.6856 89.3459 90.0062 89.8026 89.5991 88.6489
    87.6987 85.4936 83.2886 83.4939 83.6992 81.863 80.0268 80.1207 80.2146 81.2462
    82.2778 80.281 78.2842 74.0027 69.7213 70.6652 71.6091 72.979 74.349 67.9765 61.604
    65.7448 69.8856 72.4863 75.087 69.3398 63.5927 55.0054 46.4182 56.6118 66.8054
    65.0941 63.3828 63.8434 64.304 61.8779 59.4519 55.7054 51.959 54.6998 57.4406
    58.8765 60.3125
"""
_CIE_MIN, _CIE_MAX = 360.0, 830.0
_CIE_Y_NORMALIZATION = 1.0 / 106.7502593994140625     # MI_CIE_Y_NORMALIZATION
_D65_NORMALIZATION = 0.010101273599490354               # MI_CIE_D65_NORMALIZATION
_XYZ_TO_SRGB = np.array([[3.240479, -1.537150, -0.498535],
                         [-0.969256, 1.875991, 0.041556],
                         [0.055648, -0.204043, 1.057311]])


@functools.lru_cache(maxsize=1)
def _cie_tables():
    """(wavelengths, xyz (95, 3), d65 (95,)), as float32 like Mitsuba's."""
    def parse(text):
        return np.array(text.split(), dtype=np.float32).astype(np.float64)
    xyz = np.stack([parse(_CIE_X), parse(_CIE_Y), parse(_CIE_Z)], axis=1)
    return np.arange(_CIE_MIN, _CIE_MAX + 1, 5.0), xyz, parse(_D65) * _D65_NORMALIZATION


def _spectrum_to_srgb(wavelengths, values, emission: bool) -> np.ndarray:
    """Mitsuba's `spectrum_list_to_srgb`: 1,000 samples of 360-830 nm, the
    spectrum linear between its points and zero outside them; reflectances
    are weighted by D65 so a flat 1 maps to white, as in spectral variants."""
    table_wl, cie, d65 = _cie_tables()
    samples = _CIE_MIN + np.arange(1000) / 999 * (_CIE_MAX - _CIE_MIN)
    samples = samples[(samples >= wavelengths[0]) & (samples <= wavelengths[-1])]
    weight = np.interp(samples, wavelengths, values)
    if not emission:
        weight = weight * np.interp(samples, table_wl, d65)
    cmf = np.stack([np.interp(samples, table_wl, cie[:, k]) for k in range(3)], axis=1)
    xyz = (cmf * weight[:, None]).sum(axis=0) * (_CIE_MAX - _CIE_MIN) / 1000 * _CIE_Y_NORMALIZATION
    return _XYZ_TO_SRGB @ xyz


def _prop_rgb(prop) -> np.ndarray:
    """The RGB a colour property becomes; `in_emitter` is Mitsuba's
    `within_emitter` (the property is a direct child of an <emitter>)."""
    if prop.kind in ("float", "integer"):
        return np.full(3, float(prop.value))
    if prop.kind == "rgb":
        return prop.value                      # 'srgb' and 'd65' textures return it in RGB modes
    if prop.value[0] == "constant":
        v = prop.value[1]
        # A flat emission spectrum is not white under sRGB's D65 white point.
        return v * _XYZ_TO_SRGB.sum(axis=1) if prop.in_emitter else np.full(3, v)
    rgb = _spectrum_to_srgb(prop.value[1], prop.value[2], prop.in_emitter)
    clipped = np.clip(rgb, 0.0, np.inf if prop.in_emitter else 1.0)
    if np.any(clipped != rgb):
        warnings.warn(f"{prop.node.file}:{prop.node.line}: {prop.node.label}: spectrum maps to "
                      f"{np.round(rgb, 4)} outside the sRGB gamut; clamped as Mitsuba does", stacklevel=2)
    return clipped


# Mitsuba's named indices of refraction (include/mitsuba/render/ior.h).
_IORS = {
    "vacuum": 1.0, "helium": 1.000036, "hydrogen": 1.000132, "air": 1.000277,
    "carbon dioxide": 1.00045, "water": 1.3330, "acetone": 1.36, "ethanol": 1.361,
    "carbon tetrachloride": 1.461, "glycerol": 1.4729, "benzene": 1.501,
    "silicone oil": 1.52045, "bromine": 1.661, "water ice": 1.31, "fused quartz": 1.458,
    "pyrex": 1.470, "acrylic glass": 1.49, "polypropylene": 1.49, "bk7": 1.5046,
    "sodium chloride": 1.544, "amber": 1.55, "pet": 1.575, "diamond": 2.419,
}

# ---------------------------------------------------------------------------
# Object tree: XML with $parameters substituted, includes spliced, values parsed

_OBJECT_TAGS = {"sensor", "film", "sampler", "rfilter", "integrator", "shape", "bsdf",
                "emitter", "texture", "medium", "phase", "volume"}
_VALUE_TAGS = {"float", "integer", "boolean", "string", "point", "vector", "rgb", "spectrum"}
_PLUGINS = {
    "shape": {"obj", "ply", "rectangle", "cube", "sphere"},
    "bsdf": {"diffuse", "twosided", "conductor", "roughconductor", "dielectric"},
    "emitter": {"area", "point", "spot"},
    "sensor": {"perspective", "thinlens"},
    "film": {"hdrfilm"},
    "rfilter": {"box", "tent", "gaussian", "mitchell", "catmullrom", "lanczos"},
    "sampler": {"independent", "stratified", "multijitter", "orthogonal", "ldsampler"},
    "integrator": {"path", "volpath", "volpathmis", "ptracer", "direct"},
}
_NORI_PLUGINS = {**_PLUGINS, "shape": {"obj"}, "bsdf": {"diffuse", "conductor", "dielectric"},
                 "emitter": {"area"}, "sensor": {"perspective"}, "sampler": {"independent"},
                 "integrator": {"photonmapper", "path_mis", "path_mats", "path_ems", "mipath",
                                "whitted", "direct", "direct_mis", "direct_ems", "direct_mats"}}
_MAX_INCLUDE_DEPTH = 15                                  # Mitsuba's recursion limit


@dataclass(eq=False)
class _Prop:
    node: _Node
    kind: str              # the value's tag: float, rgb, spectrum, transform, ...
    value: object
    in_emitter: bool
    used: bool = False


@dataclass(eq=False)
class _Ref:
    node: _Node
    id: str


@dataclass(eq=False)
class _Obj:
    """One plugin instance: its parameters and nested objects/references."""
    node: _Node
    tag: str
    type: str
    props: dict = field(default_factory=dict)
    children: list = field(default_factory=list)

    def take(self, name: str, kinds) -> _Prop | None:
        prop = self.props.get(name)
        if prop is not None:
            if prop.kind not in kinds:
                prop.node.fail(f"expected {' or '.join(f'<{k}>' for k in kinds)} for {name!r}")
            prop.used = True
        return prop

    def name(self) -> str:
        return self.node.attrib.get("id") or f"{self.tag}@{os.path.basename(self.node.file)}:{self.node.line}"

    def where(self) -> str:
        return f"{self.node.file}:{self.node.line}: {self.node.label}"


def _version(node: _Node) -> tuple | None:
    text = node.attrib.get("version")
    if text is None:
        return None
    if not re.fullmatch(r"\d+\.\d+\.\d+", text.strip()):
        node.fail(f"cannot parse version {text!r}")
    return tuple(int(p) for p in text.split("."))


def _upgrade_names(root: _Node) -> None:
    """Mitsuba 0.x and Nori spell parameters in camelCase; Mitsuba 3 upgrades
    them to snake_case on load (toWorld -> to_world, intIOR -> int_ior)."""
    for node in _walk(root):
        if node.tag == "lookAt":
            node.tag = "lookat"
        if "name" in node.attrib and node.tag != "default":
            node.attrib["name"] = re.sub(r"([a-z])([A-Z]+)", lambda m: m[1] + "_" + m[2].lower(),
                                         node.attrib["name"])
    for node in _walk(root):
        if node.tag == "bsdf" and node.attrib.get("type") == "diffuse":
            for prop in node.children:
                if prop.attrib.get("name") == "diffuse_reflectance":
                    prop.attrib["name"] = "reflectance"


class _Expander:
    """Builds the `_Obj` tree of a file and its includes."""

    def __init__(self, path: str, params: dict, plugins: dict):
        self.root_dir = os.path.dirname(os.path.abspath(path))
        self.params = {name: [str(value), False] for name, value in params.items()}
        self.plugins = plugins
        self.ids: dict[str, _Obj] = {}
        self.includes = [os.path.realpath(path)]          # the chain of files being read

    def unused_params(self) -> list:
        return [name for name, (_, used) in self.params.items() if not used]

    def substitute(self, node: _Node) -> None:
        """Mitsuba's rule: longest names first, plain text replacement, and
        any '$' left over is an undefined parameter."""
        for key, value in node.attrib.items():
            if "$" not in value:
                continue
            for name in sorted(self.params, key=len, reverse=True):
                if "$" + name in value:
                    value = value.replace("$" + name, self.params[name][0])
                    self.params[name][1] = True
            if "$" in value:
                node.fail(f"undefined parameter in {key}={node.attrib[key]!r}")
            node.attrib[key] = value

    def object(self, node: _Node) -> _Obj:
        _check_attrs(node, {"type", "id", "name"} | ({"version"} if node.tag == "scene" else set()))
        kind = "scene" if node.tag == "scene" else node.attrib.get("type")
        if node.tag != "scene" and kind not in self.plugins.get(node.tag, ()):
            node.fail("unsupported plugin")
        obj = _Obj(node, node.tag, kind)
        ident = node.attrib.get("id")
        if ident is not None:
            if ident in self.ids:
                first = self.ids[ident].node
                node.fail(f"duplicate id {ident!r} (first at {first.file}:{first.line})")
            self.ids[ident] = obj
        for child in node.children:
            self.child(obj, child)
        return obj

    def child(self, parent: _Obj, node: _Node) -> None:
        self.substitute(node)
        tag = node.tag
        if tag in ("default", "include", "ref") or tag in _VALUE_TAGS and "type" not in node.attrib:
            _no_children(node)
        if tag == "default":
            self.default(node)
        elif tag == "include":
            self.include(parent, node)
        elif tag == "ref":
            _check_attrs(node, {"id", "name"}, required=("id",))
            parent.children.append(_Ref(node, node.attrib["id"]))
        elif tag in _OBJECT_TAGS or (tag in _VALUE_TAGS and "type" in node.attrib):
            parent.children.append(self.object(node))
        elif tag in _VALUE_TAGS or tag == "transform":
            self.property(parent, node)
        else:
            node.fail("unsupported element")

    def default(self, node: _Node) -> None:
        _check_attrs(node, {"name", "value"}, required=("name", "value"))
        if not node.attrib["name"]:
            node.fail("empty name")
        # Keyword overrides and earlier defaults win; defaults count as used.
        self.params.setdefault(node.attrib["name"], [node.attrib["value"], True])

    def property(self, parent: _Obj, node: _Node) -> None:
        if node.tag == "transform":
            _check_attrs(node, {"name"}, required=("name",))
            value = np.eye(4)
            for op in node.children:
                self.substitute(op)
                _no_children(op)
                value = _transform_op(op) @ value
        else:
            value = _read_value(node)
        name = node.attrib["name"]
        if name in parent.props:
            node.fail(f"parameter {name!r} given twice (first at line {parent.props[name].node.line})")
        parent.props[name] = _Prop(node, node.tag, value, in_emitter=parent.tag == "emitter")

    def include(self, parent: _Obj, node: _Node) -> None:
        _check_attrs(node, {"filename"}, required=("filename",))
        path = _resolve(node, node.attrib["filename"], self.root_dir)
        real = os.path.realpath(path)
        if real in self.includes or len(self.includes) > _MAX_INCLUDE_DEPTH:
            node.fail("include cycle (or deeper than 15 levels)")
        root = _parse_xml(path)
        self.includes.append(real)
        if root.tag != "scene":
            self.child(parent, root)
        else:
            _check_attrs(root, {"version"})
            if (_version(root) or (3, 0, 0)) < (2, 0, 0):
                _upgrade_names(root)
            for child in root.children:
                self.child(parent, child)
        self.includes.pop()


# ---------------------------------------------------------------------------
# Nori's dialect, rewritten to the Mitsuba elements it means

_NORI_ONLY_TAGS = {"mesh", "camera", "color"}
_NORI_TAGS = {"mesh": "shape", "camera": "sensor", "color": "rgb"}


def _dialect(root: _Node) -> str:
    if root.tag != "scene":
        root.fail("the root element must be <scene>")
    if "version" in root.attrib:
        return "mitsuba"
    if any(node.tag in _NORI_ONLY_TAGS for node in _walk(root)):
        return "nori"
    root.fail('missing version attribute (Mitsuba 3 scenes start with <scene version="3.0.0">)')


def _nori_to_mitsuba(root: _Node) -> None:
    _upgrade_names(root)
    for node in _walk(root):
        node.tag = _NORI_TAGS.get(node.tag, node.tag)
        kind = node.attrib.get("type")
        if node.tag == "bsdf" and kind == "mirror":
            node.attrib["type"] = "conductor"
        if node.tag == "bsdf" and kind == "diffuse":
            for prop in node.children:
                if prop.attrib.get("name") == "albedo":
                    prop.attrib["name"] = "reflectance"
        if node.tag == "rotate" and "axis" in node.attrib:      # Nori normalises its axes
            axis = _numbers(node, node.attrib.pop("axis"), (3,))
            node.attrib["value"] = " ".join(map(repr, axis / (np.linalg.norm(axis) or 1.0)))
    samplers = [c for c in root.children if c.tag == "sampler"]
    cameras = [c for c in root.children if c.tag == "sensor"]
    for camera in cameras:
        _nori_camera(camera, samplers if camera is cameras[0] else [])
    if cameras:
        root.children = [c for c in root.children if c not in samplers]


def _nori_camera(camera: _Node, samplers: list) -> None:
    """Width, height and rfilter move into a film; Nori's defaults are made
    explicit; its image x axis runs along camera +x where Mitsuba's runs along
    -x, so the camera-to-world gets scale(-1, 1, 1) applied first."""
    film = _synthetic("film", {"type": "hdrfilm"}, camera)
    size = {"width": "1280", "height": "720"}
    kept = []
    for child in camera.children:
        if child.tag == "rfilter" or (child.tag == "integer" and child.attrib.get("name") in size):
            film.children.append(child)
            size.pop(child.attrib.get("name"), None)
        else:
            kept.append(child)
    film.children += [_synthetic("integer", {"name": k, "value": v}, camera) for k, v in size.items()]
    names = {c.attrib.get("name") for c in kept}
    for name, value in (("fov", "30"), ("near_clip", "1e-4"), ("far_clip", "1e4")):
        if name not in names:
            kept.append(_synthetic("float", {"name": name, "value": value}, camera))
    to_world = next((c for c in kept if c.tag == "transform" and c.attrib.get("name") == "to_world"), None)
    if to_world is None:
        to_world = _synthetic("transform", {"name": "to_world"}, camera)
        kept.append(to_world)
    to_world.children.insert(0, _synthetic("scale", {"x": "-1"}, to_world))
    camera.children = kept + [film] + samplers


# ---------------------------------------------------------------------------
# Typed parameter access; every plugin ends with `_finish`


def _float(obj: _Obj, name: str, default=None):
    prop = obj.take(name, ("float", "integer"))
    return default if prop is None else float(prop.value)


def _int(obj: _Obj, name: str, default=None):
    prop = obj.take(name, ("integer",))
    return default if prop is None else prop.value


def _bool(obj: _Obj, name: str, default=None):
    prop = obj.take(name, ("boolean",))
    return default if prop is None else prop.value


def _str(obj: _Obj, name: str, default=None):
    prop = obj.take(name, ("string",))
    return default if prop is None else prop.value


def _point(obj: _Obj, name: str, default=None):
    prop = obj.take(name, ("point", "vector"))
    return default if prop is None else prop.value


def _matrix(obj: _Obj, name: str = "to_world") -> np.ndarray:
    prop = obj.take(name, ("transform",))
    return np.eye(4) if prop is None else prop.value


def _rgb(obj: _Obj, name: str, default: float) -> tuple:
    prop = obj.take(name, ("rgb", "spectrum", "float", "integer"))
    return (default,) * 3 if prop is None else tuple(float(c) for c in _prop_rgb(prop))


def _required(obj: _Obj, name: str, getter):
    value = getter(obj, name)
    if value is None:
        obj.node.fail(f"missing parameter {name!r}")
    return value


def _finish(obj: _Obj) -> None:
    """Mitsuba's rule: a parameter no plugin read is an error."""
    for prop in obj.props.values():
        if not prop.used:
            prop.node.fail(f"unsupported parameter of {obj.node.label}")


def _no_metal(obj: _Obj) -> None:
    prop = obj.take("material", ("string",))
    if prop is not None and prop.value != "none":
        prop.node.fail(f"unsupported attribute: named conductor {prop.value!r} (only material=\"none\", "
                       "a perfect mirror tinted by specular_reflectance)")


# ---------------------------------------------------------------------------
# Geometry


def _orient_outward(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Wind every triangle of a shape centred on the origin to face outward."""
    v0 = vertices[faces[:, 0]]
    normal = np.cross(vertices[faces[:, 1]] - v0, vertices[faces[:, 2]] - v0)
    inward = np.einsum("ij,ij->i", normal, vertices[faces].mean(axis=1)) < 0
    faces = faces.copy()
    faces[inward] = faces[inward][:, ::-1]
    return faces


def _rectangle():
    """Mitsuba's rectangle: [-1, 1]^2 in z = 0, front +z."""
    v = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64)
    return v, np.array([[0, 1, 2], [0, 2, 3]])


@functools.lru_cache(maxsize=1)
def _cube():
    """Mitsuba's cube: [-1, 1]^3, 24 vertices, faces outward."""
    vertices, faces = [], []
    for axis in range(3):
        for side in (-1.0, 1.0):
            base = len(vertices)
            for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = np.zeros(3)
                p[axis], p[(axis + 1) % 3], p[(axis + 2) % 3] = side, a, b
                vertices.append(p)
            faces += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
    vertices = np.array(vertices)
    return vertices, _orient_outward(vertices, np.array(faces))


@functools.lru_cache(maxsize=1)
def _unit_sphere():
    """Mitsuba's sphere is analytic; 20,480 flat triangles (subdivision 5 of
    an icosahedron) keep the chord error under 0.03% of the radius."""
    import trimesh                       # deferred: trimesh is slow to import
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    vertices = np.asarray(mesh.vertices, np.float64)
    return vertices, _orient_outward(vertices, np.asarray(mesh.faces, np.int64))


def _load_mesh_file(path: str, node: _Node):
    from dosppm_core.scene.tomlfile import read_mesh_file
    try:
        return read_mesh_file(path)
    except ValueError as exc:
        node.fail(str(exc))


def _sphere_frame(obj: _Obj, to_world: np.ndarray) -> np.ndarray:
    """Mitsuba composes to_world * translate(center) * scale(radius)."""
    r3 = to_world[:3, :3]
    gram = r3.T @ r3
    if not np.allclose(gram, np.eye(3) * gram[0, 0], rtol=1e-5, atol=1e-9 * gram[0, 0]):
        obj.node.fail("to_world of a sphere must be a similarity (Mitsuba ignores other scales)")
    radius = _float(obj, "radius", 1.0)
    if not radius > 0:
        obj.node.fail(f"radius must be positive, got {radius}")
    local = np.diag([radius, radius, radius, 1.0])
    local[:3, 3] = _point(obj, "center", np.zeros(3))
    return to_world @ local


# ---------------------------------------------------------------------------
# The scene, plugin by plugin


class _SceneReader:
    """Interprets the object tree into `SceneBuilder` calls."""

    def __init__(self, path: str, ids: dict, dialect: str):
        self.builder = SceneBuilder(source=path, name=os.path.splitext(os.path.basename(path))[0])
        self.root_dir = os.path.dirname(os.path.abspath(path))
        self.ids = ids
        self.dialect = dialect
        self.settings: dict = {}
        self._bsdfs: dict = {}              # id(_Obj) -> Material without emission
        self._material_ids: dict = {}       # (id(bsdf), id(emitter)) -> builder material id
        self._radiance: dict = {}           # id(area emitter) -> RGB radiance
        self._loose_area_emitters: list = []

    def read(self, scene: _Obj) -> Scene:
        handlers = {"shape": self._shape, "sensor": self._sensor, "integrator": self._integrator,
                    "bsdf": self._bsdf, "emitter": self._emitter}
        for child in scene.children:
            if isinstance(child, _Ref) or child.tag not in handlers:
                child.node.fail("not supported at scene level")
            handlers[child.tag](child)
        _finish(scene)
        for emitter in self._loose_area_emitters:
            if id(emitter) not in self._radiance:
                emitter.node.fail("area emitter is not attached to any shape")
        result = self.builder.build()
        result.render_settings = self.settings
        return result

    def _children(self, obj: _Obj, allowed) -> list:
        """Nested objects and references, each of a tag `allowed` here."""
        out = []
        for child in obj.children:
            target = child
            if isinstance(child, _Ref):
                target = self.ids.get(child.id) or child.node.fail(f"unknown id {child.id!r}")
            if target.tag not in allowed:
                child.node.fail(f"not allowed inside {obj.node.label}")
            out.append(target)
        return out

    def _single(self, obj: _Obj, children: list, tag: str):
        found = [c for c in children if c.tag == tag]
        if len(found) > 1:
            obj.node.fail(f"more than one <{tag}>")
        return found[0] if found else None

    # -- materials ----------------------------------------------------------
    def _bsdf(self, obj: _Obj) -> Material:
        """The material a <bsdf> describes: one object, one material."""
        if id(obj) not in self._bsdfs:
            convert = {"diffuse": self._diffuse, "twosided": self._twosided,
                       "conductor": self._conductor, "roughconductor": self._roughconductor,
                       "dielectric": self._dielectric}[obj.type]
            material = convert(obj)
            _finish(obj)
            material.validate(obj.where())
            self._bsdfs[id(obj)] = material
        return self._bsdfs[id(obj)]

    def _diffuse(self, obj: _Obj) -> Material:
        self._children(obj, ())
        return Material(obj.name(), "diffuse", _rgb(obj, "reflectance", 0.5), two_sided=False)

    def _twosided(self, obj: _Obj) -> Material:
        inner = self._children(obj, {"bsdf"})
        if len(inner) != 1:
            obj.node.fail("needs exactly one BSDF (separate front and back BSDFs are unsupported)")
        return dataclasses.replace(self._bsdf(inner[0]), name=obj.name(), two_sided=True)

    def _conductor(self, obj: _Obj) -> Material:
        self._children(obj, ())
        _no_metal(obj)
        return Material(obj.name(), "mirror", _rgb(obj, "specular_reflectance", 1.0), two_sided=False)

    def _roughconductor(self, obj: _Obj) -> Material:
        self._children(obj, ())
        _no_metal(obj)
        prop = obj.take("distribution", ("string",))
        if prop is None or prop.value != "ggx":
            (prop.node if prop else obj.node).fail(
                f"distribution {prop.value if prop else 'beckmann (Mitsuba default)'!r} is unsupported; "
                'only GGX: add <string name="distribution" value="ggx"/>')
        _bool(obj, "sample_visible")          # a sampling strategy: the image is the same
        return Material(obj.name(), "glossy", _rgb(obj, "specular_reflectance", 1.0),
                        roughness=self._alpha(obj), two_sided=False)

    def _alpha(self, obj: _Obj) -> float:
        alpha, alpha_u, alpha_v = (_float(obj, n) for n in ("alpha", "alpha_u", "alpha_v"))
        if alpha_u is None and alpha_v is None:
            return 0.1 if alpha is None else alpha
        if alpha is not None or alpha_u != alpha_v:
            obj.node.fail("anisotropic roughness is unsupported (give alpha, or equal alpha_u and alpha_v)")
        return alpha_u

    def _dielectric(self, obj: _Obj) -> Material:
        self._children(obj, ())
        eta = self._ior(obj, "int_ior", "bk7") / self._ior(obj, "ext_ior", "air")
        tint = _rgb(obj, "specular_reflectance", 1.0)
        if not np.allclose(tint, _rgb(obj, "specular_transmittance", 1.0)):
            obj.node.fail("specular_reflectance and specular_transmittance differ; our glass has one tint")
        return Material(obj.name(), "glass", tint, ior=eta, two_sided=True)

    def _ior(self, obj: _Obj, name: str, default: str) -> float:
        prop = obj.take(name, ("float", "integer", "string"))
        value = default if prop is None else prop.value
        if isinstance(value, str):
            if value.lower() not in _IORS:
                prop.node.fail(f"unknown IOR name {value!r} (known: {', '.join(_IORS)})")
            return _IORS[value.lower()]
        return float(value)

    def _material_id(self, bsdf, emitter, shape: _Obj) -> int:
        """Emission belongs to the material, so each (bsdf, emitter) pair a
        shape uses becomes one builder material."""
        key = (id(bsdf), id(emitter))
        if key not in self._material_ids:
            material = self._bsdf(bsdf) if bsdf is not None else self._default_bsdf(emitter)
            if emitter is not None:
                material = dataclasses.replace(material, name=f"{material.name}+{emitter.name()}",
                                               emission=self._area_radiance(emitter))
            where = (bsdf or emitter or shape).where()
            self._material_ids[key] = self.builder.add_material(material, where)
        return self._material_ids[key]

    def _default_bsdf(self, emitter) -> Material:
        # Mitsuba gives a bare emitter a black BSDF; Nori a grey one.
        if emitter is not None and self.dialect == "mitsuba":
            return Material("default-black", "diffuse", (0.0, 0.0, 0.0), two_sided=False)
        return Material("default", "diffuse", (0.5, 0.5, 0.5), two_sided=False)

    # -- shapes -------------------------------------------------------------
    def _shape(self, obj: _Obj) -> None:
        vertices, faces = self._geometry(obj)
        to_world = _matrix(obj)
        if obj.type == "sphere":
            to_world = _sphere_frame(obj, to_world)
        if obj.type in ("rectangle", "cube") and np.linalg.det(to_world[:3, :3]) < 0:
            # Mitsuba moves these shading normals with the inverse transpose, so
            # a mirror keeps their front outward; its sphere's turns inward.
            faces = faces[:, ::-1]
        if _bool(obj, "flip_normals", False):
            faces = faces[:, ::-1]
        children = self._children(obj, {"bsdf", "emitter"})
        bsdf, emitter = self._single(obj, children, "bsdf"), self._single(obj, children, "emitter")
        material = self._material_id(bsdf, emitter, obj)
        _finish(obj)
        self.builder.add_mesh(vertices, faces, material, obj.where(), transform=to_world)

    def _geometry(self, obj: _Obj):
        if obj.type in ("obj", "ply"):
            filename = _required(obj, "filename", _str)
            _bool(obj, "face_normals")        # our normals are always the faces'
            path = _resolve(obj.take("filename", ("string",)).node, filename, self.root_dir)
            return _load_mesh_file(path, obj.node)
        return {"rectangle": _rectangle, "cube": _cube, "sphere": _unit_sphere}[obj.type]()

    # -- emitters -----------------------------------------------------------
    def _area_radiance(self, emitter: _Obj) -> tuple:
        if emitter.type != "area":
            emitter.node.fail("only area emitters can be attached to a shape")
        if id(emitter) not in self._radiance:
            self._children(emitter, ())
            self._radiance[id(emitter)] = _rgb(emitter, "radiance", 1.0)
            _finish(emitter)
        return self._radiance[id(emitter)]

    def _emitter(self, obj: _Obj) -> None:
        if obj.type == "area":                # a definition: some shape must reference it
            self._loose_area_emitters.append(obj)
            return
        self._children(obj, ())
        intensity = _rgb(obj, "intensity", 1.0)
        if obj.type == "point":
            position = _point(obj, "position")
            to_world = obj.take("to_world", ("transform",))
            if position is not None and to_world is not None:
                obj.node.fail("give position or to_world, not both")
            if position is None:
                position = np.eye(4)[:3, 3] if to_world is None else to_world.value[:3, 3]
            _finish(obj)
            self.builder.add_point_light(position, intensity, obj.where())
            return
        m = _matrix(obj)
        cutoff, beam = _float(obj, "cutoff_angle", 20.0), _float(obj, "beam_width")
        _finish(obj)
        target = m[:3, 3] + m[:3, :3] @ np.array([0.0, 0.0, 1.0])
        self.builder.add_spot_light(m[:3, 3], target, intensity, cutoff, beam, obj.where())

    # -- sensor and render settings -----------------------------------------
    def _sensor(self, obj: _Obj) -> None:
        if self.builder.camera is not None:
            obj.node.fail("a second sensor: only one camera is supported")
        children = self._children(obj, {"film", "sampler"})
        film, sampler = self._single(obj, children, "film"), self._single(obj, children, "sampler")
        width, height = self._film(film) if film is not None else (768, 576)
        if sampler is not None:
            self._sampler(sampler)
        position, look_at, up = self._camera_frame(obj)
        fov, axis = _field_of_view(obj, width, height)
        camera = Camera(position, look_at, up, fov, width, height, fov_axis=axis,
                        near_clip=_float(obj, "near_clip", 0.01))
        far_clip = _float(obj, "far_clip")
        if far_clip is not None:
            self.settings["far_clip"] = far_clip
        if obj.type == "thinlens":
            camera.aperture_radius = _required(obj, "aperture_radius", _float)
            camera.focus_distance = _float(obj, "focus_distance", far_clip or 1e4)
        else:                                 # stored only: a pinhole has no focus
            camera.focus_distance = _float(obj, "focus_distance", camera.focus_distance)
        _finish(obj)
        camera.validate(obj.where())
        self.builder.camera = camera

    def _camera_frame(self, obj: _Obj):
        """Mitsuba's camera looks along local +z with +y up; our camera's
        image right is forward x up, which matches a proper rotation only."""
        prop = obj.take("to_world", ("transform",))
        m = np.eye(4) if prop is None else prop.value
        rotation = m[:3, :3]
        node = prop.node if prop else obj.node
        if not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-5):
            node.fail("a sensor's to_world must be rotation and translation only (Mitsuba rejects scale)")
        if np.linalg.det(rotation) < 0:
            hint = ' (a Nori camera needs <scale value="-1,1,1"/> before its <lookat>)' \
                if self.dialect == "nori" else ""
            node.fail("a sensor's to_world mirrors the image, which our camera cannot" + hint)
        position = m[:3, 3]
        return (tuple(map(float, position)), tuple(map(float, position + rotation[:, 2])),
                tuple(map(float, rotation[:, 1])))

    def _film(self, film: _Obj) -> tuple:
        rfilter = self._single(film, self._children(film, {"rfilter"}), "rfilter")
        if rfilter is not None:
            self._children(rfilter, ())
            params = {n: _float(rfilter, n) for n in ("radius", "stddev", "B", "C", "lobes")
                      if n in rfilter.props}
            _finish(rfilter)
            self.settings["rfilter"] = {"type": rfilter.type, **params}
        size = (_int(film, "width", 768), _int(film, "height", 576))
        pixel_format = _str(film, "pixel_format")
        if pixel_format is not None:
            self.settings["pixel_format"] = pixel_format
        _finish(film)
        return size

    def _sampler(self, obj: _Obj) -> None:
        self._children(obj, ())
        self.settings["sampler"] = obj.type
        self.settings["spp"] = _int(obj, "sample_count", 4)
        seed = _int(obj, "seed")
        if seed is not None:
            self.settings["seed"] = seed
        _finish(obj)

    def _integrator(self, obj: _Obj) -> None:
        if "integrator" in self.settings:
            obj.node.fail("a second integrator")
        self._children(obj, ())
        self.settings["integrator"] = obj.type
        params = {"max_depth": _int, "rr_depth": _int, "hide_emitters": _bool}
        if self.dialect == "nori":
            params = {"photon_radius": _float, "photon_count": _int}
        for name, getter in params.items():
            value = getter(obj, name)
            if value is not None:
                self.settings[name] = value
        _finish(obj)


def _field_of_view(obj: _Obj, width: int, height: int) -> tuple:
    """(fov in degrees, axis). A focal length (default 50mm, a diagonal fov
    of 35 mm film) and the diagonal axis become the equivalent x fov, as
    Mitsuba's `parse_fov` computes them."""
    fov, focal = _float(obj, "fov"), obj.take("focal_length", ("string",))
    axis_prop = obj.take("fov_axis", ("string",))
    axis = "x" if axis_prop is None else axis_prop.value.lower()
    if fov is not None and focal is not None:
        obj.node.fail("give fov or focal_length, not both")
    if fov is None:
        text = "50mm" if focal is None else focal.value
        if not text.endswith("mm"):
            (focal.node if focal else obj.node).fail(f"focal_length must end in 'mm', got {text!r}")
        mm = _to_float(focal.node if focal else obj.node, text[:-2])
        fov, axis = math.degrees(2 * math.atan(math.hypot(36, 24) / (2 * mm))), "diagonal"
    if axis == "diagonal":
        half_width = math.tan(math.radians(fov) / 2) / math.sqrt(1 + (height / width) ** 2)
        fov, axis = math.degrees(2 * math.atan(half_width)), "x"
    if axis not in ("x", "y", "smaller", "larger"):
        axis_prop.node.fail(f"fov_axis must be x, y, diagonal, smaller or larger, got {axis!r}")
    return fov, axis


# ---------------------------------------------------------------------------


def load_mitsuba_xml(path: str, **defaults) -> Scene:
    """Load a Mitsuba 3 (or Nori) scene file. Keyword arguments override the
    file's `<default>` parameters, like `mitsuba.load_file(path, spp=16)`.
    Settings with no home in `Scene` go to `scene.render_settings`."""
    path = os.fspath(path)
    root = _parse_xml(path)
    dialect = _dialect(root)
    if dialect == "nori":
        _nori_to_mitsuba(root)
    elif _version(root) < (2, 0, 0):
        _upgrade_names(root)
    expander = _Expander(path, defaults, _NORI_PLUGINS if dialect == "nori" else _PLUGINS)
    expander.substitute(root)
    scene = expander.object(root)
    unused = expander.unused_params()
    if unused:
        raise SceneError(f"{path}: parameter(s) {', '.join(unused)} given but never used as $name in the file")
    return _SceneReader(path, expander.ids, dialect).read(scene)
