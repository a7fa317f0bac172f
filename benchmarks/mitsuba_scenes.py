"""Issue 33: how far the Mitsuba XML reader gets through Mitsuba 3's own
render-test scenes (../shared/scenes/mitsuba-data/tests/scenes, 41 files;
see its SOURCE.md). Each scene is loaded as a user would load it; the
loader stops at the first thing outside our subset, so each scene gets
"loads" or that one-line refusal, and the refusals are counted by the
element refused.

    python benchmarks/mitsuba_scenes.py [--root DIR] [--out benchmarks/results/mitsuba-scenes.json]

With --out, writes per scene its first refusal (null: it loads) and the
errors of reading its language in full, with provenance.

Exits 1 when a scene fails other than by a `SceneError` (a crash).
"""
from __future__ import annotations

import argparse
import collections
import glob
import os
import re
import sys
import warnings

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from dosppm_core.scene.mitsuba import load_mitsuba_xml  # noqa: E402
from dosppm_core.scene.mitsuba.objects import (  # noqa: E402
    PLUGINS,
    REFUSED,
    Expander,
    Obj,
    upgrade_names,
    version,
)
from dosppm_core.scene.mitsuba.shapes import shape_geometry  # noqa: E402
from dosppm_core.scene.mitsuba.state import ReaderState  # noqa: E402
from dosppm_core.scene.mitsuba.xmltree import parse_xml  # noqa: E402
from dosppm_core.scene.model import SceneError  # noqa: E402

SCENES = os.path.join(ROOT, "..", "shared", "scenes", "mitsuba-data", "tests", "scenes")

# Plugins refused because later parts of issue 33 (or none of it) build
# them: textures, materials, lights, media and shapes beyond part 1's.
LATER = {
    "texture": {"bitmap", "checkerboard", "mesh_attribute", "rawconstant"},
    "emitter": {"envmap", "constant", "directional", "projector"},
    "bsdf": {"roughplastic", "plastic", "roughdielectric", "principled", "principledthin", "normalmap",
             "bumpmap", "mask", "null", "thindielectric", "blendbsdf"},
    "medium": None, "phase": None, "volume": None,     # participating media: any type
    "shape": {"serialized", "sdfgrid"},
}


def scene_files(root: str = SCENES) -> list:
    """The scenes Mitsuba's test renders: tests/scenes/FOLDER/*.xml (the
    fragments/ and include/ folders hold pieces they include)."""
    return sorted(glob.glob(os.path.join(root, "*", "*.xml")))


