//! The HTML report of a replay (`imucald replay LOG --html FILE`): one self-contained file, its
//! data embedded as JSON, drawn by the page's own canvas code. Per IMU instance and sensor: the
//! field directions on the sphere before and after calibration with the coverage regions (the
//! regions `coverage` counts), the residual of every fitted point, the fitted values or the named
//! failure, the gyro's bias or why there is none; the onboard calibration when the log has one;
//! each compass judged on the blocks of the log it was not fitted on (`quality`); a diagnosis
//! when one is given. Every status, method, model and figure is the report's record of that
//! instance (`calibration`, `instances[k].calibration`): the page gives the report's one answer,
//! and draws the pipelines' points only where they are the reported calibration's. Building the
//! page is pure; [`write`] writes it atomically.

use crate::calib::outcome::{MagMethod, SensorResult};
use crate::calib::pipeline::FitResults;
use crate::error::Error;
use crate::report::{CalStatus, CalibrationReport, GyroCalibration, Report, SensorCalibration};
use crate::types::Vec3;
use serde::Serialize;
use std::path::Path;

/// Schema of the data embedded in the page.
pub(crate) const HTML_SCHEMA: &str = "imucald.html/1";
/// Most directions drawn per sphere (evenly thinned beyond).
pub(crate) const MAX_DIRECTIONS: usize = 1500;
/// Most residuals plotted per sensor (evenly thinned beyond).
pub(crate) const MAX_RESIDUALS: usize = 2000;

/// One sphere: unit directions and the regions they fill.
#[derive(Debug, Clone, Serialize)]
pub struct SphereView {
    /// Unit vectors, body axes, rounded to 1e-3.
    pub dirs: Vec<[f32; 3]>,
    /// Regions filled ([`crate::calib::coverage::regions_hex`]).
    pub regions: String,
    pub filled: usize,
}

/// One sensor of one instance.
#[derive(Debug, Clone, Serialize)]
pub struct SensorView {
    /// "mag" or "accel".
    pub sensor: &'static str,
    /// The report's record of it, as the report holds it (status, failure, method, model,
    /// offset, matrix): the page shows no other answer.
    pub calibration: SensorCalibration,
    /// About the raw data's centre; none without the fitted points.
    pub before: Option<SphereView>,
    /// After the reported calibration: only when it passed and the points at hand were fitted
    /// with it.
    pub after: Option<SphereView>,
    /// |calibrated| - radius of the fitted points, calibrated units, in fit order (thinned);
    /// empty unless they are the reported calibration's.
    pub residuals: Vec<f32>,
    /// Fitted points the residuals stand for (before thinning).
    pub residual_points: usize,
    /// Why the view after calibration and the residuals are not drawn, when they are not.
    pub plots_note: Option<String>,
}

/// The gyro of one instance: the report's record and, when it gives no bias, why.
#[derive(Debug, Clone, Serialize)]
pub struct GyroView {
    pub calibration: GyroCalibration,
    /// The report's reason for a gyro without a bias, in words; none when the bias passed.
    pub no_bias_reason: Option<String>,
}

/// One IMU instance.
#[derive(Debug, Clone, Serialize)]
pub struct InstanceView {
    /// `highres_imu:1`, ...; empty for a log with one instance.
    pub instance: String,
    pub compass_id: Option<u8>,
    pub primary: bool,
    pub sensors: Vec<SensorView>,
    pub gyro: GyroView,
}

/// What the page draws, per instance: the report's records, with the fitted points of the
/// pipelines for the plots.
#[derive(Debug, Clone, Serialize)]
pub struct Views {
    pub instances: Vec<InstanceView>,
}

/// Every `ceil(n / max)`-th element, at most about `max` of them.
fn thin<T: Copy>(v: &[T], max: usize) -> impl Iterator<Item = T> + '_ {
    let step = v.len().div_ceil(max.max(1)).max(1);
    v.iter().step_by(step).copied()
}

