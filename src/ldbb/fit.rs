//! Fits of the LDBB analysis: in = values on the angle grid; out = the centring sine (Eq. 9,
//! linear and nonlinear) and the least-squares line of deflection against load per angle.
//!
//! Eq. 9 is a·sin(bθ − φ) + offset with θ the circle angle. A centring offset e of the circle
//! against the table ball changes the bar length by (R/L)·e·cos(θ − θ₀) to first order, a
//! sine with b = 1: so the linear least squares on [sin θ, cos θ, 1] needs no initial guess and
//! is the physical model. The paper's nonlinear fit frees b; it is started here from the linear
//! solution (or from the paper's guess a = 0.8 mm, b = 1, φ = 22.5°) by Levenberg–Marquardt.

use serde::Serialize;

/// A fitted sine a·sin(bθ − φ) + offset (SI: m, rad), with standard uncertainties.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Sine {
    pub a: f64,
    pub b: f64,
    pub phi: f64,
    pub offset: f64,
    pub std_a: f64,
    /// 0 for the linear fit (b held at 1).
    pub std_b: f64,
    pub std_phi: f64,
    pub std_offset: f64,
    /// RMS of the data about the sine (m).
    pub rms: f64,
    pub converged: bool,
    pub iterations: usize,
}

impl Sine {
    #[inline]
    pub fn eval(&self, theta: f64) -> f64 {
        self.a * (self.b * theta - self.phi).sin() + self.offset
    }
}

/// Lag-1 autocorrelation of a periodic residual, clamped to [0, 0.98]: residuals that are a
/// smooth curve rather than noise carry fewer independent samples, N_eff = N(1 − ρ)/(1 + ρ).
pub fn lag1(r: &[f64]) -> f64 {
    let n = r.len();
    if n < 3 {
        return 0.0;
    }
    let mean = r.iter().sum::<f64>() / n as f64;
    let var: f64 = r.iter().map(|x| (x - mean).powi(2)).sum();
    if var <= 0.0 {
        return 0.0;
    }
    let cov: f64 = (0..n)
        .map(|i| (r[i] - mean) * (r[(i + 1) % n] - mean))
        .sum();
    (cov / var).clamp(0.0, 0.98)
}

/// Variance inflation for correlated residuals: (1 + ρ)/(1 − ρ).
pub fn inflation(r: &[f64]) -> f64 {
    let rho = lag1(r);
    (1.0 + rho) / (1.0 - rho)
}

