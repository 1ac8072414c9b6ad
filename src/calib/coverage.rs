//! Sphere coverage: which of 100 equal-area regions of the unit sphere hold at least one measured
//! direction (MotionCal's layout of latitude bands: 1 + 15 + 34 + 34 + 15 + 1 regions), and the
//! (theta, phi) projection of Camps, Harasse and Monin, "Numerical calibration for 3-axis
//! accelerometers and magnetometers" (2009). Directions are taken about the current hard-iron centre.

use crate::calib::sections::{section80, set_section};
use crate::types::Vec3;
use serde::{Deserialize, Serialize};

/// Number of regions.
pub(crate) const REGIONS: usize = 100;

/// Latitude bands north to south as (lowest z = sin(latitude), regions in the band). Equal areas
/// on a sphere are equal spans of z, so with 100 regions the edges are z = 0.98, 0.68, 0, -0.68,
/// -0.98 (latitudes 78.52, 42.84, 0, -42.84, -78.52 deg).
pub(crate) const BANDS: [(f64, usize); 6] = [
    (0.98, 1),
    (0.68, 15),
    (0.0, 34),
    (-0.68, 34),
    (-0.98, 15),
    (-1.0, 1),
];

/// Region index (0..100) of a direction (any length, not zero).
pub fn region(v: &Vec3) -> Option<usize> {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if !(n > 0.0) || !n.is_finite() {
        return None;
    }
    let z = (v[2] / n).clamp(-1.0, 1.0);
    let mut base = 0;
    for &(lo, count) in BANDS.iter() {
        if z >= lo {
            if count == 1 {
                return Some(base);
            }
            let phi = v[1].atan2(v[0]); // -pi..pi
            let k = (((phi + std::f64::consts::PI) / std::f64::consts::TAU) * count as f64).floor()
                as usize;
            return Some(base + k.min(count - 1));
        }
        base += count;
    }
    None
}

/// (theta, phi) of Camps et al. in degrees: theta polar angle from +z (0..180), phi azimuth (-180..180).
pub fn theta_phi(v: &Vec3) -> (f64, f64) {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-300);
    (
        (v[2] / n).clamp(-1.0, 1.0).acos().to_degrees(),
        v[1].atan2(v[0]).to_degrees(),
    )
}

/// Regions as 25 hexadecimal digits (region `i` is bit `i % 4` of digit `i / 4`), as the JSON
/// `progress` line and the pages carry them.
pub(crate) fn regions_hex(regions: &[bool]) -> String {
    regions
        .chunks(4)
        .map(|c| {
            let d = c
                .iter()
                .enumerate()
                .map(|(b, &f)| (f as u32) << b)
                .sum::<u32>();
            char::from_digit(d, 16).unwrap_or('0')
        })
        .collect()
}

/// Coverage summary as the report gives it.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Coverage {
    pub regions: usize,
    pub filled: usize,
    pub gaps_pct: f64,
    #[serde(skip)]
    pub filled_mask: Vec<bool>,
}

/// Coverage of a set of directions about `centre`. The points are visited interleaved (every 61st,
/// then the next offset, ...) so that sorted input still reaches every part of the sphere early, and
/// the scan stops once every region holds a point.
pub fn coverage(points: &[Vec3], centre: &Vec3) -> Coverage {
    const STRIDE: usize = 61;
    let mut mask = vec![false; REGIONS];
    let mut filled = 0;
    let interleaved =
        (0..STRIDE.min(points.len())).flat_map(|s| points[s..].iter().step_by(STRIDE));
    for p in interleaved {
        if let Some(r) = region(&[p[0] - centre[0], p[1] - centre[1], p[2] - centre[2]]) {
            if !mask[r] {
                mask[r] = true;
                filled += 1;
                if filled == REGIONS {
                    break;
                }
            }
        }
    }
    Coverage {
        regions: REGIONS,
        filled,
        gaps_pct: 100.0 * (REGIONS - filled) as f64 / REGIONS as f64,
        filled_mask: mask,
    }
}

