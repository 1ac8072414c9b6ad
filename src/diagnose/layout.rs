//! The forward model: the fixed context of a diagnosis, the parameter layout of the base model plus
//! the catalogue of effects as switchable terms, decoding a parameter vector, the residuals every
//! evidence unit gives in each channel ([`super::channel`]). The physical ranges of the effects'
//! parameters are [`super::plausible`].

use super::channel::{Ch, NCH};
use super::evidence::{
    v3, Driver, Evidence, MagObs, Unit, DRIVER_LAGS_S, MIN_TEMP_RANGE_C, N_DRIVER_LAGS,
    N_TEMP_LAGS, TEMP_LAGS_S,
};
use super::Effect;
use crate::calib::model::{a_from_params, rotation_from_vector, Calibration, ModelKind};
use crate::types::Vec3;
use nalgebra::{DVector, Matrix3, Vector3};

/// Newton steps of the per-axis inverse of the cubic scale term.
const CUBIC_NEWTON_STEPS: usize = 4;

/// Fixed context of one diagnosis.
pub(super) struct Ctx {
    pub base: ModelKind,
    pub ch: [bool; NCH],
    pub acc_free: bool,
    pub fixed_acc: Calibration,
    pub g: f64,
    pub c0m: Vector3<f64>,
    pub s0m: f64,
    pub c0a: Vector3<f64>,
    pub s0a: f64,
    pub temp_ok: bool,
    pub drv_ok: bool,
    pub gyro_temp: bool,
    pub driver: Option<Driver>,
    pub drv_range: f64,
    pub temp_range: f64,
    pub time_span: f64,
}

pub(super) fn n_a(kind: ModelKind) -> usize {
    if kind == ModelKind::Sym9 {
        6
    } else {
        3
    }
}

#[derive(Debug, Clone, Copy)]
pub(super) struct EffBlock {
    pub effect: Effect,
    pub start: usize,
    pub len: usize,
    pub mag: bool,
    pub acc: bool,
    pub time: bool,
    pub temp: bool,
}

#[derive(Debug, Clone)]
pub(super) struct Layout {
    pub mag: Option<usize>,
    pub acc: Option<usize>,
    pub dip: Option<usize>,
    pub vec: Option<usize>,
    pub gyro: Option<usize>,
    /// Number of base parameters (they come first, in a fixed order).
    pub n_base: usize,
    pub effects: Vec<EffBlock>,
    pub n: usize,
    pub typ: Vec<f64>,
    pub names: Vec<(String, String)>,
    /// Which lag of [`TEMP_LAGS_S`] the temperature effect follows (chosen by profiling, not a
    /// parameter of the solver).
    pub temp_lag: usize,
    /// Which lag of [`DRIVER_LAGS_S`] the motor field follows (likewise).
    pub drv_lag: usize,
}

impl Layout {
    /// Append a parameter: its name, unit and typical size (which sets the difference step).
    fn push(&mut self, name: String, unit: &str, typ: f64) {
        self.n += 1;
        self.typ.push(typ);
        self.names.push((name, unit.to_string()));
    }
    pub(super) fn block(&self, e: Effect) -> Option<&EffBlock> {
        self.effects.iter().find(|b| b.effect == e)
    }
    /// The same layout with the temperature effect following lag `k` of [`TEMP_LAGS_S`].
    pub(super) fn with_temp_lag(mut self, k: usize) -> Layout {
        self.temp_lag = k.min(N_TEMP_LAGS - 1);
        self
    }
    /// The time constant the temperature effect follows, s.
    pub(super) fn temp_lag_s(&self) -> f64 {
        TEMP_LAGS_S[self.temp_lag]
    }
    /// The same layout with the motor field following lag `k` of [`DRIVER_LAGS_S`].
    pub(super) fn with_drv_lag(mut self, k: usize) -> Layout {
        self.drv_lag = k.min(N_DRIVER_LAGS - 1);
        self
    }
    /// The time constant the motor field follows, s.
    pub(super) fn drv_lag_s(&self) -> f64 {
        DRIVER_LAGS_S[self.drv_lag]
    }
    /// The same layout with the lags of `other`.
    pub(super) fn with_lags_of(self, other: &Layout) -> Layout {
        self.with_temp_lag(other.temp_lag)
            .with_drv_lag(other.drv_lag)
    }
    /// The lag grid of an effect that follows a lagged regressor: (how many lags, the time
    /// constant in use, s), or None.
    pub(super) fn lag_of(&self, e: Effect) -> Option<(usize, f64)> {
        match e {
            Effect::TemperatureBias => Some((N_TEMP_LAGS, self.temp_lag_s())),
            Effect::MotorInterference => Some((N_DRIVER_LAGS, self.drv_lag_s())),
            _ => None,
        }
    }
    /// The same layout with effect `e` following lag `k` of its grid.
    pub(super) fn with_lag(self, e: Effect, k: usize) -> Layout {
        match e {
            Effect::TemperatureBias => self.with_temp_lag(k),
            Effect::MotorInterference => self.with_drv_lag(k),
            _ => self,
        }
    }
}

