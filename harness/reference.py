"""Independent reference images from Mitsuba 3.

This is the only module that imports mitsuba. It translates our `Scene`
into a Mitsuba scene dict, renders it with Mitsuba's path tracer (`path`)
or light tracer (`ptracer`) and returns a float32 (H, W, 3) array; Mitsuba
has no photon mapper, so these unbiased estimators are SPPM's peers.

Mapping (see `dosppm_core.scene` for our conventions, which follow Mitsuba):

=========  ==========================================================
ours       Mitsuba 3
=========  ==========================================================
diffuse    `diffuse`, reflectance
mirror     `conductor`, material "none", specular_reflectance
glossy     `roughconductor`, ggx, alpha = roughness, material "none"
glass      `dielectric`, int_ior = ior, ext_ior = 1, reflectance tints
           specular_reflectance and specular_transmittance
roughdielectric, plastic, roughplastic, conductor, roughconductor (eta,
           k): Mitsuba's own, distribution and
           alpha, int_ior = ior, ext_ior = 1, reflectance is the transmit
           tint / the diffuse_reflectance, specular the other tint
opacity    < 1: wrapped in `mask`
two_sided  reflecting kinds wrapped in `twosided` (dielectrics never are)
emission   `area` emitter (one-sided, along the CCW winding normal)
point      `point`, intensity
spot       `spot`, cutoff_angle, beam_width, intensity
camera     `perspective` (`thinlens` when aperture_radius > 0), look_at;
           `orthographic` with to_world = look_at @ scale(ortho_scale, 1)
film       `hdrfilm` RGB float32, the camera's pixel filter (`box`, `tent`,
           `gaussian` with Mitsuba's 4-stddev cut-off) and sample_border
sampler    `independent`
=========  ==========================================================

Geometry becomes one `mi.Mesh` per material, and per shading: triangles
whose three vertices carry normals (`Scene.normals`, a smooth mesh) get
them as Mitsuba vertex normals, the others none, so Mitsuba shades each
triangle as our kernels do (`kernels.smooth`).

Depth convention: our `max_depth` counts scattering events (bounces) on a
light path from the emitter to the camera, the surface seen by the camera
included; 0 means only emitters seen directly, 1 direct lighting. Mitsuba's
`max_depth` counts path vertices after the camera, the emitter included, so
``mitsuba max_depth = max_depth + 1`` (a negative value means unbounded, -1
in Mitsuba). For a diffuse scene this is exactly the set of paths an SPPM
render with at most `max_depth` photon bounces (deposits) estimates; with
specular chains in front of the camera SPPM may add eye bounces on top.
References are unbounded by default (-1), as the renderer's default is
(Russian roulette ends its paths; its depth limit is only a safety net).

Variant: the caller's choice, `scalar_rgb` (`SAFE_VARIANT`) by default.
`llvm_ad_rgb` is about 3x faster, but an unsupported libLLVM aborts the
whole process while compiling a kernel (it cannot be caught), so whether it
works here is found by trying it in a child process:
`harness.mitsuba_probe.best_variant()` does that (once per process), and
its answer is passed in as `variant`, so a caller that names its variant
(the tests) starts no process.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import re
from dataclasses import asdict

import numpy as np

from dosppm_core.film import FilmError, one_line, read_exr, write_exr
from dosppm_core.scene.model import (
    CONDUCTOR,
    DIFFUSE,
    GLASS,
    GLOSSY,
    LIGHT_DIRECTIONAL,
    LIGHT_ENV,
    LIGHT_POINT,
    LIGHT_PROJECTOR,
    LIGHT_SPOT,
    LIGHT_TRIANGLE,
    MICROFACETS,
    MIRROR,
    PLASTIC,
    ROUGH_CONDUCTOR,
    ROUGH_DIELECTRIC,
    ROUGH_PLASTIC,
    Scene,
    SceneError,
)

DEFAULT_MAX_DEPTH = -1    # unbounded: the converged image the renderer's default estimates
INTEGRATORS = ("path", "ptracer")
FAST_VARIANT, SAFE_VARIANT = "llvm_ad_rgb", "scalar_rgb"
# Bump when the translation changes, so cached references are re-rendered.
MAPPING_VERSION = 1


class ReferenceRenderError(RuntimeError):
    """Mitsuba is missing or failed; the message is one line."""


# -- Mitsuba loading and variant choice -------------------------------------
def _import_mitsuba():
    try:
        import mitsuba  # optional (the [reference] extra), and 0.2 s to import
    except ImportError:
        raise ReferenceRenderError("Mitsuba 3 is not installed: pip install 'dosppm[reference]'") from None
    return mitsuba


def available_variants() -> list[str]:
    """The variants this Mitsuba build has (not all of them may work here:
    see the module doc)."""
    return list(_import_mitsuba().variants())


def _mitsuba(variant: str):
    """The mitsuba module with `variant` set."""
    mi = _import_mitsuba()
    if mi.variant() != variant:
        try:
            mi.set_variant(variant)
        except Exception as exc:
            raise ReferenceRenderError(f"Mitsuba variant {variant!r} is unavailable: "
                                 f"{one_line(exc)}") from None
    return mi


# -- Scene translation ------------------------------------------------------
def mitsuba_max_depth(max_depth: int) -> int:
    """Our bounce count -> Mitsuba's vertex count (see the module doc)."""
    return -1 if max_depth < 0 else int(max_depth) + 1


