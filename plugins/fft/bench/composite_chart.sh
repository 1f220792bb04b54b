#!/usr/bin/env bash
# Runs the composite-voxel error/time sweep and draws docs/stages/composite_error_vs_time.png
# with matplotlib in the bench's own venv (never installed by make test).
set -euo pipefail
cd "$(dirname "$0")/../../.."
venv=plugins/fft/bench/.venv
if [ ! -x $venv/bin/python ] || ! $venv/bin/python -c 'import matplotlib' 2>/dev/null; then
  python3 -m venv $venv
  $venv/bin/pip install -q matplotlib
fi
[ "${RUN:-1}" = 0 ] || cargo run --release -q -p grainpipe-fft --example composite_errtime >plugins/fft/bench/composite_errtime.csv
$venv/bin/python plugins/fft/bench/composite_chart.py "$@"