/// Why an effect cannot be a candidate with this data, if it cannot.
pub(super) fn applicable(ctx: &Ctx, e: Effect) -> Result<(), String> {
    let mag = ctx.ch[Ch::MagNorm.i()] || ctx.ch[Ch::Dip.i()] || ctx.ch[Ch::VecMag.i()];
    match e {
        Effect::CrossAxis => {
            if ctx.base != ModelKind::Diag6 {
                Err("already in the base model (sym9)".into())
            } else if !(ctx.ch[Ch::MagNorm.i()] || ctx.acc_free) {
                Err("no field-magnitude residual".into())
            } else {
                Ok(())
            }
        }
        Effect::MagAccelMisalignment => {
            if ctx.ch[Ch::Dip.i()] || ctx.ch[Ch::VecMag.i()] {
                Ok(())
            } else {
                Err("too few static poses with both accel and mag for the dip angle".into())
            }
        }
        Effect::TemperatureBias => {
            if !ctx.temp_ok {
                Err(format!(
                    "no temperature, or it does not vary (< {MIN_TEMP_RANGE_C} degC)"
                ))
            } else if !(mag || ctx.acc_free) {
                Err("no mag or accel residual".into())
            } else {
                Ok(())
            }
        }
        Effect::MotorInterference => {
            if !ctx.drv_ok {
                Err(match ctx.driver {
                    None => "no throttle or current in the log".into(),
                    Some(_) => "the motor driver does not vary between units".into(),
                })
            } else if !mag {
                Err("no magnetometer".into())
            } else {
                Ok(())
            }
        }
        Effect::HeadingOffset => {
            if ctx.ch[Ch::VecAcc.i()] || ctx.ch[Ch::VecMag.i()] {
                Ok(())
            } else {
                Err("no reference attitude".into())
            }
        }
        Effect::ScaleNonlinearity => {
            if ctx.ch[Ch::MagNorm.i()] || ctx.acc_free {
                Ok(())
            } else {
                Err("no magnitude residual".into())
            }
        }
        Effect::GyroBiasDrift => {
            if ctx.ch[Ch::Gyro.i()] {
                Ok(())
            } else {
                Err("too few static poses with the gyro".into())
            }
        }
    }
}

