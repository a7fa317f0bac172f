#!/usr/bin/env bash
# Regenerates benchmarks/results/reliability.json: what the fault, load and
# rejoin tests measure (tests/helpers/figures.py), then the tables built
# from it (issue 34: k of n runs, failures recorded, from a clean tree).
#
#   benchmarks/reliability.sh [--runs N] [--dirty]
#
# Runs tests/test_faults.py, test_load.py and test_netns_faults.py RUNS
# times (--runs, or $RUNS; default 5), each run a separate pytest, so the
# samples of one commit accumulate in the file; every test records its
# success flag, 0 in a failed run, and a failed run does not stop the
# script. Refuses a tree with changes to tracked files (untracked files are
# fine, but make the commit read +dirty) unless --dirty is given, which the
# results file records. Needs root for the network namespaces
# (tests/test_netns_faults.py) and iptables; about 15 minutes per run on 2
# cores, on a quiet machine.
set -euo pipefail
cd "$(dirname "$0")/.."
runs="${RUNS:-5}"
dirty=0
while [ $# -gt 0 ]; do
    case "$1" in
        --runs) runs="$2"; shift 2 ;;
        --runs=*) runs="${1#--runs=}"; shift ;;
        --dirty) dirty=1; shift ;;
        *) echo "reliability.sh: unknown argument $1 (usage: reliability.sh [--runs N] [--dirty])" >&2; exit 2 ;;
    esac
done
case "$runs" in ''|*[!0-9]*|0) echo "reliability.sh: --runs must be a positive whole number, not '$runs'" >&2; exit 2 ;; esac
# Results files do not count (harness/provenance.py leaves them out too).
if [ "$dirty" = 0 ] && [ -n "$(git status --porcelain --untracked-files=no -- . ':(exclude)benchmarks/results')" ]; then
    echo "reliability.sh: the tree has changes to tracked files; commit them, or pass --dirty to measure them anyway" >&2
    exit 1
fi
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
out=benchmarks/results/reliability.json
rm -f "$out"     # this script's runs only, not a merge with an older batch
failed=0
for i in $(seq 1 "$runs"); do
    echo "reliability.sh: run $i of $runs" >&2
    # A failed test records its 0 (tests/helpers/figures.py); go on.
    DOSPPM_FIGURES_DIRTY="$dirty" DOSPPM_RECORD_FIGURES="$out" python -m pytest -q -p no:cacheprovider \
        tests/test_faults.py tests/test_load.py tests/test_netns_faults.py \
        || { failed=$((failed + 1)); echo "reliability.sh: run $i had failures (above); recorded as such in $out" >&2; }
done
echo "reliability.sh: $failed of $runs runs had a failure" >&2
python benchmarks/tables.py
