"""The object tree: a file's XML with `$parameters` substituted, includes
spliced in, values parsed and ids recorded. Each <shape>, <bsdf>, ...
element becomes an `Obj` holding its parameters (`Prop`) and nested
objects or references (`Ref`)."""
from __future__ import annotations

import os
import re
from dataclasses import dataclass, field

import numpy as np

from dosppm_core.scene.mitsuba.values import read_value, transform_op
from dosppm_core.scene.mitsuba.xmltree import Node, check_attrs, no_children, parse_xml, resolve, walk

OBJECT_TAGS = {"sensor", "film", "sampler", "rfilter", "integrator", "shape", "bsdf",
               "emitter", "texture", "medium", "phase", "volume"}
VALUE_TAGS = {"float", "integer", "boolean", "string", "point", "vector", "rgb", "spectrum"}
PLUGINS = {
    "shape": {"obj", "ply", "rectangle", "cube", "sphere", "disk", "cylinder", "shapegroup", "instance"},
    "bsdf": {"diffuse", "twosided", "conductor", "roughconductor", "dielectric", "roughdielectric",
             "plastic", "roughplastic", "mask", "blendbsdf", "normalmap", "bumpmap"},
    "emitter": {"area", "point", "spot", "directional", "constant", "envmap", "projector"},
    "texture": {"bitmap", "checkerboard", "mesh_attribute", "rawconstant"},
    "sensor": {"perspective", "thinlens", "orthographic"},
    "film": {"hdrfilm"},
    "rfilter": {"box", "tent", "gaussian", "mitchell", "catmullrom", "lanczos"},
    "sampler": {"independent", "stratified", "multijitter", "orthogonal", "ldsampler"},
    "integrator": {"path", "volpath", "volpathmis", "ptracer", "direct", "moment"},
}
NORI_PLUGINS = {**PLUGINS, "shape": {"obj"}, "bsdf": {"diffuse", "conductor", "dielectric"},
                "emitter": {"area"}, "sensor": {"perspective"}, "sampler": {"independent"},
                "integrator": {"photonmapper", "path_mis", "path_mats", "path_ems", "mipath",
                               "whitted", "direct", "direct_mis", "direct_ems", "direct_mats"}}
# Plugins refused with a reason beyond "unsupported plugin".
REFUSED = {
    ("bsdf", "principled"): "the principled BSDF is unsupported (out of scope); "
                            "roughplastic, roughconductor or roughdielectric come closest",
    ("bsdf", "principledthin"): "the thin principled BSDF is unsupported (out of scope); "
                                "roughdielectric or a twosided roughplastic come closest",
}
MAX_INCLUDE_DEPTH = 15                                  # Mitsuba's recursion limit


@dataclass(eq=False)
class Prop:
    """One parameter of an object."""
    node: Node
    kind: str              # the value's tag: float, rgb, spectrum, transform, ...
    value: object
    in_emitter: bool
    used: bool = False


@dataclass(eq=False)
class Ref:
    """A <ref id>, resolved when the object holding it is read."""
    node: Node
    id: str


@dataclass(eq=False)
class Obj:
    """One plugin instance: its parameters and nested objects/references."""
    node: Node
    tag: str
    type: str
    props: dict = field(default_factory=dict)
    children: list = field(default_factory=list)

    def take(self, name: str, kinds) -> Prop | None:
        """The parameter `name` (None if absent), marked as read; it must be
        one of the value tags `kinds`."""
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


def version(node: Node) -> tuple | None:
    text = node.attrib.get("version")
    if text is None:
        return None
    if not re.fullmatch(r"\d+\.\d+\.\d+", text.strip()):
        node.fail(f"cannot parse version {text!r}")
    return tuple(int(p) for p in text.split("."))


def upgrade_names(root: Node) -> None:
    """Mitsuba 0.x and Nori spell parameters in camelCase; Mitsuba 3 upgrades
    them to snake_case on load (toWorld -> to_world, intIOR -> int_ior)."""
    for node in walk(root):
        if node.tag == "lookAt":
            node.tag = "lookat"
        if "name" in node.attrib and node.tag != "default":
            node.attrib["name"] = re.sub(r"([a-z])([A-Z]+)", lambda m: m[1] + "_" + m[2].lower(),
                                         node.attrib["name"])
    for node in walk(root):
        if node.tag == "bsdf" and node.attrib.get("type") == "diffuse":
            for prop in node.children:
                if prop.attrib.get("name") == "diffuse_reflectance":
                    prop.attrib["name"] = "reflectance"


