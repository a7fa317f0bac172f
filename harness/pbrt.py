"""pbrt-v4 as a peer renderer: our `Scene` written as a pbrt-v4 scene, and
the `pbrt` binary run on it (this is the only module that knows pbrt's
scene format and command line).

pbrt-v4's `sppm` integrator is the strongest public SPPM, and its `path`
integrator a second independent reference beside Mitsuba 3. The binary is
`$DOSPPM_PBRT`, else `pbrt` on the PATH (the project's peers folder has a
script that builds one); without it the evaluation skips the pbrt methods.

Mapping (our conventions follow Mitsuba's; see `harness.reference`):

=========  ==========================================================
ours       pbrt-v4
=========  ==========================================================
diffuse    `diffuse`, reflectance
mirror     `conductor`, roughness 0, Fresnel 1 (eta 1, k 1e4), tinted
glossy     `conductor`, roughness = alpha (remaproughness false), as mirror
glass      `dielectric`, eta = ior
tint       grey tint t < 1: `mix` of the surface (amount t) and black;
           a coloured mirror/glossy tint: the conductor's `reflectance`
           (exact at normal incidence, whiter towards grazing: pbrt-v4 has
           no tinted Fresnel-1 conductor); coloured glass: an error
two_sided  ignored: pbrt-v4 surfaces reflect on both sides (ours are black
           behind when one-sided, which only matters where a back is seen)
emission   `diffuse` AreaLightSource, one-sided along the CCW winding normal
point      `point`, I (W/sr)
spot       `spot`, I, coneangle = cutoff, conedeltaangle = cutoff - beam
           (pbrt's falloff is a smoothstep in cos, ours linear in angle)
camera     `Scale -1 1 1` before `LookAt` (pbrt's camera is left-handed:
           without it the image is mirrored), `perspective`, fov along the
           shorter image axis, lensradius / focaldistance for a thin lens
film       `rgb` film, EXR, the camera's filter (`pixel_filter`: box, triangle
           for our tent, gaussian), `independent` sampler
           (not pmj02bn: its tables are stand-ins in the shared build)
depth      pbrt's `maxdepth` counts bounces as our `max_depth` does; the
           evaluation runs pbrt at 100 (`suites.PEER_DEPTH`), since the
           references are unbounded
=========  ==========================================================

Units: pbrt-v4 renders spectrally, and divides each light's spectrum by its
luminance, so an `rgb` emission of a grey light comes out as those RGB
numbers (a closed-form sphere agrees to 0.03%).
Coloured lights and reflectances go through pbrt's RGB-to-spectrum
upsampling: products of saturated colours differ from an RGB renderer's by
a few percent.

Why the evaluation's pbrt-v4 images came out 1-34% dark against Mitsuba 3's
references (`benchmarks/pbrt_dark.py`, table `pbrt-dark` in
docs/accuracy.md, which separates the causes scene by scene): its depth
(issue 12 ran it at 10, the references are unbounded; a lamp in glass
lost most), its spectra (coloured walls and lamps), and on
`far-from-origin` its float32 at 1e5. cardioid's deficit for `path` is
path tracing's blind spot, a point light's caustic off a mirror.
"""
from __future__ import annotations

import math
import os
import re
import shutil
import subprocess
import time
from dataclasses import dataclass

import numpy as np

from dosppm_core.film import read_exr
from dosppm_core.scene.model import (
    DIFFUSE,
    GLASS,
    GLOSSY,
    LIGHT_POINT,
    LIGHT_SPOT,
    MIRROR,
    Camera,
    Scene,
    SceneError,
)

BINARY_ENV = "DOSPPM_PBRT"
BUILD_HINT = "build pbrt-v4 and put it on the PATH, or set DOSPPM_PBRT"
# A conductor with eta 1 and a huge k reflects everything at every angle:
# Mitsuba's `conductor` with material "none" (Fresnel 1).
PERFECT_CONDUCTOR = '"spectrum eta" [300 1 900 1] "spectrum k" [300 1e4 900 1e4]'
# The directives this module writes; those of a given scene file are dropped.
RENDER_DIRECTIVES = ("Sampler", "Integrator", "Film", "PixelFilter")


