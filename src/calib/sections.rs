//! ArduPilot's 80 sections of the sphere, the cells of its compass calibrator's completion mask
//! (MAG_CAL_PROGRESS `completion_mask`): each of the 20 faces of an icosahedron is cut at its edge
//! midpoints into four triangles, and the 80 flat triangles are projected from the centre onto the
//! unit sphere. Faces, vertices and sub-triangles are numbered as ArduPilot's `AP_GeodesicGrid`
//! numbers them, so a section here is the same patch of sky as on the flight controller and in a
//! ground station's drawing of the mask.
//!
//! [`section80`] names the section of a direction, [`section80_triangle`] gives its corners (unit
//! vectors), [`set_section`], [`mask_has`] and [`completion_mask`] read and write the 80-bit mask
//! (section `s` is bit `s % 8` of byte `s / 8`). Directions are dimensionless: any length but zero.
//! Pure.

/// Golden ratio (1 + sqrt 5) / 2.
const GOLDEN: f64 = 1.618_033_988_749_895;

/// The 12 icosahedron vertices (0, +-1, +-g) and their cyclic permutations, named so that the faces
/// below read in ArduPilot's `AP_GeodesicGrid` order.
const ICO_V: [[f64; 3]; 12] = [
    [-GOLDEN, 1.0, 0.0],  // 0
    [-1.0, 0.0, -GOLDEN], // 1
    [-GOLDEN, -1.0, 0.0], // 2
    [0.0, -GOLDEN, -1.0], // 3
    [0.0, -GOLDEN, 1.0],  // 4
    [1.0, 0.0, -GOLDEN],  // 5
    [GOLDEN, -1.0, 0.0],  // 6
    [GOLDEN, 1.0, 0.0],   // 7
    [0.0, GOLDEN, -1.0],  // 8
    [-1.0, 0.0, GOLDEN],  // 9
    [1.0, 0.0, GOLDEN],   // 10
    [0.0, GOLDEN, 1.0],   // 11
];

/// The 20 faces (a, b, c) in the order and vertex order of ArduPilot's geodesic grid, so that our
/// section numbers (and so the MAG_CAL_PROGRESS completion mask) mean the same sections as the
/// firmware's and a ground station's drawing of them.
const ICO_F: [[usize; 3]; 20] = [
    [0, 1, 2],
    [1, 2, 3],
    [2, 3, 4],
    [1, 3, 5],
    [3, 4, 6],
    [3, 5, 6],
    [6, 5, 7],
    [5, 7, 8],
    [5, 8, 1],
    [8, 0, 1],
    [0, 9, 2],
    [9, 2, 4],
    [9, 4, 10],
    [4, 10, 6],
    [6, 10, 7],
    [10, 7, 11],
    [7, 11, 8],
    [10, 11, 9],
    [11, 8, 0],
    [11, 0, 9],
];

/// Number of sphere sections in the completion mask.
pub(crate) const SECTIONS: usize = 80;

/// Bytes of a completion mask: one bit per section.
pub(crate) const MASK_BYTES: usize = SECTIONS / 8;

