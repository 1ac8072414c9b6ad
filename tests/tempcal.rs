//! Temperature calibration from a simulated warm-up at rest (`sim::warmup`): the hidden cubic
//! bias curves of three IMU instances recovered; warm-ups that span too few degrees or move are
//! refused with their reason; the ArduPilot and PX4 parameters named, scaled and ranged as the
//! stacks define them.

use imucald::calib::tempcal::export::{self, InstanceExport};
use imucald::calib::tempcal::{
    calibrate, Refusal, TempCal, TempCalSettings, TempOutcome, ARDUPILOT_SCALE,
};
use imucald::sim::warmup::{simulate, InstanceTruth, WarmupSettings, WarmupTurn};

fn calibrated(o: &TempOutcome) -> &TempCal {
    match o {
        TempOutcome::Calibrated(c) => c,
        TempOutcome::Refused(r) => panic!("refused: {r}"),
    }
}

/// The largest error of the fitted bias over the calibrated range, per sensor: accelerometer
/// (m/s^2, relative to the value at 35 C, as ArduPilot's has no constant) and gyro (rad/s).
fn largest_errors(c: &TempCal, truth: &InstanceTruth) -> [f64; 2] {
    let mut worst = [0.0f64; 2];
    for k in 0..=100 {
        let t = c.tmin_c + (c.tmax_c - c.tmin_c) * k as f64 / 100.0;
        for a in 0..3 {
            let acc = &c.accel.axes[a];
            let fit = acc.bias_at(t) - acc.bias_at(35.0);
            let truth_a = truth.bias(false, a, t) - truth.bias(false, a, 35.0);
            worst[0] = worst[0].max((fit - truth_a).abs());
            let gyr = c.gyro.axes[a].bias_at(t);
            worst[1] = worst[1].max((gyr - truth.bias(true, a, t)).abs());
        }
    }
    worst
}

#[test]
fn a_simulated_warm_up_gives_back_the_hidden_curves_of_every_instance() {
    let w = simulate(&WarmupSettings::default(), 11);
    let s = TempCalSettings::default();
    for (k, (samples, truth)) in w.instances.iter().zip(&w.truth).enumerate() {
        let r = calibrate(samples, &s);
        let c = calibrated(&r.outcome);
        assert!(
            c.tmin_c < 16.5 && c.tmax_c > 38.0,
            "{k}: {} .. {}",
            c.tmin_c,
            c.tmax_c
        );
        let [acc, gyr] = largest_errors(c, truth);
        // Measured (seed 11): largest errors 6.4e-3, 4.1e-3, 3.7e-3 m/s^2 and 1.1e-4, 1.5e-4,
        // 1.6e-4 rad/s over the three instances (the bins' standard errors about 1.2e-3 and
        // 1.2e-4; the rest is the temperature reading's lag); tolerances 3x the largest.
        assert!(acc < 0.02, "instance {k}: accel {acc}");
        assert!(gyr < 5e-4, "instance {k}: gyro {gyr}");
        let shrink = |axes: &[imucald::calib::tempcal::AxisCurve]| {
            axes.iter()
                .map(|a| a.held_out.expect("held-out score").shrink)
                .fold(f64::INFINITY, f64::min)
        };
        // Measured: the smallest held-out shrink 28 (accelerometer) and 4.4 (gyro) over the
        // instances; a third of it.
        assert!(shrink(&c.accel.axes) > 9.0, "instance {k}");
        assert!(shrink(&c.gyro.axes) > 1.5, "instance {k}");
    }
}

#[test]
fn a_warm_up_of_six_degrees_gives_no_calibration_and_says_why() {
    let ws = WarmupSettings {
        end_c: 21.0,
        instances: 1,
        ..Default::default()
    };
    let w = simulate(&ws, 5);
    let r = calibrate(&w.instances[0], &TempCalSettings::default());
    match &r.outcome {
        TempOutcome::Refused(Refusal::Span { span_c, min_span_c }) => {
            // The reading runs from 15 to just under 21 C (noise included).
            assert!(*span_c > 5.0 && *span_c < 6.2, "{span_c}");
            assert_eq!(*min_span_c, 10.0);
            let text = Refusal::Span {
                span_c: *span_c,
                min_span_c: *min_span_c,
            }
            .to_string();
            assert!(text.contains("under the 10 C needed"), "{text}");
        }
        o => panic!("{o:?}"),
    }
}

