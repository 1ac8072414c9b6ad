"""Interop peer written against pymavlink (not by imucald): a vehicle resting at a known yaw, then a
ground station asking `imucald run` for a fixed-yaw compass calibration (MAV_CMD_FIXED_MAG_CAL_YAW),
the way Mission Planner's "Large Vehicle MagCal" does.

usage: pymavlink_fixed_yaw.py PORT YAW_DEG ROLL_DEG PITCH_DEG LAT LON BN BE BD OX OY OZ
(B: the earth field, NED, uT; O: the hidden hard iron, uT.)

As system 1 component 1 it streams HIGHRES_IMU at 100 Hz for 2 s: the field R^T B + O (gauss) and
the specific force R^T (0, 0, -g), R = Rz(yaw) Ry(pitch) Rx(roll), with a little noise. Then, as
the ground station (255/190), it sends the command to the service (1/191) with the yaw and the
place, and waits for COMMAND_ACK and MAG_CAL_REPORT. Prints one JSON line with what it saw; exit 0
when the ACK says accepted and the report's offsets (ArduPilot COMPASS_OFS convention, mGauss,
ofs = -hard_iron) are within 10 mGauss (1 uT) of the truth, 1 otherwise.
"""
import json
import math
import os
import random
import sys
import time

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402

args = [float(a) for a in sys.argv[2:]]
port = sys.argv[1]
yaw, roll, pitch, lat, lon = args[0:5]
b_ned = args[5:8]
hard = args[8:11]


def rot_body_to_ned(r, p, y):
    r, p, y = math.radians(r), math.radians(p), math.radians(y)
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ]


R = rot_body_to_ned(roll, pitch, yaw)


def to_body(v):
    return [sum(R[i][k] * v[i] for i in range(3)) for k in range(3)]


mag_body = to_body(b_ned)
acc_body = to_body([0.0, 0.0, -9.80665])
m = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1, dialect="ardupilotmega")
rng = random.Random(7)
t0 = time.time()
for k in range(200):
    mag = [(mag_body[i] + hard[i] + rng.gauss(0, 0.05)) / 100.0 for i in range(3)]
    acc = [acc_body[i] + rng.gauss(0, 0.02) for i in range(3)]
    m.mav.highres_imu_send(
        int(1e6 + k * 1e4), acc[0], acc[1], acc[2], 0.0, 0.0, 0.0, mag[0], mag[1], mag[2],
        1013.0, 0.0, 0.0, 25.0, 0x1FFF,
    )
    time.sleep(max(0.0, t0 + (k + 1) * 0.01 - time.time()))

# STALE_S: the data stops this long before the command (the service must refuse stale data).
stale_s = float(os.environ.get("STALE_S", "0"))
time.sleep(stale_s)

# The ground station's turn.
m.mav.srcSystem, m.mav.srcComponent = 255, 190
m.mav.command_long_send(1, 191, mavutil.mavlink.MAV_CMD_FIXED_MAG_CAL_YAW, 0, yaw, 0, lat, lon, 0, 0, 0)
seen = {"ack": None, "report": None, "texts": []}
deadline = time.time() + 5.0
while time.time() < deadline and (seen["ack"] is None or (seen["report"] is None and not stale_s)):
    msg = m.recv_match(type=["COMMAND_ACK", "MAG_CAL_REPORT", "STATUSTEXT"], blocking=True, timeout=0.5)
    if msg is None:
        continue
    if msg.get_type() == "COMMAND_ACK" and msg.command == mavutil.mavlink.MAV_CMD_FIXED_MAG_CAL_YAW:
        seen["ack"] = msg.result
    elif msg.get_type() == "MAG_CAL_REPORT":
        seen["report"] = {"ofs": [msg.ofs_x, msg.ofs_y, msg.ofs_z], "status": msg.cal_status, "autosaved": msg.autosaved}
    elif msg.get_type() == "STATUSTEXT":
        seen["texts"].append(msg.text)

if stale_s:
    # Refused (MAV_RESULT_FAILED, 4), nothing reported, and the reason said.
    ok = seen["ack"] == 4 and seen["report"] is None and "old" in "".join(seen["texts"])
    print(json.dumps(seen))
    sys.exit(0 if ok else 1)

ok = seen["ack"] == 0 and seen["report"] is not None
if ok:
    err = max(abs(seen["report"]["ofs"][i] + 10.0 * hard[i]) for i in range(3))
    seen["ofs_error_mgauss"] = err
    ok = err < 10.0 and seen["report"]["status"] == 4
print(json.dumps(seen))
sys.exit(0 if ok else 1)
