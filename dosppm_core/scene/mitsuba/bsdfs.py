"""BSDFs to `Material`s: diffuse; twosided (one nested BSDF); conductor
(material="none") -> mirror; roughconductor (GGX) -> glossy;
dielectric (one tint) -> glass; conductor and roughconductor with eta
and k, or Beckmann -> their kinds; roughdielectric (GGX or Beckmann),
plastic and roughplastic -> their kinds; mask (a constant opacity) -> its
nested material with `opacity`. One <bsdf> object is one material; a
shape's (bsdf, area emitter) pair becomes one builder material, since
emission belongs to the material. The colour (reflectance, or the
conductor's or glass's tint) may be a texture (`textures`)."""
from __future__ import annotations

import dataclasses

from dosppm_core.scene.mitsuba.colour import prop_rgb
from dosppm_core.scene.mitsuba.emitters import area_radiance
from dosppm_core.scene.mitsuba.objects import Obj
from dosppm_core.scene.mitsuba.params import finish, get_bool, get_float, get_rgb
from dosppm_core.scene.mitsuba.state import ReaderState
from dosppm_core.scene.mitsuba.textures import TextureParams
from dosppm_core.scene.model import Material

# Mitsuba's named indices of refraction (include/mitsuba/render/ior.h).
IORS = {
    "vacuum": 1.0, "helium": 1.000036, "hydrogen": 1.000132, "air": 1.000277,
    "carbon dioxide": 1.00045, "water": 1.3330, "acetone": 1.36, "ethanol": 1.361,
    "carbon tetrachloride": 1.461, "glycerol": 1.4729, "benzene": 1.501,
    "silicone oil": 1.52045, "bromine": 1.661, "water ice": 1.31, "fused quartz": 1.458,
    "pyrex": 1.470, "acrylic glass": 1.49, "polypropylene": 1.49, "bk7": 1.5046,
    "sodium chloride": 1.544, "amber": 1.55, "pet": 1.575, "diamond": 2.419,
}


def bsdf_material(reader: ReaderState, obj: Obj) -> Material:
    """The material a <bsdf> describes: one object, one material."""
    if id(obj) not in reader.bsdfs:
        convert = {"diffuse": _diffuse, "twosided": _twosided, "conductor": _conductor,
                   "roughconductor": _roughconductor, "dielectric": _dielectric,
                   "roughdielectric": _roughdielectric, "plastic": _plastic,
                   "roughplastic": _roughplastic, "mask": _mask}[obj.type]
        material = convert(reader, obj)
        finish(obj)
        material.validate(obj.where())
        reader.bsdfs[id(obj)] = material
    return reader.bsdfs[id(obj)]


def material_id(reader: ReaderState, bsdf, emitter, shape: Obj) -> int:
    """Emission belongs to the material, so each (bsdf, emitter) pair a
    shape uses becomes one builder material."""
    key = (id(bsdf), id(emitter))
    if key not in reader.material_ids:
        material = bsdf_material(reader, bsdf) if bsdf is not None else _default_bsdf(reader, emitter)
        if emitter is not None:
            radiance, texture = area_radiance(reader, emitter)
            material = dataclasses.replace(material, name=f"{material.name}+{emitter.name()}",
                                           emission=radiance, emission_texture=texture)
        where = (bsdf or emitter or shape).where()
        reader.material_ids[key] = reader.builder.add_material(material, where)
    return reader.material_ids[key]


def _default_bsdf(reader: ReaderState, emitter) -> Material:
    # Mitsuba gives a bare emitter a black BSDF; Nori a grey one.
    if emitter is not None and reader.dialect == "mitsuba":
        return Material("default-black", "diffuse", (0.0, 0.0, 0.0), two_sided=False)
    return Material("default", "diffuse", (0.5, 0.5, 0.5), two_sided=False)


def _coloured(name: str, kind: str, colour: tuple, **kw) -> Material:
    """A material of `colour` = (RGB, -1) or (None, texture id)."""
    rgb, texture = colour
    return Material(name, kind, (1.0, 1.0, 1.0) if rgb is None else rgb, texture=texture, **kw)


