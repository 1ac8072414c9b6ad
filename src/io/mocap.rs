//! Optical motion capture: the CSV export of OptiTrack Motive (format versions 1.2x), one rigid
//! body's poses over time.
//!
//! # The format
//! A Motive export starts with a metadata row (`Format Version,1.23,Take Name,...,Export Frame
//! Rate,180.000000,...,Rotation Type,Quaternion,Length Units,Millimeters,...`), a blank row, then
//! rows labelled in their second cell `Type` (`Rigid Body`, `Rigid Body Marker`, `Marker`, ...),
//! `Name` and `ID`, a row of column kinds (`Rotation`, `Position`, `Mean Marker Error`, ...) and the
//! axis row `Frame,Time (Seconds),X,Y,Z,W,...`; then one row per exported frame. A rigid body has
//! four `Rotation` columns (the quaternion X, Y, Z, W of the body -> world rotation) and three
//! `Position` columns (in the file's length unit). Motive's default world is Y-up. Cells are empty
//! where the body was not tracked.
//!
//! # What is skipped (and counted)
//! * occluded rows: a cell of the body is empty;
//! * untracked rows: the identity rotation exactly at the origin (a body defined in the take but
//!   never solved is exported that way);
//! * held rows: the rotation repeats the previous kept row's to the last printed digit. Motive holds
//!   a body's last solution through a short loss of tracking (in `mocap_2023-04-17_0150.csv` of the
//!   shared data: 0.94 s from 7.93 s, then a jump of 5 deg); a measured rotation of a real body does
//!   not repeat to six decimals (the other two takes of that set have no repeated row at all);
//! * malformed rows: numbers that do not parse, a quaternion whose norm is not 1 within 1 %, a time
//!   that does not increase.
//!
//! # Time
//! The `Time (Seconds)` column of these exports is cut to the millisecond (a 180 Hz take steps
//! 5, 6, 5, 6 ms), which would put 1 ms of jitter into every rate taken from it. When the metadata
//! gives the export frame rate and every row's time agrees with `frame / rate` within 1.5 ms, the
//! sample time is `frame / rate`; otherwise the column as printed.

use crate::error::Error;
use nalgebra::{Quaternion, UnitQuaternion};
use std::path::{Path, PathBuf};

/// One tracked frame of a rigid body.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MocapSample {
    /// Time since the start of the take, s.
    pub t_s: f64,
    /// Rotation of the rigid body's frame into the capture world (Motive: Y-up).
    pub q: UnitQuaternion<f64>,
    /// Position of the rigid body in the capture world, m.
    pub position_m: [f64; 3],
}

/// One rigid body read from a Motive export, with what was skipped.
#[derive(Debug, Clone)]
pub struct MocapTake {
    /// The file read.
    pub path: PathBuf,
    /// The rigid body whose poses these are.
    pub rigid_body: String,
    /// Every rigid body the file has, in column order.
    pub rigid_bodies: Vec<String>,
    /// The tracked frames, time increasing.
    pub samples: Vec<MocapSample>,
    /// Data rows in the file.
    pub rows: usize,
    /// Rows with an empty cell for this body (occluded).
    pub occluded: usize,
    /// Rows with the identity rotation exactly at the origin (body not solved).
    pub untracked: usize,
    /// Rows repeating the previous kept rotation exactly (Motive held its last solution).
    pub held: usize,
    /// Rows that did not parse, had no unit quaternion or did not advance in time.
    pub malformed: usize,
    /// The export frame rate from the metadata, Hz.
    pub export_rate_hz: Option<f64>,
    /// True when sample times are `frame / export_rate_hz` rather than the printed time column.
    pub time_from_frames: bool,
    /// The take's name in the metadata.
    pub take_name: Option<String>,
}

impl MocapTake {
    /// The take's poses as the alignment takes them (time, rotation).
    pub fn poses(&self) -> Vec<crate::attitude::align::Pose> {
        self.samples
            .iter()
            .map(|s| crate::attitude::align::Pose { t_s: s.t_s, q: s.q })
            .collect()
    }

