//! Plots for people: the coverage map of Camps, Harasse and Monin, "Numerical calibration for 3-axis accelerometers and magnetometers" (2009) (the θ/φ projection of measured directions, with
//! MotionCal's 100 equal-area regions) and residual-versus-time plots, as PNG or SVG.
//!
//! The format follows the file extension (`.png` or `.svg`, any case). Every plot is rendered to a
//! temporary file in the destination's directory and then renamed over the destination, so a reader
//! never sees half a file.
//!
//! Text: plotters built without its `ttf`/`ab_glyph` features has no font rasteriser, and drawing text
//! into a bitmap then panics. So this module lays out every label itself: in SVG a label is a plain
//! `<text>` element (the viewer's sans-serif font), in PNG it is drawn with the small built-in 5x7
//! bitmap font below, as filled pixel squares. Both formats carry the same labels, with no system
//! fonts, font files or extra Cargo features.

use std::io::Write as _;
use std::path::{Path, PathBuf};

use plotters::coord::types::RangedCoordf64;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

use crate::error::Error;

// ---------------------------------------------------------------------------------------------
// Public API
// ---------------------------------------------------------------------------------------------

/// Number of MotionCal coverage regions.
pub(crate) const REGIONS: usize = 100;

/// The 2-D projection of measured directions of Camps, Harasse and Monin, "Numerical calibration for 3-axis accelerometers and magnetometers" (2009): theta = polar angle from +z (0..180 deg) on the
/// y axis (0 at the top), phi = azimuth atan2(y, x) (-180..180 deg) on the x axis; one point per
/// direction vector (any length; normalised inside; zero or non-finite vectors are skipped), plus the
/// 100 equal-area region boundaries drawn faintly and filled regions shaded (`filled[i]` for region
/// `i` as numbered by [`region_outline`]; a missing entry counts as not filled). Two panels side by
/// side: "before" (raw directions about the raw centroid) and "after" (directions after calibration).
pub(crate) fn coverage_map(
    path: &Path,
    title: &str,
    before: &[[f64; 3]],
    after: &[[f64; 3]],
    filled_before: &[bool],
    filled_after: &[bool],
) -> Result<(), Error> {
    let fig = CoverageFigure {
        title,
        panels: [
            Panel {
                name: "before",
                dirs: before,
                filled: filled_before,
                color: BEFORE_COLOR,
            },
            Panel {
                name: "after",
                dirs: after,
                filled: filled_after,
                color: AFTER_COLOR,
            },
        ],
    };
    render(path, &fig)
}

/// Residual plot: for each series (label, t seconds, residual), residual vs time as points; a
/// horizontal zero line; `y_label` (which should name the units) on the y axis; a legend with the
/// series labels. The two slices of a series must have the same length; non-finite pairs are skipped.
pub fn residuals(
    path: &Path,
    title: &str,
    y_label: &str,
    series: &[(&str, &[f64], &[f64])],
) -> Result<(), Error> {
    residuals_vs(path, title, "time (s)", y_label, series)
}

/// Residual plot against any regressor: as [`residuals`], with `x_label` (naming the regressor and
/// its unit) on the x axis instead of time.
pub(crate) fn residuals_vs(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[(&str, &[f64], &[f64])],
) -> Result<(), Error> {
    for (label, t, r) in series {
        if t.len() != r.len() {
            return Err(Error::Other(format!(
                "residual series {label:?}: {} times but {} residuals",
                t.len(),
                r.len()
            )));
        }
    }
    render(
        path,
        &ResidualFigure {
            title,
            x_label,
            y_label,
            series,
        },
    )
}

/// The plots of a diagnosis (`imucald diagnose --plot DIR`): per effect found, its residual channel
/// against its regressor before (base model) and after (with the effect), as
/// `diagnose_<effect>.png` and `.svg` in `dir` (created if missing), and the same against the
/// residual the effect's fitted term predicts (`diagnose_<effect>_term.*`: before lies on the
/// diagonal when the effect is what was missing). Returns the files written.
pub fn diagnosis(
    dir: &Path,
    report: &crate::diagnose::DiagnosisReport,
) -> Result<Vec<PathBuf>, Error> {
    std::fs::create_dir_all(dir).map_err(|source| Error::Write {
        path: dir.to_path_buf(),
        source,
    })?;
    let mut written = vec![];
    for s in &report.residual_plots {
        let title = format!(
            "{}: {} residual before and after adding the effect",
            s.effect, s.channel
        );
        let y = format!("{} residual ({})", s.channel, s.unit);
        let series: [(&str, &[f64], &[f64]); 2] = [
            ("before (base model)", &s.x, &s.before),
            ("after (with the effect)", &s.x, &s.after),
        ];
        let term_x = format!(
            "{} predicted by the {} term ({})",
            s.channel, s.effect, s.unit
        );
        let term: [(&str, &[f64], &[f64]); 2] = [
            ("before (base model)", &s.predicted, &s.before),
            ("after (with the effect)", &s.predicted, &s.after),
        ];
        for ext in ["png", "svg"] {
            let path = dir.join(format!("diagnose_{}.{ext}", s.effect));
            residuals_vs(&path, &title, &s.regressor, &y, &series)?;
            written.push(path);
            if s.predicted.len() == s.before.len() && !s.regressor.contains("predicted") {
                let path = dir.join(format!("diagnose_{}_term.{ext}", s.effect));
                residuals_vs(&path, &title, &term_x, &y, &term)?;
                written.push(path);
            }
        }
    }
    Ok(written)
}

/// Outline of MotionCal coverage region `index` (0..100) as
/// `(theta_min_deg, theta_max_deg, phi_min_deg, phi_max_deg)`, theta being the polar angle from +z
/// and phi the azimuth atan2(y, x).
///
/// Numbering: 0 is the north cap (theta below ~11.48 deg), then the bands of 15, 34, 34 and 15
/// regions from north to south, each numbered with phi rising from -180 deg, and 99 the south cap.
/// Band edges are at latitudes ±asin(0.98) ≈ ±78.52 deg, ±asin(0.68) ≈ ±42.84 deg and 0, which makes
/// all 100 solid angles exactly 4π/100.
///
/// # Panics
/// If `index >= 100`.
pub(crate) fn region_outline(index: usize) -> (f64, f64, f64, f64) {
    assert!(
        index < REGIONS,
        "coverage region {index} out of range 0..{REGIONS}"
    );
    // (regions in the band, cos(theta) at the band's northern edge, at its southern edge)
    const BANDS: [(usize, f64, f64); 6] = [
        (1, 1.0, 0.98),
        (15, 0.98, 0.68),
        (34, 0.68, 0.0),
        (34, 0.0, -0.68),
        (15, -0.68, -0.98),
        (1, -0.98, -1.0),
    ];
    let mut first = 0;
    for (count, cos_north, cos_south) in BANDS {
        if index < first + count {
            let k = (index - first) as f64;
            let width = 360.0 / count as f64;
            let theta_min = cos_north.acos().to_degrees();
            let theta_max = cos_south.acos().to_degrees();
            return (
                theta_min,
                theta_max,
                -180.0 + k * width,
                -180.0 + (k + 1.0) * width,
            );
        }
        first += count;
    }
    unreachable!("the bands hold {REGIONS} regions")
}