#[test]
fn a_warm_up_where_the_vehicle_is_turned_gives_no_calibration_and_says_how_much_it_moved() {
    let ws = WarmupSettings {
        instances: 1,
        turn: Some(WarmupTurn {
            at_s: 600.0,
            duration_s: 3.0,
            angle_deg: 25.0,
        }),
        ..Default::default()
    };
    let w = simulate(&ws, 6);
    let r = calibrate(&w.instances[0], &TempCalSettings::default());
    match &r.outcome {
        TempOutcome::Refused(Refusal::Motion {
            rotated_deg,
            moving_s,
            peak_rate_dps,
            ..
        }) => {
            eprintln!("turned: {rotated_deg} deg over {moving_s} s, peak {peak_rate_dps} deg/s");
            assert!(*rotated_deg > 2.0, "{rotated_deg}");
            assert!(*moving_s >= 2.0 && *moving_s < 10.0, "{moving_s}");
        }
        o => panic!("{o:?}"),
    }
}

#[test]
fn the_exports_name_scale_and_range_every_parameter_as_the_stacks_do() {
    let w = simulate(&WarmupSettings::default(), 12);
    let s = TempCalSettings::default();
    let results: Vec<_> = w.instances.iter().map(|x| calibrate(x, &s)).collect();
    let names = ["IMU0", "IMU1", "IMU2"];
    let list: Vec<InstanceExport<'_>> = results
        .iter()
        .enumerate()
        .map(|(k, r)| InstanceExport {
            index: k,
            name: names[k],
            device_id: Some(2_490_378 + k as u32),
            outcome: &r.outcome,
        })
        .collect();
    let ap = export::ardupilot_file(&list);
    let px4 = export::px4_file(&list);
    for (k, r) in results.iter().enumerate() {
        let c = calibrated(&r.outcome);
        let ap_params = export::ardupilot_params(k, c).unwrap();
        let n = k + 1;
        let mut want = vec![
            format!("INS_TCAL{n}_ENABLE"),
            format!("INS_TCAL{n}_TMIN"),
            format!("INS_TCAL{n}_TMAX"),
        ];
        for s in ["ACC", "GYR"] {
            for p in 1..=3 {
                for a in ["X", "Y", "Z"] {
                    want.push(format!("INS_TCAL{n}_{s}{p}_{a}"));
                }
            }
        }
        let got: Vec<&str> = ap_params.iter().map(|(n, _)| n.as_str()).collect();
        assert_eq!(got, want.iter().map(String::as_str).collect::<Vec<_>>());
        // x1e6: the file's GYR1_Z is the fitted rad/s per C times a million.
        let g1z = ap_params
            .iter()
            .find(|(n, _)| n.ends_with("GYR1_Z"))
            .unwrap()
            .1;
        assert!((g1z - c.gyro.axes[2].ardupilot[1] * ARDUPILOT_SCALE).abs() < 1e-9);
        assert_eq!(ARDUPILOT_SCALE, 1.0e6);
        let tmin = ap_params[1].1;
        let tmax = ap_params[2].1;
        assert!(tmax - tmin >= 10.0, "{tmin} {tmax}");
        for (name, v) in &ap_params {
            let (lo, hi) = export::documented_range(name);
            assert!(v.is_finite() && *v >= lo && *v <= hi, "{name} {v}");
            assert!(
                ap.contains(&format!("{name} ")),
                "{name} missing from the file"
            );
        }
        let px = export::px4_params(k, Some(2_490_378 + k as u32), c).unwrap();
        assert_eq!(px.len(), 2 * 16);
        for s in ['A', 'G'] {
            for suffix in ["ID", "TREF", "TMIN", "TMAX"] {
                assert!(px
                    .iter()
                    .any(|((n, _), _)| *n == format!("TC_{s}{k}_{suffix}")));
            }
            for p in 0..4 {
                for a in 0..3 {
                    assert!(px
                        .iter()
                        .any(|((n, _), int)| *n == format!("TC_{s}{k}_X{p}_{a}") && !int));
                }
            }
        }
        for ((name, v), int) in &px {
            let (lo, hi) = export::documented_range(name);
            assert!(v.is_finite() && *v >= lo && *v <= hi, "{name} {v}");
            let ty = if *int { "\t6\n" } else { "\t9\n" };
            assert!(px4.contains(&format!("1\t1\t{name}\t")), "{name}");
            assert_eq!(name.ends_with("_ID"), *int, "{name}");
            let line = px4
                .lines()
                .find(|l| l.contains(&format!("\t{name}\t")))
                .unwrap();
            assert!(format!("{line}\n").ends_with(ty), "{line}");
        }
        // PX4's TREF is the middle of the range and its offset is the same curve: the gyro's
        // X0..X3 about TREF give ArduPilot's cubic's value at any temperature.
        let tref = px
            .iter()
            .find(|((n, _), _)| *n == format!("TC_G{k}_TREF"))
            .unwrap()
            .0
             .1;
        assert!((tref - 0.5 * (tmin + tmax)).abs() < 1e-12);
        let x = |p: usize, a: usize| {
            px.iter()
                .find(|((n, _), _)| *n == format!("TC_G{k}_X{p}_{a}"))
                .unwrap()
                .0
                 .1
        };
        let dt = 38.0 - tref;
        let px4_at = x(0, 1) + x(1, 1) * dt + x(2, 1) * dt * dt + x(3, 1) * dt * dt * dt;
        assert!((px4_at - c.gyro.axes[1].bias_at(38.0)).abs() < 1e-12);
    }
    for (name, v) in [("TC_A_ENABLE", 1.0), ("TC_G_ENABLE", 1.0)] {
        let line = format!("1\t1\t{name}\t{v}\t6");
        assert!(px4.contains(&line), "{px4}");
        let (lo, hi) = export::documented_range(name);
        assert!(v >= lo && v <= hi);
    }
}