    /// One line: the file, the body, its frames and what was skipped.
    pub fn summary(&self) -> String {
        let span = match (self.samples.first(), self.samples.last()) {
            (Some(a), Some(b)) => b.t_s - a.t_s,
            _ => 0.0,
        };
        format!(
            "capture {}: rigid body `{}`, {} of {} rows over {:.1} s ({} occluded, {} held, {} untracked, {} malformed)\n",
            self.path.display(),
            self.rigid_body,
            self.samples.len(),
            self.rows,
            span,
            self.occluded,
            self.held,
            self.untracked,
            self.malformed
        )
    }
}

/// Largest disagreement, s, between the printed time and `frame / rate` for the frame count to be
/// taken as the clock (the column is cut to 1 ms).
const TIME_COLUMN_TOLERANCE_S: f64 = 1.5e-3;
/// How far from 1 a quaternion's norm may be (the export prints six decimals).
const QUATERNION_NORM_TOLERANCE: f64 = 0.01;

/// Read one rigid body of a Motive CSV export: the one named `rigid_body`, or the first that is
/// tracked in at least one row. Errors name the file and what is wrong (not a Motive export, no such
/// rigid body, rotations not quaternions, a body never tracked).
pub fn read_motive(path: &Path, rigid_body: Option<&str>) -> Result<MocapTake, Error> {
    let bytes = std::fs::read(path).map_err(|source| Error::Read {
        path: path.to_path_buf(),
        source,
    })?;
    parse_motive(&bytes, path, rigid_body)
}

/// Column positions of one rigid body.
#[derive(Debug, Clone)]
struct BodyColumns {
    name: String,
    /// Quaternion X, Y, Z, W.
    rot: [usize; 4],
    /// Position X, Y, Z.
    pos: [usize; 3],
}

/// As [`read_motive`], from the file's bytes; `path` only names it in errors. In steps: the
/// header block ([`header_block`]), the metadata ([`Meta::of`]), the rigid bodies' columns
/// ([`rigid_body_columns`]), the data rows ([`data_rows`]), then the body asked for or the first
/// tracked one ([`first_tracked`]).
pub(crate) fn parse_motive(
    bytes: &[u8],
    path: &Path,
    rigid_body: Option<&str>,
) -> Result<MocapTake, Error> {
    let mut reader = csv::ReaderBuilder::new()
        .has_headers(false)
        .flexible(true)
        .from_reader(bytes);
    let mut records = reader.records();
    let (header, axis_row) = header_block(&mut records, path)?;
    let meta = Meta::of(&header, path)?;
    let bodies = rigid_body_columns(&header, &axis_row, path)?;
    // Every row parsed once; the body chosen afterwards (the first tracked one by default).
    let rows = data_rows(records);
    first_tracked(&bodies, &rows, meta, rigid_body, path)
}

/// A format error naming the file.
fn bad(path: &Path, message: String) -> Error {
    Error::Format {
        path: path.to_path_buf(),
        message,
    }
}

/// The file is not a Motive export: `what` is missing, and what one looks like.
fn not_motive(path: &Path, what: &str) -> Error {
    bad(
        path,
        format!(
            "not an OptiTrack Motive CSV export ({what}); expected a first row starting \
             `Format Version,...`, rows labelled Type, Name and ID, and a row `Frame,Time (Seconds),...`"
        ),
    )
}

/// The header block's rows (at most 16) and the axis row `Frame,Time (Seconds),...` that ends it.
fn header_block(
    records: &mut csv::StringRecordsIter<'_, &[u8]>,
    path: &Path,
) -> Result<(Vec<csv::StringRecord>, csv::StringRecord), Error> {
    let mut header: Vec<csv::StringRecord> = Vec::new();
    loop {
        match records.next() {
            None => return Err(not_motive(path, "no `Frame,Time` row")),
            Some(Err(e)) => return Err(not_motive(path, &format!("unreadable header: {e}"))),
            Some(Ok(r)) => {
                let first = r.get(0).unwrap_or("").trim();
                let second = r.get(1).unwrap_or("").trim();
                if first.eq_ignore_ascii_case("frame")
                    && second.to_ascii_lowercase().starts_with("time")
                {
                    return Ok((header, r));
                }
                if header.len() >= 16 {
                    return Err(not_motive(path, "no `Frame,Time` row in the first 16 rows"));
                }
                header.push(r);
            }
        }
    }
}

