#!/bin/sh
# Installs the peer `peripy` (PyPI; OpenCL, run on the CPU by Debian's pocl-opencl-icd) into
# its own venv plugins/peridynamics/bench/.venv (never the repository's .venv) and reports
# what works. Usage: sh plugins/peridynamics/bench/peer.sh
set -eu
here=$(cd "$(dirname "$0")" && pwd)
venv="$here/.venv"
if ! dpkg -s pocl-opencl-icd >/dev/null 2>&1; then
    echo "pocl-opencl-icd is not installed: sudo apt-get install pocl-opencl-icd ocl-icd-opencl-dev" >&2
fi
python3 -m venv "$venv"
"$venv/bin/pip" install --quiet --upgrade pip
# peripy ships only an sdist whose setup.py imports Cython: install it first and build
# without isolation so the build sees it.
"$venv/bin/pip" install --quiet numpy pyopencl cython setuptools
"$venv/bin/pip" install --quiet --no-build-isolation peripy
"$venv/bin/python" - <<'PY'
import pyopencl as cl
print("OpenCL platforms:", [p.name for p in cl.get_platforms()])
import peripy
print("peripy", getattr(peripy, "__version__", "?"), "imported")
PY
