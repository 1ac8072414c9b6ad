"""Interop peer written against pymavlink (not by imucald): streams a simulated tumble as HIGHRES_IMU
over UDP to `imucald run` and checks what comes back.

usage: pymavlink_peer.py PORT SAMPLES.csv TRUTH.json SPEED [gcs CAL_DIR]
Prints one JSON line with what it saw; exit 0 when every check holds, 1 otherwise.

Mode `gcs` (the service runs with daemon.mag_cal = "on_command", its calibration in CAL_DIR): the peer
is also the ground station (system 255, component 190), driving the calibration as Mission Planner or
MAVProxy do. Pass 1: DO_START_MAG_CAL (autosave 0) to the service's ids -> COMMAND_ACK accepted ->
MAG_CAL_PROGRESS -> MAG_CAL_REPORT success with autosaved 0 -> no magnetometer calibration on disk yet ->
DO_ACCEPT_MAG_CAL (broadcast) -> ACK accepted -> the calibration on disk, with the reported offsets.
Pass 2: DO_START_MAG_CAL (broadcast) -> ACK -> report -> DO_CANCEL_MAG_CAL -> ACK -> the magnetometer
calibration on disk unchanged.
Also: the service's HEARTBEAT (onboard controller, ids 1/191), no progress before the first start.
Checks: MAG_CAL_PROGRESS reaches 100; a MAG_CAL_REPORT with MAG_CAL_SUCCESS whose offsets (ArduPilot
COMPASS_OFS convention, mGauss, ofs = -hard_iron) match the truth within 1 mGauss; NAMED_VALUE_FLOAT
HEADING within 1 deg of the true heading on static poses of the second pass (the tumble is streamed
twice: the first pass calibrates).
"""
import csv
import json
import math
import os
import sys
import time

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402

port, samples_path, truth_path, speed = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4])
gcs_mode = len(sys.argv) > 6 and sys.argv[5] == "gcs"
truth = json.load(open(truth_path))
rows = list(csv.DictReader(open(samples_path)))
poses = truth["poses"]
decl = math.degrees(math.atan2(truth["world"]["field_ned_ut"][1], truth["world"]["field_ned_ut"][0]))

m = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1, dialect="ardupilotmega")
seen = {"progress_max": 0, "reports": [], "heading_checked": 0, "heading_err_max": 0.0, "heading_err_max_first_pass": 0.0, "sent": 0}
current_pass = [0]
report_ok = None


def pose_at(t):
    for p in poses:
        # Heading is undefined at pitch +-90 deg (roll and yaw become one axis): judge it away from there.
        if p["t_start"] + 1.0 <= t <= p["t_end"] - 0.3 and abs(p["pitch_deg"]) < 70.0:
            return p
    return None


def drain(t_now):
    global report_ok
    while True:
        msg = m.recv_match(blocking=False)
        if msg is None:
            return
        typ = msg.get_type()
        if typ == "MAG_CAL_PROGRESS":
            seen["progress_max"] = max(seen["progress_max"], msg.completion_pct)
        elif typ == "MAG_CAL_REPORT":
            seen["reports"].append({"status": msg.cal_status, "ofs": [msg.ofs_x, msg.ofs_y, msg.ofs_z], "fitness": msg.fitness})
            if msg.cal_status == mavutil.mavlink.MAG_CAL_SUCCESS:
                report_ok = msg
        elif typ == "NAMED_VALUE_FLOAT" and msg.name == "HEADING" and report_ok is not None:
            p = pose_at(t_now)
            if p is not None:
                err = (msg.value - (p["yaw_deg"] - decl) + 180.0) % 360.0 - 180.0
                if current_pass[0] == 0:
                    # Still calibrating: recorded for the log, not judged.
                    seen["heading_err_max_first_pass"] = max(seen["heading_err_max_first_pass"], abs(err))
                else:
                    seen["heading_checked"] += 1
                    seen["heading_err_max"] = max(seen["heading_err_max"], abs(err))


