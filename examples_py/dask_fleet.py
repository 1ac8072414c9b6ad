"""Replay a fleet's logs with imucald on Dask distributed and write one Parquet table.

Every log under LOG_DIR (.tlog, .csv, .csv.gz, .bin, .ulg; searched recursively) is replayed by
``imucald.replay`` on a Dask worker. The table has one row per log and compass: the log, the
compass instance, whether it is the log's primary one, the fit's status ("ok", "failed", or
"error" when the log could not be replayed at all), its failure and detail, the method (sphere,
vector, planar), the model, the offset's three components and the 3x3 matrix (row-major, 9
values; calibrated = matrix * (raw - offset)), the mounting verdict, the held-out verdict as a
word (better, keep_vehicle, no_onboard, failed), whether the calibration is one to load and why
(a word), the rung of the model ladder taken, the field's radius and the RMS residual in uT, the
direction regions filled (the primary's), and the held-out spreads of the field's norm (%) and
dip (deg) through imucald's calibration and through the vehicle's. A row whose status is not
"ok" carries no numbers, only its words. A log that cannot be read becomes one row with status
"error" and the library's message as its failure: the batch goes on. The columns are those of
`imucald replay DIR --table` (docs/replay.md), the matrix there spread over nine columns.

    pip install . dask[distributed] pyarrow        # at the repository's root
    python examples_py/dask_fleet.py LOG_DIR --out fleet.parquet               # LocalCluster
    python examples_py/dask_fleet.py LOG_DIR --out fleet.parquet --workers 4
    python examples_py/dask_fleet.py LOG_DIR --out fleet.parquet --scheduler tcp://HOST:8786

Without --scheduler a LocalCluster of --workers processes (one thread each) runs on this machine;
with it, the running cluster at that address does the work: its workers need the imucald package
installed and the logs at the same paths (a shared file system). Progress goes to stderr; the
table is written to a temporary file beside --out and renamed into place when complete.
"""

import argparse
import os
import sys
import time

import imucald

# The log formats imucald's replay reads, by file name ending.
LOG_SUFFIXES = (".tlog", ".csv", ".csv.gz", ".bin", ".ulg")

# Seconds between two progress lines at most.
PROGRESS_EVERY_S = 2.0

# Most logs a Dask task replays (see default_batch).
MAX_BATCH = 32


def table_schema():
    """The Parquet table's columns (pyarrow is imported here so workers never need it)."""
    import pyarrow as pa

    return pa.schema(
        [
            ("log", pa.string()),
            ("instance", pa.string()),
            ("primary", pa.bool_()),
            ("status", pa.string()),
            ("failure", pa.string()),
            ("detail", pa.string()),
            ("method", pa.string()),
            ("model", pa.string()),
            ("units", pa.string()),
            ("offset_x", pa.float64()),
            ("offset_y", pa.float64()),
            ("offset_z", pa.float64()),
            ("matrix", pa.list_(pa.float64(), 9)),
            ("mounting_verdict", pa.string()),
            ("verdict", pa.string()),
            ("load", pa.bool_()),
            ("load_reason", pa.string()),
            ("rung", pa.string()),
            ("radius_ut", pa.float64()),
            ("rms_ut", pa.float64()),
            ("coverage_regions", pa.int64()),
            ("heldout_norm_pct", pa.float64()),
            ("heldout_dip_deg", pa.float64()),
            ("vehicle_norm_pct", pa.float64()),
            ("vehicle_dip_deg", pa.float64()),
        ]
    )


def find_logs(root):
    """Every log file under `root`, sorted, as paths (absolute when `root` is: the workers may
    run elsewhere than here)."""
    found = []
    for d, _, names in os.walk(root):
        found.extend(os.path.join(d, n) for n in names if n.lower().endswith(LOG_SUFFIXES))
    return sorted(found)


# The name a log of one unnamed stream (a CSV) is judged and decided under in the report's
# `quality` and `load`.
UNNAMED_INSTANCE = "primary"

# The columns that hold numbers: empty in a row whose status is not "ok".
NUMBER_COLUMNS = (
    "offset_x",
    "offset_y",
    "offset_z",
    "matrix",
    "radius_ut",
    "rms_ut",
    "coverage_regions",
    "heldout_norm_pct",
    "heldout_dip_deg",
    "vehicle_norm_pct",
    "vehicle_dip_deg",
)


