//! Writers of flight-controller logs from samples, for simulated tests: an ArduPilot DataFlash
//! `.bin` and a PX4 `.ulg` whose magnetometer is logged **corrected** by a known onboard
//! calibration, as the flight controllers log it, with that calibration in the parameters. A replay
//! undoes the correction ([`crate::io::flightlog`]) and so sees the raw field again. A sample's
//! reference attitude (`ref_q`) is written as the flight controller's (`ATT`, `vehicle_attitude`).

use crate::calib::ardupilot::Correction;
use crate::error::Error;
use crate::types::{Sample, Vec3};
use nalgebra::{Matrix3, Vector3};

/// The calibration a simulated flight controller applied, in imucald's model:
/// corrected = matrix (raw - offset), uT. ArduPilot and PX4 both store a symmetric matrix.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OnboardMag {
    pub offset_ut: Vec3,
    pub matrix: [[f64; 3]; 3],
}

impl OnboardMag {
    /// A plausible onboard calibration, deliberately not the truth of any scenario.
    pub fn example() -> Self {
        OnboardMag {
            offset_ut: [12.0, -7.5, 20.0],
            matrix: [
                [1.04, 0.02, -0.01],
                [0.02, 0.97, 0.015],
                [-0.01, 0.015, 1.01],
            ],
        }
    }

    fn correct(&self, raw_ut: &Vec3) -> Vec3 {
        let m = crate::calib::model::rows_to_mat(&self.matrix);
        let d = Vector3::new(
            raw_ut[0] - self.offset_ut[0],
            raw_ut[1] - self.offset_ut[1],
            raw_ut[2] - self.offset_ut[2],
        );
        let c: Vector3<f64> = m * d;
        [c[0], c[1], c[2]]
    }

    fn symmetric(&self) -> bool {
        let m = Matrix3::from_fn(|i, j| self.matrix[i][j]);
        (m - m.transpose()).abs().max() < 1e-12
    }
}

/// Roll, pitch, yaw (deg, Euler ZYX, body -> NED) of a sample's reference attitude (sensor -> ENU).
fn body_ned_euler_deg(q_enu: [f64; 4]) -> Option<[f64; 3]> {
    let q = crate::attitude::ned_to_enu(q_enu)?;
    let (w, x, y, z) = (q[0], q[1], q[2], q[3]);
    let roll = (2.0 * (w * x + y * z)).atan2(1.0 - 2.0 * (x * x + y * y));
    let pitch = (2.0 * (w * y - z * x)).clamp(-1.0, 1.0).asin();
    let yaw = (2.0 * (w * z + x * y)).atan2(1.0 - 2.0 * (y * y + z * z));
    Some([roll.to_degrees(), pitch.to_degrees(), yaw.to_degrees()])
}

/// Microseconds of `t_s = 0` in written logs (a flight controller's time since boot).
const T0_US: u64 = 1_000_000;

fn time_us(t_s: f64) -> u64 {
    T0_US + (t_s.max(0.0) * 1e6).round() as u64
}

pub(super) fn fmt_record(id: u8, name: &str, format: &str, cols: &str) -> Vec<u8> {
    let len: usize = 3 + format
        .bytes()
        .map(|c| super::dataflash::Kind::from_char(c).map_or(0, |k| k.size()))
        .sum::<usize>();
    let mut r = vec![0xA3, 0x95, 0x80, id, len as u8];
    for (s, n) in [(name, 4), (format, 16), (cols, 64)] {
        let mut b = s.as_bytes().to_vec();
        b.resize(n, 0);
        r.extend(b);
    }
    r
}

/// What a DataFlash log carries besides the primary's samples.
#[derive(Debug, Clone, Copy, Default)]
pub struct DataflashExtra<'a> {
    /// Further IMU instances (1, 2, ...), each time-ordered: their accelerometer, gyro and
    /// temperature as `IMU` records with the instance field `I`, as ArduPilot 4.x logs them (the
    /// primary's then carry `I` 0). Empty: the `IMU` records have no `I`, as before ArduPilot 4.
    pub further_imus: &'a [Vec<Sample>],
    /// Parameters logged (PARM) besides the compass's and accelerometer's, as float32.
    pub params: &'a [(String, f64)],
}

