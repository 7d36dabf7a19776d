//! Steps in the residual: in = a fitted problem (its estimate and free columns); out = the row
//! where a fixture most likely moved and the row where the length zero most likely changed
//! (a slipped fixture, a re-zeroed bar), each with the residual sum of squares a new fixture
//! or zero from there on would remove. No file I/O.
//!
//! For a split at row s of a group (rows a..b), the new parameters' columns X₂ are the fixture
//! columns (or ones) on rows s..b. With the model's columns X₁ already fitted, the sum of
//! squares they remove is gᵀS⁻¹g, g = X₂ᵀr − X₂ᵀX₁N₁₁⁻¹X₁ᵀr and S = X₂ᵀX₂ − X₂ᵀX₁N₁₁⁻¹X₁ᵀX₂:
//! the new columns net of what the model already explains. Suffix sums over s make every
//! split cost one small solve; long groups are scanned on a grid and refined around the best.

use super::fit::{inverse, model_cols, rows_of, Col, Estimate, Param, Problem};
use crate::twin::measured::Form;
use nalgebra::{DMatrix, DVector};

/// The best split of one kind.
#[derive(Clone, Debug, PartialEq)]
pub struct Split {
    /// True: a new fixture position; false: a new length zero.
    pub fixture: bool,
    /// First row (of the concatenated problem) of the new segment.
    pub at: usize,
    /// One past the last row of the new segment (the end of the group it splits).
    pub to: usize,
    /// Weighted sum of squares the new parameters remove (m²).
    pub gain: f64,
}

/// Fewest rows a segment may have: a fixture needs its three coordinates well seen, a zero
/// its one.
pub const MIN_FIXTURE_ROWS: usize = 24;
pub const MIN_OFFSET_ROWS: usize = 8;
/// Splits evaluated per group before refining around the best.
const GRID: usize = 2000;

/// The best fixture split and the best length-zero split over every group, where one exists.
pub fn scan(problem: &Problem, est: &Estimate, free: &[Param]) -> Vec<Split> {
    let n = problem.rows();
    let base = model_cols(est, free);
    let c1 = base.len();
    let mut cols = base;
    cols.extend((0..3).map(|axis| Col::StepFix {
        from: 0,
        to: n,
        axis,
    }));
    cols.push(Col::StepOff { from: 0, to: n });
    let c = cols.len();
    let (xs, rs, _) = rows_of(problem, est, &cols);
    let x1 = |k: usize| &xs[k * c..k * c + c1];
    // N₁₁⁻¹ and X₁ᵀr over every row.
    let mut n11 = DMatrix::zeros(c1, c1);
    let mut b1 = DVector::zeros(c1);
    for k in 0..n {
        let x = x1(k);
        for a in 0..c1 {
            if x[a] == 0.0 {
                continue;
            }
            b1[a] += x[a] * rs[k];
            for bb in a..c1 {
                n11[(a, bb)] += x[a] * x[bb];
            }
        }
    }
    for a in 0..c1 {
        for bb in 0..a {
            n11[(a, bb)] = n11[(bb, a)];
        }
    }
    let kinv = inverse(&n11);
    let kb1 = &kinv * &b1;
    let mut out = Vec::new();
    for fixture in [true, false] {
        let (extra, min): (Vec<usize>, usize) = if fixture {
            ((c1..c1 + 3).collect(), MIN_FIXTURE_ROWS)
        } else {
            (vec![c1 + 3], MIN_OFFSET_ROWS)
        };
        let groups = if fixture {
            &problem.fix_groups
        } else {
            &problem.off_groups
        };
        let mut best: Option<Split> = None;
        for g in groups {
            let (a, b) = (g.rows.start, g.rows.end);
            let kept: Vec<usize> = (a..b).filter(|&k| problem.weight[k] > 0.0).collect();
            // A continuous recording's segment lasts at least 5 % of the run: a fault is a
            // change that stays, not a transient a few samples long.
            let min = if problem.forms[g.run] == Form::Continuous {
                min.max(problem.ranges[g.run].len() / 20)
            } else {
                min
            };
            if kept.len() < 2 * min {
                continue;
            }
            // Candidate splits: at kept rows, leaving `min` kept rows on either side.
            let lo = kept[min];
            let hi = kept[kept.len() - min];
            let stride = ((hi - lo) / GRID).max(1);
            let gain_at = |grid: &dyn Fn(usize) -> bool| -> Option<(usize, f64)> {
                let p = extra.len();
                let mut s12 = DMatrix::zeros(c1, p);
                let mut s22 = DMatrix::zeros(p, p);
                let mut g2 = DVector::zeros(p);
                let mut top: Option<(usize, f64)> = None;
                for s in (lo..b).rev() {
                    let row = &xs[s * c..s * c + c];
                    for (i, &e) in extra.iter().enumerate() {
                        let v = row[e];
                        if v == 0.0 {
                            continue;
                        }
                        g2[i] += v * rs[s];
                        for (i2, &e2) in extra.iter().enumerate() {
                            s22[(i, i2)] += v * row[e2];
                        }
                        for a1 in 0..c1 {
                            s12[(a1, i)] += row[a1] * v;
                        }
                    }
                    if s > hi || !grid(s) || problem.weight[s] <= 0.0 {
                        continue;
                    }
                    let t = &kinv * &s12;
                    let sch = &s22 - s12.transpose() * &t;
                    let geff = &g2 - s12.transpose() * &kb1;
                    let gain = geff.dot(&(inverse(&sch) * &geff));
                    if gain.is_finite() && top.is_none_or(|(_, v)| gain > v) {
                        top = Some((s, gain));
                    }
                }
                top
            };
            let Some((coarse, _)) = gain_at(&|s| (s - lo) % stride == 0) else {
                continue;
            };
            let (from, to) = (coarse.saturating_sub(stride), coarse + stride);
            let refined = if stride > 1 {
                gain_at(&|s| s >= from && s <= to)
            } else {
                gain_at(&|s| s == coarse)
            };
            if let Some((at, gain)) = refined {
                if best.as_ref().is_none_or(|bs| gain > bs.gain) {
                    best = Some(Split {
                        fixture,
                        at,
                        to: b,
                        gain,
                    });
                }
            }
        }
        out.extend(best);
    }
    out
}