#[test]
fn a_replay_of_a_simulated_warm_up_reports_and_exports_its_temperature_calibration() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("warm.csv");
    let written = imucald::app::simulate::write_warmup(&out, 3, None).unwrap();
    assert_eq!(written.len(), 3);
    let exports = dir.path().join("exp");
    let opts = imucald::app::replay::ReplayOptions {
        export_dir: Some(exports.clone()),
        ..Default::default()
    };
    let cfg = imucald::config::Config::default();
    let r = imucald::app::replay::replay(&written[1], &cfg, &opts, &mut |_, _| {}).unwrap();
    let t = &r.report.temperature;
    assert_eq!(t.len(), 1);
    assert_eq!(t[0].onboard, imucald::report::OnboardTcal::NoParameters);
    let c = calibrated(&t[0].result.outcome);
    assert!(c.points >= 40, "{}", c.points);
    let json = serde_json::to_value(&r.report).unwrap();
    assert_eq!(json["temperature"][0]["status"], "calibrated");
    assert!(json["temperature"][0]["gyro"]["axes"][2]["held_out"]["shrink"].is_number());
    let summary = imucald::app::replay::summary(&r.report);
    assert!(
        summary.contains("temperature (primary, IMU 0)"),
        "{summary}"
    );
    let parm = std::fs::read_to_string(exports.join("tempcal_ardupilot.parm")).unwrap();
    assert!(parm.contains("\nINS_TCAL1_GYR3_Z "), "{parm}");
    let px4 = std::fs::read_to_string(exports.join("tempcal_px4.params")).unwrap();
    assert!(px4.contains("\tTC_G0_X3_2\t"), "{px4}");
}

#[test]
fn a_log_without_temperature_has_no_temperature_section() {
    let dir = tempfile::tempdir().unwrap();
    let w = simulate(
        &WarmupSettings {
            duration_s: 60.0,
            instances: 1,
            ..Default::default()
        },
        2,
    );
    let samples: Vec<_> = w.instances[0]
        .iter()
        .map(|s| imucald::types::Sample { temp_c: None, ..*s })
        .collect();
    let p = dir.path().join("cold.csv");
    imucald::io::samplelog::write_csv(&p, &samples).unwrap();
    let cfg = imucald::config::Config::default();
    let r = imucald::app::replay::replay(&p, &cfg, &Default::default(), &mut |_, _| {}).unwrap();
    assert!(r.report.temperature.is_empty());
    let json = serde_json::to_value(&r.report).unwrap();
    assert!(json.get("temperature").is_none(), "{json}");
    assert!(!imucald::app::replay::summary(&r.report).contains("temperature"));
}

/// ArduPilot's temperature correction as its parameters give it: per axis
/// `1e-6 * (c1 x + c2 x^2 + c3 x^3)`, x = T - 35 (T inside TMIN..TMAX, no calibration temperature).
fn ardupilot_correction(c: &[[f64; 3]; 3], temp_c: f64) -> [f64; 3] {
    let x = temp_c - 35.0;
    std::array::from_fn(|a| 1e-6 * (c[a][0] * x + c[a][1] * x * x + c[a][2] * x * x * x))
}

