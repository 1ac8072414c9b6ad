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
    /// Cells by (row, column) ([`cell_id`]); the kept points come out sorted by it.
    cells: CellMap,
    /// The cell of the last vector looked up, which is filled (it was kept there, or found
    /// filled): a stream at IMU rates stays in one cell for many samples, which then cost no
    /// look-up in `cells`. Cleared whenever the cells are rebuilt.
    last: Option<u64>,
}

/// The cells of [`DirectionBins`]: a hash map with [`CellHasher`].
type CellMap = std::collections::HashMap<u64, Vec3, std::hash::BuildHasherDefault<CellHasher>>;

/// A (row, column) cell as one key that sorts as the pair does (rows and columns are never
/// negative).
fn cell_id(row: u32, col: u32) -> u64 {
    (u64::from(row) << 32) | u64::from(col)
}

/// Hashes a cell id with the finaliser of SplitMix64 (Steele, Lea and Flood, "Fast splittable
/// pseudorandom number generators", 2014): every bit of the id reaches the bits the map indexes
/// by, at a few multiplications (the default hasher's protection against chosen keys is not
/// needed for cells).
#[derive(Debug, Clone, Copy, Default)]
struct CellHasher(u64);

impl std::hash::Hasher for CellHasher {
    fn finish(&self) -> u64 {
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0 << 8) | u64::from(b);
        }
    }
    fn write_u64(&mut self, v: u64) {
        self.0 = v;
    }
}

impl DirectionBins {
    pub fn new(centre: Vec3, min_separation_deg: f64) -> Self {
        DirectionBins {
            centre,
            cell_rad: min_separation_deg.max(0.01).to_radians(),
            cells: Default::default(),
            last: None,
        }
    }

    /// The cell of a direction: rows of constant polar angle one cell high, `floor(acos(z) /
    /// cell)`, each ring cut into as many cells as fit its circumference, column
    /// `floor((atan2(y, x) + pi) / 2 pi * ring)`. The angles come from polynomials
    /// ([`cell_index`]); `acos` and `atan2` are called only within a hair of a cell's edge, so the
    /// cells are those of the formula.
    fn key(&self, raw: &Vec3) -> Option<u64> {
        let d = [
            raw[0] - self.centre[0],
            raw[1] - self.centre[1],
            raw[2] - self.centre[2],
        ];
        let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        if !(n > 0.0) {
            return None;
        }
        let z = (d[2] / n).clamp(-1.0, 1.0);
        let cell = self.cell_rad;
        // The near positions multiply where the formula divides (a rounding apart, far inside
        // the margin); the exact ones are the formula's.
        let per_cell = 1.0 / cell;
        let row = cell_index(acos_near(z) * per_cell, per_cell, || z.acos() / cell);
        // sin(theta) from z directly (the same value, without a second transcendental call).
        let ring =
            ceil_small((1.0 - z * z).max(0.0).sqrt() * std::f64::consts::TAU / cell).max(1.0);
        let per_turn = ring * (0.5 * std::f64::consts::FRAC_1_PI);
        let col = cell_index(
            (atan2_near(d[1], d[0]) + std::f64::consts::PI) * per_turn,
            per_turn,
            || ((d[1].atan2(d[0]) + std::f64::consts::PI) / std::f64::consts::TAU) * ring,
        );
        Some(cell_id(row, col))
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
        let Some(k) = self.key(raw) else {
            return false;
        };
        if self.last == Some(k) {
            return false;
        }
        self.last = Some(k);
        match self.cells.entry(k) {
            std::collections::hash_map::Entry::Vacant(e) => {
                e.insert(*raw);
                true
            }
            std::collections::hash_map::Entry::Occupied(_) => false,
        }
    }

    /// Current cell width, degrees.
    pub(crate) fn cell_deg(&self) -> f64 {
        self.cell_rad.to_degrees()
    }

    /// Re-bin the kept vectors about a new centre (after a fit moved the hard-iron estimate).
    pub(crate) fn recentre(&mut self, centre: Vec3) {
        let mut old: Vec<Vec3> = std::mem::take(&mut self.cells).into_values().collect();
        self.last = None;
        // Deterministic order whatever the hash map did (kept vectors are distinct and finite).
        old.sort_by(|a, b| a.partial_cmp(b).unwrap_or(std::cmp::Ordering::Equal));
        self.centre = centre;
        for p in old {
            self.insert(&p);
        }
    }

    /// Kept raw vectors, in a deterministic order (by cell: row, then column).
    pub fn points(&self) -> Vec<Vec3> {
        let mut kept: Vec<(u64, Vec3)> = self.cells.iter().map(|(k, v)| (*k, *v)).collect();
        kept.sort_unstable_by_key(|(k, _)| *k);
        kept.into_iter().map(|(_, v)| v).collect()
    }