// ---------------------------------------------------------------------------------------------
// Rendering to a file, atomically
// ---------------------------------------------------------------------------------------------

type DrawResult = std::result::Result<(), String>;

/// How labels reach the image.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Ink {
    /// `<text>` elements (SVG).
    Vector,
    /// The built-in bitmap font, as filled squares (PNG).
    Pixels,
}

/// A figure that can draw itself on any plotters backend.
trait Figure {
    fn size(&self) -> (u32, u32);
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>, ink: Ink) -> DrawResult;
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Format {
    Png,
    Svg,
}

fn format_of(path: &Path) -> Result<Format, Error> {
    match path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .as_deref()
    {
        Some("png") => Ok(Format::Png),
        Some("svg") => Ok(Format::Svg),
        _ => Err(Error::Other(format!(
            "{}: unsupported plot format (use a .png or .svg file name)",
            path.display()
        ))),
    }
}

fn write_error(path: &Path, source: std::io::Error) -> Error {
    Error::Write {
        path: path.to_path_buf(),
        source,
    }
}

fn render<F: Figure>(path: &Path, fig: &F) -> Result<(), Error> {
    let format = format_of(path)?;
    let file = crate::io::publish::AtomicFile::new(path)?;
    render_to(path, file.temp_path(), format, fig)?;
    file.commit()
}

/// Render into `tmp`; errors name `dest`, the file the caller asked for.
fn render_to<F: Figure>(dest: &Path, tmp: &Path, format: Format, fig: &F) -> Result<(), Error> {
    let failed = |e: String| Error::Other(format!("cannot draw {}: {e}", dest.display()));
    match format {
        Format::Svg => {
            let mut svg = String::new();
            {
                let root = SVGBackend::with_string(&mut svg, fig.size()).into_drawing_area();
                fig.draw(&root, Ink::Vector).map_err(failed)?;
                root.present().map_err(|e| failed(e.to_string()))?;
            }
            let mut file = std::fs::File::create(tmp).map_err(|e| write_error(dest, e))?;
            file.write_all(svg.as_bytes())
                .map_err(|e| write_error(dest, e))?;
            file.sync_all().map_err(|e| write_error(dest, e))?;
        }
        Format::Png => {
            {
                let root = BitMapBackend::new(tmp, fig.size()).into_drawing_area();
                fig.draw(&root, Ink::Pixels).map_err(failed)?;
                root.present()
                    .map_err(|e| write_error(dest, std::io::Error::other(e.to_string())))?;
            }
            let file = std::fs::File::open(tmp).map_err(|e| write_error(dest, e))?;
            file.sync_all().map_err(|e| write_error(dest, e))?;
        }
    }
    Ok(())
}

fn de<E: std::fmt::Display>(e: E) -> String {
    e.to_string()
}

// ---------------------------------------------------------------------------------------------
// Labels
// ---------------------------------------------------------------------------------------------

/// Cap height of a label, in units of the bitmap font's pixel (`unit` image pixels each).
const CAP_ROWS: i32 = 7;
/// Horizontal advance of one character, in font pixels.
const ADVANCE: i32 = 6;

/// Draw `text` on `area` (pixel coordinates) with its anchor at `pos`; `unit` sets the size (the
/// font's pixel is `unit` image pixels; capitals are 7 units tall); `vertical` turns the text to read
/// from bottom to top. `v` anchors on the capitals' box (descenders hang below it).
#[allow(clippy::too_many_arguments)]
fn label<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    ink: Ink,
    text: &str,
    pos: (i32, i32),
    unit: i32,
    color: RGBColor,
    (h, v): (HPos, VPos),
    vertical: bool,
) -> DrawResult {
    if text.is_empty() {
        return Ok(());
    }
    match ink {
        Ink::Vector => {
            // An em of 10 units gives capitals about 7 units tall; plotters' SVG backend writes
            // font-size = size / 1.24.
            let size = 10.0 * f64::from(unit) * 1.24;
            let mut font = ("sans-serif", size).into_font();
            if vertical {
                font = font.transform(FontTransform::Rotate270);
            }
            let style = TextStyle::from(font).color(&color).pos(Pos::new(h, v));
            area.draw(&Text::new(text.to_string(), pos, style))
                .map_err(de)
        }
        Ink::Pixels => {
            let u = unit.max(1);
            let n = text.chars().count() as i32;
            let width = (ADVANCE * n - 1) * u;
            let x0 = match h {
                HPos::Left => 0,
                HPos::Center => -width / 2,
                HPos::Right => -width,
            };
            let y0 = match v {
                VPos::Top => 0,
                VPos::Center => -(CAP_ROWS * u) / 2,
                VPos::Bottom => -CAP_ROWS * u,
            };
            let style = color.filled();
            for (k, ch) in text.chars().enumerate() {
                let gx = x0 + k as i32 * ADVANCE * u;
                for (r, bits) in glyph(ch).iter().enumerate() {
                    // One rectangle per horizontal run of set pixels.
                    let mut c = 0;
                    while c < 5 {
                        if bits & (0x10 >> c) == 0 {
                            c += 1;
                            continue;
                        }
                        let start = c;
                        while c < 5 && bits & (0x10 >> c) != 0 {
                            c += 1;
                        }
                        // The run in text coordinates: [lx, lx + w) x [ly, ly + u).
                        let (lx, ly, w) = (gx + start * u, y0 + r as i32 * u, (c - start) * u);
                        let (a, b) = if vertical {
                            // Rotate270: (x, y) -> (y, -x).
                            ((pos.0 + ly, pos.1 - lx - w), (pos.0 + ly + u, pos.1 - lx))
                        } else {
                            ((pos.0 + lx, pos.1 + ly), (pos.0 + lx + w, pos.1 + ly + u))
                        };
                        area.draw(&Rectangle::new([a, b], style)).map_err(de)?;
                    }
                }
            }
            Ok(())
        }
    }
}

