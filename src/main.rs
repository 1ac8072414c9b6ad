//! The `imucald` binary: a thin edge over the library (anyhow lives only here).

use anyhow::{Context, Result};
use clap::{Args, Parser, Subcommand, ValueEnum};
use imucald::attitude::eval::Alignment;
use imucald::config::Config;
use imucald::io::decode::Format;
use std::path::PathBuf;

#[derive(Parser)]
#[command(
    name = "imucald",
    version,
    about = "Calibrate accelerometer, magnetometer and gyroscope; publish heading"
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Run a captured log (MAVLink .tlog, ArduPilot DataFlash .bin, PX4 .ulg, CSV or .csv.gz)
    /// through the calibration pipeline.
    Replay(ReplayArgs),
    /// Run the live service: read IMU data from links, calibrate online, publish heading and calibrations.
    /// With no config: the embedded default, a simulated IMU tumbling with pauses.
    Run(RunArgs),
    /// Find where the fitted model and the measured data disagree: name the missing effect (from a
    /// catalogue), add it to the model and show how far the residual shrinks on held-out poses.
    Diagnose(DiagnoseArgs),
    /// Score imucald's orientation filter (gyro + accel + mag) against the reference orientation a
    /// log carries (ref_qw..ref_qz, sensor -> ENU, e.g. BROAD's optical motion capture): total,
    /// heading and inclination RMSE over the movement phase, by BROAD's definitions.
    Eval(EvalArgs),
    /// Magnetometer offsets of a vehicle resting at a known yaw (for vehicles that cannot be
    /// tumbled): tilt from the accelerometer (calibrated by the log's fit when it passed), the
    /// earth field from the World Magnetic Model at the place, the soft iron fitted on the log
    /// kept (none without one). The live service does the same for MAV_CMD_FIXED_MAG_CAL_YAW.
    FixedYaw(FixedYawArgs),
    /// Simulate an IMU with known calibration errors and write a log (.tlog, .csv, .csv.gz, or a
    /// flight-controller log .bin / .ulg with a known onboard magnetometer calibration applied).
    Simulate(SimulateArgs),
}

#[derive(Args)]
struct ReplayArgs {
    /// The log file. Default: a simulated tumble built into the binary (140 s, `.tlog`). Several
    /// logs, or a directory (every .tlog, .csv, .csv.gz, .bin and .ulg under it), make a batch:
    /// one log per core, one table of every log's compasses (--table) and their reports (--reports).
    #[arg(value_name = "LOG")]
    logs: Vec<PathBuf>,
    /// A batch's table: one CSV row per log and compass (status, method, offset, matrix, the
    /// quality verdict against the onboard calibration, the failure).
    #[arg(long, value_name = "FILE.csv")]
    table: Option<PathBuf>,
    /// A batch's reports: one JSON line per log, {"log": ..., "report": {...}} or {"log": ...,
    /// "error": "..."}.
    #[arg(long, value_name = "FILE.jsonl")]
    reports: Option<PathBuf>,
    /// A batch's worker threads (default: the cores).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    jobs: Option<u32>,
    /// TOML configuration (see config/).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Override format detection: tlog, csv, bin (ArduPilot DataFlash) or ulg (PX4 ULog).
    #[arg(long, value_enum)]
    format: Option<FormatArg>,
    /// Rows per second (Hz) of a CSV without a time column (as `rate_hz` under [input.csv]).
    #[arg(long)]
    rate_hz: Option<f64>,
    /// Write the readings of each compass's held-out check here, one CSV per compass (block,
    /// field in body axes with the onboard correction undone, attitude, the vehicle's calibrated
    /// field): to fit another tool on the same blocks.
    #[arg(long)]
    quality_points: Option<PathBuf>,
    /// Refit while reading, every `fit.refit_every_s` of data as the live service does, and keep
    /// the history in the report's `refits` (default: one fit per sensor on all the data).
    #[arg(long)]
    refits: bool,
    /// Write every compass to the exports as values to load, also those the held-out check or
    /// the vehicle's own parameters say not to load (the files say so); by default those are
    /// written as comments with the reason.
    #[arg(long)]
    export_all: bool,
    /// Write the JSON report here.
    #[arg(long)]
    report: Option<PathBuf>,
    /// Write calibrated samples (CSV) here.
    #[arg(long)]
    calibrated_out: Option<PathBuf>,
    /// Write plots (coverage maps, residuals) into this directory.
    #[arg(long)]
    plot: Option<PathBuf>,
    /// Write ArduPilot, PX4 and x-io Fusion parameter files into this directory.
    #[arg(long)]
    export: Option<PathBuf>,
    /// Write one self-contained HTML page (no network needed) with the field directions on the
    /// sphere before and after calibration, coverage, residuals, fitted values and failures.
    #[arg(long)]
    html: Option<PathBuf>,
    /// A diagnosis (`imucald diagnose --report`, imucald.diagnosis/1) of the same log to show in
    /// the `--html` page.
    #[arg(long, requires = "html")]
    diagnosis: Option<PathBuf>,
}

