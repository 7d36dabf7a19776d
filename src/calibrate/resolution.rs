//! Reading noise as it is: in = a campaign's runs, the joints' logged resolution (given, or
//! found in the logged values) and a first fit's residual; out = each reading's standard
//! uncertainty, the instrument's noise combined with what rounding the joints to their
//! resolution does to the length there, to weight the fit.
//!
//! A joint logged to 0.1° moves the tool ball by up to 0.9 mm on a 1 m arm before the
//! reading says so: rounding to a step g is uniform error of variance g²/12 on each joint, and
//! the length sees Σⱼ (∂L/∂qⱼ)²·gⱼ²/12 of it, which depends on the pose (nothing where the bar
//! points along the joint's axis, most where it is tangent to the joint's circle). Readings
//! where the rounding matters less are worth more.

use super::{round, Calibration, ReadingWeights};
use crate::diagnose::Run;
use crate::model::{MeasurementModel, Params};
use crate::twin::Measured;
use crate::units::DEG;

/// Grid steps a controller or logger rounds joint angles to (deg), coarse to fine.
const STEPS_DEG: [f64; 9] = [1.0, 0.5, 0.1, 0.05, 0.01, 0.005, 0.001, 0.0005, 0.0001];

/// A joint needs this many distinct logged values for its grid to be read from them.
const DISTINCT: usize = 10;

/// Weighting pays when the readings' uncertainties differ by more than this ratio (RMS of the
/// larger half over the smaller); below it the fit is the same.
const SPREAD: f64 = 1.2;

/// The campaign's runs with every reading's standard uncertainty set, and how they were
/// weighted; `None` when weighting would not change the fit (no joint logged on a grid, the
/// uncertainties nearly equal) or the residual of the first fit `first` contradicts a grid read
/// from the values. `given`: the joints' step (rad) for every run, else read per run.
pub(super) fn reweighted(
    model: &MeasurementModel,
    runs: &[Run],
    first: &Calibration,
    given: Option<f64>,
) -> Option<(Vec<Measured>, ReadingWeights)> {
    let steps: Vec<[f64; 6]> = runs
        .iter()
        .map(|r| given.map_or_else(|| detect(r.measured), |g| [g; 6]))
        .collect();
    if steps.iter().flatten().all(|g| *g == 0.0) {
        return None;
    }
    let rounding: Vec<Vec<f64>> = runs
        .iter()
        .zip(&steps)
        .enumerate()
        .map(|(k, (r, s))| rounding_std(model, &first.estimate.params(k), r.measured, s))
        .collect();
    let all: Vec<f64> = rounding.iter().flatten().copied().collect();
    let rounding_rms = (all.iter().map(|x| x * x).sum::<f64>() / all.len().max(1) as f64).sqrt();
    // A grid read from the values may be the poses' own (a program's targets in whole
    // degrees, a designed grid), not a logger's rounding: the residual then says so, being
    // far below what such rounding would leave.
    if given.is_none() && rounding_rms > 1.5 * instrument_noise(&first.residual, &[]) {
        return None;
    }
    // The instrument's noise where no run states it: the residual of those runs less the
    // rounding's share.
    let (res, rnd): (Vec<f64>, Vec<f64>) = runs
        .iter()
        .enumerate()
        .filter(|(_, r)| r.measured.std.is_none())
        .flat_map(|(k, _)| {
            first.ranges[k]
                .clone()
                .zip(&rounding[k])
                .map(|(i, q)| (first.residual[i], *q))
        })
        .unzip();
    let noise = instrument_noise(&res, &rnd);
    let combined: Vec<f64> = runs
        .iter()
        .zip(&rounding)
        .flat_map(|(r, rk)| {
            let stated = r.measured.std.as_deref();
            rk.iter()
                .enumerate()
                .map(move |(i, q)| q.hypot(stated.map_or(noise, |s| s[i])))
        })
        .collect();
    let std = reading_std(&combined, 0.0)?;
    let mut at = 0;
    let weighted = runs
        .iter()
        .map(|r| {
            let mut m = r.measured.clone();
            m.std = Some(std[at..at + m.len()].to_vec());
            at += m.len();
            m
        })
        .collect();
    let how = ReadingWeights {
        joint_resolution_deg: steps.iter().map(|s| s.map(|g| round(g / DEG, 6))).collect(),
        instrument_noise_um: (!res.is_empty()).then(|| round(noise * 1e6, 3)),
        rounding_rms_um: round(rounding_rms * 1e6, 3),
        rounding_max_um: round(all.iter().fold(0.0f64, |a, &b| a.max(b)) * 1e6, 3),
    };
    Some((weighted, how))
}

