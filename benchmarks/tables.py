"""Fill the performance tables of the README and docs/ from the results
files under benchmarks/results/, so that no quoted figure is typed by hand.

A Markdown file marks each generated table:

    <!-- table:core -->
    ...replaced on every run...
    <!-- /table:core -->

and the table is followed by a line naming its results file, commit, date,
machine and command. `--check` changes nothing and fails if a marked table
differs from what its results file gives (the test suite runs it).

    python benchmarks/tables.py [--check] [FILE.md ...]
"""
from __future__ import annotations

import ast
import argparse
import json
import os
import re
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "benchmarks"))

DOCS = ("README.md", "docs/performance.md", "docs/accuracy.md", "docs/reliability.md", "docs/out-of-core.md",
        "docs/mitsuba-scenes.md")
MARKED = re.compile(r"(<!-- table:([\w-]+) -->\n)(.*?)(<!-- /table:\2 -->)", re.S)


def _core(doc: dict) -> str:
    from harness import bench
    return bench.report(doc["results"])


def _dosppm(doc: dict) -> str:
    import dosppm as service_bench
    return service_bench.report(doc) if "sppm" in doc.get("runs", {}) else service_bench.report_building(doc)


def _osppm(doc: dict) -> str:
    import osppm
    return osppm.report(doc["rows"] if isinstance(doc, dict) else doc)


def _equal_work(doc: dict) -> str:
    import equal_work
    return equal_work.report(doc)


def _reliability(doc: dict) -> str:
    """What the fault, load and rejoin tests measured (tests/helpers/figures.py), k of n."""
    import reliability_table
    return reliability_table.full(doc)


def _reliability_short(doc: dict) -> str:
    """The README's cut of the same figures: what happened, one line each."""
    import reliability_table
    return reliability_table.short(doc)


def _subdivide_memory(doc: dict) -> str:
    """Peak RSS of the subdivider against the scene's size (issue 17)."""
    lines = ["| triangles | scene | peak RSS | growth while subdividing | chunks |", "|---|---|---|---|---|"]
    for r in doc["rows"]:
        lines.append(f"| {r['triangles'] / 1e6:g}M | {r['scene_bytes'] / 2**20:,.0f} MiB "
                     f"| {r['peak_bytes'] / 2**20:,.0f} MiB | {r['working_bytes'] / 2**20:,.0f} MiB "
                     f"| {r['chunks']} |")
    before = doc.get("before")
    if before:
        was = ", ".join(f"{r['peak_bytes'] / 2**20:,.0f} MiB at {r['triangles'] / 1e6:g}M" for r in before["rows"])
        lines += ["", f"Before (memory-mapped reads, commit {before['commit']}, measured the same way): peak {was}."]
    return "\n".join(lines)


def _pacing(doc: dict) -> str:
    import pacing
    return pacing.report(doc)


def _out_of_core_pipeline(doc: dict) -> str:
    import out_of_core_pipeline
    return out_of_core_pipeline.report(doc)


def _render_default(doc: dict) -> str:
    import render_default
    return render_default.report(doc)


def _replay(doc: dict) -> str:
    from harness import replay
    return replay.report(doc)


def _pbrt_side_by_side(doc: dict) -> str:
    p, o = doc["pbrt_sppm"], doc["dosppm_sppm"]
    w, h = doc["resolution"]
    return "\n".join([
        f"Equal work per iteration: {doc['scene']} at {w}x{h}, {doc['photons_per_iteration']:,} photons per "
        f"iteration, depth {doc['max_depth']}, {doc['threads']} threads, shadow rays for direct light in both; "
        f"medians of {p['repeats']}, alternated in one run.", "",
        "| renderer | photons/s | vs pbrt-v4 | hit points/s |", "|---|---|---|---|",
        f"| pbrt-v4 `sppm` (process time at {p['iterations'][1]} minus at {p['iterations'][0]} iterations) "
        f"| {p['photons_per_s']:,.0f} | 1.00 | - |",
        f"| dosppm SPPM, one process ({o['iterations']:.0f} iterations after a warm-up) "
        f"| {o['photons_per_s']:,.0f} | {o['photons_per_s'] / p['photons_per_s']:.2f} | {o['hit_points_per_s']:,.0f} |"])