pub(super) fn build_layout(ctx: &Ctx, effects: &[Effect]) -> Layout {
    let mut lay = Layout {
        mag: None,
        acc: None,
        dip: None,
        vec: None,
        gyro: None,
        n_base: 0,
        effects: vec![],
        n: 0,
        typ: vec![],
        names: vec![],
        temp_lag: 0,
        drv_lag: 0,
    };
    let axes = ["x", "y", "z"];
    let mat_names: &[&str] = if ctx.base == ModelKind::Sym9 {
        &["a11", "a22", "a33", "a12", "a13", "a23"]
    } else {
        &["a11", "a22", "a33"]
    };
    let mag_on = ctx.ch[Ch::MagNorm.i()] || ctx.ch[Ch::Dip.i()] || ctx.ch[Ch::VecMag.i()];
    if mag_on {
        lay.mag = Some(lay.n);
        for a in axes {
            lay.push(format!("mag_offset_{a}"), "1", 1.0);
        }
        for m in mat_names {
            lay.push(format!("mag_{m}"), "1", 1.0);
        }
    }
    if ctx.acc_free {
        lay.acc = Some(lay.n);
        for a in axes {
            lay.push(format!("accel_offset_{a}"), "1", 1.0);
        }
        for m in mat_names {
            lay.push(format!("accel_{m}"), "1", 1.0);
        }
    }
    if ctx.ch[Ch::Dip.i()] {
        lay.dip = Some(lay.n);
        lay.push("sin_dip".into(), "1", 1.0);
    }
    if ctx.ch[Ch::VecAcc.i()] || ctx.ch[Ch::VecMag.i()] {
        lay.vec = Some(lay.n);
        lay.push("declination".into(), "rad", 1.0);
        lay.push("inclination".into(), "rad", 1.0);
    }
    if ctx.ch[Ch::Gyro.i()] {
        lay.gyro = Some(lay.n);
        for a in axes {
            lay.push(format!("gyro_bias_{a}"), "rad/s", 0.01);
        }
    }
    lay.n_base = lay.n;
    for &e in effects {
        if applicable(ctx, e).is_ok() {
            push_effect(ctx, &mut lay, e);
        }
    }
    lay
}

/// Append the parameters of effect `e` (its block) to `lay`.
fn push_effect(ctx: &Ctx, lay: &mut Layout, e: Effect) {
    let axes = ["x", "y", "z"];
    let mag_on = ctx.ch[Ch::MagNorm.i()] || ctx.ch[Ch::Dip.i()] || ctx.ch[Ch::VecMag.i()];
    let drv_unit = match ctx.driver {
        Some(Driver::Current) => "uT/A",
        _ => "uT/throttle",
    };
    let start = lay.n;
    let mut b = EffBlock {
        effect: e,
        start,
        len: 0,
        mag: false,
        acc: false,
        time: false,
        temp: false,
    };
    let mag_n = ctx.ch[Ch::MagNorm.i()];
    match e {
        Effect::CrossAxis => {
            if mag_n {
                b.mag = true;
                for p in ["xy", "xz", "yz"] {
                    lay.push(format!("mag_{p}"), "1", 0.1);
                }
            }
            if ctx.acc_free {
                b.acc = true;
                for p in ["xy", "xz", "yz"] {
                    lay.push(format!("accel_{p}"), "1", 0.1);
                }
            }
        }
        Effect::MagAccelMisalignment => {
            b.mag = true;
            for a in axes {
                lay.push(format!("rotation_{a}"), "rad", 0.1);
            }
        }
        Effect::TemperatureBias => {
            if mag_on {
                b.mag = true;
                for a in axes {
                    lay.push(format!("mag_{a}"), "uT/degC", 0.1);
                }
            }
            if ctx.acc_free {
                b.acc = true;
                for a in axes {
                    lay.push(format!("accel_{a}"), "m/s^2/degC", 0.01);
                }
            }
        }
        Effect::MotorInterference => {
            b.mag = true;
            let typ = if ctx.driver == Some(Driver::Current) {
                0.1
            } else {
                1.0
            };
            for a in axes {
                lay.push(format!("k_{a}"), drv_unit, typ);
            }
        }
        Effect::HeadingOffset => {
            lay.push("heading_offset".into(), "rad", 0.1);
        }
        Effect::ScaleNonlinearity => {
            if mag_n {
                b.mag = true;
                for a in axes {
                    lay.push(format!("mag_cubic_{a}"), "1", 0.1);
                }
            }
            if ctx.acc_free {
                b.acc = true;
                for a in axes {
                    lay.push(format!("accel_cubic_{a}"), "1", 0.1);
                }
            }
        }
        Effect::GyroBiasDrift => {
            b.time = true;
            for a in axes {
                lay.push(format!("{a}_per_s"), "rad/s/s", 1e-4);
            }
            if ctx.gyro_temp {
                b.temp = true;
                for a in axes {
                    lay.push(format!("{a}_per_degc"), "rad/s/degC", 1e-4);
                }
            }
        }
    }
    b.len = lay.n - start;
    if b.len > 0 {
        lay.effects.push(b);
    }
}