class PbrtError(RuntimeError):
    """pbrt is missing or failed, or a scene has no pbrt equivalent; one line."""


@dataclass(frozen=True)
class RenderSettings:
    """One pbrt run: `samples` is spp for `path` and iterations for `sppm`
    (pbrt's SPPM runs one iteration per pixel sample)."""
    integrator: str                    # 'path' or 'sppm'
    samples: int
    max_depth: int
    width: int
    height: int
    photons_per_iteration: int = 100_000
    radius: float = 1.0                # SPPM's initial radius (pbrt's default 1)
    pixel_filter: str = 'PixelFilter "box" "float xradius" 0.5 "float yradius" 0.5'   # `pixel_filter_line`


def pixel_filter_line(cam: Camera) -> str:
    """pbrt's PixelFilter for our camera's: its gaussian is Mitsuba's
    windowed one (untabulated), its triangle our tent. pbrt samples the
    filter past the film's edges, as our `sample_border` does."""
    r = _num(cam.filter_radius_px())
    radii = f'"float xradius" {r} "float yradius" {r}'
    if cam.pixel_filter == "gaussian":
        return f'PixelFilter "gaussian" "float sigma" {_num(cam.filter_stddev)} {radii}'
    return f'PixelFilter "{"triangle" if cam.pixel_filter == "tent" else "box"}" {radii}'


# -- the binary -------------------------------------------------------------

def find_binary() -> str | None:
    """$DOSPPM_PBRT when set (None if it is no executable), else `pbrt` on the PATH."""
    given = os.environ.get(BINARY_ENV)
    if given:
        return given if os.path.isfile(given) and os.access(given, os.X_OK) else None
    return shutil.which("pbrt")


def missing_reason() -> str | None:
    """None, or why pbrt cannot run here (one line)."""
    if find_binary():
        return None
    given = os.environ.get(BINARY_ENV)
    if given:
        return f"{BINARY_ENV}={given} is not an executable file ({BUILD_HINT})"
    return f"pbrt is not on the PATH ({BUILD_HINT})"


def render(scene_file: str, out_path: str, seed: int, threads: int = 2) -> tuple[float, np.ndarray]:
    """(seconds, image): `pbrt` on `scene_file`, timed as a whole process
    (start, scene load and BVH build included)."""
    binary = find_binary()
    if binary is None:
        raise PbrtError(missing_reason())
    cmd = [binary, "--nthreads", str(threads), "--quiet", "--seed", str(seed),
           "--outfile", out_path, scene_file]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    seconds = time.perf_counter() - t0
    if done.returncode != 0:
        last = (done.stderr.strip() or done.stdout.strip() or "no output").splitlines()[-1]
        raise PbrtError(f"pbrt failed on {scene_file} (exit {done.returncode}): {last}")
    return seconds, read_exr(out_path)[0]


# -- render settings in a scene file ------------------------------------------

def render_directives(s: RenderSettings, out_path: str) -> str:
    if s.integrator == "path":
        integrator = f'Integrator "path" "integer maxdepth" {s.max_depth}'
    elif s.integrator == "sppm":
        integrator = (f'Integrator "sppm" "integer maxdepth" {s.max_depth} '
                      f'"integer photonsperiteration" {s.photons_per_iteration} '
                      f'"float radius" {_num(s.radius)}')
    else:
        raise ValueError(f"unknown pbrt integrator {s.integrator!r} (known: path, sppm)")
    return "\n".join([
        f'Sampler "independent" "integer pixelsamples" {s.samples}',
        integrator,
        (f'Film "rgb" "integer xresolution" {s.width} "integer yresolution" {s.height} '
         f'"string filename" "{out_path}"'),
        s.pixel_filter, ""])


