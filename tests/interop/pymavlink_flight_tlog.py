#!/usr/bin/env python3
"""Write a .tlog with pymavlink from a CSV of a simulated flight, as a ground station records an
ArduPilot vehicle: HIGHRES_IMU per sample, ATTITUDE (Euler angles, body FRD -> NED) whenever the
reference attitude changes, GPS_RAW_INT (3-D fix) and SYS_STATUS (battery current) at 5 Hz.

    pymavlink_flight_tlog.py CSV OUT

The CSV has t,ax,ay,az,gx,gy,gz,mx,my,mz (s, m/s^2, rad/s, uT), current (A), ref_qw..ref_qz (the
attitude, sensor -> ENU) and lat,lon,alt (deg, deg, m). The attitude is turned into MAVLink's
convention here, independently of the reader: ENU -> NED is the half-turn about (1, 1, 0)/sqrt(2),
then roll, pitch, yaw of the ZYX Euler sequence.
"""
import csv
import math
import struct
import sys

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

EPOCH_US = 1_700_000_000_000_000
BOOT_US = 10_000_000


def qmul(a, b):
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def euler_zyx(q):
    w, x, y, z = q
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def main():
    src, out = sys.argv[1], sys.argv[2]
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    h = math.sqrt(0.5)
    ned_from_enu = (0.0, h, h, 0.0)
    last_q = None
    next_slow = -1.0
    with open(out, "wb") as f:
        def put(record, msg):
            f.write(struct.pack(">Q", record) + msg.pack(mav))

        for r in csv.DictReader(open(src)):
            t = float(r["t"])
            t_us = int(round(t * 1e6))
            record = EPOCH_US + t_us
            boot_ms = (BOOT_US + t_us) // 1000
            # Cells are empty where the simulation has no reference (yet).
            q = tuple(float(r[k]) for k in ("ref_qw", "ref_qx", "ref_qy", "ref_qz") if r[k])
            if len(q) == 4 and q != last_q:
                last_q = q
                roll, pitch, yaw = euler_zyx(qmul(ned_from_enu, q))
                put(record, mav.attitude_encode(boot_ms, roll, pitch, yaw, 0.0, 0.0, 0.0))
            if t >= next_slow and r["lat"] and r["current"]:
                next_slow = t + 0.2
                lat, lon, alt = (float(r[k]) for k in ("lat", "lon", "alt"))
                put(record, mav.gps_raw_int_encode(
                    BOOT_US + t_us, 3, int(round(lat * 1e7)), int(round(lon * 1e7)),
                    int(round(alt * 1e3)), 80, 120, 1500, 0, 12))
                current_ca = int(round(float(r["current"]) * 100))
                put(record, mav.sys_status_encode(
                    0, 0, 0, 500, 15800, current_ca, 80, 0, 0, 0, 0, 0, 0))
            v = [float(r[k]) for k in ("ax", "ay", "az", "gx", "gy", "gz", "mx", "my", "mz")]
            put(record, mav.highres_imu_encode(
                BOOT_US + t_us, v[0], v[1], v[2], v[3], v[4], v[5],
                v[6] / 100.0, v[7] / 100.0, v[8] / 100.0,  # uT -> gauss
                0.0, 0.0, 0.0, 25.0, 0x1FFF, 0))


if __name__ == "__main__":
    main()