/// Most field vectors [`DirectionBins`] keeps (about 3 deg cells over the whole sphere).
pub(crate) const MAX_BINNED: usize = 4000;

/// Keeps fit points at least about a minimum angle apart: directions about a centre are binned on a
/// grid of cells about `min_separation_deg` wide and each cell keeps the first raw vector that fell in
/// it. Raw samples are kept as they are (no averaging: a mean of points on a sphere lies inside it and
/// would bias the fit).
#[derive(Debug, Clone)]
pub struct DirectionBins {
    pub centre: Vec3,
    cell_rad: f64,
    /// Cells by (row, column); ordered, so the kept points come out in a fixed order with no sort.
    cells: std::collections::BTreeMap<(i32, i32), Vec3>,
}

impl DirectionBins {
    pub fn new(centre: Vec3, min_separation_deg: f64) -> Self {
        DirectionBins {
            centre,
            cell_rad: min_separation_deg.max(0.01).to_radians(),
            cells: Default::default(),
        }
    }

    fn key(&self, raw: &Vec3) -> Option<(i32, i32)> {
        let d = [
            raw[0] - self.centre[0],
            raw[1] - self.centre[1],
            raw[2] - self.centre[2],
        ];
        let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        if !(n > 0.0) {
            return None;
        }
        // Rows of constant polar angle one cell high, each ring cut into as many cells as fit its circumference.
        let z = (d[2] / n).clamp(-1.0, 1.0);
        let theta = z.acos();
        let row = (theta / self.cell_rad).floor() as i32;
        // sin(theta) from z directly (the same value, without a second transcendental call).
        let ring = ((1.0 - z * z).max(0.0).sqrt() * std::f64::consts::TAU / self.cell_rad)
            .ceil()
            .max(1.0);
        let phi = d[1].atan2(d[0]) + std::f64::consts::PI;
        let col = ((phi / std::f64::consts::TAU) * ring).floor() as i32;
        Some((row, col))
    }

    /// Keep `raw` if its cell is still empty. Returns whether it was kept. Past [`MAX_BINNED`] kept
    /// vectors the cells widen by sqrt(2) (and the kept ones are binned again, about half stay), so
    /// memory and fit time stay bounded however long the stream runs.
    pub fn add(&mut self, raw: &Vec3) -> bool {
        let kept = self.insert(raw);
        if kept && self.cells.len() > MAX_BINNED {
            self.cell_rad *= std::f64::consts::SQRT_2;
            let c = self.centre;
            self.recentre(c);
        }
        kept
    }

    fn insert(&mut self, raw: &Vec3) -> bool {
        match self.key(raw) {
            Some(k) => match self.cells.entry(k) {
                std::collections::btree_map::Entry::Vacant(e) => {
                    e.insert(*raw);
                    true
                }
                std::collections::btree_map::Entry::Occupied(_) => false,
            },
            None => false,
        }
    }

    /// Current cell width, degrees.
    pub(crate) fn cell_deg(&self) -> f64 {
        self.cell_rad.to_degrees()
    }

    /// Re-bin the kept vectors about a new centre (after a fit moved the hard-iron estimate).
    pub(crate) fn recentre(&mut self, centre: Vec3) {
        let mut old: Vec<Vec3> = std::mem::take(&mut self.cells).into_values().collect();
        // Deterministic order whatever the hash map did.
        old.sort_by(|a, b| a.partial_cmp(b).unwrap_or(std::cmp::Ordering::Equal));
        self.centre = centre;
        for p in old {
            self.insert(&p);
        }
    }

    /// Kept raw vectors, in a deterministic order.
    pub fn points(&self) -> Vec<Vec3> {
        self.cells.values().copied().collect()
    }

    pub fn len(&self) -> usize {
        self.cells.len()
    }
    pub fn is_empty(&self) -> bool {
        self.cells.is_empty()
    }
}