/// A DataFlash warm-up logged as ArduPilot logs it with INS_TCAL1_ENABLE `enable`: the readings
/// corrected by the INS_TCAL1_* curves (accelerometer `acc`, gyro `gyr`, 1e6 x per C^k).
fn ardupilot_corrected_log(
    path: &std::path::Path,
    enable: f64,
    acc: &[[f64; 3]; 3],
    gyr: &[[f64; 3]; 3],
) -> InstanceTruth {
    let w = simulate(
        &WarmupSettings {
            instances: 1,
            ..Default::default()
        },
        7,
    );
    let corrected: Vec<_> = w.instances[0]
        .iter()
        .map(|s| {
            let t = s.temp_c.unwrap();
            let (ca, cg) = (ardupilot_correction(acc, t), ardupilot_correction(gyr, t));
            let sub = |v: [f64; 3], c: [f64; 3]| std::array::from_fn(|a| v[a] - c[a]);
            imucald::types::Sample {
                accel_mps2: s.accel_mps2.map(|v| sub(v, ca)),
                gyro_rad_s: s.gyro_rad_s.map(|v| sub(v, cg)),
                ..*s
            }
        })
        .collect();
    let mut params = vec![
        ("INS_TCAL1_ENABLE".to_string(), enable),
        ("INS_TCAL1_TMIN".to_string(), 5.0),
        ("INS_TCAL1_TMAX".to_string(), 60.0),
    ];
    for (s, c) in [("ACC", acc), ("GYR", gyr)] {
        for (a, axis) in ["X", "Y", "Z"].iter().enumerate() {
            for (k, v) in c[a].iter().enumerate() {
                params.push((format!("INS_TCAL1_{s}{}_{axis}", k + 1), *v));
            }
        }
    }
    let extra = imucald::io::flightlog::write::DataflashExtra {
        params: &params,
        ..Default::default()
    };
    let onboard = imucald::io::flightlog::write::OnboardMag::example();
    imucald::io::flightlog::write::write_dataflash_with(path, &corrected, &onboard, &extra)
        .unwrap();
    w.truth[0].clone()
}

#[test]
fn an_enabled_onboard_temperature_correction_is_undone_before_fitting() {
    let dir = tempfile::tempdir().unwrap();
    // Steep onboard curves: over 15..40 C several times the tolerances below.
    let acc = [
        [4000.0, 20.0, 0.0],
        [-3000.0, 0.0, 1.0],
        [2500.0, -30.0, 0.0],
    ];
    let gyr = [[200.0, 0.0, 0.0], [-150.0, 2.0, 0.0], [120.0, 0.0, -0.1]];
    let cfg = imucald::config::Config::default();
    let mut errors = vec![];
    for enable in [1.0, 0.0] {
        let p = dir.path().join(format!("warm{enable}.bin"));
        let truth = ardupilot_corrected_log(&p, enable, &acc, &gyr);
        let r =
            imucald::app::replay::replay(&p, &cfg, &Default::default(), &mut |_, _| {}).unwrap();
        let t = &r.report.temperature;
        assert_eq!(t.len(), 1, "{t:?}");
        let want = if enable == 1.0 {
            imucald::report::OnboardTcal::Undone
        } else {
            imucald::report::OnboardTcal::NotEnabled
        };
        assert_eq!(t[0].onboard, want);
        errors.push(largest_errors(calibrated(&t[0].result.outcome), &truth));
    }
    // Measured (seed 7): undone, largest errors 3.2e-3 m/s^2 and 5.9e-5 rad/s (3x as
    // tolerance); not enabled (the readings as logged, what the onboard curve left), 6.8e-2 m/s^2
    // and 4.0e-3 rad/s (a third as the floor).
    assert!(errors[0][0] < 0.01 && errors[0][1] < 1.8e-4, "{errors:?}");
    assert!(errors[1][0] > 0.023 && errors[1][1] > 1.3e-3, "{errors:?}");
}

