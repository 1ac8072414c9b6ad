//! Our component's parameters, served over the MAVLink parameter protocol (PARAM_REQUEST_LIST,
//! PARAM_REQUEST_READ, PARAM_SET), so a ground station's parameter list shows the service: its
//! settings and the calibration values in use.
//!
//! Every value is sent as REAL32. Names (at most 16 characters):
//!
//! | name | meaning | unit | writable |
//! | --- | --- | --- | --- |
//! | `CAL_MAG_MODE` | `daemon.mag_cal`: 0 continuous, 1 on_command | - | with `daemon.params_writable` |
//! | `CAL_DEBUG_VECT` | `daemon.debug_vect`: 0 off, 1 on | - | with `daemon.params_writable` |
//! | `CAL_WRITE_PARAMS` | `daemon.write_params` | - | never (the config alone enables writes to a flight controller) |
//! | `CAL_PARAMS_WRITE` | `daemon.params_writable` | - | never |
//! | `CAL_HDG_RATE`, `CAL_ATT_RATE` | heading and attitude rates | Hz | never (fixed at start) |
//! | `CAL_REFIT_S` | `fit.refit_every_s` | s | never |
//! | `MAGk_OK` | compass `k` (its flight-stack index) has a calibration in use | - | never |
//! | `MAGk_OFS_X/Y/Z` | its offset (calibrated = M (raw - offset)) | uT | never |
//! | `MAGk_M_XX` .. `MAGk_M_ZZ` | its matrix M, row then column | - | never |
//! | `MAGk_RADIUS`, `MAGk_RMS` | field radius, fit RMS residual | uT | never |
//! | `ACC_OK`, `ACC_OFS_*`, `ACC_M_**` | the accelerometer's, as the compass's | m/s^2 | never |
//! | `GYR_OK`, `GYR_BIAS_X/Y/Z` | gyro bias at rest | rad/s | never |
//!
//! The list never changes shape: every name is there from the start, in a fixed order (the
//! settings, `MAG0` to `MAG2`, `ACC`, `GYR`), so the count and each name's index stay the same for
//! the whole run, as a ground station that fills its list by index expects. A value not known
//! reads NaN: a sensor with no calibration in use (its `_OK` 0), and a value the data did not
//! determine (a planar fit's z offset and z soft iron). A compass numbered 3 or more is not served
//! (ArduPilot has three). A refused PARAM_SET is answered, as the protocol asks, with the unchanged
//! value, and a STATUSTEXT says why.
//! Settings changed by PARAM_SET last for this run only.

use super::*;
use crate::calib::export::Unknowns;
use crate::io::mavout::ParamRequest;
use crate::types::CalUnits;

/// One parameter as served.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Param {
    pub name: String,
    pub value: f32,
}

/// The settings a ground station may change (with `daemon.params_writable`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Writable {
    MagMode,
    DebugVect,
}

impl Writable {
    fn of(name: &str) -> Option<Writable> {
        match name {
            "CAL_MAG_MODE" => Some(Writable::MagMode),
            "CAL_DEBUG_VECT" => Some(Writable::DebugVect),
            _ => None,
        }
    }
}