/// The step each joint's logged values lie on (rad), 0 where they lie on none of the usual
/// logging steps, 1° to 0.0001° (logged finer, or computed). A joint with too few distinct
/// values (it hardly moved) takes the finest step of the others.
pub fn detect(m: &Measured) -> [f64; 6] {
    let mut out = [f64::NAN; 6];
    for (j, step) in out.iter_mut().enumerate() {
        let deg: Vec<f64> = m.q.iter().map(|q| q[j] / DEG).collect();
        let mut distinct = deg.clone();
        distinct.sort_by(f64::total_cmp);
        distinct.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
        if distinct.len() < DISTINCT {
            continue;
        }
        *step = STEPS_DEG
            .iter()
            .find(|&&g| deg.iter().all(|v| ((v / g) - (v / g).round()).abs() < 1e-6))
            .map_or(0.0, |g| g * DEG);
    }
    let finest = out
        .iter()
        .filter(|s| s.is_finite())
        .fold(f64::INFINITY, |a, &s| a.min(s));
    out.map(|s| {
        if s.is_finite() {
            s
        } else if finest.is_finite() {
            finest
        } else {
            0.0
        }
    })
}

/// Per reading, the standard uncertainty (m) joint rounding to `steps` (rad) adds to the
/// length at parameters `p`: √(Σⱼ (∂L/∂qⱼ)²·gⱼ²/12), ∂L/∂qⱼ by central differences.
pub fn rounding_std(
    model: &MeasurementModel,
    p: &Params,
    m: &Measured,
    steps: &[f64; 6],
) -> Vec<f64> {
    let h = 1e-6;
    m.q.iter()
        .map(|q| {
            (0..6)
                .filter(|&j| steps[j] > 0.0)
                .map(|j| {
                    let (mut a, mut b) = (*q, *q);
                    a[j] += h;
                    b[j] -= h;
                    let d = (model.length(p, &a) - model.length(p, &b)) / (2.0 * h);
                    d * d * steps[j] * steps[j] / 12.0
                })
                .sum::<f64>()
                .sqrt()
        })
        .collect()
}

/// Each reading's standard uncertainty (m): the instrument's noise `noise` (m) and the
/// rounding's, combined; `None` when weighting would not change the fit (the uncertainties
/// nearly equal).
pub fn reading_std(rounding: &[f64], noise: f64) -> Option<Vec<f64>> {
    let std: Vec<f64> = rounding.iter().map(|r| r.hypot(noise)).collect();
    let mut sorted = std.clone();
    sorted.sort_by(f64::total_cmp);
    let half = sorted.len() / 2;
    if half == 0 {
        return None;
    }
    let ms = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64;
    let (lo, hi) = (ms(&sorted[..half]), ms(&sorted[half..]));
    (lo > 0.0 && (hi / lo).sqrt() > SPREAD).then_some(std)
}

/// The median of a χ² variable of one degree of freedom: a normal residual's median square
/// over its mean square.
const CHI2_MEDIAN: f64 = 0.454_936;

