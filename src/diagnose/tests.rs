use super::evidence::v3;
use super::*;
use crate::sim::{
    simulate, BenchSettings, Effects, GyroBiasDrift, MotorDriver, ScaleCubic, Scenario,
    SensorTruth, TemperatureBias,
};
use crate::types::Vec3;
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Which effect a blind case hides.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Case {
    Nothing,
    Hide(Effect),
}

impl Case {
    fn name(self) -> &'static str {
        match self {
            Case::Nothing => "none",
            Case::Hide(e) => e.name(),
        }
    }
}

pub(super) fn rand_dir(rng: &mut ChaCha8Rng) -> Vector3<f64> {
    loop {
        let v = Vector3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        );
        let n = v.norm();
        if n > 0.2 && n <= 1.0 {
            return v / n;
        }
    }
}

fn signed(rng: &mut ChaCha8Rng, lo: f64, hi: f64) -> f64 {
    let v = rng.random_range(lo..hi);
    if rng.random_bool(0.5) {
        v
    } else {
        -v
    }
}

/// A sensor truth with a diagonal matrix: offsets drawn within +-`offset`, then scales within
/// 1 +- `scale`, then the noise `noise_sd`.
fn diag_truth(rng: &mut ChaCha8Rng, offset: f64, scale: f64, noise_sd: f64) -> SensorTruth {
    let offset = std::array::from_fn(|_| rng.random_range(-offset..offset));
    let d: [f64; 3] = std::array::from_fn(|_| 1.0 + rng.random_range(-scale..scale));
    SensorTruth {
        offset,
        matrix: [[d[0], 0.0, 0.0], [0.0, d[1], 0.0], [0.0, 0.0, d[2]]],
        noise_sd,
    }
}

/// A bench scenario with a diag6-exact truth (so the base model is right when nothing is hidden).
pub(super) fn base_bench(rng: &mut ChaCha8Rng) -> Scenario {
    let mut sc = Scenario::named("bench").unwrap();
    sc.truth.rate_hz = 50.0;
    sc.pauses = rng.random_range(20..=30);
    sc.bench = BenchSettings {
        levels: vec![0.0, 0.3, 0.6, 0.9],
        level_s: 1.0,
        temp_swing_c: rng.random_range(10.0..20.0),
        log_current: rng.random_bool(0.5),
    };
    sc.slew_s = [0.8, 1.2];
    sc.temp_c = rng.random_range(15.0..30.0);
    sc.truth.mag = diag_truth(rng, 40.0, 0.05, 0.15);
    sc.truth.accel = diag_truth(rng, 0.1, 0.01, 0.02);
    sc.reference_noise_deg = if rng.random_bool(0.7) {
        Some(0.05)
    } else {
        None
    };
    sc
}

/// Symmetric off-diagonal terms xy, xz, yz into `m`, each of size `lo..hi` and random sign.
fn cross_axis(rng: &mut ChaCha8Rng, m: &mut [[f64; 3]; 3], lo: f64, hi: f64) {
    for (i, j) in [(0, 1), (0, 2), (1, 2)] {
        let v = signed(rng, lo, hi);
        m[i][j] = v;
        m[j][i] = v;
    }
}

