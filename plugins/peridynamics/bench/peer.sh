#!/bin/sh
# Installs the peer `peripy` 1.0.0 (PyPI; OpenCL, run on the CPU by Debian's pocl-opencl-icd)
# into its own venv plugins/peridynamics/bench/.venv (never the repository's .venv) and runs
# the force-sweep comparison of BENCHMARKS.md.
# Usage: sh plugins/peridynamics/bench/peer.sh [N] [STEPS]
#
# Why the detour: 1.0.0 is the only release; its sdist lacks the .pyx sources its setup.py
# names ("'peripy/create_crack.pyx' doesn't match any files") but ships the C files Cython
# 0.29.24 generated from them. Those compile against CPython <= 3.10 only (3.11 changed
# PyCode_New, the frame and thread-state structs: "too few arguments to function
# 'PyCode_New'"), so the venv uses a 3.10 interpreter and setup.py is pointed at the .c files.
set -eu
here=$(cd "$(dirname "$0")" && pwd)
venv="$here/.venv"
n=${1:-512}
steps=${2:-20}
py=${PYTHON310:-}
if [ -z "$py" ]; then
    for c in python3.10 "$HOME/.pyenv/versions/3.10"*/bin/python; do
        if command -v "$c" >/dev/null 2>&1; then py=$c; break; fi
    done
fi
[ -n "$py" ] || { echo "needs a Python 3.10 interpreter (set PYTHON310)" >&2; exit 1; }
if ! dpkg -s pocl-opencl-icd >/dev/null 2>&1; then
    echo "pocl-opencl-icd is missing: apt-get install -y pocl-opencl-icd ocl-icd-opencl-dev" >&2
    exit 1
fi
if [ ! -x "$venv/bin/python" ] || ! "$venv/bin/python" -c "import peripy" 2>/dev/null; then
    "$py" -m venv "$venv"
    "$venv/bin/pip" install --quiet "numpy<2" pyopencl setuptools wheel scipy meshio tqdm h5py \
        scikit-learn
    work=$(mktemp -d)
    # The sdist itself (pip download would try to build its metadata and fail as above).
    url=$(curl -s https://pypi.org/simple/peripy/ | grep -o 'https://[^"#]*peripy-1.0.0.tar.gz' | head -1)
    curl -s -o "$work/peripy.tar.gz" "$url"
    tar xzf "$work/peripy.tar.gz" -C "$work"
    src="$work/peripy-1.0.0"
    # Build the shipped C files instead of the missing .pyx; 'sklearn' is the deprecated
    # alias of scikit-learn and sphinx_rtd_theme only builds its docs.
    sed -i 's/\.pyx"/.c"/; s/^from Cython.Build import cythonize/cythonize = lambda x: x/' "$src/setup.py"
    sed -i "/'sklearn',/d; /sphinx_rtd_theme/d" "$src/setup.py"
    "$venv/bin/pip" install --quiet --no-build-isolation --no-deps "$src"
    rm -rf "$work"
fi
"$venv/bin/python" -c "import pyopencl as cl; print('OpenCL:', [(p.name, [d.name for d in p.get_devices()]) for p in cl.get_platforms()])"
"$venv/bin/python" "$here/peer_sweep.py" "$n" "$steps" 2>&1 | grep -a "peripy n="
