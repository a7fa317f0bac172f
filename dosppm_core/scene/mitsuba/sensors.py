"""The sensor (perspective, thinlens or orthographic) becomes the `Camera`,
its film's size and reconstruction filter with it (Mitsuba's default: a
Gaussian of standard deviation 0.5 px); the sampler and the integrator
become render settings: what `Scene` cannot hold (integrator, max_depth,
spp, far_clip, pixel format) lands in ``reader.settings``, only the keys
the file sets (and the <rfilter> as read, for the record)."""
from __future__ import annotations

import math

import numpy as np

from dosppm_core.scene.mitsuba.objects import Obj
from dosppm_core.scene.mitsuba.params import finish, get_bool, get_float, get_int, get_str, required
from dosppm_core.scene.mitsuba.state import ReaderState
from dosppm_core.scene.mitsuba.values import to_float
from dosppm_core.scene.model import MAX_FILTER_RADIUS, Camera


def read_sensor(reader: ReaderState, obj: Obj) -> None:
    """Set the builder's camera; the film and sampler go to the settings."""
    if reader.builder.camera is not None:
        obj.node.fail("a second sensor: only one camera is supported")
    children = reader.children(obj, {"film", "sampler"})
    film, sampler = reader.single(obj, children, "film"), reader.single(obj, children, "sampler")
    width, height, pixel_filter = _film(reader, film) if film is not None else (768, 576, DEFAULT_FILTER)
    if sampler is not None:
        _sampler(reader, sampler)
    if obj.type == "orthographic":
        camera = _orthographic(reader, obj, width, height)
    else:
        position, look_at, up = _camera_frame(reader, obj)
        fov, axis = field_of_view(obj, width, height)
        camera = Camera(position, look_at, up, fov, width, height, fov_axis=axis,
                        near_clip=get_float(obj, "near_clip", 0.01))
    far_clip = get_float(obj, "far_clip")
    if far_clip is not None:
        reader.settings["far_clip"] = far_clip
    if obj.type == "thinlens":
        camera.aperture_radius = required(obj, "aperture_radius", get_float)
        camera.focus_distance = get_float(obj, "focus_distance", far_clip or 1e4)
    elif obj.type == "perspective":       # stored only: a pinhole has no focus
        camera.focus_distance = get_float(obj, "focus_distance", camera.focus_distance)
    finish(obj)
    for name, value in pixel_filter.items():
        setattr(camera, name, value)
    camera.validate(obj.where())
    reader.builder.camera = camera


def _orthographic(reader: ReaderState, obj: Obj, width: int, height: int) -> Camera:
    """Mitsuba's orthographic sensor: its to_world's scale sizes the view
    (local x in [-1, 1], y in [-height/width, height/width]) and its z scale
    stretches the distance to the near plane."""
    prop = obj.take("to_world", ("transform",))
    m = np.eye(4) if prop is None else prop.value
    scale = np.linalg.norm(m[:3, :3], axis=0)
    if np.any(scale < 1e-12):
        (prop.node if prop else obj.node).fail("a sensor's to_world must not collapse an axis")
    unscaled = m.copy()
    unscaled[:3, :3] = m[:3, :3] / scale
    position, look_at, up = _camera_frame(reader, obj, unscaled, prop.node if prop else obj.node)
    near = get_float(obj, "near_clip", 0.01) * float(scale[2])
    return Camera(position, look_at, up, 90.0, width, height, near_clip=near,
                  projection="orthographic", ortho_scale=(float(scale[0]), float(scale[1])))


def _camera_frame(reader: ReaderState, obj: Obj, m=None, node=None):
    """Mitsuba's camera looks along local +z with +y up; our camera's
    image right is forward x up, which matches a proper rotation only."""
    if m is None:
        prop = obj.take("to_world", ("transform",))
        m = np.eye(4) if prop is None else prop.value
        node = prop.node if prop else obj.node
    rotation = m[:3, :3]
    if not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-5):
        node.fail("a sensor's to_world must be rotation and translation only (Mitsuba rejects scale"
                  " but for an orthographic sensor, and there it may not shear)")
    if np.linalg.det(rotation) < 0:
        hint = ' (a Nori camera needs <scale value="-1,1,1"/> before its <lookat>)' \
            if reader.dialect == "nori" else ""
        node.fail("a sensor's to_world mirrors the image, which our camera cannot" + hint)
    position = m[:3, 3]
    return (tuple(map(float, position)), tuple(map(float, position + rotation[:, 2])),
            tuple(map(float, rotation[:, 1])))


