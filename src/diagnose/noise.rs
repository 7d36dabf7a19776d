//! Reading noise: in = a problem's runs (their form, joints, stated uncertainties) and a
//! residual; out = the standard deviation of one reading that the model cannot be asked to
//! explain, and what it was estimated from ([`Noise`]).
//!
//! Why not the residual's successive differences alone: along a continuous recording (rows in
//! time, the robot moving a little between them) they are the high-frequency part of the
//! residual, the instrument's; but static readings are poses in whatever order they were
//! taken, often far apart in joint space, and there successive differences are the robot's
//! systematic error itself. For static runs the noise comes, in this order, from the
//! instrument's statement (a flag), the readings' own stated uncertainties (a plateau's
//! standard error), poses measured twice, or the nearest poses in joint space (an upper bound:
//! the robot's error changes a little between them). When none of these exists the data do not
//! separate noise from the robot's error, and the noise is reported unknown.

use super::fit::{noise_estimate, Problem};
use crate::stats::median_in_place;
use crate::twin::measured::Form;
use serde::Serialize;

/// Where a reading-noise figure comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum NoiseSource {
    /// The instrument as the user states it (`--noise`).
    Given,
    /// The readings' own standard uncertainties (the static form's `std_um`, a plateau's
    /// standard error).
    Stated,
    /// A continuous recording: the high-frequency part of the residual along time.
    Sequence,
    /// Poses measured more than once (joints within [`TIERS_DEG`]'s first step): the spread of
    /// their readings.
    Repeats,
    /// The nearest poses in joint space: an upper bound, since the robot's error changes a
    /// little between them.
    Neighbours,
    /// Static readings without repeats or close neighbours: nothing in the data separates the
    /// noise from the robot's error.
    Unknown,
}

impl NoiseSource {
    /// The phrase a summary prints after the figure.
    pub fn describe(&self, within_deg: f64) -> String {
        match self {
            NoiseSource::Given => "as given".into(),
            NoiseSource::Stated => "the readings' stated uncertainties".into(),
            NoiseSource::Sequence => "high-frequency part of the residual".into(),
            NoiseSource::Repeats => "poses measured twice".into(),
            NoiseSource::Neighbours => {
                format!("an upper bound, from the nearest poses in joint space, within {within_deg}°")
            }
            NoiseSource::Unknown => {
                "unknown: static readings without repeated or neighbouring poses; state the instrument's with --noise".into()
            }
        }
    }
}

/// One reading's noise (m, along the bar) and its source. `sigma` is 0 when unknown.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Noise {
    pub sigma: f64,
    pub source: NoiseSource,
    /// For [`NoiseSource::Neighbours`] and [`NoiseSource::Repeats`]: the largest joint
    /// distance (deg, the largest joint's difference) of a pair used.
    pub within_deg: f64,
}

impl Noise {
    pub fn known(&self) -> bool {
        self.source != NoiseSource::Unknown
    }

    /// The figure a test against the noise uses: the noise when known, else `fallback` (a
    /// caller's conservative stand-in, e.g. 0 to count every excess).
    pub fn or(&self, fallback: f64) -> f64 {
        if self.known() {
            self.sigma
        } else {
            fallback
        }
    }
}

/// Joint distances (deg, the largest joint's difference) within which two static poses count
/// as the same pose measured twice (the first step) or as neighbours: the first step with at
/// least [`MIN_PAIRS`] pairs is used, the closest pairs being the least contaminated by the
/// robot's error.
pub const TIERS_DEG: [f64; 4] = [0.001, 0.1, 0.3, 1.0];

/// Pairs of poses a tier needs before it gives a noise figure.
pub const MIN_PAIRS: usize = 30;

/// The pairs of nearest static poses of a problem, found once (they do not depend on the
/// residual): per static run, each row's nearest other row within the last tier.
#[derive(Clone, Debug, Default)]
pub struct Neighbours {
    /// Per run: (row, row, joint distance in deg), each pair once.
    pairs: Vec<Vec<(usize, usize, f64)>>,
}

