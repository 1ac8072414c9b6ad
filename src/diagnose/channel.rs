//! The residual channels: the kinds of residual the forward model gives for an evidence unit, each
//! with its name and unit in the report. The evidence counts its samples per channel, the forward
//! model fills the channels, the rounds weight them and the report names them.

/// How many residual channels there are.
pub(super) const NCH: usize = 6;

/// A residual channel (its index into per-channel arrays is [`Ch::i`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Ch {
    /// |calibrated field| - F, uT.
    MagNorm,
    /// |calibrated accel| - g, m/s^2.
    AccNorm,
    /// The gravity-field angle, g.m - sin(dip), 1.
    Dip,
    /// Calibrated accel turned into ENU against up, rad.
    VecAcc,
    /// Calibrated field direction turned into ENU against the earth field's, rad.
    VecMag,
    /// Static gyro mean minus the bias, rad/s.
    Gyro,
}

/// Every channel, in index order.
pub(super) const ALL_CH: [Ch; NCH] = [
    Ch::MagNorm,
    Ch::AccNorm,
    Ch::Dip,
    Ch::VecAcc,
    Ch::VecMag,
    Ch::Gyro,
];

impl Ch {
    pub(super) fn i(self) -> usize {
        self as usize
    }
    pub(super) fn name(self) -> &'static str {
        [
            "mag_norm",
            "accel_norm",
            "dip",
            "vector_accel",
            "vector_mag",
            "gyro",
        ][self.i()]
    }
    pub(super) fn unit(self) -> &'static str {
        ["uT", "m/s^2", "1", "rad", "rad", "rad/s"][self.i()]
    }
}
