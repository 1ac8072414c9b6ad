//! Start-up configuration (TOML). Every section and key has a default, unknown keys are errors that
//! name the key, and `validate` checks ranges with messages that say what to fix.

use crate::attitude::Place;
use crate::calib::gate::GateConfig;
pub use crate::calib::settings::{
    AccelUnits, AcceptConfig, AcceptLimits, CalibSettings, FitConfig, MagModelChoice, ModelChoice,
};
pub use crate::calib::tempcal::TempCalSettings;
use crate::error::Error;
pub use crate::io::sources::{InputConfig, InputFormat};
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, Default)]
#[serde(deny_unknown_fields, default)]
pub struct Config {
    /// `[input]`: formats and units. Default: see [`InputConfig`].
    pub input: InputConfig,
    /// `[gate]`: the static-pose detector. Default: see [`GateConfig`].
    pub gate: GateConfig,
    /// `[fit]`: models and refits. Default: see [`FitConfig`].
    pub fit: FitConfig,
    /// `[accept]`: acceptance limits. Default: see [`AcceptLimits`].
    pub accept: AcceptConfig,
    /// Where and when: enables true heading (declination) and the expected field strength.
    /// Default: none (magnetic heading).
    pub place: Option<Place>,
    /// `[orientation]`: the IMU's mounting. Default: see [`OrientationConfig`].
    pub orientation: OrientationConfig,
    /// The live service (`imucald run`). Default: see [`DaemonConfig`].
    pub daemon: DaemonConfig,
    /// `[ui]`: the live page of the service. Default: see [`UiConfig`] (no page).
    pub ui: UiConfig,
    /// `[tempcal]`: the temperature calibration of `replay`. Default: see [`TempCalSettings`].
    pub tempcal: TempCalSettings,
}

/// The live page (`imucald run --ui ADDR`): a web page and its JSON/event stream served by the
/// service while it runs.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, Default)]
#[serde(deny_unknown_fields, default)]
pub struct UiConfig {
    /// Serve the page at this `IP:PORT` (port 0: any free port, logged). A loopback address unless
    /// `allow_remote`. Default: none (no page).
    pub listen: Option<String>,
    /// Allow a `listen` address that is not loopback (the page has no authentication: anyone who
    /// reaches the address sees the calibration and can keep a stream open). Default: false.
    pub allow_remote: bool,
}

/// One input of the live service.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SourceConfig {
    /// `udpin:IP:PORT`, `udpout:IP:PORT`, `tcpout:HOST:PORT`, `tcpin:IP:PORT`, `serial:/dev/ttyX:BAUD`,
    /// `file:PATH[?speed=N]`, `sim:SCENARIO[?seed=N&speed=N]`. Required (no default).
    pub address: String,
    /// What the bytes are: "mavlink", "motioncal" (`Raw:` lines), "csv" (lines of `fields`).
    /// Default: "mavlink".
    #[serde(default)]
    pub payload: PayloadKind,
    /// For "csv": field names in column order (t, ax, ay, az, gx, gy, gz, mx, my, mz, temp, ...).
    /// Default: none.
    #[serde(default)]
    pub fields: Vec<String>,
    /// For "csv": unit factors per field. Default: none (1).
    #[serde(default)]
    pub scales: std::collections::BTreeMap<String, f64>,
}