impl Neighbours {
    pub fn new(problem: &Problem) -> Self {
        let reach = TIERS_DEG[TIERS_DEG.len() - 1].to_radians();
        let pairs = problem
            .ranges
            .iter()
            .zip(&problem.forms)
            .map(|(range, form)| {
                if !matches!(form, Form::Static { .. }) {
                    return Vec::new();
                }
                let q = &problem.m.q[range.clone()];
                nearest_pairs(q, reach)
                    .into_iter()
                    .map(|(a, b, d)| (range.start + a, range.start + b, d.to_degrees()))
                    .collect()
            })
            .collect();
        Neighbours { pairs }
    }
}

/// Each pose's nearest other pose within `reach` (rad, Chebyshev distance over the joints),
/// as pairs (i < j, distance), each once, in a deterministic order.
fn nearest_pairs(q: &[[f64; 6]], reach: f64) -> Vec<(usize, usize, f64)> {
    let n = q.len();
    if n < 2 {
        return Vec::new();
    }
    // Sweep along the joint with the widest spread: only rows within `reach` of it can pair.
    let spread = |j: usize| {
        let (lo, hi) = q.iter().fold((f64::MAX, f64::MIN), |(lo, hi), r| {
            (lo.min(r[j]), hi.max(r[j]))
        });
        hi - lo
    };
    let axis = (0..6)
        .max_by(|&a, &b| spread(a).total_cmp(&spread(b)))
        .unwrap_or(0);
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| q[a][axis].total_cmp(&q[b][axis]).then(a.cmp(&b)));
    let mut best = vec![(f64::INFINITY, usize::MAX); n];
    for (p, &i) in order.iter().enumerate() {
        for &j in &order[p + 1..] {
            if q[j][axis] - q[i][axis] > reach {
                break;
            }
            let d = (0..6).fold(0.0f64, |m, k| m.max((q[i][k] - q[j][k]).abs()));
            if d <= reach {
                if d < best[i].0 {
                    best[i] = (d, j);
                }
                if d < best[j].0 {
                    best[j] = (d, i);
                }
            }
        }
    }
    let mut pairs: Vec<(usize, usize, f64)> = best
        .iter()
        .enumerate()
        .filter(|(_, (_, j))| *j != usize::MAX)
        .map(|(i, &(d, j))| (i.min(j), i.max(j), d))
        .collect();
    pairs.sort_by_key(|p| (p.0, p.1));
    pairs.dedup_by(|a, b| a.0 == b.0 && a.1 == b.1);
    pairs
}