/// Put the effect of `case` into `sc`, sized by `scale` (1 = the drawn size).
fn hide(case: Case, sc: &mut Scenario, rng: &mut ChaCha8Rng) {
    let mut fx = Effects::default();
    match case {
        Case::Nothing => {}
        Case::Hide(Effect::CrossAxis) => {
            cross_axis(rng, &mut sc.truth.mag.matrix, 0.01, 0.04);
            if rng.random_bool(0.5) {
                cross_axis(rng, &mut sc.truth.accel.matrix, 0.003, 0.01);
            }
        }
        Case::Hide(Effect::MagAccelMisalignment) => {
            let v = rand_dir(rng) * rng.random_range(0.5..3.0);
            fx.mag_accel_rotation_deg = Some([v.x, v.y, v.z]);
        }
        Case::Hide(Effect::TemperatureBias) => {
            let mode = rng.random_range(0..3);
            let mut tb = TemperatureBias {
                mag_ut_per_c: [0.0; 3],
                accel_mps2_per_c: [0.0; 3],
                ref_temp_c: 25.0,
            };
            if mode != 1 {
                let v = rand_dir(rng) * rng.random_range(0.05..0.15);
                tb.mag_ut_per_c = [v.x, v.y, v.z];
            }
            if mode != 0 {
                let v = rand_dir(rng) * rng.random_range(0.006..0.015);
                tb.accel_mps2_per_c = [v.x, v.y, v.z];
            }
            fx.temperature_bias = Some(tb);
        }
        Case::Hide(Effect::MotorInterference) => {
            let current = sc.bench.log_current;
            let size = if current {
                rng.random_range(0.1..0.4)
            } else {
                rng.random_range(2.0..10.0)
            };
            let v = rand_dir(rng) * size;
            fx.motor_interference = Some([v.x, v.y, v.z]);
            fx.motor_driver = if current {
                MotorDriver::Current
            } else {
                MotorDriver::Throttle
            };
        }
        Case::Hide(Effect::HeadingOffset) => {
            sc.reference_noise_deg = Some(0.05);
            fx.heading_offset_deg = Some(signed(rng, 0.5, 3.0));
        }
        Case::Hide(Effect::ScaleNonlinearity) => {
            let mut c = ScaleCubic::default();
            for k in 0..3 {
                c.mag[k] = signed(rng, 0.02, 0.05);
            }
            if rng.random_bool(0.5) {
                for k in 0..3 {
                    c.accel[k] = signed(rng, 0.01, 0.03);
                }
            }
            fx.scale_cubic = Some(c);
        }
        Case::Hide(Effect::GyroBiasDrift) => {
            let total = rng.random_range(0.01..0.03);
            let v = rand_dir(rng) * total;
            // Length of the run: poses x (hold + slew).
            let dur = sc.pauses as f64 * (4.0 + 1.0);
            let mut d = GyroBiasDrift {
                rad_s_per_s: [0.0; 3],
                rad_s_per_c: [0.0; 3],
                ref_temp_c: 25.0,
            };
            if rng.random_bool(0.5) {
                d.rad_s_per_s = [v.x / dur, v.y / dur, v.z / dur];
            } else {
                let sw = sc.bench.temp_swing_c;
                d.rad_s_per_c = [v.x / sw, v.y / sw, v.z / sw];
            }
            fx.gyro_bias_drift = Some(d);
        }
    }
    sc.effects = fx;
}

/// Largest change of the tilt-compensated heading at the static poses that the hidden effect
/// causes (same seed, same noise; the calibration of the effect-free truth), degrees.
fn heading_shift_deg(case: Case, with: &Scenario, without: &Scenario, seed: u64) -> f64 {
    match case {
        Case::Nothing => return 0.0,
        Case::Hide(Effect::HeadingOffset) => {
            return with.effects.heading_offset_deg.unwrap_or(0.0).abs()
        }
        Case::Hide(Effect::GyroBiasDrift) => {
            // Heading error integrated by a gyro whose bias is taken as constant: the drift's
            // departure from its mean, integrated over the run.
            let d = with.effects.gyro_bias_drift.unwrap();
            let a = simulate(with, seed);
            let b = simulate(without, seed);
            let dt = 1.0 / a.truth.rate_hz;
            let mut acc = Vector3::zeros();
            let n = a.samples.len();
            let mut diffs = vec![];
            for (sa, sb) in a.samples.iter().zip(&b.samples) {
                let ga = v3(&sa.gyro_rad_s.unwrap());
                let gb = v3(&sb.gyro_rad_s.unwrap());
                diffs.push(ga - gb);
            }
            let mean = diffs.iter().fold(Vector3::zeros(), |s, v| s + v) / n as f64;
            let mut worst: f64 = 0.0;
            for dv in &diffs {
                acc += (dv - mean) * dt;
                worst = worst.max(acc.norm());
            }
            let _ = d;
            return worst.to_degrees();
        }
        _ => {}
    }
    let a = simulate(with, seed);
    let b = simulate(without, seed);
    let ca = without.truth.accel.calibration();
    let cm = without.truth.mag.calibration();
    let mut worst: f64 = 0.0;
    for p in &a.truth.poses {
        let mean = |out: &crate::sim::SimOutput, f: &dyn Fn(&Sample) -> Vec3| {
            let v: Vec<Vec3> = out
                .samples
                .iter()
                .filter(|s| s.t_s >= p.t_start && s.t_s < p.t_end)
                .map(f)
                .collect();
            let n = v.len() as f64;
            v.iter().fold([0.0; 3], |s, x| {
                [s[0] + x[0] / n, s[1] + x[1] / n, s[2] + x[2] / n]
            })
        };
        let h = |out: &crate::sim::SimOutput| {
            let acc = ca.apply(&mean(out, &|s| s.accel_mps2.unwrap()));
            let mag = cm.apply(&mean(out, &|s| s.mag_ut.unwrap()));
            crate::attitude::attitude_deg(&acc, &mag, None).2
        };
        worst = worst.max(crate::attitude::angle_diff_deg(h(&a), h(&b)).abs());
    }
    worst
}

