"""The scene: flat arrays that every kernel, chunk and process shares.

A scene is triangles (one material id each), a material table, a light table
(`scene.lights`) and a camera. Every loader (TOML scene files, Mitsuba XML, the built-in
procedural scenes) goes through `SceneBuilder`, which owns validation, so a
bad scene gets the same one-line error whatever it came from.

Colours are linear RGB triples. Emission belongs to the material: an emissive
mesh is an area light of that radiance, emitting on the side its triangle
winding faces (counter-clockwise = front), as in Mitsuba.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np

from dosppm_core import arrays
from dosppm_core.scene.errors import SceneError
from dosppm_core.scene.light_textures import normalised
from dosppm_core.scene.lights import (  # noqa: F401 (the light kinds are the scene's vocabulary too)
    LIGHT_DIRECTIONAL,
    LIGHT_ENV,
    LIGHT_POINT,
    LIGHT_PROJECTOR,
    LIGHT_SPOT,
    LIGHT_TRIANGLE,
    SPHERE_MARGIN,
    LightTable,
    bounding_radius,
    light_table,
)
from dosppm_core.scene.normals import smooth_normals
from dosppm_core.scene.textures import Texture, TextureTable

# Material kinds, as stored in `MaterialTable.kind` and read by the kernels.
DIFFUSE, MIRROR, GLASS, GLOSSY = 0, 1, 2, 3
ROUGH_DIELECTRIC, PLASTIC, ROUGH_PLASTIC, CONDUCTOR, ROUGH_CONDUCTOR = 4, 5, 6, 7, 8
MATERIAL_KINDS = {"diffuse": DIFFUSE, "mirror": MIRROR, "glass": GLASS, "glossy": GLOSSY,
                  "roughdielectric": ROUGH_DIELECTRIC, "plastic": PLASTIC, "roughplastic": ROUGH_PLASTIC,
                  "conductor": CONDUCTOR, "roughconductor": ROUGH_CONDUCTOR}
MICROFACETS = ("ggx", "beckmann")     # `Material.distribution`, ids as kernels.microfacet

# Pixel reconstruction filters (`Camera.pixel_filter`), as `Camera.frame()` codes them.
PIXEL_FILTERS = {"box": 0, "gaussian": 1, "tent": 2}
FILTER_BOX, FILTER_GAUSSIAN, FILTER_TENT = 0, 1, 2
MAX_FILTER_RADIUS = 16.0     # pixels: wider would blur the image away, surely a unit mistake


# Absolute part of a spawned ray's offset from its surface, as a fraction of
# the scene diagonal (the relative part is `trace.EPS_REL`): every mode and
# every chunk must offset alike, or chunked and unchunked paths diverge.
SPAWN_EPSILON = 1e-6


def _rgb(value, where: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.size == 1:
        arr = np.repeat(arr, 3)
    if arr.size != 3 or not np.all(np.isfinite(arr)):
        raise SceneError(f"{where}: expected an RGB triple of finite numbers, got {value!r}")
    return arr


@dataclass
class Material:
    """One surface description.

    kind: 'diffuse' (Lambertian, albedo `reflectance`), 'mirror' (perfect
    specular, `reflectance`), 'glass' (smooth dielectric with `ior`, Fresnel
    reflection/refraction; `reflectance` tints both), 'glossy' (one GGX
    microfacet reflection lobe of `roughness` = alpha, tinted by
    `reflectance`). `two_sided=False` makes the back of a diffuse, mirror or
    glossy surface black, as Mitsuba does without its `twosided` wrapper.
    `texture` >= 0 (an id from `SceneBuilder.add_texture`) replaces
    `reflectance` by that texture's value at the hit's UV;
    `emission_texture` >= 0 (from `SceneBuilder.add_emission_texture`)
    multiplies `emission` by a texture's value there (Mitsuba's area light
    with a textured radiance).

    Mitsuba's 'roughdielectric' (relative `ior` = int_ior / ext_ior,
    `roughness` alpha of the `distribution` 'ggx' or 'beckmann';
    `reflectance` tints transmission, `specular` reflection), 'plastic' and
    'roughplastic' (a dielectric coating of `ior` over a diffuse base of
    albedo `reflectance`; `specular` tints the coating; `nonlinear` is
    Mitsuba's flag). `opacity` < 1 is Mitsuba's `mask`: a ray passes
    straight through with probability 1 - opacity; `opacity_texture` >= 0
    reads the opacity from that texture at the hit instead (its luminance).
    `blend` = (first, second) material ids makes Mitsuba's `blendbsdf`: at
    each interaction the second scatters with probability `blend_weight`
    (or `blend_texture`'s luminance at the hit), else the first; the
    blend's own kind and colours are unused, its emission is its own. See
    kernels.materials.

    Mitsuba's `normalmap` and `bumpmap` wrappers: `normal_map` >= 0 is the
    texture whose raw RGB c gives the tangent-space normal 2c - 1,
    `bump_map` >= 0 the height texture whose UV gradient times `bump_scale`
    tilts the normal; `shading_flags` holds their options (bit 1
    flip_invalid_normals, bit 2 use_shadowing_function). See
    kernels.shading.
    """
    name: str
    kind: str = "diffuse"
    reflectance: tuple = (0.5, 0.5, 0.5)
    ior: float = 1.5
    roughness: float = 0.1
    emission: tuple = (0.0, 0.0, 0.0)
    two_sided: bool = True
    texture: int = -1
    specular: tuple = (1.0, 1.0, 1.0)
    distribution: str = "ggx"
    nonlinear: bool = False
    opacity: float = 1.0
    conductor_eta: tuple = (0.0, 0.0, 0.0)
    conductor_k: tuple = (1.0, 1.0, 1.0)
    normal_map: int = -1
    bump_map: int = -1
    bump_scale: float = 1.0
    shading_flags: int = 3
    opacity_texture: int = -1
    blend: tuple = (-1, -1)
    blend_weight: float = 0.0
    blend_texture: int = -1
    emission_texture: int = -1
    roughness_v: float = -1.0       # a roughconductor's alpha_v; < 0: `roughness` (isotropic)
    alpha_u_texture: int = -1       # textured alpha_u (replaces `roughness`), -1 for none
    alpha_v_texture: int = -1       # textured alpha_v

    def validate(self, where: str) -> None:
        if self.kind not in MATERIAL_KINDS:
            raise SceneError(f"{where}: unknown material kind {self.kind!r} "
                             f"(known: {', '.join(MATERIAL_KINDS)})")
        refl = _rgb(self.reflectance, f"{where}.reflectance")
        if np.any(refl < 0) or (self.kind not in ("glass", "roughdielectric") and np.any(refl > 1)):
            raise SceneError(f"{where}.reflectance: must lie in [0, 1], got {tuple(refl)}")
        if not (math.isfinite(self.ior) and self.ior > 0):
            raise SceneError(f"{where}.ior: must be a positive number, got {self.ior!r}")
        if not (math.isfinite(self.roughness) and 1e-4 <= self.roughness <= 1.0):
            raise SceneError(f"{where}.roughness: must lie in [1e-4, 1], got {self.roughness!r}")
        if np.any(_rgb(self.emission, f"{where}.emission") < 0):
            raise SceneError(f"{where}.emission: must be non-negative")
        spec = _rgb(self.specular, f"{where}.specular")
        if np.any(spec < 0) or (self.kind != "roughdielectric" and np.any(spec > 1)):
            raise SceneError(f"{where}.specular: must lie in [0, 1], got {tuple(spec)}")
        if self.distribution not in MICROFACETS:
            raise SceneError(f"{where}.distribution: must be one of {', '.join(MICROFACETS)}, "
                             f"got {self.distribution!r}")
        if np.any(_rgb(self.conductor_eta, f"{where}.eta") < 0) or np.any(_rgb(self.conductor_k, f"{where}.k") < 0):
            raise SceneError(f"{where}: a conductor's eta and k must be non-negative")
        if not (math.isfinite(self.opacity) and 0.0 <= self.opacity <= 1.0):
            raise SceneError(f"{where}.opacity: must lie in [0, 1], got {self.opacity!r}")
        if self.roughness_v >= 0 and not (math.isfinite(self.roughness_v) and 1e-4 <= self.roughness_v <= 1.0):
            raise SceneError(f"{where}.roughness_v: must lie in [1e-4, 1], got {self.roughness_v!r}")
        if not (math.isfinite(self.blend_weight) and 0.0 <= self.blend_weight <= 1.0):
            raise SceneError(f"{where}.blend_weight: must lie in [0, 1], got {self.blend_weight!r}")


@dataclass
class Camera:
    """Perspective camera; `aperture_radius > 0` gives a thin lens focused at
    `focus_distance`. `fov_deg` is measured along `fov_axis`
    ('x', 'y', 'smaller' or 'larger'), as in Mitsuba.

    `projection="orthographic"` is Mitsuba's orthographic sensor: parallel
    rays along the view direction from a plane `near_clip` ahead, which
    spans `ortho_scale[0]` either side of the centre across the image and
    `ortho_scale[1] * height / width` up and down (the scale of its
    to_world); `fov_deg` and the lens are unused then.

    `pixel_filter` is the film's reconstruction filter, from which each
    eye ray samples its offset from the pixel centre (filter importance
    sampling, so every pixel stays an unbiased estimate of its filtered
    value): `box` (half-width `filter_radius`, default 0.5: the pixel
    itself), `tent` (1 - |x| / `filter_radius`, default 1) or `gaussian`
    (standard deviation `filter_stddev` pixels, minus its value at the
    cut-off `filter_radius`, default 4 stddev: Mitsuba 3's windowed
    Gaussian), tabulated in steps as Mitsuba's film applies them
    (`kernels.emit.filter_table`); a 2D filter is the product of two.
    Offsets stay on the film unless `sample_border`, as Mitsuba's film
    (its `sample_border`) weighs them."""
    position: tuple
    look_at: tuple
    up: tuple
    fov_deg: float
    width: int
    height: int
    fov_axis: str = "x"
    aperture_radius: float = 0.0
    focus_distance: float = 1.0
    near_clip: float = 0.0
    projection: str = "perspective"
    ortho_scale: tuple = (1.0, 1.0)
    pixel_filter: str = "box"
    filter_radius: float | None = None
    filter_stddev: float = 0.5
    sample_border: bool = False

    def validate(self, where: str = "camera") -> None:
        for name in ("position", "look_at", "up"):
            _rgb(getattr(self, name), f"{where}.{name}")
        if self.width is None or self.height is None:
            raise SceneError(f"{where}: missing resolution (width and height)")
        if int(self.width) < 1 or int(self.height) < 1:
            raise SceneError(f"{where}: resolution must be positive, got {self.width}x{self.height}")
        if self.projection not in ("perspective", "orthographic"):
            raise SceneError(f"{where}.projection: must be perspective or orthographic, "
                             f"got {self.projection!r}")
        if self.projection == "orthographic":
            if not (len(self.ortho_scale) == 2 and all(math.isfinite(v) and v > 0 for v in self.ortho_scale)):
                raise SceneError(f"{where}.ortho_scale: must be two positive numbers, got {self.ortho_scale!r}")
            if self.aperture_radius > 0:
                raise SceneError(f"{where}: an orthographic camera has no lens (aperture_radius > 0)")
        elif not (0 < self.fov_deg < 180):
            raise SceneError(f"{where}.fov: must lie in (0, 180) degrees, got {self.fov_deg!r}")
        if self.fov_axis not in ("x", "y", "smaller", "larger"):
            raise SceneError(f"{where}.fov_axis: must be x, y, smaller or larger, got {self.fov_axis!r}")
        self._validate_filter(where)
        fwd = np.subtract(self.look_at, self.position)
        if np.linalg.norm(fwd) == 0 or np.linalg.norm(np.cross(fwd, self.up)) == 0:
            raise SceneError(f"{where}: look_at must differ from position and not be parallel to up")
        if self.aperture_radius < 0 or (self.aperture_radius > 0 and self.focus_distance <= 0):
            raise SceneError(f"{where}: thin lens needs aperture >= 0 and focus_distance > 0")

    def _validate_filter(self, where: str) -> None:
        if self.pixel_filter not in PIXEL_FILTERS:
            raise SceneError(f"{where}.pixel_filter: must be one of {', '.join(PIXEL_FILTERS)}, "
                             f"got {self.pixel_filter!r}")
        if not (math.isfinite(self.filter_stddev) and self.filter_stddev > 0):
            raise SceneError(f"{where}.filter_stddev: must be a positive number, got {self.filter_stddev!r}")
        radius = self.filter_radius_px()
        if not (math.isfinite(radius) and 0 < radius <= MAX_FILTER_RADIUS):
            raise SceneError(f"{where}.filter_radius: must lie in (0, {MAX_FILTER_RADIUS}] pixels, "
                             f"got {radius!r}")

    def filter_radius_px(self) -> float:
        """The filter's half-width in pixels: as given, else Mitsuba's
        default: the box's 0.5, the tent's 1, the Gaussian's 4 standard
        deviations."""
        if self.filter_radius is not None:
            return float(self.filter_radius)
        return {"box": 0.5, "tent": 1.0}.get(self.pixel_filter, 4.0 * float(self.filter_stddev))

    def frame(self) -> np.ndarray:
        """Rows: position, right, up, forward (unit), (tan_x, tan_y, height),
        (aperture, focus, near clip), (orthographic 1 or 0, sample_border 1
        or 0, 0), (filter code of PIXEL_FILTERS, radius, stddev): an (8, 3)
        float64 array for the eye-ray kernel. Image right is forward x up, so
        Mitsuba scenes come out unmirrored. An orthographic camera puts the
        half width and half height of its view in place of tan_x and tan_y."""
        pos = np.asarray(self.position, np.float64)
        fwd = np.asarray(self.look_at, np.float64) - pos
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, np.asarray(self.up, np.float64))
        right /= np.linalg.norm(right)
        up = np.cross(right, fwd)
        t = math.tan(math.radians(self.fov_deg) / 2)
        w, h = int(self.width), int(self.height)
        axis = self.fov_axis
        if axis == "smaller":
            axis = "x" if w <= h else "y"
        elif axis == "larger":
            axis = "x" if w >= h else "y"
        tan_x, tan_y = (t, t * h / w) if axis == "x" else (t * w / h, t)
        ortho = self.projection == "orthographic"
        if ortho:
            tan_x, tan_y = self.ortho_scale[0], self.ortho_scale[1] * h / w
        lens = (self.aperture_radius, self.focus_distance, self.near_clip)
        pixel_filter = (PIXEL_FILTERS[self.pixel_filter], self.filter_radius_px(), self.filter_stddev)
        return np.array([pos, right, up, fwd, (tan_x, tan_y, h), lens,
                         (float(ortho), float(bool(self.sample_border)), 0.0), pixel_filter], dtype=np.float64)


@dataclass
class MaterialTable:
    """Struct-of-arrays view of the materials, indexed by material id."""
    kind: np.ndarray          # int32 (m,)
    reflectance: np.ndarray   # float32 (m, 3)
    emission: np.ndarray      # float32 (m, 3)
    ior: np.ndarray           # float32 (m,)
    roughness: np.ndarray     # float32 (m,)
    two_sided: np.ndarray     # bool (m,)
    names: list
    # The texture giving each material's reflectance, -1 for none. A
    # textured material's `reflectance` row is (1, 1, 1): the kernels fold
    # the texel into the path weight at the hit (`kernels.texture`), so
    # every reader of `reflectance` multiplies by the texel through it.
    texture: np.ndarray = None  # int32 (m,)
    specular: np.ndarray = None      # float32 (m, 3): coating / reflection tint
    distribution: np.ndarray = None  # int32 (m,): index into MICROFACETS
    nonlinear: np.ndarray = None     # bool (m,)
    opacity: np.ndarray = None       # float32 (m,): Mitsuba's mask
    conductor_eta: np.ndarray = None  # float32 (m, 3): real part of a conductor's index
    conductor_k: np.ndarray = None    # float32 (m, 3): its imaginary part
    # Normal and bump maps (texture ids, -1 for none; `Material`).
    normal_map: np.ndarray = None     # int32 (m,)
    bump_map: np.ndarray = None       # int32 (m,)
    bump_scale: np.ndarray = None     # float32 (m,)
    shading_flags: np.ndarray = None  # int32 (m,)
    opacity_texture: np.ndarray = None  # int32 (m,): a mask's textured opacity, -1 for none
    blend: np.ndarray = None          # int32 (m, 2): a blendbsdf's two materials, -1 for none
    blend_weight: np.ndarray = None   # float32 (m,): the second one's probability
    blend_texture: np.ndarray = None  # int32 (m,): a textured weight, -1 for none
    # The texture (an index into the LightTable's own textures) that
    # `emission` is multiplied by, -1 for none (`scene.light_textures`).
    emission_texture: np.ndarray = None  # int32 (m,)
    # Anisotropic and textured roughness of a rough conductor (`Material`).
    roughness_v: np.ndarray = None      # float32 (m,): alpha_v, < 0 for `roughness`
    alpha_u_texture: np.ndarray = None  # int32 (m,)
    alpha_v_texture: np.ndarray = None  # int32 (m,)

    def __post_init__(self):
        # Tables made before these columns (tests, older callers) get the
        # defaults: white coating, GGX, linear, opaque.
        m = len(self.kind)
        if self.texture is None:
            self.texture = np.full(m, -1, np.int32)
        if self.specular is None:
            self.specular = np.ones((m, 3), np.float32)
        if self.distribution is None:
            self.distribution = np.zeros(m, np.int32)
        if self.nonlinear is None:
            self.nonlinear = np.zeros(m, np.bool_)
        if self.opacity is None:
            self.opacity = np.ones(m, np.float32)
        if self.conductor_eta is None:
            self.conductor_eta = np.zeros((m, 3), np.float32)
        if self.conductor_k is None:
            self.conductor_k = np.ones((m, 3), np.float32)
        for name, dtype, value in (("normal_map", np.int32, -1), ("bump_map", np.int32, -1),
                                   ("bump_scale", np.float32, 1.0), ("shading_flags", np.int32, 3),
                                   ("opacity_texture", np.int32, -1), ("blend_weight", np.float32, 0.0),
                                   ("blend_texture", np.int32, -1), ("emission_texture", np.int32, -1),
                                   ("roughness_v", np.float32, -1.0), ("alpha_u_texture", np.int32, -1),
                                   ("alpha_v_texture", np.int32, -1)):
            if getattr(self, name) is None:
                setattr(self, name, np.full(m, value, dtype))
        if self.blend is None:
            self.blend = np.full((m, 2), -1, np.int32)

    @property
    def textured(self) -> bool:
        return bool(np.any(self.texture >= 0))

    @property
    def shading_mapped(self) -> bool:
        """Whether a material has a normal or bump map (`kernels.shading`)."""
        return bool(np.any(self.normal_map >= 0) or np.any(self.bump_map >= 0))

    @classmethod
    def from_materials(cls, mats: list[Material]) -> "MaterialTable":
        refl = [(1.0, 1.0, 1.0) if m.texture >= 0 else _rgb(m.reflectance, m.name) for m in mats]
        return cls(
            kind=np.array([MATERIAL_KINDS[m.kind] for m in mats], np.int32),
            reflectance=np.array(refl, np.float32).reshape(-1, 3),
            emission=np.array([_rgb(m.emission, m.name) for m in mats], np.float32).reshape(-1, 3),
            ior=np.array([m.ior for m in mats], np.float32),
            roughness=np.array([m.roughness for m in mats], np.float32),
            two_sided=np.array([m.two_sided for m in mats], np.bool_),
            names=[m.name for m in mats],
            texture=np.array([m.texture for m in mats], np.int32),
            specular=np.array([_rgb(m.specular, m.name) for m in mats], np.float32).reshape(-1, 3),
            distribution=np.array([MICROFACETS.index(m.distribution) for m in mats], np.int32),
            nonlinear=np.array([m.nonlinear for m in mats], np.bool_),
            opacity=np.array([m.opacity for m in mats], np.float32),
            conductor_eta=np.array([_rgb(m.conductor_eta, m.name) for m in mats], np.float32).reshape(-1, 3),
            conductor_k=np.array([_rgb(m.conductor_k, m.name) for m in mats], np.float32).reshape(-1, 3),
            normal_map=np.array([m.normal_map for m in mats], np.int32),
            bump_map=np.array([m.bump_map for m in mats], np.int32),
            bump_scale=np.array([m.bump_scale for m in mats], np.float32),
            shading_flags=np.array([m.shading_flags for m in mats], np.int32),
            opacity_texture=np.array([m.opacity_texture for m in mats], np.int32),
            blend=np.array([m.blend for m in mats], np.int32).reshape(-1, 2),
            blend_weight=np.array([m.blend_weight for m in mats], np.float32),
            blend_texture=np.array([m.blend_texture for m in mats], np.int32),
            emission_texture=np.array([m.emission_texture for m in mats], np.int32),
            roughness_v=np.array([m.roughness_v for m in mats], np.float32),
            alpha_u_texture=np.array([m.alpha_u_texture for m in mats], np.int32),
            alpha_v_texture=np.array([m.alpha_v_texture for m in mats], np.int32),
        )


@dataclass
class Scene:
    vertices: np.ndarray        # float32 (nv, 3)
    triangles: np.ndarray       # int32 (nt, 3)
    tri_material: np.ndarray    # int32 (nt,)
    materials: MaterialTable
    lights: LightTable
    camera: Camera
    name: str = "scene"
    source: str = "<memory>"
    render_settings: dict = field(default_factory=dict)  # hints a scene file carries
    # Per-vertex texture coordinates, float32 (nv, 2), Mitsuba's convention
    # (see `textures`); (0, 2) when the scene has none, so it stores nothing.
    uvs: np.ndarray = None
    textures: TextureTable = None
    # Per-vertex shading normals, float32 (nv, 3), of smooth meshes (zero at
    # a flat mesh's vertices: `kernels.smooth`); (0, 3) when every mesh is flat.
    normals: np.ndarray = None

    def __post_init__(self):
        if self.uvs is None:
            self.uvs = np.zeros((0, 2), np.float32)
        if self.normals is None:
            self.normals = np.zeros((0, 3), np.float32)
        if self.textures is None:
            self.textures = TextureTable.empty()

    @property
    def triangle_count(self) -> int:
        return int(self.triangles.shape[0])

    def bounds(self) -> np.ndarray:
        """(2, 3) float64 box of the geometry and the point/spot lights."""
        pts = [self.vertices.astype(np.float64)]
        delta = np.isin(self.lights.kind, (LIGHT_POINT, LIGHT_SPOT, LIGHT_PROJECTOR))
        if np.any(delta):
            pts.append(self.lights.p0[delta])
        allp = np.concatenate(pts)
        return np.stack([allp.min(0), allp.max(0)])

    def diagonal(self) -> float:
        b = self.bounds()
        return float(np.linalg.norm(b[1] - b[0]))

    def spawn_epsilon(self) -> float:
        return SPAWN_EPSILON * self.diagonal()

    def header(self) -> "SceneHeader":
        return SceneHeader(self.materials, self.lights, self.camera, self.bounds(), self.name,
                           self.source, dict(self.render_settings), self.textures)


@dataclass
class SceneHeader:
    """Everything of a scene except its triangles: what a chunk store's
    manifest, the server and OSPPM need (materials, lights, camera, bounds)."""
    materials: MaterialTable
    lights: LightTable
    camera: Camera
    bounds: np.ndarray          # float64 (2, 3), as Scene.bounds()
    name: str = "scene"
    source: str = "<memory>"
    render_settings: dict = field(default_factory=dict)
    textures: TextureTable = None

    def __post_init__(self):
        if self.textures is None:
            self.textures = TextureTable.empty()

    def diagonal(self) -> float:
        return float(np.linalg.norm(self.bounds[1] - self.bounds[0]))

    def spawn_epsilon(self) -> float:
        return SPAWN_EPSILON * self.diagonal()

    def to_wire(self) -> dict:
        """msgpack-ready dict: arrays as (dtype, shape, raw bytes)."""
        return {"materials": {k: _pack(v) for k, v in vars(self.materials).items()},
                "lights": {k: _pack(v) for k, v in self.lights.wire_fields().items()},
                "camera": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(self.camera).items()},
                "bounds": _pack(self.bounds), "name": self.name, "source": self.source,
                "render_settings": dict(self.render_settings),
                "textures": {k: _pack(v) for k, v in vars(self.textures).items()}}

    @classmethod
    def from_wire(cls, d: dict) -> "SceneHeader":
        """Inverse of to_wire; a malformed dict raises SceneError naming the field."""
        try:
            mats = MaterialTable(**{k: _unpack(v) for k, v in d["materials"].items()})
            lights = LightTable(**{k: _unpack(v) for k, v in d["lights"].items()})
            cam = {k: (tuple(v) if isinstance(v, list) else v) for k, v in d["camera"].items()}
            textures = TextureTable(**{k: _unpack(v) for k, v in d["textures"].items()})
            header = cls(mats, lights, Camera(**cam), _unpack(d["bounds"]), d["name"],
                         d["source"], dict(d["render_settings"]), textures)
        except (KeyError, TypeError, ValueError) as e:
            raise SceneError(f"scene header: malformed field {e}") from None
        header.camera.validate("scene header: camera")
        return header


def _pack(v):
    if isinstance(v, np.ndarray):
        return arrays.pack(v)
    return list(v) if isinstance(v, tuple) else v


def _unpack(v):
    return arrays.unpack(v, copy=True) if arrays.is_packed(v) else v


@dataclass
class _Mesh:
    vertices: np.ndarray
    faces: np.ndarray
    material: int
    uv: np.ndarray | None = None
    normals: np.ndarray | None = None


@dataclass
class SceneBuilder:
    """Collects meshes, materials, lights and a camera, then validates them
    into a `Scene`. `source` names the file for error messages."""
    source: str = "<memory>"
    name: str = "scene"
    _materials: list = field(default_factory=list)
    _material_ids: dict = field(default_factory=dict)
    _meshes: list = field(default_factory=list)
    _delta_lights: list = field(default_factory=list)
    _directional: list = field(default_factory=list)
    _environment: tuple | None = None
    _textures: list = field(default_factory=list)
    _emission_textures: list = field(default_factory=list)
    camera: Camera | None = None

    def add_texture(self, texture: Texture) -> int:
        """A texture materials may name by the id returned."""
        self._textures.append(texture)
        return len(self._textures) - 1

    def add_emission_texture(self, texture: Texture) -> tuple[int, np.ndarray]:
        """A texture an emissive material's `emission` may be multiplied by:
        (its `emission_texture` id, the mean RGB texel, by which the kernels'
        copy is divided: give `emission` times that mean, so that the
        light's power counts the texture)."""
        scaled, mean = normalised(texture)
        self._emission_textures.append(scaled)
        return len(self._emission_textures) - 1, mean

    def add_material(self, material: Material, where: str | None = None) -> int:
        where = where or f"{self.source}: material {material.name!r}"
        material.validate(where)
        for name in ("texture", "opacity_texture", "blend_texture", "normal_map", "bump_map",
                     "alpha_u_texture", "alpha_v_texture"):
            if not -1 <= getattr(material, name) < len(self._textures):
                raise SceneError(f"{where}: {name} id {getattr(material, name)} out of range")
        if not -1 <= material.emission_texture < len(self._emission_textures):
            raise SceneError(f"{where}: emission texture id {material.emission_texture} out of range")
        if material.blend != (-1, -1) and not all(0 <= b < len(self._materials) for b in material.blend):
            raise SceneError(f"{where}: blend of material ids {material.blend}, not two earlier materials")
        if material.name in self._material_ids:
            raise SceneError(f"{where}: duplicate material name {material.name!r}")
        self._material_ids[material.name] = len(self._materials)
        self._materials.append(material)
        return self._material_ids[material.name]

    def textured(self, material: int) -> bool:
        """Whether material id `material` reads a texture (its meshes keep
        UVs): its colour, a mask's opacity, a blend's weight or its parts',
        a normal or bump map, or its emission; or it is anisotropic (its
        frame follows dp/du)."""
        m = self._materials[material]
        if max(m.texture, m.opacity_texture, m.blend_texture, m.normal_map, m.bump_map,
               m.emission_texture, m.alpha_u_texture, m.alpha_v_texture) >= 0 or m.roughness_v >= 0:
            return True
        return m.blend != (-1, -1) and any(self.textured(b) for b in m.blend)

    def material_id(self, name: str, where: str) -> int:
        try:
            return self._material_ids[name]
        except KeyError:
            raise SceneError(f"{where}: unknown material {name!r}") from None

    def add_mesh(self, vertices, faces, material: str | int, where: str,
                 transform: np.ndarray | None = None, uv=None, normals=None) -> None:
        """Add triangles. `transform` is a 4x4 object-to-world matrix; `uv`
        (nv, 2) the vertices' texture coordinates, if the mesh has any;
        `normals` a smooth mesh's (nv, 3) vertex normals, or "computed" for
        Mitsuba's own (`scene.normals`), None for a flat mesh."""
        v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
        f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        if not np.all(np.isfinite(v)):
            raise SceneError(f"{where}: vertices contain NaN or Inf")
        if uv is not None:
            uv = np.asarray(uv, np.float64)
            if uv.shape != (len(v), 2) or not np.all(np.isfinite(uv)):
                raise SceneError(f"{where}: texture coordinates must be {len(v)} finite (u, v) pairs")
        if f.size and (f.min() < 0 or f.max() >= len(v)):
            raise SceneError(f"{where}: face index out of range (0..{len(v) - 1})")
        if transform is not None:
            t = np.asarray(transform, np.float64)
            v = v @ t[:3, :3].T + t[:3, 3]
            if not np.all(np.isfinite(v)):
                raise SceneError(f"{where}: transform produced NaN or Inf vertices")
        normals = smooth_normals(normals, vertices, v, f, transform, where)
        mid = material if isinstance(material, int) else self.material_id(material, where)
        if not self.textured(mid):
            uv = None       # only textured surfaces store UVs: the rest pay nothing
        elif uv is None:
            # Mitsuba's uv on a mesh without texture coordinates is the
            # hit's barycentrics (b1, b2): one vertex per corner gives that.
            normals = None if normals is None else normals[f].reshape(-1, 3)
            v, f = v[f].reshape(-1, 3), np.arange(f.size).reshape(-1, 3)
            uv = np.tile([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], (len(f), 1))
        self._meshes.append(_Mesh(v, f, mid, uv, normals))

    def add_point_light(self, position, intensity, where: str) -> None:
        pos, val = _rgb(position, f"{where}.position"), _rgb(intensity, f"{where}.intensity")
        if np.any(val < 0):
            raise SceneError(f"{where}.intensity: must be non-negative")
        self._delta_lights.append((LIGHT_POINT, pos, np.zeros(3), val, np.zeros(4)))

    def add_spot_light(self, position, target, intensity, cutoff_deg: float,
                       beam_width_deg: float | None, where: str, x_axis=None,
                       texture: Texture | None = None) -> None:
        """Mitsuba's spot: full intensity inside `beam_width_deg`, falling
        linearly in angle to zero at `cutoff_deg`, times `texture` (an image
        spanning the cutoff's square, `x_axis` its horizontal) if given."""
        pos, tgt = _rgb(position, f"{where}.position"), _rgb(target, f"{where}.target")
        val = _rgb(intensity, f"{where}.intensity")
        axis = tgt - pos
        if np.linalg.norm(axis) == 0:
            raise SceneError(f"{where}: target equals position")
        if not (0 < cutoff_deg < 180):
            raise SceneError(f"{where}.cutoff_angle: must lie in (0, 180), got {cutoff_deg}")
        beam = cutoff_deg * 0.75 if beam_width_deg is None else beam_width_deg
        if not (0 < beam <= cutoff_deg):
            raise SceneError(f"{where}.beam_width: must lie in (0, cutoff_angle], got {beam}")
        c, b = math.radians(cutoff_deg), math.radians(beam)
        cone = np.array([math.cos(c), math.cos(b), c, b])
        axis = axis / np.linalg.norm(axis)
        if texture is None:
            self._delta_lights.append((LIGHT_SPOT, pos, axis, val, cone))
            return
        if cutoff_deg >= 90:
            raise SceneError(f"{where}.cutoff_angle: a textured spot's must be below 90, got {cutoff_deg}")
        x = _image_x_axis(axis, x_axis, where)
        self._delta_lights.append((LIGHT_SPOT, pos, axis, val, cone, x, texture))

    def add_directional_light(self, direction, irradiance, where: str) -> None:
        """Mitsuba's directional: parallel light travelling along
        `direction`, of `irradiance` (W/m^2) on a plane facing it."""
        d, val = _rgb(direction, f"{where}.direction"), _rgb(irradiance, f"{where}.irradiance")
        if np.any(val < 0):
            raise SceneError(f"{where}.irradiance: must be non-negative")
        if not np.linalg.norm(d) > 0:
            raise SceneError(f"{where}.direction: must not be zero")
        self._directional.append((d / np.linalg.norm(d), val))

    def set_environment(self, texels, to_world, where: str) -> None:
        """The environment light: `texels` as `LightTable.env_texels`
        (`scene.envmap`), `to_world` a 3x3 rotation. At most one."""
        if self._environment is not None:
            raise SceneError(f"{where}: only one environment emitter (envmap or constant) per scene")
        t = np.ascontiguousarray(texels, np.float32)
        r = np.asarray(to_world, np.float64)
        if t.ndim != 3 or t.shape[0] < 2 or t.shape[1] < 2 or t.shape[2] != 3 or not np.all(np.isfinite(t)):
            raise SceneError(f"{where}: environment texels must be finite, (H >= 2, W >= 2, 3)")
        if r.shape != (3, 3) or not np.allclose(r @ r.T, np.eye(3), atol=1e-5) or np.linalg.det(r) < 0:
            raise SceneError(f"{where}.to_world: an environment takes a rotation only")
        self._environment = (np.maximum(t, 0.0), r)

    def add_projector_light(self, position, axis, x_axis, irradiance, tan_half_fov: float, where: str,
                            texture: Texture | None = None) -> None:
        """Mitsuba's projector: the plane at distance 1 along `axis`, within
        +-tan_half_fov along `x_axis` (and +-tan_half_fov / aspect across
        it, the texture's aspect), gets pi x `irradiance` (times the
        `texture` seen there, if given)."""
        pos, val = _rgb(position, f"{where}.position"), _rgb(irradiance, f"{where}.irradiance")
        z = np.asarray(axis, np.float64)
        if np.any(val < 0):
            raise SceneError(f"{where}.irradiance: must be non-negative")
        if not (math.isfinite(tan_half_fov) and tan_half_fov > 0):
            raise SceneError(f"{where}.fov: must lie in (0, 180) degrees")
        z = z / np.linalg.norm(z)
        x = _image_x_axis(z, x_axis, f"{where}.to_world")
        aspect = 1.0 if texture is None else texture.texels.shape[1] / texture.texels.shape[0]
        cone = np.array([tan_half_fov, tan_half_fov / aspect, 0.0, 0.0])
        self._delta_lights.append((LIGHT_PROJECTOR, pos, z, val, cone, x) + ((texture,) if texture else ()))

    # -- building ---------------------------------------------------------
    def build(self) -> Scene:
        if self.camera is None:
            raise SceneError(f"{self.source}: no camera")
        self.camera.validate(f"{self.source}: camera")
        if not self._meshes:
            raise SceneError(f"{self.source}: no geometry")
        verts, tris, mats = self._merge_meshes()
        mtable = MaterialTable.from_materials(self._materials)
        lights = self._light_table(verts, tris, mats, mtable, self._merged_uv())
        if lights.kind.size == 0 or lights.total_power <= 0:
            raise SceneError(f"{self.source}: no light (no emissive material, point or spot light)")
        return Scene(verts.astype(np.float32), tris.astype(np.int32), mats.astype(np.int32),
                     mtable, lights, self.camera, self.name, self.source, uvs=self._merged_uv(),
                     textures=TextureTable.from_textures(self._textures), normals=self._merged_normals())

    def _merged_normals(self) -> np.ndarray:
        """The vertices' shading normals in merged order, zero for flat
        meshes; (0, 3) when all are flat, so flat scenes store nothing."""
        if all(m.normals is None for m in self._meshes):
            return np.zeros((0, 3), np.float32)
        return np.concatenate([np.zeros((len(m.vertices), 3)) if m.normals is None else m.normals
                               for m in self._meshes]).astype(np.float32)

    def _merged_uv(self) -> np.ndarray:
        """The vertices' UVs in merged order; (0, 2) when no mesh has any
        (meshes without UVs among some with get (0, 0))."""
        if all(m.uv is None for m in self._meshes):
            return np.zeros((0, 2), np.float32)
        return np.concatenate([np.zeros((len(m.vertices), 2)) if m.uv is None else m.uv
                               for m in self._meshes]).astype(np.float32)

    def _merge_meshes(self):
        offsets = np.cumsum([0] + [len(m.vertices) for m in self._meshes])
        verts = np.concatenate([m.vertices for m in self._meshes])
        tris = np.concatenate([m.faces + o for m, o in zip(self._meshes, offsets)])
        mats = np.concatenate([np.full(len(m.faces), m.material, np.int32) for m in self._meshes])
        area2 = np.linalg.norm(_triangle_cross(verts, tris), axis=1)
        # Degenerate: zero area relative to the edge lengths (a sliver with
        # collapsed vertices); Embree never hits them and lights must not emit.
        edge = np.linalg.norm(verts[tris[:, 1]] - verts[tris[:, 0]], axis=1) + \
            np.linalg.norm(verts[tris[:, 2]] - verts[tris[:, 0]], axis=1)
        keep = area2 > 1e-12 * np.maximum(edge * edge, 1e-300)
        dropped = int((~keep).sum())
        if dropped:
            warnings.warn(f"{self.source}: dropped {dropped} degenerate triangle(s)", stacklevel=3)
        if not np.any(keep):
            raise SceneError(f"{self.source}: every triangle is degenerate")
        return verts, tris[keep], mats[keep]

    def _light_table(self, verts, tris, mats, mtable: MaterialTable, uvs) -> LightTable:
        emit = mtable.emission.astype(np.float64)[mats]
        lit = np.flatnonzero(emit.max(axis=1) > 0)
        p0, p1, p2 = (verts[tris[lit, k]] for k in range(3))
        # The sphere of the infinite lights: that of the box Scene.bounds() gives.
        pts = np.concatenate([verts] + [d[1][None] for d in self._delta_lights])
        lo, hi = pts.min(0), pts.max(0)
        sphere = (0.5 * (lo + hi), bounding_radius(lo, hi))
        tri_texture = mtable.emission_texture[mats[lit]]
        tri_uv = np.zeros((len(lit), 6))
        if len(uvs):
            tri_uv = uvs[tris[lit]].reshape(-1, 6).astype(np.float64)
        return light_table(p0, p1, p2, emit[lit], self._delta_lights, self._directional,
                           self._environment, sphere, (tri_texture, tri_uv, self._emission_textures))


def _image_x_axis(axis, x_axis, where: str) -> np.ndarray:
    """`x_axis` made a unit vector perpendicular to the unit `axis`."""
    x = np.asarray(x_axis, np.float64)
    x = x - axis * (x @ axis)
    if not np.linalg.norm(x) > 1e-9:
        raise SceneError(f"{where}: degenerate")
    return x / np.linalg.norm(x)


def _triangle_cross(verts: np.ndarray, tris: np.ndarray) -> np.ndarray:
    v0 = verts[tris[:, 0]]
    return np.cross(verts[tris[:, 1]] - v0, verts[tris[:, 2]] - v0)
