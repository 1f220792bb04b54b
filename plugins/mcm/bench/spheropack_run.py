"""spheropack to a volume fraction in the periodic unit cube; writes x,y,z,r CSV (box 1).

python spheropack_run.py PHI N LAW SEED OUT.csv   (LAW: fixed, or weibull with shape 3.55)
"""
import sys
import time

import numpy as np
import spheropack

phi, n, law, seed, out = float(sys.argv[1]), int(sys.argv[2]), sys.argv[3], int(sys.argv[4]), sys.argv[5]
if law == "fixed":
    radii = np.ones(n)
else:
    radii = np.random.default_rng(seed).weibull(3.55, n)
t0 = time.perf_counter()
p = spheropack.pack(n=n, radii=radii, density=phi, seed=seed)
dt = time.perf_counter() - t0
with open(out, "w") as f:
    f.write("# box 1 1 1\nx,y,z,r\n")
    for (x, y, z), r in zip(p.positions, p.radii):
        f.write(f"{float(x)!r},{float(y)!r},{float(z)!r},{float(r)!r}\n")
print(f"status {p.status}, density {p.density:.4f}, {dt:.2f} s in pack()")