def stream(passes, on_message, on_pass):
    """Stream the samples `passes` times at `speed`, handing every received message to on_message."""
    t0 = time.monotonic()
    duration = float(rows[-1]["t"]) + 0.01
    for k in range(passes):
        on_pass(k)
        for i, r in enumerate(rows):
            t = float(r["t"]) + k * duration
            now = time.monotonic() - t0
            if t / speed > now:
                time.sleep(t / speed - now)
            g = lambda c: float(r[c])
            m.mav.highres_imu_send(
                int(1e7 + t * 1e6), g("ax"), g("ay"), g("az"), g("gx"), g("gy"), g("gz"),
                g("mx") / 100.0, g("my") / 100.0, g("mz") / 100.0, 0.0, 0.0, 0.0, g("temp"), 0x1FF, 0)
            if i % 100 == 0:
                m.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_QUADROTOR, mavutil.mavlink.MAV_AUTOPILOT_PX4, 0, 0, 0)
            while True:
                msg = m.recv_match(blocking=False)
                if msg is None:
                    break
                on_message(msg)


def gcs():
    cal_dir = sys.argv[6]
    store = os.path.join(cal_dir, "calibration.json")
    g = {"acks": [], "progress_before_start": 0, "progress_in_run": [0, 0], "reports": [], "heartbeats": 0,
         "heartbeat_ok": True, "mag_on_disk_before_accept": None, "mag_on_disk_after_accept": None,
         "file_changed_by_cancel": None}
    run = [-1]  # the run the peer started (0, 1), -1 before the first
    pending = []  # actions to take outside the message handler

    def command(cmd, target_sys, target_comp, p1=0, p2=0, p3=0, p4=0, p5=0):
        m.mav.srcSystem, m.mav.srcComponent = 255, 190
        m.mav.command_long_send(target_sys, target_comp, cmd, 0, p1, p2, p3, p4, p5, 0, 0)
        m.mav.srcSystem, m.mav.srcComponent = 1, 1

    def mag_on_disk():
        try:
            return json.load(open(store)).get("mag")
        except (OSError, ValueError):
            return None

    def on_message(msg):
        typ = msg.get_type()
        if typ == "HEARTBEAT":
            g["heartbeats"] += 1
            g["heartbeat_ok"] &= (msg.get_srcSystem(), msg.get_srcComponent()) == (1, 191) and \
                msg.type == mavutil.mavlink.MAV_TYPE_ONBOARD_CONTROLLER and \
                msg.autopilot == mavutil.mavlink.MAV_AUTOPILOT_INVALID
        elif typ == "COMMAND_ACK":
            g["acks"].append([msg.command, msg.result, msg.target_system, msg.target_component])
        elif typ == "MAG_CAL_PROGRESS":
            if run[0] < 0:
                g["progress_before_start"] += 1
            else:
                g["progress_in_run"][run[0]] = max(g["progress_in_run"][run[0]], msg.completion_pct)
        elif typ == "MAG_CAL_REPORT":
            g["reports"].append({"run": run[0], "status": msg.cal_status, "autosaved": msg.autosaved,
                                 "ofs": [msg.ofs_x, msg.ofs_y, msg.ofs_z]})
            if msg.cal_status == mavutil.mavlink.MAG_CAL_SUCCESS and run[0] == 0 and not g.get("accept_sent"):
                g["accept_sent"] = True
                pending.append("accept")
            elif msg.cal_status == mavutil.mavlink.MAG_CAL_SUCCESS and run[0] == 1:
                pending.append("cancel")

    def on_pass(k):
        if k == 0:
            command(42424, 1, 191, p1=0, p2=0, p3=0)  # start, to our ids, autosave 0
        else:
            # As a ground station does, the next run is started only once the last one reported
            # (a busy machine may finish the fit after the data ended): 5 s at the most.
            deadline = time.monotonic() + 5.0
            while time.monotonic() < deadline and not any(r["run"] == 0 for r in g["reports"]):
                msg = m.recv_match(blocking=False)
                if msg is None:
                    time.sleep(0.01)
                else:
                    handle(msg)
            command(42424, 0, 0, p1=0, p2=0, p3=0)  # start, broadcast
        run[0] = k

    def handle(msg):
        on_message(msg)
        while pending:
            what = pending.pop(0)
            if what == "accept":
                time.sleep(0.3)  # anything the service would (wrongly) write has time to land
                g["mag_on_disk_before_accept"] = mag_on_disk()
                command(42425, 0, 0)
                deadline = time.monotonic() + 3.0
                while time.monotonic() < deadline and mag_on_disk() is None:
                    time.sleep(0.02)
                g["mag_on_disk_after_accept"] = mag_on_disk()
            elif what == "cancel":
                # (The accelerometer is not under the ground station's control: its part of the
                # file may change; the magnetometer's must not.)
                before = mag_on_disk()
                command(42426, 0, 0)
                time.sleep(1.0)
                g["file_changed_by_cancel"] = before != mag_on_disk()

    stream(2, handle, on_pass)
    end = time.monotonic() + 2.0
    while time.monotonic() < end:
        msg = m.recv_match(blocking=False)
        if msg is None:
            time.sleep(0.01)
        else:
            handle(msg)
    ok_acks = [a[0] for a in g["acks"] if a[1] == mavutil.mavlink.MAV_RESULT_ACCEPTED and a[2:] == [255, 190]]
    success = [r for r in g["reports"] if r["status"] == mavutil.mavlink.MAG_CAL_SUCCESS]
    hard_iron = truth["mag"]["offset"]
    first = success[0] if success else None
    disk = g["mag_on_disk_after_accept"]
    checks = {
        "acks": ok_acks == [42424, 42425, 42424, 42426],
        "heartbeats": g["heartbeats"] >= 5 and g["heartbeat_ok"],
        "no_progress_before_start": g["progress_before_start"] == 0,
        # A commanded run ends on a passing fit once the data covered the sphere.
        "progress_in_runs": g["progress_in_run"][0] >= 100 and g["progress_in_run"][1] >= 100,
        "report_held": first is not None and first["run"] == 0 and first["autosaved"] == 0,
        "nothing_on_disk_before_accept": g["mag_on_disk_before_accept"] is None,
        # The file holds what was reported (uT there, mGauss added in the report).
        "written_on_accept": disk is not None and disk["status"] == "ok" and first is not None
        and max(abs(-o * 10.0 - got) for o, got in zip(disk["offset"], first["ofs"])) < 0.01,
        "second_run_reported": any(r["run"] == 1 for r in success),
        "cancel_kept_the_file": g["file_changed_by_cancel"] is False,
    }
    if first is not None:
        g["offset_err_mgauss"] = max(abs(-o * 10.0 - got) for o, got in zip(hard_iron, first["ofs"]))
        g["truth_ofs"] = [-o * 10.0 for o in hard_iron]
    g["failed_checks"] = [k for k, v in checks.items() if not v]
    ok = not g["failed_checks"]
    g["ok"] = bool(ok)
    print(json.dumps(g))
    sys.exit(0 if ok else 1)


