//! Joint stiffness from the compliance along the bar: in = the compliance c(θ) per grid angle
//! with its uncertainty and the compliance regressor rows (uᵀJᵢ)² of the same angles; out =
//! the stiffnesses this circle determines, with uncertainties, the combinations it determines
//! where single joints are not, and why the others stay unknown.
//!
//! c(θ) = uᵀ Jₚ K⁻¹ Jₚᵀ u = Σᵢ (uᵀJᵢ)² / kᵢ is linear in the joint compliances xᵢ = 1/kᵢ. One
//! circle does not determine all six: with the tool ball on the axis of joint 6 that joint has
//! no lever, and on a horizontal circle with a vertical tool the columns of joints 1 and 4
//! (both turn the ball sideways) and of 2, 3 and 5 (all in the arm's plane) are nearly
//! parallel. The least squares runs on columns scaled to unit norm, through an SVD; a joint
//! counts as determined when its compliance is positive and its relative standard uncertainty
//! is at most [`REL_LIMIT`]. The uncertainty has three parts: the repeatability, propagated
//! from each run's deviation from its load's mean as a whole curve (a run's LVDT offset is
//! the same at every angle and must not average out over the angles); the model error, the
//! fit's residual variance inflated for the residual's correlation along the circle (a smooth
//! misfit is not noise), and a floor of [`MODEL_FLOOR`] of the compliance's RMS; and the
//! load dependence: half the difference between the compliances identified from the lower and
//! from the upper half of the loads. A joint model with linear gears gives the same from
//! both; nonlinear gears do not, and a fit that cannot follow them spreads their effect over
//! the other joints while its residual stays small, so only this comparison shows it.

use super::fit::inflation;
use nalgebra::{DMatrix, DVector, SymmetricEigen};
use serde::Serialize;

/// A joint is determined when its relative standard uncertainty is at most this (so that the
/// stiffness is good to about 10 % at three standard deviations).
pub const REL_LIMIT: f64 = 0.03;

/// The joint-compliance model is taken to hold to this share of the compliance's RMS at best:
/// without it, noise-free data would call any non-parallel columns "determined".
pub const MODEL_FLOOR: f64 = 0.001;

/// A combination Σ wᵢ/kᵢ the circle determines (weights normalised to max |w| = 1).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Combination {
    /// 1-based joints.
    pub joints: Vec<usize>,
    pub weights: Vec<f64>,
    /// Σ wᵢ/kᵢ, rad/(N·m).
    pub compliance_rad_per_nm: f64,
    pub std_rad_per_nm: f64,
    /// 1/(Σ wᵢ/kᵢ) when every weight is positive: the stiffness of a single joint with the
    /// combination's effect.
    pub effective_stiffness_nm_per_rad: Option<f64>,
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Stiffness {
    /// N·m/rad for the determined joints, None for the others.
    pub stiffness_nm_per_rad: [Option<f64>; 6],
    pub std_nm_per_rad: [Option<f64>; 6],
    /// Why a joint is not determined (None for the determined ones).
    pub why: [Option<String>; 6],
    pub combinations: Vec<Combination>,
    /// The least-squares compliance of every joint with a lever and its standard uncertainty
    /// (rad/(N·m)), determined or not.
    pub estimate_rad_per_nm: [Option<f64>; 6],
    pub estimate_std_rad_per_nm: [Option<f64>; 6],
    /// Singular values of the regressor with unit-norm columns (joints with a lever only).
    pub singular_values: Vec<f64>,
    /// RMS of the compliance about the fitted model, µm/N.
    pub fit_rms_um_per_n: f64,
    pub relative_std_limit: f64,
}

