"""Peers for the held-out quality bench: two other fits of a compass on the same fitting blocks.

Usage: peer_magfit.py QUALITY.csv   (one file of `imucald replay --quality-points DIR`)
Prints JSON: {"lsq": FIT, "magfit_wmm": FIT}, where FIT is {"offset_ut": [3], "matrix": [[3]x3]}
(calibrated = matrix (raw - offset), body axes, uT) or {"skipped": reason}.

- lsq: SciPy least squares of M (raw - o) = R^T B over the fitting rows, M symmetric (6), o (3)
  and the earth field's direction (inclination, declination: 2) fitted; B's strength is held (it
  trades against M's scale) at the model's strength when the file gives the place's field, else at
  the radius of a sphere fitted to the readings. R is the body -> NED attitude of each row.
- magfit_wmm: ArduPilot's MAGFit against the WMM, pymavlink's `magfit_WMM.py --elliptical`
  (offsets, diagonals, off-diagonals and scale; the field from its own model table at the place),
  run as ArduPilot's users run it: on a DataFlash log, here a text DataFlash log of the fitting
  rows (MAG in mGauss with no onboard offsets, ATT roll/pitch/yaw, one GPS fix, PARM). Needs a
  place (the file's `# place` line).
"""
import json
import math
import os
import subprocess
import sys
import tempfile

import numpy as np
from scipy.optimize import least_squares


def read(path):
    place = field = None
    with open(path) as f:
        comments = [l for l in f if l.startswith("#")]
    for first in (c for c in comments if c.startswith("# place")):
        head, tail = first[len("# place"):].split(";")
        lat, lon, _date = head.split()
        place = (float(lat), float(lon))
        field = np.array([float(x) for x in tail.split()[3:6]])
    with open(path) as f:
        rows = [l.rstrip("\n").split(",") for l in f if not l.startswith("#")]
    head, rows = rows[0], rows[1:]
    num = lambda c: float(c) if c else math.nan
    d = {h: np.array([num(r[i]) for r in rows]) for i, h in enumerate(head)}
    return d, place, field


def rot(q):
    """Body -> NED rotation matrices of unit quaternions (w, x, y, z), shape (n, 3, 3)."""
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def sphere(x):
    a = np.column_stack([2 * x, np.ones(len(x))])
    s, *_ = np.linalg.lstsq(a, (x * x).sum(1), rcond=None)
    return s[:3], math.sqrt(max(s[3] + s[:3] @ s[:3], 1e-9))


def sym(p):
    a, b, c, d, e, f = p
    return np.array([[a, d, e], [d, b, f], [e, f, c]])


def lsq(raw, r, field):
    o0, rad = sphere(raw)
    strength = np.linalg.norm(field) if field is not None else rad
    ned = np.einsum("nij,nj->ni", r, raw - o0).mean(0)
    inc0 = math.atan2(ned[2], math.hypot(ned[0], ned[1]))
    dec0 = math.atan2(ned[1], ned[0])
    k = strength / rad
    p0 = np.concatenate([o0, [k, k, k, 0, 0, 0], [inc0, dec0]])

    def resid(p):
        o, m, (inc, dec) = p[:3], sym(p[3:9]), p[9:]
        b = strength * np.array([math.cos(inc) * math.cos(dec), math.cos(inc) * math.sin(dec), math.sin(inc)])
        body = np.einsum("nji,j->ni", r, b)
        return ((raw - o) @ m.T - body).ravel()

    res = least_squares(resid, p0, method="lm", xtol=1e-12, ftol=1e-12)
    if not res.success:
        return {"skipped": "did not converge: " + res.message}
    return {"offset_ut": res.x[:3].tolist(), "matrix": sym(res.x[3:9]).tolist()}


def euler_deg(r):
    """ZYX Euler angles (roll, pitch, yaw; deg) of body -> NED rotation matrices."""
    roll = np.degrees(np.arctan2(r[:, 2, 1], r[:, 2, 2]))
    pitch = np.degrees(-np.arcsin(np.clip(r[:, 2, 0], -1, 1)))
    yaw = np.degrees(np.arctan2(r[:, 1, 0], r[:, 0, 0]))
    return roll, pitch, yaw


