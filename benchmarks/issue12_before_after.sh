#!/usr/bin/env bash
# Issue 12's cost of shadow rays, Russian roulette to depth 256 and MIS:
# `dosppm bench` (photon paths/s, photon rays/s, hit points/s of eye passes
# with their shadow rays) on the code before issue 12 (BEFORE, a commit,
# checked out as a worktree) and on this tree, alternated in one run so both
# see the same machine. Writes benchmarks/results/issue12-before-after/.
#
# usage: benchmarks/issue12_before_after.sh [BEFORE]   (default c79e961)
set -euo pipefail
cd "$(dirname "$0")/.."
HERE=$(pwd)
BEFORE=${1:-c79e961}
OUT=$HERE/benchmarks/results/issue12-before-after
TREE=$(mktemp -d)/before
git worktree add -q --detach "$TREE" "$BEFORE"
trap 'git worktree remove --force "$TREE"' EXIT
mkdir -p "$OUT"
git rev-parse HEAD > "$OUT/after.commit"
git rev-parse "$BEFORE" > "$OUT/before.commit"
for round in 1 2; do
  # The editable install puts the current directory first on sys.path, so
  # each run imports the tree it starts in.
  (cd "$TREE" && python -m services.cli bench cornell-glass cornell-box --photons 1000000 --repeats 5 \
      --json "$OUT/before-$round.json")
  python -m services.cli bench cornell-glass cornell-box --photons 1000000 --repeats 5 \
      --json "$OUT/after-$round.json"
done
python - "$OUT" <<'PY'
import json, statistics, sys
out = sys.argv[1]
rows = []
for scene in ("cornell-glass", "cornell-box"):
    for key in ("photon_paths_per_s", "photon_rays_per_s", "ratio_to_raw", "hit_points_per_s"):
        vals = {}
        for side in ("before", "after"):
            got = []
            for r in (1, 2):
                for res in json.load(open(f"{out}/{side}-{r}.json"))["results"]:
                    if res["scene"] == scene:
                        got.append(res[key])
            vals[side] = statistics.median(got)
        rows.append((scene, key, vals["before"], vals["after"], vals["after"] / vals["before"]))
with open(f"{out}/summary.md", "w") as f:
    f.write("| scene | figure | before | after | after / before |\n|---|---|---|---|---|\n")
    for s, k, b, a, q in rows:
        f.write(f"| {s} | {k} | {b:,.3g} | {a:,.3g} | {q:.2f} |\n")
print(open(f"{out}/summary.md").read())
PY
