"""The evaluation's suites, cases and methods (`dosppm evaluate SUITE`),
and where a case's shared files are found (or a flat-shaded copy made):
data, so the runner (`evaluate.py`) and its tests read one table."""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

from dosppm_core.settings import RenderSettings

SHARED_ENV = "DOSPPM_SHARED"


class CaseSkipped(Exception):
    """A case cannot run on this machine (its shared files are absent); one line."""


@dataclass(frozen=True)
class SharedFiles:
    """A case's files, relative to the shared folder."""
    scene: str                    # for dosppm and Mitsuba: Mitsuba XML or TOML
    reference: str                # EXR at the scene's own resolution
    about: str                    # how the reference was made
    pbrt: str = ""                # the same scene for pbrt-v4 (else it is exported)
    # Shade the XML's meshes flat (Mitsuba's face_normals on every obj and
    # ply shape): a PLY without normals is flat in pbrt-v4 but smooth in
    # Mitsuba 3 and in our reader, so a pbrt-v4 reference of it needs this.
    face_normals: bool = False


@dataclass(frozen=True)
class Case:
    """One scene of a suite: what it tests and how its reference is made."""
    scene: str                    # a built-in scene, or the case's name when `files` is set
    tests: str
    reference: str = "path"       # 'path', 'ptracer', 'ptracer+path' or 'file'
    spp: int = 4096               # reference samples per pixel
    # Pixels scored: 'all', or 'no-specular-in-view' where what the camera
    # sees in a mirror or through glass is lit by caustics of a point light
    # or a tiny lamp (specular-diffuse-specular paths): no independent
    # method converges there (a path tracer's fireflies stay at 4096 spp).
    scored: str = "all"
    # Also score the pixels where the camera sees a mirror against the
    # limit reference of `mirror_limit` (a flat Lambertian floor seen in
    # perfect mirrors).
    mirror_limit: bool = False
    # Scene and reference image from the shared folder (`reference` 'file');
    # the scene keeps its own resolution, which the reference has.
    files: SharedFiles | None = None


@dataclass(frozen=True)
class Suite:
    name: str
    width: int
    height: int
    cases: tuple
    methods: tuple
    reference_spp_scale: float = 1.0


@dataclass(frozen=True)
class Method:
    name: str
    kind: str                     # 'sppm', 'osppm', 'dosppm', 'mitsuba' or 'pbrt'
    options: dict = field(default_factory=dict)
    about: str = ""


# The peers' path depth: deep enough that no light the unbounded references
# hold is lost (pbrt_dark.py: depths 100 and 256 give the same images to
# 0.01%; Russian roulette ends paths long before), but not ours (256):
# pbrt-v4's SPPM dies of SIGSEGV at maxdepth 256 on scenes with glass
# (cornell-caustic, glass-small-light, thin-wall; at 200 it runs).
PEER_DEPTH = min(RenderSettings().max_depth, 100)

METHODS = {m.name: m for m in (
    Method("sppm-grid", "sppm", {"gather": "grid"},
           "SPPM, exact grid gather, the default estimator (direct light by shadow rays)"),
    Method("sppm-photons", "sppm", {"gather": "grid", "direct": "photons"},
           "SPPM, exact grid gather, the paper's pure estimator (direct light from photons)"),
    # One global initial radius, as a user's --radius would give, beside the
    # default's radius fitted per hit point (issue 12): the bias these leave
    # is what the fit removes.
    Method("sppm-radius-1/400", "sppm", {"gather": "grid", "radius_of_diagonal": 1 / 400},
           "SPPM with one global initial radius, 1/400 of the scene's diagonal (--radius)"),
    Method("sppm-radius-1/100", "sppm", {"gather": "grid", "radius_of_diagonal": 1 / 100},
           "SPPM with one global initial radius, 1/100 of the scene's diagonal (--radius)"),
    Method("sppm-hash-512x128x512", "sppm", {"gather": "hash", "resolution": (512, 128, 512)},
           "SPPM, stochastic hash at the paper's table size"),
    Method("sppm-hash-128x32x128", "sppm", {"gather": "hash", "resolution": (128, 32, 128)},
           "SPPM, stochastic hash, 64x fewer cells"),
    Method("sppm-hash-32x8x32", "sppm", {"gather": "hash", "resolution": (32, 8, 32)},
           "SPPM, stochastic hash too coarse for the scene (collisions lose photons)"),
    Method("osppm-c4", "osppm", {"chunks": 4}, "OSPPM, 4 chunks, one process"),
    Method("osppm-c8", "osppm", {"chunks": 8}, "OSPPM, 8 chunks, one process"),
    Method("dosppm", "dosppm", {}, "DOSPPM: server and 2 tracer processes on this machine"),
    Method("mitsuba-path", "mitsuba", {"integrator": "path"}, "Mitsuba 3 path tracer"),
    Method("mitsuba-ptracer", "mitsuba", {"integrator": "ptracer"}, "Mitsuba 3 light tracer"),
    # pbrt-v4 at PEER_DEPTH (with Russian roulette both sides), as every
    # reference is unbounded: at depth 10
    # (issue 12's setting) its images came out up to 13% dark (light past 10
    # bounces: glass-small-light's lamp in glass, many-lights' lamps), which
    # was taken for an export fault.
    Method("pbrt-sppm", "pbrt", {"integrator": "sppm", "max_depth": PEER_DEPTH},
           f"pbrt-v4 SPPM, 100k photons per iteration, radius 3 pixel footprints, depth {PEER_DEPTH}"),
    Method("pbrt-sppm-radius-1/100", "pbrt", {"integrator": "sppm", "max_depth": PEER_DEPTH,
                                               "radius_of_diagonal": 1 / 100},
           f"pbrt-v4 SPPM, radius 1/100 of the scene's diagonal (tuned by hand on Sponza), depth {PEER_DEPTH}"),
    Method("pbrt-path", "pbrt", {"integrator": "path", "max_depth": PEER_DEPTH},
           f"pbrt-v4 path tracer, depth {PEER_DEPTH}"),
)}