def compass_row(log, instance, primary, mag, quality, load, coverage):
    """One compass's row from its `calibration.mag`, its held-out `quality` entry and its `load`
    decision (each None when the report has none), and `coverage`, the report's magnetometer
    coverage when the compass is the primary (else None)."""
    offset = mag.get("offset") or [None, None, None]
    matrix = mag.get("matrix")
    quality = quality or {}
    load = load or {}
    ours = quality.get("imucald") or {}
    theirs = quality.get("onboard") or {}
    in_ut = mag.get("units") == "uT"
    row = {
        "log": log,
        "instance": instance,
        "primary": primary,
        "status": mag.get("status"),
        "failure": mag.get("failure"),
        "detail": mag.get("detail"),
        "method": mag.get("method"),
        "model": mag.get("model"),
        "units": mag.get("units"),
        "offset_x": offset[0],
        "offset_y": offset[1],
        "offset_z": offset[2],
        "matrix": [v for r in matrix for v in r] if matrix else None,
        "mounting_verdict": (mag.get("mounting") or {}).get("verdict"),
        "verdict": quality.get("verdict_kind"),
        "load": load.get("load"),
        "load_reason": load.get("reason"),
        "rung": quality.get("rung") or mag.get("rung"),
        "radius_ut": mag.get("radius") if in_ut else None,
        "rms_ut": mag.get("rms_residual") if in_ut else None,
        "coverage_regions": (coverage or {}).get("filled"),
        "heldout_norm_pct": ours.get("norm_spread_pct"),
        "heldout_dip_deg": ours.get("dip_spread_deg"),
        "vehicle_norm_pct": theirs.get("norm_spread_pct"),
        "vehicle_dip_deg": theirs.get("dip_spread_deg"),
    }
    if row["status"] != "ok":
        row.update(dict.fromkeys(NUMBER_COLUMNS))
    return row


def compass_rows(log, report):
    """The rows of one replay report: each instance of a multi-instance log (the primary first,
    as the report lists them), else the log's one compass. Each compass's `quality` and `load`
    entries are those of its instance (a log of one unnamed stream's: those named
    UNNAMED_INSTANCE)."""
    quality = {q["instance"]: q for q in report.get("quality", [])}
    load = {d["instance"]: d for d in report.get("load", [])}
    coverage = (report.get("coverage") or {}).get("mag")
    instances = report.get("instances") or [
        {
            "instance": report["input"].get("instance"),
            "primary": True,
            "calibration": report["calibration"],
        }
    ]
    rows = []
    for i in instances:
        name = i["instance"] if i["instance"] is not None else UNNAMED_INSTANCE
        rows.append(
            compass_row(
                log,
                i["instance"],
                i["primary"],
                i["calibration"]["mag"],
                quality.get(name),
                load.get(name),
                coverage if i["primary"] else None,
            )
        )
    return rows


def error_row(log, message):
    """The one row of a log that could not be replayed."""
    row = compass_row(log, None, None, {}, None, None, None)
    row.update(status="error", failure=message)
    return row


def replay_rows(log, config=None):
    """On a worker: the rows of one log; a log imucald cannot use gives its error row, and so
    does a panic in the library (PyO3 raises it as PanicException, a BaseException), so that it
    costs its own log only, not the task's other logs."""
    try:
        return compass_rows(log, imucald.replay(log, config))
    except imucald.Error as e:
        return [error_row(log, str(e))]
    except (KeyboardInterrupt, SystemExit):
        raise
    except BaseException as e:  # noqa: BLE001 - see the docstring
        return [error_row(log, f"{type(e).__name__}: {e}")]


class Progress:
    """Lines on stderr: logs done of the total, those not replayed, the rate; at most every
    PROGRESS_EVERY_S seconds."""

    def __init__(self, total):
        self.total = total
        self.done = 0
        self.errors = 0
        self.start = time.monotonic()
        self.last = self.start

    def add(self, rows):
        self.done += 1
        self.errors += any(r["status"] == "error" for r in rows)
        now = time.monotonic()
        if now - self.last >= PROGRESS_EVERY_S or self.done == self.total:
            self.last = now
            rate = self.done / max(now - self.start, 1e-9)
            print(
                f"{self.done}/{self.total} logs, {self.errors} not replayed, {rate:.1f} logs/s",
                file=sys.stderr,
                flush=True,
            )