/// Which parts of the sphere magnetometer points cover about one centre: the coverage regions
/// ([`region`]) and ArduPilot's 80 sections ([`section80`]). Built up point by point, so a
/// progress report costs the points kept since the last one, not all.
#[derive(Debug, Clone)]
pub struct CoverageMap {
    pub centre: Vec3,
    pub regions: [bool; REGIONS],
    pub regions_filled: usize,
    /// ArduPilot's completion mask.
    pub mask: [u8; 10],
    /// Direction of the last point added, about the centre.
    pub last_dir: Vec3,
}

impl CoverageMap {
    pub fn new(centre: Vec3) -> CoverageMap {
        CoverageMap {
            centre,
            regions: [false; REGIONS],
            regions_filled: 0,
            mask: [0; 10],
            last_dir: [0.0; 3],
        }
    }

    /// Mark the regions and sections of `points` (raw vectors) about the centre.
    pub fn add(&mut self, points: &[Vec3]) {
        let c = self.centre;
        for p in points {
            let d = [p[0] - c[0], p[1] - c[1], p[2] - c[2]];
            if let Some(r) = region(&d) {
                if !self.regions[r] {
                    self.regions[r] = true;
                    self.regions_filled += 1;
                }
            }
            if let Some(s) = section80(&d) {
                set_section(&mut self.mask, s);
            }
            self.last_dir = d;
        }
    }
}

/// Completion of one calibration run (from the start, or from a restart of the calibration), as
/// MAG_CAL_PROGRESS and the JSON `progress` line report it.
///
/// * No region is counted before a centre is known (a calibration, or the pipeline's centre from
///   points spread enough, [`crate::calib::pipeline::Pipeline::mag_centre`]): directions about a guessed
///   centre make a still sensor look like it filled half the sphere.
/// * The regions are the union of all regions seen about the current centre (points the pipeline
///   drops or re-bins later still count). When the centre moves, they are derived again from the
///   kept points about the new centre.
/// * Completion is a high-water mark: it never goes down within a run, also when a new centre
///   shows fewer regions than the old one did.
#[derive(Debug, Clone)]
pub struct Progress {
    full_regions: usize,
    map: Option<CoverageMap>,
    /// The pipeline's magnetometer epoch the map holds the points of (see
    /// [`crate::calib::pipeline::Pipeline::take_fresh_mag`]).
    epoch: u64,
    high_water_pct: u8,
}

/// One progress report.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProgressReport {
    /// High-water mark of filled regions / `full_regions`, 0..=100.
    pub completion_pct: u8,
    /// Regions (of [`REGIONS`]) filled about the current centre; 0 while no centre is known.
    pub filled_regions: usize,
    /// ArduPilot's 80-section completion mask about the current centre.
    pub mask: [u8; 10],
    /// Which of the [`REGIONS`] regions are filled about the current centre (none while no
    /// centre is known).
    pub regions: [bool; REGIONS],
    /// Direction of the latest point about the centre (zero while no centre is known).
    pub direction: Vec3,
    /// Whether a centre is known.
    pub centre_known: bool,
}

impl Progress {
    /// `full_regions`: regions that count as 100 % (`daemon.progress_full_regions`, 1..=100).
    pub fn new(full_regions: usize) -> Progress {
        Progress {
            full_regions: full_regions.clamp(1, REGIONS),
            map: None,
            epoch: 0,
            high_water_pct: 0,
        }
    }

    /// A new calibration run: no regions, completion back to zero.
    pub fn restart(&mut self) {
        *self = Progress::new(self.full_regions);
    }

    /// Completion so far in this run, percent.
    pub fn completion_pct(&self) -> u8 {
        self.high_water_pct
    }