/// What the metadata row (`Format Version,...`) gives.
struct Meta {
    /// Metres per length unit of the positions.
    unit_m: f64,
    /// The export frame rate, Hz.
    export_rate_hz: Option<f64>,
    take_name: Option<String>,
}

impl Meta {
    /// The metadata of the first header row; an error when it is not one, when the rotations are
    /// not quaternions or the length unit is unknown.
    fn of(header: &[csv::StringRecord], path: &Path) -> Result<Meta, Error> {
        let meta = header
            .first()
            .filter(|r| r.get(0).is_some_and(|c| c.trim() == "Format Version"))
            .ok_or_else(|| not_motive(path, "first row is not `Format Version,...`"))?;
        let meta_value = |key: &str| -> Option<String> {
            let cells: Vec<&str> = meta.iter().map(str::trim).collect();
            cells
                .iter()
                .position(|c| c.eq_ignore_ascii_case(key))
                .and_then(|i| cells.get(i + 1))
                .map(|s| s.to_string())
        };
        if let Some(rt) = meta_value("Rotation Type") {
            if !rt.eq_ignore_ascii_case("quaternion") {
                return Err(bad(
                    path,
                    format!(
                        "rotations are exported as `{rt}`: export them as Quaternion (Motive's export dialog)"
                    ),
                ));
            }
        }
        // Motive's default length unit is the millimetre.
        let unit_m = match meta_value("Length Units")
            .as_deref()
            .map(str::to_ascii_lowercase)
        {
            None => 1e-3,
            Some(u) if u.starts_with("millimet") => 1e-3,
            Some(u) if u.starts_with("centimet") => 1e-2,
            Some(u) if u.starts_with("met") => 1.0,
            Some(u) => return Err(bad(path, format!("unknown length unit `{u}`"))),
        };
        let export_rate_hz = meta_value("Export Frame Rate")
            .and_then(|s| s.parse::<f64>().ok())
            .filter(|r| r.is_finite() && *r > 0.0);
        Ok(Meta {
            unit_m,
            export_rate_hz,
            take_name: meta_value("Take Name"),
        })
    }
}

/// The rigid bodies' columns from the rows labelled Type, Name and ID and the column-kind row
/// (the last of the header block); an error when a row is missing or no body has all seven.
fn rigid_body_columns(
    header: &[csv::StringRecord],
    axis_row: &csv::StringRecord,
    path: &Path,
) -> Result<Vec<BodyColumns>, Error> {
    let labelled = |label: &str| {
        header.iter().find(|r| {
            r.get(1)
                .is_some_and(|c| c.trim().eq_ignore_ascii_case(label))
        })
    };
    let types = labelled("Type").ok_or_else(|| not_motive(path, "no `Type` row"))?;
    let names = labelled("Name").ok_or_else(|| not_motive(path, "no `Name` row"))?;
    let ids = labelled("ID");
    let kinds = header
        .last()
        .ok_or_else(|| not_motive(path, "no column-kind row"))?;
    let cell = |r: &csv::StringRecord, i: usize| r.get(i).unwrap_or("").trim().to_string();
    let bodies = body_columns(axis_row, types, names, ids, kinds, &cell);
    if bodies.is_empty() {
        return Err(bad(
            path,
            "no rigid body with Rotation X, Y, Z, W and Position X, Y, Z columns".into(),
        ));
    }
    Ok(bodies)
}

/// The data rows, blank ones left out; a broken line is kept as a row that does not parse (a
/// malformed row when read).
fn data_rows(records: csv::StringRecordsIter<'_, &[u8]>) -> Vec<csv::StringRecord> {
    let mut rows: Vec<csv::StringRecord> = Vec::new();
    for r in records {
        match r {
            Ok(r) if r.iter().all(|c| c.trim().is_empty()) => {}
            Ok(r) => rows.push(r),
            Err(_) => rows.push(csv::StringRecord::from(vec!["?"])),
        }
    }
    rows
}