/// `daemon.sources[].payload`: what a source's bytes are.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PayloadKind {
    /// MAVLink frames (v1 or v2).
    #[default]
    Mavlink,
    /// MotionCal's `Raw:` text lines.
    Motioncal,
    /// Text lines of comma-separated numbers in the order `fields` names.
    Csv,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct DaemonConfig {
    /// Inputs. Empty: the embedded default, a simulated IMU tumbling with pauses (`sim:tumble`).
    /// Default: empty.
    pub sources: Vec<SourceConfig>,
    /// JSON-lines consumers: "stdout", "udp:IP:PORT", "tcp:IP:PORT", "mqtt://HOST:PORT/PREFIX"
    /// (an MQTT broker, see [`MqttUrl`]) (schema imucald.live/1). Default: none.
    pub publish: Vec<String>,
    /// Where calibration files go (JSON + ArduPilot/PX4/Fusion exports); loaded at start and
    /// printed then. Default: the per-user state directory's `imucald/calibration`
    /// (`$XDG_STATE_HOME`, else `~/.local/state`, on Linux; the local data directory elsewhere),
    /// or `calibration` in the working directory when there is no home.
    pub calibration_dir: String,
    /// Keep the latest report (imucald.report/1) here. Default: none.
    pub report: Option<String>,
    /// Heading and calibrated vectors, per second (Hz). Default: 5.
    pub heading_rate_hz: f64,
    /// MAG_CAL_PROGRESS and JSON progress, per second (Hz). Default: 1.
    pub progress_rate_hz: f64,
    /// MAVLink message of the heading. Default: "named_value_float".
    pub heading_message: HeadingMessage,
    /// Fused attitude (gyro + accel + mag orientation filter) per second: MAVLink per
    /// `attitude_message` and JSON `attitude` lines (Hz). At most [`MAX_RATE_HZ`]. Default: 10.
    pub attitude_rate_hz: f64,
    /// MAVLink message of the fused attitude. Default: "attitude_quaternion".
    pub attitude_message: AttitudeMessage,
    /// Also publish the fused attitude right after every N-th sample (0: off, the timer alone).
    /// For consumers that steer by it: sample-in to attitude-out is then the processing time only.
    /// Default: 0.
    pub attitude_every_samples: u32,
    /// Send calibrated vectors as DEBUG_VECT ("MAG_UT", "ACC_MPS2"). Default: true.
    pub debug_vect: bool,
    /// Coverage regions (of 100) that count as 100% complete in MAG_CAL_PROGRESS. Default: 80.
    pub progress_full_regions: usize,
    /// Send accepted parameters to the flight controller with PARAM_SET. Default: false.
    pub write_params: bool,
    /// Flight-stack convention of the parameters written. Default: "ardupilot".
    pub param_target: ParamTarget,
    /// Let a ground station change the service's own live settings with PARAM_SET (those its
    /// parameter list marks writable: `CAL_MAG_MODE`, `CAL_DEBUG_VECT`), for this run only. The
    /// service always answers the parameter protocol (PARAM_REQUEST_LIST/READ) with its settings
    /// and the calibration values in use; those values, and `CAL_WRITE_PARAMS`, are never
    /// writable. Default: false (every PARAM_SET is answered with the value unchanged).
    pub params_writable: bool,
    /// The flight controller's system id, for parameter writes and reads (of the first vehicle
    /// calibrated; a further vehicle's go to its own system id). Default: 1.
    pub target_system: u8,
    /// The flight controller's component id, for parameter writes and reads. Default: 1.
    pub target_component: u8,
    /// Our own MAVLink ids (1..=255 each; 0 is broadcast): every message we send carries them
    /// (about a further vehicle than the first: its own system id with our component id), and
    /// an inbound frame that carries the ids we send with is our own echoed back, dropped
    /// (counted as `own_echo`). Default: 1.
    pub system_id: u8,
    /// Our component id. Default: 191 (MAV_COMP_ID_ONBOARD_COMPUTER).
    pub component_id: u8,
    /// HEARTBEAT (MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID) per second on every MAVLink
    /// link, so ground stations and routers see the component (Hz); 0 = none. At most
    /// [`MAX_RATE_HZ`]. Default: 1.
    pub heartbeat_rate_hz: f64,
    /// Magnetometer calibration without a ground-station command. Either way the commands
    /// DO_START/ACCEPT/CANCEL_MAG_CAL addressed to our ids (or broadcast) start, accept and cancel a
    /// run. Default: "continuous".
    pub mag_cal: MagCalMode,
    /// The largest fitness (RMS residual of the fit, mGauss) a ground-station calibration run
    /// passes with: ArduPilot's COMPASS_CAL_FIT. As ArduPilot, compass 0 gets it as given when its
    /// COMPASS_EXTERNAL says external, every other compass (and compass 0 when internal or not
    /// known) twice it. A run whose fitness is above fails (MAG_CAL_REPORT status
    /// FAILED_RESIDUALS_HIGH). Continuous calibration is judged on held-out points instead.
    /// Default: 16 (1.6 uT; 32 for an internal or further compass).
    pub mag_cal_fit_mgauss: f64,
    /// How links map to vehicles: "separate" (each link and system id is a vehicle, calibrated on
    /// its own) or "merged" (every link is one vehicle). Default: "separate".
    pub links: Links,
    /// What to do with ArduPilot's magnetometer data, which comes with its calibration applied.
    /// Default: "undo".
    pub ardupilot_corrected_mag: ArdupilotCorrectedMag,
    /// Capacity of the queue from the links to the pipeline (frames and samples). Default: 4096.
    pub queue_capacity: usize,
    /// A link with no bytes for this long is reported silent, s. Default: 3.
    pub silent_after_s: f64,
    /// UDP sources: read the socket every this many ms, taking all that queued, instead of waking
    /// for every datagram (at 1 kHz waking costs more CPU than the samples); more often, down to
    /// 1 ms, while datagrams arrive fast enough to fill the kernel's buffer. 0 = wake per datagram;
    /// ignored (0) when `attitude_every_samples` is set. At most
    /// [`crate::io::link::UDP_POLL_MAX`] (200 ms). Default (not set): the period of the fastest
    /// periodic output (heading, attitude, progress; 100 ms with their defaults), as polling more
    /// often than anything reads the state buys no latency a consumer sees; see
    /// [`DaemonConfig::udp_poll`].
    pub udp_poll_ms: Option<f64>,
    /// Streams faster than this are averaged over equal blocks of samples to about this rate
    /// before the calibration and the attitude filter see them (a 1 kHz IMU in blocks of ten;
    /// [`crate::calib::blockmean`] says why nothing is lost); slower ones pass unchanged. Hz;
    /// 0 = every sample; ignored (0) when `attitude_every_samples` is set. Default: 100.
    pub pipeline_rate_hz: f64,
}

impl DaemonConfig {
    /// How often UDP sources are read ([`DaemonConfig::udp_poll_ms`]); zero: every datagram wakes
    /// the service (set so, or `attitude_every_samples` set). Not set: the period of the fastest
    /// periodic output, at most [`crate::io::link::UDP_POLL_MAX`] and at least 1 ms.
    pub fn udp_poll(&self) -> std::time::Duration {
        use std::time::Duration;
        if self.attitude_every_samples > 0 {
            return Duration::ZERO;
        }
        match self.udp_poll_ms {
            Some(ms) if ms.is_finite() && ms > 0.0 => {
                Duration::from_secs_f64(ms.min(1.0e6) / 1000.0).min(crate::io::link::UDP_POLL_MAX)
            }
            Some(_) => Duration::ZERO,
            None => {
                let fastest_hz = [
                    self.heading_rate_hz,
                    self.attitude_rate_hz,
                    self.progress_rate_hz,
                ]
                .into_iter()
                .filter(|hz| hz.is_finite() && *hz > 0.0)
                .fold(0.0, f64::max);
                let period_s = if fastest_hz > 0.0 {
                    1.0 / fastest_hz
                } else {
                    f64::INFINITY
                };
                Duration::from_secs_f64(period_s.clamp(0.001, 1.0e6))
                    .min(crate::io::link::UDP_POLL_MAX)
            }
        }
    }
}