/// ArduPilot DataFlash: FMT, PARM (COMPASS_OFS/DIA/ODI from `onboard`, INS offsets 0 and scales 1),
/// then per sample `MAG` (mGauss, int16, after ArduPilot's correction `S (raw + OFS)`, with OfsX/Y/Z)
/// and `IMU` (rad/s, m/s^2).
pub(crate) fn dataflash_bytes(samples: &[Sample], onboard: &OnboardMag) -> Result<Vec<u8>, Error> {
    dataflash_bytes_with(samples, onboard, &DataflashExtra::default())
}

/// [`dataflash_bytes`] with further IMU instances and parameters ([`DataflashExtra`]); the
/// further instances' records interleaved with the primary's by time.
pub fn dataflash_bytes_with(
    samples: &[Sample],
    onboard: &OnboardMag,
    extra: &DataflashExtra<'_>,
) -> Result<Vec<u8>, Error> {
    if !onboard.symmetric() {
        return Err(Error::Other(
            "ArduPilot's compass matrix is symmetric (DIA/ODI)".into(),
        ));
    }
    let mut out = fmt_record(0x80, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns");
    out.extend(fmt_record(129, "PARM", "QNf", "TimeUS,Name,Value"));
    let instanced = !extra.further_imus.is_empty();
    out.extend(if instanced {
        fmt_record(
            130,
            "IMU",
            "QBffffffIIfBBHH",
            "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz",
        )
    } else {
        fmt_record(
            130,
            "IMU",
            "QffffffIIfBBHH",
            "TimeUS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz",
        )
    });
    out.extend(fmt_record(
        132,
        "ATT",
        "QccccCCCC",
        "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw",
    ));
    out.extend(fmt_record(
        131,
        "MAG",
        "QhhhhhhhhhBI",
        "TimeUS,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOfsX,MOfsY,MOfsZ,Health,S",
    ));
    // The onboard calibration as ArduPilot's parameters, stored and applied as float32.
    let exact = Correction::from_model(&onboard.offset_ut, &onboard.matrix);
    let ap = Correction {
        ofs_mg: exact.ofs_mg.map(|o| o as f32 as f64),
        s: exact.s.map(|x| x as f32 as f64),
        scale: 1.0,
    };
    let compass = ap
        .params(0)
        .ok_or_else(|| Error::Other("ArduPilot has no compass 0".into()))?;
    let params: Vec<(String, f64)> = compass
        .into_iter()
        .chain(
            [
                ("COMPASS_DEV_ID", 97539.0),
                ("INS_ACCOFFS_X", 0.0),
                ("INS_ACCOFFS_Y", 0.0),
                ("INS_ACCOFFS_Z", 0.0),
                ("INS_ACCSCAL_X", 1.0),
                ("INS_ACCSCAL_Y", 1.0),
                ("INS_ACCSCAL_Z", 1.0),
            ]
            .map(|(n, v)| (n.to_string(), v)),
        )
        .chain(extra.params.iter().cloned())
        .collect();
    for (n, v) in &params {
        out.extend([0xA3, 0x95, 129]);
        out.extend(T0_US.to_le_bytes());
        let mut name = n.as_bytes().to_vec();
        name.resize(16, 0);
        out.extend(name);
        out.extend((*v as f32).to_le_bytes());
    }
    let i16_of = |x: f64| x.round().clamp(i16::MIN as f64, i16::MAX as f64) as i16;
    let mut further = FurtherImus::new(extra.further_imus);
    for s in samples {
        let t = time_us(s.t_s);
        if let Some([r, p, y]) = s.ref_q.and_then(body_ned_euler_deg) {
            out.extend([0xA3, 0x95, 132]);
            out.extend(t.to_le_bytes());
            let c = |x: f64| i16_of(x * 100.0).to_le_bytes();
            let yaw = ((y.rem_euclid(360.0) * 100.0).round() as u16).min(35999);
            out.extend(c(r));
            out.extend(c(r));
            out.extend(c(p));
            out.extend(c(p));
            out.extend(yaw.to_le_bytes());
            out.extend(yaw.to_le_bytes());
            out.extend([0u8; 4]);
        }
        if let Some(raw) = s.mag_ut {
            out.extend([0xA3, 0x95, 131]);
            out.extend(t.to_le_bytes());
            for v in ap.apply(raw) {
                out.extend(i16_of(v).to_le_bytes());
            }
            for v in ap.ofs_mg {
                out.extend(i16_of(v).to_le_bytes());
            }
            out.extend([0u8; 6]);
            out.push(1);
            out.extend((t as u32).to_le_bytes());
        }
        if let (Some(a), Some(g)) = (s.accel_mps2, s.gyro_rad_s) {
            further.flush_until(t, &mut out);
            out.extend(imu_record(t, instanced.then_some(0), a, g, s.temp_c));
        }
    }
    further.flush_until(u64::MAX, &mut out);
    Ok(out)
}

/// An `IMU` record (id 130): gyro rad/s, accelerometer m/s^2, temperature deg C (25 when the
/// sample has none), with the instance field `I` when given.
fn imu_record(t: u64, instance: Option<u8>, a: Vec3, g: Vec3, temp_c: Option<f64>) -> Vec<u8> {
    let mut out = vec![0xA3, 0x95, 130];
    out.extend(t.to_le_bytes());
    out.extend(instance);
    for v in g.iter().chain(&a) {
        out.extend((*v as f32).to_le_bytes());
    }
    out.extend([0u8; 8]);
    out.extend((temp_c.unwrap_or(25.0) as f32).to_le_bytes());
    out.extend([1, 1]);
    out.extend(1000u16.to_le_bytes());
    out.extend(1000u16.to_le_bytes());
    out
}

/// The further IMU instances' samples, written in time order as the primary's go by.
struct FurtherImus<'a> {
    instances: &'a [Vec<Sample>],
    /// The next sample of each instance.
    next: Vec<usize>,
}