def scene_to_mitsuba_dict(scene: Scene, spp: int, max_depth: int = DEFAULT_MAX_DEPTH,
                          integrator: str = "path", seed: int = 0,
                          variant: str = SAFE_VARIANT) -> dict:
    """A Mitsuba 3 scene dict for `scene`; meshes are `mi.Mesh` objects of
    `variant`, which is set as a side effect."""
    if integrator not in INTEGRATORS:
        raise ValueError(f"unknown integrator {integrator!r} (known: {', '.join(INTEGRATORS)})")
    if int(spp) < 1:
        raise ValueError(f"spp must be positive, got {spp!r}")
    mi = _mitsuba(variant)
    out = {"type": "scene",
           "integrator": {"type": integrator, "max_depth": mitsuba_max_depth(max_depth),
                          "hide_emitters": False},
           "sensor": _sensor(mi, scene, int(spp), int(seed))}
    out.update(_meshes(mi, scene))
    out.update(_delta_emitters(mi, scene))
    return out


def _sensor(mi, scene: Scene, spp: int, seed: int) -> dict:
    cam = scene.camera
    # Mitsuba needs 0 < near_clip < far_clip; keep its default 1e6 ratio
    # but scale it to the scene so nothing in view is clipped.
    reach = scene.diagonal() + float(np.linalg.norm(np.mean(scene.bounds(), axis=0)
                                                    - np.asarray(cam.position, float)))
    far = max(10.0 * reach, 1e-3)
    sensor = {
        "type": "perspective",
        "to_world": mi.ScalarTransform4f().look_at(origin=_vec(cam.position),
                                                   target=_vec(cam.look_at), up=_vec(cam.up)),
        "fov": float(cam.fov_deg), "fov_axis": cam.fov_axis,
        "near_clip": float(cam.near_clip) if cam.near_clip > 0 else far * 1e-6,
        "far_clip": far,
        "film": {"type": "hdrfilm", "width": int(cam.width), "height": int(cam.height),
                 "pixel_format": "rgb", "component_format": "float32",
                 "sample_border": bool(cam.sample_border), "rfilter": _rfilter(cam)},
        "sampler": {"type": "independent", "sample_count": spp, "seed": seed},
    }
    if cam.aperture_radius > 0:
        sensor.update(type="thinlens", aperture_radius=float(cam.aperture_radius),
                      focus_distance=float(cam.focus_distance))
    if cam.projection == "orthographic":
        # Mitsuba sizes the orthographic view by the scale of its to_world.
        scale = mi.ScalarTransform4f().scale([float(cam.ortho_scale[0]), float(cam.ortho_scale[1]), 1.0])
        del sensor["fov"], sensor["fov_axis"]
        sensor.update(type="orthographic", to_world=sensor["to_world"] @ scale)
    return sensor


def _rfilter(cam) -> dict:
    """Mitsuba's rfilter for our camera's pixel filter: its box is half a
    pixel wide and its Gaussian ends at 4 stddev, so other radii have no mapping."""
    radius = cam.filter_radius_px()
    if cam.pixel_filter == "tent":
        return {"type": "tent", "radius": radius}
    fixed = 0.5 if cam.pixel_filter == "box" else 4.0 * float(cam.filter_stddev)
    if not math.isclose(radius, fixed, rel_tol=1e-6):
        raise SceneError(f"camera: a {cam.pixel_filter} filter of radius {radius:g} has no Mitsuba "
                         f"mapping (Mitsuba's is {fixed:g})")
    return {"type": "box"} if cam.pixel_filter == "box" else {"type": "gaussian",
                                                                "stddev": float(cam.filter_stddev)}