/// The per-user state directory's `imucald/calibration` (see [`DaemonConfig::calibration_dir`]).
pub(crate) fn default_calibration_dir() -> String {
    dirs::state_dir()
        .or_else(dirs::data_local_dir)
        .map(|d| d.join("imucald").join("calibration").display().to_string())
        .unwrap_or_else(|| "calibration".into())
}

impl Default for DaemonConfig {
    fn default() -> Self {
        DaemonConfig {
            sources: vec![],
            publish: vec![],
            calibration_dir: default_calibration_dir(),
            report: None,
            heading_rate_hz: 5.0,
            progress_rate_hz: 1.0,
            heading_message: HeadingMessage::NamedValueFloat,
            attitude_rate_hz: 10.0,
            attitude_message: AttitudeMessage::AttitudeQuaternion,
            attitude_every_samples: 0,
            debug_vect: true,
            progress_full_regions: 80,
            write_params: false,
            param_target: ParamTarget::Ardupilot,
            params_writable: false,
            target_system: 1,
            target_component: 1,
            system_id: 1,
            component_id: 191,
            heartbeat_rate_hz: 1.0,
            mag_cal: MagCalMode::Continuous,
            mag_cal_fit_mgauss: 16.0,
            links: Links::Separate,
            ardupilot_corrected_mag: ArdupilotCorrectedMag::Undo,
            queue_capacity: 4096,
            silent_after_s: 3.0,
            udp_poll_ms: None,
            pipeline_rate_hz: 100.0,
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct OrientationConfig {
    /// MAV_SENSOR_ORIENTATION name of the IMU in the body frame, e.g. "ROTATION_NONE", "ROTATION_YAW_90".
    /// Default: "ROTATION_NONE".
    pub sensor: String,
}

impl Default for OrientationConfig {
    fn default() -> Self {
        OrientationConfig {
            sensor: "ROTATION_NONE".into(),
        }
    }
}

/// The dotted key a TOML line sets (`daemon.mag_cal` for `mag_cal = ...` under `[daemon]`), for
/// errors; "toml" when the line sets none.
fn key_at_line(text: &str, line: usize) -> String {
    let lines: Vec<&str> = text.lines().collect();
    let Some(here) = lines.get(line.saturating_sub(1)) else {
        return "toml".into();
    };
    let Some((key, _)) = here.split_once('=') else {
        return "toml".into();
    };
    let key = key.trim().trim_matches('"');
    let table = lines[..line - 1]
        .iter()
        .rev()
        .map(|l| l.trim_start_matches('\u{feff}').trim())
        .find(|l| l.starts_with('['))
        .map(|l| l.trim_matches(|c| c == '[' || c == ']').trim());
    match table {
        Some(t) if !t.is_empty() => format!("{t}.{key}"),
        _ => key.to_string(),
    }
}

/// Highest publication rate of the live service, per second (the timers need a non-zero period).
pub(crate) const MAX_RATE_HZ: f64 = 1000.0;

/// `daemon.heading_message`: the MAVLink message of the heading.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum HeadingMessage {
    /// NAMED_VALUE_FLOAT "HEADING" (deg).
    NamedValueFloat,
    /// ATTITUDE (roll, pitch, yaw in rad).
    Attitude,
    /// None (JSON lines only).
    None,
}

/// `daemon.attitude_message`: the MAVLink message of the fused attitude.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AttitudeMessage {
    /// ATTITUDE_QUATERNION.
    AttitudeQuaternion,
    /// ATTITUDE.
    Attitude,
    /// Both.
    Both,
    /// None (JSON lines only).
    None,
}

impl AttitudeMessage {
    pub fn quaternion(self) -> bool {
        matches!(
            self,
            AttitudeMessage::AttitudeQuaternion | AttitudeMessage::Both
        )
    }
    pub(crate) fn euler(self) -> bool {
        matches!(self, AttitudeMessage::Attitude | AttitudeMessage::Both)
    }
}

/// `daemon.param_target`: whose parameter names and conventions a parameter write uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ParamTarget {
    /// COMPASS_OFS/DIA/ODI (COMPASS_OFS2 ... for further compasses).
    Ardupilot,
    /// CAL_MAGn_*.
    Px4,
}

/// `daemon.mag_cal`: magnetometer calibration without a ground-station command.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MagCalMode {
    /// Passing fits are installed and written as they come.
    Continuous,
    /// Only a run started by MAV_CMD_DO_START_MAG_CAL calibrates the magnetometer.
    OnCommand,
}

/// `daemon.links`: how links map to vehicles.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Links {
    /// Each link and system id is a vehicle with its own converter (instances, clocks) and
    /// ArduPilot state; the first vehicle whose IMU data arrives is the one calibrated (the others'
    /// samples are counted as `other_vehicle`).
    Separate,
    /// Every link is one vehicle (one sensor seen over several links).
    Merged,
}

/// `daemon.ardupilot_corrected_mag`: ArduPilot streams its magnetometer with its calibration applied.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ArdupilotCorrectedMag {
    /// Undo it (reading the COMPASS_* parameters of each compass) before fitting.
    Undo,
    /// Do not fit such data (the magnetometer samples are dropped, counted).
    Refuse,
}

fn err(key: &str, message: impl Into<String>) -> Error {
    Error::Config {
        key: key.to_string(),
        message: message.into(),
    }
}

