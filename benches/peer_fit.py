"""Peer for the fit benchmark: SciPy least_squares (Levenberg-Marquardt) on the same sym9 norm residual.

Usage: peer_fit.py POINTS.csv REPEATS [BATCHES]   (prints JSON: seconds per fit, the best of BATCHES
(default 20) batches of REPEATS fits; offset; iterations)
The residual and start mirror imucald's: data normalised by a linear sphere fit, r_i = |A (x_i - p)| - 1
with A symmetric, analytic Jacobian, so SciPy gets its best chance.
"""
import json
import sys
import time

import numpy as np
from scipy.optimize import least_squares


def sphere_start(x):
    a = np.column_stack([2 * x, np.ones(len(x))])
    b = (x * x).sum(axis=1)
    s, *_ = np.linalg.lstsq(a, b, rcond=None)
    c = s[:3]
    return c, np.sqrt(s[3] + c @ c)


def unpack(p):
    a11, a22, a33, a12, a13, a23 = p[3:]
    return p[:3], np.array([[a11, a12, a13], [a12, a22, a23], [a13, a23, a33]])


def resid(p, x):
    c, a = unpack(p)
    u = (x - c) @ a.T
    return np.linalg.norm(u, axis=1) - 1.0


def jac(p, x):
    c, a = unpack(p)
    v = x - c
    u = v @ a.T
    n = np.linalg.norm(u, axis=1)[:, None]
    j = np.empty((len(x), 9))
    j[:, :3] = -(u @ a) / n
    d = lambda i, k: (u[:, i] * v[:, k])[:, None] / n
    j[:, 3:4] = d(0, 0)
    j[:, 4:5] = d(1, 1)
    j[:, 5:6] = d(2, 2)
    j[:, 6:7] = d(0, 1) + d(1, 0)
    j[:, 7:8] = d(0, 2) + d(2, 0)
    j[:, 8:9] = d(1, 2) + d(2, 1)
    return j


def fit(raw):
    c0, s0 = sphere_start(raw)
    x = (raw - c0) / s0
    p0 = np.array([0, 0, 0, 1, 1, 1, 0, 0, 0], dtype=float)
    r = least_squares(resid, p0, jac=jac, args=(x,), method="lm", xtol=1e-12, ftol=1e-12)
    return c0 + s0 * r.x[:3], r.nfev


def main():
    raw = np.loadtxt(sys.argv[1], delimiter=",")
    reps = int(sys.argv[2])
    off, nfev = fit(raw)
    # Best of BATCHES batches of REPEATS fits (imucald's side does the same).
    batches = int(sys.argv[3]) if len(sys.argv) > 3 else 20
    dt = float("inf")
    for _ in range(batches):
        t0 = time.perf_counter()
        for _ in range(reps):
            fit(raw)
        dt = min(dt, (time.perf_counter() - t0) / reps)
    print(json.dumps({"seconds_per_fit": dt, "offset": off.tolist(), "nfev": int(nfev), "scipy": __import__("scipy").__version__}))


if __name__ == "__main__":
    main()