def _smooth_triangles(scene: Scene) -> np.ndarray:
    """Per triangle: whether all three of its vertices carry a normal."""
    if not len(scene.normals):
        return np.zeros(len(scene.triangles), bool)
    has = np.any(scene.normals != 0, axis=1)
    return has[scene.triangles].all(axis=1)


def _meshes(mi, scene: Scene) -> dict:
    """One `mi.Mesh` per used material and shading (smooth or flat),
    carrying its BSDF and, when emissive, its area emitter."""
    smooth = _smooth_triangles(scene)
    out = {}
    for mid in np.unique(scene.tri_material):
        for shaded in (False, True):
            pick = (scene.tri_material == mid) & (smooth == shaded)
            if pick.any():
                name, mesh = _material_mesh(mi, scene, int(mid), pick, shaded)
                out[name] = mesh
    return out


def _material_mesh(mi, scene: Scene, mid: int, pick: np.ndarray, shaded: bool):
    mats = scene.materials
    faces = scene.triangles[pick]
    used, local = np.unique(faces, return_inverse=True)
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(_bsdf(mats, mid))
    if mats.emission_texture[mid] >= 0:
        raise ValueError("a textured area light has no reference render here: render the Mitsuba file itself")
    if np.max(mats.emission[mid]) > 0:
        props["emitter"] = mi.load_dict({"type": "area", "radiance": _spectrum(mats.emission[mid])})
    name = f"mesh_{mid}_{_safe_name(mats.names[mid])}" + ("_smooth" if shaded else "")
    normals = scene.normals[used] if shaded else None
    return name, _mesh(mi, name, scene.vertices[used], local.reshape(-1, 3), props, normals)


def _mesh(mi, name: str, vertices: np.ndarray, faces: np.ndarray, props, normals=None):
    mesh = mi.Mesh(name, vertex_count=len(vertices), face_count=len(faces), props=props,
                   has_vertex_normals=normals is not None, has_vertex_texcoords=False)
    params = mi.traverse(mesh)
    params["vertex_positions"] = np.ascontiguousarray(vertices, np.float32).ravel()
    params["faces"] = np.ascontiguousarray(faces, np.uint32).ravel()
    if normals is not None:
        params["vertex_normals"] = np.ascontiguousarray(normals, np.float32).ravel()
    params.update()  # rebuilds the bounding box and the area sampling table
    return mesh


def _bsdf(mats, mid: int) -> dict:
    if mats.opacity_texture[mid] >= 0 or mats.blend[mid, 1] >= 0:
        raise SceneError(f"material {mats.names[mid]!r}: a textured mask or a blend has no Mitsuba "
                         "form here (render the Mitsuba file itself)")
    bsdf = _opaque_bsdf(mats, mid)
    if float(mats.opacity[mid]) < 1.0:
        return {"type": "mask", "opacity": float(mats.opacity[mid]), "bsdf": bsdf}
    return bsdf


def _opaque_bsdf(mats, mid: int) -> dict:
    if mats.texture[mid] >= 0:
        # Its reflectance row is (1, 1, 1), the texel being folded in by the
        # kernels: exporting that would render another scene.
        raise SceneError(f"material {mats.names[mid]!r}: a textured material has no Mitsuba "
                         "mapping here (reference a Mitsuba .xml scene directly)")
    if mats.normal_map[mid] >= 0 or mats.bump_map[mid] >= 0:
        raise SceneError(f"material {mats.names[mid]!r}: a normal or bump map has no Mitsuba "
                         "mapping here (reference a Mitsuba .xml scene directly)")
    kind, tint = int(mats.kind[mid]), _spectrum(mats.reflectance[mid])
    if ROUGH_DIELECTRIC <= kind <= ROUGH_CONDUCTOR:
        return _coloured_bsdf(mats, mid, kind, tint)
    if kind == GLASS:
        return {"type": "dielectric", "int_ior": float(mats.ior[mid]), "ext_ior": 1.0,
                "specular_reflectance": tint, "specular_transmittance": tint}
    if kind == DIFFUSE:
        bsdf = {"type": "diffuse", "reflectance": tint}
    elif kind == MIRROR:
        bsdf = {"type": "conductor", "material": "none", "specular_reflectance": tint}
    elif kind == GLOSSY:
        bsdf = {"type": "roughconductor", "distribution": "ggx", "material": "none",
                "alpha": float(mats.roughness[mid]), "specular_reflectance": tint}
    else:
        raise SceneError(f"material {mats.names[mid]!r}: kind {kind} has no Mitsuba mapping")
    return {"type": "twosided", "bsdf": bsdf} if mats.two_sided[mid] else bsdf


