"""BSDFs to `Material`s: diffuse; twosided (one nested BSDF); conductor
(material="none") -> mirror; roughconductor (GGX) -> glossy; dielectric
(one tint) -> glass; conductor and roughconductor with eta and k (or a
named metal, `metals`), or Beckmann -> their kinds; roughdielectric (GGX
or Beckmann), plastic and roughplastic -> their kinds; mask (a constant
or textured opacity) -> its nested material with `opacity`; blendbsdf ->
a material naming its two parts; normalmap and bumpmap (a texture, and a
nested diffuse, rough conductor or rough plastic) -> the nested material
with its `normal_map` or `bump_map` (kernels.shading). One <bsdf> object
is one material; a shape's (bsdf, area emitter) pair becomes one builder
material, since emission belongs to the material. The colour
(reflectance, or the conductor's or glass's tint) may be a texture
(`textures`)."""
from __future__ import annotations

import dataclasses

from dosppm_core.scene.mitsuba.colour import prop_rgb
from dosppm_core.scene.mitsuba.emitters import area_radiance
from dosppm_core.scene.mitsuba.metals import CONDUCTORS
from dosppm_core.scene.mitsuba.objects import Obj
from dosppm_core.scene.mitsuba.params import finish, get_bool, get_float, get_rgb
from dosppm_core.scene.mitsuba.state import ReaderState
from dosppm_core.scene.mitsuba.textures import TextureParams, read_texture
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
                   "roughplastic": _roughplastic, "mask": _mask, "normalmap": _normalmap,
                   "bumpmap": _bumpmap, "blendbsdf": _blendbsdf}[obj.type]
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
        if material.name in reader.builder._material_ids:
            # Two BSDFs on one line (a blend and its part) share a name.
            material = dataclasses.replace(material, name=f"{material.name}#{len(reader.material_ids)}")
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
    0.5; a texture's luminance at the hit), else the ray passes straight
    through."""
    inner = _nested(reader, obj, 1)
    params = TextureParams(reader, obj, skip={"bsdf"})
    opacity, texture = params.scalar("opacity", 0.5)
    params.finish()
    if texture >= 0:
        return dataclasses.replace(bsdf_material(reader, inner[0]), name=obj.name(), opacity_texture=texture)
    if not 0.0 <= opacity <= 1.0:
        obj.node.fail(f"opacity must lie in [0, 1], got {opacity}")
    return dataclasses.replace(bsdf_material(reader, inner[0]), name=obj.name(), opacity=opacity)


# What a normal or bump map may wrap: the kinds whose eye paths stop in a
# hit point, which takes the perturbed normal (kernels.shading). A smooth
# or transmissive BSDF would need it in the eye bounce too.
MAPPABLE = ("diffuse", "glossy", "roughconductor", "roughplastic")


def _normalmap(reader: ReaderState, obj: Obj) -> Material:
    """Mitsuba's normalmap: the tangent-space normal 2 c - 1 of the texture
    named normalmap (a bitmap should be read raw)."""
    nested, textures = _wrapped(reader, obj)
    if len(textures) != 1 or textures[0][0] != "normalmap":
        obj.node.fail("needs one texture named 'normalmap'")
    return dataclasses.replace(nested, name=obj.name(), normal_map=read_texture(reader, textures[0][1]),
                               shading_flags=_shading_flags(obj))


def _bumpmap(reader: ReaderState, obj: Obj) -> Material:
    """Mitsuba's bumpmap: the normal of the surface displaced by `scale`
    (default 1) times its one texture's height."""
    nested, textures = _wrapped(reader, obj)
    if len(textures) != 1:
        obj.node.fail("needs exactly one texture (the height)")
    return dataclasses.replace(nested, name=obj.name(), bump_map=read_texture(reader, textures[0][1]),
                               bump_scale=get_float(obj, "scale", 1.0), shading_flags=_shading_flags(obj))


def _wrapped(reader: ReaderState, obj: Obj):
    """(the nested material, [(name, texture object)]) of a normal or bump
    map, whose nested BSDF must be one it can wrap."""
    bsdfs, textures = [], []
    for child, target in zip(obj.children, reader.children(obj, {"bsdf", "texture"})):
        if target.tag == "bsdf":
            bsdfs.append(target)
        else:
            textures.append((child.node.attrib.get("name"), target))
    if len(bsdfs) != 1:
        obj.node.fail("needs exactly one nested BSDF")
    nested = bsdf_material(reader, bsdfs[0])
    if nested.kind not in MAPPABLE or nested.normal_map >= 0 or nested.bump_map >= 0:
        bsdfs[0].node.fail(f"a {obj.type} of this BSDF is unsupported (only of {', '.join(MAPPABLE)}, "
                           "not of a smooth, transmissive or already mapped one)")
    return nested, textures


def _shading_flags(obj: Obj) -> int:
    """Mitsuba's two options of the normal and bump maps (both default on)."""
    return (int(bool(get_bool(obj, "flip_invalid_normals", True)))
            | 2 * int(bool(get_bool(obj, "use_shadowing_function", True))))