pub(super) struct Blind {
    pub samples: Vec<Sample>,
    pub shift_deg: f64,
}

/// Generate a blind case: random sizes and log, the effect scaled up until it moves the heading by
/// at least 0.5 deg.
pub(super) fn generate(case: Case, seed: u64) -> Blind {
    let mut rng = ChaCha8Rng::seed_from_u64(
        seed.wrapping_mul(7919)
            .wrapping_add(case.name().len() as u64 * 104729),
    );
    let base = base_bench(&mut rng);
    let mut sc = base.clone();
    hide(case, &mut sc, &mut rng);
    let mut without = sc.clone();
    without.effects = Effects::default();
    without.truth = base.truth.clone();
    let mut shift = heading_shift_deg(case, &sc, &without, seed);
    let mut tries = 0;
    while case != Case::Nothing && shift < 0.5 && tries < 8 {
        // Grow the hidden effect by 1.5x.
        scale_effect(case, &mut sc, &base, 1.5);
        shift = heading_shift_deg(case, &sc, &without, seed);
        tries += 1;
    }
    // The diagnoser sees only the log: written as CSV and read back through the log reader.
    let samples = simulate(&sc, seed).samples;
    let dir = std::env::temp_dir().join(format!(
        "imucald-blind-{}-{}-{seed}",
        std::process::id(),
        case.name()
    ));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("blind.csv");
    crate::io::samplelog::write_csv(&path, &samples).unwrap();
    let log = crate::io::sources::read_log(&path, None, &Default::default()).unwrap();
    let _ = std::fs::remove_dir_all(&dir);
    assert_eq!(log.samples.len(), samples.len());
    Blind {
        samples: log.samples,
        shift_deg: shift,
    }
}

fn scale_effect(case: Case, sc: &mut Scenario, base: &Scenario, k: f64) {
    let s3 = |v: &mut [f64; 3]| v.iter_mut().for_each(|x| *x *= k);
    let fx = &mut sc.effects;
    match case {
        Case::Hide(Effect::CrossAxis) => {
            for (m, b) in [
                (&mut sc.truth.mag.matrix, &base.truth.mag.matrix),
                (&mut sc.truth.accel.matrix, &base.truth.accel.matrix),
            ] {
                for i in 0..3 {
                    for j in 0..3 {
                        if i != j {
                            m[i][j] = b[i][j] + (m[i][j] - b[i][j]) * k;
                        }
                    }
                }
            }
        }
        Case::Hide(Effect::MagAccelMisalignment) => {
            fx.mag_accel_rotation_deg.iter_mut().for_each(s3)
        }
        Case::Hide(Effect::TemperatureBias) => {
            if let Some(t) = fx.temperature_bias.as_mut() {
                s3(&mut t.mag_ut_per_c);
                s3(&mut t.accel_mps2_per_c);
            }
        }
        Case::Hide(Effect::MotorInterference) => fx.motor_interference.iter_mut().for_each(s3),
        Case::Hide(Effect::HeadingOffset) => fx.heading_offset_deg.iter_mut().for_each(|x| *x *= k),
        Case::Hide(Effect::ScaleNonlinearity) => {
            if let Some(c) = fx.scale_cubic.as_mut() {
                s3(&mut c.mag);
                s3(&mut c.accel);
            }
        }
        Case::Hide(Effect::GyroBiasDrift) => {
            if let Some(d) = fx.gyro_bias_drift.as_mut() {
                s3(&mut d.rad_s_per_s);
                s3(&mut d.rad_s_per_c);
            }
        }
        Case::Nothing => {}
    }
}