/// The bitmap of one character: 9 rows of 5 pixels (bit 4 is the leftmost column); rows 0..7 hold
/// the capitals, rows 7 and 8 the descenders. Characters without a glyph show as a hollow box.
fn glyph(c: char) -> &'static [u8; 9] {
    const BOX: [u8; 9] = [
        0b11111, 0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b11111, 0, 0,
    ];
    const DEGREE: [u8; 9] = [0b01100, 0b10010, 0b10010, 0b01100, 0, 0, 0, 0, 0];
    const MICRO: [u8; 9] = [
        0, 0, 0b10001, 0b10001, 0b10001, 0b10011, 0b11101, 0b10000, 0b10000,
    ];
    const SQUARED: [u8; 9] = [0b01100, 0b10010, 0b00100, 0b01000, 0b11110, 0, 0, 0, 0];
    const CUBED: [u8; 9] = [0b11100, 0b00010, 0b01100, 0b00010, 0b11100, 0, 0, 0, 0];
    const THETA: [u8; 9] = [
        0b01110, 0b10001, 0b10001, 0b11111, 0b10001, 0b10001, 0b01110, 0, 0,
    ];
    const PHI: [u8; 9] = [
        0b00100, 0b01110, 0b10101, 0b10101, 0b10101, 0b01110, 0b00100, 0, 0,
    ];
    const SIGMA: [u8; 9] = [0, 0, 0b01111, 0b10010, 0b10001, 0b10001, 0b01110, 0, 0];
    const PLUS_MINUS: [u8; 9] = [
        0b00100, 0b00100, 0b11111, 0b00100, 0b00100, 0, 0b11111, 0, 0,
    ];
    match c {
        ' '..='~' => &ASCII[c as usize - ' ' as usize],
        '°' => &DEGREE,
        'µ' | 'μ' => &MICRO,
        '²' => &SQUARED,
        '³' => &CUBED,
        'θ' => &THETA,
        'φ' | 'ϕ' => &PHI,
        'σ' => &SIGMA,
        '±' => &PLUS_MINUS,
        '−' | '–' | '—' => &ASCII['-' as usize - ' ' as usize],
        _ => &BOX,
    }
}