def _blendbsdf(reader: ReaderState, obj: Obj) -> Material:
    """Mitsuba's blendbsdf: (1 - weight) first + weight second, `weight`
    (required) a number or a texture's luminance at the hit. Each
    interaction picks one part with that probability (as Mitsuba samples
    it), so the parts become materials of their own and the blend names
    them; a shape of the blend holds the blend's emission, if any."""
    inner = _nested(reader, obj, 2)
    params = TextureParams(reader, obj, skip={"bsdf"})
    weight, texture = params.scalar("weight", None)
    params.finish()
    if weight is None and texture < 0:
        obj.node.fail("needs a weight (a number or a texture)")
    if texture < 0 and not 0.0 <= weight <= 1.0:
        obj.node.fail(f"weight must lie in [0, 1], got {weight}")
    parts = [bsdf_material(reader, b) for b in inner]
    ids = tuple(material_id(reader, b, None, obj) for b in inner)
    # The blend's own kind only tells the photon bounce whether a photon
    # may be deposited here (some part is not specular) and on which side.
    kind = "mirror" if all(p.kind in ("mirror", "glass", "conductor") for p in parts) else "diffuse"
    return Material(obj.name(), kind, two_sided=any(p.two_sided for p in parts), blend=ids,
                    blend_weight=0.0 if weight is None else weight, blend_texture=texture)


def _nested(reader: ReaderState, obj: Obj, count: int) -> list:
    inner = [c for c in reader.children(obj, {"bsdf", "texture"}) if c.tag == "bsdf"]
    if len(inner) != count:
        obj.node.fail(f"needs exactly {'one nested BSDF' if count == 1 else f'{count} nested BSDFs'}")
    return inner


def _conductor(reader: ReaderState, obj: Obj) -> Material:
    """Mitsuba's conductor: a perfect mirror (our "mirror") without eta and
    k, else Fresnel of the complex index eta + i k ("conductor"). The tint
    (specular_reflectance) may be a texture: the kernels fold its texel in
    where the material's reflectance (white then) is read."""
    params = TextureParams(reader, obj)
    colour = params.rgb("specular_reflectance", 1.0)
    eta_k = _metal_index(obj)
    params.finish()
    if eta_k is None:
        return _coloured(obj.name(), "mirror", colour, two_sided=False)
    return _metal(obj.name(), "conductor", colour, eta_k)


def _roughconductor(reader: ReaderState, obj: Obj) -> Material:
    """Mitsuba's roughconductor: our GGX "glossy" when it is GGX with a
    Fresnel of 1 (no eta, k), else "roughconductor" (Beckmann or GGX,
    visible normals, Fresnel of eta + i k)."""
    params = TextureParams(reader, obj)
    distribution = _distribution(obj)
    colour = params.rgb("specular_reflectance", 1.0)
    eta_k = _metal_index(obj)
    rough = _conductor_alpha(obj, params)
    params.finish()
    if eta_k is None and distribution == "ggx" and len(rough) == 1:
        return _coloured(obj.name(), "glossy", colour, two_sided=False, **rough)
    return _metal(obj.name(), "roughconductor", colour, eta_k or ((0.0,) * 3, (1.0,) * 3),
                  distribution=distribution, **rough)


def _conductor_alpha(obj: Obj, params: TextureParams) -> dict:
    """The roughness fields of a rough conductor: {roughness} when
    isotropic and constant, else alpha_u and alpha_v (Mitsuba: `alpha`
    sets both; without it both alpha_u and alpha_v are needed), each a
    value or a texture (kernels.anisotropic)."""
    if "alpha_u" not in obj.props and "alpha_u" not in params.named and \
            "alpha_v" not in obj.props and "alpha_v" not in params.named:
        alpha, texture = params.scalar("alpha", 0.1)
        if texture < 0:
            return {"roughness": _checked_alpha(obj, "alpha", alpha)}
        return {"alpha_u_texture": texture, "alpha_v_texture": texture}
    if "alpha" in obj.props or "alpha" in params.named:
        obj.node.fail("give alpha, or alpha_u and alpha_v, not both")
    out = {}
    for name, value_field, texture_field in (("alpha_u", "roughness", "alpha_u_texture"),
                                             ("alpha_v", "roughness_v", "alpha_v_texture")):
        if name not in obj.props and name not in params.named:
            obj.node.fail(f"needs {name} with the other of alpha_u and alpha_v")
        value, texture = params.scalar(name, None)
        if texture >= 0:
            out[texture_field] = texture
        else:
            out[value_field] = _checked_alpha(obj, name, value)
    if out.get("roughness") == out.get("roughness_v", -1.0) and len(out) == 2:
        return {"roughness": out["roughness"]}      # alpha_u == alpha_v: isotropic
    return out


def _checked_alpha(obj: Obj, name: str, value: float) -> float:
    if not 1e-4 <= value <= 1.0:
        obj.node.fail(f"{name} must lie in [1e-4, 1], got {value}")
    return value


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


def _metal_index(obj: Obj):
    """(eta, k) RGB of a conductor: a named material's (Mitsuba's table,
    `metals`), or the given eta and k, or None (`_eta_k`). As Mitsuba,
    naming both is an error."""
    prop = obj.take("material", ("string",))
    if prop is None or prop.value == "none":
        return _eta_k(obj)
    if "eta" in obj.props or "k" in obj.props:
        prop.node.fail("give either eta and k or a material, not both (as Mitsuba)")
    if prop.value not in CONDUCTORS:
        prop.node.fail(f"unknown conductor {prop.value!r} (Mitsuba's names: {', '.join(CONDUCTORS)})")
    return CONDUCTORS[prop.value]