fn wrap_pi(a: f64) -> f64 {
    let a = (a + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI;
    if a <= -std::f64::consts::PI {
        a + std::f64::consts::TAU
    } else {
        a
    }
}

/// Solves the small symmetric system `m x = v` (Cholesky; None when singular).
fn solve(m: nalgebra::DMatrix<f64>, v: nalgebra::DVector<f64>) -> Option<nalgebra::DVector<f64>> {
    m.cholesky().map(|c| c.solve(&v))
}

/// Linear least squares of y = A sin θ + B cos θ + C: the sine with b = 1.
pub fn sine_linear(theta: &[f64], y: &[f64]) -> Option<Sine> {
    use nalgebra::{DMatrix, DVector};
    let n = theta.len();
    if n < 4 {
        return None;
    }
    let x = DMatrix::from_fn(n, 3, |i, k| match k {
        0 => theta[i].sin(),
        1 => theta[i].cos(),
        _ => 1.0,
    });
    let yv = DVector::from_column_slice(y);
    let xtx = x.transpose() * &x;
    let p = solve(xtx.clone(), x.transpose() * &yv)?;
    let r: Vec<f64> = (0..n).map(|i| y[i] - (x.row(i) * &p)[0]).collect();
    let rss: f64 = r.iter().map(|v| v * v).sum();
    let s2 = rss / (n - 3) as f64 * inflation(&r);
    let cov = xtx.try_inverse()? * s2;
    let (sa, ca) = (p[0], p[1]);
    // A sin θ + B cos θ = a sin(θ − φ) with A = a cos φ, B = −a sin φ.
    let a = sa.hypot(ca);
    let phi = (-ca).atan2(sa);
    // Uncertainties by the Jacobian of (A, B) → (a, φ).
    let (ga, gp) = if a > 0.0 {
        ([sa / a, ca / a], [ca / (a * a), -sa / (a * a)])
    } else {
        ([0.0, 0.0], [0.0, 0.0])
    };
    let var = |g: [f64; 2]| {
        g[0] * g[0] * cov[(0, 0)] + 2.0 * g[0] * g[1] * cov[(0, 1)] + g[1] * g[1] * cov[(1, 1)]
    };
    Some(Sine {
        a,
        b: 1.0,
        phi,
        offset: p[2],
        std_a: var(ga).max(0.0).sqrt(),
        std_b: 0.0,
        std_phi: var(gp).max(0.0).sqrt(),
        std_offset: cov[(2, 2)].max(0.0).sqrt(),
        rms: (rss / n as f64).sqrt(),
        converged: true,
        iterations: 0,
    })
}

/// Levenberg–Marquardt on a·sin(bθ − φ) + offset, from `start` (a, b, φ, offset).
pub fn sine_nonlinear(theta: &[f64], y: &[f64], start: [f64; 4]) -> Option<Sine> {
    use nalgebra::{DMatrix, DVector};
    let n = theta.len();
    if n < 5 {
        return None;
    }
    let resid = |p: &[f64; 4]| -> Vec<f64> {
        (0..n)
            .map(|i| y[i] - (p[0] * (p[1] * theta[i] - p[2]).sin() + p[3]))
            .collect()
    };
    let jac = |p: &[f64; 4]| -> DMatrix<f64> {
        DMatrix::from_fn(n, 4, |i, k| {
            let arg = p[1] * theta[i] - p[2];
            match k {
                0 => arg.sin(),
                1 => p[0] * theta[i] * arg.cos(),
                2 => -p[0] * arg.cos(),
                _ => 1.0,
            }
        })
    };
    let cost = |r: &[f64]| r.iter().map(|v| v * v).sum::<f64>();
    let mut p = start;
    let mut r = resid(&p);
    let mut c = cost(&r);
    let mut lambda = 1e-3;
    let mut converged = false;
    let mut it = 0;
    while it < 200 {
        it += 1;
        let j = jac(&p);
        let jtj = j.transpose() * &j;
        let g = j.transpose() * DVector::from_column_slice(&r);
        let mut improved = false;
        for _ in 0..20 {
            let mut m = jtj.clone();
            for k in 0..4 {
                m[(k, k)] += lambda * jtj[(k, k)].max(1e-300);
            }
            let Some(d) = solve(m, g.clone()) else {
                lambda *= 10.0;
                continue;
            };
            let q = [p[0] + d[0], p[1] + d[1], p[2] + d[2], p[3] + d[3]];
            let rq = resid(&q);
            let cq = cost(&rq);
            if cq < c {
                let small = (0..4).all(|k| d[k].abs() <= 1e-10 * (1.0 + q[k].abs()));
                p = q;
                r = rq;
                let rel = (c - cq) / c.max(1e-300);
                c = cq;
                lambda = (lambda * 0.3).max(1e-12);
                improved = true;
                if small || rel < 1e-14 {
                    converged = true;
                }
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            // No step lowers the cost: a minimum to the solver's precision.
            converged = true;
        }
        if converged {
            break;
        }
    }
    let j = jac(&p);
    let s2 = c / (n - 4) as f64 * inflation(&r);
    let cov = (j.transpose() * &j).try_inverse().map(|m| m * s2);
    let sd = |k: usize| cov.as_ref().map_or(f64::NAN, |m| m[(k, k)].max(0.0).sqrt());
    let (mut a, mut phi) = (p[0], p[2]);
    if a < 0.0 {
        a = -a;
        phi += std::f64::consts::PI;
    }
    Some(Sine {
        a,
        b: p[1],
        phi: wrap_pi(phi),
        offset: p[3],
        std_a: sd(0),
        std_b: sd(1),
        std_phi: sd(2),
        std_offset: sd(3),
        rms: (c / n as f64).sqrt(),
        converged,
        iterations: it,
    })
}

/// The least-squares line of `y` (per load) against `load`: (slope, intercept, residual sum
/// of squares). Every load counts alike.
pub fn line(load: &[f64], y: &[f64]) -> (f64, f64, f64) {
    let n = load.len() as f64;
    let fm = load.iter().sum::<f64>() / n;
    let ym = y.iter().sum::<f64>() / n;
    let sxx: f64 = load.iter().map(|f| (f - fm).powi(2)).sum();
    let sxy: f64 = load.iter().zip(y).map(|(f, v)| (f - fm) * (v - ym)).sum();
    let slope = sxy / sxx;
    let icpt = ym - slope * fm;
    let rss = load
        .iter()
        .zip(y)
        .map(|(f, v)| (v - icpt - slope * f).powi(2))
        .sum();
    (slope, icpt, rss)
}

/// A periodic moving average over ±`half` nodes (for variances that change slowly around
/// the circle).
pub fn smooth(v: &[f64], half: usize) -> Vec<f64> {
    let n = v.len();
    let w = (2 * half + 1).min(n);
    (0..n)
        .map(|i| (0..w).map(|k| v[(i + n + k - w / 2) % n]).sum::<f64>() / w as f64)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn grid(n: usize) -> Vec<f64> {
        (0..n)
            .map(|k| k as f64 * std::f64::consts::TAU / n as f64)
            .collect()
    }

    #[test]
    fn linear_sine_recovers_amplitude_phase_offset_and_a_fair_uncertainty() {
        let th = grid(360);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let (a, phi, off) = (0.764e-3, 14.08f64.to_radians(), 5e-6);
        let mut errs = Vec::new();
        let mut stds = Vec::new();
        for _ in 0..40 {
            let y: Vec<f64> = th
                .iter()
                .map(|&t| a * (t - phi).sin() + off + 2e-6 * rng.random_range(-1.7..1.7))
                .collect();
            let s = sine_linear(&th, &y).unwrap();
            assert!((s.a - a).abs() < 1e-6 && (s.phi - phi).abs() < 2e-3);
            assert!((s.offset - off).abs() < 1e-6);
            errs.push(s.a - a);
            stds.push(s.std_a);
        }
        // The stated std matches the scatter over repeats (within a factor 1.5).
        let rms = (errs.iter().map(|e| e * e).sum::<f64>() / errs.len() as f64).sqrt();
        let sd = stds.iter().sum::<f64>() / stds.len() as f64;
        assert!(
            rms / sd > 0.66 && rms / sd < 1.5,
            "scatter {rms} vs std {sd}"
        );
    }

    #[test]
    fn nonlinear_sine_finds_b_and_agrees_with_finite_differences_of_the_cost() {
        let th = grid(720);
        let truth = [0.764e-3, 0.933, 14.08f64.to_radians(), -3e-6];
        let y: Vec<f64> = th
            .iter()
            .map(|&t| truth[0] * (truth[1] * t - truth[2]).sin() + truth[3])
            .collect();
        // From the paper's guess: a = 0.8 mm, b = 1, φ = 22.5°.
        let s = sine_nonlinear(&th, &y, [0.8e-3, 1.0, 22.5f64.to_radians(), 0.0]).unwrap();
        assert!(s.converged);
        assert!(
            (s.a - truth[0]).abs() < 1e-9 && (s.b - truth[1]).abs() < 1e-7,
            "{s:?}"
        );
        assert!((s.phi - truth[2]).abs() < 1e-6 && (s.offset - truth[3]).abs() < 1e-9);
        // A pure b = 1 sine: the linear and the nonlinear fit agree.
        let y: Vec<f64> = th.iter().map(|&t| 3e-4 * (t + 1.0).sin()).collect();
        let l = sine_linear(&th, &y).unwrap();
        let n = sine_nonlinear(&th, &y, [l.a, 1.0, l.phi, l.offset]).unwrap();
        assert!((n.b - 1.0).abs() < 1e-9 && (n.a - l.a).abs() < 1e-12);
        assert!((l.phi - (-1.0)).abs() < 1e-12);
    }

    #[test]
    fn line_and_smooth() {
        let (s, i, r) = line(&[125.0, 250.0, 375.0], &[1.0 + 0.25, 1.0 + 0.5, 1.0 + 0.75]);
        assert!((s - 0.002).abs() < 1e-15 && (i - 1.0).abs() < 1e-12 && r < 1e-20);
        assert_eq!(smooth(&[0.0, 3.0, 0.0, 0.0], 1), vec![1.0, 1.0, 1.0, 0.0]);
    }
}
