"""The Python package against the CLI: same report, the library's errors, the GIL released."""

import json
import subprocess
import threading
import time

import pytest

import imucald
from conftest import ROOT, cli_report, simulate


def test_version_is_the_cli_version(binary):
    out = subprocess.run([binary, "--version"], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["imucald", imucald.__version__]


@pytest.mark.parametrize("seed", [1, 7])
def test_replay_is_the_cli_report(tmp_path, seed):
    log = simulate(str(tmp_path / f"tumble{seed}.tlog"), seed)
    cli = json.loads(cli_report(log, str(tmp_path / "r.json")))
    got = imucald.replay(log)
    assert got == cli
    # Not two empty or failed reports: a fitted magnetometer, as the tumble makes.
    assert got["calibration"]["mag"]["status"] == "ok"
    assert got["input"]["path"] == log


def test_replay_with_a_config_is_the_cli_report(tmp_path):
    log = simulate(str(tmp_path / "tumble.csv"), 3)
    config = str(ROOT / "config" / "replay.toml")
    cli = json.loads(cli_report(log, str(tmp_path / "r.json"), config))
    assert imucald.replay(log, config=config) == cli
    assert imucald.replay(log, config) == cli


def test_path_like_is_a_path(tmp_path):
    log = tmp_path / "tumble.tlog"
    simulate(str(log), 2)
    assert imucald.replay(log) == imucald.replay(str(log))


def cli_error(binary, *args):
    """The CLI's stderr for a replay that fails."""
    out = subprocess.run([binary, "replay", *args], capture_output=True, text=True)
    assert out.returncode != 0
    return out.stderr


def test_missing_file_raises_the_library_message(binary, tmp_path):
    log = str(tmp_path / "absent.tlog")
    with pytest.raises(imucald.Error) as e:
        imucald.replay(log)
    assert str(e.value).startswith(f"cannot read {log}: ")
    assert str(e.value) in cli_error(binary, log)


def test_unreadable_log_raises_the_library_message(binary, tmp_path):
    log = tmp_path / "noise.tlog"
    log.write_bytes(bytes(range(256)) * 20)
    with pytest.raises(imucald.Error, match="cannot tell the format") as e:
        imucald.replay(str(log))
    assert str(e.value) in cli_error(binary, str(log))


def test_bad_config_raises_the_library_message(binary, tmp_path):
    log = simulate(str(tmp_path / "tumble.tlog"), 1)
    config = tmp_path / "bad.toml"
    config.write_text("[gate]\nwindow_seconds = 1.0\n")
    with pytest.raises(imucald.Error, match="window_seconds") as e:
        imucald.replay(log, config=str(config))
    assert str(e.value) in cli_error(binary, log, "--config", str(config))


def test_wrong_argument_type_is_a_type_error():
    with pytest.raises(TypeError):
        imucald.replay(12)


def test_the_gil_is_released_while_replaying(tmp_path):
    # A Python thread ticks every millisecond. Were the GIL held through a replay, the thread could
    # not run until it returned, and would tick at most once or twice per replay. Replays are run
    # back to back for at least 0.5 s, however fast one is on this machine.
    log = simulate(str(tmp_path / "flight.tlog"), 1, scenario="flight")
    ticks = 0
    stop = threading.Event()

    def ticker():
        nonlocal ticks
        while not stop.is_set():
            time.sleep(0.001)
            ticks += 1

    t = threading.Thread(target=ticker)
    t.start()
    try:
        time.sleep(0.05)
        before, start, replays = ticks, time.monotonic(), 0
        while time.monotonic() - start < 0.5:
            imucald.replay(log)
            replays += 1
        during, elapsed = ticks - before, time.monotonic() - start
    finally:
        stop.set()
        t.join()
    # Measured: 523-605 ticks in 0.62-0.73 s of replay (830-880 per second, on two busy cores);
    # held, the GIL allows one or two per replay. The bounds are a third of the measured rate and
    # three times what a held GIL would allow.
    assert during >= 250 * elapsed, f"{during} ticks in {elapsed:.2f} s of replay: the GIL was held"
    assert during > 6 * replays, f"{during} ticks over {replays} replays: the GIL was held"