/// The take of the body named `rigid_body`, or of the first body tracked in at least one row;
/// an error naming the bodies when there is no such body or it is never tracked.
fn first_tracked(
    bodies: &[BodyColumns],
    rows: &[csv::StringRecord],
    meta: Meta,
    rigid_body: Option<&str>,
    path: &Path,
) -> Result<MocapTake, Error> {
    let rigid_bodies: Vec<String> = bodies.iter().map(|b| b.name.clone()).collect();
    let candidates: Vec<&BodyColumns> = match rigid_body {
        Some(want) => {
            let b = bodies.iter().find(|b| b.name == want).ok_or_else(|| {
                bad(
                    path,
                    format!(
                        "no rigid body named `{want}`; the file has: {}",
                        rigid_bodies.join(", ")
                    ),
                )
            })?;
            vec![b]
        }
        None => bodies.iter().collect(),
    };
    let times = row_times(rows, meta.export_rate_hz);
    for b in &candidates {
        let take = read_body(b, rows, &times, meta.unit_m);
        if !take.samples.is_empty() {
            return Ok(MocapTake {
                path: path.to_path_buf(),
                rigid_body: b.name.clone(),
                rigid_bodies,
                rows: rows.len(),
                export_rate_hz: meta.export_rate_hz,
                time_from_frames: times.from_frames,
                take_name: meta.take_name,
                ..take
            });
        }
    }
    Err(bad(
        path,
        match rigid_body {
            Some(want) => format!(
                "rigid body `{want}` is never tracked in its {} rows",
                rows.len()
            ),
            None => format!(
                "no rigid body is tracked in any of the {} rows (bodies: {})",
                rows.len(),
                rigid_bodies.join(", ")
            ),
        },
    ))
}

/// The rigid bodies whose seven columns are all present, in column order.
fn body_columns(
    axis: &csv::StringRecord,
    types: &csv::StringRecord,
    names: &csv::StringRecord,
    ids: Option<&csv::StringRecord>,
    kinds: &csv::StringRecord,
    cell: &dyn Fn(&csv::StringRecord, usize) -> String,
) -> Vec<BodyColumns> {
    // (name, id) -> [rot x, y, z, w, pos x, y, z]
    let mut found: Vec<(String, String, [Option<usize>; 7])> = Vec::new();
    for i in 2..axis.len() {
        if !cell(types, i).eq_ignore_ascii_case("rigid body") {
            continue;
        }
        let name = cell(names, i);
        let id = ids.map(|r| cell(r, i)).unwrap_or_default();
        let slot = match (
            cell(kinds, i).to_ascii_lowercase().as_str(),
            cell(axis, i).as_str(),
        ) {
            ("rotation", "X") => 0,
            ("rotation", "Y") => 1,
            ("rotation", "Z") => 2,
            ("rotation", "W") => 3,
            ("position", "X") => 4,
            ("position", "Y") => 5,
            ("position", "Z") => 6,
            _ => continue,
        };
        let k = match found.iter().position(|(n, d, _)| *n == name && *d == id) {
            Some(k) => k,
            None => {
                found.push((name.clone(), id.clone(), [None; 7]));
                found.len() - 1
            }
        };
        found[k].2[slot].get_or_insert(i);
    }
    found
        .into_iter()
        .filter_map(|(name, _, c)| {
            Some(BodyColumns {
                name,
                rot: [c[0]?, c[1]?, c[2]?, c[3]?],
                pos: [c[4]?, c[5]?, c[6]?],
            })
        })
        .collect()
}

/// Each data row's time (None: unreadable), and whether it came from the frame count.
struct RowTimes {
    t_s: Vec<Option<f64>>,
    from_frames: bool,
}