/// Parameter values of `lay` taken from `(old, p)` where they exist there, else zero.
pub(super) fn carry_params(old: &Layout, p: &DVector<f64>, lay: &Layout) -> DVector<f64> {
    let mut out = DVector::zeros(lay.n);
    let nb = old.n_base.min(lay.n_base);
    for i in 0..nb {
        out[i] = p[i];
    }
    for b in &lay.effects {
        if let Some(ob) = old.block(b.effect) {
            if ob.len == b.len {
                for k in 0..b.len {
                    out[b.start + k] = p[ob.start + k];
                }
            }
        }
    }
    out
}

/// A decoded parameter vector.
pub(super) struct Model {
    pub pm: Vector3<f64>,
    pub am: Matrix3<f64>,
    pub mot: Vector3<f64>,
    pub tm: Vector3<f64>,
    /// Which lag of [`TEMP_LAGS_S`] the temperature terms `tm` and `ta` follow.
    pub lag_k: usize,
    /// Which lag of [`DRIVER_LAGS_S`] the motor field `mot` follows.
    pub drv_lag_k: usize,
    pub cub_m: Option<Vector3<f64>>,
    pub rot: Matrix3<f64>,
    pub pa: Vector3<f64>,
    pub aa: Matrix3<f64>,
    pub ta: Vector3<f64>,
    pub cub_a: Option<Vector3<f64>>,
    pub s_dip: f64,
    pub e1: Vector3<f64>,
    pub e2: Vector3<f64>,
    pub q: Matrix3<f64>,
    pub bg: Vector3<f64>,
    pub dt: Vector3<f64>,
    pub dtemp: Vector3<f64>,
}

pub(super) fn sl3(p: &[f64]) -> Vector3<f64> {
    Vector3::new(p[0], p[1], p[2])
}

pub(super) fn rz(psi: f64) -> Matrix3<f64> {
    let (s, c) = psi.sin_cos();
    Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0)
}

/// Earth-field direction in ENU from declination and inclination, and two unit vectors across it.
pub(super) fn field_frame(dec: f64, inc: f64) -> (Vector3<f64>, Vector3<f64>, Vector3<f64>) {
    let h = Vector3::new(inc.cos() * dec.sin(), inc.cos() * dec.cos(), -inc.sin());
    let e1 = Vector3::new(dec.cos(), -dec.sin(), 0.0);
    let e2 = h.cross(&e1);
    (h, e1, e2)
}

pub(super) fn sym_off(p: &[f64]) -> Matrix3<f64> {
    Matrix3::new(0.0, p[0], p[1], p[0], 0.0, p[2], p[1], p[2], 0.0)
}