    pub fn len(&self) -> usize {
        self.cells.len()
    }
    pub fn is_empty(&self) -> bool {
        self.cells.is_empty()
    }
}

/// Largest error of [`acos_near`] and [`atan2_near`], rad: the polynomials' own (2e-8, Abramowitz
/// and Stegun, "Handbook of Mathematical Functions" (1964), 4.4.46 and 4.4.49) with a wide margin
/// for rounding.
const NEAR_ERR_RAD: f64 = 1e-6;

/// `x.ceil()` without a call to libm's `ceil` (the baseline x86-64 target has no rounding
/// instruction) for `x` above 0 and below 2^52: the truncation (exact there), one up when it fell
/// short. `ceil` itself elsewhere (zeros, negatives, NaN, larger values).
fn ceil_small(x: f64) -> f64 {
    if x > 0.0 && x < 4_503_599_627_370_496.0 {
        let t = x as u64 as f64;
        if t < x {
            t + 1.0
        } else {
            t
        }
    } else {
        x.ceil()
    }
}

/// The cell index `floor(u)` of a position `u` along a row or ring (in cells, not negative),
/// given `near`, within [`NEAR_ERR_RAD`] times `per_rad` (cells per radian) of it: `exact()`,
/// the position by the formula itself, is computed only when `near` lies that close to a cell
/// edge, so the index is always the formula's. (Truncation is the floor here, and costs no call.)
fn cell_index(near: f64, per_rad: f64, exact: impl FnOnce() -> f64) -> u32 {
    let margin = NEAR_ERR_RAD * per_rad;
    let i = near as u32;
    let frac = near - f64::from(i);
    if frac > margin && frac < 1.0 - margin {
        i
    } else {
        exact().floor() as u32
    }
}

/// acos(z) for z in [-1, 1] to within 2e-8 rad (Abramowitz and Stegun 4.4.46): sqrt(1 - x)
/// times a polynomial of degree 7 for x = |z|, reflected for z < 0.
fn acos_near(z: f64) -> f64 {
    const A: [f64; 8] = [
        1.570_796_305_0,
        -0.214_598_801_6,
        0.088_978_987_4,
        -0.050_174_304_6,
        0.030_891_881_0,
        -0.017_088_125_6,
        0.006_670_090_1,
        -0.001_262_491_1,
    ];
    let x = z.abs();
    let p = A.iter().rev().fold(0.0, |acc, &a| acc * x + a);
    let r = (1.0 - x).max(0.0).sqrt() * p;
    if z < 0.0 {
        std::f64::consts::PI - r
    } else {
        r
    }
}