fn row_times(rows: &[csv::StringRecord], export_rate_hz: Option<f64>) -> RowTimes {
    let num = |r: &csv::StringRecord, i: usize| {
        r.get(i)
            .and_then(|c| c.trim().parse::<f64>().ok())
            .filter(|x| x.is_finite())
    };
    let printed: Vec<Option<f64>> = rows.iter().map(|r| num(r, 1)).collect();
    if let Some(rate) = export_rate_hz {
        let from_frames: Vec<Option<f64>> =
            rows.iter().map(|r| num(r, 0).map(|f| f / rate)).collect();
        let agree = printed.iter().zip(&from_frames).all(|(p, f)| match (p, f) {
            (Some(p), Some(f)) => (p - f).abs() <= TIME_COLUMN_TOLERANCE_S,
            _ => true,
        });
        let some = from_frames.iter().any(Option::is_some);
        if agree && some {
            return RowTimes {
                t_s: from_frames,
                from_frames: true,
            };
        }
    }
    RowTimes {
        t_s: printed,
        from_frames: false,
    }
}

/// The kept samples of one body and the counts of what was skipped.
fn read_body(
    b: &BodyColumns,
    rows: &[csv::StringRecord],
    times: &RowTimes,
    unit_m: f64,
) -> MocapTake {
    let mut take = MocapTake {
        path: PathBuf::new(),
        rigid_body: b.name.clone(),
        rigid_bodies: Vec::new(),
        samples: Vec::new(),
        rows: rows.len(),
        occluded: 0,
        untracked: 0,
        held: 0,
        malformed: 0,
        export_rate_hz: None,
        time_from_frames: false,
        take_name: None,
    };
    // The previous kept row's rotation as printed (held rows repeat it exactly).
    let mut last_rot: Option<[f64; 4]> = None;
    for (r, t) in rows.iter().zip(&times.t_s) {
        let cells: Vec<&str> = b
            .rot
            .iter()
            .chain(&b.pos)
            .map(|&i| r.get(i).unwrap_or("").trim())
            .collect();
        if cells.iter().any(|c| c.is_empty()) {
            take.occluded += 1;
            continue;
        }
        let v: Option<Vec<f64>> = cells
            .iter()
            .map(|c| c.parse::<f64>().ok().filter(|x| x.is_finite()))
            .collect();
        let (Some(v), Some(t)) = (v, *t) else {
            take.malformed += 1;
            continue;
        };
        let rot = [v[0], v[1], v[2], v[3]];
        let pos = [v[4] * unit_m, v[5] * unit_m, v[6] * unit_m];
        if rot == [0.0, 0.0, 0.0, 1.0] && pos == [0.0; 3] {
            take.untracked += 1;
            continue;
        }
        let q = Quaternion::new(rot[3], rot[0], rot[1], rot[2]);
        if (q.norm() - 1.0).abs() > QUATERNION_NORM_TOLERANCE {
            take.malformed += 1;
            continue;
        }
        if take.samples.last().is_some_and(|s| t <= s.t_s) {
            take.malformed += 1;
            continue;
        }
        if last_rot == Some(rot) {
            take.held += 1;
            continue;
        }
        last_rot = Some(rot);
        take.samples.push(MocapSample {
            t_s: t,
            q: UnitQuaternion::from_quaternion(q),
            position_m: pos,
        });
    }
    take
}

#[cfg(test)]
mod tests {
    use super::*;

    const HEAD: &str = "Format Version,1.23,Take Name,Take 1,Capture Frame Rate,200.000000,\
Export Frame Rate,180.000000,Rotation Type,Quaternion,Length Units,Millimeters,Coordinate Space,Global\n\
\n\
,Type,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body\n\
,Name,Frame,Frame,Frame,Frame,Frame,Frame,Frame,Drone,Drone,Drone,Drone,Drone,Drone,Drone\n\
,ID,A,A,A,A,A,A,A,B,B,B,B,B,B,B\n\
,,Rotation,Rotation,Rotation,Rotation,Position,Position,Position,Rotation,Rotation,Rotation,Rotation,Position,Position,Position\n\
Frame,Time (Seconds),X,Y,Z,W,X,Y,Z,X,Y,Z,W,X,Y,Z\n";

    const IDLE: &str = "0.000000,0.000000,0.000000,1.000000,0.000000,0.000000,0.000000";