pub(super) fn decode(ctx: &Ctx, lay: &Layout, p: &[f64]) -> Model {
    let na = n_a(ctx.base);
    let mut md = Model {
        pm: Vector3::zeros(),
        am: Matrix3::identity(),
        mot: Vector3::zeros(),
        tm: Vector3::zeros(),
        lag_k: lay.temp_lag,
        drv_lag_k: lay.drv_lag,
        cub_m: None,
        rot: Matrix3::identity(),
        pa: Vector3::zeros(),
        aa: Matrix3::identity(),
        ta: Vector3::zeros(),
        cub_a: None,
        s_dip: 0.0,
        e1: Vector3::x(),
        e2: Vector3::y(),
        q: Matrix3::identity(),
        bg: Vector3::zeros(),
        dt: Vector3::zeros(),
        dtemp: Vector3::zeros(),
    };
    if let Some(s) = lay.mag {
        md.pm = sl3(&p[s..]);
        md.am = a_from_params(ctx.base, &p[s + 3..s + 3 + na]);
    }
    if let Some(s) = lay.acc {
        md.pa = sl3(&p[s..]);
        md.aa = a_from_params(ctx.base, &p[s + 3..s + 3 + na]);
    }
    if let Some(s) = lay.dip {
        md.s_dip = p[s];
    }
    if let Some(s) = lay.vec {
        let (_, e1, e2) = field_frame(p[s], p[s + 1]);
        md.e1 = e1;
        md.e2 = e2;
    }
    if let Some(s) = lay.gyro {
        md.bg = sl3(&p[s..]);
    }
    for b in &lay.effects {
        let q = &p[b.start..b.start + b.len];
        let mut k = 0;
        match b.effect {
            Effect::CrossAxis => {
                if b.mag {
                    md.am += sym_off(&q[k..]);
                    k += 3;
                }
                if b.acc {
                    md.aa += sym_off(&q[k..]);
                }
            }
            Effect::MagAccelMisalignment => md.rot = rotation_from_vector(&sl3(q)),
            Effect::TemperatureBias => {
                if b.mag {
                    md.tm = sl3(&q[k..]);
                    k += 3;
                }
                if b.acc {
                    md.ta = sl3(&q[k..]);
                }
            }
            Effect::MotorInterference => md.mot = sl3(q),
            Effect::HeadingOffset => md.q = rz(q[0]),
            Effect::ScaleNonlinearity => {
                if b.mag {
                    md.cub_m = Some(sl3(&q[k..]));
                    k += 3;
                }
                if b.acc {
                    md.cub_a = Some(sl3(&q[k..]));
                }
            }
            Effect::GyroBiasDrift => {
                if b.time {
                    md.dt = sl3(&q[k..]);
                    k += 3;
                }
                if b.temp {
                    md.dtemp = sl3(&q[k..]);
                }
            }
        }
    }
    md
}

/// Solve w + c w^3 = u per axis (the sensed-to-true inverse of the cubic nonlinearity).
pub(super) fn invert_cubic(u: &Vector3<f64>, c: &Vector3<f64>) -> Vector3<f64> {
    let mut w = *u;
    for k in 0..3 {
        for _ in 0..CUBIC_NEWTON_STEPS {
            let f = w[k] + c[k] * w[k].powi(3) - u[k];
            let d = 1.0 + 3.0 * c[k] * w[k] * w[k];
            if d.abs() > 1e-6 {
                w[k] -= f / d;
            }
        }
    }
    w
}

impl Ctx {
    /// Calibrated field, normalised so that |u| = 1 for the earth field.
    #[inline]
    pub(super) fn cal_mag(&self, md: &Model, o: &MagObs) -> Vector3<f64> {
        let x =
            (o.m - md.mot * o.dlag[md.drv_lag_k] - md.tm * o.tlag[md.lag_k] - self.c0m) / self.s0m;
        let u = md.am * (x - md.pm);
        match &md.cub_m {
            Some(c) => invert_cubic(&u, c),
            None => u,
        }
    }
    /// Calibrated specific force in units of g.
    #[inline]
    pub(super) fn cal_acc(
        &self,
        md: &Model,
        a: &Vector3<f64>,
        tlag: &[f64; N_TEMP_LAGS],
    ) -> Vector3<f64> {
        if self.acc_free {
            let x = (a - md.ta * tlag[md.lag_k] - self.c0a) / self.s0a;
            let u = md.aa * (x - md.pa);
            match &md.cub_a {
                Some(c) => invert_cubic(&u, c),
                None => u,
            }
        } else {
            let c = self.fixed_acc.apply(&[a[0], a[1], a[2]]);
            Vector3::new(c[0], c[1], c[2]) / self.g
        }
    }
}