#[derive(Args)]
struct RunArgs {
    /// TOML configuration (see config/).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Source address, overriding the config's (repeatable): udpin:IP:PORT, udpout:IP:PORT,
    /// tcpout:HOST:PORT, tcpin:IP:PORT, serial:/dev/ttyX:BAUD, file:LOG[?speed=N], sim:SCENARIO.
    #[arg(long = "source")]
    sources: Vec<String>,
    /// JSON-lines consumer, overriding the config's (repeatable): stdout, udp:IP:PORT, tcp:IP:PORT,
    /// mqtt://HOST:PORT/PREFIX.
    #[arg(long = "publish")]
    publish: Vec<String>,
    /// Keep the latest report (imucald.report/1) in this file.
    #[arg(long)]
    report: Option<PathBuf>,
    /// Serve the live page at IP:PORT (loopback unless `ui.allow_remote`), overriding `[ui] listen`.
    #[arg(long)]
    ui: Option<String>,
}

#[derive(Args)]
struct DiagnoseArgs {
    /// The log file: .tlog, CSV or .csv.gz, ArduPilot DataFlash (.bin) or PX4 ULog (.ulg).
    log: PathBuf,
    /// TOML configuration (see config/).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Override format detection: tlog, csv, bin (ArduPilot DataFlash) or ulg (PX4 ULog).
    #[arg(long, value_enum)]
    format: Option<FormatArg>,
    /// Base calibration model: diag6 (cross_axis is then a candidate) or sym9.
    #[arg(long, value_enum, default_value_t = BaseModel::Diag6)]
    base_model: BaseModel,
    /// Family-wise significance level of each round.
    #[arg(long, default_value_t = 0.01)]
    alpha: f64,
    /// Seed of the held-out split.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Write the JSON report (imucald.diagnosis/1) here.
    #[arg(long)]
    report: Option<PathBuf>,
    /// Write residual-versus-regressor plots (before and after) into this directory.
    #[arg(long)]
    plot: Option<PathBuf>,
    /// Write the flight controller's parameters that remove the effects named into this
    /// directory: diagnose.parm (ArduPilot) and diagnose.params (PX4).
    #[arg(long)]
    export: Option<PathBuf>,
}

#[derive(Args)]
struct EvalArgs {
    /// The log file (CSV or .csv.gz with ref_q columns).
    log: PathBuf,
    /// TOML configuration (see config/); only the input mapping is used.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Override format detection: tlog, csv, bin (ArduPilot DataFlash) or ulg (PX4 ULog).
    #[arg(long, value_enum)]
    format: Option<FormatArg>,
    /// Constant offsets to remove first: none (BROAD's published, pre-aligned reference; the
    /// default), heading (the default with --reference), or heading-and-misalignment.
    #[arg(long, value_enum, ignore_case = true)]
    align: Option<AlignArg>,
    /// Score against optical motion capture (an OptiTrack Motive CSV export) instead of the log's
    /// own reference: its clock offset, the rigid body's rotation to the log's axes and the tilt of
    /// its world are found from the gyro and accelerometer; the flight controller's attitude, when
    /// the log has one, is scored too. Given several times, the take whose rotation rate correlates
    /// best with the gyro is used.
    #[arg(long)]
    reference: Vec<PathBuf>,
    /// The rigid body in the Motive export (default: the first one tracked).
    #[arg(long, requires = "reference")]
    rigid_body: Option<String>,
    /// Without the magnetometer (6D: heading from the gyro alone).
    #[arg(long)]
    no_mag: bool,
    /// Apply this calibration first: the service's calibration.json or a replay's --report file
    /// (a raw log scored without one is scored uncalibrated).
    #[arg(long)]
    calibration: Option<PathBuf>,
    /// Write the figures as JSON here.
    #[arg(long)]
    report: Option<PathBuf>,
}

#[derive(Args)]
struct FixedYawArgs {
    /// The log file (any format `replay` reads).
    log: PathBuf,
    /// The vehicle's true yaw while it rested, degrees clockwise from true north.
    #[arg(long)]
    yaw_deg: f64,
    /// Where it rested (degrees); without both, the log's position or GPS fix, else `[place]`
    /// from the config.
    #[arg(long, requires = "lon", allow_hyphen_values = true)]
    lat: Option<f64>,
    /// Longitude of where it rested (degrees east); with --lat.
    #[arg(long, requires = "lat", allow_hyphen_values = true)]
    lon: Option<f64>,
    /// The rest ends at this time of the log (s, as the report's times); default: the log's end.
    #[arg(long)]
    at_s: Option<f64>,
    /// TOML configuration (see config/): input mapping, sensor orientation, `[place]`.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Override format detection: tlog, csv, bin (ArduPilot DataFlash) or ulg (PX4 ULog).
    #[arg(long, value_enum)]
    format: Option<FormatArg>,
}