def _coloured_bsdf(mats, mid: int, kind: int, tint: dict) -> dict:
    spec, ior = _spectrum(mats.specular[mid]), float(mats.ior[mid])
    rough = {"distribution": MICROFACETS[int(mats.distribution[mid])], "alpha": float(mats.roughness[mid])}
    if kind == ROUGH_DIELECTRIC:
        return {"type": "roughdielectric", "int_ior": ior, "ext_ior": 1.0, **rough,
                "specular_transmittance": tint, "specular_reflectance": spec}
    if kind in (CONDUCTOR, ROUGH_CONDUCTOR):
        bsdf = {"type": "conductor", "eta": _spectrum(mats.conductor_eta[mid]),
                "k": _spectrum(mats.conductor_k[mid]), "specular_reflectance": spec}
        if kind == ROUGH_CONDUCTOR:
            bsdf.update(rough, type="roughconductor")
        return {"type": "twosided", "bsdf": bsdf} if mats.two_sided[mid] else bsdf
    bsdf = {"type": "plastic" if kind == PLASTIC else "roughplastic", "int_ior": ior, "ext_ior": 1.0,
            "diffuse_reflectance": tint, "specular_reflectance": spec,
            "nonlinear": bool(mats.nonlinear[mid])}
    if kind == ROUGH_PLASTIC:
        bsdf.update(rough)
    return {"type": "twosided", "bsdf": bsdf} if mats.two_sided[mid] else bsdf


def _delta_emitters(mi, scene: Scene) -> dict:
    lights, out = scene.lights, {}
    for i in np.flatnonzero(lights.kind != LIGHT_TRIANGLE):
        if lights.texture[i] >= 0:
            raise ValueError("a textured spot or projector has no reference render here: "
                             "render the Mitsuba file itself")
        pos, value = _vec(lights.p0[i]), _spectrum(lights.value[i])
        if lights.kind[i] == LIGHT_POINT:
            out[f"light_{i}"] = {"type": "point", "position": pos, "intensity": value}
        elif lights.kind[i] == LIGHT_SPOT:
            axis = np.asarray(lights.p1[i], float)
            out[f"light_{i}"] = {
                "type": "spot", "intensity": value,
                "to_world": mi.ScalarTransform4f().look_at(
                    origin=pos, target=_vec(lights.p0[i] + axis), up=_vec(_any_perpendicular(axis))),
                "cutoff_angle": math.degrees(lights.cone[i, 2]),
                "beam_width": math.degrees(lights.cone[i, 3])}
        elif lights.kind[i] == LIGHT_PROJECTOR:
            axis = np.asarray(lights.p1[i], float)
            out[f"light_{i}"] = {
                "type": "projector", "irradiance": value, "fov": math.degrees(2 * math.atan(lights.cone[i, 0])),
                "to_world": mi.ScalarTransform4f().look_at(
                    origin=pos, target=_vec(lights.p0[i] + axis), up=_vec(np.cross(axis, lights.p2[i])))}
        elif lights.kind[i] == LIGHT_DIRECTIONAL:
            out[f"light_{i}"] = {"type": "directional", "direction": pos, "irradiance": value}
        elif lights.kind[i] == LIGHT_ENV:
            out[f"light_{i}"] = _environment(mi, lights)
    return out


def _environment(mi, lights) -> dict:
    """Mitsuba's constant for a uniform map, else its envmap of our texels
    (less the wrap column, which Mitsuba adds back) and rotation."""
    texels = lights.env_texels
    if np.all(texels == texels[0, 0]):
        return {"type": "constant", "radiance": _spectrum(texels[0, 0])}
    rotation = np.eye(4)
    rotation[:3, :3] = lights.env_to_world
    return {"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(texels[:, :-1])),
            "to_world": mi.ScalarTransform4f(rotation)}


def _spectrum(rgb) -> dict:
    value = [float(x) for x in rgb]
    if max(value) <= 1.0:
        return {"type": "rgb", "value": value}
    # Mitsuba rejects reflectance above 1 unless marked unbounded (glass
    # tints and emission may exceed it).
    return {"type": "srgb", "color": value, "unbounded": True}


def _any_perpendicular(axis: np.ndarray) -> np.ndarray:
    """An up vector not parallel to `axis`; a spot is round, so any will do."""
    return np.array([1.0, 0, 0]) if abs(axis[1]) > 0.9 * np.linalg.norm(axis) else np.array([0, 1.0, 0])


def _vec(v) -> list:
    return [float(x) for x in v]


def _safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_]", "_", str(name))[:40]