/// Identifies the joint compliances from `c` (m/N per angle) and the regressor rows (m², one
/// per angle). `c_err`: curves e_k whose Σ e_k e_kᵀ is the covariance of `c` over the angles
/// (from the repeats; empty when there are none). `levels`: the compliance from the lower and
/// from the upper half of the loads (None with fewer than three loads).
pub fn identify(
    rows: &[[f64; 6]],
    c: &[f64],
    c_err: &[Vec<f64>],
    levels: Option<(&[f64], &[f64])>,
) -> Stiffness {
    let n = rows.len();
    let norms: [f64; 6] =
        std::array::from_fn(|i| rows.iter().map(|r| r[i] * r[i]).sum::<f64>().sqrt());
    let top = norms.iter().cloned().fold(0.0, f64::max);
    let active: Vec<usize> = (0..6).filter(|&i| norms[i] > 1e-6 * top).collect();
    let mut why: [Option<String>; 6] = Default::default();
    for i in 0..6 {
        if !active.contains(&i) {
            why[i] = Some(format!(
                "no lever: the load along the bar makes no torque about joint {} anywhere on this circle",
                i + 1
            ));
        }
    }
    let p = active.len();
    let mut out = Stiffness {
        stiffness_nm_per_rad: [None; 6],
        std_nm_per_rad: [None; 6],
        why,
        combinations: Vec::new(),
        estimate_rad_per_nm: [None; 6],
        estimate_std_rad_per_nm: [None; 6],
        singular_values: Vec::new(),
        fit_rms_um_per_n: f64::NAN,
        relative_std_limit: REL_LIMIT,
    };
    if p == 0 || n <= p {
        return out;
    }
    let Some(sol) = solve(rows, c, c_err, levels, active, norms) else {
        return out;
    };
    out.singular_values = sol.singular_values.clone();
    out.fit_rms_um_per_n = sol.fit_rms_um_per_n;
    let undetermined = sol.judge(&mut out);
    // The combinations of the undetermined joints that are determined: eigenvectors of their
    // marginal covariance (in scaled coordinates) with a small relative uncertainty.
    if undetermined.len() >= 2 {
        out.combinations = sol.combinations(&undetermined);
    }
    out
}

/// The least-squares solution over the joints with a lever (`active`; `norms`: the column
/// norms of all six) and what the judgement of each joint needs.
struct Solution {
    active: Vec<usize>,
    norms: [f64; 6],
    /// Compliances and their standard uncertainties (rad/(N·m)), per active joint.
    x: Vec<f64>,
    sd: Vec<f64>,
    /// Covariance in the scaled coordinates xs_k = ||a_k|| x_k.
    cov: DMatrix<f64>,
    /// The load dependence (upper minus lower loads' solution, scaled) and the standard
    /// uncertainty before it was added.
    level_change: Vec<f64>,
    before: Vec<f64>,
    singular_values: Vec<f64>,
    fit_rms_um_per_n: f64,
}

/// The fit of [`identify`] on the columns scaled to unit norm; None when the SVD fails.
fn solve(
    rows: &[[f64; 6]],
    c: &[f64],
    c_err: &[Vec<f64>],
    levels: Option<(&[f64], &[f64])>,
    active: Vec<usize>,
    norms: [f64; 6],
) -> Option<Solution> {
    let n = rows.len();
    let p = active.len();
    let a = DMatrix::from_fn(n, p, |r, k| rows[r][active[k]] / norms[active[k]]);
    let y = DVector::from_column_slice(c);
    let svd = a.clone().svd(true, true);
    let (Some(u), Some(vt)) = (svd.u.as_ref(), svd.v_t.as_ref()) else {
        return None;
    };
    let s = &svd.singular_values;
    let singular_values = s.iter().copied().collect();
    let smax = s.iter().cloned().fold(0.0, f64::max);
    // Minimum-norm least squares in the scaled coordinates xs_k = ||a_k|| x_k.
    let mut xs = DVector::zeros(p);
    let mut sinv2 = DVector::zeros(p);
    for k in 0..p {
        if s[k] > 1e-12 * smax {
            let coef = u.column(k).dot(&y) / s[k];
            xs += vt.row(k).transpose() * coef;
            sinv2[k] = 1.0 / (s[k] * s[k]);
        } else {
            sinv2[k] = f64::INFINITY;
        }
    }
    let resid: Vec<f64> = (0..n).map(|r| y[r] - (a.row(r) * &xs)[0]).collect();
    let rss: f64 = resid.iter().map(|v| v * v).sum();
    let fit_rms_um_per_n = (rss / n as f64).sqrt() * 1e6;
    let rms_c = (c.iter().map(|v| v * v).sum::<f64>() / n as f64).sqrt();
    let s2 = rss / (n - p) as f64 * inflation(&resid) + (MODEL_FLOOR * rms_c).powi(2);
    // Model error and floor: s² V S⁻² Vᵀ (infinite along a null direction).
    let mut cov = DMatrix::from_fn(p, p, |i, j| {
        (0..p)
            .map(|k| {
                let w = vt[(k, i)] * vt[(k, j)];
                if w == 0.0 {
                    0.0
                } else {
                    w * sinv2[k]
                }
            })
            .sum::<f64>()
            * s2
    });
    // The pseudo-inverse V S⁻¹ Uᵀ applied to a curve over the angles.
    let pinv = |e: &[f64]| -> DVector<f64> {
        let ev = DVector::from_column_slice(e);
        let mut g = DVector::<f64>::zeros(p);
        for k in 0..p {
            if sinv2[k].is_finite() {
                g += vt.row(k).transpose() * (u.column(k).dot(&ev) / s[k]);
            }
        }
        g
    };
    // Repeatability: each error curve through the pseudo-inverse.
    for e in c_err {
        let g = pinv(e);
        cov += &g * g.transpose();
    }
    // Load dependence: half the difference of the lower and the upper loads' solutions.
    // The load dependence counts as shown only where it stands out of the other uncertainty.
    let before: Vec<f64> = (0..p).map(|k| cov[(k, k)].max(0.0).sqrt()).collect();
    let mut level_change = vec![0.0; p];
    if let Some((lo, hi)) = levels {
        let d: Vec<f64> = lo.iter().zip(hi).map(|(a, b)| 0.5 * (b - a)).collect();
        let g = pinv(&d);
        cov += &g * g.transpose();
        for k in 0..p {
            level_change[k] = 2.0 * g[k];
        }
    }
    let x: Vec<f64> = (0..p).map(|k| xs[k] / norms[active[k]]).collect();
    let sd: Vec<f64> = (0..p)
        .map(|k| cov[(k, k)].max(0.0).sqrt() / norms[active[k]])
        .collect();
    Some(Solution {
        active,
        norms,
        x,
        sd,
        cov,
        level_change,
        before,
        singular_values,
        fit_rms_um_per_n,
    })
}