#[test]
fn a_dataflash_warm_up_of_three_imus_calibrates_each_into_one_parameter_file() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("warm.bin");
    let truth = dir.path().join("truth.json");
    let written = imucald::app::simulate::write_warmup(&out, 3, Some(&truth)).unwrap();
    assert_eq!(written, [out.clone(), truth.clone()]);
    let truths: Vec<InstanceTruth> =
        serde_json::from_str(&std::fs::read_to_string(&truth).unwrap()).unwrap();
    let exports = dir.path().join("exp");
    let opts = imucald::app::replay::ReplayOptions {
        export_dir: Some(exports.clone()),
        ..Default::default()
    };
    let cfg = imucald::config::Config::default();
    let r = imucald::app::replay::replay(&out, &cfg, &opts, &mut |_, _| {}).unwrap();
    let t = &r.report.temperature;
    let imus: Vec<usize> = t.iter().map(|r| r.imu).collect();
    assert_eq!(imus, [0, 1, 2], "{t:?}");
    let mut worst = [0.0f64; 2];
    for r in t {
        assert_eq!(r.onboard, imucald::report::OnboardTcal::NotEnabled);
        let e = largest_errors(calibrated(&r.result.outcome), &truths[r.imu]);
        worst = [worst[0].max(e[0]), worst[1].max(e[1])];
    }
    // Measured (seed 3): largest errors over the three instances 4.3e-3 m/s^2 and 1.1e-4 rad/s;
    // tolerances 3x.
    assert!(worst[0] < 0.013 && worst[1] < 3.3e-4, "{worst:?}");
    let parm = std::fs::read_to_string(exports.join("tempcal_ardupilot.parm")).unwrap();
    for n in 1..=3 {
        assert!(parm.contains(&format!("\nINS_TCAL{n}_ENABLE ")), "{parm}");
        assert!(parm.contains(&format!("\nINS_TCAL{n}_GYR1_X ")), "{parm}");
    }
    let px4 = std::fs::read_to_string(exports.join("tempcal_px4.params")).unwrap();
    assert!(px4.contains("\tTC_G2_X3_2\t"), "{px4}");
}

/// A replay whose one result is a temperature calibration succeeds (exit status 0, not 3:
/// nothing calibrated) and `next:` names the files to load.
#[test]
fn a_replay_that_only_calibrates_temperature_succeeds_and_says_to_load_its_files() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("warm.bin");
    let exports = dir.path().join("exp");
    let imucald = |args: &[&std::ffi::OsStr]| {
        std::process::Command::new(env!("CARGO_BIN_EXE_imucald"))
            .args(args)
            .output()
            .unwrap()
    };
    let sim = imucald(&[
        "simulate".as_ref(),
        "--scenario".as_ref(),
        "warmup".as_ref(),
        "--out".as_ref(),
        log.as_os_str(),
    ]);
    assert!(sim.status.success(), "{sim:?}");
    let out = imucald(&[
        "replay".as_ref(),
        log.as_os_str(),
        "--export".as_ref(),
        exports.as_os_str(),
    ]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(0), "{stdout}\n{stderr}");
    assert!(!stderr.contains("nothing was calibrated"), "{stderr}");
    let next = stdout.lines().find(|l| l.starts_with("next:")).unwrap();
    let parm = exports.join("tempcal_ardupilot.parm");
    assert!(
        next.starts_with("next: load the temperature calibration")
            && next.contains(&parm.display().to_string()),
        "{next}"
    );
    assert_eq!(
        stdout.matches("accel and gyro biases fitted").count(),
        3,
        "{stdout}"
    );
}

/// `[tempcal]` in the configuration reaches the replay's fit, and bad values name their key.
#[test]
fn the_tempcal_section_of_the_configuration_is_read_by_replay() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("warm.csv");
    let written = imucald::app::simulate::write_warmup(&out, 3, None).unwrap();
    let cfg = imucald::config::Config::from_toml_str("[tempcal]\nmin_span_c = 30.0\nbin_c = 1.0\n")
        .unwrap();
    assert_eq!(cfg.tempcal.bin_c, 1.0);
    let r = imucald::app::replay::replay(&written[0], &cfg, &Default::default(), &mut |_, _| {})
        .unwrap();
    // The warm-up spans about 24 C: refused under a 30 C minimum, with the minimum named.
    match &r.report.temperature[0].result.outcome {
        TempOutcome::Refused(Refusal::Span { min_span_c, .. }) => assert_eq!(*min_span_c, 30.0),
        o => panic!("{o:?}"),
    }
    let cfg = imucald::config::Config::from_toml_str("[tempcal]\nbin_c = 1.0\n").unwrap();
    let r = imucald::app::replay::replay(&written[0], &cfg, &Default::default(), &mut |_, _| {})
        .unwrap();
    let c = calibrated(&r.report.temperature[0].result.outcome);
    assert_eq!(c.bin_c, 1.0);
    assert!(imucald::app::replay::summary(&r.report).contains("points of 1 C"));
    for bad in [
        "bin_c = 0.0",
        "max_moving_fraction = 1.5",
        "min_per_bin = 0",
        "bins = 3",
    ] {
        let e = imucald::config::Config::from_toml_str(&format!("[tempcal]\n{bad}\n"))
            .unwrap_err()
            .to_string();
        let key = bad.split(' ').next().unwrap();
        assert!(e.contains(key), "{bad}: {e}");
    }
}