impl Config {
    /// The settings the calibration pipeline reads.
    pub fn calib(&self) -> CalibSettings {
        CalibSettings {
            fit: self.fit.clone(),
            accept: self.accept,
            gate: self.gate,
            sensor_orientation: self.orientation.sensor.clone(),
            accel_units: self.input.accel_units,
        }
    }

    /// Parse and validate TOML text.
    pub fn from_toml_str(text: &str) -> Result<Config, Error> {
        let cfg: Config = toml::from_str(text).map_err(|e| {
            let msg = e.message().to_string();
            match e.span() {
                Some(s) => {
                    let line = text[..s.start.min(text.len())].matches('\n').count() + 1;
                    err(&key_at_line(text, line), format!("{msg} (line {line})"))
                }
                None => err("toml", msg),
            }
        })?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Read, parse and validate a TOML file.
    pub fn load(path: &std::path::Path) -> Result<Config, Error> {
        let text = std::fs::read_to_string(path).map_err(|source| Error::Read {
            path: path.to_path_buf(),
            source,
        })?;
        Config::from_toml_str(&text).map_err(|e| match e {
            Error::Config { key, message } => Error::Config {
                key: format!("{}: {key}", path.display()),
                message,
            },
            other => other,
        })
    }

    /// The orientation filter's settings for this configuration: world NED, the given declination
    /// (true north) or none (magnetic north), gravity as the fit's. Used by `run` and `replay`.
    pub(crate) fn fusion_config(
        &self,
        declination_deg: Option<f64>,
    ) -> crate::attitude::fusion::FusionConfig {
        crate::attitude::fusion::FusionConfig {
            world: crate::attitude::fusion::WorldFrame::Ned,
            use_mag: true,
            declination_deg: declination_deg.unwrap_or(0.0),
            gravity_mps2: self.fit.gravity_mps2,
            ..Default::default()
        }
    }

    /// The configured place, dated today (by this computer's clock) when `[place]` gives no date:
    /// the live service's field.
    pub(crate) fn place_today(&self) -> Option<Place> {
        let today = crate::io::clock::today().iso();
        self.place.as_ref().map(|p| p.dated(&today))
    }

    /// Declination (deg, east positive) of the configured place (today, when it gives no date), or
    /// `None` without a place.
    pub fn declination_deg(&self) -> Result<Option<f64>, Error> {
        match &self.place_today() {
            Some(p) => Ok(Some(
                crate::attitude::earth_field(p)
                    .map_err(|m| err("place", m))?
                    .declination_deg,
            )),
            None => Ok(None),
        }
    }

    /// Range and name checks; each error names the key and the fix.
    pub fn validate(&self) -> Result<(), Error> {
        self.validate_fit()?;
        self.validate_daemon()?;
        self.validate_ui()?;
        self.validate_tempcal()?;
        crate::attitude::sensor_rotation(&self.orientation.sensor)
            .map_err(|m| err("orientation.sensor", m))?;
        if let Some(p) = &self.place_today() {
            crate::attitude::earth_field(p).map_err(|m| err("place", m))?;
        }
        Ok(())
    }

    /// `[tempcal]`: lengths and limits above 0, shares between 0 and 1.
    fn validate_tempcal(&self) -> Result<(), Error> {
        let t = &self.tempcal;
        for (key, v) in [
            ("tempcal.block_s", t.block_s),
            ("tempcal.accel_std_max_mps2", t.accel_std_max_mps2),
            ("tempcal.gyro_std_max_rad_s", t.gyro_std_max_rad_s),
            ("tempcal.max_rotation_deg", t.max_rotation_deg),
            ("tempcal.bin_c", t.bin_c),
            ("tempcal.min_span_c", t.min_span_c),
            ("tempcal.held_out_band_c", t.held_out_band_c),
        ] {
            positive(key, v)?;
        }
        for (key, v) in [
            ("tempcal.max_moving_fraction", t.max_moving_fraction),
            ("tempcal.max_thin_fraction", t.max_thin_fraction),
        ] {
            if !(0.0..=1.0).contains(&v) {
                return Err(err(key, format!("must be between 0 and 1, got {v}")));
            }
        }
        if t.min_per_bin == 0 {
            return Err(err("tempcal.min_per_bin", "must be 1 or more readings"));
        }
        Ok(())
    }

    /// `[ui]`: an address, loopback unless another is allowed.
    fn validate_ui(&self) -> Result<(), Error> {
        if let Some(l) = &self.ui.listen {
            let addr: std::net::SocketAddr = l
                .parse()
                .map_err(|_| err("ui.listen", format!("`{l}` is not IP:PORT")))?;
            if !addr.ip().is_loopback() && !self.ui.allow_remote {
                return Err(err(
                    "ui.listen",
                    format!("`{l}` is not a loopback address; set ui.allow_remote = true to serve the page (no authentication) beyond this machine"),
                ));
            }
        }
        Ok(())
    }

    /// `[fit]`, `[gate]` and `[accept]`.
    fn validate_fit(&self) -> Result<(), Error> {
        positive("fit.refit_every_s", self.fit.refit_every_s)?;
        positive("fit.gravity_mps2", self.fit.gravity_mps2)?;
        positive("fit.min_separation_deg", self.fit.min_separation_deg)?;
        if !(self.fit.centre_min_spread_radii > 0.0 && self.fit.centre_min_spread_radii < 1.0) {
            return Err(err(
                "fit.centre_min_spread_radii",
                format!(
                    "must be between 0 and 1 field radii, got {}",
                    self.fit.centre_min_spread_radii
                ),
            ));
        }
        positive("fit.prefilter_q", self.fit.prefilter_q)?;
        positive("fit.prefilter_r", self.fit.prefilter_r)?;
        positive("gate.window_s", self.gate.window_s)?;
        positive("gate.threshold_factor", self.gate.threshold_factor)?;
        if !(self.gate.min_pose_s >= 0.0) {
            return Err(err("gate.min_pose_s", "must be zero or more seconds"));
        }
        if let Some(t) = self.gate.threshold {
            positive("gate.threshold", t)?;
        }
        for (name, l) in [
            ("accept.mag", &self.accept.mag),
            ("accept.accel", &self.accept.accel),
        ] {
            for (key, v) in [
                ("min_radius", l.min_radius),
                ("max_offset", l.max_offset),
                ("min_diag", l.min_diag),
                ("max_offdiag", l.max_offdiag),
                ("max_rms_ratio", l.max_rms_ratio),
            ] {
                if !(v >= 0.0) {
                    return Err(err(
                        &format!("{name}.{key}"),
                        format!("must be 0 or more (it is {v})"),
                    ));
                }
            }
            if !(l.min_radius < l.max_radius) {
                return Err(err(
                    &format!("{name}.min_radius"),
                    "must be below max_radius",
                ));
            }
            if !(l.min_diag < l.max_diag) {
                return Err(err(&format!("{name}.min_diag"), "must be below max_diag"));
            }
            if l.min_filled_regions > crate::calib::coverage::REGIONS {
                return Err(err(
                    &format!("{name}.min_filled_regions"),
                    "there are only 100 regions",
                ));
            }
        }
        Ok(())
    }

    /// `[daemon]`: sources, consumers, rates, ids.
    fn validate_daemon(&self) -> Result<(), Error> {
        let d = &self.daemon;
        for (i, src) in d.sources.iter().enumerate() {
            crate::io::link::Address::parse(&src.address)
                .map_err(|e| err(&format!("daemon.sources[{i}].address"), e.to_string()))?;
            if src.payload == PayloadKind::Csv && src.fields.is_empty() {
                return Err(err(&format!("daemon.sources[{i}].fields"), "a csv source needs its column order, e.g. fields = [\"ax\", \"ay\", \"az\", \"mx\", \"my\", \"mz\"]"));
            }
        }
        for (i, p) in d.publish.iter().enumerate() {
            PublishTarget::parse(p).map_err(|e| err(&format!("daemon.publish[{i}]"), e))?;
        }
        let rate = |key: &str, v: f64| {
            if v > 0.0 && v <= MAX_RATE_HZ {
                Ok(())
            } else {
                Err(err(
                    key,
                    format!("must be a rate above 0 and at most {MAX_RATE_HZ} per second, got {v}"),
                ))
            }
        };
        rate("daemon.heading_rate_hz", d.heading_rate_hz)?;
        rate("daemon.progress_rate_hz", d.progress_rate_hz)?;
        rate("daemon.attitude_rate_hz", d.attitude_rate_hz)?;
        if d.heartbeat_rate_hz != 0.0 {
            rate("daemon.heartbeat_rate_hz", d.heartbeat_rate_hz)?;
        }
        for (key, id) in [
            ("daemon.system_id", d.system_id),
            ("daemon.component_id", d.component_id),
        ] {
            if id == 0 {
                return Err(err(key, "0 is the broadcast id: use 1..=255"));
            }
        }
        positive("daemon.silent_after_s", d.silent_after_s)?;
        positive("daemon.mag_cal_fit_mgauss", d.mag_cal_fit_mgauss)?;
        let poll_max_ms = crate::io::link::UDP_POLL_MAX.as_secs_f64() * 1000.0;
        if let Some(ms) = d.udp_poll_ms.filter(|ms| !(0.0..=poll_max_ms).contains(ms)) {
            return Err(err(
                "daemon.udp_poll_ms",
                format!(
                    "must be between 0 (wake per datagram) and {poll_max_ms} ms (a 1 kHz stream \
                     must not fill the kernel's receive buffer between two reads), got {ms}"
                ),
            ));
        }
        if !(d.pipeline_rate_hz.is_finite() && (0.0..=100_000.0).contains(&d.pipeline_rate_hz)) {
            return Err(err(
                "daemon.pipeline_rate_hz",
                format!(
                    "must be between 0 (every sample) and 100000 Hz, got {}",
                    d.pipeline_rate_hz
                ),
            ));
        }
        if d.heading_message == HeadingMessage::Attitude && d.attitude_message.euler() {
            return Err(err(
                "daemon.attitude_message",
                "it sends ATTITUDE, which heading_message = \"attitude\" already sends: use attitude_quaternion or none here, or another heading_message",
            ));
        }
        if d.queue_capacity == 0 || d.progress_full_regions == 0 || d.progress_full_regions > 100 {
            return Err(err(
                "daemon.queue_capacity",
                "queue_capacity must be > 0 and progress_full_regions in 1..=100",
            ));
        }
        if d.calibration_dir.is_empty() {
            return Err(err("daemon.calibration_dir", "must name a directory"));
        }
        Ok(())
    }
}

/// `Ok` for a finite number above 0; otherwise an error naming `key`.
fn positive(key: &str, v: f64) -> Result<(), Error> {
    if v > 0.0 && v.is_finite() {
        Ok(())
    } else {
        Err(err(key, format!("must be a positive number, got {v}")))
    }
}

/// Where a `publish` entry sends the JSON lines. The one parser of those entries: the
/// configuration's check and the service's sinks both read them through [`PublishTarget::parse`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum PublishTarget {
    /// `stdout`.
    Stdout,
    /// `udp:IP:PORT`: one datagram per line.
    Udp(std::net::SocketAddr),
    /// `tcp:IP:PORT`: a stream of lines to a listener.
    Tcp(std::net::SocketAddr),
    /// `mqtt://HOST:PORT/PREFIX`.
    Mqtt(MqttUrl),
}