def magfit_wmm(raw, r, t, place):
    if place is None:
        return {"skipped": "no place: MAGFit's field needs a GPS fix"}
    exe = os.path.join(os.path.dirname(sys.executable), "magfit_WMM.py")
    if not os.path.exists(exe):
        return {"skipped": "pymavlink's magfit_WMM.py is not installed"}
    roll, pitch, yaw = euler_deg(r)
    with tempfile.TemporaryDirectory() as tmp:
        log = os.path.join(tmp, "fit.log")
        with open(log, "w") as f:
            f.write("FMT, 128, 89, FMT, BBnNZ, Type,Length,Name,Format,Columns\n")
            f.write("FMT, 129, 0, PARM, QNf, TimeUS,Name,Value\n")
            f.write("FMT, 130, 0, GPS, QBIHff, TimeUS,Status,GMS,GWk,Lat,Lng\n")
            f.write("FMT, 131, 0, ATT, Qfff, TimeUS,Roll,Pitch,Yaw\n")
            f.write("FMT, 132, 0, MAG, Qffffff, TimeUS,MagX,MagY,MagZ,OfsX,OfsY,OfsZ\n")
            params = {"AHRS_EKF_TYPE": 0, "AHRS_TRIM_X": 0, "AHRS_TRIM_Y": 0, "AHRS_TRIM_Z": 0}
            for a in "XYZ":
                params.update({f"COMPASS_OFS_{a}": 0, f"COMPASS_DIA_{a}": 1, f"COMPASS_ODI_{a}": 0})
            for k, v in params.items():
                f.write(f"PARM, 0, {k}, {v}\n")
            f.write(f"GPS, 0, 3, 0, 2000, {place[0]}, {place[1]}\n")
            for i in range(len(t)):
                us = int(1e6 * t[i]) + 1
                f.write(f"ATT, {us}, {roll[i]}, {pitch[i]}, {yaw[i]}\n")
                m = 10.0 * raw[i]  # uT -> mGauss
                f.write(f"MAG, {us}, {m[0]}, {m[1]}, {m[2]}, 0, 0, 0\n")
        env = dict(os.environ, MPLBACKEND="Agg")
        out = subprocess.run([sys.executable, exe, "--elliptical", "--save-params", log],
                             cwd=tmp, env=env, capture_output=True, text=True)
        parm = os.path.join(tmp, "fit-magfit-mag-1.param")
        if out.returncode != 0 or not os.path.exists(parm):
            tail = (out.stdout + out.stderr).strip().splitlines()[-1:] or ["no output"]
            return {"skipped": "magfit_WMM.py failed: " + tail[0]}
        p = {}
        for line in open(parm):
            k, v = line.split()
            p[k] = float(v)
    # ArduPilot: corrected = scale * M (raw + OFS), OFS in mGauss; imucald: matrix (raw - offset), uT.
    ofs = np.array([p["COMPASS_OFS_" + a] for a in "XYZ"])
    dia = [p["COMPASS_DIA_" + a] for a in "XYZ"]
    odi = [p["COMPASS_ODI_" + a] for a in "XYZ"]
    m = p["COMPASS_SCALE"] * np.array([[dia[0], odi[0], odi[1]], [odi[0], dia[1], odi[2]], [odi[1], odi[2], dia[2]]])
    return {"offset_ut": (-ofs / 10.0).tolist(), "matrix": m.tolist()}


def main():
    d, place, field = read(sys.argv[1])
    fit = d["fit"] == 1
    raw = np.column_stack([d["mx"], d["my"], d["mz"]])[fit]
    r = rot(np.column_stack([d["qw"], d["qx"], d["qy"], d["qz"]])[fit])
    out = {}
    if len(raw) < 30:
        out = {k: {"skipped": f"{len(raw)} fitting readings"} for k in ("lsq", "magfit_wmm")}
    else:
        out["lsq"] = lsq(raw, r, field)
        out["magfit_wmm"] = magfit_wmm(raw, r, d["t"][fit], place)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