def with_render_settings(scene_text: str, directives: str, base_dir: str) -> str:
    """`scene_text` with its sampler, integrator, film and filter replaced by
    `directives`, and its relative file names made absolute against
    `base_dir` (the copy is written elsewhere)."""
    head, sep, world = scene_text.partition("WorldBegin")
    if not sep:
        raise PbrtError("pbrt scene has no WorldBegin")
    kept = [s for s in _statements(head) if s.split(None, 1)[0] not in RENDER_DIRECTIVES]
    return _absolute_names("".join(kept) + directives + sep + world, base_dir)


def _statements(text: str) -> list[str]:
    """Split on lines that start with a directive name (a parameter list may
    go on over lines that start with a quote, bracket, number or comment)."""
    out = []
    for line in text.splitlines(keepends=True):
        if re.match(r"\s*[A-Z]", line) or not out:
            out.append(line)
        else:
            out[-1] += line
    return [s for s in out if s.strip()]


def _absolute_names(text: str, base_dir: str) -> str:
    def fix(m):
        name = m.group(2)
        return m.group(1) + (name if os.path.isabs(name) else os.path.join(base_dir, name)) + m.group(3)
    text = re.sub(r'("string filename"\s*\[?\s*")([^"]+)(")', fix, text)
    return re.sub(r'(\b(?:Include|Import)\s+")([^"]+)(")', fix, text)


# -- our scene as a pbrt scene ------------------------------------------------

def write_scene(scene: Scene, directory: str) -> str:
    """Write `scene` as `directory/scene.pbrt` (camera and world, no render
    settings) with one binary PLY per material; returns the .pbrt path."""
    os.makedirs(directory, exist_ok=True)
    lines = ["# written by dosppm from " + scene.source, *camera_lines(scene.camera),
             "WorldBegin", *light_lines(scene)]
    for mid in np.unique(scene.tri_material):
        ply = f"mesh-{int(mid)}.ply"
        write_ply(os.path.join(directory, ply), scene.vertices,
                  scene.triangles[scene.tri_material == mid])
        lines += ["AttributeBegin", *surface_lines(scene, int(mid)),
                  f'  Shape "plymesh" "string filename" "{ply}"', "AttributeEnd"]
    path = os.path.join(directory, "scene.pbrt")
    with open(path, "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")
    return path


def camera_lines(cam: Camera) -> list[str]:
    """Our camera's image right is forward x up; pbrt's is up x forward, so
    `Scale -1 1 1` flips the camera's x. pbrt's fov spans the shorter axis."""
    if cam.projection != "perspective":
        # pbrt's orthographic rays start at the camera, Mitsuba's at near_clip: not yet mapped.
        raise PbrtError(f"camera: no pbrt mapping for a {cam.projection} camera")
    tan_x, tan_y = cam.frame()[4, :2]
    fov = 2.0 * math.degrees(math.atan(tan_x if cam.width <= cam.height else tan_y))
    camera = f'Camera "perspective" "float fov" [ {_num(fov)} ]'
    if cam.aperture_radius > 0:
        camera += (f' "float lensradius" {_num(cam.aperture_radius)}'
                   f' "float focaldistance" {_num(cam.focus_distance)}')
    return ["Scale -1 1 1",
            "LookAt " + "   ".join(_vec(v) for v in (cam.position, cam.look_at, cam.up)), camera]