impl PublishTarget {
    /// Parse one entry; the error says what the forms are, or what is wrong with an MQTT URL.
    pub fn parse(spec: &str) -> Result<PublishTarget, String> {
        if spec.starts_with(MqttUrl::SCHEME) {
            return MqttUrl::parse(spec).map(PublishTarget::Mqtt);
        }
        let addr = |a: &str| a.parse::<std::net::SocketAddr>().ok();
        let target = if spec == "stdout" {
            Some(PublishTarget::Stdout)
        } else if let Some(a) = spec.strip_prefix("udp:") {
            addr(a).map(PublishTarget::Udp)
        } else if let Some(a) = spec.strip_prefix("tcp:") {
            addr(a).map(PublishTarget::Tcp)
        } else {
            None
        };
        target.ok_or_else(|| {
            format!("`{spec}` is not stdout, udp:IP:PORT, tcp:IP:PORT or mqtt://HOST:PORT/PREFIX")
        })
    }
}

/// A `publish` entry `mqtt://HOST:PORT/PREFIX`: an MQTT broker reached over plain TCP (no TLS)
/// and the topic levels every line's topic starts with (`PREFIX/<vehicle>/<type>`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct MqttUrl {
    /// A host name, an IPv4 address or an IPv6 address (written in brackets in the URL).
    pub host: String,
    /// The broker's TCP port. Default (none in the URL): [`MqttUrl::DEFAULT_PORT`].
    pub port: u16,
    /// One or more topic levels, without wildcards (`+`, `#`), empty levels or a leading `$`.
    pub prefix: String,
}