/// The scorer: a case is right when exactly the hidden effect is named (nothing for the no-effect
/// case) and, when an effect was named, the held-out RMS shrank at least 2x.
pub(super) fn score(case: Case, r: &DiagnosisReport) -> (bool, bool) {
    let named_ok = match case {
        Case::Nothing => r.found.is_empty(),
        Case::Hide(e) => r.found == vec![e],
    };
    let shrink_ok = case == Case::Nothing || r.rms_before / r.rms_after >= 2.0;
    (named_ok, shrink_ok)
}

fn run_case(case: Case, seeds: std::ops::Range<u64>, verbose: bool) -> (usize, usize, usize, f64) {
    let cfg = Config::default();
    let (mut named, mut shrunk, mut n) = (0, 0, 0);
    let mut min_shift = f64::INFINITY;
    for seed in seeds {
        let b = generate(case, seed);
        min_shift = min_shift.min(b.shift_deg);
        let r = diagnose(
            &b.samples,
            &cfg,
            &DiagnoseOptions {
                seed,
                ..Default::default()
            },
        );
        let (ok, sh) = score(case, &r);
        named += ok as usize;
        shrunk += sh as usize;
        n += 1;
        if verbose || !ok || !sh {
            eprintln!(
                "[{}] seed {seed} (shift {:.2} deg): {}",
                case.name(),
                b.shift_deg,
                r.outcome()
            );
            if !ok || std::env::var("TABLE").is_ok() {
                eprintln!("{}", summary_table(&r));
            }
        }
    }
    (named, shrunk, n, min_shift)
}

#[test]
#[ignore = "exploration harness (CASE=, N=, FIRST=): prints per-seed tables, asserts nothing"]
fn explore() {
    let which = std::env::var("CASE").unwrap_or_default();
    let n: u64 = std::env::var("N")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(3);
    let first: u64 = std::env::var("FIRST")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    let mut cases = vec![Case::Nothing];
    cases.extend(Effect::ALL.iter().map(|e| Case::Hide(*e)));
    for c in cases {
        if !which.is_empty() && c.name() != which {
            continue;
        }
        let t = std::time::Instant::now();
        let (a, b, n, _) = run_case(c, first..first + n, true);
        eprintln!(
            "== {}: named {a}/{n}, shrink {b}/{n}, {:.1} s",
            c.name(),
            t.elapsed().as_secs_f64()
        );
    }
}

// -----------------------------------------------------------------------------------------
// Real recordings (tyrex phone magnetometer tumbles) with a synthetic motor field.

fn tyrex(set: &str) -> Option<Vec<Sample>> {
    let data = crate::testdata::shared_data()?;
    let path = data.join(format!("tyrex/{set}.csv.gz"));
    let log = crate::io::sources::read_log(&path, None, &Default::default())
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    Some(log.samples)
}

/// A stepped throttle signal (levels 0..0.8 held 1.5-3 s), set on every sample; when `k` is
/// given, `k * throttle` is added to every magnetometer reading.
fn with_throttle(samples: &[Sample], seed: u64, k: Option<[f64; 3]>) -> Vec<Sample> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut out = samples.to_vec();
    let mut next = f64::NEG_INFINITY;
    let mut level = 0.0;
    for s in out.iter_mut() {
        if s.t_s >= next {
            level = rng.random_range(0.0..0.8);
            next = s.t_s + rng.random_range(1.5..3.0);
        }
        s.throttle = Some(level);
        if let (Some(k), Some(m)) = (k, s.mag_ut.as_mut()) {
            for j in 0..3 {
                m[j] += k[j] * level;
            }
        }
    }
    out
}