/// Printable ASCII, ' ' (0x20) to '~' (0x7e).
#[rustfmt::skip]
const ASCII: [[u8; 9]; 95] = [
    [0, 0, 0, 0, 0, 0, 0, 0, 0],                                                    // ' '
    [0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0, 0b00100, 0, 0],                // !
    [0b01010, 0b01010, 0b01010, 0, 0, 0, 0, 0, 0],                                  // "
    [0b01010, 0b01010, 0b11111, 0b01010, 0b11111, 0b01010, 0b01010, 0, 0],          // #
    [0b00100, 0b01111, 0b10100, 0b01110, 0b00101, 0b11110, 0b00100, 0, 0],          // $
    [0b11000, 0b11001, 0b00010, 0b00100, 0b01000, 0b10011, 0b00011, 0, 0],          // %
    [0b01100, 0b10010, 0b10100, 0b01000, 0b10101, 0b10010, 0b01101, 0, 0],          // &
    [0b00100, 0b00100, 0b01000, 0, 0, 0, 0, 0, 0],                                  // '
    [0b00010, 0b00100, 0b01000, 0b01000, 0b01000, 0b00100, 0b00010, 0, 0],          // (
    [0b01000, 0b00100, 0b00010, 0b00010, 0b00010, 0b00100, 0b01000, 0, 0],          // )
    [0, 0b00100, 0b10101, 0b01110, 0b10101, 0b00100, 0, 0, 0],                      // *
    [0, 0b00100, 0b00100, 0b11111, 0b00100, 0b00100, 0, 0, 0],                      // +
    [0, 0, 0, 0, 0, 0, 0b01100, 0b00100, 0b01000],                                  // ,
    [0, 0, 0, 0b11111, 0, 0, 0, 0, 0],                                              // -
    [0, 0, 0, 0, 0, 0b01100, 0b01100, 0, 0],                                        // .
    [0, 0b00001, 0b00010, 0b00100, 0b01000, 0b10000, 0, 0, 0],                      // /
    [0b01110, 0b10001, 0b10011, 0b10101, 0b11001, 0b10001, 0b01110, 0, 0],          // 0
    [0b00100, 0b01100, 0b00100, 0b00100, 0b00100, 0b00100, 0b01110, 0, 0],          // 1
    [0b01110, 0b10001, 0b00001, 0b00010, 0b00100, 0b01000, 0b11111, 0, 0],          // 2
    [0b11111, 0b00010, 0b00100, 0b00010, 0b00001, 0b10001, 0b01110, 0, 0],          // 3
    [0b00010, 0b00110, 0b01010, 0b10010, 0b11111, 0b00010, 0b00010, 0, 0],          // 4
    [0b11111, 0b10000, 0b11110, 0b00001, 0b00001, 0b10001, 0b01110, 0, 0],          // 5
    [0b00110, 0b01000, 0b10000, 0b11110, 0b10001, 0b10001, 0b01110, 0, 0],          // 6
    [0b11111, 0b00001, 0b00010, 0b00100, 0b01000, 0b01000, 0b01000, 0, 0],          // 7
    [0b01110, 0b10001, 0b10001, 0b01110, 0b10001, 0b10001, 0b01110, 0, 0],          // 8
    [0b01110, 0b10001, 0b10001, 0b01111, 0b00001, 0b00010, 0b01100, 0, 0],          // 9
    [0, 0b01100, 0b01100, 0, 0b01100, 0b01100, 0, 0, 0],                            // :
    [0, 0b01100, 0b01100, 0, 0b01100, 0b00100, 0b01000, 0, 0],                      // ;
    [0b00010, 0b00100, 0b01000, 0b10000, 0b01000, 0b00100, 0b00010, 0, 0],          // <
    [0, 0, 0b11111, 0, 0b11111, 0, 0, 0, 0],                                        // =
    [0b01000, 0b00100, 0b00010, 0b00001, 0b00010, 0b00100, 0b01000, 0, 0],          // >
    [0b01110, 0b10001, 0b00001, 0b00010, 0b00100, 0, 0b00100, 0, 0],                // ?
    [0b01110, 0b10001, 0b00001, 0b01101, 0b10101, 0b10101, 0b01110, 0, 0],          // @
    [0b01110, 0b10001, 0b10001, 0b11111, 0b10001, 0b10001, 0b10001, 0, 0],          // A
    [0b11110, 0b10001, 0b10001, 0b11110, 0b10001, 0b10001, 0b11110, 0, 0],          // B
    [0b01110, 0b10001, 0b10000, 0b10000, 0b10000, 0b10001, 0b01110, 0, 0],          // C
    [0b11100, 0b10010, 0b10001, 0b10001, 0b10001, 0b10010, 0b11100, 0, 0],          // D
    [0b11111, 0b10000, 0b10000, 0b11110, 0b10000, 0b10000, 0b11111, 0, 0],          // E
    [0b11111, 0b10000, 0b10000, 0b11110, 0b10000, 0b10000, 0b10000, 0, 0],          // F
    [0b01110, 0b10001, 0b10000, 0b10111, 0b10001, 0b10001, 0b01111, 0, 0],          // G
    [0b10001, 0b10001, 0b10001, 0b11111, 0b10001, 0b10001, 0b10001, 0, 0],          // H
    [0b01110, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0b01110, 0, 0],          // I
    [0b00111, 0b00010, 0b00010, 0b00010, 0b00010, 0b10010, 0b01100, 0, 0],          // J
    [0b10001, 0b10010, 0b10100, 0b11000, 0b10100, 0b10010, 0b10001, 0, 0],          // K
    [0b10000, 0b10000, 0b10000, 0b10000, 0b10000, 0b10000, 0b11111, 0, 0],          // L
    [0b10001, 0b11011, 0b10101, 0b10101, 0b10001, 0b10001, 0b10001, 0, 0],          // M
    [0b10001, 0b10001, 0b11001, 0b10101, 0b10011, 0b10001, 0b10001, 0, 0],          // N
    [0b01110, 0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b01110, 0, 0],          // O
    [0b11110, 0b10001, 0b10001, 0b11110, 0b10000, 0b10000, 0b10000, 0, 0],          // P
    [0b01110, 0b10001, 0b10001, 0b10001, 0b10101, 0b10010, 0b01101, 0, 0],          // Q
    [0b11110, 0b10001, 0b10001, 0b11110, 0b10100, 0b10010, 0b10001, 0, 0],          // R
    [0b01111, 0b10000, 0b10000, 0b01110, 0b00001, 0b00001, 0b11110, 0, 0],          // S
    [0b11111, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0, 0],          // T
    [0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b01110, 0, 0],          // U
    [0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b01010, 0b00100, 0, 0],          // V
    [0b10001, 0b10001, 0b10001, 0b10101, 0b10101, 0b10101, 0b01010, 0, 0],          // W
    [0b10001, 0b10001, 0b01010, 0b00100, 0b01010, 0b10001, 0b10001, 0, 0],          // X
    [0b10001, 0b10001, 0b10001, 0b01010, 0b00100, 0b00100, 0b00100, 0, 0],          // Y
    [0b11111, 0b00001, 0b00010, 0b00100, 0b01000, 0b10000, 0b11111, 0, 0],          // Z
    [0b01110, 0b01000, 0b01000, 0b01000, 0b01000, 0b01000, 0b01110, 0, 0],          // [
    [0, 0b10000, 0b01000, 0b00100, 0b00010, 0b00001, 0, 0, 0],                      // \
    [0b01110, 0b00010, 0b00010, 0b00010, 0b00010, 0b00010, 0b01110, 0, 0],          // ]
    [0b00100, 0b01010, 0b10001, 0, 0, 0, 0, 0, 0],                                  // ^
    [0, 0, 0, 0, 0, 0, 0, 0b11111, 0],                                              // _
    [0b01000, 0b00100, 0b00010, 0, 0, 0, 0, 0, 0],                                  // `
    [0, 0, 0b01110, 0b00001, 0b01111, 0b10001, 0b01111, 0, 0],                      // a
    [0b10000, 0b10000, 0b10110, 0b11001, 0b10001, 0b10001, 0b11110, 0, 0],          // b
    [0, 0, 0b01110, 0b10000, 0b10000, 0b10001, 0b01110, 0, 0],                      // c
    [0b00001, 0b00001, 0b01101, 0b10011, 0b10001, 0b10001, 0b01111, 0, 0],          // d
    [0, 0, 0b01110, 0b10001, 0b11111, 0b10000, 0b01110, 0, 0],                      // e
    [0b00110, 0b01001, 0b01000, 0b11100, 0b01000, 0b01000, 0b01000, 0, 0],          // f
    [0, 0, 0b01111, 0b10001, 0b10001, 0b10001, 0b01111, 0b00001, 0b01110],          // g
    [0b10000, 0b10000, 0b10110, 0b11001, 0b10001, 0b10001, 0b10001, 0, 0],          // h
    [0b00100, 0, 0b01100, 0b00100, 0b00100, 0b00100, 0b01110, 0, 0],                // i
    [0b00010, 0, 0b00110, 0b00010, 0b00010, 0b00010, 0b00010, 0b10010, 0b01100],    // j
    [0b10000, 0b10000, 0b10010, 0b10100, 0b11000, 0b10100, 0b10010, 0, 0],          // k
    [0b01100, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0b01110, 0, 0],          // l
    [0, 0, 0b11010, 0b10101, 0b10101, 0b10101, 0b10101, 0, 0],                      // m
    [0, 0, 0b10110, 0b11001, 0b10001, 0b10001, 0b10001, 0, 0],                      // n
    [0, 0, 0b01110, 0b10001, 0b10001, 0b10001, 0b01110, 0, 0],                      // o
    [0, 0, 0b11110, 0b10001, 0b10001, 0b10001, 0b11110, 0b10000, 0b10000],          // p
    [0, 0, 0b01111, 0b10001, 0b10001, 0b10001, 0b01111, 0b00001, 0b00001],          // q
    [0, 0, 0b10110, 0b11001, 0b10000, 0b10000, 0b10000, 0, 0],                      // r
    [0, 0, 0b01111, 0b10000, 0b01110, 0b00001, 0b11110, 0, 0],                      // s
    [0b01000, 0b01000, 0b11100, 0b01000, 0b01000, 0b01001, 0b00110, 0, 0],          // t
    [0, 0, 0b10001, 0b10001, 0b10001, 0b10011, 0b01101, 0, 0],                      // u
    [0, 0, 0b10001, 0b10001, 0b10001, 0b01010, 0b00100, 0, 0],                      // v
    [0, 0, 0b10001, 0b10001, 0b10101, 0b10101, 0b01010, 0, 0],                      // w
    [0, 0, 0b10001, 0b01010, 0b00100, 0b01010, 0b10001, 0, 0],                      // x
    [0, 0, 0b10001, 0b10001, 0b10001, 0b10001, 0b01111, 0b00001, 0b01110],          // y
    [0, 0, 0b11111, 0b00010, 0b00100, 0b01000, 0b11111, 0, 0],                      // z
    [0b00010, 0b00100, 0b00100, 0b01000, 0b00100, 0b00100, 0b00010, 0, 0],          // {
    [0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0, 0],          // |
    [0b01000, 0b00100, 0b00100, 0b00010, 0b00100, 0b00100, 0b01000, 0, 0],          // }
    [0, 0, 0b01000, 0b10101, 0b00010, 0, 0, 0, 0],                                  // ~
];