class Expander:
    """Builds the `Obj` tree of a file and its includes."""

    def __init__(self, path: str, params: dict, plugins: dict):
        self.root_dir = os.path.dirname(os.path.abspath(path))
        self.params = {name: [str(value), False] for name, value in params.items()}
        self.plugins = plugins
        self.ids: dict[str, Obj] = {}
        self.includes = [os.path.realpath(path)]          # the chain of files being read
        self.paths: list[str] = []                        # <path> folders, the latest first

    def unused_params(self) -> list:
        return [name for name, (_, used) in self.params.items() if not used]

    def substitute(self, node: Node) -> None:
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

    def object(self, node: Node) -> Obj:
        check_attrs(node, {"type", "id", "name"} | ({"version"} if node.tag == "scene" else set()))
        kind = "scene" if node.tag == "scene" else node.attrib.get("type")
        if node.tag != "scene" and kind not in self.plugins.get(node.tag, ()):
            node.fail(REFUSED.get((node.tag, kind), "unsupported plugin"))
        obj = Obj(node, node.tag, kind)
        ident = node.attrib.get("id")
        if ident is not None:
            if ident in self.ids:
                first = self.ids[ident].node
                node.fail(f"duplicate id {ident!r} (first at {first.file}:{first.line})")
            self.ids[ident] = obj
        for child in node.children:
            self.child(obj, child)
        return obj

    def child(self, parent: Obj, node: Node) -> None:
        self.substitute(node)
        tag = node.tag
        if tag in ("default", "include", "ref", "path") or tag in VALUE_TAGS and "type" not in node.attrib:
            no_children(node)
        if tag == "default":
            self.default(node)
        elif tag == "path":
            self.search_path(parent, node)
        elif tag == "include":
            self.include(parent, node)
        elif tag == "ref":
            check_attrs(node, {"id", "name"}, required=("id",))
            parent.children.append(Ref(node, node.attrib["id"]))
        elif tag in OBJECT_TAGS or (tag in VALUE_TAGS and "type" in node.attrib):
            parent.children.append(self.object(node))
        elif tag in VALUE_TAGS or tag == "transform":
            self.property(parent, node)
        else:
            node.fail("unsupported element")

    def default(self, node: Node) -> None:
        check_attrs(node, {"name", "value"}, required=("name", "value"))
        if not node.attrib["name"]:
            node.fail("empty name")
        # Keyword overrides and earlier defaults win; defaults count as used.
        self.params.setdefault(node.attrib["name"], [node.attrib["value"], True])

    def search_path(self, parent: Obj, node: Node) -> None:
        """Mitsuba's <path value>: a folder searched for relative file names,
        written directly in a scene (or an included scene). A relative folder
        is taken from the directory of the file that writes it."""
        check_attrs(node, {"value"}, required=("value",))
        if parent.tag != "scene":
            node.fail("a <path> can only be a child of <scene>")
        value = node.attrib["value"]
        # Beside the writing file first, then as any file name is resolved.
        found = [value] if os.path.isabs(value) else [
            os.path.join(d, value) for d in (os.path.dirname(node.file), *self.paths, self.root_dir)]
        folder = next((f for f in found if os.path.isdir(f)), None)
        if folder is None:
            node.fail(f"folder {value!r} not found")
        # Prepended, as Mitsuba's resolver does: a later <path> is searched first.
        self.paths.insert(0, os.path.normpath(folder))

    def property(self, parent: Obj, node: Node) -> None:
        if node.tag == "transform":
            check_attrs(node, {"name"}, required=("name",))
            value = np.eye(4)
            for op in node.children:
                self.substitute(op)
                no_children(op)
                value = transform_op(op) @ value
        else:
            value = read_value(node)
        name = node.attrib["name"]
        if name in parent.props:
            node.fail(f"parameter {name!r} given twice (first at line {parent.props[name].node.line})")
        parent.props[name] = Prop(node, node.tag, value, in_emitter=parent.tag == "emitter")

    def include(self, parent: Obj, node: Node) -> None:
        check_attrs(node, {"filename"}, required=("filename",))
        path = resolve(node, node.attrib["filename"], self.root_dir, self.paths)
        real = os.path.realpath(path)
        if real in self.includes or len(self.includes) > MAX_INCLUDE_DEPTH:
            node.fail("include cycle (or deeper than 15 levels)")
        root = parse_xml(path)
        self.includes.append(real)
        if root.tag != "scene":
            self.child(parent, root)
        else:
            check_attrs(root, {"version"})
            if (version(root) or (3, 0, 0)) < (2, 0, 0):
                upgrade_names(root)
            for child in root.children:
                self.child(parent, child)
        self.includes.pop()
