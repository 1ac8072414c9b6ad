//! Diagnosis of effects whose real form is not the one the catalogue fits: the field grows with the
//! square of the throttle, the bias follows the temperature with a lag, the field follows the motor
//! current while the log has only the throttle, the field follows the motor with a delay. The
//! catalogue's linear motor term only approximates the first two; the temperature and motor
//! terms follow a fitted lag. The tests measure how often the right effect is still named, how far the held-out
//! residual shrinks and, for the temperature, how close the fitted lag comes to the hidden one.

use super::tests::{base_bench, rand_dir};
use super::*;
use crate::sim::{simulate, MotorDriver};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// The hidden effect's form.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Form {
    /// Field `k * throttle^2` (the catalogue fits `k * throttle`).
    ThrottleSquared,
    /// Mag (and accel) bias linear in a first-order lag of the logged temperature (time constant
    /// 5-15 s on a run of 100-150 s whose temperature is a half sine).
    TemperatureShortLag,
    /// The same with a time constant of 20-60 s: the bias loops against the logged temperature.
    TemperatureLongLag,
    /// Field `k * current` with the current `0.3 + 30 throttle^1.5` A not logged: only the throttle
    /// is there to fit against.
    CurrentNotLogged,
    /// Field `k * y`, `y` a first-order lag of the throttle (time constant 0.1-0.4 s; levels are held
    /// 1 s): the field settles after each step, and the catalogue's lag follows it.
    FieldLagsMotor,
}

impl Form {
    const ALL: [Form; 5] = [
        Form::ThrottleSquared,
        Form::TemperatureShortLag,
        Form::TemperatureLongLag,
        Form::CurrentNotLogged,
        Form::FieldLagsMotor,
    ];
    fn name(self) -> &'static str {
        match self {
            Form::ThrottleSquared => "throttle_squared",
            Form::TemperatureShortLag => "temperature_lag_5_15s",
            Form::TemperatureLongLag => "temperature_lag_20_60s",
            Form::CurrentNotLogged => "current_not_logged",
            Form::FieldLagsMotor => "field_lags_motor",
        }
    }
    /// The catalogue effect that should be named.
    fn effect(self) -> Effect {
        match self {
            Form::TemperatureShortLag | Form::TemperatureLongLag => Effect::TemperatureBias,
            _ => Effect::MotorInterference,
        }
    }
}

/// First-order lag (time constant `tau_s`) of `x` along the samples, starting at the first value.
fn lagged(samples: &[Sample], x: impl Fn(&Sample) -> f64, tau_s: f64) -> Vec<f64> {
    let mut out = Vec::with_capacity(samples.len());
    let mut prev: Option<(f64, f64)> = None;
    for s in samples {
        let v = x(s);
        let y = match prev {
            None => v,
            Some((yp, tp)) => yp + (1.0 - (-(s.t_s - tp).max(0.0) / tau_s).exp()) * (v - yp),
        };
        out.push(y);
        prev = Some((y, s.t_s));
    }
    out
}

fn add(v: &mut Option<crate::types::Vec3>, k: &Vector3<f64>, x: f64) {
    if let Some(v) = v.as_mut() {
        for j in 0..3 {
            v[j] += k[j] * x;
        }
    }
}

use nalgebra::Vector3;

/// A bench log (random truth as in the blind tests, no current logged) with the effect of `form`,
/// and the hidden lag of the temperature forms (s).
fn generate(form: Form, seed: u64) -> (Vec<Sample>, Option<f64>) {
    let mut rng =
        ChaCha8Rng::seed_from_u64(seed.wrapping_mul(7919).wrapping_add(31 * (1 + form as u64)));
    let mut sc = base_bench(&mut rng);
    sc.bench.log_current = false;
    if form == Form::CurrentNotLogged {
        // 0.1-0.4 uT/A: 2.5 to 10 uT at the top level (21 A).
        let k = rand_dir(&mut rng) * rng.random_range(0.1..0.4);
        sc.effects.motor_interference = Some([k.x, k.y, k.z]);
        sc.effects.motor_driver = MotorDriver::Current;
        return (simulate(&sc, seed).samples, None);
    }
    let mut s = simulate(&sc, seed).samples;
    let thr = |x: &Sample| x.throttle.unwrap_or(0.0);
    let mut hidden_lag = None;
    match form {
        Form::ThrottleSquared => {
            // 3-10 uT per unit throttle squared: 2.4 to 8 uT at the top level (0.9).
            let k = rand_dir(&mut rng) * rng.random_range(3.0..10.0);
            for x in s.iter_mut() {
                let t = thr(x);
                add(&mut x.mag_ut, &k, t * t);
            }
        }
        Form::FieldLagsMotor => {
            let k = rand_dir(&mut rng) * rng.random_range(2.0..10.0);
            let tau = rng.random_range(0.1..0.4);
            let y = lagged(&s, thr, tau);
            for (x, y) in s.iter_mut().zip(y) {
                add(&mut x.mag_ut, &k, y);
            }
            hidden_lag = Some(tau);
        }
        Form::TemperatureShortLag | Form::TemperatureLongLag => {
            let tau = if form == Form::TemperatureShortLag {
                rng.random_range(5.0..15.0)
            } else {
                rng.random_range(20.0..60.0)
            };
            let km = rand_dir(&mut rng) * rng.random_range(0.05..0.15);
            let ka = if rng.random_bool(0.5) {
                rand_dir(&mut rng) * rng.random_range(0.006..0.015)
            } else {
                Vector3::zeros()
            };
            let y = lagged(&s, |x| x.temp_c.unwrap_or(25.0), tau);
            for (x, y) in s.iter_mut().zip(y) {
                add(&mut x.mag_ut, &km, y - 25.0);
                add(&mut x.accel_mps2, &ka, y - 25.0);
            }
            hidden_lag = Some(tau);
        }
        Form::CurrentNotLogged => unreachable!("simulated above"),
    }
    (s, hidden_lag)
}

