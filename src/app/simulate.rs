//! `imucald simulate`: a scenario ([`crate::sim`]) simulated and written as a log of the kind its
//! file name asks for, with the truth beside it when wanted.

use crate::error::Error;
use crate::io::flightlog::write::OnboardMag;
use crate::io::samplelog::TlogWriteOptions;
use crate::sim::Scenario;
use std::path::{Path, PathBuf};

/// The kinds of log a simulation is written as, by the output file's name.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SimLog {
    /// A MAVLink telemetry log (`.tlog`).
    Tlog,
    /// imucald's CSV (`.csv`, or gzip-compressed `.csv.gz`).
    Csv,
    /// A flight-controller log (ArduPilot DataFlash `.bin`, PX4 ULog `.ulg`), the magnetometer
    /// logged through a known onboard calibration.
    FlightLog,
}

impl SimLog {
    /// The names [`SimLog::of`] knows, for a message.
    pub const NAMES: &'static str = ".tlog, .csv, .csv.gz, .bin or .ulg";

    /// The kind of log a file of this name is (case does not matter); `None` for another name.
    pub fn of(path: &Path) -> Option<SimLog> {
        let name = path.to_string_lossy().to_lowercase();
        if name.ends_with(".tlog") {
            Some(SimLog::Tlog)
        } else if name.ends_with(".csv") || name.ends_with(".csv.gz") {
            Some(SimLog::Csv)
        } else if name.ends_with(".bin") || name.ends_with(".ulg") {
            Some(SimLog::FlightLog)
        } else {
            None
        }
    }
}

/// How to simulate and what to write.
#[derive(Debug, Clone, Default)]
pub struct SimulateRequest {
    /// Seed of the simulated noise (the same seed gives the same log).
    pub seed: u64,
    /// The IMU message and MAVLink version of a `.tlog` (ignored for other logs).
    pub tlog: TlogWriteOptions,
    /// Write the true parameters and poses (JSON) here too.
    pub truth: Option<PathBuf>,
}

/// What was written.
#[derive(Debug, Clone, PartialEq)]
pub struct Simulated {
    /// Samples in the log.
    pub samples: usize,
    /// Time of the last sample, s.
    pub duration_s: f64,
    /// The onboard magnetometer calibration a flight-controller log was written through.
    pub onboard: Option<OnboardMag>,
    /// The truth file, when asked for.
    pub truth: Option<PathBuf>,
}

/// Simulate `sc` and write it to `out` as a `kind` log (and the truth, when asked). Atomic writes.
pub fn write(
    sc: &Scenario,
    out: &Path,
    kind: SimLog,
    req: &SimulateRequest,
) -> Result<Simulated, Error> {
    let sim = crate::sim::simulate(sc, req.seed);
    let onboard = write_log(out, kind, &sim.samples, &req.tlog)?;
    if let Some(t) = &req.truth {
        crate::io::publish::write_json(t, &sim.truth)?;
    }
    Ok(Simulated {
        samples: sim.samples.len(),
        duration_s: sim.samples.last().map_or(0.0, |s| s.t_s),
        onboard,
        truth: req.truth.clone(),
    })
}

/// The samples as a `kind` log at `out`; the onboard calibration of a flight-controller log.
fn write_log(
    out: &Path,
    kind: SimLog,
    samples: &[crate::types::Sample],
    tlog: &TlogWriteOptions,
) -> Result<Option<OnboardMag>, Error> {
    match kind {
        SimLog::Tlog => crate::io::samplelog::write_tlog(out, samples, tlog).map(|()| None),
        SimLog::Csv => crate::io::samplelog::write_csv(out, samples).map(|()| None),
        SimLog::FlightLog => {
            // The magnetometer logged corrected by a known onboard calibration, as flight
            // controllers log it; replay undoes it from the log's parameters.
            let onboard = OnboardMag::example();
            crate::io::flightlog::write::write_flight_log(out, samples, &onboard)?;
            Ok(Some(onboard))
        }
    }
}

