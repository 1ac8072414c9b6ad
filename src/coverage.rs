//! Sphere coverage: which of 100 equal-area regions of the unit sphere hold at least one measured
//! direction (MotionCal's layout of latitude bands: 1 + 15 + 34 + 34 + 15 + 1 regions), and the
//! seed-002 (theta, phi) projection. Directions are taken about the current hard-iron centre.

use crate::types::Vec3;
use serde::{Deserialize, Serialize};

/// Number of regions.
pub const REGIONS: usize = 100;

/// Latitude bands north to south as (lowest z = sin(latitude), regions in the band). Equal areas
/// on a sphere are equal spans of z, so with 100 regions the edges are z = 0.98, 0.68, 0, -0.68,
/// -0.98 (latitudes 78.52, 42.84, 0, -42.84, -78.52 deg).
const BANDS: [(f64, usize); 6] = [
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

/// (theta, phi) of seed 002 in degrees: theta polar angle from +z (0..180), phi azimuth (-180..180).
pub fn theta_phi(v: &Vec3) -> (f64, f64) {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-300);
    (
        (v[2] / n).clamp(-1.0, 1.0).acos().to_degrees(),
        v[1].atan2(v[0]).to_degrees(),
    )
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
pub const MAX_BINNED: usize = 4000;

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
    pub fn cell_deg(&self) -> f64 {
        self.cell_rad.to_degrees()
    }

    /// Re-bin the kept vectors about a new centre (after a fit moved the hard-iron estimate).
    pub fn recentre(&mut self, centre: Vec3) {
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

#[cfg(test)]
mod tests {
    use super::*;

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
