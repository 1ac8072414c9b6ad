//! What the live page shows, kept from the service's JSON lines (imucald.live/1): the latest
//! progress and calibration per sensor and instance, heading, attitude, the latest calibrated
//! vectors, a trail of field directions, the status log, and whether lines are arriving. Pure: no
//! I/O, no tokio; times are handed in.

use crate::io::mavout::LiveEvent;
use crate::types::Vec3;
use serde::Serialize;
use std::collections::{BTreeMap, VecDeque};

/// Schema of `/api/state`.
pub(crate) const UI_SCHEMA: &str = "imucald.ui/1";
/// Status lines the page's log keeps.
pub(crate) const LOG_LINES: usize = 50;
/// Field directions the sphere's trail keeps (one per progress line).
pub(crate) const TRAIL_POINTS: usize = 600;
/// Lines arriving within this long count as a live stream, s.
pub(crate) const LIVE_WITHIN_S: f64 = 3.0;

/// Whether the service's lines are arriving.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub(crate) enum LinkState {
    /// No line yet.
    Waiting,
    /// A line within the last [`LIVE_WITHIN_S`].
    Live,
    /// Lines came, none lately (sources silent or ended).
    Stale,
}

/// The latest of everything the page shows.
#[derive(Debug, Clone, Default)]
pub struct UiState {
    /// Lines taken.
    pub lines: u64,
    /// Lines that were not an event of the schema (counted, not shown).
    pub unreadable: u64,
    /// Lines about a vehicle other than the first the service calibrates (the page shows the
    /// first), counted, not shown.
    pub other_vehicle_lines: u64,
    last_line_s: Option<f64>,
    progress: BTreeMap<(String, u8), LiveEvent>,
    calibration: BTreeMap<(String, u8), LiveEvent>,
    heading: Option<LiveEvent>,
    attitude: Option<LiveEvent>,
    calibrated: Option<LiveEvent>,
    trail: VecDeque<Vec3>,
    log: VecDeque<LiveEvent>,
}

/// `/api/state`.
#[derive(Serialize)]
struct Snapshot<'a> {
    schema: &'static str,
    lines: u64,
    unreadable: u64,
    other_vehicle_lines: u64,
    link: LinkStatus,
    progress: Vec<&'a LiveEvent>,
    calibration: Vec<&'a LiveEvent>,
    heading: Option<&'a LiveEvent>,
    attitude: Option<&'a LiveEvent>,
    calibrated: Option<&'a LiveEvent>,
    /// Field directions about the centre, oldest first, body axes (x forward, y right, z down).
    trail: Vec<[f32; 3]>,
    log: Vec<&'a LiveEvent>,
    /// The coverage regions' latitude bands (`[[lowest z, regions], ...]`).
    bands: serde_json::Value,
    stream: StreamStats,
}

#[derive(Serialize)]
struct LinkStatus {
    state: LinkState,
    /// Seconds since the last line (null before the first).
    last_line_age_s: Option<f64>,
}

/// The page stream's counters, for the snapshot.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub(crate) struct StreamStats {
    /// Pages connected to the event stream now.
    pub clients: u64,
    /// Lines a slow page missed (it fell behind the stream's buffer), all pages together.
    pub lagged_lines: u64,
}

impl UiState {
    /// Take one JSON line received at `now_s`; a line that is not an event of the schema is
    /// counted and otherwise ignored.
    pub(crate) fn apply_line(&mut self, line: &str, now_s: f64) {
        self.lines += 1;
        self.last_line_s = Some(now_s);
        // The page shows the first vehicle; lines about a further one say so (`vehicle`).
        if line.contains("\"vehicle\":{") {
            self.other_vehicle_lines += 1;
            return;
        }
        match serde_json::from_str::<LiveEvent>(line) {
            Ok(ev) => self.apply(ev),
            Err(_) => self.unreadable += 1,
        }
    }

    /// Take one event.
    pub fn apply(&mut self, ev: LiveEvent) {
        match &ev {
            LiveEvent::Progress {
                sensor,
                instance,
                direction,
                ..
            } => {
                let n = direction.iter().map(|v| v * v).sum::<f64>().sqrt();
                if n > 0.0 && n.is_finite() && *instance == self.first_instance(sensor, *instance) {
                    if self.trail.len() == TRAIL_POINTS {
                        self.trail.pop_front();
                    }
                    self.trail.push_back(direction.map(|v| v / n));
                }
                self.progress.insert((sensor.clone(), *instance), ev);
            }
            LiveEvent::Calibration {
                sensor, instance, ..
            } => {
                self.calibration.insert((sensor.clone(), *instance), ev);
            }
            LiveEvent::Heading { .. } => self.heading = Some(ev),
            LiveEvent::Attitude { .. } => self.attitude = Some(ev),
            LiveEvent::Calibrated { .. } => self.calibrated = Some(ev),
            LiveEvent::Status { .. } => {
                if self.log.len() == LOG_LINES {
                    self.log.pop_front();
                }
                self.log.push_back(ev);
            }
        }
    }

    /// The instance whose directions the trail shows: the lowest compass id with progress (the
    /// sphere shows one compass; every compass has its regions).
    fn first_instance(&self, sensor: &str, candidate: u8) -> u8 {
        self.progress
            .keys()
            .filter(|(s, _)| s == sensor)
            .map(|(_, i)| *i)
            .min()
            .map_or(candidate, |i| i.min(candidate))
    }

    /// Whether lines are arriving, at `now_s`.
    pub(crate) fn link_state(&self, now_s: f64) -> LinkState {
        match self.last_line_s {
            None => LinkState::Waiting,
            Some(t) if now_s - t <= LIVE_WITHIN_S => LinkState::Live,
            Some(_) => LinkState::Stale,
        }
    }

