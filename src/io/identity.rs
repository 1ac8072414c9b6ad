//! What identifies a vehicle's hardware on a MAVLink link, pure: the flight controller's unique id
//! (AUTOPILOT_VERSION `uid`, or the first 8 bytes of `uid2` when `uid` is 0) and each compass's
//! device id (ArduPilot's COMPASS_DEV_ID, COMPASS_DEV_ID2, COMPASS_DEV_ID3; PX4's CAL_MAG0_ID to
//! CAL_MAG2_ID), the requests that ask for them, and the answers read.
//!
//! A device id names the bus, the address and the chip of one compass, so it stays the same when
//! the vehicle moves to another radio or is given another system id, and differs between two
//! vehicles of the same build only when their compasses sit on other buses; the flight
//! controller's id differs between any two boards. The live service binds a stored calibration
//! to both where the link carries them ([`Hardware::same_as`]).

use mavlink::dialects::ardupilotmega::{
    MavCmd, MavMessage, MavParamType, COMMAND_LONG_DATA, PARAM_REQUEST_READ_DATA,
};
use serde::{Deserialize, Serialize};

/// AUTOPILOT_VERSION's message id (what MAV_CMD_REQUEST_MESSAGE asks for).
const AUTOPILOT_VERSION_ID: f32 = 148.0;

/// The compasses whose device ids are read (ArduPilot's three).
pub const COMPASSES: usize = 3;

/// The flight stack whose parameter names and value encoding a vehicle uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stack {
    ArduPilot,
    Px4,
}

/// The device-id parameter of compass `k` (0-based).
pub fn dev_id_name(stack: Stack, k: usize) -> String {
    match (stack, k) {
        (Stack::ArduPilot, 0) => "COMPASS_DEV_ID".into(),
        (Stack::ArduPilot, k) => format!("COMPASS_DEV_ID{}", k + 1),
        (Stack::Px4, k) => format!("CAL_MAG{k}_ID"),
    }
}

/// The requests for a vehicle's identity: AUTOPILOT_VERSION (MAV_CMD_REQUEST_MESSAGE) and each
/// compass's device id (PARAM_REQUEST_READ), to (`target_system`, `target_component`).
pub fn requests(stack: Stack, target_system: u8, target_component: u8) -> Vec<MavMessage> {
    let mut out = vec![MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
        target_system,
        target_component,
        command: MavCmd::MAV_CMD_REQUEST_MESSAGE,
        confirmation: 0,
        param1: AUTOPILOT_VERSION_ID,
        ..Default::default()
    })];
    for k in 0..COMPASSES {
        let name = dev_id_name(stack, k);
        let mut id = [0u8; 16];
        id[..name.len()].copy_from_slice(name.as_bytes());
        out.push(MavMessage::PARAM_REQUEST_READ(PARAM_REQUEST_READ_DATA {
            param_index: -1,
            target_system,
            target_component,
            param_id: id.into(),
        }));
    }
    out
}

/// A vehicle's hardware as far as its link told it.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Hardware {
    /// The flight controller's unique id (AUTOPILOT_VERSION), when it sent a non-zero one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub uid: Option<u64>,
    /// Device id of compass 0, 1, 2 (0: none there, or not read).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub compass_dev_ids: Vec<u32>,
}

impl Hardware {
    /// Take what `msg` says of the hardware (AUTOPILOT_VERSION, or a device-id PARAM_VALUE of
    /// `stack`); returns whether it changed anything.
    pub fn absorb(&mut self, stack: Stack, msg: &MavMessage) -> bool {
        match msg {
            MavMessage::AUTOPILOT_VERSION(v) => {
                let uid2 = u64::from_le_bytes(v.uid2[..8].try_into().unwrap_or([0; 8]));
                let uid = [v.uid, uid2].into_iter().find(|&u| u != 0);
                let changed = uid.is_some() && uid != self.uid;
                self.uid = uid.or(self.uid);
                changed
            }
            MavMessage::PARAM_VALUE(p) => {
                let bytes: &[u8; 16] = &p.param_id;
                let end = bytes.iter().position(|&b| b == 0).unwrap_or(16);
                let name = String::from_utf8_lossy(&bytes[..end]);
                let Some(k) = (0..COMPASSES).find(|&k| dev_id_name(stack, k) == name) else {
                    return false;
                };
                let id = dev_id_value(stack, p.param_type, p.param_value);
                if self.compass_dev_ids.len() <= k {
                    self.compass_dev_ids.resize(k + 1, 0);
                }
                let changed = self.compass_dev_ids[k] != id;
                self.compass_dev_ids[k] = id;
                changed
            }
            _ => false,
        }
    }

    /// Nothing known.
    pub fn is_unknown(&self) -> bool {
        self.uid.is_none() && self.compass_dev_ids.iter().all(|&d| d == 0)
    }

