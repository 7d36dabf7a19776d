//! Visiting order: in = measurement poses (joint vectors, rad), a start pose and the joint speed
//! limits (rad/s); out = [`Tour`], a time-short open path over all poses that starts at the start
//! pose (Eq. 7 cost, a travelling-salesman path with a free end).
//!
//! The cost of a move is the time of its slowest axis (Eq. 7), a weighted Chebyshev distance, so
//! it is symmetric and obeys the triangle inequality. The tour is built by nearest neighbour and
//! then improved by 2-opt, Or-opt and sequential 3-opt moves over candidate lists (`cost.rs`,
//! `local.rs`) and seeded kicks; everything is deterministic (ties go to the lowest index, work
//! queues are FIFO, no hashing, a fixed-seed generator).
//!
//! **Architecture Invariant:** no I/O, no printing, no threads whose scheduling can change the
//! result (rayon only fills the cost matrix and candidate lists, entry by entry).

mod cost;
mod local;

#[cfg(test)]
mod tests;

use serde::{Deserialize, Serialize};

pub use cost::move_time;

/// Moves must shorten the path by more than this (seconds, scaled by the largest cost when that
/// exceeds 1 s) to be accepted, so rounding noise can never make the search cycle.
const EPS: f64 = 1e-12;

/// Perturbations after the first local optimum (see `local::perturb`): [`MIN_KICKS`] plus
/// this many per pose, at most [`MAX_KICKS_PER_POSE`] per pose. A kick on a big pool costs more
/// than on a small one (its repair moves reverse and shift longer stretches of the array: about
/// 4,200 positions per kick at 3,400 poses against 1,100 at 1,000), so the count grows slower than
/// the pool. On the NJ-130 bench pool of 3,400 poses, over 5 kick seeds, 60,400 kicks (this rule)
/// gave a mean gap to LKH-3 of 0.259 % (0.232-0.291 %) in 0.83-0.94 s, the former 2,400 per 100
/// poses (81,600) 0.254 % (0.231-0.277 %) in 1.10-1.18 s on the same (slow) machine; at 1,000
/// poses 46,000 kicks gave 0.166 % where 40,000 gave 0.202 %.
const KICKS_PER_POSE: usize = 6;
/// Fewest perturbations on instances big enough to use them (at most [`MAX_KICKS_PER_POSE`] per
/// pose): smaller pools are cheap to kick, and their gap to LKH-3 varies more with the seed. At
/// 1,000 poses 40,000 instead of 24,000 took the mean gap over 4 seeds from 0.22 to 0.16 % (worst
/// 0.28 to 0.20 %) for 0.28 s.
const MIN_KICKS: usize = 40_000;
/// Caps the count on small instances (35 poses are solved exactly long before 40,000 kicks; a
/// compile's tours, of tens of poses, get 200 per pose).
const MAX_KICKS_PER_POSE: usize = 200;
/// Fixed seed of the perturbation generator: the tour is a function of the input alone.
const KICK_SEED: u64 = 0x6564_6262;

/// Estimated time of visiting `poses` in the given order (sum of Eq. 7 over consecutive pairs).
/// Sums left to right, so equal inputs give bit-identical results.
pub fn path_time(poses: &[[f64; 6]], order: &[usize], max_speed: &[f64; 6]) -> f64 {
    order
        .windows(2)
        .map(|w| move_time(&poses[w[0]], &poses[w[1]], max_speed))
        .sum()
}

/// An ordered visit of all poses.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Tour {
    /// Indices into the input poses; a permutation of `0..n` whose first element is the start.
    pub order: Vec<usize>,
    /// [`path_time`] of the input order with the start pose moved to the front (s).
    pub time_unsorted: f64,
    /// [`path_time`] of [`Tour::order`] (s).
    pub time_sorted: f64,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum OrderError {
    #[error("start pose {start} is out of range: there are {len} poses")]
    StartOutOfRange { start: usize, len: usize },
    /// `joint` is 1-based, as users see it.
    #[error("joint {joint}: max speed {value} rad/s must be finite and positive")]
    InvalidSpeed { joint: usize, value: f64 },
    /// `pose` is the 0-based input index, `joint` is 1-based.
    #[error("pose {pose}, joint {joint}: value {value} is not finite")]
    NonFinitePose {
        pose: usize,
        joint: usize,
        value: f64,
    },
}