def try_load(path: str) -> str | None:
    """None when the scene loads, else the loader's one-line refusal."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")     # out-of-gamut spectra, as in Mitsuba
            load_mitsuba_xml(path)
    except SceneError as exc:
        return str(exc)
    return None


class _AnyPlugin(dict):
    """Every family takes every plugin type: expanding with it reads a whole
    file's language (path, include, default, $name, values, spectra,
    transforms, ids) while leaving plugins alone."""
    class _All:
        def __contains__(self, _item):
            return True

    def get(self, _key, _default=None):
        return self._All()


def _expanded(path: str):
    """(expander, scene object) of the file with every plugin allowed."""
    root = parse_xml(path)
    if version(root) < (2, 0, 0):
        upgrade_names(root)
    expander = Expander(path, {}, _AnyPlugin())
    expander.substitute(root)
    return expander, expander.object(root)


def read_language(path: str) -> list:
    """[] when the whole file, plugins aside, is in our language (its
    directives expand and every value parses) and every shape of a type we
    read finds its file and makes its triangles; else the one-line errors."""
    try:
        expander, scene = _expanded(path)
    except SceneError as exc:
        return [str(exc)]
    reader, errors = ReaderState(path, expander.ids, "mitsuba", expander.paths), []
    for obj in _objects(scene):
        if obj.tag == "shape" and obj.type in PLUGINS["shape"] - {"shapegroup", "instance"}:
            try:
                shape_geometry(reader, obj)
            except SceneError as exc:
                errors.append(str(exc))
    return errors


def plugins_needed(path: str) -> list:
    """Every plugin of the file (and its includes) outside our subset, as
    'family:type': what it takes for the scene to load."""
    try:
        _, scene = _expanded(path)
    except SceneError:
        return []
    return sorted({f"{o.tag}:{o.type}" for o in _objects(scene)
                   if o.tag != "scene" and o.type not in PLUGINS.get(o.tag, ())})


def _objects(obj):
    yield obj
    for child in obj.children:
        if isinstance(child, Obj):
            yield from _objects(child)


def reason(message: str) -> str:
    """The refused element and why, without file, line, id or name:
    '<emitter type="envmap">: unsupported plugin'."""
    body = re.sub(r"^.*?:\d+: ", "", message, count=1)
    return re.sub(r' (id|name|filename)="[^"]*"', "", body)


def later_part(message: str) -> bool:
    """Whether a refusal is of a plugin a later part of issue 33 builds
    (textures, materials, lights, media, other shapes): an unsupported
    plugin of a family and type in `LATER`, or one refused with its reason
    (`objects.REFUSED`: principled, out of scope), or a conductor's eta and k."""
    if re.search(r': <\w+ name="(eta|k)">: unsupported parameter of <bsdf type="(rough)?conductor">$', message):
        return True     # a conductor's complex index of refraction: the materials part
    if re.search(r': <string name="material">: unsupported attribute: named conductor ', message):
        return True     # a named conductor (its eta and k): the materials part
    if re.search(r': <texture type="[^"]*"[^>]*>: not allowed inside <emitter type="(spot|projector|area)"', message):
        return True     # a textured emitter: the lights part (the textures part reads BSDFs' textures)
    if re.search(r': <texture type="[^"]*" name="opacity">: not allowed inside <bsdf type="mask">', message):
        return True     # a textured mask: opacity read from a texture, not built yet
    found = re.search(r': <(\w+) type="([^"]*)"[^>]*>: (.+)$', message)
    if not found:
        return False
    tag, kind, why = found.groups()
    if why != "unsupported plugin" and why != REFUSED.get((tag, kind)):
        return False
    return tag in LATER and (LATER[tag] is None or kind in LATER[tag])


def survey(root: str = SCENES) -> list:
    """[(scene path relative to root, None or refusal)] for every scene."""
    return [(os.path.relpath(p, root), try_load(p)) for p in scene_files(root)]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--root", default=SCENES, help="the tests/scenes folder (default: %(default)s)")
    p.add_argument("--out", help="also write the results here (JSON)")
    args = p.parse_args(argv)
    if not os.path.isdir(args.root):
        print(f"{args.root}: no such folder (the shared scenes sit beside the checkout)", file=sys.stderr)
        return 2
    results = survey(args.root)
    for name, message in results:
        print(f"{name}: {'loads' if message is None else message.replace(args.root + os.sep, '')}")
    language = [(n, read_language(os.path.join(args.root, n))) for n, _ in results]
    for name, errors in language:
        for message in errors:
            print(f"language or shape: {name}: {message.replace(args.root + os.sep, '')}")
    print(f"\n{sum(not e for _, e in language)} of {len(results)} read in full, plugins aside, "
          f"every shape we support making its triangles")
    counts = collections.Counter(reason(m) for _, m in results if m is not None)
    loads = sum(m is None for _, m in results)
    print(f"{loads} of {len(results)} load; first refusals by count:")
    for text, n in counts.most_common():
        print(f"{n:4d}  {text}")
    needs = {n: plugins_needed(os.path.join(args.root, n)) for n, _ in results}
    print("\nscenes by the plugins outside our subset they use (all of them, not only the first):")
    for group, n in collections.Counter(tuple(v) for v in needs.values()).most_common():
        print(f"{n:4d}  {', '.join(group) or '(none)'}")
    if args.out:
        from services.evaluation.provenance import write_results
        short = {n: (m and m.replace(args.root + os.sep, "")) for n, m in results}
        write_results(args.out, {"scenes": short, "loads": loads, "refusals": dict(counts.most_common()),
                                 "plugins_needed": needs,
                                 "language_errors": {n: [m.replace(args.root + os.sep, "") for m in e]
                                                     for n, e in language if e}})
    return 0


if __name__ == "__main__":
    sys.exit(main())
