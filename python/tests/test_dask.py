"""examples_py/dask_fleet.py on a LocalCluster of two worker processes against the CLI."""

import csv
import importlib.util
import json
import subprocess
import sys

import pyarrow.parquet as pq

from conftest import ROOT, cli_report, imucald_binary, simulate

EXAMPLE = ROOT / "examples_py" / "dask_fleet.py"


def load_example():
    spec = importlib.util.spec_from_file_location("dask_fleet", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_fleet_table_is_the_cli_result(tmp_path):
    logs_dir = tmp_path / "logs"
    (logs_dir / "b").mkdir(parents=True)
    logs = [simulate(str(logs_dir / f"tumble{s}.tlog"), s) for s in range(1, 6)]
    logs += [simulate(str(logs_dir / "b" / f"tumble{s}.csv"), s) for s in range(6, 9)]
    bad = logs_dir / "b" / "truncated.tlog"
    bad.write_bytes(b"\x00" * 100)
    (logs_dir / "notes.txt").write_text("not a log")
    out = tmp_path / "fleet.parquet"
    run = subprocess.run(
        [sys.executable, EXAMPLE, logs_dir, "--out", out, "--workers", "2"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr
    assert "9/9 logs, 1 not replayed" in run.stderr
    assert "on 2 workers" in run.stdout
    rows = pq.read_table(out).to_pylist()
    by_log = {r["log"]: r for r in rows}
    assert len(rows) == len(by_log) == 9
    for log in logs:
        cli = json.loads(cli_report(log, str(tmp_path / "r.json")))
        mag = cli["calibration"]["mag"]
        row = by_log[log]
        assert row["instance"] == cli["input"]["instance"]
        assert row["primary"] is True
        assert row["status"] == mag["status"] == "ok"
        assert row["failure"] is None and row["detail"] is None
        assert row["method"] == mag["method"]
        assert row["model"] == mag["model"]
        assert row["units"] == mag["units"]
        assert [row["offset_x"], row["offset_y"], row["offset_z"]] == mag["offset"]
        assert row["matrix"] == [v for r in mag["matrix"] for v in r]
        assert row["mounting_verdict"] == mag["mounting"]["verdict"]
        # A log of one stream: its held-out entry and load decision are its instance's, or
        # "primary"'s when the stream has no name (a CSV).
        name = cli["input"]["instance"] or "primary"
        quality = next((q for q in cli.get("quality", []) if q["instance"] == name), {})
        load = next(d for d in cli["load"] if d["instance"] == name)
        assert row["verdict"] == quality.get("verdict_kind")
        assert row["load"] is load["load"] and row["load_reason"] == load["reason"]
        assert row["rung"] == (quality.get("rung") or mag.get("rung"))
        assert row["radius_ut"] == mag["radius"] and row["rms_ut"] == mag["rms_residual"]
        assert row["coverage_regions"] == cli["coverage"]["mag"]["filled"]
        assert row["heldout_norm_pct"] == (quality.get("imucald") or {}).get("norm_spread_pct")
        assert row["vehicle_dip_deg"] == (quality.get("onboard") or {}).get("dip_spread_deg")
    failed = by_log[str(bad)]
    assert failed["status"] == "error"
    assert failed["failure"].startswith(f"{bad}: ")
    assert failed["instance"] is None and failed["offset_x"] is None
    assert failed["load"] is None and failed["radius_ut"] is None

    # The CLI's batch table over the same directory: the same rows, column for column, the
    # Parquet matrix spread over matrix_RC.
    table = tmp_path / "fleet.csv"
    subprocess.run(
        [imucald_binary(), "replay", logs_dir, "--table", table], capture_output=True, timeout=600
    )
    with open(table, newline="") as f:
        cli_rows = list(csv.DictReader(f))
    assert len(cli_rows) == len(rows)
    for cli_row in cli_rows:
        row = by_log[cli_row["log"]]
        assert set(cli_row) == (set(row) - {"matrix"}) | {f"matrix_{i // 3}{i % 3}" for i in range(9)}
        for col, cell in cli_row.items():
            if col.startswith("matrix_"):
                r, c = int(col[-2]), int(col[-1])
                value = row["matrix"][3 * r + c] if row["matrix"] else None
            else:
                value = row[col]
            assert same_cell(cell, value), (cli_row["log"], col, cell, value)


def same_cell(cell, value):
    """Whether the CLI's table cell holds `value`: empty for none, true/false, text as is, a
    number the same float (both sides read the same report's numbers)."""
    if value is None:
        return cell == ""
    if isinstance(value, bool):
        return cell == ("true" if value else "false")
    if isinstance(value, (int, float)):
        return cell != "" and float(cell) == value
    return cell == value


def test_a_failed_compass_has_words_and_no_numbers_and_its_verdict_is_a_word():
    fleet = load_example()
    failed_mag = {
        "status": "failed",
        "failure": "coverage",
        "detail": "4 of 100 sphere regions filled",
        "method": "vector",
        "model": "sym9",
        "units": "uT",
        "offset": [0.0, 0.0, 0.0],
        "matrix": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        "radius": 0.0,
        "rms_residual": 0.0,
    }
    quality = {
        "instance": "IMU+MAG",
        "verdict": "imucald's held-out fit failed ...",
        "verdict_kind": "keep_vehicle",
        "imucald": {"norm_spread_pct": 0.3, "dip_spread_deg": 0.5},
        "onboard": {"norm_spread_pct": 0.4, "dip_spread_deg": 0.6},
    }
    report = {
        "input": {"instance": "IMU+MAG"},
        "coverage": {"mag": {"regions": 100, "filled": 4}},
        "calibration": {"mag": failed_mag},
        "quality": [quality],
        "load": [{"instance": "IMU+MAG", "compass_id": 0, "load": False, "reason": "fit_failed"}],
    }
    (row,) = fleet.compass_rows("f.bin", report)
    assert row["status"] == "failed" and row["failure"] == "coverage"
    assert row["detail"] == "4 of 100 sphere regions filled"
    assert row["verdict"] == "keep_vehicle"
    assert row["load"] is False and row["load_reason"] == "fit_failed"
    for col in fleet.NUMBER_COLUMNS:
        assert row[col] is None, col


class PanicException(BaseException):
    """Like PyO3's exception for a panic: a BaseException, not an Exception."""


def test_a_panic_costs_its_own_log_only(tmp_path, monkeypatch):
    fleet = load_example()
    good = simulate(str(tmp_path / "good.tlog"), 1)
    real_replay = fleet.imucald.replay

    def replay(log, config=None):
        if log.endswith("bad.tlog"):
            raise PanicException("index out of bounds")
        return real_replay(log, config)

    monkeypatch.setattr(fleet.imucald, "replay", replay)
    rows = fleet.replay_batch([str(tmp_path / "bad.tlog"), good])
    assert rows[0] == [fleet.error_row(str(tmp_path / "bad.tlog"), "PanicException: index out of bounds")]
    assert rows[1][0]["status"] == "ok" and rows[1][0]["log"] == good
