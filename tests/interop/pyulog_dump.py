#!/usr/bin/env python3
"""Print what pyulog reads from a ULog file, as JSON on stdout, for the reader's parity test:

    pyulog_dump.py FILE.ulg

{"datasets": [{"name", "multi_id", "count", "fields": {field: [values]}}], "params": {name: value},
 "dropouts": n}. Every data set is counted; the values are given for the topics imucald uses
(sensor_mag, sensor_accel, sensor_gyro, sensor_combined, vehicle_magnetometer, vehicle_attitude),
every field of them; numbers as text (Python's repr of the double: exact for float32 and for
integers below 2^53).
"""
import json
import sys

from pyulog import ULog

USED = {"sensor_mag", "sensor_accel", "sensor_gyro", "sensor_combined",
        "vehicle_magnetometer", "vehicle_attitude"}


def num(x):
    """A number as the shortest text that reads back to the same double ("nan" for NaN): text, so
    that no JSON float parsing stands between pyulog's values and the comparison."""
    return repr(float(x))


def main():
    u = ULog(sys.argv[1])
    out = {"datasets": [], "params": {k: num(v) for k, v in u.initial_parameters.items()},
           "dropouts": len(u.dropouts)}
    for d in u.data_list:
        entry = {"name": d.name, "multi_id": d.multi_id, "count": len(d.data["timestamp"])}
        if d.name in USED:
            entry["fields"] = {k: [num(x) for x in v] for k, v in d.data.items()}
        out["datasets"].append(entry)
    json.dump(out, sys.stdout)


if __name__ == "__main__":
    main()