def field_of_view(obj: Obj, width: int, height: int) -> tuple:
    """(fov in degrees, axis). A focal length (default 50mm, a diagonal fov
    of 35 mm film) and the diagonal axis become the equivalent x fov, as
    Mitsuba's `parse_fov` computes them."""
    fov, focal = get_float(obj, "fov"), obj.take("focal_length", ("string",))
    axis_prop = obj.take("fov_axis", ("string",))
    axis = "x" if axis_prop is None else axis_prop.value.lower()
    if fov is not None and focal is not None:
        obj.node.fail("give fov or focal_length, not both")
    if fov is None:
        text = "50mm" if focal is None else focal.value
        if not text.endswith("mm"):
            (focal.node if focal else obj.node).fail(f"focal_length must end in 'mm', got {text!r}")
        mm = to_float(focal.node if focal else obj.node, text[:-2])
        fov, axis = math.degrees(2 * math.atan(math.hypot(36, 24) / (2 * mm))), "diagonal"
    if axis == "diagonal":
        half_width = math.tan(math.radians(fov) / 2) / math.sqrt(1 + (height / width) ** 2)
        fov, axis = math.degrees(2 * math.atan(half_width)), "x"
    if axis not in ("x", "y", "smaller", "larger"):
        axis_prop.node.fail(f"fov_axis must be x, y, diagonal, smaller or larger, got {axis!r}")
    return fov, axis


def _film(reader: ReaderState, film: Obj) -> tuple:
    """(width, height, the camera's pixel filter fields)."""
    rfilter = reader.single(film, reader.children(film, {"rfilter"}), "rfilter")
    pixel_filter = dict(DEFAULT_FILTER) if rfilter is None else _rfilter(reader, rfilter)
    border = get_bool(film, "sample_border")
    if border is not None:
        pixel_filter["sample_border"] = border
    size = (get_int(film, "width", 768), get_int(film, "height", 576))
    for name in ("pixel_format", "component_format"):    # how Mitsuba would write its image
        value = get_str(film, name)
        if value is not None:
            reader.settings[name] = value
    finish(film)
    return (*size, pixel_filter)


# Mitsuba's (and Nori's) film filter when the file names none.
DEFAULT_FILTER = {"pixel_filter": "gaussian", "filter_stddev": 0.5, "filter_radius": None}


def _rfilter(reader: ReaderState, rfilter: Obj) -> dict:
    """The camera's pixel filter fields of an <rfilter>. Mitsuba's box and
    gaussian take no radius (Nori's do); the filters with negative lobes
    (mitchell, catmullrom, lanczos) are refused: sampling them would give
    eye rays negative weights."""
    reader.children(rfilter, ())
    if rfilter.type not in ("box", "tent", "gaussian"):
        rfilter.node.fail(f"rfilter {rfilter.type!r} is not supported (box, tent and gaussian are)")
    params = {"radius": get_float(rfilter, "radius")} if rfilter.type == "tent" or reader.dialect == "nori" else {}
    if rfilter.type == "gaussian":
        params["stddev"] = get_float(rfilter, "stddev")
    finish(rfilter)
    params = {k: v for k, v in params.items() if v is not None}
    for name, value in params.items():
        if not 0 < value <= MAX_FILTER_RADIUS:
            rfilter.node.fail(f"{name} must lie in (0, {MAX_FILTER_RADIUS:g}] pixels, got {value:g}")
    reader.settings["rfilter"] = {"type": rfilter.type, **params}
    return {"pixel_filter": rfilter.type, "filter_radius": params.get("radius"),
            "filter_stddev": params.get("stddev", 0.5)}


def _sampler(reader: ReaderState, obj: Obj) -> None:
    reader.children(obj, ())
    reader.settings["sampler"] = obj.type
    reader.settings["spp"] = get_int(obj, "sample_count", 4)
    seed = get_int(obj, "seed")
    if seed is not None:
        reader.settings["seed"] = seed
    finish(obj)


def read_integrator(reader: ReaderState, obj: Obj) -> None:
    """The integrator's type and depth settings (Nori's photon mapper: its
    radius and photon count)."""
    if "integrator" in reader.settings:
        obj.node.fail("a second integrator")
    if obj.type == "moment":
        # Mitsuba's test scenes wrap the integrator to record its second
        # moment; we read through to it, as our variance is our own.
        nested = reader.children(obj, {"integrator"})
        if len(nested) != 1:
            obj.node.fail("a moment integrator must wrap exactly one integrator")
        finish(obj)
        read_integrator(reader, nested[0])
        return
    reader.children(obj, ())
    reader.settings["integrator"] = obj.type
    params = {"max_depth": get_int, "rr_depth": get_int, "hide_emitters": get_bool}
    if reader.dialect == "nori":
        params = {"photon_radius": get_float, "photon_count": get_int}
    for name, getter in params.items():
        value = getter(obj, name)
        if value is not None:
            reader.settings[name] = value
    finish(obj)