// ---------------------------------------------------------------------------------------------
// Axes, ticks
// ---------------------------------------------------------------------------------------------

const TEXT: RGBColor = RGBColor(20, 20, 20);
const FRAME: RGBColor = RGBColor(60, 60, 60);
const GRID: RGBColor = RGBColor(225, 225, 225);
const TICK_UNIT: i32 = 2;
const TITLE_UNIT: i32 = 3;
const TICK_LEN: i32 = 6;

/// "Nice" tick values (1, 2 or 5 times a power of ten) covering `lo..=hi`, about `target` of them,
/// and the number of decimals their labels need.
fn nice_ticks(lo: f64, hi: f64, target: usize) -> (Vec<f64>, usize) {
    let span = hi - lo;
    if !(span.is_finite() && span > 0.0) {
        return (vec![lo], 0);
    }
    let raw = span / target.max(1) as f64;
    let exp = raw.log10().floor() as i32;
    let pow = |e: i32| 10f64.powi(e.abs());
    // value of k * mult * 10^exp, computed so that e.g. 3 * 0.1 gives exactly 0.3
    let value = |k: i64, mult: f64| {
        if exp < 0 {
            k as f64 * mult / pow(exp)
        } else {
            k as f64 * mult * pow(exp)
        }
    };
    let mult = [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .find(|&m| value(1, m) >= raw)
        .unwrap_or(10.0);
    let step = value(1, mult);
    let decimals = (-step.log10().floor()).max(0.0) as usize;
    let first = (lo / step - 1e-9).ceil() as i64;
    let last = (hi / step + 1e-9).floor() as i64;
    let ticks = (first..=last).map(|k| value(k, mult)).collect();
    (ticks, decimals)
}

/// Frame of the plotting area, ticks with labels on the left and bottom, and the axis titles.
/// `xt`/`yt` are (value in chart coordinates, label).
#[allow(clippy::too_many_arguments)]
fn axes<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    chart: &ChartContext<'_, DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>,
    ink: Ink,
    (x_lo, x_hi): (f64, f64),
    (y_lo, y_hi): (f64, f64),
    xt: &[(f64, String)],
    yt: &[(f64, String)],
    x_title: &str,
    y_title: &str,
) -> DrawResult {
    let (left, top) = chart.backend_coord(&(x_lo, y_hi));
    let (right, bottom) = chart.backend_coord(&(x_hi, y_lo));
    root.draw(&Rectangle::new(
        [(left, top), (right, bottom)],
        FRAME.stroke_width(1),
    ))
    .map_err(de)?;
    let line = FRAME.stroke_width(1);
    let gap = TICK_LEN + 4;
    // One tick: its line between two points, its label at `at` anchored by `anchor`.
    let tick = |ends: [(i32, i32); 2], text: &str, at: (i32, i32), anchor: (HPos, VPos)| {
        root.draw(&PathElement::new(ends.to_vec(), line))
            .map_err(de)?;
        label(root, ink, text, at, TICK_UNIT, TEXT, anchor, false)
    };
    for (x, text) in xt {
        let (px, _) = chart.backend_coord(&(*x, y_lo));
        tick(
            [(px, bottom), (px, bottom + TICK_LEN)],
            text,
            (px, bottom + gap),
            (HPos::Center, VPos::Top),
        )?;
    }
    let mut widest = 0;
    for (y, text) in yt {
        let (_, py) = chart.backend_coord(&(x_lo, *y));
        tick(
            [(left - TICK_LEN, py), (left, py)],
            text,
            (left - gap, py),
            (HPos::Right, VPos::Center),
        )?;
        widest = widest.max(text.chars().count() as i32);
    }
    let char_w = ADVANCE * TICK_UNIT;
    label(
        root,
        ink,
        x_title,
        ((left + right) / 2, bottom + gap + 10 * TICK_UNIT + 10),
        TICK_UNIT,
        TEXT,
        (HPos::Center, VPos::Top),
        false,
    )?;
    label(
        root,
        ink,
        y_title,
        (left - gap - widest * char_w - 12, (top + bottom) / 2),
        TICK_UNIT,
        TEXT,
        (HPos::Center, VPos::Bottom),
        true,
    )
}

// ---------------------------------------------------------------------------------------------
// Coverage map
// ---------------------------------------------------------------------------------------------

const BEFORE_COLOR: RGBColor = RGBColor(31, 90, 180);
const AFTER_COLOR: RGBColor = RGBColor(200, 70, 20);
const FILLED_SHADE: RGBColor = RGBColor(196, 232, 196);
const REGION_LINE: RGBColor = RGBColor(185, 185, 185);

struct Panel<'a> {
    name: &'a str,
    dirs: &'a [[f64; 3]],
    filled: &'a [bool],
    color: RGBColor,
}

struct CoverageFigure<'a> {
    title: &'a str,
    panels: [Panel<'a>; 2],
}

/// (theta, phi) in degrees of a direction, or None for a zero or non-finite vector.
fn theta_phi(v: &[f64; 3]) -> Option<(f64, f64)> {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if !(n.is_finite() && n > 0.0) {
        return None;
    }
    let theta = (v[2] / n).clamp(-1.0, 1.0).acos().to_degrees();
    Some((theta, v[1].atan2(v[0]).to_degrees()))
}