impl<'a> FurtherImus<'a> {
    fn new(instances: &'a [Vec<Sample>]) -> Self {
        FurtherImus {
            instances,
            next: vec![0; instances.len()],
        }
    }

    /// Write every further sample up to `t_us` (instance order within a time).
    fn flush_until(&mut self, t_us: u64, out: &mut Vec<u8>) {
        for (k, v) in self.instances.iter().enumerate() {
            let instance = u8::try_from(k + 1).unwrap_or(u8::MAX);
            while let Some(s) = v.get(self.next[k]).filter(|s| time_us(s.t_s) <= t_us) {
                self.next[k] += 1;
                if let (Some(a), Some(g)) = (s.accel_mps2, s.gyro_rad_s) {
                    out.extend(imu_record(time_us(s.t_s), Some(instance), a, g, s.temp_c));
                }
            }
        }
    }
}

fn ulog_msg(out: &mut Vec<u8>, ty: u8, body: &[u8]) {
    out.extend((body.len() as u16).to_le_bytes());
    out.push(ty);
    out.extend_from_slice(body);
}

fn ulog_param(out: &mut Vec<u8>, name: &str, v: f64, int: bool) {
    let key = if int {
        format!("int32_t {name}")
    } else {
        format!("float {name}")
    };
    let mut b = vec![key.len() as u8];
    b.extend(key.as_bytes());
    if int {
        b.extend((v as i32).to_le_bytes());
    } else {
        b.extend((v as f32).to_le_bytes());
    }
    ulog_msg(out, b'P', &b);
}

/// A further compass of a simulated PX4 log ([`ulog_bytes_with`]).
#[derive(Debug, Clone)]
pub struct FurtherCompass {
    /// Its device id (CAL_MAGn_ID, `sensor_mag.device_id`).
    pub device_id: u32,
    /// Its onboard calibration (CAL_MAGn_*).
    pub onboard: OnboardMag,
    /// Its raw readings: time (s) and field (body axes, uT).
    pub readings: Vec<(f64, Vec3)>,
    /// The rate its raw `sensor_mag` topic is logged at, Hz (PX4's default logger: 1 Hz); the
    /// corrected `vehicle_magnetometer` instance carries every reading.
    pub raw_rate_hz: f64,
}

/// PX4 ULog: CAL_MAG0_* from `onboard` (CAL_MAG_PRIME its id, no rotation), `sensor_combined`
/// (gyroscope, accelerometer) and `vehicle_magnetometer` (gauss, after PX4's correction
/// `S (raw - OFF)`).
pub(crate) fn ulog_bytes(samples: &[Sample], onboard: &OnboardMag) -> Result<Vec<u8>, Error> {
    ulog_bytes_with(samples, onboard, &[])
}

