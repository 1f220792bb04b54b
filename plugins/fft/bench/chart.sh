#!/usr/bin/env bash
# Draws docs/stages/elasticity_error_vs_time.png from errtime.csv and peer.csv with
# matplotlib in the bench's own venv (created by peer.sh, or here if missing).
set -euo pipefail
cd "$(dirname "$0")/../../.."
venv=plugins/fft/bench/.venv
if [ ! -x $venv/bin/python ] || ! $venv/bin/python -c 'import matplotlib' 2>/dev/null; then
  python3 -m venv $venv
  $venv/bin/pip install -q 'numpy<2' 'muspectre==0.27.0' matplotlib
fi
$venv/bin/python plugins/fft/bench/chart.py "$@"