/// The warm-up scenario's name (`imucald simulate --scenario warmup`): [`write_warmup`].
pub const WARMUP: &str = "warmup";

/// The simulated warm-up at rest ([`crate::sim::warmup`], its default settings) written as an
/// ArduPilot DataFlash `.bin` with every IMU instance (`IMU` records with their instance `I` and
/// temperature `T`), or as one CSV per IMU instance beside `out` (`warm.csv` -> `warm_imu0.csv`,
/// `warm_imu1.csv`, ...). With `truth`, the hidden bias curves (JSON).
pub fn write_warmup(out: &Path, seed: u64, truth: Option<&Path>) -> Result<Vec<PathBuf>, Error> {
    let name = out.to_string_lossy().to_string();
    let stem = name
        .strip_suffix(".csv.gz")
        .or_else(|| name.strip_suffix(".csv"));
    let dataflash = name.to_ascii_lowercase().ends_with(".bin");
    if stem.is_none() && !dataflash {
        return Err(Error::Other(format!(
            "{name}: the warm-up is written as a DataFlash .bin, or as CSV, one file per IMU instance (.csv or .csv.gz)"
        )));
    }
    let w = crate::sim::warmup::simulate(&crate::sim::warmup::WarmupSettings::default(), seed);
    let mut written = vec![];
    match (stem, w.instances.split_first()) {
        (_, None) => {}
        (None, Some((first, further))) => {
            let extra = crate::io::flightlog::write::DataflashExtra {
                further_imus: further,
                params: &[],
            };
            crate::io::flightlog::write::write_dataflash_with(
                out,
                first,
                &OnboardMag::example(),
                &extra,
            )?;
            written.push(out.to_path_buf());
        }
        (Some(stem), Some(_)) => {
            let ext = &name[stem.len()..];
            for (k, samples) in w.instances.iter().enumerate() {
                let p = PathBuf::from(format!("{stem}_imu{k}{ext}"));
                crate::io::samplelog::write_csv(&p, samples)?;
                written.push(p);
            }
        }
    }
    if let Some(t) = truth {
        crate::io::publish::write_json(t, &w.truth)?;
        written.push(t.to_path_buf());
    }
    Ok(written)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_log_kind_follows_the_name() {
        let of = |n: &str| SimLog::of(Path::new(n));
        assert_eq!(of("a.TLOG"), Some(SimLog::Tlog));
        assert_eq!(of("dir.x/a.csv.gz"), Some(SimLog::Csv));
        assert_eq!(of("a.Csv"), Some(SimLog::Csv));
        assert_eq!(of("a.ulg"), Some(SimLog::FlightLog));
        assert_eq!(of("a.bin"), Some(SimLog::FlightLog));
        assert_eq!(of("a.json"), None);
        assert_eq!(of("tlog"), None);
    }

    #[test]
    fn a_short_simulation_is_written_with_its_truth() {
        let dir = tempfile::tempdir().unwrap();
        let mut sc = Scenario::named("tumble").unwrap();
        sc.duration_s = Some(2.0);
        let out = dir.path().join("short.csv");
        let truth = dir.path().join("truth.json");
        let req = SimulateRequest {
            seed: 4,
            truth: Some(truth.clone()),
            ..Default::default()
        };
        let w = write(&sc, &out, SimLog::Csv, &req).unwrap();
        assert_eq!(w.samples, 200);
        assert!((w.duration_s - 1.99).abs() < 1e-9, "{}", w.duration_s);
        assert_eq!(w.onboard, None);
        let rows = std::fs::read_to_string(&out).unwrap().lines().count();
        assert_eq!(rows, 201);
        let t: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&truth).unwrap()).unwrap();
        assert!(t["mag"]["offset"].is_array(), "{t}");
        let bin = dir.path().join("short.bin");
        let w = write(&sc, &bin, SimLog::FlightLog, &SimulateRequest::default()).unwrap();
        assert_eq!(w.onboard, Some(OnboardMag::example()));
        assert!(std::fs::metadata(&bin).unwrap().len() > 0);
    }
}