fn sphere(dirs: &[Vec3], mask: &[bool]) -> SphereView {
    let dirs = thin(dirs, MAX_DIRECTIONS)
        .filter_map(|d| {
            let n = crate::types::norm(&d);
            (n > 0.0 && n.is_finite())
                .then(|| d.map(|v| ((v / n * 1000.0).round() / 1000.0) as f32))
        })
        .collect();
    SphereView {
        dirs,
        regions: crate::calib::coverage::regions_hex(mask),
        filled: mask.iter().filter(|&&f| f).count(),
    }
}

/// Whether two numbers are the same figure (the same fit's, copied), allowing for rounding.
fn same_figure(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-9 * a.abs().max(b.abs()).max(1.0)
}

/// Whether the pipeline's points after calibration and residuals (`fitted`, its own record of
/// the norm fit they were made with) are those of the calibration the report holds: the report's
/// method is the norm fit's and its model, offset and matrix are that fit's.
fn fitted_with_reported(reported: &SensorCalibration, fitted: &SensorCalibration) -> bool {
    let norm_fit = reported
        .method
        .as_ref()
        .is_none_or(|m| m.method == MagMethod::Sphere);
    norm_fit
        && reported.model == fitted.model
        && reported
            .offset
            .iter()
            .zip(&fitted.offset)
            .all(|(a, b)| same_figure(*a, *b))
        && reported
            .matrix
            .iter()
            .flatten()
            .zip(fitted.matrix.iter().flatten())
            .all(|(a, b)| same_figure(*a, *b))
}

/// Why the points of the norm fit are not drawn for the reported calibration.
fn plots_note(reported: &SensorCalibration) -> String {
    match reported.method.as_ref().map(|m| m.method) {
        Some(m @ (MagMethod::Vector | MagMethod::Planar)) => format!(
            "The {} calibration the report holds was not fitted on these points: no view after \
             calibration and no residuals are drawn (its figures are in the table).",
            m.name()
        ),
        _ => "The points at hand belong to another fit than the one the report holds: no view \
              after calibration and no residuals are drawn (its figures are in the table)."
            .to_string(),
    }
}

/// One sensor as the report holds it (`reported`), drawn with the pipeline's points (`fitted`)
/// where they are its own.
fn sensor_view(
    sensor: &'static str,
    reported: &SensorCalibration,
    fitted: Option<&SensorResult>,
) -> SensorView {
    let before = fitted
        .filter(|r| !r.dirs_before.is_empty())
        .map(|r| sphere(&r.dirs_before, &r.coverage_before.filled_mask));
    let own = fitted.filter(|r| fitted_with_reported(reported, &r.report));
    let after = own
        .filter(|r| reported.status == CalStatus::Ok && !r.dirs_after.is_empty())
        .map(|r| sphere(&r.dirs_after, &r.coverage_after.filled_mask));
    let residuals: &[f64] = own.map_or(&[], |r| &r.residuals);
    let drawn = fitted.is_some_and(|r| !r.dirs_after.is_empty() || !r.residuals.is_empty());
    SensorView {
        sensor,
        calibration: reported.clone(),
        before,
        after,
        residuals: thin(residuals, MAX_RESIDUALS)
            .map(|x| ((x * 1e4).round() / 1e4) as f32)
            .collect(),
        residual_points: residuals.len(),
        plots_note: (drawn && own.is_none()).then(|| plots_note(reported)),
    }
}

/// The report's reason for a gyro record without a bias (its failure and the poses it counted).
fn no_bias_reason(g: &GyroCalibration) -> Option<String> {
    if g.status == CalStatus::Ok {
        return None;
    }
    let poses = format!(
        "{} static pose{} at rest with gyro readings, {} left out as turning",
        g.poses_used,
        if g.poses_used == 1 { "" } else { "s" },
        g.poses_turning
    );
    Some(match g.failure {
        Some(f) => format!("{}: {poses}", f.name()),
        None => format!("failed, no reason recorded: {poses}"),
    })
}

fn instance_view(
    instance: String,
    compass_id: Option<u8>,
    primary: bool,
    reported: &CalibrationReport,
    fitted: Option<&FitResults>,
) -> InstanceView {
    InstanceView {
        instance,
        compass_id,
        primary,
        sensors: vec![
            sensor_view("mag", &reported.mag, fitted.map(|r| &r.mag)),
            sensor_view("accel", &reported.accel, fitted.map(|r| &r.accel)),
        ],
        gyro: GyroView {
            calibration: reported.gyro.clone(),
            no_bias_reason: no_bias_reason(&reported.gyro),
        },
    }
}

