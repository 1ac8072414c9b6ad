"""Shared fixtures: the imucald binary and simulated logs made with it."""

import os
import pathlib
import subprocess

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]


def imucald_binary():
    """The CLI the package is compared with: $IMUCALD_BIN, else the checkout's release build."""
    path = pathlib.Path(os.environ.get("IMUCALD_BIN", ROOT / "target" / "release" / "imucald"))
    if not path.is_file():
        pytest.fail(f"{path} is missing: run `cargo build --release` (or set IMUCALD_BIN)")
    return path


def simulate(out, seed, scenario="tumble"):
    """A simulated log at `out` (the format follows its extension)."""
    subprocess.run(
        [imucald_binary(), "simulate", "--scenario", scenario, "--seed", str(seed), "--out", out],
        check=True,
        capture_output=True,
    )
    return out


def cli_report(log, out, config=None):
    """The report `imucald replay LOG --report OUT` writes, as text. The exit status is not
    checked: a replay that calibrated nothing still writes its report."""
    cmd = [imucald_binary(), "replay", log, "--report", out]
    if config:
        cmd += ["--config", config]
    subprocess.run(cmd, capture_output=True)
    return pathlib.Path(out).read_text()


@pytest.fixture(scope="session")
def binary():
    return imucald_binary()
