//! Sources: the only layer that knows where bytes come from. For now, files (`file:` addresses and
//! plain paths) decoded whole; live transports build on the same decoders.

use crate::config::Config;
use crate::decode::{
    decode_csv, decode_tlog, detect_format, maybe_gunzip, DecodeStats, Format, InstanceChoice,
    MessageConverter,
};
use crate::error::Error;
use crate::types::{Sample, Unit, Units};
use std::path::Path;

/// A decoded log.
#[derive(Debug, Clone)]
pub struct Log {
    pub format: Format,
    pub samples: Vec<Sample>,
    pub stats: DecodeStats,
    pub instance: Option<String>,
    pub units: Units,
}

/// Read and decode a log file (`.tlog`, `.csv`, `.csv.gz`). `format` overrides detection.
pub fn read_log(path: &Path, format: Option<Format>, cfg: &Config) -> Result<Log, Error> {
    let bytes = std::fs::read(path).map_err(|source| Error::Read {
        path: path.to_path_buf(),
        source,
    })?;
    decode_log(&bytes, path, format, cfg)
}

/// Decode the bytes of a log file (gzip or not, tlog or CSV); `path` only names it in errors.
/// Any bytes give a log or an error, never a panic (fuzzed: `fuzz/fuzz_targets/tlog.rs`).
pub fn decode_log(
    bytes: &[u8],
    path: &Path,
    format: Option<Format>,
    cfg: &Config,
) -> Result<Log, Error> {
    let data = maybe_gunzip(bytes).map_err(|e| Error::Format {
        path: path.to_path_buf(),
        message: format!("gzip: {e}"),
    })?;
    let cfg_format = Format::parse(&cfg.input.format);
    let format = match format.or(cfg_format).or_else(|| detect_format(&data)) {
        Some(f) => f,
        None => {
            return Err(Error::Format {
                path: path.to_path_buf(),
                message: "cannot tell the format: neither a MAVLink .tlog (u64 timestamp + frame) nor CSV with a header row; use --format tlog|csv".into(),
            })
        }
    };
    match format {
        Format::Tlog => {
            let choice = if cfg.input.instance == "auto" {
                InstanceChoice::Auto
            } else {
                InstanceChoice::Named(cfg.input.instance.clone())
            };
            let mut conv = MessageConverter::new(choice, cfg.input.raw_imu_scale);
            let samples = decode_tlog(&data, &mut conv);
            if samples.is_empty() {
                let what = match &conv.choice {
                    InstanceChoice::Auto => {
                        "no IMU message with a magnetometer (HIGHRES_IMU, SCALED_IMU*, RAW_IMU)"
                            .to_string()
                    }
                    InstanceChoice::Named(n) => format!(
                        "no messages of instance `{n}` (set input.instance to one the log has)"
                    ),
                };
                return Err(Error::Format {
                    path: path.to_path_buf(),
                    message: format!("{what}; skipped: {:?}", conv.stats.skipped),
                });
            }
            let units = conv.units();
            Ok(Log {
                format,
                samples,
                instance: conv.instance().map(String::from),
                stats: conv.stats,
                units,
            })
        }
        Format::Csv => {
            let text = String::from_utf8_lossy(&data);
            let mut stats = DecodeStats::default();
            let samples =
                decode_csv(&text, &cfg.input.csv, &mut stats).map_err(|message| Error::Format {
                    path: path.to_path_buf(),
                    message,
                })?;
            let accel_units = match cfg.input.accel_units.as_str() {
                "counts" => Unit::Counts,
                _ => Unit::Si,
            };
            Ok(Log {
                format,
                samples,
                stats,
                instance: None,
                units: Units {
                    accel: accel_units,
                    gyro: Unit::Si,
                    mag: Unit::Si,
                },
            })
        }
    }
}
