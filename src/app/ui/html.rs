//! The HTML report of a replay (`imucald replay LOG --html FILE`): one self-contained file, its
//! data embedded as JSON, drawn by the page's own canvas code. Per IMU instance and sensor: the
//! field directions on the sphere before and after calibration with the coverage regions (the
//! regions `coverage` counts), the residual of every fitted point, the fitted values or the named
//! failure; the onboard calibration when the log has one; each compass judged on the blocks of
//! the log it was not fitted on (`quality`); a diagnosis when one is given. Building
//! the page is pure; [`write`] writes it atomically.

use crate::calib::outcome::SensorResult;
use crate::calib::pipeline::FitResults;
use crate::error::Error;
use crate::report::{Report, SensorCalibration};
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
    pub calibration: SensorCalibration,
    /// About the raw data's centre.
    pub before: SphereView,
    /// After calibration (none when the fit failed).
    pub after: Option<SphereView>,
    /// |calibrated| - radius of the fitted points, calibrated units, in fit order (thinned).
    pub residuals: Vec<f32>,
    /// Fitted points the residuals stand for (before thinning).
    pub residual_points: usize,
}

/// One IMU instance.
#[derive(Debug, Clone, Serialize)]
pub struct InstanceView {
    /// `highres_imu:1`, ...; empty for a log with one instance.
    pub instance: String,
    pub compass_id: Option<u8>,
    pub primary: bool,
    pub sensors: Vec<SensorView>,
}

/// What the page draws, per instance.
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

fn sensor_view(sensor: &'static str, r: &SensorResult) -> Option<SensorView> {
    if r.dirs_before.is_empty() && r.report.samples_used == 0 {
        return None;
    }
    Some(SensorView {
        sensor,
        calibration: r.report.clone(),
        before: sphere(&r.dirs_before, &r.coverage_before.filled_mask),
        after: (r.calibration.is_some() && !r.dirs_after.is_empty())
            .then(|| sphere(&r.dirs_after, &r.coverage_after.filled_mask)),
        residuals: thin(&r.residuals, MAX_RESIDUALS)
            .map(|x| ((x * 1e4).round() / 1e4) as f32)
            .collect(),
        residual_points: r.residuals.len(),
    })
}

fn instance_view(
    instance: String,
    compass_id: Option<u8>,
    primary: bool,
    r: &FitResults,
) -> InstanceView {
    InstanceView {
        instance,
        compass_id,
        primary,
        sensors: [("mag", &r.mag), ("accel", &r.accel)]
            .into_iter()
            .filter_map(|(n, s)| sensor_view(n, s))
            .collect(),
    }
}

impl Views {
    /// The primary's results and the other instances' (name, results), as the report names them.
    pub fn new(report: &Report, primary: &FitResults, others: Vec<(String, FitResults)>) -> Views {
        let inst = |name: &str| report.instances.iter().find(|i| i.instance == name);
        let p = report.instances.iter().find(|i| i.primary);
        let mut instances = vec![instance_view(
            p.map(|i| i.instance.clone())
                .or_else(|| report.input.instance.clone())
                .unwrap_or_default(),
            p.map(|i| i.compass_id),
            true,
            primary,
        )];
        for (name, r) in others {
            let id = inst(&name).map(|i| i.compass_id);
            instances.push(instance_view(name, id, false, &r));
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
