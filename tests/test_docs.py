"""The README is a front door (issue 14): short, its two commands first,
and every link in it and in docs/ leads somewhere that exists."""
from __future__ import annotations

import glob
import os
import pathlib
import re

import pytest

from tests.helpers.paths import REPO

DOCS = ["README.md", "deploy/README.md"] + sorted(os.path.relpath(p, REPO)
                                                  for p in glob.glob(os.path.join(REPO, "docs", "*.md")))
LINK = re.compile(r"\]\(([^)\s#]+)(?:#[^)]*)?\)")


def _read(name: str) -> str:
    with open(os.path.join(REPO, name), encoding="utf-8") as f:
        return f.read()


def test_the_readme_reads_in_two_minutes_and_starts_with_the_two_commands():
    text = _read("README.md")
    assert len(text) < 8000, f"README.md is {len(text)} characters"
    assert text.index("pip install . && dosppm render --time 30") < text.index("## Using it")
    assert "pip install -e '.[test]' && python -m pytest -q" in text
    assert text.index("![") < text.index("## The two commands"), "the picture comes first"


@pytest.mark.parametrize("name", DOCS)
def test_every_relative_link_exists(name):
    base = os.path.dirname(os.path.join(REPO, name))
    missing = [url for url in LINK.findall(_read(name))
               if not re.match(r"^[a-z]+:", url) and not os.path.exists(os.path.normpath(os.path.join(base, url)))]
    assert not missing, f"{name}: broken links {missing}"


def _python_files() -> list[str]:
    root = pathlib.Path(REPO)
    return [p.relative_to(root).as_posix() for p in root.rglob("*.py")
            if not any(part in (".venv", "build", ".git") for part in p.relative_to(root).parts)]


def test_every_module_and_class_the_architecture_walk_names_exists():
    """docs/architecture.md walks a photon through the code by file and
    class names (`state.py`, `modes/sppm.Renderer`): each must still be
    there, or the walk misleads. Not found: the doc names a moved module."""
    text = (pathlib.Path(REPO) / "docs" / "architecture.md").read_text()
    files = _python_files()
    modules = set(re.findall(r"([A-Za-z_][\w/]*\.py)\b", text))
    assert len(modules) > 30                      # the walk names the modules it passes
    missing = [m for m in sorted(modules) if not any(f == m or f.endswith("/" + m) for f in files)]
    assert not missing, f"docs/architecture.md names modules that do not exist: {missing}"
    for mod, name in set(re.findall(r"\b((?:[a-z_]+/)+[a-z_]+)\.([A-Z]\w+)", text)):
        found = [f for f in files if f == mod + ".py" or f.endswith("/" + mod + ".py")]
        assert any(re.search(rf"^(class|def) {name}\b", (pathlib.Path(REPO) / f).read_text(), re.M) for f in found), \
            f"docs/architecture.md names {mod}.{name}, which is not defined there"