    fn take(rows: &[&str], body: Option<&str>) -> Result<MocapTake, Error> {
        let text = format!("{HEAD}{}\n", rows.join("\n"));
        parse_motive(text.as_bytes(), Path::new("take.csv"), body)
    }

    #[test]
    fn first_tracked_body_with_skips_counted() {
        let rows = [
            format!("0,0.000000,{IDLE},0.000000,0.000000,0.000000,1.000000,1000.0,2000.0,3000.0"),
            // occluded
            format!("1,0.005000,{IDLE},,,,,,,"),
            format!("2,0.011000,{IDLE},0.100000,0.000000,0.000000,0.994987,1001.0,2000.0,3000.0"),
            // held: same rotation as the row before, position jitter only
            format!("3,0.016000,{IDLE},0.100000,0.000000,0.000000,0.994987,1001.1,2000.0,3000.0"),
            // not a unit quaternion
            format!("4,0.022000,{IDLE},0.500000,0.000000,0.000000,0.500000,1.0,2.0,3.0"),
            format!("5,0.027000,{IDLE},0.200000,0.000000,0.000000,0.979796,1002.0,2000.0,3000.0"),
            format!("6,0.033000,{IDLE},abc,0.000000,0.000000,0.979796,1002.0,2000.0,3000.0"),
        ];
        let rows: Vec<&str> = rows.iter().map(String::as_str).collect();
        let t = take(&rows, None).unwrap();
        assert_eq!(t.rigid_body, "Drone");
        assert_eq!(
            t.rigid_bodies,
            vec!["Frame".to_string(), "Drone".to_string()]
        );
        assert_eq!(t.rows, 7);
        assert_eq!(t.samples.len(), 3);
        assert_eq!((t.occluded, t.held, t.malformed, t.untracked), (1, 1, 2, 0));
        assert!(t.time_from_frames);
        assert!((t.samples[2].t_s - 5.0 / 180.0).abs() < 1e-12);
        assert!((t.samples[0].position_m[2] - 3.0).abs() < 1e-12);
        // X, Y, Z, W in the file: 0.1 along x.
        let q = t.samples[1].q;
        assert!((q.i - 0.1).abs() < 1e-6 && (q.w - 0.994987).abs() < 1e-6);
        // The body never solved is there, but untracked in every row.
        let f = take(&rows, Some("Frame"));
        assert!(f.is_err_and(|e| e.to_string().contains("never tracked")));
    }

    #[test]
    fn errors_name_the_file_and_the_problem() {
        let e = parse_motive(b"t,ax,ay\n0,1,2\n", Path::new("imu.csv"), None).unwrap_err();
        let s = e.to_string();
        assert!(
            s.contains("imu.csv") && s.contains("not an OptiTrack Motive"),
            "{s}"
        );
        let e = take(&[], Some("Plane")).unwrap_err().to_string();
        assert!(
            e.contains("no rigid body named `Plane`") && e.contains("Frame, Drone"),
            "{e}"
        );
        let euler = HEAD.replace("Rotation Type,Quaternion", "Rotation Type,XYZ");
        let e = parse_motive(euler.as_bytes(), Path::new("e.csv"), None).unwrap_err();
        assert!(e.to_string().contains("`XYZ`"), "{e}");
        let e = parse_motive(b"", Path::new("empty.csv"), None).unwrap_err();
        assert!(e.to_string().contains("empty.csv"));
    }

    #[test]
    fn printed_time_kept_when_it_disagrees_with_the_frame_count() {
        let rows = [
            format!("0,0.000000,{IDLE},0.000000,0.000000,0.000000,1.000000,1.0,2.0,3.0"),
            format!("1,0.100000,{IDLE},0.100000,0.000000,0.000000,0.994987,1.0,2.0,3.0"),
        ];
        let rows: Vec<&str> = rows.iter().map(String::as_str).collect();
        let t = take(&rows, Some("Drone")).unwrap();
        assert!(!t.time_from_frames);
        assert!((t.samples[1].t_s - 0.1).abs() < 1e-12);
    }
}
