#!/usr/bin/env bash
# Issue 2's benchmark: the default scene and the Stanford dragon in the
# Cornell box, measured in one run. Writes benchmarks/results/core.json and
# prints the table that docs/performance.md quotes.
set -euo pipefail
cd "$(dirname "$0")/.."
mkdir -p benchmarks/results
DRAGON=../shared/scenes/stanford_dragon/dragon_100k.ply
MESH=()
[ -f "$DRAGON" ] && MESH=(--mesh "$DRAGON")
dosppm bench cornell-glass "${MESH[@]}" --photons 1000000 --repeats 5 \
    --json benchmarks/results/core.json "$@"