    /// Take in the magnetometer points kept since the last call and report. `centre`: the current
    /// centre, `None` while unknown; `epoch` and `fresh` as [`crate::calib::pipeline::Pipeline::take_fresh_mag`]
    /// gives them; `all` the kept points (called only when the centre or the epoch changed).
    pub fn update(
        &mut self,
        centre: Option<Vec3>,
        epoch: u64,
        fresh: &[Vec3],
        all: impl FnOnce() -> Vec<Vec3>,
    ) -> ProgressReport {
        let Some(c) = centre.filter(|c| c.iter().all(|v| v.is_finite())) else {
            self.map = None;
            return ProgressReport {
                completion_pct: self.high_water_pct,
                filled_regions: 0,
                mask: [0; 10],
                regions: [false; REGIONS],
                direction: [0.0; 3],
                centre_known: false,
            };
        };
        match &mut self.map {
            // Same centre and the same kept set: only the new points.
            Some(m) if m.centre == c && self.epoch == epoch => m.add(fresh),
            // Same centre, points dropped or re-binned: the union with what was seen before.
            Some(m) if m.centre == c => m.add(&all()),
            // A new centre: the regions about it, from the points kept.
            slot => {
                let m = slot.insert(CoverageMap::new(c));
                m.add(&all());
            }
        }
        self.epoch = epoch;
        let m = self.map.as_ref().expect("set above");
        let pct = ((100 * m.regions_filled) / self.full_regions).min(100) as u8;
        self.high_water_pct = self.high_water_pct.max(pct);
        ProgressReport {
            completion_pct: self.high_water_pct,
            filled_regions: m.regions_filled,
            mask: m.mask,
            regions: m.regions,
            direction: m.last_dir,
            centre_known: true,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn coverage_map_built_in_steps_matches_the_full_scan() {
        // Points on a sphere of radius 40 about c, over about two thirds of the directions.
        let c = [12.0, -7.0, 30.0];
        let pts: Vec<Vec3> = (0..1500)
            .map(|i| {
                let z = 1.0 - 2.0 * (i as f64 + 0.5) / 1500.0;
                let phi = i as f64 * 2.399_963;
                let r = (1.0 - z * z).sqrt();
                [40.0 * r * phi.cos(), 40.0 * r * phi.sin(), 40.0 * z]
            })
            .filter(|d| d[2] < 15.0)
            .map(|d| [d[0] + c[0], d[1] + c[1], d[2] + c[2]])
            .collect();
        let mut stepped = CoverageMap::new(c);
        for chunk in pts.chunks(97) {
            stepped.add(chunk);
        }
        let dirs: Vec<Vec3> = pts
            .iter()
            .map(|p| [p[0] - c[0], p[1] - c[1], p[2] - c[2]])
            .collect();
        let full = coverage(&dirs, &[0.0; 3]);
        let (mask, sections) = crate::calib::sections::completion_mask(dirs.iter().copied());
        assert_eq!(stepped.regions_filled, full.filled);
        assert!(full.filled > 30 && full.filled < 100, "{}", full.filled);
        assert_eq!(stepped.mask, mask);
        assert!(sections > 20 && sections < 80, "{sections}");
        assert_eq!(stepped.last_dir, *dirs.last().unwrap());
    }

    #[test]
    fn direction_bins_stay_bounded_and_spread() {
        // A million directions (Fibonacci sphere, shuffled by a stride) about a centre.
        let mut b = DirectionBins::new([10.0, -5.0, 3.0], 1.0);
        let n = 1_000_000usize;
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        for j in 0..n {
            let i = (j * 7919) % n;
            let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = golden * i as f64;
            b.add(&[
                10.0 + 50.0 * r * phi.cos(),
                -5.0 + 50.0 * r * phi.sin(),
                3.0 + 50.0 * z,
            ]);
            assert!(b.len() <= MAX_BINNED);
        }
        assert!(b.len() > MAX_BINNED / 3, "{} kept", b.len());
        assert!(b.cell_deg() > 1.0);
        // Still the whole sphere.
        assert_eq!(coverage(&b.points(), &[10.0, -5.0, 3.0]).filled, REGIONS);
    }

    /// Points on a sphere of radius 50 about `c` with polar angle below `max_deg` (Fibonacci spiral).
    fn cap(c: Vec3, max_deg: f64, n: usize) -> Vec<Vec3> {
        let zmin = max_deg.to_radians().cos();
        (0..n)
            .map(|i| {
                let z = 1.0 - (1.0 - zmin) * (i as f64 + 0.5) / n as f64;
                let r = (1.0 - z * z).sqrt();
                let phi = i as f64 * 2.399_963;
                [
                    c[0] + 50.0 * r * phi.cos(),
                    c[1] + 50.0 * r * phi.sin(),
                    c[2] + 50.0 * z,
                ]
            })
            .collect()
    }

    #[test]
    fn progress_counts_nothing_without_a_centre_and_never_goes_down_in_a_run() {
        let c = [10.0, -20.0, 30.0];
        let half = cap(c, 90.0, 2000);
        let mut p = Progress::new(80);
        // No centre: nothing counted, whatever the points.
        let r = p.update(None, 0, &half, || half.clone());
        assert_eq!(
            (r.completion_pct, r.filled_regions, r.centre_known),
            (0, 0, false)
        );
        // About the centre: the upper hemisphere (51 regions: the cap, band 1 and band 2).
        let r = p.update(Some(c), 1, &[], || half.clone());
        assert_eq!(r.filled_regions, 50);
        assert_eq!(r.completion_pct, 62);
        // The pipeline dropped half of its points (new epoch): the regions seen stay.
        let fewer: Vec<Vec3> = half.iter().step_by(2).copied().collect();
        let r = p.update(Some(c), 2, &[], || fewer.clone());
        assert_eq!(r.filled_regions, 50);
        // A fresh point in the same epoch is added.
        let south = [c[0], c[1], c[2] - 50.0];
        let r = p.update(Some(c), 2, &[south], || unreachable!());
        assert_eq!(r.filled_regions, 51);
        assert_eq!(r.direction, [0.0, 0.0, -50.0]);
        // A new centre far below: the points all point up about it, the completion stays.
        let moved = [c[0], c[1], c[2] - 200.0];
        let r = p.update(Some(moved), 2, &[], || fewer.clone());
        assert!(r.filled_regions < 20, "{}", r.filled_regions);
        assert_eq!(r.completion_pct, 63);
        // A restarted run starts from zero.
        p.restart();
        assert_eq!(p.completion_pct(), 0);
        let r = p.update(Some(c), 2, &[south], || vec![south]);
        assert_eq!((r.filled_regions, r.completion_pct), (1, 1));
    }

    #[test]
    fn regions_are_equal_area_and_numbered_0_to_99() {
        // Monte-Carlo over a Fibonacci sphere: each region gets ~1% of the points.
        let n = 200_000;
        let mut counts = [0usize; REGIONS];
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        for i in 0..n {
            let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = golden * i as f64;
            counts[region(&[r * phi.cos(), r * phi.sin(), z]).unwrap()] += 1;
        }
        for (i, c) in counts.iter().enumerate() {
            let frac = *c as f64 / n as f64;
            assert!((frac - 0.01).abs() < 0.0005, "region {i}: {frac}");
        }
        assert_eq!(region(&[0.0, 0.0, 1.0]), Some(0));
        assert_eq!(region(&[0.0, 0.0, -1.0]), Some(99));
    }

    #[test]
    fn coverage_counts_filled_regions() {
        let c = coverage(
            &[[0.0, 0.0, 5.0], [0.0, 0.0, 6.0], [0.0, 0.0, -1.0]],
            &[0.0, 0.0, 1.0],
        );
        assert_eq!(c.filled, 2);
        assert!((c.gaps_pct - 98.0).abs() < 1e-12);
    }

    #[test]
    fn bins_keep_points_apart() {
        let mut b = DirectionBins::new([0.0; 3], 5.0);
        for i in 0..1000 {
            let a = i as f64 * 0.001; // 1 rad arc in 1000 steps
            b.add(&[a.cos() * 50.0, a.sin() * 50.0, 0.0]);
        }
        // ~57 deg of arc at 5 deg cells: about 12 cells (rows straddle the equator: up to 2x)
        assert!(b.len() >= 11 && b.len() <= 26, "{}", b.len());
    }
}
