"""XML elements with the file and line they were written at, so every error
names ``file:line: <tag ...>``; expat gives the line of each start tag."""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import NoReturn
from xml.parsers import expat

from dosppm_core.scene.model import SceneError


@dataclass(eq=False)
class Node:
    """One XML element and where it was written."""
    tag: str
    attrib: dict
    file: str
    line: int
    label: str                      # the start tag as written, for messages
    children: list = field(default_factory=list)

    def fail(self, message: str) -> NoReturn:
        raise SceneError(f"{self.file}:{self.line}: {self.label}: {message}")


def start_tag(tag: str, attrib: dict) -> str:
    shown = "".join(f' {k}="{attrib[k]}"' for k in ("type", "name", "id", "filename") if k in attrib)
    return f"<{tag}{shown}>"


def synthetic(tag: str, attrib: dict, origin: Node) -> Node:
    """An element the Nori rewrite adds; errors point at `origin`."""
    return Node(tag, attrib, origin.file, origin.line, origin.label)


def parse_xml(path: str) -> Node:
    """Parse one file into its root element."""
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError as exc:
        raise SceneError(f"{path}: cannot read: {exc.strerror}") from None
    parser = expat.ParserCreate()
    stack = [Node("#document", {}, path, 0, "")]

    def start(tag, attrib):
        node = Node(tag, dict(attrib), path, parser.CurrentLineNumber, start_tag(tag, attrib))
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


def walk(node: Node):
    """`node` and every element below it, depth first."""
    yield node
    for child in node.children:
        yield from walk(child)


def no_children(node: Node) -> None:
    if node.children:
        node.children[0].fail(f"cannot occur inside {node.label}")


def check_attrs(node: Node, allowed, required=()) -> None:
    for key in node.attrib:
        if key not in allowed:
            node.fail(f"unsupported attribute {key!r}")
    for key in required:
        if key not in node.attrib:
            node.fail(f"missing attribute {key!r}")


def resolve(node: Node, filename: str, root_dir: str, paths=()) -> str:
    """A relative name is looked up in the folders `<path>` added (the
    latest first, as Mitsuba's file resolver prepends them), then beside the
    file that names it, then beside the main file (Mitsuba's resolver:
    cbox-rgb.xml's fragments name meshes/ relative to the main file, and an
    included file's own includes are found from the main file's folder)."""
    candidates = [filename] if os.path.isabs(filename) else [
        *(os.path.join(folder, filename) for folder in paths),
        os.path.join(os.path.dirname(node.file), filename), os.path.join(root_dir, filename)]
    for path in candidates:
        if os.path.isfile(path):
            return path
    node.fail(f"file {filename!r} not found")