/// Why a PARAM_SET was not applied.
#[derive(Debug, Clone, PartialEq)]
enum Refused {
    /// The parameter is read only (a calibration value, or a setting fixed at start).
    ReadOnly,
    /// `daemon.params_writable` is off.
    NotEnabled,
    /// The value is not one the setting takes.
    BadValue(&'static str),
}

fn flag(b: bool) -> f32 {
    if b {
        1.0
    } else {
        0.0
    }
}

/// The service's settings as parameters.
fn settings(cfg: &Config) -> Vec<Param> {
    let d = &cfg.daemon;
    [
        ("CAL_MAG_MODE", flag(d.mag_cal == MagCalMode::OnCommand)),
        ("CAL_DEBUG_VECT", flag(d.debug_vect)),
        ("CAL_WRITE_PARAMS", flag(d.write_params)),
        ("CAL_PARAMS_WRITE", flag(d.params_writable)),
        ("CAL_HDG_RATE", d.heading_rate_hz as f32),
        ("CAL_ATT_RATE", d.attitude_rate_hz as f32),
        ("CAL_REFIT_S", cfg.fit.refit_every_s as f32),
    ]
    .into_iter()
    .map(|(n, v)| Param {
        name: n.into(),
        value: v,
    })
    .collect()
}

const AXES: [char; 3] = ['X', 'Y', 'Z'];

/// Compasses served, `MAG0` to `MAG2`: ArduPilot's (COMPASS_OFS to COMPASS_OFS3).
const SERVED_COMPASSES: u8 = crate::calib::ardupilot::COMPASSES;

/// `prefix`'s `_OK` and values ([`values`]): those of its calibration when one in `units` is in
/// use, else NaN.
fn sensor(prefix: &str, cal: Option<&SensorCalibration>, units: CalUnits) -> Vec<Param> {
    let usable = cal.filter(|c| c.calibration().is_some() && c.units == units);
    let mut out = vec![Param {
        name: format!("{prefix}_OK"),
        value: flag(usable.is_some()),
    }];
    let unknown = usable.map(|c| c.unknowns()).unwrap_or_default();
    out.extend(values(prefix, usable, &unknown));
    out
}

/// The offset, matrix, radius and RMS residual of `c`, always all of them, in this order; NaN
/// without a calibration and for what the data did not determine (`unknown`).
fn values(prefix: &str, c: Option<&SensorCalibration>, unknown: &Unknowns) -> Vec<Param> {
    let mut out = Vec::new();
    let mut put = |name: String, v: Option<f64>| {
        out.push(Param {
            name,
            value: v.map_or(f32::NAN, |v| v as f32),
        })
    };
    for (k, a) in AXES.iter().enumerate() {
        put(
            format!("{prefix}_OFS_{a}"),
            c.filter(|_| !unknown.offset[k]).map(|c| c.offset[k]),
        );
    }
    for (r, ra) in AXES.iter().enumerate() {
        for (col, ca) in AXES.iter().enumerate() {
            put(
                format!("{prefix}_M_{ra}{ca}"),
                c.filter(|_| !(unknown.axis[r] || unknown.axis[col]))
                    .map(|c| c.matrix[r][col]),
            );
        }
    }
    put(format!("{prefix}_RADIUS"), c.map(|c| c.radius));
    put(format!("{prefix}_RMS"), c.map(|c| c.rms_residual));
    out
}

/// The parameter list of calibrated vehicle `cal`: the settings, then `MAG0` to `MAG2`, the
/// accelerometer and the gyro; the same names in the same order whatever is calibrated.
pub(super) fn table(cfg: &Config, cal: &Cal) -> Vec<Param> {
    let store = &cal.store;
    let mut out = settings(cfg);
    for k in 0..SERVED_COMPASSES {
        let mag = if store.compass_id == k {
            store.mag.as_ref()
        } else {
            store
                .instances
                .iter()
                .find(|i| i.compass_id == k)
                .and_then(|i| i.mag.as_ref())
        };
        out.extend(sensor(&format!("MAG{k}"), mag, CalUnits::Ut));
    }
    out.extend(sensor("ACC", store.accel.as_ref(), CalUnits::Mps2));
    let gyro = store
        .gyro
        .as_ref()
        .filter(|g| g.status == crate::report::CalStatus::Ok);
    out.push(Param {
        name: "GYR_OK".into(),
        value: flag(gyro.is_some()),
    });
    for (k, a) in AXES.iter().enumerate() {
        out.push(Param {
            name: format!("GYR_BIAS_{a}"),
            value: gyro.map_or(f32::NAN, |g| g.bias[k] as f32),
        });
    }
    out
}

/// Apply PARAM_SET `name` = `value` to the settings, or say why not. Returns what it now means.
fn set(cfg: &mut Config, name: &str, value: f32) -> Result<&'static str, Refused> {
    let w = Writable::of(name).ok_or(Refused::ReadOnly)?;
    if !cfg.daemon.params_writable {
        return Err(Refused::NotEnabled);
    }
    let on = if value == 0.0 {
        false
    } else if value == 1.0 {
        true
    } else {
        return Err(Refused::BadValue("0 or 1"));
    };
    Ok(match w {
        Writable::MagMode => {
            cfg.daemon.mag_cal = if on {
                MagCalMode::OnCommand
            } else {
                MagCalMode::Continuous
            };
            if on {
                "on_command"
            } else {
                "continuous"
            }
        }
        Writable::DebugVect => {
            cfg.daemon.debug_vect = on;
            if on {
                "on"
            } else {
                "off"
            }
        }
    })
}

impl State {
    /// The calibrated vehicle a parameter request addressed to (`system`, `component`) is for:
    /// the one whose ids we speak with, for our component or every component (0).
    fn param_target(&self, system: u8, component: u8) -> Option<usize> {
        self.cals.iter().position(|c| {
            c.own.system_id == system && (component == 0 || component == c.own.component_id)
        })
    }

