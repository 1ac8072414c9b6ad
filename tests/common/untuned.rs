//! The attitude filter's settings before any tuning on BROAD: where every run of the tuning
//! procedure (`cargo bench --bench broad -- --tune`) starts, values with a physical reason or a
//! round guess, none of them chosen on data. Shared by that bench and by the tests that score the
//! tuned defaults on data the tuning never saw (the stress simulations, the PX4 flights against
//! motion capture), so that each shows the tuned figure next to the untuned one.

use imucald::attitude::fusion::{
    BiasConfig, FusionConfig, GyroScaleConfig, HeadingConfig, MagRefConfig, ProcessConfig,
    RestConfig, TiltConfig,
};

pub fn untuned_fusion() -> FusionConfig {
    FusionConfig {
        process: ProcessConfig {
            gyro_noise_density: 0.001,
            gyro_rate_noise: 0.001,
            intensity_tau_s: 3.0,
            ..ProcessConfig::default()
        },
        bias: BiasConfig {
            bias_walk: 0.0001f64.to_radians(),
            ..BiasConfig::default()
        },
        tilt: TiltConfig {
            acc_noise_mps2: 2.0,
            acc_rest_noise_mps2: 0.5,
            acc_lin_tau_s: 1.0,
            acc_lp_tau_s: 1.0,
            ..TiltConfig::default()
        },
        heading: HeadingConfig {
            mag_heading_noise_deg: 60.0,
            mag_rest_heading_noise_deg: 60.0,
            mag_gate_deg: 20.0,
            mag_gate_timeout_s: 10.0,
            ..HeadingConfig::default()
        },
        mag_ref: MagRefConfig {
            mag_norm_tol: 0.1,
            mag_dip_tol_deg: 10.0,
            mag_new_field_s: 20.0,
            ..MagRefConfig::default()
        },
        rest: RestConfig {
            rest_gyro_rad_s: 2.0f64.to_radians(),
            ..RestConfig::default()
        },
        // A MEMS gyro's sensitivity error, of the order of a percent or less, and a milliradian of
        // unmodelled error per radian turned (a misalignment of that size).
        scale: GyroScaleConfig {
            gyro_scale_sigma: 0.005,
            gyro_scale_path_sd: 0.001,
        },
        ..FusionConfig::default()
    }
}
