//! The `imucald` binary: a thin edge over the library (anyhow lives only here).

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use imucald::config::Config;
use imucald::decode::Format;
use std::path::PathBuf;

#[derive(Parser)]
#[command(name = "imucald", version, about = "Calibrate accelerometer, magnetometer and gyroscope; publish heading")]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Run a captured log (MAVLink .tlog, CSV or .csv.gz) through the calibration pipeline.
    Replay {
        /// The log file. Default: the bundled simulated tumble in fixtures/.
        log: Option<PathBuf>,
        /// TOML configuration (see config/).
        #[arg(long)]
        config: Option<PathBuf>,
        /// Override format detection: tlog or csv.
        #[arg(long)]
        format: Option<String>,
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
    },
}

fn load_config(path: Option<&PathBuf>) -> Result<Config> {
    match path {
        Some(p) => Ok(Config::load(p)?),
        None => Ok(Config::default()),
    }
}

fn main() -> Result<()> {
    tracing_subscriber::fmt().with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into())).with_writer(std::io::stderr).init();
    let cli = Cli::parse();
    match cli.cmd {
        Cmd::Replay { log, config, format, report, calibrated_out, plot, export } => {
            let cfg = load_config(config.as_ref())?;
            let format = match format.as_deref() {
                None => None,
                Some(f) => Some(Format::parse(f).with_context(|| format!("--format `{f}`: use tlog or csv"))?),
            };
            let log = log.unwrap_or_else(|| PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/tumble.tlog")));
            let opts = imucald::replay::ReplayOptions { format, report, calibrated_out, plot_dir: plot, export_dir: export };
            let bar = indicatif::ProgressBar::new(0);
            bar.set_style(indicatif::ProgressStyle::with_template("{bar:40} {pos}/{len} samples {per_sec} eta {eta}").expect("template"));
            let out = imucald::replay::replay(&log, &cfg, &opts, &mut |done, total| {
                bar.set_length(total);
                bar.set_position(done);
            })
            .with_context(|| format!("replay of {}", log.display()))?;
            bar.finish_and_clear();
            print!("{}", imucald::replay::summary(&out.report));
            for p in &out.written {
                println!("wrote {}", p.display());
            }
        }
    }
    Ok(())
}