    /// A parameter request from a ground station: the list, one parameter, or a change.
    pub(super) async fn on_param_request(&mut self, msg: &MavMessage) {
        let Some(((system, component), req)) = mavout::param_request(msg) else {
            return;
        };
        let Some(c) = self.param_target(system, component) else {
            return;
        };
        let params = table(&self.cfg, &self.cals[c]);
        let count = params.len() as u16;
        let value =
            |i: usize| mavout::param_value(&params[i].name, params[i].value, i as u16, count);
        let index = |name: &str| params.iter().position(|p| p.name == name);
        match req {
            ParamRequest::List => {
                let all: Vec<_> = (0..params.len()).map(value).collect();
                self.send_mav(To::Cal(c), &all).await;
            }
            ParamRequest::ReadIndex(i) if (i as usize) < params.len() => {
                self.send_mav(To::Cal(c), &[value(i as usize)]).await;
            }
            ParamRequest::ReadIndex(_) => {}
            ParamRequest::ReadName(n) => {
                if let Some(i) = index(&n) {
                    self.send_mav(To::Cal(c), &[value(i)]).await;
                }
            }
            ParamRequest::Set(n, v) => {
                // A name not ours, sent to every component, is another's (the flight controller's).
                let Some(i) = index(&n) else {
                    if component != 0 {
                        let text =
                            format!("no parameter {n} here: ours are CAL_*, MAG*, ACC_*, GYR_*");
                        self.status(MavSeverity::MAV_SEVERITY_WARNING, text).await;
                    }
                    return;
                };
                let result = set(&mut self.cfg, &n, v);
                let now = table(&self.cfg, &self.cals[c]);
                let answer = mavout::param_value(&n, now[i].value, i as u16, count);
                self.send_mav(To::Cal(c), &[answer]).await;
                let severity = if result.is_ok() {
                    MavSeverity::MAV_SEVERITY_INFO
                } else {
                    MavSeverity::MAV_SEVERITY_WARNING
                };
                let text = match result {
                    Ok(meaning) => format!("{n} set to {v} ({meaning}) for this run"),
                    Err(Refused::ReadOnly) => format!("{n} is read only"),
                    Err(Refused::NotEnabled) => format!(
                        "{n} not changed: parameters are read only unless the config sets daemon.params_writable = true"
                    ),
                    Err(Refused::BadValue(takes)) => format!("{n} not changed: it takes {takes}, got {v}"),
                };
                self.status(severity, text).await;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settings_change_only_when_enabled_and_writable() {
        let mut cfg = Config::default();
        assert_eq!(set(&mut cfg, "CAL_MAG_MODE", 1.0), Err(Refused::NotEnabled));
        cfg.daemon.params_writable = true;
        assert_eq!(set(&mut cfg, "CAL_MAG_MODE", 1.0), Ok("on_command"));
        assert_eq!(cfg.daemon.mag_cal, MagCalMode::OnCommand);
        assert_eq!(
            set(&mut cfg, "CAL_DEBUG_VECT", 0.5),
            Err(Refused::BadValue("0 or 1"))
        );
        // The config alone enables writes to a flight controller.
        assert_eq!(
            set(&mut cfg, "CAL_WRITE_PARAMS", 1.0),
            Err(Refused::ReadOnly)
        );
        assert!(!cfg.daemon.write_params);
        assert_eq!(set(&mut cfg, "MAG0_OFS_X", 3.0), Err(Refused::ReadOnly));
    }

    #[test]
    fn a_sensor_lists_every_value_and_nan_for_what_the_data_did_not_determine() {
        let names = |ps: &[Param]| ps.iter().map(|p| p.name.clone()).collect::<Vec<_>>();
        let none = sensor("MAG0", None, CalUnits::Ut);
        assert_eq!(none.len(), 1 + 3 + 9 + 2);
        assert_eq!(none[0].value, 0.0);
        assert!(none[1..].iter().all(|p| p.value.is_nan()));
        let mut c = SensorCalibration::new(
            crate::report::CalStatus::Ok,
            crate::calib::model::CalModel::Full12,
            CalUnits::Ut,
        );
        c.offset = [1.0, 2.0, 3.0];
        let full = sensor("MAG0", Some(&c), CalUnits::Ut);
        // The same names in the same order, calibrated or not.
        assert_eq!(names(&full), names(&none));
        assert!(full.iter().all(|p| p.name.len() <= 16));
        assert!(full.iter().all(|p| !p.value.is_nan()));
        assert_eq!(full[0].value, 1.0);
        // Counts are not uT: no values.
        let counts = sensor("MAG0", Some(&c), CalUnits::Mps2);
        assert_eq!(counts[0].value, 0.0);
        assert!(counts[1..].iter().all(|p| p.value.is_nan()));
        // A planar fit: its z offset and z row and column are not determined.
        let planar = Unknowns {
            offset: [false, false, true],
            axis: [false, false, true],
            why: String::new(),
        };
        let values = values("MAG0", Some(&c), &planar);
        assert_eq!(names(&values), names(&none[1..]));
        let unknown: Vec<_> = values
            .iter()
            .filter(|p| p.value.is_nan())
            .map(|p| p.name.clone())
            .collect();
        assert!(unknown.iter().all(|n| n.contains('Z')), "{unknown:?}");
        // Known: 2 offsets, the 2x2 block of x and y, radius and RMS.
        assert_eq!(values.len() - unknown.len(), 2 + 4 + 2, "{unknown:?}");
    }
}
