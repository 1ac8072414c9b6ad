#!/usr/bin/env python3
"""Read an ArduPilot telemetry log (.tlog) with pymavlink and write what the vehicle streamed, as
it arrived: the magnetometer with the vehicle's own calibration still applied.

    pymavlink_ardupilot_stream.py TLOG OUT_CSV OUT_JSON

OUT_CSV: one row per RAW_IMU message, in the project's CSV shape
    t (s, the message's time_usec), ax ay az (m/s^2), gx gy gz (rad/s), mx my mz (uT),
    ref_qw..ref_qz (sensor -> ENU, from ATTITUDE), lat lon alt (the newest fix).
ArduPilot fills RAW_IMU in SCALED_IMU's units: mG, mrad/s, mGauss. An attitude rides on the first
RAW_IMU after it arrives when it arrived at most 0.25 s before; a position on every row after the
first fix. A frame repeating the last one exactly is left out.

OUT_JSON: {"ofs": [COMPASS_OFS_X, _Y, _Z] as the vehicle last sent them (mGauss),
           "changes": number of times they changed, "rows": rows written}.
"""
import csv
import json
import math
import sys

from pymavlink import mavutil

G = 9.80665


def quat_mul(a, b):
    return [
        a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
        a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
        a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
        a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
    ]


def ref_q(roll, pitch, yaw):
    """Body FRD -> NED from ZYX Euler angles, then NED -> ENU (half turn about (1, 1, 0))."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    q = [
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    ]
    h = math.sqrt(0.5)
    return quat_mul([0.0, h, h, 0.0], q)


def main():
    src, out_csv, out_json = sys.argv[1:4]
    m = mavutil.mavlink_connection(src, dialect="ardupilotmega")
    params = {}
    ofs_history = []
    att = None  # (record time s, quaternion, taken)
    pos = None
    last = None
    rows = []
    while True:
        msg = m.recv_match()
        if msg is None:
            break
        kind = msg.get_type()
        ts = msg._timestamp
        if kind == "PARAM_VALUE":
            params[msg.param_id] = msg.param_value
            if msg.param_id.startswith("COMPASS_OFS_"):
                ofs = [params.get("COMPASS_OFS_" + a) for a in "XYZ"]
                if None not in ofs and (not ofs_history or ofs_history[-1] != ofs):
                    ofs_history.append(ofs)
        elif kind == "ATTITUDE":
            att = [ts, ref_q(msg.roll, msg.pitch, msg.yaw), False]
        elif kind == "GLOBAL_POSITION_INT" and (msg.lat != 0 or msg.lon != 0):
            pos = (msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3)
        elif kind == "GPS_RAW_INT" and msg.fix_type >= 3:
            pos = (msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3)
        elif kind == "RAW_IMU":
            key = (msg.time_usec, msg.xacc, msg.yacc, msg.zacc, msg.xgyro, msg.ygyro,
                   msg.zgyro, msg.xmag, msg.ymag, msg.zmag)
            if key == last:
                continue
            last = key
            row = {
                "t": msg.time_usec / 1e6,
                "ax": msg.xacc * G / 1000.0, "ay": msg.yacc * G / 1000.0,
                "az": msg.zacc * G / 1000.0,
                "gx": msg.xgyro * 1e-3, "gy": msg.ygyro * 1e-3, "gz": msg.zgyro * 1e-3,
                "mx": msg.xmag * 0.1, "my": msg.ymag * 0.1, "mz": msg.zmag * 0.1,
            }
            if att is not None and not att[2] and abs(ts - att[0]) <= 0.25:
                q = att[1]
                row.update(ref_qw=q[0], ref_qx=q[1], ref_qy=q[2], ref_qz=q[3])
            if att is not None:
                att[2] = True
            if pos is not None:
                row.update(lat=pos[0], lon=pos[1], alt=pos[2])
            rows.append(row)
    cols = ["t", "ax", "ay", "az", "gx", "gy", "gz", "mx", "my", "mz",
            "ref_qw", "ref_qx", "ref_qy", "ref_qz", "lat", "lon", "alt"]
    with open(out_csv, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols)
        w.writeheader()
        for r in rows:
            w.writerow({k: repr(v) for k, v in r.items()})
    with open(out_json, "w") as f:
        json.dump({"ofs": ofs_history[-1] if ofs_history else None,
                   "changes": max(len(ofs_history) - 1, 0), "rows": len(rows)}, f)


if __name__ == "__main__":
    main()