    /// Whether `other` is the same hardware: the flight controllers' ids equal when both are
    /// known, else the device ids of the compasses both know (at least one); `None` when nothing
    /// can be compared (the link carries neither).
    pub fn same_as(&self, other: &Hardware) -> Option<bool> {
        if let (Some(a), Some(b)) = (self.uid, other.uid) {
            return Some(a == b);
        }
        let both: Vec<(u32, u32)> = self
            .compass_dev_ids
            .iter()
            .zip(&other.compass_dev_ids)
            .filter(|(a, b)| **a != 0 && **b != 0)
            .map(|(a, b)| (*a, *b))
            .collect();
        (!both.is_empty()).then(|| both.iter().all(|(a, b)| a == b))
    }

    /// A short name for messages and directories: `fc-<uid hex>`, else `compass-<dev id>` of
    /// the first compass known; `None` when nothing is known.
    pub fn tag(&self) -> Option<String> {
        if let Some(u) = self.uid {
            return Some(format!("fc-{u:016x}"));
        }
        let d = self.compass_dev_ids.iter().find(|&&d| d != 0)?;
        Some(format!("compass-{d}"))
    }
}

/// A device id as the stack sends it: ArduPilot sends an integer parameter's value as the float
/// of the number; PX4 sends an INT32's four bytes in the float's place.
fn dev_id_value(stack: Stack, ty: MavParamType, value: f32) -> u32 {
    match (stack, ty) {
        (Stack::Px4, MavParamType::MAV_PARAM_TYPE_INT32 | MavParamType::MAV_PARAM_TYPE_UINT32) => {
            value.to_bits()
        }
        _ if value.is_finite() && value >= 0.0 => value as u32,
        _ => 0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavlink::dialects::ardupilotmega::{AUTOPILOT_VERSION_DATA, PARAM_VALUE_DATA};

    fn dev_id(name: &str, ty: MavParamType, value: f32) -> MavMessage {
        let mut id = [0u8; 16];
        id[..name.len()].copy_from_slice(name.as_bytes());
        MavMessage::PARAM_VALUE(PARAM_VALUE_DATA {
            param_value: value,
            param_id: id.into(),
            param_type: ty,
            ..Default::default()
        })
    }

    #[test]
    fn ids_are_read_as_each_stack_sends_them() {
        let mut ap = Hardware::default();
        assert!(ap.is_unknown());
        let int32 = MavParamType::MAV_PARAM_TYPE_INT32;
        assert!(ap.absorb(
            Stack::ArduPilot,
            &dev_id("COMPASS_DEV_ID2", int32, 590114.0)
        ));
        assert_eq!(ap.compass_dev_ids, vec![0, 590114]);
        assert!(!ap.absorb(Stack::ArduPilot, &dev_id("COMPASS_OFS_X", int32, 5.0)));
        let mut px4 = Hardware::default();
        let bits = f32::from_bits(12_345_678);
        assert!(px4.absorb(Stack::Px4, &dev_id("CAL_MAG0_ID", int32, bits)));
        assert_eq!(px4.compass_dev_ids, vec![12_345_678]);
        let mut v = AUTOPILOT_VERSION_DATA::default();
        assert!(!ap.absorb(Stack::ArduPilot, &MavMessage::AUTOPILOT_VERSION(v.clone())));
        v.uid2[..8].copy_from_slice(&7u64.to_le_bytes());
        assert!(ap.absorb(Stack::ArduPilot, &MavMessage::AUTOPILOT_VERSION(v.clone())));
        assert_eq!(ap.uid, Some(7));
        v.uid = 0x00ab_cdef;
        ap.absorb(Stack::ArduPilot, &MavMessage::AUTOPILOT_VERSION(v));
        assert_eq!(ap.tag().as_deref(), Some("fc-0000000000abcdef"));
    }

    #[test]
    fn hardware_is_the_same_only_where_the_ids_say_so() {
        let fc = |uid| Hardware {
            uid,
            compass_dev_ids: vec![97539, 0],
        };
        assert_eq!(fc(Some(1)).same_as(&fc(Some(1))), Some(true));
        assert_eq!(fc(Some(1)).same_as(&fc(Some(2))), Some(false));
        // No board id on one side: the compasses decide.
        assert_eq!(fc(None).same_as(&fc(Some(2))), Some(true));
        let other = Hardware {
            uid: None,
            compass_dev_ids: vec![97540],
        };
        assert_eq!(fc(None).same_as(&other), Some(false));
        assert_eq!(Hardware::default().same_as(&fc(Some(1))), None);
        assert_eq!(other.tag().as_deref(), Some("compass-97540"));
    }

    #[test]
    fn the_requests_ask_for_the_version_and_every_device_id() {
        let reqs = requests(Stack::Px4, 3, 1);
        assert_eq!(reqs.len(), 1 + COMPASSES);
        let MavMessage::COMMAND_LONG(c) = &reqs[0] else {
            panic!("{reqs:?}")
        };
        assert_eq!(
            (c.command, c.param1, c.target_system),
            (MavCmd::MAV_CMD_REQUEST_MESSAGE, 148.0, 3)
        );
        let MavMessage::PARAM_REQUEST_READ(r) = &reqs[3] else {
            panic!("{reqs:?}")
        };
        let id: &[u8; 16] = &r.param_id;
        assert_eq!(&id[..11], b"CAL_MAG2_ID");
        assert_eq!(dev_id_name(Stack::ArduPilot, 2), "COMPASS_DEV_ID3");
    }
}