def replay_batch(logs, config=None):
    """On a worker: the rows of each log of a batch, a list per log."""
    return [replay_rows(log, config) for log in logs]


def default_batch(n_logs, n_threads):
    """Logs per task: up to MAX_BATCH, so that Dask's own cost per task (a few ms of the
    scheduler's and the worker's) is small beside the replays (tens of ms for a short log), and
    few enough that each worker thread gets about four tasks to even out the load."""
    return max(1, min(MAX_BATCH, n_logs // (4 * max(n_threads, 1))))


def replay_all(client, logs, config=None, batch=1):
    """Every log's rows, replayed on `client`'s cluster `batch` logs a task; in the order of `logs`.

    A task that dies (a worker lost, a panic) gives each of its logs an error row, like an
    unreadable log."""
    from distributed import as_completed

    starts = range(0, len(logs), batch)
    futures = client.map(replay_batch, [logs[i : i + batch] for i in starts], config=config, pure=False)
    start_of = {f.key: i for i, f in zip(starts, futures)}
    rows = [None] * len(logs)
    progress = Progress(len(logs))
    for future in as_completed(futures):
        i = start_of[future.key]
        part = logs[i : i + batch]
        try:
            got = future.result()
        except Exception as e:  # noqa: BLE001 - any task failure is its logs' rows
            got = [[error_row(log, f"task failed: {e!r}")] for log in part]
        rows[i : i + len(part)] = got
        for log_rows in got:
            progress.add(log_rows)
        future.release()
    return [r for log_rows in rows for r in log_rows]


def write_parquet(rows, out):
    """The rows as a Parquet table at `out`, through a temporary file renamed into place."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pa.Table.from_pylist(rows, schema=table_schema())
    tmp = f"{out}.{os.getpid()}.tmp"
    try:
        pq.write_table(table, tmp)
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return table


def connect(args):
    """A client of the cluster at --scheduler, or of a new LocalCluster of --workers processes."""
    from distributed import Client, LocalCluster

    if args.scheduler:
        return Client(args.scheduler)
    cluster = LocalCluster(
        n_workers=args.workers,
        threads_per_worker=1,
        processes=True,
        dashboard_address=None,
    )
    return Client(cluster)


def parse_args(argv):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("log_dir", help="directory searched recursively for logs")
    p.add_argument("--out", required=True, help="the Parquet table to write")
    p.add_argument("--config", help="imucald TOML configuration for every replay (default: none)")
    p.add_argument(
        "--workers",
        type=int,
        default=os.cpu_count() or 1,
        help="worker processes of the LocalCluster (default: the cores)",
    )
    p.add_argument("--scheduler", help="address of a running Dask scheduler instead of a LocalCluster")
    p.add_argument(
        "--batch",
        type=int,
        help=f"logs per Dask task (default: a quarter of the logs per worker thread, 1 to {MAX_BATCH})",
    )
    return p.parse_args(argv)


def main(argv=None):
    args = parse_args(argv)
    if args.batch is not None and args.batch < 1:
        print(f"--batch must be at least 1, not {args.batch}", file=sys.stderr)
        return 2
    logs = find_logs(os.path.abspath(args.log_dir))
    if not logs:
        print(f"no logs ({', '.join(LOG_SUFFIXES)}) under {args.log_dir}", file=sys.stderr)
        return 2
    config = os.path.abspath(args.config) if args.config else None
    with connect(args) as client:
        workers = len(client.scheduler_info().get("workers", {}))
        batch = args.batch or default_batch(len(logs), sum(client.nthreads().values()))
        start = time.monotonic()
        rows = replay_all(client, logs, config, batch)
        elapsed = time.monotonic() - start
    table = write_parquet(rows, args.out)
    errors = sum(r["status"] == "error" for r in rows)
    print(
        f"wrote {args.out}: {table.num_rows} rows from {len(logs)} logs ({errors} not replayed) "
        f"in {elapsed:.1f} s on {workers} workers, {batch} a task: {len(logs) / elapsed:.1f} logs/s"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
