"""examples_py/dask_fleet.py on a LocalCluster of two worker processes against the CLI."""

import importlib.util
import json
import subprocess
import sys

import pyarrow.parquet as pq

from conftest import ROOT, cli_report, simulate

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
    failed = by_log[str(bad)]
    assert failed["status"] == "error"
    assert failed["failure"].startswith(f"{bad}: ")
    assert failed["instance"] is None and failed["offset_x"] is None


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