if gcs_mode:
    gcs()

t_wall0 = time.monotonic()
duration = float(rows[-1]["t"]) + 0.01
passes = 2  # the second pass sees the calibration accepted during the first
for k in range(passes):
    current_pass[0] = k
    m.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_QUADROTOR, mavutil.mavlink.MAV_AUTOPILOT_PX4, 0, 0, 0)
    for i, r in enumerate(rows):
        t = float(r["t"]) + k * duration
        target = t / speed
        now = time.monotonic() - t_wall0
        if target > now:
            time.sleep(target - now)
        g = lambda c: float(r[c])
        m.mav.highres_imu_send(
            int(1e7 + t * 1e6), g("ax"), g("ay"), g("az"), g("gx"), g("gy"), g("gz"),
            g("mx") / 100.0, g("my") / 100.0, g("mz") / 100.0, 0.0, 0.0, 0.0, g("temp"), 0x1FF, 0)
        seen["sent"] += 1
        if i % 100 == 0:
            m.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_QUADROTOR, mavutil.mavlink.MAV_AUTOPILOT_PX4, 0, 0, 0)
        drain(float(r["t"]))
end = time.monotonic() + 3.0
while time.monotonic() < end:
    drain(-1.0)
    time.sleep(0.01)

hard_iron = truth["mag"]["offset"]
ok = seen["progress_max"] >= 100 and report_ok is not None
if report_ok is not None:
    ofs_err = max(abs(-o * 10.0 - got) for o, got in zip(hard_iron, [report_ok.ofs_x, report_ok.ofs_y, report_ok.ofs_z]))
    seen["offset_err_mgauss"] = ofs_err
    ok = ok and ofs_err < 1.0
ok = ok and seen["heading_checked"] >= 20 and seen["heading_err_max"] < 1.0
seen["ok"] = ok
print(json.dumps(seen))
sys.exit(0 if ok else 1)