impl Solution {
    /// Enters every active joint's estimate in `out`, its stiffness where it is determined and
    /// why where it is not; returns the undetermined ones (indices into `active`).
    fn judge(&self, out: &mut Stiffness) -> Vec<usize> {
        let Solution { active, x, sd, .. } = self;
        let p = active.len();
        let mut undetermined = Vec::new();
        for k in 0..p {
            let j = active[k];
            out.estimate_rad_per_nm[j] = Some(x[k]);
            out.estimate_std_rad_per_nm[j] = Some(sd[k]);
            let rel = sd[k] / x[k].abs();
            if x[k] > 0.0 && rel.is_finite() && rel <= REL_LIMIT {
                let kk = 1.0 / x[k];
                out.stiffness_nm_per_rad[j] = Some(kk);
                out.std_nm_per_rad[j] = Some(kk * rel);
                continue;
            }
            undetermined.push(k);
            out.why[j] = Some(self.why_not(k, rel));
        }
        undetermined
    }

    /// Why active joint `k` (relative uncertainty `rel`) is not determined.
    fn why_not(&self, k: usize, rel: f64) -> String {
        let Solution {
            active,
            norms,
            x,
            sd,
            cov,
            level_change,
            before,
            ..
        } = self;
        let p = active.len();
        let j = active[k];
        // The joints it is confused with: correlation of the estimates above 0.9.
        let partners: Vec<String> = (0..p)
            .filter(|&m| m != k)
            .filter_map(|m| {
                let r = cov[(k, m)] / (cov[(k, k)] * cov[(m, m)]).sqrt();
                (r.is_finite() && r.abs() > 0.9)
                    .then(|| format!("joint {} (correlation {:.3})", active[m] + 1, r))
            })
            .collect();
        let mut with = if partners.is_empty() {
            String::new()
        } else {
            format!(
                "; its column is nearly parallel to those of {}",
                partners.join(", ")
            )
        };
        let change = level_change[k] / norms[j] / x[k].abs();
        if change.abs() > REL_LIMIT && level_change[k].abs() > 3.0 * before[k] {
            with += &format!(
                "; from the upper half of the loads it comes out {:+.0} % against the lower half (the compliance is not linear in the load)",
                change * 100.0
            );
        }
        if x[k] <= 0.0 {
            format!(
                "not determined by this circle: the fit gives a non-positive compliance ({:.3e} ± {:.1e} rad/(N·m)){with}",
                x[k], sd[k]
            )
        } else if rel.is_finite() {
            format!(
                "not determined by this circle: relative uncertainty {:.0} % > {:.0} %{with}",
                rel * 100.0,
                REL_LIMIT * 100.0
            )
        } else {
            format!(
                "not determined by this circle: its column lies in the span of the others{with}"
            )
        }
    }