fn dot(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: &[f64; 3], b: &[f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// Triple product a . (b x c).
fn det3(a: &[f64; 3], b: &[f64; 3], c: &[f64; 3]) -> f64 {
    dot(a, &cross(b, c))
}

fn unit(v: [f64; 3]) -> [f64; 3] {
    let n = dot(&v, &v).sqrt();
    [v[0] / n, v[1] / n, v[2] / n]
}

fn mid(a: &[f64; 3], b: &[f64; 3]) -> [f64; 3] {
    [
        0.5 * (a[0] + b[0]),
        0.5 * (a[1] + b[1]),
        0.5 * (a[2] + b[2]),
    ]
}

/// Per face (a, b, c), the rows `(b x c, c x a, a x b) / det(a, b, c)`: their dot products with a
/// direction are its barycentric coordinates in the face's plane (Cramer's rule with the face's
/// determinant taken once). Built on first use.
fn face_rows() -> &'static [[[f64; 3]; 3]; 20] {
    static ROWS: std::sync::OnceLock<[[[f64; 3]; 3]; 20]> = std::sync::OnceLock::new();
    ROWS.get_or_init(|| {
        ICO_F.map(|f| {
            let (a, b, c) = (&ICO_V[f[0]], &ICO_V[f[1]], &ICO_V[f[2]]);
            let d = det3(a, b, c);
            [cross(b, c), cross(c, a), cross(a, b)].map(|r| r.map(|x| x / d))
        })
    })
}

/// The face whose cone holds `dir`, with the barycentric coordinates (alpha, beta, gamma) of the
/// ray's crossing of its plane, scaled to sum to 1. The face that holds the ray has all three >= 0;
/// the search keeps the face whose smallest coordinate is largest, so a ray that rounding leaves
/// just outside every face on an edge still gets the nearest one, and on an edge the first face
/// found wins.
fn face_of(dir: &[f64; 3]) -> Option<(usize, [f64; 3])> {
    let mut best: Option<(usize, [f64; 3])> = None;
    let mut best_min = f64::NEG_INFINITY;
    for (i, rows) in face_rows().iter().enumerate() {
        let w = rows.map(|r| dot(dir, &r));
        let s = w[0] + w[1] + w[2];
        if !(s > 0.0) {
            continue; // the ray meets this face's plane behind the centre
        }
        let n = [w[0] / s, w[1] / s, w[2] / s];
        let m = n[0].min(n[1]).min(n[2]);
        if m > best_min {
            best_min = m;
            best = Some((i, n));
            if m >= 0.0 {
                break;
            }
        }
    }
    best
}

/// The sub-triangle of a face holding barycentric coordinates `n`: 1, 2 or 3 for the corner
/// triangles at a, b, c (that coordinate at least 1/2), 0 for the middle one.
fn sub_triangle(n: &[f64; 3]) -> usize {
    if n[0] >= 0.5 {
        1
    } else if n[1] >= 0.5 {
        2
    } else if n[2] >= 0.5 {
        3
    } else {
        0
    }
}

/// Section (0..80) of a direction (any length; `None` for zero or non-finite): `4 i + j` for
/// icosahedron face `i` and its sub-triangle `j`. A face (a, b, c) with edge midpoints
/// m_a = (a+b)/2, m_b = (b+c)/2, m_c = (c+a)/2 has the sub-triangles W_0 = (m_a, m_b, m_c) in the
/// middle, W_1 = (a, m_a, m_c), W_2 = (m_a, b, m_b) and W_3 = (m_c, m_b, c).
pub(crate) fn section80(dir: &[f64; 3]) -> Option<usize> {
    if !dir.iter().all(|x| x.is_finite()) || !(dot(dir, dir) > 0.0) {
        return None;
    }
    let (face, n) = face_of(dir)?;
    Some(4 * face + sub_triangle(&n))
}

/// The corners (unit vectors) of a section, in the order [`section80`] gives them, for drawing the
/// completion mask. `None` for a section of 80 or more.
pub fn section80_triangle(section: usize) -> Option<[[f64; 3]; 3]> {
    if section >= SECTIONS {
        return None;
    }
    let f = ICO_F[section / 4];
    let (a, b, c) = (ICO_V[f[0]], ICO_V[f[1]], ICO_V[f[2]]);
    let (ma, mb, mc) = (mid(&a, &b), mid(&b, &c), mid(&c, &a));
    let t = match section % 4 {
        0 => [ma, mb, mc],
        1 => [a, ma, mc],
        2 => [ma, b, mb],
        _ => [mc, mb, c],
    };
    Some(t.map(unit))
}

/// Set section `s` in a completion mask (bit `s % 8` of byte `s / 8`); sections of 80 or more are
/// ignored.
pub(crate) fn set_section(mask: &mut [u8; MASK_BYTES], s: usize) {
    if s < SECTIONS {
        mask[s / 8] |= 1 << (s % 8);
    }
}

/// Whether section `s` is set in a completion mask.
pub fn mask_has(mask: &[u8; MASK_BYTES], s: usize) -> bool {
    s < SECTIONS && mask[s / 8] & (1 << (s % 8)) != 0
}

/// The completion mask of a set of directions, and how many sections hold at least one. ArduPilot
/// takes the directions about the current hard-iron centre (and preferably corrected); zero or
/// non-finite ones are ignored.
pub fn completion_mask(dirs: impl IntoIterator<Item = [f64; 3]>) -> ([u8; MASK_BYTES], usize) {
    let mut mask = [0u8; MASK_BYTES];
    for d in dirs {
        if let Some(s) = section80(&d) {
            set_section(&mut mask, s);
        }
    }
    let filled = mask.iter().map(|b| b.count_ones() as usize).sum();
    (mask, filled)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    /// `n` directions spread evenly over the unit sphere (Fibonacci spiral).
    fn fib_sphere(n: usize) -> impl Iterator<Item = [f64; 3]> {
        let golden = PI * (3.0 - 5f64.sqrt());
        (0..n).map(move |i| {
            let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let p = golden * i as f64;
            [r * p.cos(), r * p.sin(), z]
        })
    }

    /// Solid angle of a spherical triangle with unit corners, sr (Van Oosterom and Strackee).
    fn solid_angle(t: &[[f64; 3]; 3]) -> f64 {
        let [a, b, c] = t;
        let num = det3(a, b, c).abs();
        let den = 1.0 + dot(a, b) + dot(b, c) + dot(c, a);
        2.0 * num.atan2(den)
    }

    #[test]
    fn icosahedron_faces_are_well_formed_and_tile_the_sphere() {
        for f in ICO_F.iter() {
            for (i, j) in [(0, 1), (1, 2), (2, 0)] {
                let (a, b) = (ICO_V[f[i]], ICO_V[f[j]]);
                let d = [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
                assert!((dot(&d, &d) - 4.0).abs() < 1e-12, "face {f:?} edge");
            }
        }
        let total: f64 = (0..SECTIONS)
            .map(|s| solid_angle(&section80_triangle(s).unwrap()))
            .sum();
        assert!((total - 4.0 * PI).abs() < 1e-9, "{total}");
        assert!(section80_triangle(80).is_none());
    }

    #[test]
    fn every_section_is_hit_and_numbered_like_its_triangle() {
        for s in 0..SECTIONS {
            let t = section80_triangle(s).unwrap();
            let c = [0, 1, 2].map(|k| t[0][k] + t[1][k] + t[2][k]);
            assert_eq!(section80(&c), Some(s), "centroid of section {s}");
            assert_eq!(
                section80(&c.map(|x| x * 37.5)),
                Some(s),
                "length does not matter"
            );
        }
        // ArduPilot's layout: the middle of face 0 is section 0, near its first corner section 1.
        let [a, b, c] = [ICO_V[0], ICO_V[1], ICO_V[2]];
        let near_a = [0, 1, 2].map(|k| 0.8 * a[k] + 0.1 * b[k] + 0.1 * c[k]);
        assert_eq!(section80(&near_a), Some(1));
        let near_c = [0, 1, 2].map(|k| 0.1 * a[k] + 0.1 * b[k] + 0.8 * c[k]);
        assert_eq!(section80(&near_c), Some(3));
        assert_eq!(section80(&[0.0; 3]), None);
        assert_eq!(section80(&[f64::NAN, 1.0, 0.0]), None);
        // Vertices and edges still land somewhere.
        for v in ICO_V.iter() {
            assert!(section80(v).is_some());
        }
        for axis in [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]] {
            assert!(section80(&axis).is_some());
        }
    }

    #[test]
    fn sections_have_near_equal_solid_angle() {
        let mean = 4.0 * PI / SECTIONS as f64;
        let areas: Vec<f64> = (0..SECTIONS)
            .map(|s| solid_angle(&section80_triangle(s).unwrap()))
            .collect();
        for (s, a) in areas.iter().enumerate() {
            assert!((a / mean - 1.0).abs() < 0.3, "section {s}: {}", a / mean);
        }
        // Uniform directions fall into sections in proportion to those solid angles.
        let n = 400_000;
        let mut counts = [0usize; SECTIONS];
        for d in fib_sphere(n) {
            counts[section80(&d).unwrap()] += 1;
        }
        for s in 0..SECTIONS {
            let frac = counts[s] as f64 / n as f64;
            let want = areas[s] / (4.0 * PI);
            assert!(
                (frac - want).abs() < 0.05 * want,
                "section {s}: {frac} vs {want}"
            );
        }
    }

    #[test]
    fn completion_mask_sets_one_bit_per_section() {
        let centroid = |s: usize| {
            let t = section80_triangle(s).unwrap();
            [0, 1, 2].map(|k| t[0][k] + t[1][k] + t[2][k])
        };
        let (mask, filled) = completion_mask([0, 2, 9, 79, 9].map(centroid));
        assert_eq!(filled, 4);
        assert_eq!(mask[0], 0b0000_0101);
        assert_eq!(mask[1], 0b0000_0010);
        assert_eq!(mask[9], 0b1000_0000);
        assert!(mask[2..9].iter().all(|b| *b == 0));
        assert!(mask_has(&mask, 79) && !mask_has(&mask, 78) && !mask_has(&mask, 80));
        let (full, n) = completion_mask(fib_sphere(20_000));
        assert_eq!(n, 80);
        assert_eq!(full, [0xFF; 10]);
        assert_eq!(completion_mask([[0.0; 3]]).1, 0);
    }

    #[test]
    fn set_section_marks_one_bit_and_ignores_sections_past_the_mask() {
        let mut mask = [0u8; MASK_BYTES];
        set_section(&mut mask, 13);
        set_section(&mut mask, 13);
        set_section(&mut mask, SECTIONS);
        assert_eq!(mask[1], 0b0010_0000);
        assert_eq!(mask.iter().map(|b| b.count_ones()).sum::<u32>(), 1);
        assert!(mask_has(&mask, 13));
    }
}