fn named(r: &DiagnosisReport, e: Effect) -> bool {
    r.found.contains(&e)
}

#[test]
fn tyrex_injected_motor_field_is_named_and_recovered() {
    // |k| = 15.2 uT per unit throttle: ~30% of the earth field at full throttle, a typical
    // compassmot size. Three throttle step patterns per recording.
    let k_true = [8.0, -5.0, 12.0];
    for set in ["calib_mag_Nexus5_d1", "calib_mag_Nexus5_d3"] {
        let Some(samples) = tyrex(set) else { return };
        for seed in [11u64, 12, 13] {
            let s = with_throttle(&samples, seed, Some(k_true));
            let r = diagnose(&s, &Config::default(), &DiagnoseOptions::default());
            if seed == 11 {
                eprintln!("{set} + k {k_true:?} uT/throttle:\n{}", summary_table(&r));
            }
            assert!(
                named(&r, Effect::MotorInterference),
                "{set}: found {:?}",
                r.found
            );
            assert!(!named(&r, Effect::TemperatureBias));
            let p = &r.effects["motor_interference"];
            let k = [p["k_x"].value, p["k_y"].value, p["k_z"].value];
            let err = ((k[0] - k_true[0]).powi(2)
                + (k[1] - k_true[1]).powi(2)
                + (k[2] - k_true[2]).powi(2))
            .sqrt();
            let size = (k_true.iter().map(|x| x * x).sum::<f64>()).sqrt();
            eprintln!(
                "{set} throttle seed {seed}: found {:?}, k [{:.2}, {:.2}, {:.2}], error {:.2} uT = {:.1}% of |k|",
                r.found, k[0], k[1], k[2], err, 100.0 * err / size
            );
            assert!(err < 0.1 * size, "{set}: k {k:?} vs {k_true:?}");
        }
    }
}

#[test]
fn tyrex_untouched_names_no_motor_or_temperature_effect() {
    for set in ["calib_mag_Nexus5_d1", "calib_mag_Nexus5_d3"] {
        let Some(samples) = tyrex(set) else { return };
        // As recorded (no throttle, no temperature) and with a throttle signal that drives nothing.
        for (what, s) in [
            ("as recorded", samples.clone()),
            ("placebo throttle", with_throttle(&samples, 5, None)),
        ] {
            let r = diagnose(&s, &Config::default(), &DiagnoseOptions::default());
            eprintln!("{set} ({what}):\n{}", summary_table(&r));
            assert!(
                !named(&r, Effect::MotorInterference),
                "{set} {what}: {:?}",
                r.found
            );
            assert!(
                !named(&r, Effect::TemperatureBias),
                "{set} {what}: {:?}",
                r.found
            );
        }
    }
}

#[test]
#[ignore = "exploration harness: prints recovered coefficients for several sizes, asserts nothing"]
fn tyrex_explore_motor() {
    for set in ["calib_mag_Nexus5_d1", "calib_mag_Nexus5_d3"] {
        let Some(samples) = tyrex(set) else { return };
        for (seed, k_true) in [
            (1u64, [3.0, 2.0, -4.0]),
            (2, [-10.0, 6.0, 2.0]),
            (3, [5.0, 5.0, 5.0]),
            (4, [0.0, -8.0, 3.0]),
            (5, [2.0, 1.0, 1.5]),
            (6, [15.0, -10.0, 20.0]),
        ] {
            let s = with_throttle(&samples, seed, Some(k_true));
            let r = diagnose(&s, &Config::default(), &DiagnoseOptions::default());
            let k = r
                .effects
                .get("motor_interference")
                .map(|p| [p["k_x"].value, p["k_y"].value, p["k_z"].value]);
            let err = k.map(|k| {
                ((k[0] - k_true[0]).powi(2)
                    + (k[1] - k_true[1]).powi(2)
                    + (k[2] - k_true[2]).powi(2))
                .sqrt()
                    / k_true.iter().map(|x| x * x).sum::<f64>().sqrt()
            });
            eprintln!(
                "{set} seed {seed} k {k_true:?}: found {:?} k {:?} rel err {:?}",
                r.found, k, err
            );
        }
        for seed in 10..20 {
            let s = with_throttle(&samples, seed, None);
            let r = diagnose(&s, &Config::default(), &DiagnoseOptions::default());
            eprintln!("{set} placebo seed {seed}: found {:?}", r.found);
        }
    }
}