/// [`ulog_bytes`] with further compasses as PX4 1.13 and later logs them: compass i's raw
/// `sensor_mag[i]` at its `raw_rate_hz` and its corrected `vehicle_magnetometer[i + 1]` at every
/// reading, CAL_MAG{i + 1}_* its calibration.
pub fn ulog_bytes_with(
    samples: &[Sample],
    onboard: &OnboardMag,
    further: &[FurtherCompass],
) -> Result<Vec<u8>, Error> {
    if !onboard.symmetric() || further.iter().any(|f| !f.onboard.symmetric()) {
        return Err(Error::Other(
            "PX4's compass matrix is symmetric (SCALE/ODIAG)".into(),
        ));
    }
    let mut out = super::ulog::MAGIC.to_vec();
    out.push(1);
    out.extend(0u64.to_le_bytes());
    ulog_msg(&mut out, b'B', &[0u8; 40]);
    ulog_msg(
        &mut out,
        b'F',
        b"sensor_combined:uint64_t timestamp;float[3] gyro_rad;float[3] accelerometer_m_s2;",
    );
    ulog_msg(
        &mut out,
        b'F',
        b"vehicle_magnetometer:uint64_t timestamp;uint32_t device_id;float[3] magnetometer_ga;",
    );
    ulog_msg(
        &mut out,
        b'F',
        b"sensor_mag:uint64_t timestamp;uint32_t device_id;float x;float y;float z;",
    );
    ulog_msg(
        &mut out,
        b'F',
        b"vehicle_attitude:uint64_t timestamp;float[4] q;",
    );
    const ID: f64 = 197_388.0;
    let off = onboard.offset_ut.map(|o| o / 100.0);
    let m = &onboard.matrix;
    for (n, v, int) in [
        ("CAL_MAG0_ID", ID, true),
        ("CAL_MAG0_ROT", 0.0, true),
        ("CAL_MAG_PRIME", ID, true),
        ("SENS_BOARD_ROT", 0.0, true),
        ("CAL_MAG0_XOFF", off[0], false),
        ("CAL_MAG0_YOFF", off[1], false),
        ("CAL_MAG0_ZOFF", off[2], false),
        ("CAL_MAG0_XSCALE", m[0][0], false),
        ("CAL_MAG0_YSCALE", m[1][1], false),
        ("CAL_MAG0_ZSCALE", m[2][2], false),
        ("CAL_MAG0_XODIAG", m[0][1], false),
        ("CAL_MAG0_YODIAG", m[0][2], false),
        ("CAL_MAG0_ZODIAG", m[1][2], false),
    ] {
        ulog_param(&mut out, n, v, int);
    }
    further_params(&mut out, further);
    let used = as_used(onboard).1;
    let mut sub = |multi: u8, id: u16, name: &str| {
        let mut b = vec![multi];
        b.extend(id.to_le_bytes());
        b.extend(name.as_bytes());
        ulog_msg(&mut out, b'A', &b);
    };
    sub(0, 0, "sensor_combined");
    sub(0, 1, "vehicle_magnetometer");
    sub(0, 2, "vehicle_attitude");
    // Further compass i: sensor_mag[i] as message 3 + 2i, vehicle_magnetometer[i + 1] as 4 + 2i.
    for i in 0..further.len() {
        sub(i as u8, 3 + 2 * i as u16, "sensor_mag");
        sub(i as u8 + 1, 4 + 2 * i as u16, "vehicle_magnetometer");
    }
    let mut further_msgs = further_messages(further).into_iter().peekable();
    for s in samples {
        let t = time_us(s.t_s);
        // Readings before this sample's time; those at it follow its attitude.
        while let Some((_, b)) = further_msgs.next_if(|(tf, _)| *tf < t) {
            ulog_msg(&mut out, b'D', &b);
        }
        if let Some(q) = s.ref_q.and_then(crate::attitude::ned_to_enu) {
            let mut b = 2u16.to_le_bytes().to_vec();
            b.extend(t.to_le_bytes());
            for v in q {
                b.extend((v as f32).to_le_bytes());
            }
            ulog_msg(&mut out, b'D', &b);
        }
        if let Some(raw) = s.mag_ut {
            let c = used.correct(&raw);
            ulog_msg(&mut out, b'D', &mag_msg(1, t, ID as u32, c));
        }
        if let (Some(a), Some(g)) = (s.accel_mps2, s.gyro_rad_s) {
            let mut b = 0u16.to_le_bytes().to_vec();
            b.extend(t.to_le_bytes());
            for v in g.iter().chain(&a) {
                b.extend((*v as f32).to_le_bytes());
            }
            ulog_msg(&mut out, b'D', &b);
        }
        while let Some((_, b)) = further_msgs.next_if(|(tf, _)| *tf <= t) {
            ulog_msg(&mut out, b'D', &b);
        }
    }
    for (_, b) in further_msgs {
        ulog_msg(&mut out, b'D', &b);
    }
    Ok(out)
}