/// A figure's white background and its title centred at the top.
fn titled<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, ink: Ink, title: &str) -> DrawResult {
    root.fill(&WHITE).map_err(de)?;
    let (w, _) = root.dim_in_pixel();
    label(
        root,
        ink,
        title,
        (w as i32 / 2, 14),
        TITLE_UNIT,
        TEXT,
        (HPos::Center, VPos::Top),
        false,
    )
}

impl Figure for CoverageFigure<'_> {
    fn size(&self) -> (u32, u32) {
        (1600, 640)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>, ink: Ink) -> DrawResult {
        titled(root, ink, self.title)?;
        let (w, _) = root.dim_in_pixel();
        let (left_half, right_half) = root.split_horizontally(w / 2);
        for (panel, area) in self.panels.iter().zip([left_half, right_half]) {
            self.draw_panel(root, &area, panel, ink)?;
        }
        Ok(())
    }
}

impl CoverageFigure<'_> {
    fn draw_panel<DB: DrawingBackend>(
        &self,
        root: &DrawingArea<DB, Shift>,
        area: &DrawingArea<DB, Shift>,
        panel: &Panel<'_>,
        ink: Ink,
    ) -> DrawResult {
        // y is -theta so that the north pole (theta = 0) is at the top.
        let chart = ChartBuilder::on(area)
            .margin_top(92)
            .margin_bottom(78)
            .margin_left(104)
            .margin_right(28)
            .build_cartesian_2d(-180f64..180f64, -180f64..0f64)
            .map_err(de)?;
        let plot = chart.plotting_area();

        let filled = |i: usize| panel.filled.get(i).copied().unwrap_or(false);
        for i in (0..REGIONS).filter(|&i| filled(i)) {
            let (t0, t1, p0, p1) = region_outline(i);
            plot.draw(&Rectangle::new(
                [(p0, -t0), (p1, -t1)],
                FILLED_SHADE.filled(),
            ))
            .map_err(de)?;
        }
        let faint = REGION_LINE.stroke_width(1);
        for i in 0..REGIONS {
            let (t0, t1, p0, _) = region_outline(i);
            plot.draw(&PathElement::new(vec![(-180.0, -t1), (180.0, -t1)], faint))
                .map_err(de)?;
            if p0 > -180.0 {
                plot.draw(&PathElement::new(vec![(p0, -t0), (p0, -t1)], faint))
                    .map_err(de)?;
            }
        }

        let points: Vec<(f64, f64)> = panel
            .dirs
            .iter()
            .filter_map(theta_phi)
            .map(|(t, p)| (p, -t))
            .collect();
        let radius = if points.len() > 20_000 { 1 } else { 2 };
        let dot = panel.color.mix(0.8).filled();
        plot.draw_series_points(&points, radius, dot)?;

        let ticks = |values: &[f64], sign: f64| -> Vec<(f64, String)> {
            values
                .iter()
                .map(|&v| (sign * v, format!("{v:.0}")))
                .collect()
        };
        let xt = ticks(&[-180.0, -120.0, -60.0, 0.0, 60.0, 120.0, 180.0], 1.0);
        let yt = ticks(&[0.0, 30.0, 60.0, 90.0, 120.0, 150.0, 180.0], -1.0);
        axes(
            root,
            &chart,
            ink,
            (-180.0, 180.0),
            (-180.0, 0.0),
            &xt,
            &yt,
            "azimuth φ = atan2(y, x) (°)",
            "polar angle θ from +z (°)",
        )?;

        let count = (0..REGIONS).filter(|&i| filled(i)).count();
        let caption = format!(
            "{}: {} directions, {count}/{REGIONS} regions covered",
            panel.name,
            points.len()
        );
        let (left, top) = chart.backend_coord(&(-180.0, 0.0));
        // A dot in the panel's colour before the caption doubles as its legend.
        root.draw(&Circle::new((left + 6, top - 22), 5, panel.color.filled()))
            .map_err(de)?;
        label(
            root,
            ink,
            &caption,
            (left + 18, top - 22),
            TICK_UNIT,
            TEXT,
            (HPos::Left, VPos::Center),
            false,
        )
    }
}

/// Drawing many points on a plotting area.
trait DrawPoints {
    fn draw_series_points(
        &self,
        points: &[(f64, f64)],
        radius: u32,
        style: ShapeStyle,
    ) -> DrawResult;
}

impl<DB: DrawingBackend> DrawPoints
    for DrawingArea<DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>
{
    fn draw_series_points(
        &self,
        points: &[(f64, f64)],
        radius: u32,
        style: ShapeStyle,
    ) -> DrawResult {
        for &p in points {
            self.draw(&Circle::new(p, radius, style)).map_err(de)?;
        }
        Ok(())
    }
}

// ---------------------------------------------------------------------------------------------
// Residuals
// ---------------------------------------------------------------------------------------------

/// Colours of successive series (cycled).
const SERIES_COLORS: [RGBColor; 8] = [
    RGBColor(31, 119, 180),
    RGBColor(230, 110, 10),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(100, 100, 100),
];

struct ResidualFigure<'a> {
    title: &'a str,
    x_label: &'a str,
    y_label: &'a str,
    series: &'a [(&'a str, &'a [f64], &'a [f64])],
}

impl ResidualFigure<'_> {
    fn finite_points(&self, s: usize) -> impl Iterator<Item = (f64, f64)> + '_ {
        let (_, t, r) = self.series[s];
        t.iter()
            .zip(r.iter())
            .map(|(&t, &r)| (t, r))
            .filter(|(t, r)| t.is_finite() && r.is_finite())
    }

    /// x range (time) and y range (symmetric about zero), padded.
    fn ranges(&self) -> ((f64, f64), (f64, f64)) {
        let (mut t_lo, mut t_hi, mut r_max) = (f64::INFINITY, f64::NEG_INFINITY, 0f64);
        for s in 0..self.series.len() {
            for (t, r) in self.finite_points(s) {
                t_lo = t_lo.min(t);
                t_hi = t_hi.max(t);
                r_max = r_max.max(r.abs());
            }
        }
        if t_lo > t_hi {
            (t_lo, t_hi) = (0.0, 1.0);
        } else if t_hi - t_lo < 1e-9 * t_lo.abs().max(1.0) {
            (t_lo, t_hi) = (t_lo - 0.5, t_hi + 0.5);
        } else {
            let pad = 0.02 * (t_hi - t_lo);
            (t_lo, t_hi) = (t_lo - pad, t_hi + pad);
        }
        let r = if r_max > 0.0 && r_max.is_finite() {
            1.1 * r_max
        } else {
            1.0
        };
        ((t_lo, t_hi), (-r, r))
    }
}