#[derive(Args)]
struct SimulateArgs {
    /// A built-in scenario (turntable, tumble, flight, bench, cruise, rover; warmup: a warm-up
    /// at rest, every IMU instance in one .bin, or one CSV each) or a scenario TOML file.
    #[arg(long, default_value = "tumble")]
    scenario: String,
    /// Output log; the format follows the extension.
    #[arg(long)]
    out: PathBuf,
    /// Write the true parameters and poses here (JSON).
    #[arg(long)]
    truth: Option<PathBuf>,
    /// Seed of the simulated noise (the same seed gives the same log).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// IMU message in a .tlog: highres_imu or scaled_imu.
    #[arg(long, value_enum, default_value_t = Message::HighresImu)]
    message: Message,
    /// MAVLink version of the frames in a .tlog (1 or 2).
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u8).range(1..=2))]
    mavlink_version: u8,
}

/// `diagnose --base-model`.
#[derive(Clone, Copy, ValueEnum)]
enum BaseModel {
    Diag6,
    Sym9,
}

/// `simulate --message`.
#[derive(Clone, Copy, ValueEnum)]
enum Message {
    #[value(name = "highres_imu")]
    HighresImu,
    #[value(name = "scaled_imu")]
    ScaledImu,
}

/// `--format`: a log format as the command line names it (the library's [`Format`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum FormatArg {
    /// MAVLink telemetry log (.tlog)
    Tlog,
    /// CSV (plain or .gz)
    Csv,
    /// ArduPilot DataFlash log (.bin)
    Bin,
    /// PX4 ULog (.ulg)
    Ulg,
}

impl From<FormatArg> for Format {
    fn from(f: FormatArg) -> Format {
        match f {
            FormatArg::Tlog => Format::Tlog,
            FormatArg::Csv => Format::Csv,
            FormatArg::Bin => Format::Bin,
            FormatArg::Ulg => Format::Ulg,
        }
    }
}

/// `--align`: which constant offsets `eval` removes (the library's [`Alignment`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum AlignArg {
    /// None: the reference is already aligned
    None,
    /// A constant heading offset between the reference and the estimate world frames
    Heading,
    /// The heading offset and a constant sensor-to-marker misalignment
    #[value(alias = "heading_and_misalignment", alias = "full")]
    HeadingAndMisalignment,
}

impl From<AlignArg> for Alignment {
    fn from(a: AlignArg) -> Alignment {
        match a {
            AlignArg::None => Alignment::None,
            AlignArg::Heading => Alignment::Heading,
            AlignArg::HeadingAndMisalignment => Alignment::HeadingAndMisalignment,
        }
    }
}

fn load_config(path: Option<&PathBuf>) -> Result<Config> {
    match path {
        Some(p) => Ok(Config::load(p)?),
        None => Ok(Config::default()),
    }
}

/// SIGINT or SIGTERM.
async fn wait_for_signal() {
    #[cfg(unix)]
    {
        let mut term =
            match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
                Ok(t) => t,
                Err(_) => {
                    let _ = tokio::signal::ctrl_c().await;
                    return;
                }
            };
        tokio::select! {
            _ = tokio::signal::ctrl_c() => {}
            _ = term.recv() => {}
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}

/// How a command ended, as the process's exit status.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Outcome {
    /// Done (0).
    Done,
    /// Ran, but produced nothing usable: no sensor calibrated (3).
    NothingCalibrated,
    /// Calibrated something, but nothing to load on the vehicle: a gyro bias only, or compasses
    /// whose calibration is not one to load (4).
    NothingToLoad,
}

/// Exit status of an error: bad input, a file that cannot be read or written (1). A source that
/// can never work, or a calibration store held by another service, ends `run` with 2.
const EXIT_ERROR: u8 = 1;
const EXIT_SOURCE_FAILED: u8 = 2;
const EXIT_NOTHING_CALIBRATED: u8 = 3;
const EXIT_NOTHING_TO_LOAD: u8 = 4;

/// A `run` whose replays could not be read at all.
#[derive(Debug)]
struct SourcesFailed(Vec<String>);

impl std::fmt::Display for SourcesFailed {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "no source could be read: {} (check the path, or give a live link such as --source udpin:127.0.0.1:14550)",
            self.0.join("; ")
        )
    }
}

impl std::error::Error for SourcesFailed {}

