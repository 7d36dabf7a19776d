//! A start for the set-up that needs none: in = a problem, an estimate (the robot's geometry
//! and the given set-up) and the set-up parameters that are free (the MAP, each run's fixture
//! and length zero); out = the estimate with the set-up fitted to the nominal robot, from
//! whichever start explains the readings better. No file I/O.
//!
//! A tool point given tens of millimetres off, or a draw-wire's anchor and zero unknown, put
//! the Gauss-Newton fit far outside the region where its linearisation holds. The length
//! equation has an algebraic form that is linear in new unknowns and needs no start: with the
//! flange pose (R_k, t_k) of reading k, the MAP m in the flange frame, the fixture F and the
//! zero c (reading ℓ_k = ‖R_k m + t_k − F‖ + c),
//!
//! ℓ_k² − ‖t_k‖² = a₀ + 2 (R_kᵀ t_k)·m − 2 t_k·F − 2 Σᵢⱼ (R_k)ᵢⱼ Mᵢⱼ + 2 c ℓ_k,
//!
//! with a₀ = ‖m‖² + ‖F‖² − c² and M = F mᵀ taken as independent unknowns (17 per run; m is
//! shared). Least squares on it gives m, F and c; Levenberg-Marquardt on the set-up from that
//! start and from the given values, and the one with the smaller median absolute residual wins
//! (zero jumps and outliers do not steer the choice).

use super::fit::{inverse, refit, Estimate, Param, Problem};
use crate::model::MAP;
use crate::robot::kinematics::chain_frames;
use nalgebra::{DMatrix, DVector, Vector3};

/// Rows the algebraic solution and the start's fits use at most.
const START_ROWS: usize = 4000;

/// Fits the free set-up parameters `setup` (MAP, fixtures, length zeros; the robot held) from
/// the better of two starts; `est` keeps the result.
pub fn setup(problem: &Problem, est: &mut Estimate, setup: &[Param]) {
    if setup.is_empty() {
        return;
    }
    let thin = problem.thinned(START_ROWS);
    let mut best: Option<(f64, Estimate)> = None;
    let mut starts = vec![est.clone()];
    if let Some(a) = algebraic(&thin, est, setup) {
        starts.push(a);
    }
    for mut s in starts {
        refit(&thin, &mut s, setup);
        let cost = median_abs(&thin.residual(&s), &thin.weight);
        if cost.is_finite() && best.as_ref().is_none_or(|b| cost < b.0) {
            best = Some((cost, s));
        }
    }
    if let Some((_, s)) = best {
        for &q in setup {
            est.set(q, s.get(q));
        }
    }
}