impl MqttUrl {
    pub(crate) const SCHEME: &'static str = "mqtt://";
    /// MQTT's registered port for plain TCP.
    pub(crate) const DEFAULT_PORT: u16 = 1883;

    /// Parse `mqtt://HOST[:PORT]/PREFIX`; the error says what is wrong.
    pub fn parse(url: &str) -> Result<MqttUrl, String> {
        let bad = |why: &str| format!("`{url}` is not mqtt://HOST:PORT/PREFIX: {why}");
        let rest = url
            .strip_prefix(Self::SCHEME)
            .ok_or_else(|| bad("no mqtt://"))?;
        let (authority, prefix) = rest.split_once('/').ok_or_else(|| bad("no topic prefix"))?;
        let (host, port) = Self::split_authority(authority).ok_or_else(|| bad("bad HOST:PORT"))?;
        if prefix.is_empty() || prefix.split('/').any(str::is_empty) {
            return Err(bad("the topic prefix has an empty level"));
        }
        if prefix.contains(['+', '#', '\0']) || prefix.starts_with('$') {
            return Err(bad(
                "the topic prefix has a wildcard (+, #), a NUL or a leading $",
            ));
        }
        Ok(MqttUrl {
            host,
            port,
            prefix: prefix.to_string(),
        })
    }

    /// `host`, `host:port`, `[v6]` or `[v6]:port` into the host and the port (never 0).
    fn split_authority(a: &str) -> Option<(String, u16)> {
        let (host, port) = match a.strip_prefix('[') {
            Some(v6) => {
                let (h, after) = v6.split_once(']')?;
                h.parse::<std::net::Ipv6Addr>().ok()?;
                (h, after.strip_prefix(':'))
            }
            None => match a.split_once(':') {
                Some((h, p)) => (h, Some(p)),
                None => (a, None),
            },
        };
        let name_ok = |h: &str| {
            !h.is_empty()
                && h.chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '.' || c == '-' || c == ':')
        };
        let port = match port {
            Some(p) => p.parse::<u16>().ok().filter(|&p| p > 0)?,
            None => Self::DEFAULT_PORT,
        };
        name_ok(host).then(|| (host.to_string(), port))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn config_mqtt_urls_are_parsed_and_bad_ones_say_why() {
        let u = MqttUrl::parse("mqtt://127.0.0.1:1884/fleet/north").unwrap();
        assert_eq!(
            (u.host.as_str(), u.port, u.prefix.as_str()),
            ("127.0.0.1", 1884, "fleet/north")
        );
        let u = MqttUrl::parse("mqtt://broker.local/fleet").unwrap();
        assert_eq!(
            (u.host.as_str(), u.port),
            ("broker.local", MqttUrl::DEFAULT_PORT)
        );
        let u = MqttUrl::parse("mqtt://[::1]:1885/f").unwrap();
        assert_eq!((u.host.as_str(), u.port), ("::1", 1885));
        for (bad, why) in [
            ("mqtt://127.0.0.1:1883", "no topic prefix"),
            ("mqtt://127.0.0.1:1883/", "empty level"),
            ("mqtt://127.0.0.1:1883/a//b", "empty level"),
            ("mqtt://127.0.0.1:1883/fleet/#", "wildcard"),
            ("mqtt://127.0.0.1:1883/+/x", "wildcard"),
            ("mqtt://127.0.0.1:1883/$SYS", "leading $"),
            ("mqtt://127.0.0.1:0/fleet", "HOST:PORT"),
            ("mqtt://127.0.0.1:99999/fleet", "HOST:PORT"),
            ("mqtt://:1883/fleet", "HOST:PORT"),
            ("mqtt://[::1/fleet", "HOST:PORT"),
            ("mqtt://user@host/fleet", "HOST:PORT"),
        ] {
            let e = MqttUrl::parse(bad).expect_err(bad);
            assert!(e.contains(why), "{bad}: {e}");
        }
        let mut cfg = Config::default();
        cfg.daemon.publish = vec!["mqtt://127.0.0.1:1883/fleet".into()];
        cfg.validate().unwrap();
        cfg.daemon.publish = vec!["mqtt://127.0.0.1:1883/fleet/#".into()];
        let e = cfg.validate().unwrap_err().to_string();
        assert!(
            e.contains("daemon.publish[0]") && e.contains("wildcard"),
            "{e}"
        );
    }

