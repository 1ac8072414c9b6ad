//! Which hardware a stored calibration belongs to, and the checks that resume it only there.
//!
//! A vehicle whose HEARTBEAT names ArduPilot or PX4 is asked once for AUTOPILOT_VERSION (the
//! flight controller's unique id) and for its compasses' device ids ([`crate::io::identity`]).
//! What it answered before its first IMU sample chooses its calibration: the stored one of the
//! same board and compasses, on whichever link and system id they come back. A vehicle whose
//! link carries neither (no HEARTBEAT, another stack, a log replayed, no answer yet) is known by
//! its link and system id, as its record then says; an answer that comes later and names other
//! hardware than the calibration resumed drops it (said) and calibration starts again, and is
//! recorded for the next start.

use super::*;
use crate::io::identity::{self, Stack};
use mavlink::dialects::ardupilotmega::MavAutopilot;

/// Whether stored vehicle `s` may be resumed onto vehicle `me`: never a simulator's; the same
/// hardware where both know an id ([`Hardware::same_as`]); else the same link and system id, or
/// the same system id when `s`'s link is no longer configured (`link_gone`: an address edited).
pub(super) fn resumable(s: &StoredVehicle, me: &StoredVehicle, link_gone: bool) -> bool {
    if s.source == VehicleSource::Simulator {
        return false;
    }
    match s.hardware.same_as(&me.hardware) {
        Some(same) => same,
        None => s.system_id == me.system_id && (s.link == me.link || link_gone),
    }
}

/// Whether the calibration in a vehicle's own directory (named for its hardware, or its link and
/// system id) may be resumed onto `me`: not a simulator's, and not other hardware's.
pub(super) fn same_kind(s: &StoredVehicle, me: &StoredVehicle) -> bool {
    s.source != VehicleSource::Simulator && s.hardware.same_as(&me.hardware) != Some(false)
}

/// "resumed the calibration of ... written ..." when `store` holds a calibration, read from
/// `dir`.
pub(super) fn resumed_from(store: &StoredCalibration, dir: &Path) -> Option<String> {
    if store.mag.is_none() && store.accel.is_none() {
        return None;
    }
    let of = store
        .vehicle
        .as_ref()
        .map(|v| format!(" of {}", v.describe()))
        .unwrap_or_default();
    let when = std::fs::metadata(dir.join(STORE_FILE))
        .and_then(|m| m.modified())
        .map(|t| format!(" written {}", utc_text(t)))
        .unwrap_or_default();
    Some(format!("resumed the calibration{of}{when}"))
}

/// `YYYY-MM-DD HH:MM:SS UTC`.
fn utc_text(t: std::time::SystemTime) -> String {
    let s = t
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    let day = crate::types::LogDate::from_unix_us(
        s.saturating_mul(1_000_000),
        crate::types::DateSource::RecordClock,
    )
    .map_or_else(|| "before 2000".into(), |d| d.iso());
    let (h, m, sec) = (s % 86_400 / 3600, s % 3600 / 60, s % 60);
    format!("{day} {h:02}:{m:02}:{sec:02} UTC")
}

/// The stack a HEARTBEAT names, when it is one whose identity is read.
fn stack_of(hb: &MavMessage) -> Option<Stack> {
    match hb {
        MavMessage::HEARTBEAT(h) => match h.autopilot {
            MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA => Some(Stack::ArduPilot),
            MavAutopilot::MAV_AUTOPILOT_PX4 => Some(Stack::Px4),
            _ => None,
        },
        _ => None,
    }
}

impl State {
    /// A sample from `link`: a simulator's makes calibrated vehicle 0's record the simulator's
    /// (while no vehicle on a MAVLink link took it), so it is never resumed onto a vehicle.
    pub(super) fn note_simulator(&mut self, link: usize) {
        let Some(l) = self.links.get(link).filter(|l| l.simulator) else {
            return;
        };
        let cal0 = &mut self.cals[0];
        let recorded = cal0
            .store
            .vehicle
            .as_ref()
            .is_some_and(|v| v.source == VehicleSource::Simulator);
        if cal0.vehicle.is_none() && !recorded {
            cal0.store.vehicle = Some(StoredVehicle::simulator(&l.label));
        }
    }

    /// A HEARTBEAT of vehicle `v` (on `link`, from `system`, `component`): a flight controller is
    /// asked for its identity once.
    pub(super) async fn identity_heartbeat(
        &mut self,
        v: usize,
        link: usize,
        (system, component): (u8, u8),
        hb: &MavMessage,
    ) {
        let Some(stack) = stack_of(hb) else {
            return;
        };
        let veh = &mut self.vehicles[v];
        if veh.identity.is_some() {
            return;
        }
        veh.identity = Some(stack);
        let reqs = identity::requests(stack, system, component);
        self.send_mav(To::Link(link), &reqs).await;
    }