/// The reading noise of `problem`'s rows that count, for `residual` (measured − model, m):
/// `given` (the instrument's, m) when stated; otherwise per run, from its form (see the
/// module's text); pooled over the runs by their rows. `weighted`: the noise of the weighted
/// residual (each row's value, stated uncertainty and the given noise times the row's weight),
/// as the held-out sums see it.
pub fn reading_noise(
    problem: &Problem,
    neighbours: &Neighbours,
    residual: &[f64],
    given: Option<f64>,
    weighted: bool,
) -> Noise {
    if let (Some(sigma), false) = (given, weighted) {
        return Noise {
            sigma,
            source: NoiseSource::Given,
            within_deg: 0.0,
        };
    }
    let w = |k: usize| if weighted { problem.weight[k] } else { 1.0 };
    let mut sum = 0.0;
    let mut rows = 0usize;
    let mut source = NoiseSource::Unknown;
    let mut within = 0.0f64;
    let mut largest = 0usize;
    for (r, range) in problem.ranges.iter().enumerate() {
        let idx: Vec<usize> = range.clone().filter(|&k| problem.weight[k] > 0.0).collect();
        if idx.is_empty() {
            continue;
        }
        let (ms, src, tier) = if let Some(g) = given {
            let ms = idx.iter().map(|&k| (g * w(k)).powi(2)).sum::<f64>() / idx.len() as f64;
            (ms, NoiseSource::Given, 0.0)
        } else {
            match problem.forms[r] {
                Form::Continuous => {
                    let live: Vec<f64> = idx.iter().map(|&k| residual[k] * w(k)).collect();
                    (noise_estimate(&live).powi(2), NoiseSource::Sequence, 0.0)
                }
                Form::Static { .. } => {
                    let std = &problem.stated_std;
                    let stated = idx
                        .iter()
                        .all(|&k| std[k] > 0.0)
                        .then(|| {
                            median_in_place(
                                &mut idx.iter().map(|&k| std[k] * w(k)).collect::<Vec<_>>(),
                            )
                        })
                        .flatten();
                    match stated {
                        Some(s) => (s * s, NoiseSource::Stated, 0.0),
                        None => match from_pairs(problem, &neighbours.pairs[r], residual, &w) {
                            Some((s, t)) if t <= TIERS_DEG[0] => (s * s, NoiseSource::Repeats, t),
                            Some((s, t)) => (s * s, NoiseSource::Neighbours, t),
                            None => continue,
                        },
                    }
                }
            }
        };
        sum += ms * idx.len() as f64;
        rows += idx.len();
        within = within.max(tier);
        if idx.len() > largest {
            largest = idx.len();
            source = src;
        }
    }
    if rows == 0 {
        return Noise {
            sigma: 0.0,
            source: NoiseSource::Unknown,
            within_deg: 0.0,
        };
    }
    Noise {
        sigma: (sum / rows as f64).sqrt(),
        source,
        within_deg: within,
    }
}

