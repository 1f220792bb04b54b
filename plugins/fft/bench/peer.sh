#!/usr/bin/env bash
# Peer side by side (issue 12): the simple-cubic spherical pore of porosity 0.2 (E = 1,
# nu = 0.3), load cases xx and yz, solved by muSpectre 0.27.0 (PyPI) and by ours
# (examples/fft_study.rs, staggered and hex8, tolerance 1e-5), one after the other on the
# same machine. Every run goes through /usr/bin/time -v for wall time, CPU time and peak
# RSS; `uptime` is logged beside it because the 2 cores are shared.
#
#   plugins/fft/bench/peer.sh [sizes...]        (default: 32 64)
#   OURS_ONLY="96 112 128 160" plugins/fft/bench/peer.sh 32 64
#
# OURS_ONLY: sizes run by ours alone (finer grids that reach the peer's accuracy; muSpectre
# at 128^3 would need ~70 GB). PRECISIONS: ours in these precisions (default "double single";
# the peer runs in double).
#
# Writes plugins/fft/bench/peer.csv (one row per run and load case) and peer.log.
# The venv is private to the bench (plugins/fft/bench/.venv, gitignored) so `make test`
# never needs Python; muSpectre 0.27.0 is built against the numpy 1 ABI, hence numpy<2.
set -euo pipefail
cd "$(dirname "$0")/../../.."
bench=plugins/fft/bench
venv=$bench/.venv
sizes=("${@:-32 64}")
read -r -a sizes <<<"${sizes[*]}"
read -r -a ours_only <<<"${OURS_ONLY-}"
read -r -a precisions <<<"${PRECISIONS-double single}"

if [ ! -x $venv/bin/python ] || ! $venv/bin/python -c 'import muSpectre, matplotlib' 2>/dev/null; then
  python3 -m venv $venv
  $venv/bin/pip install -q 'numpy<2' 'muspectre==0.27.0' matplotlib
fi
# BUILD=0 reuses the binary already built (the cargo lock is shared with other builds).
[ "${BUILD:-1}" = 0 ] || cargo build --release -q -p grainpipe-fft --example fft_study
ours=target/release/examples/fft_study

csv=$bench/peer.csv
log=$bench/peer.log
: >"$log"
echo "solver,n,discretization,precision,tolerance,porosity,case,status,iterations,seconds,c11,c12,c44,wall_s,cpu_s,peak_rss_mb,load_before" >"$csv"

# run <label> <command...>: one timed process; its CSV rows get the process totals appended
# (the two load cases share one process, so wall/CPU/RSS are per size and solver).
run() {
  local label=$1
  shift
  local load tv out
  load=$(uptime | sed 's/.*load average: //; s/,.*//')
  tv=$(mktemp)
  out=$(/usr/bin/time -v -o "$tv" "$@")
  local wall cpu rss
  wall=$(awk -F': ' '/Elapsed \(wall clock\)/ {n=split($2,t,":"); s=0; for(i=1;i<=n;i++) s=s*60+t[i]; print s}' "$tv")
  cpu=$(awk -F': ' '/User time/ {u=$2} /System time/ {s=$2} END {print u+s}' "$tv")
  rss=$(awk -F': ' '/Maximum resident set size/ {printf "%.1f", $2/1024}' "$tv")
  {
    echo "== $label: $* (load before: $load)"
    echo "$out"
    grep -E 'Elapsed|User time|System time|Maximum resident' "$tv"
    uptime
  } >>"$log"
  while IFS= read -r row; do
    echo "$label,$row,$wall,$cpu,$rss,$load" >>"$csv"
  done <<<"$out"
  rm -f "$tv"
}

for n in "${sizes[@]}" "${ours_only[@]}"; do
  if [[ " ${sizes[*]} " == *" $n "* ]]; then
    run muspectre $venv/bin/python $bench/muspectre_sc_pore.py "$n" xx,yz 1e-5
  fi
  for d in staggered hex8; do
    for prec in "${precisions[@]}"; do
      run ours $ours "$n" $d xx,yz 1e-5 "$prec"
    done
  done
done
column -s, -t "$csv"