impl Views {
    /// The views of `report`: the primary (`calibration`) first, then every further instance of
    /// `instances` in the report's order, each with the figures of its own record. `primary` and
    /// `others` (name, the instance pipeline's results) give only the points drawn, and those
    /// only where they are the reported calibration's; an instance the report does not hold is
    /// not shown.
    pub fn new(report: &Report, primary: &FitResults, others: Vec<(String, FitResults)>) -> Views {
        let p = report.instances.iter().find(|i| i.primary);
        let mut instances = vec![instance_view(
            p.map(|i| i.instance.clone())
                .or_else(|| report.input.instance.clone())
                .unwrap_or_default(),
            p.map(|i| i.compass_id),
            true,
            &report.calibration,
            Some(primary),
        )];
        for i in report.instances.iter().filter(|i| !i.primary) {
            let fitted = others
                .iter()
                .find(|(name, _)| *name == i.instance)
                .map(|(_, r)| r);
            instances.push(instance_view(
                i.instance.clone(),
                Some(i.compass_id),
                false,
                &i.calibration,
                fitted,
            ));
        }
        Views { instances }
    }
}

#[derive(Serialize)]
struct PageData<'a> {
    schema: &'static str,
    report: &'a Report,
    views: &'a Views,
    /// The coverage regions' bands, as the live page takes them.
    bands: serde_json::Value,
    diagnosis: Option<&'a serde_json::Value>,
}