# -- Rendering -------------------------------------------------------------
def render_reference(scene: Scene, spp: int, max_depth: int = DEFAULT_MAX_DEPTH,
                     integrator: str = "path", seed: int = 0,
                     variant: str = SAFE_VARIANT) -> np.ndarray:
    """Render `scene` with Mitsuba 3: float32 (H, W, 3) linear RGB, row 0 on
    top."""
    mi = _mitsuba(variant)
    scene_dict = scene_to_mitsuba_dict(scene, spp, max_depth, integrator, seed, mi.variant())
    try:
        image = mi.render(mi.load_dict(scene_dict), spp=int(spp), seed=int(seed))
    except Exception as exc:
        raise ReferenceRenderError(f"{scene.source}: Mitsuba render failed: {one_line(exc)}") from None
    return np.ascontiguousarray(np.asarray(image, dtype=np.float32)[..., :3])


def _camera_key(cam) -> dict:
    """The camera's fields, those of the pixel filter only when they differ
    from the box's, so the keys (and cached references) of box-filtered
    scenes stay as they were before cameras had filters."""
    fields = asdict(cam)
    defaults = {"pixel_filter": "box", "filter_radius": None, "filter_stddev": 0.5, "sample_border": False}
    if all(fields[k] == v for k, v in defaults.items()):
        for k in defaults:
            del fields[k]
    return fields


def reference_key(scene: Scene, spp: int, max_depth: int = DEFAULT_MAX_DEPTH,
                  integrator: str = "path", seed: int = 0) -> str:
    """SHA-256 of everything that decides the reference image: geometry,
    materials, lights, camera, sample count, depth, integrator, seed."""
    h = hashlib.sha256()
    arrays = {"vertices": scene.vertices, "triangles": scene.triangles,
              "tri_material": scene.tri_material}
    mats = scene.materials
    # The columns of the coloured kinds and masks count only where used, so
    # the keys (and cached references) of other scenes stay as they were.
    newer = ((mats.kind >= ROUGH_DIELECTRIC).any() or (mats.opacity < 1).any()
             or (mats.opacity_texture >= 0).any() or (mats.blend[:, 1] >= 0).any())
    later = ("specular", "distribution", "nonlinear", "opacity", "conductor_eta", "conductor_k",
             "opacity_texture", "blend", "blend_weight", "blend_texture")
    mapped = ("normal_map", "bump_map", "bump_scale", "shading_flags")    # likewise, normal and bump maps
    rough = ("roughness_v", "alpha_u_texture", "alpha_v_texture")   # likewise, anisotropic roughness
    anisotropic = (mats.roughness_v >= 0).any() or (mats.alpha_u_texture >= 0).any() or \
        (mats.alpha_v_texture >= 0).any()
    arrays.update({f"mat.{k}": v for k, v in vars(mats).items()
                   if k != "names" and (newer or k not in later)
                   and (mats.shading_mapped or k not in mapped) and (anisotropic or k not in rough)})
    arrays.update({f"light.{k}": v for k, v in scene.lights.wire_fields().items()})
    for name in sorted(arrays):
        arr = np.ascontiguousarray(arrays[name])
        h.update(f"{name}:{arr.dtype.str}:{arr.shape};".encode())
        h.update(arr.tobytes())
    settings = {"camera": _camera_key(scene.camera), "spp": int(spp), "max_depth": int(max_depth),
                "integrator": integrator, "seed": int(seed), "mapping": MAPPING_VERSION}
    h.update(json.dumps(settings, sort_keys=True, default=_jsonable).encode())
    return h.hexdigest()


def _jsonable(x):
    return np.asarray(x).tolist()


def cached_reference(scene: Scene, spp: int, cache_dir: str,
                     max_depth: int = DEFAULT_MAX_DEPTH, integrator: str = "path",
                     seed: int = 0, variant: str = SAFE_VARIANT) -> np.ndarray:
    """`render_reference`, stored as `cache_dir/ref-<name>-<key>.exr` and read
    back on the next call with the same inputs. An unreadable cache file is
    rendered again."""
    key = reference_key(scene, spp, max_depth, integrator, seed)
    path = os.path.join(cache_dir, f"ref-{_safe_name(scene.name)}-{key[:24]}.exr")
    if os.path.exists(path):
        try:
            return read_exr(path)[0]
        except FilmError:
            pass  # a damaged cache entry: render and overwrite it
    image = render_reference(scene, spp, max_depth, integrator, seed, variant)
    os.makedirs(cache_dir, exist_ok=True)
    write_exr(path, image)
    return image