    /// Every setting says its default (and its unit where it has one) in its documentation, as
    /// VQF documents its parameters: a new key without one fails here.
    #[test]
    fn every_setting_documents_its_default() {
        let files: [(&str, &str, &[&str]); 12] = [
            (
                "config.rs",
                include_str!("config.rs"),
                &[
                    "Config",
                    "SourceConfig",
                    "DaemonConfig",
                    "OrientationConfig",
                    "UiConfig",
                ],
            ),
            (
                "calib/settings.rs",
                include_str!("calib/settings.rs"),
                &["FitConfig", "AcceptLimits", "AcceptConfig", "CalibSettings"],
            ),
            (
                "io/sources.rs",
                include_str!("io/sources.rs"),
                &["InputConfig"],
            ),
            (
                "calib/gate.rs",
                include_str!("calib/gate.rs"),
                &["GateConfig"],
            ),
            (
                "attitude/fusion/mod.rs",
                include_str!("attitude/fusion/mod.rs"),
                &["FusionConfig"],
            ),
            (
                "attitude/fusion/kalman.rs",
                include_str!("attitude/fusion/kalman.rs"),
                &["ProcessConfig", "BiasConfig"],
            ),
            (
                "attitude/fusion/tilt.rs",
                include_str!("attitude/fusion/tilt.rs"),
                &["TiltConfig"],
            ),
            (
                "attitude/fusion/heading.rs",
                include_str!("attitude/fusion/heading.rs"),
                &["HeadingConfig"],
            ),
            (
                "attitude/fusion/magref.rs",
                include_str!("attitude/fusion/magref.rs"),
                &["MagRefConfig"],
            ),
            (
                "attitude/fusion/delay.rs",
                include_str!("attitude/fusion/delay.rs"),
                &["MagDelayConfig"],
            ),
            (
                "attitude/fusion/scale.rs",
                include_str!("attitude/fusion/scale.rs"),
                &["GyroScaleConfig"],
            ),
            (
                "attitude/fusion/rest.rs",
                include_str!("attitude/fusion/rest.rs"),
                &["RestConfig"],
            ),
        ];
        let mut fields = 0;
        for (file, text, structs) in files {
            for st in structs {
                let start = text.find(&format!("pub struct {st} {{")).unwrap();
                let len = text[start..].find("\n}\n").unwrap();
                let mut doc = String::new();
                for line in text[start..start + len].lines().skip(1) {
                    let t = line.trim();
                    if let Some(d) = t.strip_prefix("///") {
                        doc.push_str(d);
                    } else if t.starts_with("pub ") {
                        assert!(
                            doc.contains("Default") || doc.contains("Required"),
                            "{file}: {st}: `{t}` does not say its default"
                        );
                        fields += 1;
                        doc.clear();
                    } else if !t.starts_with("#[") {
                        doc.clear();
                    }
                }
            }
        }
        assert!(fields > 60, "{fields} settings read");
    }

    #[test]
    fn fusion_config_uses_declination_ned_and_the_fit_gravity() {
        let mut cfg = Config::default();
        cfg.fit.gravity_mps2 = 9.81;
        let f = cfg.fusion_config(Some(12.5));
        assert_eq!(f.world, crate::attitude::fusion::WorldFrame::Ned);
        assert_eq!(f.declination_deg, 12.5);
        assert_eq!(f.gravity_mps2, 9.81);
        assert!(f.use_mag);
        assert_eq!(cfg.fusion_config(None).declination_deg, 0.0);
    }

    #[test]
    fn defaults_validate() {
        Config::default().validate().unwrap();
        let c = Config::from_toml_str("").unwrap();
        assert_eq!(c, Config::default());
        let c = Config::from_toml_str("[accept.mag]\nmax_rms_ratio = 0.1\n").unwrap();
        assert_eq!(c.accept.mag.max_rms_ratio, 0.1);
        assert_eq!(c.accept.mag.max_radius, 95.0);
        assert_eq!(c.accept.accel, AcceptConfig::default().accel);
    }