def light_lines(scene: Scene) -> list[str]:
    """Point and spot lights; area lights go with their triangles."""
    lights, out = scene.lights, []
    if np.any(lights.kind > LIGHT_SPOT):
        raise SceneError(f"{scene.source}: directional, environment and projector lights have no pbrt mapping here")
    for i in np.flatnonzero(lights.kind == LIGHT_POINT):
        out.append(f'LightSource "point" "point3 from" [{_vec(lights.p0[i])}] '
                   f'"rgb I" [{_vec(lights.value[i])}]')
    for i in np.flatnonzero(lights.kind == LIGHT_SPOT):
        cutoff, beam = np.degrees(lights.cone[i, 2:4])
        out.append(f'LightSource "spot" "point3 from" [{_vec(lights.p0[i])}] '
                   f'"point3 to" [{_vec(lights.p0[i] + lights.p1[i])}] '
                   f'"rgb I" [{_vec(lights.value[i])}] "float coneangle" {_num(cutoff)} '
                   f'"float conedeltaangle" {_num(cutoff - beam)}')
    return out


def surface_lines(scene: Scene, mid: int) -> list[str]:
    """The material of `mid` (named `m<mid>`) and, if it glows, its area light."""
    mats, out = scene.materials, []
    if mats.texture[mid] >= 0:
        raise PbrtError(f"material {mats.names[mid]!r}: textured materials have no pbrt mapping here")
    if mats.normal_map[mid] >= 0 or mats.bump_map[mid] >= 0:
        raise PbrtError(f"material {mats.names[mid]!r}: normal and bump maps have no pbrt mapping here")
    if mats.opacity_texture[mid] >= 0 or mats.blend[mid, 1] >= 0:
        raise PbrtError(f"material {mats.names[mid]!r}: textured masks and blends have no pbrt mapping here")
    if np.max(mats.emission[mid]) > 0:
        out.append(f'  AreaLightSource "diffuse" "rgb L" [{_vec(mats.emission[mid])}]')
    tint = np.asarray(mats.reflectance[mid], float)
    kind = int(mats.kind[mid])
    if kind == DIFFUSE:
        return out + [f'  Material "diffuse" "rgb reflectance" [{_vec(tint)}]']
    grey = bool(np.all(tint == tint[0]))
    if kind == GLASS:
        if not grey:
            raise PbrtError(f"material {mats.names[mid]!r}: pbrt-v4 has no coloured glass tint")
        surface = f'"dielectric" "float eta" {_num(mats.ior[mid])}'
    elif kind in (MIRROR, GLOSSY):
        rough = float(mats.roughness[mid]) if kind == GLOSSY else 0.0
        fresnel = PERFECT_CONDUCTOR if grey else f'"rgb reflectance" [{_vec(tint)}]'
        surface = (f'"conductor" {fresnel} "float roughness" {_num(rough)} '
                   '"bool remaproughness" false')
    else:
        raise PbrtError(f"material {mats.names[mid]!r}: kind {kind} has no pbrt mapping")
    if not grey or tint[0] >= 1.0:
        return out + [f"  Material {surface}"]
    # A grey tint t: the surface with probability t, else black (pbrt's mix
    # picks per shading point; in expectation the BSDF is t times the surface's).
    return out + [f'  MakeNamedMaterial "m{mid}" "string type" {surface}',
                  f'  MakeNamedMaterial "m{mid}-black" "string type" "diffuse" "rgb reflectance" [0 0 0]',
                  (f'  Material "mix" "string materials" ["m{mid}-black" "m{mid}"] '
                   f'"float amount" {_num(tint[0])}')]


def write_ply(path: str, vertices: np.ndarray, faces: np.ndarray) -> None:
    """A binary little-endian PLY of the vertices `faces` use, without normals
    (pbrt then shades with face normals, flat, as our kernels do)."""
    used, local = np.unique(faces, return_inverse=True)
    records = np.zeros(len(faces), dtype=[("n", "u1"), ("index", "<i4", (3,))])
    records["n"], records["index"] = 3, local.reshape(-1, 3)
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(used)}\nproperty float x\nproperty float y\nproperty float z\n"
              f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(np.ascontiguousarray(vertices[used], "<f4").tobytes())
        f.write(records.tobytes())


def _num(x) -> str:
    return repr(float(x))


def _vec(v) -> str:
    return " ".join(_num(x) for x in v)
