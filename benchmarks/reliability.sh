#!/usr/bin/env bash
# Regenerates benchmarks/results/reliability.json: what the fault, load and
# rejoin tests measure (tests/helpers/figures.py), then the tables built
# from it. The rejoin test runs REJOIN_RUNS times (default 3), so its row
# says how many of them rejoined. Needs root for the network namespaces
# (tests/test_netns_faults.py) and iptables; about 15 minutes on 2 cores.
set -euo pipefail
cd "$(dirname "$0")/.."
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
out=benchmarks/results/reliability.json
rm -f "$out"     # one run's figures, not a merge with an older commit's
# A failed rejoin is recorded as one (0 of the runs), so keep going.
DOSPPM_REJOIN_RUNS="${REJOIN_RUNS:-3}" DOSPPM_RECORD_FIGURES="$out" python -m pytest -q -p no:cacheprovider \
    tests/test_faults.py tests/test_load.py tests/test_netns_faults.py \
    || echo "reliability.sh: some tests failed (above); their figures are not in $out" >&2
python benchmarks/tables.py