    #[test]
    fn errors_name_the_key() {
        let e = Config::from_toml_str("[fit]\nmag_modle = \"sym9\"\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("mag_modle") && e.contains("line 2"), "{e}");
        let e = Config::from_toml_str("[fit]\nmag_model = \"sym10\"\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("fit.mag_model") && e.contains("sym9"), "{e}");
        let e = Config::from_toml_str("[gate]\nwindow_s = -1\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("gate.window_s"), "{e}");
        let e = Config::from_toml_str("[orientation]\nsensor = \"UPSIDE_DOWN\"\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("orientation.sensor"), "{e}");
        let e = Config::from_toml_str(
            "[place]\nlatitude_deg = 45.0\nlongitude_deg = 7.0\ndate = \"2031-01-01\"\n",
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("place"), "{e}");
    }

    #[test]
    fn heartbeat_rate_and_own_ids_validate() {
        let d = DaemonConfig::default();
        assert_eq!(
            (d.system_id, d.component_id, d.heartbeat_rate_hz),
            (1, 191, 1.0)
        );
        let c = Config::from_toml_str("[daemon]\nheartbeat_rate_hz = 0.0\n").unwrap();
        assert_eq!(c.daemon.heartbeat_rate_hz, 0.0);
        for bad in ["-1.0", "nan", "1e12"] {
            let e = Config::from_toml_str(&format!("[daemon]\nheartbeat_rate_hz = {bad}\n"))
                .unwrap_err()
                .to_string();
            assert!(e.contains("daemon.heartbeat_rate_hz"), "{bad}: {e}");
        }
        for key in ["system_id", "component_id"] {
            let e = Config::from_toml_str(&format!("[daemon]\n{key} = 0\n"))
                .unwrap_err()
                .to_string();
            assert!(
                e.contains(&format!("daemon.{key}")) && e.contains("broadcast"),
                "{e}"
            );
        }
        assert_eq!(d.mag_cal, MagCalMode::Continuous);
        let e = Config::from_toml_str("[daemon]\nmag_cal = \"manual\"\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("daemon.mag_cal") && e.contains("on_command"),
            "{e}"
        );
    }

    #[test]
    fn attitude_keys_default_parse_and_validate() {
        let d = DaemonConfig::default();
        assert_eq!(d.attitude_rate_hz, 10.0);
        assert_eq!(d.attitude_message, AttitudeMessage::AttitudeQuaternion);
        let names = ["attitude_quaternion", "attitude", "both", "none"];
        use AttitudeMessage as A;
        for (m, want) in names
            .iter()
            .zip([A::AttitudeQuaternion, A::Attitude, A::Both, A::None])
        {
            let c = Config::from_toml_str(&format!(
                "[daemon]\nattitude_rate_hz = 25.0\nattitude_message = \"{m}\"\n"
            ))
            .unwrap();
            assert_eq!(c.daemon.attitude_message, want);
            assert_eq!(c.daemon.attitude_rate_hz, 25.0);
        }
        // A bad message names the key and the values allowed.
        let e = Config::from_toml_str("[daemon]\nattitude_message = \"quaternion\"\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("daemon.attitude_message"), "{e}");
        for m in names {
            assert!(e.contains(m), "{e} lacks {m}");
        }
        // Rates: positive, finite, at most MAX_RATE_HZ (a zero timer period would panic).
        for bad in ["0.0", "-5.0", "nan", "inf", "1e12"] {
            let e = Config::from_toml_str(&format!("[daemon]\nattitude_rate_hz = {bad}\n"))
                .unwrap_err()
                .to_string();
            assert!(e.contains("daemon.attitude_rate_hz"), "{bad}: {e}");
        }
        let e = Config::from_toml_str("[daemon]\nheading_rate_hz = 1e12\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("daemon.heading_rate_hz"), "{e}");
        Config::from_toml_str("[daemon]\nattitude_rate_hz = 1000.0\n").unwrap();
        // ATTITUDE from two publishers would clash: heading_message = "attitude" excludes it here.
        for m in ["attitude", "both"] {
            let e = Config::from_toml_str(&format!(
                "[daemon]\nheading_message = \"attitude\"\nattitude_message = \"{m}\"\n"
            ))
            .unwrap_err()
            .to_string();
            assert!(e.contains("daemon.attitude_message"), "{e}");
        }
        Config::from_toml_str(
            "[daemon]\nheading_message = \"attitude\"\nattitude_message = \"attitude_quaternion\"\n",
        )
        .unwrap();
        // Unknown keys stay errors.
        let e = Config::from_toml_str("[daemon]\nattitude_hz = 5.0\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("attitude_hz"), "{e}");
    }

    /// The UDP poll follows the fastest periodic output unless set; an explicit one is taken as it
    /// is within 0..=200 ms; the latency mode never polls.
    #[test]
    fn udp_poll_defaults_to_the_fastest_output() {
        let ms = std::time::Duration::from_millis;
        let c = Config::from_toml_str("").unwrap();
        assert_eq!(c.daemon.udp_poll_ms, None);
        assert_eq!(c.daemon.udp_poll(), ms(100));
        let c = Config::from_toml_str(
            "[daemon]
heading_rate_hz = 20.0
",
        )
        .unwrap();
        assert_eq!(c.daemon.udp_poll(), ms(50));
        // Slow outputs: no longer than the longest poll allowed.
        let c = Config::from_toml_str(
            "[daemon]
heading_rate_hz = 1.0
attitude_rate_hz = 2.0
progress_rate_hz = 0.5
",
        )
        .unwrap();
        assert_eq!(c.daemon.udp_poll(), crate::io::link::UDP_POLL_MAX);
        let c = Config::from_toml_str(
            "[daemon]
udp_poll_ms = 20.0
",
        )
        .unwrap();
        assert_eq!(c.daemon.udp_poll(), ms(20));
        let c = Config::from_toml_str(
            "[daemon]
udp_poll_ms = 0.0
",
        )
        .unwrap();
        assert_eq!(c.daemon.udp_poll(), ms(0));
        let c = Config::from_toml_str(
            "[daemon]
attitude_every_samples = 10
",
        )
        .unwrap();
        assert_eq!(c.daemon.udp_poll(), ms(0));
        for bad in ["-1.0", "nan", "200.5", "1e12"] {
            let e = Config::from_toml_str(&format!("[daemon]\nudp_poll_ms = {bad}\n"))
                .unwrap_err()
                .to_string();
            assert!(e.contains("daemon.udp_poll_ms") && e.contains("200"), "{e}");
        }
    }
}
