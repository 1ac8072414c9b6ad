//! What decoding counts: records read, samples per sensor, items skipped by reason, and what the
//! source's clock did ([`DecodeStats`]).

use crate::io::clock::TimeStats;
use crate::types::Sample;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Counters of what was read and what was skipped, by reason.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct DecodeStats {
    /// Frames (or CSV rows) decoded.
    pub records: u64,
    /// Samples carrying each sensor.
    pub counts: SensorCounts,
    /// Skipped items by reason.
    pub skipped: BTreeMap<String, u64>,
    /// What the source's clock did: its choice, time segments, faults by kind.
    #[serde(default)]
    pub time: TimeStats,
}

impl DecodeStats {
    pub fn skip(&mut self, reason: &str) {
        bump(&mut self.skipped, reason, 1);
    }
    pub(crate) fn skip_n(&mut self, reason: &str, n: u64) {
        if n > 0 {
            bump(&mut self.skipped, reason, n);
        }
    }
    pub(crate) fn count_sample(&mut self, s: &Sample) {
        let c = &mut self.counts;
        c.accel += s.accel_mps2.is_some() as u64;
        c.gyro += s.gyro_rad_s.is_some() as u64;
        c.mag += s.mag_ut.is_some() as u64;
        c.temp += s.temp_c.is_some() as u64;
        c.throttle += s.throttle.is_some() as u64;
    }
}

/// How many samples carried each sensor. Serialised as a map of the non-zero counts
/// (`{"accel": 12, "mag": 12}`); counted once per sample, so plain fields rather than a map.
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize, PartialEq, Eq)]
#[serde(default, deny_unknown_fields)]
pub struct SensorCounts {
    #[serde(skip_serializing_if = "is_zero")]
    pub accel: u64,
    #[serde(skip_serializing_if = "is_zero")]
    pub gyro: u64,
    #[serde(skip_serializing_if = "is_zero")]
    pub mag: u64,
    #[serde(skip_serializing_if = "is_zero")]
    pub temp: u64,
    #[serde(skip_serializing_if = "is_zero")]
    pub throttle: u64,
}

fn is_zero(n: &u64) -> bool {
    *n == 0
}

impl SensorCounts {
    pub fn is_empty(&self) -> bool {
        *self == SensorCounts::default()
    }

    pub fn add(&mut self, o: &SensorCounts) {
        self.accel += o.accel;
        self.gyro += o.gyro;
        self.mag += o.mag;
        self.temp += o.temp;
        self.throttle += o.throttle;
    }

    /// The non-zero counts by sensor name.
    pub fn to_map(&self) -> BTreeMap<String, u64> {
        [
            ("accel", self.accel),
            ("gyro", self.gyro),
            ("mag", self.mag),
            ("temp", self.temp),
            ("throttle", self.throttle),
        ]
        .into_iter()
        .filter(|(_, n)| *n > 0)
        .map(|(k, n)| (k.to_string(), n))
        .collect()
    }
}

/// Add `n` to counter `key`, allocating the key only the first time it is seen.
fn bump(map: &mut BTreeMap<String, u64>, key: &str, n: u64) {
    match map.get_mut(key) {
        Some(c) => *c += n,
        None => {
            map.insert(key.to_string(), n);
        }
    }
}
