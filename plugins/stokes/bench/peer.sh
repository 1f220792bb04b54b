#!/usr/bin/env bash
# Installs the lattice-Boltzmann peer (lbmpy, CPU code generation through pystencils and the
# system C compiler) into its own venv beside this script and runs it on the Zick & Homsy
# simple-cubic sphere images (issue 13). Never called by `make test`: it needs PyPI.
#
#   plugins/stokes/bench/peer.sh                 # install + run the default set
#   plugins/stokes/bench/peer.sh 20 0.125 0.343  # voxels per diameter, solid fractions
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
venv="$here/.venv"
if [[ ! -x "$venv/bin/python" ]]; then
    python3 -m venv "$venv"
    "$venv/bin/pip" install --quiet --upgrade pip
    # lbmpy 2.x needs Python >= 3.12; the 1.3 series runs on the machine's 3.11.
    "$venv/bin/pip" install --quiet "lbmpy==1.3.7" "pystencils==1.3.7"
fi
"$venv/bin/python" -c 'import lbmpy, pystencils; print("lbmpy", lbmpy.__version__, "pystencils", pystencils.__version__)'
if [[ $# -eq 0 ]]; then
    set -- 20 0.125 0.343
fi
exec "$venv/bin/python" "$here/peer_lbm.py" "$@"
