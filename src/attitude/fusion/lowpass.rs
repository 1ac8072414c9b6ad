//! The filter's low-passes of 3-vectors: first order (rest detection, the latency estimate's
//! high-pass) and second-order Butterworth (the specific force in the almost-inertial frame).

use nalgebra::Vector3;

/// First-order low-pass of a 3-vector with time constant tau.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Lp3 {
    v: Vector3<f64>,
    init: bool,
}

impl Lp3 {
    pub(super) fn update(&mut self, x: &Vector3<f64>, dt: f64, tau: f64) -> Vector3<f64> {
        if !self.init {
            self.v = *x;
            self.init = true;
        } else {
            let a = (dt / tau.max(dt)).min(1.0);
            self.v += (x - self.v) * a;
        }
        self.v
    }
}

/// Second-order Butterworth low-pass of a 3-vector (bilinear transform, cut-off
/// `sqrt(2) / (2 pi tau)`), direct form I: the state is the last two inputs and outputs.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Butter3 {
    /// (tau, dt) the coefficients are for, and b0, a1, a2 (b1 = 2 b0, b2 = b0).
    key: (f64, f64),
    c: [f64; 3],
    x: [Vector3<f64>; 2],
    y: [Vector3<f64>; 2],
    init: bool,
}

impl Butter3 {
    pub(super) fn update(&mut self, v: &Vector3<f64>, dt: f64, tau: f64) -> Vector3<f64> {
        // (Recomputed only when tau or the step changes by more than a part in a thousand: real
        // clocks jitter every step, and the cut-off moves by as little.)
        if self.key.0 != tau || (dt - self.key.1).abs() > 1e-3 * self.key.1 {
            let fc = std::f64::consts::SQRT_2 / (2.0 * std::f64::consts::PI * tau);
            let k = (std::f64::consts::PI * fc * dt).min(1.5).tan();
            let d = k * k + std::f64::consts::SQRT_2 * k + 1.0;
            self.c = [
                k * k / d,
                2.0 * (k * k - 1.0) / d,
                (k * k - std::f64::consts::SQRT_2 * k + 1.0) / d,
            ];
            self.key = (tau, dt);
        }
        if !self.init {
            self.x = [*v; 2];
            self.y = [*v; 2];
            self.init = true;
        }
        let [b0, a1, a2] = self.c;
        let out = (v + self.x[0] * 2.0 + self.x[1]) * b0 - self.y[0] * a1 - self.y[1] * a2;
        self.x = [*v, self.x[0]];
        self.y = [out, self.y[0]];
        out
    }
}
