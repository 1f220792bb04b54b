#!/usr/bin/env bash
# Draws docs/stages/binder_grid.png from out/bench/binder.csv in a venv of its own.
set -euo pipefail
cd "$(dirname "$0")/../../.."
venv=.bench-venv
[ -x $venv/bin/python ] || { python3 -m venv $venv && $venv/bin/pip install -q matplotlib; }
$venv/bin/python plugins/binder/bench/chart.py "$@"