/// The noise from the closest tier of pairs with enough of them: 1.4826 × the median of
/// |r_i − r_j| / √2 (robust: a pose that moved does not carry it), and the tier (deg).
fn from_pairs(
    problem: &Problem,
    pairs: &[(usize, usize, f64)],
    residual: &[f64],
    w: &dyn Fn(usize) -> f64,
) -> Option<(f64, f64)> {
    let live: Vec<&(usize, usize, f64)> = pairs
        .iter()
        .filter(|(i, j, _)| problem.weight[*i] > 0.0 && problem.weight[*j] > 0.0)
        .collect();
    TIERS_DEG.iter().find_map(|&tier| {
        let mut d: Vec<f64> = live
            .iter()
            .filter(|p| p.2 <= tier)
            .map(|&&(i, j, _)| (residual[i] * w(i) - residual[j] * w(j)).abs())
            .collect();
        if d.len() < MIN_PAIRS {
            return None;
        }
        median_in_place(&mut d).map(|m| (1.4826 * m / 2f64.sqrt(), tier))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The sweep finds each pose's nearest neighbour as a brute-force search does.
    #[test]
    fn the_sweep_finds_the_same_nearest_pairs_as_brute_force() {
        let mut s = 7u64;
        let mut next = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        let q: Vec<[f64; 6]> = (0..400)
            .map(|_| std::array::from_fn(|j| (next() - 0.5) * if j == 2 { 0.3 } else { 0.6 }))
            .collect();
        let reach = 0.05;
        let got = nearest_pairs(&q, reach);
        let mut want = Vec::new();
        for i in 0..q.len() {
            let mut best = (f64::INFINITY, usize::MAX);
            for j in 0..q.len() {
                if i != j {
                    let d = (0..6).fold(0.0f64, |m, k| m.max((q[i][k] - q[j][k]).abs()));
                    if d <= reach && d < best.0 {
                        best = (d, j);
                    }
                }
            }
            if best.1 != usize::MAX {
                want.push((i.min(best.1), i.max(best.1), best.0));
            }
        }
        want.sort_by_key(|p| (p.0, p.1));
        want.dedup_by(|a, b| a.0 == b.0 && a.1 == b.1);
        assert!(!want.is_empty());
        assert_eq!(got, want);
    }

    /// Static readings in scattered order, each pose measured in a small cluster of
    /// neighbours: a systematic error of 200 µm (order 17 of joint 1, as a real UR10 has) and
    /// 10 µm of noise. The neighbours give the noise; successive readings give the systematic
    /// error. Poses far apart (no neighbours) leave it unknown; a continuous run takes it
    /// from its sequence; a given noise wins.
    #[test]
    fn scattered_static_readings_take_their_noise_from_neighbouring_poses() {
        use crate::twin::Measured;
        use rand::{Rng, SeedableRng};
        let robot = crate::model::tests::nj130();
        let model = crate::model::MeasurementModel::new(
            &robot,
            nalgebra::Vector3::new(1.2, 0.0, 0.5),
            nalgebra::Vector3::zeros(),
        );
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let gauss = |rng: &mut rand_chacha::ChaCha8Rng| {
            let (u1, u2): (f64, f64) = (rng.random_range(1e-12..1.0), rng.random());
            (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
        };
        let mut q: Vec<[f64; 6]> = Vec::new();
        for _ in 0..600 {
            let c: [f64; 6] = std::array::from_fn(|_| rng.random_range(-2.0..2.0));
            for _ in 0..5 {
                q.push(std::array::from_fn(|j| {
                    c[j] + rng.random_range(-4e-4..4e-4)
                }));
            }
        }
        // Scattered: the order taken is no walk through joint space.
        for i in (1..q.len()).rev() {
            q.swap(i, rng.random_range(0..=i));
        }
        let residual: Vec<f64> = q
            .iter()
            .map(|p| 200e-6 * (17.0 * p[0]).sin() + 10e-6 * gauss(&mut rng))
            .collect();
        let problem_of = |q: &[[f64; 6]], form: Form| {
            let m = Measured {
                t: (0..q.len()).map(|i| i as f64).collect(),
                q: q.to_vec(),
                length: vec![1.0; q.len()],
                form,
                ..Measured::default()
            };
            super::super::fit::Problem::new(
                &model,
                &[super::super::fit::Run {
                    measured: &m,
                    fixture: model.nominal.fix,
                }],
            )
        };
        let static_form = Form::Static { timed: false };
        let problem = problem_of(&q, static_form);
        let nb = Neighbours::new(&problem);
        let n = reading_noise(&problem, &nb, &residual, None, false);
        assert_eq!(n.source, NoiseSource::Neighbours, "{n:?}");
        assert!((8.5e-6..=11.5e-6).contains(&n.sigma), "{n:?}");
        assert!(n.within_deg <= 0.1, "{n:?}");
        let successive = noise_estimate(&residual);
        assert!(successive > 10.0 * n.sigma, "{successive}");
        // Far-apart poses: nothing separates noise from the robot's error.
        let far: Vec<[f64; 6]> = (0..300)
            .map(|_| std::array::from_fn(|_| rng.random_range(-2.0..2.0)))
            .collect();
        let problem = problem_of(&far, static_form);
        let nb = Neighbours::new(&problem);
        let r = &residual[..far.len()];
        let n = reading_noise(&problem, &nb, r, None, false);
        assert_eq!(n.source, NoiseSource::Unknown);
        assert_eq!(n.or(0.0), 0.0);
        assert_eq!(
            reading_noise(&problem, &nb, r, Some(20e-6), false),
            Noise {
                sigma: 20e-6,
                source: NoiseSource::Given,
                within_deg: 0.0
            }
        );
        let problem = problem_of(&far, Form::Continuous);
        let n = reading_noise(&problem, &Neighbours::new(&problem), r, None, false);
        assert_eq!(n.source, NoiseSource::Sequence);
        assert!((n.sigma / noise_estimate(r) - 1.0).abs() < 1e-12);
    }
}