def _evaluation(budget_s: float | None = None, mirror: bool = False):
    """A relMSE (bias) table of a `dosppm evaluate` results.json, at its
    last budget or at `budget_s`; `mirror`: the mirror-limit table instead."""
    def table(doc: dict) -> str:
        from harness import evaluate
        ev = evaluate.read_results_doc(doc)
        budget = budget_s if budget_s is not None else ev.budget_s
        if mirror:
            last = evaluate.final_samples(ev)
            methods = list(dict.fromkeys(s.method for s in ev.samples))
            return "\n".join(evaluate.mirror_limit_table(ev, last, methods)).strip("\n")
        head = f"relMSE at {budget:g} s (mean-luminance bias; Y: mean luminance where the reference is black):"
        return head + "\n\n" + "\n".join(evaluate.relmse_table(ev, budget_s))
    return table


def _slow_link(doc: dict) -> str:
    import slow_link
    return slow_link.report(doc)


def _texture_lookup(doc: dict) -> str:
    import texture_lookup
    return texture_lookup.report(doc)


def _many_lights(doc: dict) -> str:
    import many_lights
    return many_lights.report(doc)


def _many_lights_pbrt(doc: dict) -> str:
    import many_lights_pbrt
    return many_lights_pbrt.report(doc)


def _out_of_core_eye(doc: dict) -> str:
    import out_of_core_eye
    return out_of_core_eye.report(doc)


def _mitsuba_scenes(doc: dict) -> str:
    import mitsuba_scenes
    return mitsuba_scenes.report(doc)


def _sppm_phases(doc: dict) -> str:
    import sppm_phases
    return sppm_phases.report(doc)


def _pbrt_dark(doc: dict) -> str:
    import pbrt_dark
    return pbrt_dark.report(doc)


def _eye_pass(doc: dict) -> str:
    import eye_pass
    return eye_pass.report(doc)


# table name -> (results file, the function that renders it)
TABLES = {
    "core": ("benchmarks/results/core.json", _core),
    "dosppm": ("benchmarks/results/dosppm.json", _dosppm),
    "dosppm-building": ("benchmarks/results/dosppm-building.json", _dosppm),
    "osppm": ("benchmarks/results/osppm.json", _osppm),
    "equal-work": ("benchmarks/results/equal-work.json", _equal_work),
    "many-lights": ("benchmarks/results/many-lights.json", _many_lights),
    "many-lights-pbrt": ("benchmarks/results/many-lights-pbrt.json", _many_lights_pbrt),
    "eye-pass": ("benchmarks/results/eye-pass.json", _eye_pass),
    "mitsuba-scenes": ("benchmarks/results/mitsuba-scenes.json", _mitsuba_scenes),
    "out-of-core-eye": ("benchmarks/results/out-of-core-eye.json", _out_of_core_eye),
    "accuracy-failure-modes": ("docs/evaluation/results.json", _evaluation()),
    "accuracy-failure-modes-mirror": ("docs/evaluation/results.json", _evaluation(mirror=True)),
    "accuracy-sponza-20s": ("benchmarks/results/issue12-sponza/results.json", _evaluation(20.0)),
    "accuracy-sponza-80s": ("benchmarks/results/issue12-sponza/results.json", _evaluation(80.0)),
    "radius-20s": ("benchmarks/results/issue12-radius/results.json", _evaluation(20.0)),
    "radius-80s": ("benchmarks/results/issue12-radius/results.json", _evaluation(80.0)),
    "replay": ("benchmarks/results/replay.json", _replay),
    "replay-gather-tracers": ("benchmarks/results/replay-gather-tracers.json", _replay),
    "slow-link": ("benchmarks/results/slow-link.json", _slow_link),
    "sppm-phases": ("benchmarks/results/sppm-phases.json", _sppm_phases),
    "texture-lookup": ("benchmarks/results/texture-lookup.json", _texture_lookup),
    "render-default": ("benchmarks/results/render-default.json", _render_default),
    "reliability": ("benchmarks/results/reliability.json", _reliability),
    "reliability-short": ("benchmarks/results/reliability.json", _reliability_short),
    "subdivide-memory": ("benchmarks/results/subdivide-memory.json", _subdivide_memory),
    "pacing": ("benchmarks/results/pacing.json", _pacing),
    "out-of-core-pipeline": ("benchmarks/results/out-of-core-pipeline.json", _out_of_core_pipeline),
    "out-of-core-pipeline-34m": ("benchmarks/results/out-of-core-pipeline-34m.json", _out_of_core_pipeline),
    "out-of-core-pipeline-defaults": ("benchmarks/results/out-of-core-pipeline-defaults.json",
                                      _out_of_core_pipeline),
    "pbrt-side-by-side": ("benchmarks/results/pbrt-side-by-side.json", _pbrt_side_by_side),
    "pbrt-dark": ("benchmarks/results/pbrt-dark.json", _pbrt_dark),
}


