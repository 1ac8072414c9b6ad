//! MAVFTP requests addressed to the service: `@PARAM/param.pck` served from the parameter
//! table ([`super::params::table`]) at once, anything else refused with a NAK naming why
//! ([`crate::io::mavftp`]). A ground station's `param fetch` so takes one round trip and a burst
//! instead of waiting out its MAVFTP timeout before falling back to PARAM_REQUEST_LIST.
//!
//! Requests to our component are answered always; requests to every component (0) of our system
//! only while no flight controller of that system is heard (its HEARTBEAT names an autopilot):
//! then the vehicle's own server answers them, and a reply of ours would end its download.

use super::*;
use crate::io::mavftp::{self, FtpPacket};
use mavlink::dialects::ardupilotmega::{MavAutopilot, FILE_TRANSFER_PROTOCOL_DATA};

impl State {
    /// Note a HEARTBEAT (not our own) from `system`: a flight controller's makes its system's
    /// broadcast MAVFTP requests its own.
    pub(super) fn note_autopilot(&mut self, system: u8, hb: &MavMessage) {
        if let MavMessage::HEARTBEAT(h) = hb {
            if h.autopilot != MavAutopilot::MAV_AUTOPILOT_INVALID {
                self.autopilot_systems.insert(system);
            }
        }
    }

    /// The calibrated vehicle a MAVFTP request to (`system`, `component`) is for.
    fn ftp_target(&self, system: u8, component: u8) -> Option<usize> {
        let broadcast_ours = component == 0 && !self.autopilot_systems.contains(&system);
        self.cals.iter().position(|c| {
            c.own.system_id == system && (component == c.own.component_id || broadcast_ours)
        })
    }

    /// A FILE_TRANSFER_PROTOCOL request from (`from_system`, `from_component`): answered with
    /// the ids of the vehicle it is for, back to its sender.
    pub(super) async fn on_ftp(
        &mut self,
        from_system: u8,
        from_component: u8,
        d: &FILE_TRANSFER_PROTOCOL_DATA,
    ) {
        let Some(c) = self.ftp_target(d.target_system, d.target_component) else {
            return;
        };
        let req = FtpPacket::parse(&d.payload);
        let params = params::table(&self.cfg, &self.cals[c]);
        let file = || {
            let pairs: Vec<(&str, f32)> =
                params.iter().map(|p| (p.name.as_str(), p.value)).collect();
            mavftp::pack_params(&pairs)
        };
        let replies = self.cals[c]
            .ftp
            .handle((from_system, from_component), &req, file);
        let msgs: Vec<MavMessage> = replies
            .iter()
            .map(|r| mavftp::message(from_system, from_component, r))
            .collect();
        self.send_mav(To::Cal(c), &msgs).await;
    }
}