def _diffuse(reader: ReaderState, obj: Obj) -> Material:
    params = TextureParams(reader, obj)
    colour = params.rgb("reflectance", 0.5)
    params.finish()
    return _coloured(obj.name(), "diffuse", colour, two_sided=False)


def _twosided(reader: ReaderState, obj: Obj) -> Material:
    # Every kind takes it: the reflecting ones (plastics included) become
    # alike on both sides; dielectrics are two-sided already.
    inner = reader.children(obj, {"bsdf"})
    if len(inner) != 1:
        obj.node.fail("needs exactly one BSDF (separate front and back BSDFs are unsupported)")
    return dataclasses.replace(bsdf_material(reader, inner[0]), name=obj.name(), two_sided=True)


def _mask(reader: ReaderState, obj: Obj) -> Material:
    """Mitsuba's mask: the nested BSDF with probability `opacity` (default
    0.5), else the ray passes straight through."""
    inner = reader.children(obj, {"bsdf"})
    if len(inner) != 1:
        obj.node.fail("needs exactly one nested BSDF")
    opacity = get_float(obj, "opacity", 0.5)
    if not 0.0 <= opacity <= 1.0:
        obj.node.fail(f"opacity must lie in [0, 1], got {opacity}")
    return dataclasses.replace(bsdf_material(reader, inner[0]), name=obj.name(), opacity=opacity)


def _conductor(reader: ReaderState, obj: Obj) -> Material:
    """Mitsuba's conductor: a perfect mirror (our "mirror") without eta and
    k, else Fresnel of the complex index eta + i k ("conductor"). The tint
    (specular_reflectance) may be a texture: the kernels fold its texel in
    where the material's reflectance (white then) is read."""
    params = TextureParams(reader, obj)
    _no_metal(obj)
    colour = params.rgb("specular_reflectance", 1.0)
    eta_k = _eta_k(obj)
    params.finish()
    if eta_k is None:
        return _coloured(obj.name(), "mirror", colour, two_sided=False)
    return _metal(obj.name(), "conductor", colour, eta_k)


def _roughconductor(reader: ReaderState, obj: Obj) -> Material:
    """Mitsuba's roughconductor: our GGX "glossy" when it is GGX with a
    Fresnel of 1 (no eta, k), else "roughconductor" (Beckmann or GGX,
    visible normals, Fresnel of eta + i k)."""
    params = TextureParams(reader, obj)
    _no_metal(obj)
    distribution = _distribution(obj)
    colour = params.rgb("specular_reflectance", 1.0)
    eta_k = _eta_k(obj)
    params.finish()                       # a textured alpha is refused here
    if eta_k is None and distribution == "ggx":
        return _coloured(obj.name(), "glossy", colour, roughness=_alpha(obj), two_sided=False)
    return _metal(obj.name(), "roughconductor", colour, eta_k or ((0.0,) * 3, (1.0,) * 3),
                  roughness=_alpha(obj), distribution=distribution)


def _metal(name: str, kind: str, colour: tuple, eta_k, **kw) -> Material:
    """A conductor of complex index eta + i k; a textured tint rides in
    `texture` (the coloured kinds' `specular` then white)."""
    rgb, texture = colour
    return Material(name, kind, (1.0, 1.0, 1.0), specular=(1.0, 1.0, 1.0) if rgb is None else rgb,
                    texture=texture, conductor_eta=eta_k[0], conductor_k=eta_k[1], two_sided=False, **kw)


def _eta_k(obj: Obj):
    """(eta, k) RGB of a conductor, or None when neither is given (Mitsuba's
    defaults then, 0 and 1, make a perfect mirror). Values are unbounded:
    one number, an rgb, or a constant spectrum (a spectrum list would be
    clamped to [0, 1] as a reflectance, so it is refused)."""
    props = [obj.take(n, ("float", "integer", "rgb", "spectrum")) for n in ("eta", "k")]
    if props == [None, None]:
        return None
    out = []
    for prop, default in zip(props, (0.0, 1.0)):
        if prop is None:
            out.append((default,) * 3)
            continue
        if prop.kind == "spectrum" and prop.value[0] != "constant":
            prop.node.fail("a conductor's eta and k as a spectrum list are unsupported (give one value or rgb)")
        out.append(tuple(float(c) for c in prop_rgb(prop)))
    return out