fn escape_html(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// The page: HTML with the style, the data (JSON in a `<script type="application/json">`) and
/// the drawing code inline.
pub fn page(
    report: &Report,
    views: &Views,
    diagnosis: Option<&serde_json::Value>,
) -> Result<String, Error> {
    let data = PageData {
        schema: HTML_SCHEMA,
        report,
        views,
        bands: super::bands_json(),
        diagnosis,
    };
    let json =
        serde_json::to_string(&data).map_err(|e| Error::Other(format!("html report data: {e}")))?;
    let title = format!(
        "imucald calibration report: {}",
        report.input.path.as_deref().unwrap_or("input")
    );
    let mut s = String::with_capacity(json.len() + 64 * 1024);
    s.push_str("<!doctype html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\n");
    s.push_str("<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n");
    s.push_str(&format!(
        "<title>{}</title>\n<style>\n",
        escape_html(&title)
    ));
    s.push_str(super::CSS);
    s.push_str("</style></head>\n<body>\n");
    s.push_str(&format!(
        "<header><h1>{}</h1></header>\n<main id=\"main\"><p id=\"noscript\">This report draws its views with JavaScript.</p></main>\n",
        escape_html(&title)
    ));
    s.push_str("<script type=\"application/json\" id=\"data\">");
    s.push_str(&super::script_safe_json(&json));
    s.push_str("</script>\n<script>\n");
    s.push_str(super::DRAW_JS);
    s.push_str(include_str!("assets/report.js"));
    s.push_str("</script>\n</body></html>\n");
    Ok(s)
}

/// Read a diagnosis report (imucald.diagnosis/1) to show.
pub(crate) fn read_diagnosis(path: &Path) -> Result<serde_json::Value, Error> {
    let text = std::fs::read_to_string(path).map_err(|source| Error::Read {
        path: path.to_path_buf(),
        source,
    })?;
    let v: serde_json::Value = serde_json::from_str(&text).map_err(|e| Error::Format {
        path: path.to_path_buf(),
        message: format!("not JSON: {e}"),
    })?;
    if v.get("schema").and_then(|s| s.as_str()) != Some(crate::diagnose::SCHEMA) {
        return Err(Error::Format {
            path: path.to_path_buf(),
            message: format!(
                "not a diagnosis report (schema {} expected)",
                crate::diagnose::SCHEMA
            ),
        });
    }
    Ok(v)
}

/// Write the page to `path` atomically (`publish::write_atomic_with`).
pub fn write(
    path: &Path,
    report: &Report,
    views: &Views,
    diagnosis: Option<&Path>,
) -> Result<(), Error> {
    let diag = diagnosis.map(read_diagnosis).transpose()?;
    let text = page(report, views, diag.as_ref())?;
    crate::io::publish::write_atomic_with(path, |f| std::io::Write::write_all(f, text.as_bytes()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn html_thinning_keeps_at_most_about_max() {
        let v: Vec<u32> = (0..10_001).collect();
        let t: Vec<u32> = thin(&v, 1500).collect();
        assert!(t.len() <= 1500 && t.len() > 1400, "{}", t.len());
        assert_eq!(t[0], 0);
        assert_eq!(thin(&v[..10], 1500).count(), 10);
        assert_eq!(thin::<u32>(&[], 1500).count(), 0);
    }

    /// The bundled tumble's page: every view's data, and nothing that loads from elsewhere.
    #[test]
    fn html_report_of_the_tumble_embeds_its_views() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("r.html");
        let log =
            std::path::PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/tumble.tlog"));
        let opts = crate::app::replay::ReplayOptions {
            html: Some(path.clone()),
            ..Default::default()
        };
        let out = crate::app::replay::replay(
            &log,
            &crate::config::Config::default(),
            &opts,
            &mut |_, _| {},
        )
        .unwrap();
        assert!(out.written.contains(&path));
        let text = std::fs::read_to_string(&path).unwrap();
        let start = text.find("id=\"data\">").unwrap() + "id=\"data\">".len();
        let end = start + text[start..].find("</script>").unwrap();
        let v: serde_json::Value = serde_json::from_str(&text[start..end]).unwrap();
        assert_eq!(v["schema"], HTML_SCHEMA);
        let mag = &v["views"]["instances"][0]["sensors"][0];
        assert_eq!(mag["sensor"], "mag");
        assert_eq!(mag["calibration"]["status"], "ok");
        let before = mag["before"]["dirs"].as_array().unwrap().len();
        assert!(before > 100 && before <= MAX_DIRECTIONS, "{before}");
        assert_eq!(mag["after"]["filled"], out.report.coverage.mag.filled);
        assert_eq!(mag["after"]["regions"].as_str().unwrap().len(), 25);
        assert!(mag["residuals"].as_array().unwrap().len() > 100);
        assert!(v["diagnosis"].is_null());
        for bad in ["http:", "https:", " src=", "url("] {
            assert!(!text.contains(bad), "{bad}");
        }
        // No temp file left beside it.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
        eprintln!("tumble report: {} bytes", text.len());
    }

    /// Points on a sphere of `radius_ut` about `centre_ut`, spread over every direction.
    fn sphere_points_ut(centre_ut: Vec3, radius_ut: f64, n: usize) -> Vec<Vec3> {
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        (0..n)
            .map(|k| {
                let z = 1.0 - 2.0 * (k as f64 + 0.5) / n as f64;
                let r = (1.0 - z * z).sqrt();
                let a = golden * k as f64;
                [
                    centre_ut[0] + radius_ut * r * a.cos(),
                    centre_ut[1] + radius_ut * r * a.sin(),
                    centre_ut[2] + radius_ut * z,
                ]
            })
            .collect()
    }

    /// A pipeline's result of `report` on `points`, its own fit's points and residuals with it.
    fn fitted(report: SensorCalibration, points: &[Vec3], radius_ut: f64) -> SensorResult {
        let o = report.offset;
        let before: Vec<Vec3> = points
            .iter()
            .map(|p| [p[0] - o[0], p[1] - o[1], p[2] - o[2]])
            .collect();
        let cov = crate::calib::coverage::coverage(&before, &[0.0; 3]);
        SensorResult {
            calibration: None,
            coverage_before: cov.clone(),
            coverage_after: cov,
            residuals: before
                .iter()
                .map(|d| crate::types::norm(d) - radius_ut)
                .collect(),
            dirs_after: before.clone(),
            dirs_before: before,
            held_out: vec![],
            report,
        }
    }

    fn gyro_record(status: CalStatus, bias_rad_s: Vec3, poses: usize) -> GyroCalibration {
        GyroCalibration {
            status,
            failure: (status == CalStatus::Failed)
                .then_some(crate::calib::fit::FitFailure::NotEnoughSamples),
            units: crate::types::CalUnits::RadS,
            bias: bias_rad_s,
            bias_sigma: [0.0; 3],
            poses_used: poses,
            poses_turning: 2,
            scale: None,
            scale_failure: None,
        }
    }

    /// A three-compass report whose further compasses the method choice made `ok` (vector,
    /// full12) while their pipelines' own fits failed (sym9, another offset): the page carries the
    /// report's records, not the pipelines', and the primary's gyro without a bias says why.
    #[test]
    fn html_views_take_every_compass_from_the_report() {
        use crate::calib::model::CalModel;
        use crate::calib::outcome::MethodChoice;
        use crate::report::InstanceReport;
        use crate::types::CalUnits;
        let radius_ut = 50.0;
        let sphere_ok = |offset_ut: Vec3| {
            let mut c = SensorCalibration::new(CalStatus::Ok, CalModel::Sym9, CalUnits::Ut);
            c.offset = offset_ut;
            c.radius = radius_ut;
            c.samples_used = 400;
            c.method = Some(MethodChoice {
                method: MagMethod::Sphere,
                method_reason: "no attitude".into(),
                vector: None,
                planar: None,
                sphere_offset: None,
                earth_field: None,
                rung: None,
                current_ut_per_a: None,
            });
            c
        };
        let primary_offset_ut = [12.0, -25.0, 40.0];
        let primary = FitResults {
            mag: fitted(
                sphere_ok(primary_offset_ut),
                &sphere_points_ut(primary_offset_ut, radius_ut, 400),
                radius_ut,
            ),
            accel: fitted(
                SensorCalibration::new(CalStatus::Ok, CalModel::Sym9, CalUnits::Mps2),
                &sphere_points_ut([0.0; 3], 9.81, 50),
                9.81,
            ),
            gyro: gyro_record(CalStatus::Failed, [0.0; 3], 1),
        };
        // The further compasses' pipelines: failed sym9 fits about another offset.
        let raw_offset_ut = [5.17, 9.05, 30.28];
        let raw_failed = || {
            let mut c = SensorCalibration::new(CalStatus::Failed, CalModel::Sym9, CalUnits::Ut);
            c.failure = Some(crate::calib::fit::FitFailure::DidNotConverge);
            c.offset = raw_offset_ut;
            let mut r = primary.clone();
            r.mag = fitted(
                c,
                &sphere_points_ut([-3.0, 2.0, 7.0], radius_ut, 300),
                radius_ut,
            );
            r.gyro = gyro_record(CalStatus::Ok, [0.01, -0.02, 0.003], 5);
            r
        };
        // What the report holds for them: the vector fit, full12.
        let vector_ok = |offset_ut: Vec3| {
            let mut c = SensorCalibration::new(CalStatus::Ok, CalModel::Full12, CalUnits::Ut);
            c.offset = offset_ut;
            c.matrix = [[1.02, 0.01, 0.0], [0.01, 0.98, 0.0], [0.0, 0.0, 1.01]];
            c.radius = 48.7;
            c.method = Some(MethodChoice {
                method: MagMethod::Vector,
                method_reason: "attitude and earth field".into(),
                vector: None,
                planar: None,
                sphere_offset: None,
                earth_field: None,
                rung: None,
                current_ut_per_a: None,
            });
            c
        };
        let input = crate::report::InputReport::new(
            "dataflash",
            Some("flight.bin".into()),
            Some("IMU+MAG".into()),
            &crate::io::decode::DecodeStats::default(),
            1000,
            100.0,
        );
        let pipe = crate::calib::pipeline::Pipeline::new(
            &crate::calib::settings::CalibSettings::default(),
        )
        .unwrap();
        let mut report = crate::app::replay::make_report(input, &pipe, &primary, None);
        let further = [
            ("IMU2+MAG2", 1u8, [-3.0, 2.0, 7.0]),
            ("IMU3+MAG3", 2, [1.5, -4.0, 0.5]),
        ];
        report.instances.push(InstanceReport {
            instance: "IMU+MAG".into(),
            compass_id: 0,
            primary: true,
            samples: 1000,
            time: Default::default(),
            calibration: report.calibration.clone(),
        });
        for (name, id, offset_ut) in further {
            let raw = raw_failed();
            report.instances.push(InstanceReport {
                instance: name.into(),
                compass_id: id,
                primary: false,
                samples: 1000,
                time: Default::default(),
                calibration: CalibrationReport {
                    mag: vector_ok(offset_ut),
                    accel: raw.accel.report.clone(),
                    gyro: raw.gyro.clone(),
                },
            });
        }
        let others = further
            .iter()
            .map(|(name, _, _)| (name.to_string(), raw_failed()))
            .collect();
        let views = Views::new(&report, &primary, others);
        let text = page(&report, &views, None).unwrap();
        let start = text.find("id=\"data\">").unwrap() + "id=\"data\">".len();
        let end = start + text[start..].find("</script>").unwrap();
        let v: serde_json::Value = serde_json::from_str(&text[start..end]).unwrap();
        let shown = v["views"]["instances"].as_array().unwrap();
        assert_eq!(shown.len(), 3);
        // Each compass as its report record has it, field by field.
        let records = std::iter::once(&report.calibration).chain(
            report
                .instances
                .iter()
                .filter(|i| !i.primary)
                .map(|i| &i.calibration),
        );
        for (iv, rec) in shown.iter().zip(records) {
            let mag = &iv["sensors"][0];
            assert_eq!(mag["sensor"], "mag");
            let want = serde_json::to_value(&rec.mag).unwrap();
            for key in [
                "status", "failure", "method", "model", "offset", "matrix", "radius",
            ] {
                assert_eq!(
                    mag["calibration"][key], want[key],
                    "{} {key}",
                    iv["instance"]
                );
            }
            assert_eq!(
                iv["gyro"]["calibration"],
                serde_json::to_value(&rec.gyro).unwrap()
            );
        }
        for (k, (name, id, offset_ut)) in further.iter().enumerate() {
            let iv = &shown[k + 1];
            assert_eq!(iv["instance"], *name);
            assert_eq!(iv["compass_id"], *id);
            assert_eq!(iv["primary"], false);
            let mag = &iv["sensors"][0];
            assert_eq!(mag["calibration"]["status"], "ok");
            assert!(mag["calibration"]["failure"].is_null());
            assert_eq!(mag["calibration"]["method"], "vector");
            assert_eq!(mag["calibration"]["model"], "full12");
            assert_eq!(mag["calibration"]["offset"], serde_json::json!(offset_ut));
            // The pipeline's points are not the vector fit's: its raw directions only.
            assert!(mag["before"]["dirs"].as_array().unwrap().len() > 100);
            assert!(mag["after"].is_null());
            assert!(mag["residuals"].as_array().unwrap().is_empty());
            assert!(mag["plots_note"].as_str().unwrap().contains("vector"));
            // Its gyro passed: the bias, no reason.
            assert!(iv["gyro"]["no_bias_reason"].is_null());
        }
        // The primary's sphere fit is the pipeline's own: drawn after calibration.
        let mag = &shown[0]["sensors"][0];
        assert_eq!(shown[0]["primary"], true);
        assert_eq!(mag["calibration"]["method"], "sphere");
        assert!(mag["after"]["dirs"].as_array().unwrap().len() > 100);
        assert_eq!(mag["residual_points"], 400);
        assert!(mag["plots_note"].is_null());
        // The primary's gyro has no bias: the report's reason goes with it.
        let g = &shown[0]["gyro"];
        assert_eq!(g["calibration"]["status"], "failed");
        let why = g["no_bias_reason"].as_str().unwrap();
        assert!(
            why.starts_with("not_enough_samples: 1 static pose at rest"),
            "{why}"
        );
        assert!(why.contains("2 left out as turning"), "{why}");
    }

    #[test]
    fn html_diagnosis_must_be_one() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("d.json");
        std::fs::write(&p, "{\"schema\":\"imucald.report/1\"}").unwrap();
        let e = read_diagnosis(&p).unwrap_err().to_string();
        assert!(e.contains("not a diagnosis report"), "{e}");
        std::fs::write(&p, "{").unwrap();
        assert!(read_diagnosis(&p)
            .unwrap_err()
            .to_string()
            .contains("not JSON"));
    }
}
