"""Peer for the temperature-calibration benchmark: numpy polyfit (degree 3, unweighted, as
ArduPilot's tempcal_IMU.py and PX4's process_sensor_caldata.py fit) on the same binned points.

Usage: peer_tempcal.py POINTS.csv   (columns seed,instance,channel,temp_c,value,se)
Prints one JSON line per (seed, instance, channel): the cubic's c0..c3 in (T - 35 C), and the
held-out score on alternate 1 C bands (fit on one parity, score on the other, both ways pooled):
RMS about a constant (before) and about the cubic (after).
"""
import json
import sys
from collections import defaultdict

import numpy as np

TREF = 35.0


def held_out(t, v):
    band = np.floor((t - t.min()) / 1.0).astype(int) % 2
    ss_b = ss_a = 0.0
    n = 0
    for parity in (0, 1):
        tr, te = band == parity, band != parity
        c = np.polyfit(t[tr] - TREF, v[tr], 3)
        ss_b += np.sum((v[te] - np.mean(v[tr])) ** 2)
        ss_a += np.sum((v[te] - np.polyval(c, t[te] - TREF)) ** 2)
        n += te.sum()
    return float(np.sqrt(ss_b / n)), float(np.sqrt(ss_a / n))


def main():
    groups = defaultdict(lambda: ([], []))
    with open(sys.argv[1]) as f:
        next(f)
        for line in f:
            seed, inst, ch, t, v, _se = line.split(",")
            g = groups[(int(seed), int(inst), int(ch))]
            g[0].append(float(t))
            g[1].append(float(v))
    for (seed, inst, ch), (t, v) in sorted(groups.items()):
        t, v = np.array(t), np.array(v)
        c = np.polyfit(t - TREF, v, 3)[::-1]
        before, after = held_out(t, v)
        print(json.dumps({"seed": seed, "instance": inst, "channel": ch, "c": list(map(float, c)),
                          "before": before, "after": after}))


main()