fn main() -> std::process::ExitCode {
    // Status lines of the service (links connected, lost, ended) at info, everything else from
    // warnings up; RUST_LOG overrides. Short lines: level and text.
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| format!("warn,{}=info", imucald::app::daemon::STATUS_TARGET).into());
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .without_time()
        .with_target(false)
        .init();
    let cli = Cli::parse();
    let result = match cli.cmd {
        Cmd::Replay(a) => replay_cmd(a),
        Cmd::Run(a) => run_cmd(a).map(|()| Outcome::Done),
        Cmd::Diagnose(a) => diagnose_cmd(a).map(|()| Outcome::Done),
        Cmd::Eval(a) => eval_cmd(a).map(|()| Outcome::Done),
        Cmd::FixedYaw(a) => fixed_yaw_cmd(a).map(|()| Outcome::Done),
        Cmd::Simulate(a) => simulate_cmd(a).map(|()| Outcome::Done),
    };
    match result {
        Ok(Outcome::Done) => std::process::ExitCode::SUCCESS,
        Ok(Outcome::NothingCalibrated) => std::process::ExitCode::from(EXIT_NOTHING_CALIBRATED),
        Ok(Outcome::NothingToLoad) => std::process::ExitCode::from(EXIT_NOTHING_TO_LOAD),
        Err(e) => {
            // The chain once, without a backtrace (RUST_BACKTRACE is for panics, not user errors).
            let mut text = format!("error: {e}");
            let mut last = e.to_string();
            for cause in e.chain().skip(1) {
                let c = cause.to_string();
                // A cause already quoted in the message above it is not repeated.
                if !last.contains(&c) {
                    text.push_str(&format!("\n  because: {c}"));
                }
                last = c;
            }
            eprintln!("{text}");
            let store_locked = matches!(
                e.downcast_ref::<imucald::error::Error>(),
                Some(imucald::error::Error::StoreLocked { .. })
            );
            if e.downcast_ref::<SourcesFailed>().is_some() || store_locked {
                std::process::ExitCode::from(EXIT_SOURCE_FAILED)
            } else {
                std::process::ExitCode::from(EXIT_ERROR)
            }
        }
    }
}

/// The simulated tumble built into the binary (so `imucald replay` works wherever it was
/// installed), written to a temporary file for the replay and removed after.
struct EmbeddedLog(PathBuf);

impl EmbeddedLog {
    const BYTES: &'static [u8] = include_bytes!("../fixtures/tumble.tlog");
    fn write() -> Result<EmbeddedLog> {
        let p = std::env::temp_dir().join(format!(
            "imucald-embedded-tumble-{}.tlog",
            std::process::id()
        ));
        std::fs::write(&p, Self::BYTES)
            .with_context(|| format!("writing the embedded tumble to {}", p.display()))?;
        Ok(EmbeddedLog(p))
    }
}

impl Drop for EmbeddedLog {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

fn replay_cmd(args: ReplayArgs) -> Result<Outcome> {
    let is_batch = args.logs.len() > 1
        || args.logs.iter().any(|p| p.is_dir())
        || args.table.is_some()
        || args.reports.is_some()
        || args.jobs.is_some();
    if is_batch {
        return replay_batch_cmd(args);
    }
    let ReplayArgs {
        logs,
        config,
        format,
        report,
        calibrated_out,
        plot,
        export,
        html,
        diagnosis,
        rate_hz,
        quality_points,
        refits,
        export_all,
        ..
    } = args;
    let mut cfg = load_config(config.as_ref())?;
    if rate_hz.is_some() {
        cfg.input.csv.rate_hz = rate_hz;
    }
    let (log, _embedded) = match logs.into_iter().next() {
        Some(p) => (p, None),
        None => {
            let e = EmbeddedLog::write()?;
            (e.0.clone(), Some(e))
        }
    };
    let opts = imucald::app::replay::ReplayOptions {
        format: format.map(Into::into),
        report,
        calibrated_out,
        plot_dir: plot,
        export_dir: export,
        html,
        diagnosis,
        quality_points,
        refits,
        export_all,
    };
    let bar = indicatif::ProgressBar::new(0);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{bar:40} {bytes}/{total_bytes} {bytes_per_sec} eta {eta}",
        )
        .expect("template"),
    );
    let out = imucald::app::replay::replay(&log, &cfg, &opts, &mut |done, total| {
        bar.set_length(total);
        bar.set_position(done);
    })
    .with_context(|| format!("replay of {}", log.display()))?;
    bar.finish_and_clear();
    print!("{}", imucald::app::replay::summary(&out.report));
    for p in &out.written {
        println!("wrote {}", p.display());
    }
    println!(
        "{}",
        imucald::app::replay::next_step(&out.report, &out.written, opts.export_dir.is_some())
    );
    if imucald::app::replay::calibrated_nothing(&out.report) {
        eprintln!("error: nothing was calibrated (exit status {EXIT_NOTHING_CALIBRATED}): see the reasons above");
        return Ok(Outcome::NothingCalibrated);
    }
    if !imucald::app::replay::loadable(&out.report) {
        eprintln!(
            "error: nothing to load (exit status {EXIT_NOTHING_TO_LOAD}): {}; keep the vehicle's calibration, or fly or turn the vehicle through more directions and replay again",
            not_loadable(&out.report)
        );
        return Ok(Outcome::NothingToLoad);
    }
    Ok(Outcome::Done)
}