CAUSTIC_SCENES = ("cardioid", "cornell-caustic", "glass-small-light")

SUITES = {s.name: s for s in (
    Suite("failure-modes", 128, 128, (
        Case("cornell-box", "plain diffuse light transport: path tracing's home ground"),
        Case("cornell-caustic", "caustics of a glass and a mirror sphere, seen directly and "
             "in the mirror (specular-diffuse-specular)", "ptracer+path"),
        Case("cardioid", "a point light's caustic off a mirror ring: path tracing cannot "
             "render it", "ptracer+path", scored="no-specular-in-view", mirror_limit=True),
        Case("glass-small-light", "a small lamp seen through glass; the room lit by caustics",
             "ptracer+path", scored="no-specular-in-view"),
        Case("thin-wall", "light leaking through a wall 1% of the room thick"),
        Case("glossy-floor", "a glossy GGX floor, where SPPM converges slowly"),
        Case("many-lights", "400 small lamps chosen by power"),
        Case("far-from-origin", "coordinates near 1e5: float32 precision"),
    ), tuple(METHODS)),
    # CI's version: tiny images, seconds per method, the orderings that must
    # hold on any machine (error falls with time; nothing is NaN).
    Suite("mini", 32, 32, (
        Case("cornell-box", "diffuse", spp=1024),
        Case("cardioid", "point-light caustic", "ptracer+path", spp=16384,
             scored="no-specular-in-view"),
    ), ("sppm-grid", "sppm-hash-128x32x128", "osppm-c4", "mitsuba-path")),
    # A real building against pbrt-v4 (issue 12), from the shared folder.
    Suite("sponza", 320, 240, (
        Case("sponza-point", "the Sponza atrium lit by one point light: sharp direct light, "
             "long diffuse paths, a real mesh", "file", files=SharedFiles(
                 "references/sponza-point/sponza_point.xml",
                 "references/sponza-point/reference_pbrt_path_2048spp.exr",
                 "pbrt-v4 path, 2048 spp, max depth 50 (references/sponza-point/SOURCE.md)",
                 pbrt="references/sponza-point/sponza_point.pbrt", face_normals=True)),
    ), ("sppm-grid", "sppm-photons", "dosppm", "pbrt-sppm", "pbrt-path", "mitsuba-path")),
)}


@dataclass
class Sample:
    """One stop of one method on one scene."""
    scene: str
    method: str
    budget_s: float
    seconds: float
    photons: int
    finite: bool
    relmse: float = math.nan
    rmse: float = math.nan
    bias: float = math.nan             # relative; NaN where the reference is black
    blurred_relmse: float = math.nan
    mean_luminance: float = math.nan   # absolute: what leaks into a black reference
    # Over the pixels where the camera sees a mirror, against its limit
    # reference (cases with `mirror_limit`; NaN elsewhere).
    mirror_limit_relmse: float = math.nan
    mirror_limit_blurred_relmse: float = math.nan
    mirror_limit_bias: float = math.nan
    note: str = ""


def shared_dir(given: str | None = None) -> str | None:
    """The shared folder of scenes and references: `given`, else
    $DOSPPM_SHARED, else None. The product never looks for it by itself:
    tests and benchmarks say where it is."""
    return given or os.environ.get(SHARED_ENV) or None


def with_face_normals(path: str, folder: str) -> str:
    """A copy of the Mitsuba XML `path`, written into `folder`, in which
    every obj and ply shape sets face_normals (flat shading) and every
    file name is absolute, so the copy reads the same files."""
    import xml.etree.ElementTree as ET

    tree = ET.parse(path)
    here = os.path.dirname(os.path.abspath(path))
    for node in tree.iter("string"):
        if node.get("name") == "filename" and not os.path.isabs(node.get("value", "")):
            node.set("value", os.path.normpath(os.path.join(here, node.get("value"))))
    for shape in tree.iter("shape"):
        if shape.get("type") in ("obj", "ply"):
            for old in [c for c in shape if c.get("name") == "face_normals"]:
                shape.remove(old)
            ET.SubElement(shape, "boolean", name="face_normals", value="true")
    out = os.path.join(folder, "flat-" + os.path.basename(path))
    tree.write(out, encoding="utf-8")
    return out


def shared_file(shared: str | None, name: str) -> str:
    """The path of `name` in the shared folder; CaseSkipped if it is absent."""
    if shared is None:
        raise CaseSkipped(f"no shared folder for {name} (give --shared DIR or set {SHARED_ENV})")
    path = os.path.join(shared, name)
    if not os.path.isfile(path):
        raise CaseSkipped(f"{name} is not in the shared folder {shared} "
                          f"(give --shared DIR or set {SHARED_ENV})")
    return path