/// Open tour starting at `start` (an index into `poses`): nearest neighbour, then 2-opt, Or-opt
/// of single poses and sequential 3-opt moves ("Or-3opt": a segment of any length moved, with or
/// without reversal, or two adjacent reversals, found LK-style from candidate lists) until no
/// improving move remains, then a fixed number of seeded perturbations (segment swaps) each
/// followed by the same local search and kept if the tour got shorter or longer by less than a
/// threshold that falls to zero over the kicks; the shortest tour seen is kept, and a last exact
/// search from it makes the result a local optimum for these moves over the candidate lists,
/// never longer than the nearest-neighbour tour.
///
/// With no poses every `start` is out of range, so `poses` must be non-empty. One or two poses
/// have a single open path from `start`, returned as is.
pub fn solve(poses: &[[f64; 6]], start: usize, max_speed: &[f64; 6]) -> Result<Tour, OrderError> {
    solve_with(poses, start, max_speed, None)
}

/// [`solve`] with the trapezoid cost when `accel` (rad/s², every joint positive) is given: each
/// move between exact stops timed with its acceleration ramps ([`crate::timing::move_time`]);
/// the tour's times are then those too. `None` is Eq. 7.
pub fn solve_with(
    poses: &[[f64; 6]],
    start: usize,
    max_speed: &[f64; 6],
    accel: Option<&[f64; 6]>,
) -> Result<Tour, OrderError> {
    check(poses, start, max_speed)?;
    if let Some(a) = accel {
        check(poses, start, a)?;
    }
    let n = poses.len();
    let unsorted: Vec<usize> = std::iter::once(start)
        .chain((0..n).filter(|&i| i != start))
        .collect();
    let time = |order: &[usize]| match accel {
        None => path_time(poses, order, max_speed),
        Some(a) => {
            let lim = crate::timing::Limits {
                speed: *max_speed,
                accel: *a,
            };
            order
                .windows(2)
                .map(|w| crate::timing::move_time(&poses[w[0]], &poses[w[1]], &lim, 1.0))
                .sum()
        }
    };
    let time_unsorted = time(&unsorted);

    let costs = match accel {
        None => cost::Costs::new(poses, max_speed),
        Some(a) => cost::Costs::with_accel(poses, max_speed, a),
    };
    let nbrs = costs.neighbours(cost::NEIGHBOURS);
    let mut order = local::nearest_neighbour(&costs, &nbrs, start);
    let eps = EPS * costs.max().max(1.0);
    local::improve(&costs, &nbrs, &mut order, eps);
    local::perturb(
        &costs,
        &nbrs,
        &mut order,
        eps,
        (MIN_KICKS + KICKS_PER_POSE * n).min(MAX_KICKS_PER_POSE * n),
        KICK_SEED,
    );

    let time_sorted = time(&order);
    Ok(Tour {
        order,
        time_unsorted,
        time_sorted,
    })
}

fn check(poses: &[[f64; 6]], start: usize, max_speed: &[f64; 6]) -> Result<(), OrderError> {
    if start >= poses.len() {
        return Err(OrderError::StartOutOfRange {
            start,
            len: poses.len(),
        });
    }
    for (n, &w) in max_speed.iter().enumerate() {
        if !(w.is_finite() && w > 0.0) {
            return Err(OrderError::InvalidSpeed {
                joint: n + 1,
                value: w,
            });
        }
    }
    for (i, q) in poses.iter().enumerate() {
        if let Some(n) = q.iter().position(|v| !v.is_finite()) {
            return Err(OrderError::NonFinitePose {
                pose: i,
                joint: n + 1,
                value: q[n],
            });
        }
    }
    Ok(())
}