# What every table's figures measure: the product's code (whatever a render
# runs) and the harness that drives and times it (its charts aside). A
# results file is stale once a commit after the one it names touched these
# paths or the script its command ran (`staleness`, `--fresh`).
# The peers' drivers and the evaluation (Mitsuba 3, pbrt-v4, the suites,
# their scoring) count only for the tables that run them.
PEERS = ("harness/pbrt.py", "harness/reference.py", "harness/evaluate.py", "harness/suites.py",
         "harness/mirror_limit.py", "harness/mitsuba_probe.py", "harness/render_test.py")


def _measuring(*roots: str, peers: tuple = ()) -> tuple:
    """`roots` and the harness, its charts and every peer driver not in
    `peers` left out (in a git pathspec an exclude wins over any path)."""
    return (*roots, "harness", ":(exclude)harness/charts.py",
            *(f":(exclude){p}" for p in PEERS if p not in peers))


PRODUCT_PATHS = _measuring("dosppm_core", "services")
# Tables that time the rendering library alone, in one process: a change
# to the services (the server, the tracers, the wire) leaves them fresh.
LIBRARY_PATHS = _measuring("dosppm_core")
EVALUATION_PATHS = _measuring("dosppm_core", "services", peers=PEERS)
# Mitsuba's render tests run our renderer and score it (render_test.py),
# no peer: the pbrt-v4 and Mitsuba drivers do not age them.
MITSUBA_TEST_PATHS = _measuring("dosppm_core", "services", peers=("harness/render_test.py",))
MEASURES = {**dict.fromkeys(("sppm-phases", "texture-lookup", "many-lights", "eye-pass"), LIBRARY_PATHS),
            **dict.fromkeys(("accuracy-failure-modes", "accuracy-failure-modes-mirror", "accuracy-sponza-20s",
                             "accuracy-sponza-80s", "radius-20s", "radius-80s", "pbrt-side-by-side", "pbrt-dark",
                             "many-lights-pbrt", "out-of-core-eye"), EVALUATION_PATHS),
            "mitsuba-scenes": MITSUBA_TEST_PATHS}


def _provenance(doc) -> dict | None:
    p = doc.get("provenance") if isinstance(doc, dict) else None
    if not p and isinstance(doc, dict) and doc.get("commit"):     # an evaluation before provenance
        p = {"commit": doc["commit"], "date": doc.get("date", "?"), "machine": doc.get("machine", {})}
    return p or None


def _script(command: str | None) -> list[str]:
    """The benchmark file a recorded command ran (a path, or a module run with -m)."""
    for word in (command or "").split():
        if word.endswith((".py", ".sh")):
            return [word if os.path.isabs(word) else word.lstrip("./")]
        if word.startswith(("harness.", "services.", "benchmarks.")):
            return [word.replace(".", "/") + ".py"]
    return []


def _git(root: str, *args) -> subprocess.CompletedProcess:
    return subprocess.run(["git", "-C", root, *args], capture_output=True, text=True)


def staleness(name: str, root: str = ROOT) -> str | None:
    """Why table `name`'s results file is older than the code it measures,
    or None when it is fresh: it names a clean commit, and no file of the
    paths it measures (MEASURES, else PRODUCT_PATHS) or of its own
    benchmark script differs from that commit
    but in comments and docstrings (`_same_code`)."""
    path, _fn = TABLES[name]
    with open(os.path.join(root, path), encoding="utf-8") as f:
        p = _provenance(json.load(f))
    if p is None:
        return f"{path}: no provenance (no commit recorded)"
    commit = str(p["commit"])
    if commit.endswith("+dirty") or _git(root, "cat-file", "-e", commit + "^{commit}").returncode:
        return f"{path}: measured at {commit[:16]}, not a clean commit of this repository"
    script = [s for s in _script(p.get("command")) if os.path.exists(os.path.join(root, s))]
    paths = list(MEASURES.get(name, PRODUCT_PATHS)) + script
    changed = _git(root, "diff", "--name-only", commit, "HEAD", "--", *paths).stdout.split()
    changed = [f for f in changed if not _same_code(root, commit, f)]
    if changed:
        last = _git(root, "log", "-1", "--format=%H", f"{commit}..HEAD", "--", *changed).stdout.strip() or "HEAD"
        return f"{path}: measured at {commit[:10]}, but {last[:10]} changed the code it measures since " \
               f"({changed[0]}{f' and {len(changed) - 1} more' if len(changed) > 1 else ''})"
    return None