/// The instrument's noise (m) from a fit's residual and the rounding's share: the residual's
/// mean square (from its median square, so that outliers the fit dropped do not count) less
/// the rounding's, never below a tenth of the residual's RMS (the residual also holds what the
/// model misses, which weighs like noise).
pub fn instrument_noise(residual: &[f64], rounding: &[f64]) -> f64 {
    let mut sq: Vec<f64> = residual.iter().map(|r| r * r).collect();
    if sq.is_empty() {
        return 0.0;
    }
    let mid = sq.len() / 2;
    let (_, median, _) = sq.select_nth_unstable_by(mid, f64::total_cmp);
    let rr = *median / CHI2_MEDIAN;
    let qq = rounding.iter().map(|r| r * r).sum::<f64>() / rounding.len().max(1) as f64;
    if qq == 0.0 {
        return rr.sqrt();
    }
    (rr - qq).max(0.01 * rr).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::tests::nj130;

    fn measured(q: Vec<[f64; 6]>) -> Measured {
        Measured {
            t: (0..q.len()).map(|k| k as f64).collect(),
            length: vec![0.4; q.len()],
            q,
            ..Measured::default()
        }
    }

    #[test]
    fn the_grid_of_logged_joints_is_read_from_their_values() {
        // Joints 1-5 to 0.1°, joint 6 to 0.001°, from values as a CSV carries them.
        let q: Vec<[f64; 6]> = (0..40)
            .map(|k| {
                let k = k as f64;
                let mut q = [0.0; 6];
                for (j, v) in q.iter_mut().enumerate().take(5) {
                    *v = ((k * 1.7 + j as f64 * 13.1) % 90.0 * 10.0).round() / 10.0 * DEG;
                }
                q[5] = (k * 2.718_23_f64 * 1000.0).round() / 1000.0 * DEG;
                q
            })
            .collect();
        let s = detect(&measured(q));
        for (j, step) in s.iter().enumerate().take(5) {
            assert!(
                (step / DEG - 0.1).abs() < 1e-12,
                "joint {}: {}",
                j + 1,
                step / DEG
            );
        }
        assert!((s[5] / DEG - 0.001).abs() < 1e-12, "{}", s[5] / DEG);
    }

    #[test]
    fn a_joint_that_hardly_moved_takes_the_finest_step_and_computed_angles_none() {
        let q: Vec<[f64; 6]> = (0..40)
            .map(|k| {
                let k = k as f64;
                [k * 0.5 * DEG, 10.0 * DEG, k.sqrt() * DEG, 0.0, 0.0, 0.0]
            })
            .collect();
        let s = detect(&measured(q));
        assert!((s[0] / DEG - 0.5).abs() < 1e-12);
        assert_eq!(s[2], 0.0, "a computed angle lies on no grid");
        assert_eq!(s[1], 0.0, "the finest of the others: joint 3's none");
    }

    #[test]
    fn the_rounding_share_matches_a_brute_force_rounding_of_the_joints() {
        // The predicted std against the length spread of random roundings (uniform ±g/2 on
        // every joint) at one pose of the NJ-130.
        use rand::{Rng, SeedableRng};
        let robot = nj130();
        let model = MeasurementModel::new(
            &robot,
            nalgebra::Vector3::new(0.258, 1.468, 0.708),
            nalgebra::Vector3::new(0.06, 0.03, 0.12),
        );
        let q = [0.3, 0.2, -0.4, 0.5, 0.6, -0.7];
        let g = 0.1 * DEG;
        let std = rounding_std(&model, &model.nominal, &measured(vec![q]), &[g; 6])[0];
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let l0 = model.length(&model.nominal, &q);
        let n = 20000;
        let ms = (0..n)
            .map(|_| {
                let x = q.map(|v| v + rng.random_range(-0.5..0.5) * g);
                (model.length(&model.nominal, &x) - l0).powi(2)
            })
            .sum::<f64>()
            / n as f64;
        assert!(
            (ms.sqrt() / std - 1.0).abs() < 0.03,
            "{} vs {}",
            ms.sqrt(),
            std
        );
    }

    #[test]
    fn the_instrument_noise_is_what_the_residual_leaves_beyond_the_rounding_outliers_aside() {
        // Normal noise of 2 with rounding of 1.5 (RMS), and a few huge outliers.
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let n = 4000;
        let rounding = vec![1.5; n];
        // Box-Muller: normal of standard deviation 2.5 = √(2² + 1.5²).
        let mut r: Vec<f64> = (0..n)
            .map(|_| {
                let (u, v): (f64, f64) = (rng.random_range(1e-12..1.0), rng.random());
                2.5 * (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
            })
            .collect();
        for k in 0..20 {
            r[k * 150] = 1e3;
        }
        let noise = instrument_noise(&r, &rounding);
        assert!((noise - 2.0).abs() < 0.1, "{noise}");
    }

    #[test]
    fn equal_uncertainties_do_not_weight_and_unequal_ones_do() {
        assert!(reading_std(&[1e-5; 100], 1e-5).is_none());
        let r: Vec<f64> = (0..100).map(|k| k as f64 * 1e-6).collect();
        let s = reading_std(&r, 5e-6).expect("weights");
        assert!((s[0] - 5e-6).abs() < 1e-12 && (s[99] - 99e-6f64.hypot(5e-6)).abs() < 1e-12);
    }
}