/// Why a replay that calibrated something has nothing to load: each compass's load reason, the
/// accelerometer's failure, and the gyro bias when it is what passed.
fn not_loadable(r: &imucald::report::Report) -> String {
    let mut why: Vec<String> = r
        .load
        .iter()
        .map(|d| {
            format!(
                "compass {} ({}): {}",
                d.compass_id,
                d.instance,
                d.reason.words()
            )
        })
        .collect();
    if why.is_empty() {
        why.push("no compass calibrated".into());
    }
    why.push("the accelerometer did not pass".into());
    if r.calibration.gyro.status == imucald::report::CalStatus::Ok {
        why.push("the gyro bias passed, but no parameter file carries it (the flight controller learns its own)".into());
    }
    why.join("; ")
}

/// `imucald replay` over several logs or directories ([`imucald::app::batch`]): one bar, one line.
fn replay_batch_cmd(args: ReplayArgs) -> Result<Outcome> {
    let per_log = [
        ("--report", args.report.is_some(), "--reports FILE.jsonl"),
        ("--calibrated-out", args.calibrated_out.is_some(), ""),
        ("--plot", args.plot.is_some(), ""),
        ("--export", args.export.is_some(), ""),
        ("--html", args.html.is_some(), ""),
        ("--quality-points", args.quality_points.is_some(), ""),
    ];
    if let Some((name, _, instead)) = per_log.iter().find(|(_, given, _)| *given) {
        let instead = match *instead {
            "" => String::new(),
            i => format!(" (in a batch: {i})"),
        };
        anyhow::bail!("{name} writes one log's output: replay that log alone{instead}");
    }
    let mut cfg = load_config(args.config.as_ref())?;
    if args.rate_hz.is_some() {
        cfg.input.csv.rate_hz = args.rate_hz;
    }
    let found = imucald::app::batch::find_logs(&args.logs)?;
    say_skipped(&found.skipped);
    if found.logs.is_empty() {
        anyhow::bail!(
            "no logs ({}) in {}",
            imucald::app::batch::LOG_SUFFIXES.join(", "),
            args.logs
                .iter()
                .map(|p| p.display().to_string())
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    let opts = imucald::app::batch::BatchOptions {
        jobs: args.jobs.map(|j| j as usize),
        replay: imucald::app::replay::ReplayOptions {
            format: args.format.map(Into::into),
            refits: args.refits,
            ..Default::default()
        },
        table: args.table,
        reports: args.reports,
    };
    let bar = indicatif::ProgressBar::new(found.logs.len() as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{bar:40} {pos}/{len} logs, {msg}, {elapsed} elapsed, eta {eta}",
        )
        .expect("template"),
    );
    bar.set_message("0 failed");
    let s = imucald::app::batch::run(&found.logs, &cfg, &opts, &mut |p| {
        bar.set_position(p.done as u64);
        bar.set_message(format!("{} failed", p.failed));
    })?;
    bar.finish_and_clear();
    println!("{}", s.line());
    let in_rows = |what: &str| match opts.table {
        Some(_) => format!("each {what} is in its row"),
        None => format!("give --table FILE.csv for each {what}"),
    };
    match s.end() {
        imucald::app::batch::BatchEnd::SomethingToLoad => Ok(Outcome::Done),
        imucald::app::batch::BatchEnd::NothingToLoad => {
            eprintln!(
                "error: no log had anything to load (exit status {EXIT_NOTHING_TO_LOAD}): {} calibrated with nothing to load, {} calibrated nothing or were not replayed; {}; keep the vehicles' calibrations, or fly or turn them through more directions and replay again",
                s.nothing_to_load,
                s.failed(),
                in_rows("compass's load_reason"),
            );
            Ok(Outcome::NothingToLoad)
        }
        imucald::app::batch::BatchEnd::Failed => {
            eprintln!(
                "error: {} of {} logs calibrated nothing or were not replayed (exit status {EXIT_NOTHING_CALIBRATED}): {}",
                s.failed(),
                s.logs,
                in_rows("log's failure"),
            );
            Ok(Outcome::NothingCalibrated)
        }
    }
}

/// The files a batch's directories held besides logs: how many of each kind, the first few named.
fn say_skipped(skipped: &[(PathBuf, imucald::app::batch::SkipReason)]) {
    const NAMED: usize = 3;
    if skipped.is_empty() {
        return;
    }
    let named: Vec<String> = skipped
        .iter()
        .take(NAMED)
        .map(|(p, why)| format!("{} ({})", p.display(), why.name()))
        .collect();
    let more = skipped.len().saturating_sub(NAMED);
    eprintln!(
        "skipped {} file{} in the directories: {}{}",
        skipped.len(),
        if skipped.len() == 1 { "" } else { "s" },
        named.join(", "),
        if more > 0 {
            format!(" and {more} more")
        } else {
            String::new()
        }
    );
}

fn run_cmd(args: RunArgs) -> Result<()> {
    let RunArgs {
        config,
        sources,
        publish,
        report,
        ui,
    } = args;
    let mut cfg = load_config(config.as_ref())?;
    if ui.is_some() {
        cfg.ui.listen = ui;
    }
    for a in &sources {
        // Said against the option the user typed, not the configuration it lands in.
        if let Err(imucald::error::Error::Config { message, .. }) =
            imucald::io::link::Address::parse(a)
        {
            anyhow::bail!("--source {message}");
        }
    }
    if !sources.is_empty() {
        cfg.daemon.sources = sources
            .into_iter()
            .map(|address| imucald::config::SourceConfig {
                address,
                payload: imucald::config::PayloadKind::Mavlink,
                fields: vec![],
                scales: Default::default(),
            })
            .collect();
    }
    if !publish.is_empty() {
        cfg.daemon.publish = publish;
    }
    if let Some(r) = report {
        cfg.daemon.report = Some(r.display().to_string());
    }
    if cfg.daemon.sources.is_empty() && cfg.daemon.publish.is_empty() {
        // The embedded default shows its output on the terminal.
        cfg.daemon.publish = vec!["stdout".into()];
        if cfg.ui.listen.is_none() {
            cfg.daemon.heading_rate_hz = 1.0;
            cfg.daemon.attitude_rate_hz = 1.0;
        }
        eprintln!("imucald run: no sources configured, running the embedded simulated tumble (sim:tumble, 140 s). Ctrl-C stops.");
    }
    cfg.validate()?;
    // One thread: the per-sample work is small, and waking a second worker for every arriving frame
    // costs more CPU than the work itself (benches/live.rs). Fits run on the blocking pool.
    // Memory stays flat over long runs: one malloc arena for the few threads (the blocking
    // pool's fit thread had its own, whose heap crept up about 0.5 MB an hour by
    // fragmentation), and the fits' large scratch buffers (hundreds of kB per refit) always
    // from mmap, back to the system when freed.
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets allocator parameters; called before other threads start.
    unsafe {
        libc::mallopt(libc::M_ARENA_MAX, 1);
        libc::mallopt(libc::M_MMAP_THRESHOLD, 128 * 1024);
    }
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("tokio runtime")?;
    let summary = rt.block_on(async move {
        let (tx, rx) = tokio::sync::watch::channel(false);
        tokio::spawn(async move {
            wait_for_signal().await;
            let _ = tx.send(true);
        });
        // The service runs as a task, not as the `block_on` future itself: waking that
        // future goes through the I/O driver (an eventfd write and one more epoll_wait),
        // while waking a task from another task on this thread only queues it.
        let r = tokio::spawn(imucald::app::daemon::run(cfg, rx))
            .await
            .context("service task")?;
        anyhow::Ok(r?)
    })?;
    rt.shutdown_timeout(std::time::Duration::from_millis(200));
    eprintln!(
        "imucald run: {} samples, {} calibration{} accepted, {} samples dropped",
        summary.samples,
        summary.accepted,
        if summary.accepted == 1 { "" } else { "s" },
        summary.inbound_dropped
    );
    if !summary.sources_failed.is_empty() && summary.samples == 0 {
        return Err(SourcesFailed(summary.sources_failed).into());
    }
    Ok(())
}

fn diagnose_cmd(args: DiagnoseArgs) -> Result<()> {
    let DiagnoseArgs {
        log,
        config,
        format,
        base_model,
        alpha,
        seed,
        report,
        plot,
        export,
    } = args;
    let cfg = load_config(config.as_ref())?;
    let base = match base_model {
        BaseModel::Diag6 => imucald::calib::model::ModelKind::Diag6,
        BaseModel::Sym9 => imucald::calib::model::ModelKind::Sym9,
    };
    anyhow::ensure!(
        alpha > 0.0 && alpha < 1.0,
        "--alpha {alpha}: must be between 0 and 1"
    );
    let input = imucald::io::sources::read_log(&log, format.map(Into::into), &cfg.input)
        .with_context(|| format!("reading {}", log.display()))?;
    let spinner = indicatif::ProgressBar::new_spinner();
    spinner.set_message(format!(
        "diagnosing {} samples of {}",
        input.samples.len(),
        log.display()
    ));
    spinner.enable_steady_tick(std::time::Duration::from_millis(120));
    let opts = imucald::diagnose::DiagnoseOptions {
        base_model: base,
        alpha,
        seed,
        log_where: input.place(),
        ..Default::default()
    };
    let r = imucald::diagnose::diagnose(&input.samples, &cfg, &opts);
    spinner.finish_and_clear();
    print!("{}", imucald::diagnose::summary_table(&r));
    if let Some(path) = report {
        imucald::io::publish::write_json(&path, &r)?;
        println!("wrote {}", path.display());
    }
    if let Some(dir) = plot {
        for p in imucald::app::plot::diagnosis(&dir, &r)
            .with_context(|| format!("plots into {}", dir.display()))?
        {
            println!("wrote {}", p.display());
        }
    }
    if let Some(dir) = &export {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        for (name, text) in imucald::diagnose::fix::export_files(&r) {
            let path = dir.join(name);
            imucald::io::publish::write_text(&path, &text)?;
            println!("wrote {}", path.display());
        }
    }
    let shown = export.as_ref().map(|d| d.display().to_string());
    print!(
        "{}",
        imucald::diagnose::fix::closing_lines(&r, shown.as_deref())
    );
    Ok(())
}

fn eval_cmd(args: EvalArgs) -> Result<()> {
    let EvalArgs {
        log,
        config,
        format,
        align,
        reference,
        rigid_body,
        no_mag,
        calibration,
        report,
    } = args;
    let align = align.map(Alignment::from);
    let cfg = load_config(config.as_ref())?;
    let input =
        imucald::app::eval::read_log(&log, format.map(Into::into), &cfg, calibration.as_deref())
            .with_context(|| format!("reading {}", log.display()))?;
    let fcfg = imucald::attitude::fusion::FusionConfig {
        use_mag: !no_mag,
        ..Default::default()
    };
    if !reference.is_empty() {
        let alignment = match align {
            None => Alignment::Heading,
            Some(Alignment::None) => anyhow::bail!(
                "--align none with --reference: the capture world's heading is unknown, so at \
                 least the heading is aligned (--align heading or heading-and-misalignment)"
            ),
            Some(a) => a,
        };
        return eval_against_reference(
            &input,
            &reference,
            rigid_body.as_deref(),
            &fcfg,
            alignment,
            report,
        );
    }
    let alignment = align.unwrap_or(Alignment::None);
    let r = imucald::attitude::eval::evaluate_filter(&input.samples, &fcfg, alignment)
            .with_context(|| {
                format!(
                    "{}: no sample has a reference orientation (ref_qw, ref_qx, ref_qy, ref_qz columns) \
                     inside the movement phase (moving = 1, or all samples without a moving column)",
                    log.display()
                )
            })?;
    print!("{}", r.to_text());
    if let Some(path) = report {
        imucald::io::publish::write_json(&path, &r)?;
        println!("wrote {}", path.display());
    }
    Ok(())
}

/// `imucald eval LOG --reference CAPTURE...`: each capture aligned with the log, the best
/// correlated one used to score imucald's filter and the flight controller's attitude.
fn eval_against_reference(
    input: &imucald::io::sources::Log,
    references: &[PathBuf],
    rigid_body: Option<&str>,
    fcfg: &imucald::attitude::fusion::FusionConfig,
    alignment: Alignment,
    report: Option<PathBuf>,
) -> Result<()> {
    let captures = imucald::app::eval::align_captures(input, references, rigid_body)?;
    let several = captures.takes.len() > 1;
    for (take, a) in captures.takes.iter().zip(&captures.alignments) {
        print!("{}", take.summary());
        match a {
            Ok(a) if several => println!(
                "  rate correlation {:.3} at offset {:.3} s",
                a.correlation, a.time_offset_s
            ),
            Ok(_) => {}
            Err(e) => println!("  not aligned: {e}"),
        }
    }
    if let (Some(i), true) = (captures.best, several) {
        println!("using {}", captures.takes[i].path.display());
    }
    let r = captures.evaluate(input, fcfg, alignment)?;
    print!("{}", r.to_text());
    if let Some(path) = report {
        imucald::io::publish::write_json(&path, &r)?;
        println!("wrote {}", path.display());
    }
    Ok(())
}

fn fixed_yaw_cmd(a: FixedYawArgs) -> Result<()> {
    use imucald::app::fixedyaw::{from_log, FixedYawError, LogRequest, PlaceSource};
    let cfg = load_config(a.config.as_ref())?;
    let req = LogRequest {
        yaw_deg: a.yaw_deg,
        given: a.lat.zip(a.lon),
        at_s: a.at_s,
        format: a.format.map(Into::into),
        ..Default::default()
    };
    let log = a.log.display();
    let r = from_log(&a.log, &cfg, &req).map_err(|e| match e {
        FixedYawError::NoPlace => anyhow::anyhow!(
            "no place: give --lat and --lon, or [place] in the config ({log} has no position or GPS fix)"
        ),
        FixedYawError::OutsideLog {
            at_s,
            first_s,
            last_s,
        } => anyhow::anyhow!(
            "--at-s {at_s} is outside the log ({first_s:.1} to {last_s:.1} s): give the time the rest ended"
        ),
        FixedYawError::Refused(why) => {
            anyhow::anyhow!("{log}: {why} (--at-s picks the end of the rest)")
        }
        FixedYawError::Input(e) => anyhow::Error::new(e).context(format!("reading {log}")),
        other => anyhow::anyhow!("{log}: {other}"),
    })?;
    let (fy, cal) = (&r.found.fixed, &r.found.calibration);
    let o = cal.offset;
    println!(
        "fixed yaw {:.1} deg, roll {:.1} deg, pitch {:.1} deg, field {:.1} uT ({} samples): offset [{:.2}, {:.2}, {:.2}] uT",
        a.yaw_deg, fy.roll_deg, fy.pitch_deg, r.field.total_ut, fy.samples, o[0], o[1], o[2]
    );
    let source = match &r.place_source {
        PlaceSource::Given => "--lat/--lon",
        PlaceSource::Found(s) => s.as_str(),
    };
    let model = match r.place.model {
        imucald::attitude::FieldModel::Wmm => "WMM",
        imucald::attitude::FieldModel::Igrf13 => "IGRF-13",
        imucald::attitude::FieldModel::Fitted => "fitted",
    };
    let day = match r.place.date_source.as_str() {
        "today" => "today".to_string(),
        from => format!("{} (from the {})", r.place.date, from.replace('_', " ")),
    };
    println!(
        "place {:.5}, {:.5} from {source}; {model} field of {day}",
        r.place.latitude_deg.unwrap_or(f64::NAN),
        r.place.longitude_deg.unwrap_or(f64::NAN),
    );
    match (&r.mag_fit, r.found.soft_iron_kept) {
        (Some(m), true) => println!("soft iron: the log's {m} fit, kept"),
        (Some(m), false) => println!("soft iron: none (the log's {m} fit left out)"),
        (None, _) => println!("soft iron: none (the log's magnetometer fit did not pass)"),
    }
    if r.found.accel_calibrated {
        println!("tilt: from the accelerometer calibrated by the log's fit");
    } else {
        println!("tilt: from the uncalibrated accelerometer (the log's fit did not pass)");
    }
    for (name, value) in r.params() {
        println!("{name} {value}");
    }
    Ok(())
}

fn simulate_cmd(args: SimulateArgs) -> Result<()> {
    use imucald::app::simulate::{SimLog, SimulateRequest};
    use imucald::io::samplelog::{ImuMessage, TlogWriteOptions};
    let SimulateArgs {
        scenario,
        out,
        truth,
        seed,
        message,
        mavlink_version,
    } = args;
    if scenario == imucald::app::simulate::WARMUP {
        for p in imucald::app::simulate::write_warmup(&out, seed, truth.as_deref())? {
            println!("wrote {}", p.display());
        }
        return Ok(());
    }
    let sc = imucald::sim::named::scenario(&scenario)
        .with_context(|| format!("--scenario {scenario}"))?;
    let Some(kind) = SimLog::of(&out) else {
        anyhow::bail!("--out {}: use a {} name", out.display(), SimLog::NAMES);
    };
    let message = match message {
        Message::HighresImu => ImuMessage::HighresImu,
        Message::ScaledImu => ImuMessage::ScaledImu,
    };
    let req = SimulateRequest {
        seed,
        tlog: TlogWriteOptions {
            message,
            mavlink_version,
            ..Default::default()
        },
        truth,
    };
    let w = imucald::app::simulate::write(&sc, &out, kind, &req)?;
    if let Some(onboard) = &w.onboard {
        println!(
            "onboard magnetometer calibration applied in the log: offset {:?} uT, matrix {:?}",
            onboard.offset_ut, onboard.matrix
        );
    }
    println!(
        "wrote {} ({} samples, {:.1} s, scenario {}, seed {seed})",
        out.display(),
        w.samples,
        w.duration_s,
        sc.name
    );
    if let Some(t) = &w.truth {
        println!("wrote {}", t.display());
    }
    Ok(())
}
