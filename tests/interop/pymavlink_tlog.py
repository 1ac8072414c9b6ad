#!/usr/bin/env python3
"""Write a .tlog with pymavlink from a CSV of samples (t,ax,ay,az,gx,gy,gz,mx,my,mz: s, m/s^2,
rad/s, uT), the way a ground station records one: per record a big-endian u64 of its own clock
(Unix microseconds), then the frame pymavlink encoded (MAVLink 2, HIGHRES_IMU).

    pymavlink_tlog.py CSV OUT MODE

MODE sets the autopilot's message clock (time_usec):
    zero    counts from 0 at the first sample (a bridge that starts its clock with its stream)
    reboot  as from boot at 10 s, restarting at 3 s halfway through (the record clock goes on)
    first   the first half only, as from boot at 10 s
    second  the second half only, recorded a day earlier, as from boot at 500 s
"""
import csv
import struct
import sys

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

EPOCH_US = 1_700_000_000_000_000
DAY_US = 86_400_000_000


def main():
    src, out, mode = sys.argv[1], sys.argv[2], sys.argv[3]
    rows = list(csv.DictReader(open(src)))
    n = len(rows)
    half = n // 2
    if mode == "first":
        rows = rows[:half]
    elif mode == "second":
        rows = rows[half:]
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    t0 = float(rows[0]["t"])
    with open(out, "wb") as f:
        for i, r in enumerate(rows):
            t_us = int(round((float(r["t"]) - t0) * 1e6))
            record = EPOCH_US + t_us
            if mode == "zero":
                msg_us = t_us
            elif mode == "reboot":
                msg_us = 10_000_000 + t_us if i < half else 3_000_000 + t_us - half_t_us
            elif mode == "second":
                record -= DAY_US
                msg_us = 500_000_000 + t_us
            else:
                msg_us = 10_000_000 + t_us
            if i == half - 1:
                half_t_us = t_us
            v = [float(r[k]) for k in ("ax", "ay", "az", "gx", "gy", "gz", "mx", "my", "mz")]
            msg = mav.highres_imu_encode(
                msg_us, v[0], v[1], v[2], v[3], v[4], v[5],
                v[6] / 100.0, v[7] / 100.0, v[8] / 100.0,  # uT -> gauss
                0.0, 0.0, 0.0, 25.0, 0x1FFF, 0)
            f.write(struct.pack(">Q", record) + msg.pack(mav))


if __name__ == "__main__":
    main()