/// A moving window's residuals: the mean field-magnitude residual, and with reference attitudes
/// the mean of the readings' field directions turned into ENU, against the earth field's.
fn eval_window(ctx: &Ctx, md: &Model, u: &Unit, sink: &mut dyn FnMut(Ch, f64)) {
    if u.mags.is_empty() {
        return;
    }
    let cal: Vec<Vector3<f64>> = u.mags.iter().map(|o| ctx.cal_mag(md, o)).collect();
    if ctx.ch[Ch::MagNorm.i()] {
        let s: f64 = cal.iter().map(|c| c.norm() - 1.0).sum();
        sink(Ch::MagNorm, s / cal.len() as f64 * ctx.s0m);
    }
    if ctx.ch[Ch::VecMag.i()] {
        let (mut v, mut n) = (Vector3::zeros(), 0usize);
        for (o, c) in u.mags.iter().zip(&cal) {
            if let Some(w) = &o.ref_w {
                v += w * md.q * (md.rot * c.normalize());
                n += 1;
            }
        }
        if n > 0 {
            v /= n as f64;
            sink(Ch::VecMag, v.dot(&md.e1));
            sink(Ch::VecMag, v.dot(&md.e2));
        }
    }
}

/// Every residual component of `units`, in a fixed order, to `sink(unit, channel, value)` (physical units).
pub(super) fn eval_units(
    ctx: &Ctx,
    md: &Model,
    ev: &Evidence,
    units: &[usize],
    sink: &mut dyn FnMut(usize, Ch, f64),
) {
    for &ui in units {
        let u = &ev.units[ui];
        let has_mag = !u.mags.is_empty();
        if u.moving {
            eval_window(ctx, md, u, &mut |c, r| sink(ui, c, r));
            continue;
        }
        let cm = has_mag.then(|| ctx.cal_mag(md, &u.mags[0]));
        if ctx.ch[Ch::MagNorm.i()] {
            if let Some(c) = cm {
                sink(ui, Ch::MagNorm, (c.norm() - 1.0) * ctx.s0m);
            }
        }
        let ca = u.acc.map(|a| ctx.cal_acc(md, &a, &u.tlag));
        if ctx.ch[Ch::AccNorm.i()] {
            if let Some(a) = ca {
                sink(ui, Ch::AccNorm, (a.norm() - 1.0) * ctx.g);
            }
        }
        let chat = cm.map(|c| md.rot * (c / c.norm()));
        if ctx.ch[Ch::Dip.i()] {
            if let (Some(a), Some(c)) = (ca, chat) {
                sink(ui, Ch::Dip, -(a / a.norm()).dot(&c) - md.s_dip);
            }
        }
        if let Some(w) = &u.ref_w {
            let wq = w * md.q;
            if ctx.ch[Ch::VecAcc.i()] {
                if let Some(a) = ca {
                    let f = wq * (a / a.norm());
                    sink(ui, Ch::VecAcc, f.x);
                    sink(ui, Ch::VecAcc, f.y);
                }
            }
            if ctx.ch[Ch::VecMag.i()] {
                if let Some(c) = chat {
                    let v = wq * c;
                    sink(ui, Ch::VecMag, v.dot(&md.e1));
                    sink(ui, Ch::VecMag, v.dot(&md.e2));
                }
            }
        }
        if ctx.ch[Ch::Gyro.i()] {
            if let Some(g) = u.gyro {
                let r = g - md.bg - md.dt * u.t - md.dtemp * u.temp;
                sink(ui, Ch::Gyro, r.x);
                sink(ui, Ch::Gyro, r.y);
                sink(ui, Ch::Gyro, r.z);
            }
        }
    }
}