/// Over `n` seeds: how often exactly the right effect is named, how often it is named at all (other
/// effects besides), and the held-out RMS shrink (before / after) of each seed.
struct Tally {
    exact: usize,
    among: usize,
    /// Seeds where an effect other than the right one was named.
    wrong: usize,
    /// Seeds whose last round says "unexplained".
    unexplained: usize,
    n: usize,
    shrink: Vec<f64>,
    /// Lagged forms, seeds where the effect was named: |ln(fitted lag / hidden lag)|.
    lag_err: Vec<f64>,
}

fn tally(form: Form, n: u64) -> Tally {
    let mut t = Tally {
        exact: 0,
        among: 0,
        wrong: 0,
        unexplained: 0,
        n: 0,
        shrink: vec![],
        lag_err: vec![],
    };
    for seed in 0..n {
        let (s, hidden_lag) = generate(form, seed);
        let r = diagnose(
            &s,
            &Config::default(),
            &DiagnoseOptions {
                seed,
                ..Default::default()
            },
        );
        let e = form.effect();
        let exact = r.found == vec![e];
        let among = r.found.contains(&e);
        t.exact += exact as usize;
        t.among += among as usize;
        t.wrong += r.found.iter().any(|f| *f != e) as usize;
        t.unexplained += r
            .rounds
            .last()
            .is_some_and(|x| x.decision == Decision::Unexplained) as usize;
        t.n += 1;
        t.shrink.push(r.rms_before / r.rms_after);
        let fitted_lag = r
            .effects
            .get(e.name())
            .and_then(|p| p.get("lag_s"))
            .map(|p| p.value);
        if let (Some(h), Some(f)) = (hidden_lag, fitted_lag) {
            t.lag_err.push((f.max(1e-3) / h).ln().abs());
        }
        if !exact || std::env::var("MISMATCH_VERBOSE").is_ok() {
            eprintln!("[{}] seed {seed}: {}", form.name(), r.outcome());
        }
    }
    t.shrink.sort_by(|a, b| a.total_cmp(b));
    t.lag_err.sort_by(|a, b| a.total_cmp(b));
    if let Some(worst) = t.lag_err.last() {
        eprintln!(
            "MISMATCH {:<22} fitted lag / hidden lag: median within {:.0} %, worst {:.0} %",
            form.name(),
            100.0 * (t.lag_err[t.lag_err.len() / 2].exp() - 1.0),
            100.0 * (worst.exp() - 1.0)
        );
    }
    eprintln!(
        "MISMATCH {:<22} {} named exactly {}/{}, among others {}/{}, a wrong effect {}/{}, unexplained {}/{}; held-out RMS shrink median {:.2}x, smallest {:.2}x",
        form.name(),
        form.effect().name(),
        t.exact,
        t.n,
        t.among,
        t.n,
        t.wrong,
        t.n,
        t.unexplained,
        t.n,
        t.shrink[t.shrink.len() / 2],
        t.shrink[0]
    );
    t
}

#[test]
#[ignore = "measurement harness: prints the tallies of every form (MISMATCH_VERBOSE=1 for each seed)"]
fn measure_all_forms() {
    for f in Form::ALL {
        tally(f, 20);
    }
}