def _same_code(root: str, commit: str, path: str) -> bool:
    """Whether Python file `path` at HEAD is `commit`'s but for comments and
    docstrings: a review that rewords them changes no figure, and a
    run_all of hours should not be owed for it."""
    if not path.endswith(".py"):
        return False
    trees = [_git(root, "show", f"{rev}:{path}") for rev in (commit, "HEAD")]
    if any(t.returncode for t in trees):
        return False                      # added or deleted
    try:
        return _code_of(trees[0].stdout) == _code_of(trees[1].stdout)
    except SyntaxError:
        return False


def _code_of(source: str) -> str:
    """The module's syntax tree without its docstrings (positions left out)."""
    tree = ast.parse(source)
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and body \
                and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
                and isinstance(body[0].value.value, str):
            node.body = body[1:] or [ast.Pass()]
    return ast.dump(tree)


def quoted(files=DOCS, root: str = ROOT) -> list[str]:
    """The tables the documents quote, in order, each once."""
    names = []
    for name in files:
        full = os.path.join(root, name)
        if os.path.exists(full):
            with open(full, encoding="utf-8") as f:
                names += [m.group(2) for m in MARKED.finditer(f.read())]
    return list(dict.fromkeys(names))


def source_line(path: str, doc: dict, doc_dir: str = "", command: bool = True, commit: str | None = None) -> str:
    """Where the table came from, linked from a document in `doc_dir`;
    files written before provenance was recorded say so rather than guess.
    `command` False leaves out the command (the README's short tables,
    whose full versions in docs/ give it); `commit` replaces the file's
    commit (the reliability tables name their runs' commits)."""
    link = os.path.relpath(path, doc_dir or ".")
    p = _provenance(doc)
    if not p:
        return f"Source: [{path}]({link}) (written before commit and machine were recorded)."
    m = p.get("machine") or {}
    cpu = f"{m['cpu']} x{m.get('cpu_count', '?')}" if m.get("cpu") else f"{m.get('cpus', '?')} CPUs"
    command = f", `{p['command']}`" if p.get("command") and command else ""
    commit = commit or f"commit {p['commit'][:10]}"
    return f"Source: [{path}]({link}), {commit}, {p['date'][:10]}, {cpu}{command}."


def render(name: str, root: str = ROOT, doc_dir: str = "") -> str:
    path, fn = TABLES[name]
    with open(os.path.join(root, path), encoding="utf-8") as f:
        doc = json.load(f)
    commit = None
    if name.startswith("reliability"):
        import reliability_table
        commit = reliability_table.commits(doc, 7 if name.endswith("-short") else 10)
    return fn(doc).rstrip("\n") + "\n\n" + source_line(path, doc, doc_dir, not name.endswith("-short"), commit) + "\n"


def fill(text: str, root: str = ROOT, doc_dir: str = "") -> str:
    """`text` (of a document in `doc_dir`, from the top of the checkout)
    with every marked table regenerated."""
    def one(m):
        if m.group(2) not in TABLES:
            raise KeyError(f"unknown table {m.group(2)!r} (known: {', '.join(TABLES)})")
        return m.group(1) + render(m.group(2), root, doc_dir) + m.group(4)
    return MARKED.sub(one, text)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="*", default=list(DOCS))
    ap.add_argument("--check", action="store_true", help="fail if a table differs from its results")
    ap.add_argument("--fresh", action="store_true",
                    help="fail if a quoted table's results are older than the code they measure")
    args = ap.parse_args(argv)
    if args.fresh:
        old = list(dict.fromkeys(why for why in (staleness(n) for n in quoted(args.files)) if why))
        print("\n".join(old) or "every quoted table is fresh", file=sys.stderr if old else sys.stdout)
        return 1 if old else 0
    stale = []
    for name in args.files:
        path = os.path.join(ROOT, name)
        if not os.path.exists(path):
            continue
        with open(path, encoding="utf-8") as f:
            text = f.read()
        new = fill(text, doc_dir=os.path.dirname(name))
        if new != text:
            stale.append(name)
            if not args.check:
                with open(path, "w", encoding="utf-8") as f:
                    f.write(new)
    if args.check and stale:
        print(f"tables differ from benchmarks/results in: {', '.join(stale)} "
              "(run python benchmarks/tables.py)", file=sys.stderr)
        return 1
    for name in stale if not args.check else []:
        print(f"updated {name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
