#!/usr/bin/env bash
# Side by side on the same machine: mcm.classic (example classic_rcp) and spheropack
# (Lubachevsky-Stillinger, PyPI) packing N spheres to a volume fraction, each packing then
# checked independently by check_packing.py (every pair over the 27 periodic images,
# fraction from the radii and the box) from the exported CSV files.
#
#   plugins/mcm/bench/peer.sh [PHIS="0.63 0.64"] [N=1000] [LAW=fixed|weibull] [SEEDS="1 2 3"]
#
# spheropack is installed into plugins/mcm/bench/.venv (never the project's .venv).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../../.." && pwd)
phis=${1:-"0.63 0.64"}
n=${2:-1000}
law=${3:-fixed}
seeds=${4:-"1 2 3"}
venv="$here/.venv"
if [ ! -x "$venv/bin/python" ]; then python3 -m venv "$venv"; fi
"$venv/bin/python" -c "import spheropack, numpy" 2>/dev/null || "$venv/bin/pip" install -q spheropack numpy
(cd "$root" && cargo build --release -q -p grainpipe-mcm --example classic_rcp)
mcm="$root/target/release/examples/classic_rcp"
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
echo "machine: $(nproc) cores, $(uptime | sed 's/.*load/load/')"
for phi in $phis; do
  for seed in $seeds; do
    t0=$(date +%s.%N)
    if "$mcm" "$phi" "$n" "$law" "$seed" "$out/mcm.csv" > "$out/mcm.log"; then
      t1=$(date +%s.%N)
      echo "mcm.classic  phi $phi seed $seed: $(echo "$t1 - $t0" | bc) s wall; check: $("$venv/bin/python" "$here/check_packing.py" "$out/mcm.csv")"
    else
      t1=$(date +%s.%N)
      echo "mcm.classic  phi $phi seed $seed: FAILED after $(echo "$t1 - $t0" | bc) s: $(cut -c1-200 "$out/mcm.log")"
    fi
    t0=$(date +%s.%N)
    "$venv/bin/python" "$here/spheropack_run.py" "$phi" "$n" "$law" "$seed" "$out/lsp.csv" > "$out/lsp.log" 2>&1 || true
    t1=$(date +%s.%N)
    echo "spheropack   phi $phi seed $seed: $(echo "$t1 - $t0" | bc) s wall ($(tail -1 "$out/lsp.log")); check: $("$venv/bin/python" "$here/check_packing.py" "$out/lsp.csv" 2>&1 | tail -1)"
  done
done
echo "load after: $(uptime | sed 's/.*load/load/')"