/// A bench log whose mag bias wanders sinusoidally in time (3 periods over the run, 1-2 uT): an
/// effect outside the catalogue.
fn wander_case(seed: u64) -> Vec<Sample> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed + 5000);
    let mut sc = base_bench(&mut rng);
    let dur = sc.pauses as f64 * 5.0;
    let v = rand_dir(&mut rng) * rng.random_range(1.0..2.0);
    sc.effects.mag_bias_wander = Some(crate::sim::BiasWander {
        amplitude_ut: [v.x, v.y, v.z],
        period_s: dur / 3.0,
    });
    simulate(&sc, seed).samples
}

/// A bench log with a motor field where the temperature follows the throttle (motors heating the
/// board at once): motor_interference and temperature_bias cannot be told apart.
fn collinear_case(seed: u64) -> Vec<Sample> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed + 7000);
    let mut sc = base_bench(&mut rng);
    sc.bench.log_current = false;
    let v = rand_dir(&mut rng) * rng.random_range(3.0..8.0);
    sc.effects.motor_interference = Some([v.x, v.y, v.z]);
    let mut s = simulate(&sc, seed).samples;
    for x in s.iter_mut() {
        x.temp_c = Some(30.0 + 12.0 * x.throttle.unwrap_or(0.0));
    }
    s
}

#[test]
#[ignore = "exploration harness: prints the decisions on the special cases, asserts nothing"]
fn explore_special() {
    for seed in 0..10 {
        let r = diagnose(
            &wander_case(seed),
            &Config::default(),
            &DiagnoseOptions::default(),
        );
        let last = r.rounds.last().unwrap();
        eprintln!(
            "wander {seed}: found {:?}; {} {:?}: {}",
            r.found, last.decision, last.effect, last.detail
        );
        let r = diagnose(
            &collinear_case(seed),
            &Config::default(),
            &DiagnoseOptions::default(),
        );
        let last = r.rounds.last().unwrap();
        eprintln!(
            "collinear {seed}: found {:?}; {} {:?}: {}",
            r.found, last.decision, last.effect, last.detail
        );
    }
}

// -----------------------------------------------------------------------------------------
// Blind tests: the generator hides one effect (or none), the diagnoser sees only the samples.
// Score table: `cargo test --release --lib diagnose::tests::blind -- --nocapture`.

fn blind(case: Case) {
    let (named, shrunk, n, min_shift) = run_case(case, 0..20, false);
    eprintln!(
        "BLIND {:<24} named correctly {named}/{n}, held-out RMS shrank >= 2x {}, smallest heading shift {}",
        case.name(),
        if case == Case::Nothing {
            "n/a".to_string()
        } else {
            format!("{shrunk}/{n}")
        },
        if case == Case::Nothing {
            "n/a".to_string()
        } else {
            format!("{min_shift:.2} deg")
        }
    );
    if case != Case::Nothing {
        // Every hidden effect is at least as large as the issue asks: 0.5 deg of heading.
        assert!(min_shift >= 0.5, "{}: {min_shift} deg", case.name());
    }
    assert!(named >= 19, "{}: {named}/{n}", case.name());
    assert!(shrunk >= 19, "{}: {shrunk}/{n}", case.name());
}

/// One blind test per case: `name => case`.
macro_rules! blind_tests {
    ($($name:ident => $case:expr),* $(,)?) => {
        $(
            #[test]
            fn $name() {
                blind($case)
            }
        )*
    };
}

blind_tests! {
    blind_none => Case::Nothing,
    blind_cross_axis => Case::Hide(Effect::CrossAxis),
    blind_mag_accel_misalignment => Case::Hide(Effect::MagAccelMisalignment),
    blind_temperature_bias => Case::Hide(Effect::TemperatureBias),
    blind_motor_interference => Case::Hide(Effect::MotorInterference),
    blind_heading_offset => Case::Hide(Effect::HeadingOffset),
    blind_scale_nonlinearity => Case::Hide(Effect::ScaleNonlinearity),
    blind_gyro_bias_drift => Case::Hide(Effect::GyroBiasDrift),
}