fn median_abs(r: &[f64], weight: &[f64]) -> f64 {
    let mut v: Vec<f64> = r
        .iter()
        .zip(weight)
        .filter(|(_, w)| **w > 0.0)
        .map(|(x, _)| x.abs())
        .collect();
    if v.is_empty() {
        return f64::INFINITY;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// The algebraic solution (see the module doc) for the free set-up parameters, the others at
/// their current values; None when it is not determined or absurd.
fn algebraic(problem: &Problem, est: &Estimate, setup: &[Param]) -> Option<Estimate> {
    let map_free = (0..3).all(|a| setup.contains(&Param::Shared(MAP + a)));
    let groups = problem.fix_groups.len();
    // Column layout: [m (3, when free)] then per fixture group: a₀, F (3), M (9), c.
    let mut layout = Vec::new();
    let mut next = if map_free { 3 } else { 0 };
    for g in 0..groups {
        let f_free = (0..3).all(|axis| setup.contains(&Param::Fixture { group: g, axis }));
        // The length zero of the rows: one offset group per fixture group at the start.
        let og = problem
            .off_groups
            .iter()
            .position(|h| h.rows == problem.fix_groups[g].rows);
        let c_free = og.is_some_and(|o| setup.contains(&Param::Offset { group: o }));
        let a0 = next;
        next += 1;
        let f = f_free.then(|| {
            next += 3;
            next - 3
        });
        let mm = (f_free && map_free).then(|| {
            next += 9;
            next - 9
        });
        let c = c_free.then(|| {
            next += 1;
            next - 1
        });
        layout.push((a0, f, mm, c, og));
    }
    let cols = next;
    let mut n = DMatrix::<f64>::zeros(cols, cols);
    let mut b = DVector::<f64>::zeros(cols);
    let mut x = vec![0.0; cols];
    let p = est.params(0);
    for k in 0..problem.rows() {
        if problem.weight[k] <= 0.0 {
            continue;
        }
        let g = problem.fixture_group_of(k);
        let (a0, f, mm, c, og) = layout[g];
        let frames = chain_frames(
            &problem.model.base,
            &p.dh,
            &problem.model.flange,
            &problem.m.q[k],
        );
        let (r, t) = (frames[7].r, frames[7].t);
        let fix = est.fixtures[g];
        let m = Vector3::new(est.p[MAP], est.p[MAP + 1], est.p[MAP + 2]);
        let ell = problem.m.length[k];
        let zero = og.map_or(0.0, |o| est.offsets[o]);
        x.iter_mut().for_each(|v| *v = 0.0);
        // Left side with the known parts moved over.
        let reading = if c.is_some() { ell } else { ell - zero };
        let mut rhs = reading * reading;
        x[a0] = 1.0;
        match (map_free, f) {
            (true, Some(fi)) => {
                rhs -= t.norm_squared();
                let rt = r.transpose() * t;
                for a in 0..3 {
                    x[a] = 2.0 * rt[a];
                    x[fi + a] = -2.0 * t[a];
                }
                let mi = mm.unwrap_or(0);
                for i in 0..3 {
                    for j in 0..3 {
                        x[mi + 3 * i + j] = -2.0 * r[(i, j)];
                    }
                }
            }
            (true, None) => {
                // F known: ‖Rm + t − F‖² = ‖m‖² + ‖t − F‖² + 2 (Rᵀ(t − F))·m.
                let d = t - fix;
                rhs -= d.norm_squared();
                let rt = r.transpose() * d;
                for a in 0..3 {
                    x[a] = 2.0 * rt[a];
                }
            }
            (false, Some(fi)) => {
                // m known: ‖P − F‖² = ‖P‖² − 2 P·F + ‖F‖².
                let pk = r * m + t;
                rhs -= pk.norm_squared();
                for a in 0..3 {
                    x[fi + a] = -2.0 * pk[a];
                }
            }
            (false, None) => {
                let pk = r * m + t;
                rhs -= (pk - fix).norm_squared();
            }
        }
        if let Some(ci) = c {
            x[ci] = 2.0 * ell;
        }
        for a in 0..cols {
            if x[a] == 0.0 {
                continue;
            }
            b[a] += x[a] * rhs;
            for bb in a..cols {
                n[(a, bb)] += x[a] * x[bb];
            }
        }
    }
    for a in 0..cols {
        for bb in 0..a {
            n[(a, bb)] = n[(bb, a)];
        }
    }
    let sol = inverse(&n) * b;
    if sol.iter().any(|v| !v.is_finite()) {
        return None;
    }
    let mut out = est.clone();
    if map_free {
        let m = Vector3::new(sol[0], sol[1], sol[2]);
        if m.norm() > 5.0 {
            return None;
        }
        for a in 0..3 {
            out.p[MAP + a] = m[a];
        }
    }
    for (g, &(_, f, _, c, og)) in layout.iter().enumerate() {
        if let Some(fi) = f {
            let fix = Vector3::new(sol[fi], sol[fi + 1], sol[fi + 2]);
            if fix.norm() > 100.0 {
                return None;
            }
            out.fixtures[g] = fix;
        }
        if let (Some(ci), Some(o)) = (c, og) {
            if sol[ci].abs() > 100.0 {
                return None;
            }
            out.offsets[o] = sol[ci];
        }
    }
    Some(out)
}