impl Figure for ResidualFigure<'_> {
    fn size(&self) -> (u32, u32) {
        (1280, 640)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>, ink: Ink) -> DrawResult {
        titled(root, ink, self.title)?;

        let ((x_lo, x_hi), (y_lo, y_hi)) = self.ranges();
        let (x_ticks, x_dec) = nice_ticks(x_lo, x_hi, 8);
        let (y_ticks, y_dec) = nice_ticks(y_lo, y_hi, 10);
        let xt: Vec<(f64, String)> = x_ticks
            .iter()
            .map(|&v| (v, format!("{v:.x_dec$}")))
            .collect();
        let yt: Vec<(f64, String)> = y_ticks
            .iter()
            .map(|&v| (v, format!("{v:.y_dec$}")))
            .collect();
        let widest = yt
            .iter()
            .map(|(_, s)| s.chars().count() as i32)
            .max()
            .unwrap_or(1);

        let chart = ChartBuilder::on(root)
            .margin_top(64)
            .margin_bottom(80)
            .margin_left(60 + widest * ADVANCE * TICK_UNIT)
            .margin_right(30)
            .build_cartesian_2d(x_lo..x_hi, y_lo..y_hi)
            .map_err(de)?;
        let plot = chart.plotting_area();
        let grid = GRID.stroke_width(1);
        for (x, _) in &xt {
            plot.draw(&PathElement::new(vec![(*x, y_lo), (*x, y_hi)], grid))
                .map_err(de)?;
        }
        for (y, _) in &yt {
            plot.draw(&PathElement::new(vec![(x_lo, *y), (x_hi, *y)], grid))
                .map_err(de)?;
        }
        plot.draw(&PathElement::new(
            vec![(x_lo, 0.0), (x_hi, 0.0)],
            BLACK.stroke_width(2),
        ))
        .map_err(de)?;

        let total: usize = (0..self.series.len())
            .map(|s| self.finite_points(s).count())
            .sum();
        let radius = if total > 20_000 { 1 } else { 2 };
        for s in 0..self.series.len() {
            let color = SERIES_COLORS[s % SERIES_COLORS.len()];
            let points: Vec<(f64, f64)> = self.finite_points(s).collect();
            plot.draw_series_points(&points, radius, color.mix(0.75).filled())?;
        }

        axes(
            root,
            &chart,
            ink,
            (x_lo, x_hi),
            (y_lo, y_hi),
            &xt,
            &yt,
            self.x_label,
            self.y_label,
        )?;

        // Legend, top right inside the plotting area.
        if !self.series.is_empty() {
            let (_, top) = chart.backend_coord(&(x_lo, y_hi));
            let (right, _) = chart.backend_coord(&(x_hi, y_lo));
            let longest = self
                .series
                .iter()
                .map(|(l, _, _)| l.chars().count() as i32)
                .max()
                .unwrap_or(0);
            let line_h = 12 * TICK_UNIT;
            let box_w = longest * ADVANCE * TICK_UNIT + 46;
            let box_h = self.series.len() as i32 * line_h + 12;
            let (bx, by) = (right - box_w - 10, top + 10);
            root.draw(&Rectangle::new(
                [(bx, by), (bx + box_w, by + box_h)],
                WHITE.mix(0.85).filled(),
            ))
            .map_err(de)?;
            root.draw(&Rectangle::new(
                [(bx, by), (bx + box_w, by + box_h)],
                GRID.stroke_width(1),
            ))
            .map_err(de)?;
            for (s, (name, _, _)) in self.series.iter().enumerate() {
                let color = SERIES_COLORS[s % SERIES_COLORS.len()];
                let y = by + 6 + s as i32 * line_h + line_h / 2;
                root.draw(&Circle::new((bx + 16, y), 5, color.filled()))
                    .map_err(de)?;
                label(
                    root,
                    ink,
                    name,
                    (bx + 30, y),
                    TICK_UNIT,
                    TEXT,
                    (HPos::Left, VPos::Center),
                    false,
                )?;
            }
        }
        Ok(())
    }
}