    /// AUTOPILOT_VERSION or a PARAM_VALUE of vehicle `v`: what it says of the hardware is kept,
    /// recorded with its calibration, and a calibration resumed for other hardware is dropped.
    pub(super) async fn identity_message(&mut self, v: usize, msg: &MavMessage) {
        let Some(stack) = self.vehicles[v].identity else {
            return;
        };
        if !self.vehicles[v].hardware.absorb(stack, msg) {
            return;
        }
        let hardware = self.vehicles[v].hardware.clone();
        let Some(c) = self.vehicles[v].cal else {
            return;
        };
        let Some(stored) = self.cals[c].store.vehicle.clone() else {
            return;
        };
        let other = stored.hardware.same_as(&hardware) == Some(false);
        let mut me = stored.clone();
        me.hardware = hardware;
        if other && resumed_from(&self.cals[c].store, &self.cals[c].cal_dir).is_some() {
            self.restart_for_other_hardware(c, &stored, &me).await;
        }
        self.cals[c].store.vehicle = Some(me);
    }

    /// Calibrated vehicle `c` resumed `stored`'s calibration, but its hardware is `me`'s: start
    /// it again from nothing (its directory is written over with the new calibration), said.
    async fn restart_for_other_hardware(
        &mut self,
        c: usize,
        stored: &StoredVehicle,
        me: &StoredVehicle,
    ) {
        let old = &self.cals[c];
        let fresh = Cal::new(
            &self.cfg,
            StoredCalibration::empty(),
            old.cal_dir.clone(),
            old.own,
            old.target,
            self.declination,
        );
        let Ok(mut fresh) = fresh else {
            return;
        };
        fresh.vehicle = old.vehicle;
        let dir = old.cal_dir.display().to_string();
        self.cals[c] = fresh;
        let text = format!(
            "{}: the calibration in {dir} is of {}, other hardware: dropped, calibrating from scratch",
            me.describe(),
            stored.describe()
        );
        self.status_for(c, MavSeverity::MAV_SEVERITY_WARNING, text)
            .await;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::identity::Hardware;

    fn vehicle(link: &str, system_id: u8, uid: Option<u64>) -> StoredVehicle {
        StoredVehicle {
            link: link.into(),
            system_id,
            source: VehicleSource::Vehicle,
            hardware: Hardware {
                uid,
                compass_dev_ids: vec![],
            },
        }
    }

    #[test]
    fn a_calibration_is_resumed_only_onto_its_own_hardware_or_else_its_link() {
        let stored = vehicle("udpin:a", 1, Some(7));
        // The same board on another link and system id; another board on the same link.
        assert!(resumable(&stored, &vehicle("udpin:b", 4, Some(7)), false));
        assert!(!resumable(&stored, &vehicle("udpin:a", 1, Some(8)), false));
        // No ids on one side: the link and system id decide (the system id alone when the link
        // is no longer configured).
        assert!(resumable(&stored, &vehicle("udpin:a", 1, None), false));
        assert!(!resumable(&stored, &vehicle("udpin:b", 1, None), false));
        assert!(resumable(&stored, &vehicle("udpin:b", 1, None), true));
        assert!(!resumable(&stored, &vehicle("udpin:b", 2, None), true));
        // Never a simulator's.
        let sim = StoredVehicle::simulator("sim:tumble");
        assert!(!resumable(&sim, &vehicle("sim:tumble", 0, None), true));
    }

    #[test]
    fn the_builtin_simulator_keeps_its_calibration_in_a_folder_of_its_own() {
        let dir = tempfile::tempdir().unwrap();
        let mut cfg = Config::default();
        cfg.daemon.calibration_dir = dir.path().display().to_string();
        cfg.daemon.sources.clear();
        let (store, at) = super::super::service::open_store(&cfg.daemon).unwrap();
        assert_eq!(at, dir.path().join(super::super::service::SIM_DIR));
        assert!(store.mag.is_none());
        let mut link = cfg.daemon.clone();
        link.sources = vec![crate::config::SourceConfig {
            address: "udpin:127.0.0.1:0".into(),
            payload: crate::config::PayloadKind::Mavlink,
            fields: vec![],
            scales: Default::default(),
        }];
        assert_eq!(
            super::super::service::open_store(&link).unwrap().1,
            dir.path()
        );
    }
}