    /// The determined combinations of the `undetermined` joints (indices into `active`).
    fn combinations(&self, undetermined: &[usize]) -> Vec<Combination> {
        let Solution {
            active,
            norms,
            x,
            cov,
            ..
        } = self;
        let mut combinations = Vec::new();
        let m = undetermined.len();
        let sub = DMatrix::from_fn(m, m, |i, j| cov[(undetermined[i], undetermined[j])]);
        if sub.iter().all(|v| v.is_finite()) {
            let eig = SymmetricEigen::new(sub);
            let mut order: Vec<usize> = (0..m).collect();
            order.sort_by(|&i, &j| eig.eigenvalues[i].total_cmp(&eig.eigenvalues[j]));
            for &e in &order {
                let v = eig.eigenvectors.column(e);
                // Weights on the compliances: Σ v_i xs_i = Σ (v_i ||a_i||) x_i.
                let w: Vec<f64> = (0..m)
                    .map(|i| v[i] * norms[active[undetermined[i]]])
                    .collect();
                let wmax = w
                    .iter()
                    .fold(0.0f64, |b, x| if x.abs() > b.abs() { *x } else { b });
                if wmax == 0.0 {
                    continue;
                }
                let w: Vec<f64> = w.iter().map(|x| x / wmax).collect();
                let value: f64 = (0..m).map(|i| w[i] * x[undetermined[i]]).sum();
                let std = eig.eigenvalues[e].max(0.0).sqrt() / wmax.abs();
                if !(value > 0.0 && std / value <= REL_LIMIT) {
                    continue;
                }
                // Every weight stays: a small weight on a soft joint still counts.
                let keep: Vec<usize> = (0..m).collect();
                combinations.push(Combination {
                    joints: keep.iter().map(|&i| active[undetermined[i]] + 1).collect(),
                    weights: keep.iter().map(|&i| w[i]).collect(),
                    compliance_rad_per_nm: value,
                    std_rad_per_nm: std,
                    effective_stiffness_nm_per_rad: keep
                        .iter()
                        .all(|&i| w[i] > 0.0)
                        .then(|| 1.0 / value),
                });
            }
        }
        combinations
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A synthetic regressor: joints 1 and 2 independent, 3 a near copy of 2, 6 without lever.
    fn rows(n: usize) -> Vec<[f64; 6]> {
        (0..n)
            .map(|k| {
                let t = k as f64 * std::f64::consts::TAU / n as f64;
                let a = 1.0 + 0.5 * t.cos();
                let b = 0.6 + 0.4 * (2.0 * t).sin();
                [
                    a,
                    b,
                    0.5 * b * (1.0 + 1e-4 * t.sin()),
                    0.3 + 0.2 * (t + 0.3).sin().powi(2),
                    0.2 + 0.1 * t.sin(),
                    0.0,
                ]
            })
            .collect()
    }

    #[test]
    fn determines_the_independent_joints_and_names_the_rest() {
        let r = rows(360);
        let x = [
            1.0 / 8e6,
            1.0 / 5e6,
            1.0 / 4e6,
            1.0 / 1e6,
            1.0 / 1.5e6,
            1.0 / 5e5,
        ];
        let c: Vec<f64> = r
            .iter()
            .map(|row| (0..6).map(|i| row[i] * x[i]).sum())
            .collect();
        let s = identify(&r, &c, &[], None);
        let k1 = s.stiffness_nm_per_rad[0].unwrap();
        assert!((k1 / 8e6 - 1.0).abs() < 1e-6, "{k1}");
        assert!(s.stiffness_nm_per_rad[3].is_some() && s.stiffness_nm_per_rad[4].is_some());
        assert!(s.stiffness_nm_per_rad[1].is_none() && s.stiffness_nm_per_rad[2].is_none());
        assert!(s.why[5].as_deref().unwrap().starts_with("no lever"));
        assert!(
            s.why[1].as_deref().unwrap().contains("joint 3"),
            "{:?}",
            s.why[1]
        );
        // Their combination is determined: x2 + 0.5·x3 (columns a2 and 0.5·a2).
        let comb = &s.combinations[0];
        assert_eq!(comb.joints, vec![2, 3]);
        let want = x[1] * comb.weights[0] + x[2] * comb.weights[1];
        assert!((comb.compliance_rad_per_nm / want - 1.0).abs() < 1e-6);
        assert!(
            (comb.weights[1] / comb.weights[0] - 0.5).abs() < 1e-3,
            "{:?}",
            comb.weights
        );
    }
}