/// atan2(y, x) in [-pi, pi] to within 2e-8 rad (Abramowitz and Stegun 4.4.49 on the octant's
/// ratio in [0, 1], then reflected into place); `atan2` itself on the axis (signed zeros).
fn atan2_near(y: f64, x: f64) -> f64 {
    const A: [f64; 9] = [
        1.0,
        -0.333_331_452_8,
        0.199_935_508_5,
        -0.142_088_994_4,
        0.106_562_639_3,
        -0.075_289_640_0,
        0.042_909_613_8,
        -0.016_165_736_7,
        0.002_866_225_7,
    ];
    let (ax, ay) = (x.abs(), y.abs());
    let (lo, hi) = if ay > ax { (ax, ay) } else { (ay, ax) };
    if !(hi > 0.0) {
        return y.atan2(x);
    }
    let t = lo / hi;
    let t2 = t * t;
    let mut r = t * A.iter().rev().fold(0.0, |acc, &a| acc * t2 + a);
    if ay > ax {
        r = std::f64::consts::FRAC_PI_2 - r;
    }
    if x < 0.0 {
        r = std::f64::consts::PI - r;
    }
    if y < 0.0 {
        -r
    } else {
        r
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

    /// The cell of a direction by the defining formula, with `acos` and `atan2`.
    fn key_by_formula(b: &DirectionBins, raw: &Vec3) -> Option<u64> {
        let d = [
            raw[0] - b.centre[0],
            raw[1] - b.centre[1],
            raw[2] - b.centre[2],
        ];
        let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        if !(n > 0.0) {
            return None;
        }
        let z = (d[2] / n).clamp(-1.0, 1.0);
        let row = (z.acos() / b.cell_rad).floor() as u32;
        let ring = ((1.0 - z * z).max(0.0).sqrt() * std::f64::consts::TAU / b.cell_rad)
            .ceil()
            .max(1.0);
        let phi = d[1].atan2(d[0]) + std::f64::consts::PI;
        let col = ((phi / std::f64::consts::TAU) * ring).floor() as u32;
        Some(cell_id(row, col))
    }

    #[test]
    fn ceil_small_is_ceil() {
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        let mut values = vec![
            0.0,
            -0.0,
            0.5,
            1.0,
            1.5,
            2.0,
            1e-300,
            4_503_599_627_370_495.5,
        ];
        values.extend([4_503_599_627_370_496.0, 1e300, f64::INFINITY]);
        for _ in 0..200_000 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            // Cells per ring as key() forms them (up to a few thousand), and their neighbours.
            let v = (x >> 11) as f64 / (1u64 << 53) as f64 * 4000.0;
            values.extend([v, v.floor(), v.ceil(), v.next_up(), v.next_down()]);
        }
        for v in values {
            assert_eq!(ceil_small(v).to_bits(), v.ceil().to_bits(), "{v:e}");
        }
        assert!(ceil_small(f64::NAN).is_nan());
    }

    #[test]
    fn the_approximate_angles_stay_within_their_bound() {
        let (mut worst_acos, mut worst_atan2) = (0.0f64, 0.0f64);
        for i in 0..=200_000 {
            let z = -1.0 + 2.0 * i as f64 / 200_000.0;
            worst_acos = worst_acos.max((acos_near(z) - z.acos()).abs());
            let a = std::f64::consts::TAU * i as f64 / 200_000.0 - std::f64::consts::PI;
            let (y, x) = (3.0 * a.sin(), 3.0 * a.cos());
            worst_atan2 = worst_atan2.max((atan2_near(y, x) - y.atan2(x)).abs());
        }
        // Measured: 2.2e-8 and 1.4e-8 rad.
        assert!(
            worst_acos < 6.5e-8 && worst_atan2 < 4e-8,
            "{worst_acos:e} {worst_atan2:e}"
        );
        const { assert!(6.5e-8 < NEAR_ERR_RAD) };
    }

    #[test]
    fn cells_are_those_of_acos_and_atan2() {
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
        };
        let mut edge_cases = 0;
        for deg in [0.01, 0.5, 1.0, 2.83, 7.0, 45.0] {
            let b = DirectionBins::new([1.5, -2.0, 0.25], deg);
            for _ in 0..200_000 {
                let v = [next() * 60.0, next() * 60.0, next() * 60.0];
                assert_eq!(b.key(&v), key_by_formula(&b, &v), "{v:?} at {deg} deg");
            }
            // Directions on the cell edges: the axes, the poles, the branch cut of atan2, and
            // exact multiples of the cell width.
            let c = b.centre;
            let r = b.cell_rad;
            for k in 0..(std::f64::consts::PI / r) as usize + 1 {
                let t = k as f64 * r;
                for phi in [
                    -std::f64::consts::PI,
                    -1.0,
                    0.0,
                    1.0,
                    t,
                    std::f64::consts::PI,
                ] {
                    let v = [
                        c[0] + 10.0 * t.sin() * phi.cos(),
                        c[1] + 10.0 * t.sin() * phi.sin(),
                        c[2] + 10.0 * t.cos(),
                    ];
                    assert_eq!(b.key(&v), key_by_formula(&b, &v), "{v:?} at {deg} deg");
                    edge_cases += 1;
                }
            }
            let axes = [
                [0.0, 0.0, 1.0],
                [0.0, 0.0, -1.0],
                [-1.0, 0.0, 0.0],
                [-1.0, -0.0, 0.0],
            ];
            for v in axes {
                let v = [c[0] + v[0], c[1] + v[1], c[2] + v[2]];
                assert_eq!(b.key(&v), key_by_formula(&b, &v), "{v:?} at {deg} deg");
            }
            assert_eq!(b.key(&c), None);
        }
        assert!(edge_cases > 1000);
        // The kept points: the first of each cell, in the order of the cells.
        let mut b = DirectionBins::new([1.5, -2.0, 0.25], 7.0);
        let mut by_cell = std::collections::BTreeMap::new();
        for i in 0..50_000 {
            // A slow spiral, so that consecutive vectors often share a cell.
            let t = i as f64 * 0.003;
            let v = [
                1.5 + 40.0 * t.cos() * (0.1 * t).sin(),
                -2.0 + 40.0 * t.sin() * (0.1 * t).sin(),
                0.25 + 40.0 * (0.1 * t).cos() + next(),
            ];
            let kept = b.add(&v);
            let k = key_by_formula(&b, &v).unwrap();
            assert_eq!(kept, !by_cell.contains_key(&k), "{i}");
            by_cell.entry(k).or_insert(v);
        }
        assert!(
            by_cell.len() > 300 && by_cell.len() < MAX_BINNED,
            "{}",
            by_cell.len()
        );
        assert_eq!(b.points(), by_cell.into_values().collect::<Vec<_>>());
        let b = DirectionBins::new([0.0; 3], 1.0);
        for v in [[-0.0, 0.0, 1.0], [-0.0, -0.0, -2.0], [0.0, -0.0, 3.0]] {
            assert_eq!(b.key(&v), key_by_formula(&b, &v), "{v:?}");
        }
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