/// Seeds 0-4 of `case`: nothing named, and the last round's decision is `decision`; its details.
fn decided_without_effect(case: fn(u64) -> Vec<Sample>, decision: Decision) -> Vec<String> {
    (0..5)
        .map(|seed| {
            let r = diagnose(&case(seed), &Config::default(), &DiagnoseOptions::default());
            let last = r.rounds.last().unwrap();
            assert!(r.found.is_empty(), "seed {seed}: {:?}", r.found);
            assert_eq!(last.decision, decision, "seed {seed}: {}", last.detail);
            last.detail.clone()
        })
        .collect()
}

#[test]
fn effect_outside_the_catalogue_is_unexplained() {
    for detail in decided_without_effect(wander_case, Decision::Unexplained) {
        assert!(detail.contains("mag_norm"), "{detail}");
    }
}

#[test]
fn collinear_drivers_are_not_identifiable() {
    for detail in decided_without_effect(collinear_case, Decision::NotIdentifiable) {
        assert!(
            detail.contains("motor_interference") && detail.contains("temperature_bias"),
            "{detail}"
        );
    }
}

#[test]
fn report_json_contract() {
    let b = generate(Case::Hide(Effect::MotorInterference), 3);
    let r = diagnose(&b.samples, &Config::default(), &DiagnoseOptions::default());
    let v: serde_json::Value = serde_json::to_value(&r).unwrap();
    assert_eq!(v["schema"], "imucald.diagnosis/1");
    assert_eq!(v["found"], serde_json::json!(["motor_interference"]));
    let rounds = v["rounds"].as_array().unwrap();
    assert_eq!(rounds[0]["round"], 1);
    assert_eq!(rounds[0]["decision"], "named");
    assert_eq!(rounds[0]["effect"], "motor_interference");
    let allowed = ["named", "none", "unexplained", "not_identifiable"];
    for rd in rounds {
        assert!(allowed.contains(&rd["decision"].as_str().unwrap()));
        for c in rd["candidates"].as_array().unwrap() {
            for key in [
                "name",
                "statistic",
                "p_value",
                "improvement",
                "plausible",
                "identifiable",
            ] {
                assert!(c.get(key).is_some(), "candidate lacks {key}: {c}");
            }
            assert!(Effect::parse(c["name"].as_str().unwrap()).is_some());
        }
    }
    assert!(v["rms_before"].as_f64().unwrap() > 2.0 * v["rms_after"].as_f64().unwrap());
    let k = &v["effects"]["motor_interference"];
    for a in ["k_x", "k_y", "k_z"] {
        assert!(
            k[a]["value"].is_f64() && k[a]["sigma"].as_f64().unwrap() > 0.0,
            "{k}"
        );
    }
    // Round trip.
    let back: DiagnosisReport = serde_json::from_value(v).unwrap();
    assert_eq!(back.found, r.found);
    let t = summary_table(&r);
    assert!(
        t.contains("round 1: named motor_interference") && t.contains("k_x"),
        "{t}"
    );
}

#[test]
fn nothing_to_compare_is_reported_not_panicked() {
    let r = diagnose(&[], &Config::default(), &DiagnoseOptions::default());
    assert!(r.found.is_empty());
    assert_eq!(r.rounds[0].decision, Decision::NotIdentifiable);
    // Sym9 base: cross_axis is part of the base, not a candidate.
    let b = generate(Case::Nothing, 1);
    let r = diagnose(
        &b.samples,
        &Config::default(),
        &DiagnoseOptions {
            base_model: ModelKind::Sym9,
            ..Default::default()
        },
    );
    assert!(r.found.is_empty(), "{:?}", r.found);
    let ca = r.rounds[0]
        .candidates
        .iter()
        .find(|c| c.name == "cross_axis")
        .unwrap();
    assert!(!ca.identifiable && ca.note.contains("base model"));
}
