"""The README is a front door (issue 14): short, its two commands first,
and every link in it and in docs/ leads somewhere that exists."""
from __future__ import annotations

import glob
import os
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
