"""DOSPPM_REQUIRE_ALL (tests/conftest.py) turns every skip CI may not take
quietly into a failure: a skip whose reason names a required tool, any skip
in the netns, docker and browser tiers whatever its reason, and a module
that skips as it is imported. Each case is a throwaway test module run by a
child pytest with this conftest as its plugin, with and without the
variable; a skip for anything else (the pbrt-v4 peer, by design) stays a
skip.
"""
from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest

from tests.helpers.paths import REPO

CASES = {
    "tool_reason": ('import pytest\n'
                    'def test_x():\n    pytest.skip("chromium not installed")\n'),
    "netns_tier_any_reason": ('import pytest\npytestmark = pytest.mark.netns\n'
                              'def test_x():\n    pytest.skip("something went sideways")\n'),
    "docker_tier_any_reason": ('import pytest\npytestmark = pytest.mark.docker\n'
                               'def test_x():\n    pytest.skip("no daemon here")\n'),
    "one_core": ('import pytest\n@pytest.mark.skipif(True, reason="numba found one core: nothing to keep to")\n'
                 'def test_x():\n    pass\n'),
    "skips_at_import": ('import pytest\npytest.importorskip("mitsuba_not_a_module")\n'
                        'def test_x():\n    pass\n'),
}
BY_DESIGN = 'import pytest\ndef test_x():\n    pytest.skip("pbrt-v4 is not built")\n'


@pytest.fixture(scope="module")
def outcomes(tmp_path_factory):
    """{require_all: {case: 'skipped' | 'failed'}}: every case, and the
    skip by design, as test modules of a folder run by one child pytest
    each way."""
    folder = tmp_path_factory.mktemp("require-all")
    for name, source in {**CASES, "by_design": BY_DESIGN}.items():
        (folder / f"test_{name}.py").write_text(source)
    return {flag: _run(folder, flag) for flag in (False, True)}


def _run(folder, require_all: bool) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "DOSPPM_REQUIRE_ALL"}
    if require_all:
        env["DOSPPM_REQUIRE_ALL"] = "1"
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-rA", "--continue-on-collection-errors", "-p", "tests.conftest", "-p",
                        "no:cacheprovider", "--rootdir", REPO, "-c", os.path.join(REPO, "pyproject.toml"),
                        str(folder)], cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    out = {}
    for line in r.stdout.splitlines():
        m = re.match(r"(SKIPPED|FAILED|ERROR|PASSED) .*?test_(\w+?)\.py", line)
        if m:
            out[m.group(2)] = {"SKIPPED": "skipped", "PASSED": "passed"}.get(m.group(1), "failed")
    assert set(out) == {*CASES, "by_design"}, r.stdout[-3000:] + r.stderr[-2000:]
    return out


@pytest.mark.parametrize("name", sorted(CASES))
def test_a_required_skip_fails_only_under_require_all(outcomes, name):
    assert (outcomes[False][name], outcomes[True][name]) == ("skipped", "failed")


def test_a_skip_by_design_stays_a_skip(outcomes):
    assert outcomes[False]["by_design"] == outcomes[True]["by_design"] == "skipped"
