#!/usr/bin/env bash
# Table 2 resolution study (issue 12): plugins/fft/bench/resolution.yaml at 8, 4, 2 um.
#
#   plugins/fft/bench/resolution.sh [layer size, default "560 um"] [voxel sizes, default "8 4 2"]
#
# The paper's cell is 2 layers of 280 um on (560 um)^2; at 2 um that is 280^3 voxels
# (~5.5 GB and well over half an hour for six load cases on 2 shared cores), so the bench
# can run a smaller in-plane size with the same grains, e.g. `resolution.sh "280 um"`.
# Each run under /usr/bin/time -v (wall, CPU, peak RSS) with `uptime` beside it; results
# collected into plugins/fft/bench/resolution.csv (E_x ... G_xy, orthotropy error).
set -euo pipefail
cd "$(dirname "$0")/../../.."
bench=plugins/fft/bench
layer=${1:-560 um}
read -r -a voxels <<<"${2:-8 4 2}"
# BUILD=0 reuses the binary already built (the cargo lock is shared with other builds).
[ "${BUILD:-1}" = 0 ] || cargo build --release -q -p grainpipe-cli
tag=${layer// /}
csv=$bench/resolution.csv
log=$bench/resolution.log
[ -f "$csv" ] || echo "layer_size,voxel_um,constants_file,wall_s,cpu_s,peak_rss_mb,load_before" >"$csv"
for v in "${voxels[@]}"; do
  out=out/fft-resolution/$tag-${v}um
  load=$(uptime | sed 's/.*load average: //; s/,.*//')
  tv=$(mktemp)
  /usr/bin/time -v -o "$tv" ./target/release/pipe run -q $bench/resolution.yaml \
    --set "pack.layer_size=[$layer, $layer]" --set "binder.voxel_size=$v um" --out "$out"
  wall=$(awk -F': ' '/Elapsed \(wall clock\)/ {n=split($2,t,":"); s=0; for(i=1;i<=n;i++) s=s*60+t[i]; print s}' "$tv")
  cpu=$(awk -F': ' '/User time/ {u=$2} /System time/ {s=$2} END {print u+s}' "$tv")
  rss=$(awk -F': ' '/Maximum resident set size/ {printf "%.1f", $2/1024}' "$tv")
  { echo "== $layer at $v um (load before: $load)"; cat "$tv"; uptime; } >>"$log"
  echo "$layer,$v,$out/fft-resolution/constants.csv,$wall,$cpu,$rss,$load" >>"$csv"
  rm -f "$tv"
done
cat "$csv"