// ---------------------------------------------------------------------------------------------
// Tests
// ---------------------------------------------------------------------------------------------

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    /// Region index of a direction under `region_outline`'s numbering (test-only inverse).
    fn region_of(v: &[f64; 3]) -> usize {
        let (theta, phi) = theta_phi(v).unwrap();
        (0..REGIONS)
            .find(|&i| {
                let (t0, t1, p0, p1) = region_outline(i);
                theta >= t0 && theta <= t1 && phi >= p0 && phi <= p1
            })
            .unwrap()
    }

    /// Deterministic pseudo-random unit vectors (xorshift; no dependency on rand's API).
    fn directions(n: usize, seed: u64, upper_half_only: bool) -> Vec<[f64; 3]> {
        let mut s = seed.max(1);
        let mut next = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        (0..n)
            .map(|_| {
                let z = 2.0 * next() - 1.0;
                let z = if upper_half_only { z.abs() } else { z };
                let a = 2.0 * PI * next();
                let r = (1.0 - z * z).sqrt();
                let scale = 40.0 + 10.0 * next(); // any length: normalised inside
                [scale * r * a.cos(), scale * r * a.sin(), scale * z]
            })
            .collect()
    }

    fn filled(dirs: &[[f64; 3]]) -> Vec<bool> {
        let mut f = vec![false; REGIONS];
        for d in dirs {
            f[region_of(d)] = true;
        }
        f
    }

    fn only_file(dir: &Path) -> PathBuf {
        let entries: Vec<PathBuf> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().path())
            .collect();
        assert_eq!(
            entries.len(),
            1,
            "expected exactly one file, found {entries:?}"
        );
        entries[0].clone()
    }

    #[test]
    fn region_outline_covers_sphere_with_equal_solid_angles() {
        let target = 4.0 * PI / REGIONS as f64;
        let mut total = 0.0;
        for i in 0..REGIONS {
            let (t0, t1, p0, p1) = region_outline(i);
            assert!(t0 < t1 && p0 < p1, "region {i}");
            assert!((0.0..=180.0).contains(&t0) && (0.0..=180.0).contains(&t1));
            assert!((-180.0..=180.0).contains(&p0) && (-180.0..=180.0).contains(&p1));
            let omega = (t0.to_radians().cos() - t1.to_radians().cos()) * (p1 - p0).to_radians();
            assert!(
                (omega / target - 1.0).abs() < 0.01,
                "region {i}: {omega} vs {target}"
            );
            total += omega;
        }
        assert!((total - 4.0 * PI).abs() < 1e-9);
        assert_eq!(region_outline(0), (0.0, region_outline(0).1, -180.0, 180.0));
        assert!((region_outline(0).1 - 11.48).abs() < 0.01);
        assert_eq!(region_outline(99).1, 180.0);
        // Bands: 1, 15, 34, 34, 15, 1, phi rising within each band.
        let band_sizes: Vec<usize> = {
            let mut sizes = vec![];
            let mut i = 0;
            while i < REGIONS {
                let t0 = region_outline(i).0;
                let n = (i..REGIONS)
                    .take_while(|&j| region_outline(j).0 == t0)
                    .count();
                sizes.push(n);
                i += n;
            }
            sizes
        };
        assert_eq!(band_sizes, vec![1, 15, 34, 34, 15, 1]);
        assert_eq!(region_outline(1).2, -180.0);
        assert!((region_outline(15).3 - 180.0).abs() < 1e-9);
        assert!((region_outline(16).0 - 47.16).abs() < 0.01); // latitude 42.84
    }

    #[test]
    #[should_panic]
    fn region_outline_rejects_index_100() {
        region_outline(REGIONS);
    }

    #[test]
    fn region_numbering_spot_checks() {
        assert_eq!(region_of(&[0.0, 0.0, 1.0]), 0);
        assert_eq!(region_of(&[0.0, 0.0, -1.0]), 99);
        // Just north of the equator, just past phi = -180: first region of the 34-band.
        assert_eq!(region_of(&[-1.0, -1e-3, 0.01]), 16);
        assert_eq!(region_of(&[-1.0, -1e-3, -0.01]), 50);
    }

    #[test]
    fn coverage_map_writes_png_and_svg() {
        let before = directions(500, 7, true);
        let after = directions(800, 11, false);
        let (fb, fa) = (filled(&before), filled(&after));
        for ext in ["png", "svg", "PNG"] {
            let dir = tempfile::tempdir().unwrap();
            let path = dir.path().join(format!("coverage.{ext}"));
            coverage_map(&path, "mag coverage", &before, &after, &fb, &fa).unwrap();
            assert_eq!(only_file(dir.path()), path);
            assert!(std::fs::metadata(&path).unwrap().len() > 1000);
        }
    }

    #[test]
    fn coverage_map_tolerates_empty_and_degenerate_input() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.png");
        let odd = [[0.0, 0.0, 0.0], [f64::NAN, 1.0, 0.0], [0.0, 0.0, 2.0]];
        coverage_map(&path, "", &[], &odd, &[], &[true; 3]).unwrap();
        assert_eq!(only_file(dir.path()), path);
    }

    #[test]
    fn residuals_write_png_and_svg() {
        let t: Vec<f64> = (0..300).map(|i| i as f64 * 0.1).collect();
        let r1: Vec<f64> = t.iter().map(|t| 0.3 * (t * 1.7).sin()).collect();
        let r2: Vec<f64> = t.iter().map(|t| -0.2 * (t * 0.9).cos() + 0.05).collect();
        let series: [(&str, &[f64], &[f64]); 2] = [("x", &t, &r1), ("norm", &t, &r2)];
        for ext in ["png", "svg"] {
            let dir = tempfile::tempdir().unwrap();
            let path = dir.path().join(format!("res.{ext}"));
            residuals(&path, "accel residuals", "residual (m/s²)", &series).unwrap();
            assert_eq!(only_file(dir.path()), path);
            assert!(std::fs::metadata(&path).unwrap().len() > 1000);
        }
        // Degenerate: no series, one point.
        let dir = tempfile::tempdir().unwrap();
        residuals(&dir.path().join("a.png"), "t", "y", &[]).unwrap();
        residuals(
            &dir.path().join("b.svg"),
            "t",
            "y",
            &[("one", &[5.0], &[0.0])],
        )
        .unwrap();
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);
    }

    #[test]
    fn svg_carries_text_labels() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("res.svg");
        residuals(
            &path,
            "Gyro & bias <test>",
            "rate (deg/s)",
            &[("z", &[0.0, 1.0], &[0.1, -0.1])],
        )
        .unwrap();
        let svg = std::fs::read_to_string(&path).unwrap();
        assert!(svg.contains("<text"));
        assert!(svg.contains("rate (deg/s)"));
        assert!(svg.contains("time (s)"));
        assert!(svg.contains("Gyro &amp; bias &lt;test&gt;"));
    }

    #[test]
    fn png_labels_are_drawn() {
        // The same residual plot with and without a long title: the title must change pixels.
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("a.png"), dir.path().join("b.png"));
        residuals(&a, "", "y", &[]).unwrap();
        residuals(&b, "A TITLE THAT SHOWS", "y", &[]).unwrap();
        assert_ne!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
    }

    #[test]
    fn errors_leave_no_file() {
        let dir = tempfile::tempdir().unwrap();
        let bad = dir.path().join("plot.jpg");
        assert!(matches!(
            residuals(&bad, "t", "y", &[]),
            Err(Error::Other(_))
        ));
        let mismatched = dir.path().join("plot.png");
        let err = residuals(&mismatched, "t", "y", &[("s", &[1.0, 2.0], &[1.0])]);
        assert!(matches!(err, Err(Error::Other(_))));
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
        let missing_dir = dir.path().join("no/such/dir/plot.svg");
        assert!(matches!(
            residuals(&missing_dir, "t", "y", &[]),
            Err(Error::Write { .. })
        ));
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn nice_ticks_are_round() {
        let (t, d) = nice_ticks(-0.33, 0.33, 8);
        assert_eq!(d, 1);
        assert!(t.contains(&0.0) && t.contains(&0.3) && t.contains(&-0.3));
        let (t, d) = nice_ticks(0.0, 29.9, 8);
        assert_eq!((t[0], t[t.len() - 1], d), (0.0, 25.0, 0));
    }

    #[test]
    fn every_printable_ascii_has_a_glyph() {
        for c in ' '..='~' {
            let g = glyph(c);
            assert!(g.iter().all(|row| *row < 32), "{c:?}");
            assert_eq!(c == ' ', g.iter().all(|row| *row == 0), "{c:?}");
        }
    }
}