    /// The completion the state holds for a compass, percent.
    pub fn completion_pct(&self, instance: u8) -> Option<f64> {
        match self.progress.get(&("mag".to_string(), instance)) {
            Some(LiveEvent::Progress { completion_pct, .. }) => Some(*completion_pct),
            _ => None,
        }
    }

    /// `/api/state` (schema [`UI_SCHEMA`]) at `now_s`.
    pub(crate) fn snapshot_json(&self, now_s: f64, stream: StreamStats) -> String {
        let s = Snapshot {
            schema: UI_SCHEMA,
            lines: self.lines,
            unreadable: self.unreadable,
            other_vehicle_lines: self.other_vehicle_lines,
            link: LinkStatus {
                state: self.link_state(now_s),
                last_line_age_s: self.last_line_s.map(|t| (now_s - t).max(0.0)),
            },
            progress: self.progress.values().collect(),
            calibration: self.calibration.values().collect(),
            heading: self.heading.as_ref(),
            attitude: self.attitude.as_ref(),
            calibrated: self.calibrated.as_ref(),
            trail: self
                .trail
                .iter()
                .map(|d| d.map(|v| ((v * 1000.0).round() / 1000.0) as f32))
                .collect(),
            log: self.log.iter().collect(),
            bands: super::bands_json(),
            stream,
        };
        // Plain data of finite numbers or null (serde_json writes NaN as null): cannot fail.
        serde_json::to_string(&s).unwrap_or_else(|e| {
            format!(
                "{{\"schema\":\"{UI_SCHEMA}\",\"error\":{}}}",
                serde_json::json!(e.to_string())
            )
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::mavout::json_line;

    fn progress(instance: u8, pct: f64, dir: Vec3) -> LiveEvent {
        LiveEvent::Progress {
            sensor: "mag".into(),
            instance,
            completion_pct: pct,
            filled_regions: pct as usize,
            regions: crate::calib::coverage::regions_hex(&[true; 7]),
            direction: dir,
        }
    }

    #[test]
    fn ui_state_shows_the_first_vehicle_and_counts_the_others() {
        let ev = progress(0, 40.0, [1.0, 0.0, 0.0]);
        let first = crate::io::mavout::json_line(&ev);
        let tag = crate::io::mavout::VehicleTag {
            link: "udpin:127.0.0.1:14550".into(),
            system_id: 2,
        };
        let other =
            crate::io::mavout::json_line_for(&progress(0, 90.0, [0.0, 1.0, 0.0]), Some(&tag));
        let mut st = UiState::default();
        st.apply_line(&first, 1.0);
        st.apply_line(&other, 1.1);
        assert_eq!(st.completion_pct(0), Some(40.0));
        assert_eq!((st.lines, st.other_vehicle_lines, st.unreadable), (2, 1, 0));
    }

    #[test]
    fn ui_state_keeps_the_latest_per_sensor_and_instance() {
        let mut s = UiState::default();
        assert_eq!(s.link_state(0.0), LinkState::Waiting);
        s.apply_line(&json_line(&progress(0, 10.0, [0.0, 0.0, 2.0])), 1.0);
        s.apply_line(&json_line(&progress(1, 5.0, [1.0, 0.0, 0.0])), 1.1);
        s.apply_line(&json_line(&progress(0, 20.0, [0.0, 0.0, 0.0])), 1.2);
        s.apply_line("not json", 1.3);
        s.apply_line("{\"schema\":\"imucald.live/1\",\"type\":\"novel\"}", 1.4);
        assert_eq!(s.completion_pct(0), Some(20.0));
        assert_eq!(s.completion_pct(1), Some(5.0));
        assert_eq!((s.lines, s.unreadable), (5, 2));
        // The trail: compass 0 only, unit directions, none for a zero direction.
        assert_eq!(
            s.trail.iter().copied().collect::<Vec<_>>(),
            [[0.0, 0.0, 1.0]]
        );
        assert_eq!(s.link_state(2.0), LinkState::Live);
        assert_eq!(s.link_state(10.0), LinkState::Stale);
        let v: serde_json::Value =
            serde_json::from_str(&s.snapshot_json(2.4, StreamStats::default())).unwrap();
        assert_eq!(v["schema"], UI_SCHEMA);
        assert_eq!(v["progress"].as_array().unwrap().len(), 2);
        assert_eq!(v["progress"][0]["completion_pct"], 20.0);
        // Seven regions: bits 0-3 of the first digit, 0-2 of the second.
        assert_eq!(v["progress"][0]["regions"], "f7");
        assert_eq!(v["link"]["state"], "live");
        assert!((v["link"]["last_line_age_s"].as_f64().unwrap() - 1.0).abs() < 1e-9);
        assert_eq!(v["bands"][0][1], 1);
    }

    #[test]
    fn ui_state_log_and_trail_are_bounded() {
        let mut s = UiState::default();
        for i in 0..(LOG_LINES + 10) {
            s.apply(LiveEvent::Status {
                level: "info".into(),
                text: format!("{i}"),
            });
        }
        for i in 0..(TRAIL_POINTS + 10) {
            s.apply(progress(0, 1.0, [1.0, i as f64, 0.0]));
        }
        assert_eq!(s.log.len(), LOG_LINES);
        assert_eq!(s.trail.len(), TRAIL_POINTS);
        match s.log.front() {
            Some(LiveEvent::Status { text, .. }) => assert_eq!(text, "10"),
            other => panic!("{other:?}"),
        }
    }
}