/// Bounds on a tally of 20 seeds. Counts allow about three times the measured misses (at least one);
/// shrink ratios allow a third of the measured gain over 1 (1 + (measured - 1) / 3).
struct Expect {
    min_exact: usize,
    max_wrong: usize,
    min_unexplained: usize,
    min_median_shrink: f64,
    min_smallest_shrink: f64,
    /// Lagged forms: the worst fitted lag's error against the hidden one, %.
    max_lag_err_pct: f64,
}

fn check(form: Form, x: Expect) {
    let t = tally(form, 20);
    let name = form.name();
    assert!(t.exact >= x.min_exact, "{name}: named {}/20", t.exact);
    assert!(
        t.wrong <= x.max_wrong,
        "{name}: wrong effect {}/20",
        t.wrong
    );
    assert!(
        t.unexplained >= x.min_unexplained,
        "{name}: unexplained {}/20",
        t.unexplained
    );
    let median = t.shrink[t.shrink.len() / 2];
    assert!(
        median >= x.min_median_shrink,
        "{name}: median shrink {median}"
    );
    assert!(
        t.shrink[0] >= x.min_smallest_shrink,
        "{name}: smallest shrink {}",
        t.shrink[0]
    );
    let worst_lag = t.lag_err.last().map_or(0.0, |e| 100.0 * (e.exp() - 1.0));
    assert!(
        worst_lag <= x.max_lag_err_pct,
        "{name}: fitted lag {worst_lag:.0} % from the hidden one"
    );
}

#[test]
fn throttle_squared_field_is_named_motor_interference_with_structure_left() {
    // Measured: named 20/20, wrong 0/20, the last round "unexplained" 20/20 (the quadratic part the
    // linear term leaves), shrink median 3.51x, smallest 3.25x.
    check(
        Form::ThrottleSquared,
        Expect {
            min_exact: 19,
            max_wrong: 1,
            min_unexplained: 14,
            min_median_shrink: 1.84,
            min_smallest_shrink: 1.75,
            max_lag_err_pct: f64::INFINITY,
        },
    );
}

#[test]
fn field_from_an_unlogged_current_is_named_motor_interference() {
    // Measured: named 20/20, wrong 0/20, unexplained 20/20, shrink median 5.58x, smallest 5.16x.
    check(
        Form::CurrentNotLogged,
        Expect {
            min_exact: 19,
            max_wrong: 1,
            min_unexplained: 14,
            min_median_shrink: 2.53,
            min_smallest_shrink: 2.39,
            max_lag_err_pct: f64::INFINITY,
        },
    );
}

#[test]
fn field_lagging_the_motor_is_named_motor_interference_with_its_lag() {
    // The motor field follows a first-order lag of the driver whose time constant is profiled on
    // a grid. Measured: named 20/20, wrong 0/20, unexplained 0/20, shrink median 11.49x, smallest
    // 5.91x (before the lag was fitted: unexplained 20/20, 3.14x and 1.72x); fitted lag within
    // 12 % of the hidden one (median), 20 % at worst.
    check(
        Form::FieldLagsMotor,
        Expect {
            min_exact: 19,
            max_wrong: 1,
            min_unexplained: 0,
            min_median_shrink: 4.5,
            min_smallest_shrink: 2.64,
            max_lag_err_pct: 60.0,
        },
    );
}

#[test]
fn temperature_bias_with_a_short_lag_is_named_with_its_lag() {
    // The temperature effect follows a first-order lag of the logged temperature whose time
    // constant is profiled on a grid. Measured: named 20/20, wrong 0/20, unexplained 0/20, shrink
    // median 5.89x, smallest 2.08x; fitted lag within 8 % of the hidden one (median),
    // 30 % at worst.
    check(
        Form::TemperatureShortLag,
        Expect {
            min_exact: 19,
            max_wrong: 1,
            min_unexplained: 0,
            min_median_shrink: 2.64,
            min_smallest_shrink: 1.43,
            max_lag_err_pct: 69.0,
        },
    );
}

#[test]
fn temperature_bias_with_a_long_lag_is_named_with_its_lag() {
    // A bias that follows the temperature 20-60 s late loops against the logged temperature; the
    // lagged form fits it. Measured: named 20/20, wrong 0/20, unexplained 0/20, shrink median
    // 6.77x, smallest 2.69x (before the lagged form: named 1/20, the rest "unexplained", shrink
    // 1.00x); fitted lag within 9 % of the hidden one (median), 35 % at worst.
    check(
        Form::TemperatureLongLag,
        Expect {
            min_exact: 19,
            max_wrong: 1,
            min_unexplained: 0,
            min_median_shrink: 2.89,
            min_smallest_shrink: 1.56,
            max_lag_err_pct: 60.0,
        },
    );
}