/// Component tags of `units`: (unit, channel, component index within the unit and channel).
pub(super) fn tags(
    ctx: &Ctx,
    lay: &Layout,
    p: &DVector<f64>,
    ev: &Evidence,
    units: &[usize],
) -> Vec<(usize, Ch, usize)> {
    let md = decode(ctx, lay, p.as_slice());
    let mut out: Vec<(usize, Ch, usize)> = Vec::new();
    eval_units(ctx, &md, ev, units, &mut |ui, c, _| {
        let k = match out.last() {
            Some(&(pu, pc, pk)) if pu == ui && pc == c => pk + 1,
            _ => 0,
        };
        out.push((ui, c, k));
    });
    out
}

pub(super) fn residuals(
    ctx: &Ctx,
    lay: &Layout,
    ev: &Evidence,
    units: &[usize],
    p: &[f64],
) -> Vec<(Ch, f64)> {
    let md = decode(ctx, lay, p);
    let mut out = Vec::new();
    eval_units(ctx, &md, ev, units, &mut |_, c, r| out.push((c, r)));
    out
}

/// Start calibrations from the pipeline, falling back to a fit of the static means.
pub(super) fn mag_start(
    res: &crate::calib::outcome::SensorResult,
    points: &[Vec3],
    base: ModelKind,
) -> Option<(Vector3<f64>, f64, Matrix3<f64>)> {
    let r = &res.report;
    if r.radius > 0.0 && r.offset.iter().all(|x| x.is_finite()) {
        let m = crate::calib::model::rows_to_mat(&r.matrix);
        if m.determinant() > 0.0 {
            return Some((v3(&r.offset), r.radius, m / m.determinant().cbrt()));
        }
    }
    let f =
        crate::calib::fit::fit_norm(points, base, &crate::calib::fit::NormFitOptions::default())
            .ok()?;
    Some((
        v3(&f.calibration.offset),
        f.radius,
        f.calibration.normalised_matrix(),
    ))
}

/// Fewest units with a magnetometer for the magnetometer channels.
const MIN_MAG_UNITS: usize = 6;
/// Fewest static units with an accelerometer mean for the accelerometer to be refitted.
const MIN_STATIC_ACC_UNITS: usize = 12;
/// Fewest static units with both accelerometer and magnetometer for the dip channel.
const MIN_DIP_UNITS: usize = 6;
/// Fewest static units with a reference attitude for a vector channel.
const MIN_REF_UNITS: usize = 8;
/// Fewest static units with a gyro mean for the gyro channel.
const MIN_GYRO_UNITS: usize = 6;
/// Gyro drift is fitted in temperature as well as time only when |corr(time, temperature)| over the
/// gyro units is below this...
const MAX_TIME_TEMP_CORRELATION: f64 = 0.95;
/// ...over at least this many units.
const MIN_GYRO_TEMP_UNITS: usize = 6;

/// The fixed context of a diagnosis, with the start matrices of magnetometer and accelerometer
/// (scaled to unit determinant).
pub(super) struct Start {
    pub ctx: Ctx,
    pub m0: Matrix3<f64>,
    pub a0: Matrix3<f64>,
}

/// Whether temperature varies independently enough of time for a gyro drift in both.
fn gyro_temp_separable(ev: &Evidence) -> bool {
    let pts: Vec<(f64, f64)> = ev
        .units
        .iter()
        .filter(|u| u.gyro.is_some() && u.has_temp)
        .map(|u| (u.t, u.temp))
        .collect();
    let n = pts.len() as f64;
    let (mt, mx) = pts
        .iter()
        .fold((0.0, 0.0), |a, p| (a.0 + p.0 / n, a.1 + p.1 / n));
    let (mut stt, mut sxx, mut stx) = (0.0, 0.0, 0.0);
    for (t, x) in &pts {
        stt += (t - mt).powi(2);
        sxx += (x - mx).powi(2);
        stx += (t - mt) * (x - mx);
    }
    pts.len() >= MIN_GYRO_TEMP_UNITS
        && sxx > 0.0
        && stt > 0.0
        && (stx / (stt * sxx).sqrt()).abs() < MAX_TIME_TEMP_CORRELATION
}