/// An onboard calibration as PX4 reads its parameters back (float32): the offset in gauss as
/// written, and the calibration it applies.
fn as_used(o: &OnboardMag) -> ([f64; 3], OnboardMag) {
    let off = o.offset_ut.map(|v| v / 100.0);
    (
        off,
        OnboardMag {
            offset_ut: off.map(|v| v as f32 as f64 * 100.0),
            matrix: o.matrix.map(|r| r.map(|x| x as f32 as f64)),
        },
    )
}

/// CAL_MAG{i + 1}_* of each further compass i (no rotation).
fn further_params(out: &mut Vec<u8>, further: &[FurtherCompass]) {
    for (i, f) in further.iter().enumerate() {
        let n = i + 1;
        let (off, _) = as_used(&f.onboard);
        let m = &f.onboard.matrix;
        ulog_param(out, &format!("CAL_MAG{n}_ID"), f.device_id as f64, true);
        ulog_param(out, &format!("CAL_MAG{n}_ROT"), 0.0, true);
        for (k, a) in ["X", "Y", "Z"].iter().enumerate() {
            ulog_param(out, &format!("CAL_MAG{n}_{a}OFF"), off[k], false);
            ulog_param(out, &format!("CAL_MAG{n}_{a}SCALE"), m[k][k], false);
        }
        for (name, v) in [("X", m[0][1]), ("Y", m[0][2]), ("Z", m[1][2])] {
            ulog_param(out, &format!("CAL_MAG{n}_{name}ODIAG"), v, false);
        }
    }
}

/// The body of a `sensor_mag` or `vehicle_magnetometer` data message `id`: time (us), device id,
/// the field (uT, written in gauss).
fn mag_msg(id: u16, t: u64, dev: u32, v: [f64; 3]) -> Vec<u8> {
    let mut b = id.to_le_bytes().to_vec();
    b.extend(t.to_le_bytes());
    b.extend(dev.to_le_bytes());
    for x in v {
        b.extend(((x / 100.0) as f32).to_le_bytes());
    }
    b
}

/// Every further compass's messages in time order: compass i's raw `sensor_mag[i]` (message
/// 3 + 2i) at its `raw_rate_hz`, its corrected `vehicle_magnetometer[i + 1]` (4 + 2i) at every
/// reading.
fn further_messages(further: &[FurtherCompass]) -> Vec<(u64, Vec<u8>)> {
    let mut msgs = Vec::new();
    for (i, f) in further.iter().enumerate() {
        let used = as_used(&f.onboard).1;
        let mut next_raw = f64::NEG_INFINITY;
        for (t_s, raw) in &f.readings {
            let t = time_us(*t_s);
            if *t_s >= next_raw {
                msgs.push((t, mag_msg(3 + 2 * i as u16, t, f.device_id, *raw)));
                next_raw = t_s + 1.0 / f.raw_rate_hz;
            }
            msgs.push((
                t,
                mag_msg(4 + 2 * i as u16, t, f.device_id, used.correct(raw)),
            ));
        }
    }
    msgs.sort_by_key(|(t, _)| *t);
    msgs
}

/// Write `samples` as a `.bin` or `.ulg` (by `path`'s extension) through
/// [`crate::io::publish::write_atomic`].
pub fn write_flight_log(
    path: &std::path::Path,
    samples: &[Sample],
    onboard: &OnboardMag,
) -> Result<(), Error> {
    let name = path.to_string_lossy().to_ascii_lowercase();
    let bytes = if name.ends_with(".bin") {
        dataflash_bytes(samples, onboard)?
    } else if name.ends_with(".ulg") {
        ulog_bytes(samples, onboard)?
    } else {
        return Err(Error::Other(format!(
            "{}: a flight-controller log is .bin or .ulg",
            path.display()
        )));
    };
    crate::io::publish::write_atomic(path, &bytes)
}

/// Write `samples` as a DataFlash `.bin` with further IMU instances and parameters
/// ([`DataflashExtra`]) through [`crate::io::publish::write_atomic`].
pub fn write_dataflash_with(
    path: &std::path::Path,
    samples: &[Sample],
    onboard: &OnboardMag,
    extra: &DataflashExtra<'_>,
) -> Result<(), Error> {
    let bytes = dataflash_bytes_with(samples, onboard, extra)?;
    crate::io::publish::write_atomic(path, &bytes)
}
