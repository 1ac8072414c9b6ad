//! Pages for a person: the HTML report of a replay ([`html`], pure, one self-contained file) and
//! the live page of the service ([`live`]: the state the page shows, kept from the JSON lines,
//! pure; [`server`]: HTTP on the service's tokio runtime).
//!
//! The pages are plain HTML, CSS and JavaScript in `assets/`, compiled into the binary: no file,
//! font, script or other resource is loaded from anywhere else, and the drawing (the sphere of
//! field directions with the coverage regions, residual plots, the heading dial) is canvas code of
//! our own (`assets/draw.js`), shared by both pages.

pub mod html;
pub mod live;
pub mod server;

/// Shared style sheet.
pub(crate) const CSS: &str = include_str!("assets/style.css");
/// Shared drawing code: sphere, coverage regions, plots, dial.
pub(crate) const DRAW_JS: &str = include_str!("assets/draw.js");

/// The live page, whole (its data comes from `/api/state` and `/api/events`).
pub(crate) const LIVE_PAGE: &str = concat!(
    "<!doctype html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\n",
    "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n",
    "<title>imucald live calibration</title>\n<style>\n",
    include_str!("assets/style.css"),
    "</style></head>\n<body>\n",
    include_str!("assets/live.html"),
    "<script>\n",
    include_str!("assets/draw.js"),
    include_str!("assets/live.js"),
    "</script>\n</body></html>\n"
);

/// The latitude bands of the coverage regions ([`crate::calib::coverage::BANDS`]) as the pages take them:
/// `[[lowest z, regions], ...]` north to south.
pub(crate) fn bands_json() -> serde_json::Value {
    serde_json::Value::Array(
        crate::calib::coverage::BANDS
            .iter()
            .map(|&(z, n)| serde_json::json!([z, n]))
            .collect(),
    )
}

/// JSON to put inside a `<script>` element: `<` escaped, so no `</script>` (or `<!--`) in the data
/// can end the element early.
pub(crate) fn script_safe_json(json: &str) -> String {
    json.replace('<', "\\u003c")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ui_pages_load_nothing_from_elsewhere() {
        for (name, text) in [
            ("live", LIVE_PAGE),
            ("report", include_str!("assets/report.js")),
            ("draw", DRAW_JS),
            ("css", CSS),
        ] {
            for bad in ["http:", "https:", "//cdn", "src=\"/", "@import", "url("] {
                assert!(!text.contains(bad), "{name} contains {bad}");
            }
        }
        // Transfer size of the page (it loads nothing else; the state and events come after).
        assert!(LIVE_PAGE.len() < 200_000, "{}", LIVE_PAGE.len());
    }

    #[test]
    fn ui_script_data_cannot_close_its_element() {
        let s = script_safe_json(r#"{"t":"</script><script>alert(1)</script>"}"#);
        assert!(!s.contains('<'), "{s}");
        let v: serde_json::Value = serde_json::from_str(&s).unwrap();
        assert_eq!(v["t"], "</script><script>alert(1)</script>");
    }

    #[test]
    fn ui_bands_are_the_coverage_regions() {
        let b = bands_json();
        let total: u64 = b
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x[1].as_u64().unwrap())
            .sum();
        assert_eq!(total as usize, crate::calib::coverage::REGIONS);
    }
}