/// Which channels the evidence supports, and the start calibrations (the pipeline's fits).
/// Err: no channel at all.
pub(super) fn context(
    ev: &Evidence,
    results: &crate::calib::pipeline::FitResults,
    base: ModelKind,
    g: f64,
    notes: &mut Vec<String>,
) -> Result<Start, String> {
    let count =
        |f: &dyn Fn(&super::evidence::Unit) -> bool| ev.units.iter().filter(|u| f(u)).count();
    let n_mag = count(&|u| !u.mags.is_empty());
    let n_static_acc = count(&|u| !u.moving && u.acc.is_some());
    let n_dip = count(&|u| !u.moving && u.acc.is_some() && !u.mags.is_empty());
    let n_ref_acc = count(&|u| u.ref_w.is_some() && u.acc.is_some());
    let n_ref_mag = count(&|u| {
        (u.ref_w.is_some() && !u.mags.is_empty()) || u.mags.iter().any(|o| o.ref_w.is_some())
    });
    let n_gyro = count(&|u| u.gyro.is_some());
    let mag_pts: Vec<Vec3> = ev.body.iter().filter_map(|s| s.mag_ut).collect();
    let mstart = if n_mag >= MIN_MAG_UNITS {
        mag_start(&results.mag, &mag_pts, base)
    } else {
        None
    };
    if mstart.is_none() && n_mag > 0 {
        notes.push("no magnetometer fit to start from: mag channels off".into());
    }
    let acc_res = &results.accel;
    let acc_cal = {
        let r = &acc_res.report;
        let m = crate::calib::model::rows_to_mat(&r.matrix);
        (r.radius > 0.0 && m.determinant() > 0.0 && r.offset.iter().all(|x| x.is_finite()))
            .then_some(Calibration {
                model: base,
                offset: r.offset,
                matrix: r.matrix,
            })
    };
    let acc_free = n_static_acc >= MIN_STATIC_ACC_UNITS
        && acc_cal.is_some()
        && acc_res.report.status == crate::report::CalStatus::Ok;
    let mut ch = [false; NCH];
    ch[Ch::MagNorm.i()] = mstart.is_some();
    ch[Ch::AccNorm.i()] = acc_free;
    ch[Ch::Dip.i()] = mstart.is_some() && n_dip >= MIN_DIP_UNITS;
    ch[Ch::VecAcc.i()] = n_ref_acc >= MIN_REF_UNITS;
    ch[Ch::VecMag.i()] = mstart.is_some() && n_ref_mag >= MIN_REF_UNITS;
    ch[Ch::Gyro.i()] = n_gyro >= MIN_GYRO_UNITS;
    let (c0m, s0m, m0) = mstart.unwrap_or((Vector3::zeros(), 1.0, Matrix3::identity()));
    let (c0a, s0a, a0) = match (&acc_cal, acc_free) {
        (Some(c), true) => {
            let m = c.matrix3();
            let k = m.determinant().cbrt();
            (v3(&c.offset), g / k, m / k)
        }
        _ => (Vector3::zeros(), 1.0, Matrix3::identity()),
    };
    // Gyro drift in temperature too when temperature is not (nearly) a function of time.
    let gyro_temp = ev.temp_ok && gyro_temp_separable(ev);
    let ctx = Ctx {
        base,
        ch,
        acc_free,
        fixed_acc: acc_cal
            .filter(|_| acc_res.report.status == crate::report::CalStatus::Ok)
            .unwrap_or_else(Calibration::identity),
        g,
        c0m,
        s0m,
        c0a,
        s0a,
        temp_ok: ev.temp_ok,
        drv_ok: ev.drv_ok,
        gyro_temp,
        driver: ev.driver,
        drv_range: ev.drv_range,
        temp_range: ev.temp_range,
        time_span: ev.time_span,
    };
    if !ch.iter().any(|c| *c) {
        return Err("no residual channel: too few static poses and no magnetometer".into());
    }
    Ok(Start { ctx, m0, a0 })
}