def _alpha(obj: Obj) -> float:
    alpha, alpha_u, alpha_v = (get_float(obj, n) for n in ("alpha", "alpha_u", "alpha_v"))
    if alpha_u is None and alpha_v is None:
        return 0.1 if alpha is None else alpha
    if alpha is not None or alpha_u != alpha_v:
        obj.node.fail("anisotropic roughness is unsupported (give alpha, or equal alpha_u and alpha_v)")
    return alpha_u


def _dielectric(reader: ReaderState, obj: Obj) -> Material:
    params = TextureParams(reader, obj)
    eta = _ior(obj, "int_ior", "bk7") / _ior(obj, "ext_ior", "air")
    colour = params.same("specular_reflectance", "specular_transmittance", 1.0)
    params.finish()
    return _coloured(obj.name(), "glass", colour, ior=eta, two_sided=True)


def _distribution(obj: Obj) -> str:
    """Mitsuba's microfacet distribution name (its default: Beckmann)."""
    prop = obj.take("distribution", ("string",))
    name = "beckmann" if prop is None else prop.value.lower()
    if name not in ("ggx", "beckmann"):
        prop.node.fail(f"distribution {prop.value!r} is unknown (ggx or beckmann)")
    get_bool(obj, "sample_visible")       # a sampling strategy: the image is the same
    return name


def _rough_eta(obj: Obj, interior: str) -> float:
    """int_ior / ext_ior of a rough interface, which must differ (an index
    ratio of 1 has no microfacet lobe to sample)."""
    eta = _ior(obj, "int_ior", interior) / _ior(obj, "ext_ior", "air")
    if eta == 1.0:
        obj.node.fail("int_ior and ext_ior must differ")
    return eta


def _roughdielectric(reader: ReaderState, obj: Obj) -> Material:
    reader.children(obj, ())
    distribution = _distribution(obj)
    eta = _rough_eta(obj, "bk7")
    return Material(obj.name(), "roughdielectric", get_rgb(obj, "specular_transmittance", 1.0),
                    ior=eta, roughness=_alpha(obj), two_sided=True, distribution=distribution,
                    specular=get_rgb(obj, "specular_reflectance", 1.0))


def _plastic(reader: ReaderState, obj: Obj) -> Material:
    reader.children(obj, ())
    eta = _ior(obj, "int_ior", "polypropylene") / _ior(obj, "ext_ior", "air")
    return Material(obj.name(), "plastic", get_rgb(obj, "diffuse_reflectance", 0.5), ior=eta,
                    specular=get_rgb(obj, "specular_reflectance", 1.0),
                    nonlinear=bool(get_bool(obj, "nonlinear", False)), two_sided=False)


def _roughplastic(reader: ReaderState, obj: Obj) -> Material:
    reader.children(obj, ())
    distribution = _distribution(obj)
    eta = _rough_eta(obj, "polypropylene")
    return Material(obj.name(), "roughplastic", get_rgb(obj, "diffuse_reflectance", 0.5), ior=eta,
                    roughness=_alpha(obj), specular=get_rgb(obj, "specular_reflectance", 1.0),
                    nonlinear=bool(get_bool(obj, "nonlinear", False)), distribution=distribution,
                    two_sided=False)


def _ior(obj: Obj, name: str, default: str) -> float:
    prop = obj.take(name, ("float", "integer", "string"))
    value = default if prop is None else prop.value
    if isinstance(value, str):
        if value.lower() not in IORS:
            prop.node.fail(f"unknown IOR name {value!r} (known: {', '.join(IORS)})")
        return IORS[value.lower()]
    return float(value)


def _no_metal(obj: Obj) -> None:
    prop = obj.take("material", ("string",))
    if prop is not None and prop.value != "none":
        prop.node.fail(f"unsupported attribute: named conductor {prop.value!r} (only material=\"none\", "
                       "a perfect mirror tinted by specular_reflectance)")
