//! Candidate sampling: in = robot, measurement model, cell, grid steps; out = the [`Pool`] of
//! joint-grid poses whose MAP lies in the EDBB shell above the floor, plus a [`SampleReport`].
//!
//! The grid is never materialised. Restrictions that make it cheap, none of which loses a pose
//! that the brute-force grid would keep (a test compares against brute force):
//! 1. **q1 is solved, not searched.** Joint 1 turns the whole arm about z0, so for fixed q2..q6
//!    the MAP runs on a horizontal circle; the q1 intervals where that circle lies in the shell
//!    are solved in closed form and only the grid values inside them are visited (then checked
//!    exactly, so boundary rounding cannot add or drop a pose).
//! 2. **Reach pruning.** After q2..qk are fixed, the MAP lies within a ball of radius R_k (sum of
//!    the remaining link offsets plus the tool) around frame k, and q1 sweeps that ball around
//!    z0; when no position of the ball meets the shell, the whole branch is skipped.
//! 3. **One turn per joint.** A joint whose range covers 360° or more is enumerated over one turn
//!    centred on zero: q and q ± 360° give the same pose and the same Jacobian row.
//! 4. **Floor and cones over whole circles and branches.** For fixed q2..q6 the floor height,
//!    `d·socket axis` and `−d·cup axis` are bounded over every q1 in closed form (their extremes
//!    on the circle); a circle that cannot pass them is skipped, and a socket axis along joint
//!    1's axis caps the bar length (L ≤ d·axis / cos) before the q1 interval is solved. The
//!    reach ball of a branch is tested against the floor and the socket cone the same way.
//!    With joints that turn ±360° most of the grid fails the cones: the work then follows the
//!    poses that pass, not the grid (an arm with six ±360° joints: 2.2·10⁹ grid poses, 3·10⁶
//!    valid).
//! 5. **Joints that cannot move the MAP are held** (at 0, or the limit nearest to it), e.g. q6
//!    when the MAP lies on the flange axis: every value gives the same MAP and the same L.
//!
//! Streaming: survivors are reduced to a fixed-size, thread-count-independent subset (the
//! `max_candidates` poses with the smallest seeded hash of their grid index), so memory does not
//! grow with the grid, and the result is identical on any number of threads.

use crate::ir::{Candidate, Cell, Pool, Reason};
use crate::model::MeasurementModel;
use crate::robot::kinematics::dh_transform;
use crate::robot::{Frame, Robot};
use nalgebra::Vector3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::BinaryHeap;
use std::f64::consts::{PI, TAU};
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SampleConfig {
    /// Grid step per joint (rad).
    pub step: [f64; 6],
    /// At most this many valid poses are kept (a seeded, uniform subset of the valid ones).
    pub max_candidates: usize,
    pub seed: u64,
    /// Which joints can move the MAP ([`crate::model::movable_joints`]); the others are held.
    pub movable: [bool; 6],
}

/// How one joint was enumerated.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JointGrid {
    /// Grid values are `k · step` for k in `k_lo..=k_hi` (or the single `held` value), with
    /// the ends of a bounded range (the limits less the joint margin) in front and behind
    /// when they lie off the grid.
    pub step: f64,
    pub k_lo: i64,
    pub k_hi: i64,
    pub held: Option<f64>,
    #[serde(default)]
    pub ends: [Option<f64>; 2],
    /// Why the enumerated range is what it is.
    pub note: String,
}

impl JointGrid {
    pub fn len(&self) -> u64 {
        if self.held.is_some() {
            1
        } else {
            (self.k_hi - self.k_lo + 1).max(0) as u64
                + self.ends.iter().filter(|e| e.is_some()).count() as u64
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    #[inline]
    pub fn value(&self, j: u64) -> f64 {
        if let Some(v) = self.held {
            return v;
        }
        let j = match self.ends[0] {
            Some(v) if j == 0 => return v,
            Some(_) => j - 1,
            None => j,
        };
        let k = self.k_lo + j as i64;
        match self.ends[1] {
            Some(v) if k > self.k_hi => v,
            _ => k as f64 * self.step,
        }
    }

    pub fn first(&self) -> f64 {
        self.value(0)
    }

    pub fn last(&self) -> f64 {
        self.value(self.len().saturating_sub(1))
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SampleReport {
    pub grids: Vec<JointGrid>,
    /// Poses in the full grid over the enumerated ranges (what brute force would visit).
    pub grid_size: u64,
    /// Poses actually evaluated after the q1 solution and reach pruning.
    pub evaluated: u64,
    /// Valid poses: every check of [`Cell::verdict`] passed.
    pub valid: u64,
    /// Evaluated poses rejected, per reason (the first failing check counts).
    pub rejected: std::collections::BTreeMap<Reason, u64>,
    /// Valid poses kept in the pool (≤ max_candidates).
    pub kept: usize,
    /// Per joint, [min, max] of q over the valid poses (rad); NaN when there are none.
    pub valid_range: [[f64; 2]; 6],
}

/// Progress callbacks (the CLI draws a bar; stages never print).
pub trait Progress: Sync {
    /// A pipeline stage begins (named for people: `sample`, `sections`, ...).
    fn stage(&self, _name: &'static str) {}
    fn start(&self, _total: u64) {}
    fn inc(&self, _n: u64) {}
    fn finish(&self) {}
}

pub struct NoProgress;
impl Progress for NoProgress {}

/// The grid of one joint: one turn for ranges ≥ 360°, the held value for immobile joints.
/// With `ends`, a bounded range also gets its two ends (`lo`, `hi`) where they lie more than a
/// quarter step off the grid: the extremes of a joint's range are the poses that separate some
/// parameters best (a 10° grid would otherwise lose up to 10° at each end, e.g. to the joint
/// margin).
pub fn joint_grid(lo: f64, hi: f64, step: f64, movable: bool, ends: bool) -> JointGrid {
    if !movable {
        let v = 0.0f64.clamp(lo, hi);
        return JointGrid {
            step,
            k_lo: 0,
            k_hi: 0,
            held: Some(v),
            ends: [None; 2],
            note: "held: cannot move the MAP".into(),
        };
    }
    let tol = 1e-9;
    if hi - lo >= TAU - tol {
        // One turn [w, w + 2π), as close to centred on zero as the limits allow.
        let w = (-PI).clamp(lo, hi - TAU);
        let k_lo = (w / step - tol).ceil() as i64;
        let mut k_hi = ((w + TAU) / step - tol).ceil() as i64 - 1;
        while (k_hi as f64) * step > hi + tol {
            k_hi -= 1;
        }
        JointGrid {
            step,
            k_lo,
            k_hi,
            held: None,
            ends: [None; 2],
            note: "one turn of a range >= 360 deg (poses repeat)".into(),
        }
    } else {
        let k_lo = (lo / step - tol).ceil() as i64;
        let k_hi = (hi / step + tol).floor() as i64;
        let off = |v: f64, k: i64| ends && (v - k as f64 * step).abs() > 0.25 * step;
        // As the program will print them, still inside [lo, hi].
        let (plo, phi) = (
            crate::units::printable_inside(lo, lo, hi),
            crate::units::printable_inside(hi, lo, hi),
        );
        let ends = [
            off(plo, k_lo).then_some(plo),
            (off(phi, k_hi) && phi > plo).then_some(phi),
        ];
        JointGrid {
            step,
            k_lo,
            k_hi,
            held: None,
            ends,
            note: if ends.iter().any(|e| e.is_some()) {
                "full joint range less the joint margin, with its ends".into()
            } else {
                "full joint range less the joint margin".into()
            },
        }
    }
}

/// Enumerates the grid and keeps the valid poses. See the module docs.
pub fn run(
    robot: &Robot,
    model: &MeasurementModel,
    cell: &Cell,
    cfg: &SampleConfig,
    progress: &dyn Progress,
) -> (Pool, SampleReport) {
    // Measurement poses keep the joint margin from every limit.
    let (lo, hi) = robot.limits();
    let m = cell.joint_margin;
    let mut grids: Vec<JointGrid> = (0..6)
        // Joint 1 is solved in closed form over the plain grid (no ends).
        .map(|i| joint_grid(lo[i] + m, hi[i] - m, cfg.step[i], cfg.movable[i], i > 0))
        .collect();
    if cfg.movable[0] {
        grids[0].note =
            "solved per wrist configuration: only values whose MAP is in the shell".into();
    }
    for g in grids.iter_mut().take(5).skip(1) {
        if g.held.is_none() {
            g.note.push_str("; branches pruned by reach");
        }
    }
    let grid_size = grids
        .iter()
        .map(|g| g.len())
        .fold(1u64, |a, b| a.saturating_mul(b));
    let ctx = Ctx::new(model, cell, &grids);

    let n2 = grids[1].len();
    let n3 = grids[2].len();
    let units = n2 * n3;
    progress.start(units);
    let shared = AtomicU64::new(u64::MAX);
    let acc = (0..units)
        .into_par_iter()
        .fold(
            || Acc::new(cfg.max_candidates, &shared),
            |mut acc, u| {
                ctx.unit(u / n3, u % n3, cfg, &mut acc);
                progress.inc(1);
                acc
            },
        )
        .reduce(|| Acc::new(cfg.max_candidates, &shared), Acc::merge);
    progress.finish();

    let mut kept: Vec<Entry> = acc.heap.into_vec();
    kept.sort_by_key(|e| e.cand.grid);
    let candidates: Vec<Candidate> = kept.into_iter().map(|e| e.cand).collect();
    let report = SampleReport {
        grids,
        grid_size,
        evaluated: acc.evaluated,
        valid: acc.valid,
        rejected: Reason::ALL
            .iter()
            .zip(acc.rejected)
            .filter(|(_, n)| *n > 0)
            .map(|(r, n)| (*r, n))
            .collect(),
        kept: candidates.len(),
        valid_range: acc.range,
    };
    (Pool { candidates }, report)
}

/// Everything the hot loop needs, precomputed once.
struct Ctx<'a> {
    cell: &'a Cell,
    base: Frame,
    grids: &'a [JointGrid],
    /// Joint 1's fixed part TransZ(d1)·TransX(a1)·RotX(α1); T1 = RotZ(θ1 + q1)·a1.
    a1: Frame,
    theta1: f64,
    /// DH transforms of joints 2..6 at every grid value.
    t: [Vec<Frame>; 5],
    /// MAP in DH frame 5 for every q6 grid value.
    map5: Vec<Vector3<f64>>,
    /// Tool-cup axis in DH frame 5 for every q6 grid value.
    cup5: Vec<Vector3<f64>>,
    /// Joint 6 turns the MAP and the cup axis about z5 together: the cup axis's component
    /// along z5 and its length across, and the MAP's component along the axis (all the same
    /// for every q6), for the branch test [`Ctx::cup_can_pass`].
    cup_along: f64,
    cup_across: f64,
    map_dot_cup: f64,
    /// The MAP's q6 circle about z5: its centre's offset along z5 from frame 5's origin and its
    /// radius (a wrist branch's MAP positions lie on it).
    map_along: f64,
    map_across: f64,
    /// Grid poses per q1 grid value: a pose's grid index is j1 · stride + the rest.
    stride: u64,
    /// Reach radius after joints 2..5 (index k−2 for frame k).
    reach: [f64; 4],
    /// Fixture in DH frame 0, cylindrical.
    f0: Vector3<f64>,
    rf: f64,
    phif: f64,
    radix: [u64; 6],
    /// The socket axis in DH frame 0, its horizontal length and the fixture's offset along it.
    a0: Vector3<f64>,
    a0h: f64,
    f0a: f64,
    /// World z of a DH-frame-0 vector is `zrow · v` (plus the base's z): the third row of the
    /// base rotation and its horizontal length.
    zrow: Vector3<f64>,
    zrowh: f64,
    /// sin and cos of θ1 + q1 for the q1 grid values k·step, k = k_lo..=k_hi (the held value
    /// alone when joint 1 is held): computed once, not per pose.
    sc1: Vec<(f64, f64)>,
}

/// Slack of the whole-circle and whole-branch tests (m): they only ever skip what the exact
/// test would reject by more than this, so rounding cannot drop a pose brute force keeps.
const PRUNE_SLACK: f64 = 1e-9;

impl<'a> Ctx<'a> {
    fn new(model: &MeasurementModel, cell: &'a Cell, grids: &'a [JointGrid]) -> Self {
        let dh = &model.nominal.dh;
        let mut a1 = dh_transform(&dh[0], 0.0);
        // Remove RotZ(θ1): a1 = RotZ(−θ1)·T1(0).
        let rz = dh_transform(
            &crate::robot::Dh {
                alpha: 0.0,
                a: 0.0,
                d: 0.0,
                theta: -dh[0].theta,
            },
            0.0,
        );
        a1 = rz.mul(&a1);
        let t: [Vec<Frame>; 5] = std::array::from_fn(|k| {
            let g = &grids[k + 1];
            (0..g.len())
                .map(|j| dh_transform(&dh[k + 1], g.value(j)))
                .collect()
        });
        let tool = model.flange.apply(&model.nominal.map);
        let map5 = t[4].iter().map(|t6| t6.apply(&tool)).collect();
        let cup = model.flange.r * cell.tool_axis;
        let cup5: Vec<Vector3<f64>> = t[4].iter().map(|t6| t6.r * cup).collect();
        // T6 = RotZ(θ6 + q6)·(a fixed transform): these do not depend on q6.
        let c6 = dh_transform(&dh[5], 0.0);
        let (m6, u6) = (c6.apply(&tool), c6.r * cup);
        let link = |i: usize| dh[i].a.hypot(dh[i].d);
        let tail = tool.norm();
        let reach = std::array::from_fn(|k| ((k + 2)..6).map(link).sum::<f64>() + tail);
        let f0 = model.base.inverse().apply(&cell.fixture);
        let radix = std::array::from_fn(|i| grids[i].len());
        let a0 = model.base.r.transpose() * cell.fixture_axis;
        let zrow = model.base.r.row(2).transpose();
        let g1 = &grids[0];
        let sc1 = match g1.held {
            Some(v) => vec![(dh[0].theta + v).sin_cos()],
            None => (g1.k_lo..=g1.k_hi)
                .map(|k| (dh[0].theta + k as f64 * g1.step).sin_cos())
                .collect(),
        };
        Ctx {
            sc1,
            cell,
            base: model.base,
            grids,
            a1,
            theta1: dh[0].theta,
            t,
            map5,
            cup5,
            cup_along: u6.z,
            cup_across: norm2(u6.x, u6.y),
            map_dot_cup: m6.dot(&u6),
            map_along: m6.z,
            map_across: norm2(m6.x, m6.y),
            stride: grids[1..].iter().map(|g| g.len()).product(),
            reach,
            rf: f0.x.hypot(f0.y),
            phif: f0.y.atan2(f0.x),
            f0a: f0.dot(&a0),
            f0,
            radix,
            a0h: a0.x.hypot(a0.y),
            a0,
            zrowh: zrow.x.hypot(zrow.y),
            zrow,
        }
    }

    /// The least of `cos · L` over bar lengths `L` in [lmin, lmax]: what `d·axis` must reach
    /// for a cone test `d·axis ≥ cos·L` to pass somewhere.
    #[inline]
    fn cone_floor(cos: f64, lmin: f64, lmax: f64) -> f64 {
        if cos > 0.0 {
            cos * lmin
        } else {
            cos * lmax
        }
    }

    /// Can the MAP, within `reach` of point `o` (DH frame 0, any q1), meet the shell above the
    /// floor and inside the socket cone? (Necessary conditions, with slack.)
    #[inline]
    fn ball_meets_shell(&self, o: &Vector3<f64>, reach: f64) -> bool {
        let r = norm2(o.x, o.y);
        let dz = o.z - self.f0.z;
        let dmin = norm2(r - self.rf, dz);
        let dmax = norm2(r + self.rf, dz);
        if dmin - reach > self.cell.bar_max + PRUNE_SLACK
            || dmax + reach + PRUNE_SLACK < self.cell.bar_min
        {
            return false;
        }
        // Floor: the highest the ball gets over every q1 (|zrow| = 1).
        let ztop = self.zrow.z * o.z + self.zrowh * r + self.base.t.z + reach;
        if ztop + PRUNE_SLACK <= self.cell.floor_z {
            return false;
        }
        // Socket cone: the most `d·axis` gets over the ball and every q1, against the least it
        // must reach on the shell.
        let along = r * self.a0h + o.z * self.a0.z - self.f0a + reach;
        let need = Self::cone_floor(
            self.cell.fixture_cone_cos,
            self.cell.bar_min,
            self.cell.bar_max,
        );
        along + PRUNE_SLACK >= need
    }

    /// Can the bar meet the tool-cup cone anywhere on a wrist branch (frame 5 at `f5`, every
    /// q6 and every q1)? The cup test of [`Ctx::solve_q1`] bounded over the q6 circle: joint 6
    /// turns the MAP and the cup axis about z5 together, so x·cup stays the same, and the
    /// fixture's part and the cup axis's height vary within bounds the branch's frame gives.
    /// (A necessary condition with slack; with the cup axis along joint 6 it is the circles'
    /// test itself.)
    #[inline]
    fn cup_can_pass(&self, f5: &Frame) -> bool {
        let cs = self.cell.tool_cone_cos;
        if cs <= -1.0 {
            return true;
        }
        // x = o + R·Rz(q6)·m, cup = R·Rz(q6)·u: −x·cup = −m·u − (Rᵀo)·(Rz(q6)·u).
        let p = f5.r.transpose() * f5.t;
        let (along, across) = (self.cup_along, self.cup_across);
        let x_part = -self.map_dot_cup - p.z * along + norm2(p.x, p.y) * across;
        // cup_z = (Rᵀ·e_z)·(Rz(q6)·u) lies in [zc − w, zc + w]; rf·|cup_h| + f0z·cup_z =
        // rf·√(1 − c²) + f0z·c peaks at c* = f0z / |f0|.
        let r3 = f5.r.row(2);
        let zc = r3[2] * along;
        let w = norm2(r3[0], r3[1]) * across;
        let (lo, hi) = ((zc - w).max(-1.0), (zc + w).min(1.0));
        let fz = self.f0.z;
        let fnorm = norm2(self.rf, fz);
        let star = if fnorm > 0.0 { fz / fnorm } else { 0.0 };
        let g = |c: f64| self.rf * (1.0 - c * c).max(0.0).sqrt() + fz * c;
        let f_part = if star >= lo && star <= hi {
            fnorm
        } else {
            g(lo).max(g(hi))
        };
        let need = Self::cone_floor(cs, self.cell.bar_min, self.cell.bar_max);
        x_part + f_part + PRUNE_SLACK >= need
    }

    fn unit(&self, i2: u64, i3: u64, cfg: &SampleConfig, acc: &mut Acc) {
        let f2 = self.a1.mul(&self.t[0][i2 as usize]);
        if !self.ball_meets_shell(&f2.t, self.reach[0]) {
            return;
        }
        let f3 = f2.mul(&self.t[1][i3 as usize]);
        if !self.ball_meets_shell(&f3.t, self.reach[1]) {
            return;
        }
        for (i4, t4) in self.t[2].iter().enumerate() {
            let f4 = f3.mul(t4);
            if !self.ball_meets_shell(&f4.t, self.reach[2]) {
                continue;
            }
            for (i5, t5) in self.t[3].iter().enumerate() {
                let f5 = f4.mul(t5);
                // The MAP's q6 circle lies in the ball of its radius about its centre (often
                // much smaller than the reach ball about frame 5's origin).
                let centre = f5.t + f5.r.column(2) * self.map_along;
                if !self.ball_meets_shell(&f5.t, self.reach[3])
                    || !self.ball_meets_shell(&centre, self.map_across)
                    || !self.cup_can_pass(&f5)
                {
                    continue;
                }
                for (i6, m5) in self.map5.iter().enumerate() {
                    let x = f5.apply(m5);
                    let cup = f5.r * self.cup5[i6];
                    let idx = [0, i2, i3, i4 as u64, i5 as u64, i6 as u64];
                    self.solve_q1(&x, &cup, &idx, cfg, acc);
                }
            }
        }
    }

    /// Visits the q1 grid values whose MAP can lie in the shell, for the q1-free MAP position x.
    #[inline]
    fn solve_q1(
        &self,
        x: &Vector3<f64>,
        cup: &Vector3<f64>,
        idx: &[u64; 6],
        cfg: &SampleConfig,
        acc: &mut Acc,
    ) {
        let g = &self.grids[0];
        if let Some(v) = g.held {
            self.check(x, cup, v, self.sc1[0], 0, &self.circle(idx), cfg, acc);
            return;
        }
        let (rmin, mut rmax) = (self.cell.bar_min, self.cell.bar_max);
        let r = norm2(x.x, x.y);
        let dz = x.z - self.f0.z;
        let s = r * r + self.rf * self.rf + dz * dz;
        // Whole-circle tests: floor and both cones bounded over every q1 (necessary conditions
        // with slack; the poses visited are still checked exactly).
        let lmin = rmin.max((s - 2.0 * r * self.rf).max(0.0).sqrt());
        let lmax = rmax.min((s + 2.0 * r * self.rf).sqrt());
        if self.zrow.z * x.z + self.zrowh * r + self.base.t.z + PRUNE_SLACK <= self.cell.floor_z {
            return;
        }
        let socket = r * self.a0h + x.z * self.a0.z - self.f0a;
        let cs = self.cell.fixture_cone_cos;
        if socket + PRUNE_SLACK < Self::cone_floor(cs, lmin, lmax) {
            return;
        }
        let toward = -x.dot(cup) + self.rf * norm2(cup.x, cup.y) + self.f0.z * cup.z;
        if toward + PRUNE_SLACK < Self::cone_floor(self.cell.tool_cone_cos, lmin, lmax) {
            return;
        }
        // A socket axis along joint 1's axis: `d·axis` is the same all round the circle, so the
        // cone caps the bar length (L ≤ d·axis / cos).
        if self.a0h == 0.0 && cs > 0.0 {
            rmax = rmax.min(socket / cs + PRUNE_SLACK);
            if rmax < rmin {
                return;
            }
        }
        let mut iv = [(0.0f64, 0.0f64); 2];
        let n_iv;
        if r * self.rf < 1e-12 {
            // The circle degenerates (MAP or fixture on the joint-1 axis): L does not depend on q1.
            if s < rmin * rmin * (1.0 - 1e-9) || s > rmax * rmax * (1.0 + 1e-9) {
                return;
            }
            iv[0] = (g.k_lo as f64 * g.step - 1.0, g.k_hi as f64 * g.step + 1.0);
            n_iv = 1;
        } else {
            // D² = s − 2·r·rf·cos Δ; Rmin² ≤ D² ≤ Rmax²  ⇔  cmin ≤ cos Δ ≤ cmax.
            let cmin = (s - rmax * rmax) / (2.0 * r * self.rf);
            let cmax = (s - rmin * rmin) / (2.0 * r * self.rf);
            if cmin > 1.0 + 1e-12 || cmax < -1.0 - 1e-12 {
                return;
            }
            let eps = 1e-7; // widen, then check exactly: the grid set equals brute force
            let d1 = (cmax.min(1.0)).acos() - eps;
            let d2 = (cmin.max(-1.0)).acos() + eps;
            let c = self.phif - self.theta1 - x.y.atan2(x.x);
            if d1 <= 0.0 || d2 >= PI {
                // The two mirrored intervals touch: one interval.
                if d1 <= 0.0 && d2 >= PI {
                    iv[0] = (c - PI, c + PI);
                } else if d1 <= 0.0 {
                    iv[0] = (c - d2, c + d2);
                } else {
                    iv[0] = (c + d1, c + TAU - d1);
                }
                n_iv = 1;
            } else {
                iv[0] = (c - d2, c - d1);
                iv[1] = (c + d1, c + d2);
                n_iv = 2;
            }
        }
        let mut ks: [(i64, i64); 8] = [(0, -1); 8];
        let nk = grid_ranges(g, &iv[..n_iv], &mut ks);
        let mut both: [(i64, i64); 64] = [(0, -1); 64];
        let mut ranges: &[(i64, i64)] = &ks[..nk];
        // The cup cone as a q1 interval (a necessary condition): −d·cup = −x·cup +
        // rf·|cup_h|·cos(q1 − γ) + f0z·cup_z must reach the circle's least cos·L.
        let ch = norm2(cup.x, cup.y);
        if self.rf * ch > 1e-9 {
            let need = Self::cone_floor(self.cell.tool_cone_cos, lmin, lmax) - PRUNE_SLACK;
            let kappa = (need + x.dot(cup) - self.f0.z * cup.z) / (self.rf * ch);
            if kappa > 1.0 {
                return;
            }
            if kappa > -1.0 {
                let w = kappa.acos() + 1e-7;
                let gamma = self.phif - cup.y.atan2(cup.x) - self.theta1;
                let mut cs: [(i64, i64); 8] = [(0, -1); 8];
                let nc = grid_ranges(g, &[(gamma - w, gamma + w)], &mut cs);
                let mut nb = 0;
                for &(a, b) in &ks[..nk] {
                    for &(c, d) in &cs[..nc] {
                        let (lo, hi) = (a.max(c), b.min(d));
                        if lo <= hi {
                            both[nb] = (lo, hi);
                            nb += 1;
                        }
                    }
                }
                both[..nb].sort_unstable();
                ranges = &both[..nb];
            }
        }
        let mut last_k = i64::MIN;
        if ranges.is_empty() {
            return;
        }
        let circle = self.circle(idx);
        for &(lo, hi) in ranges {
            for k in lo.max(last_k.saturating_add(1))..=hi {
                self.check(
                    x,
                    cup,
                    k as f64 * g.step,
                    self.sc1[(k - g.k_lo) as usize],
                    (k - g.k_lo) as u64,
                    &circle,
                    cfg,
                    acc,
                );
                last_k = k;
            }
        }
    }

    /// What the poses of one q1 circle share (grid indices `idx` of joints 2-6).
    fn circle(&self, idx: &[u64; 6]) -> Circle {
        let mut rest = 0u64;
        let mut q = [0.0; 6];
        for i in 1..6 {
            rest = rest * self.radix[i] + idx[i];
            q[i] = self.grids[i].value(idx[i]);
        }
        Circle { q, rest }
    }

    /// The exact test of one pose; `(s, c)` = sin and cos of θ1 + q1.
    #[inline]
    #[allow(clippy::too_many_arguments)]
    fn check(
        &self,
        x: &Vector3<f64>,
        cup: &Vector3<f64>,
        q1: f64,
        (s, c): (f64, f64),
        j1: u64,
        circle: &Circle,
        cfg: &SampleConfig,
        acc: &mut Acc,
    ) {
        acc.evaluated += 1;
        let p0 = Vector3::new(c * x.x - s * x.y, s * x.x + c * x.y, x.z);
        let p = self.base.apply(&p0);
        let cup0 = Vector3::new(c * cup.x - s * cup.y, s * cup.x + c * cup.y, cup.z);
        let cup_world = self.base.r * cup0;
        let grid = j1 * self.stride + circle.rest;
        let mut q = circle.q;
        q[0] = q1;
        if let Err(reason) = self.cell.verdict(&q, &p, &cup_world) {
            acc.rejected[reason as usize] += 1;
            return;
        }
        acc.valid += 1;
        for i in 0..6 {
            acc.range[i][0] = acc.range[i][0].min(q[i]);
            acc.range[i][1] = acc.range[i][1].max(q[i]);
        }
        let key = splitmix64(cfg.seed ^ grid.wrapping_mul(0x9e37_79b9_7f4a_7c15));
        if !acc.takes(key, grid) {
            return;
        }
        let length = (p - self.cell.fixture).norm();
        acc.offer(Entry {
            key,
            cand: Candidate {
                q,
                map: [p.x, p.y, p.z],
                length,
                grid,
                key,
            },
        });
    }
}

/// The joints 2-6 of a q1 circle's poses and their part of the grid index.
struct Circle {
    q: [f64; 6],
    rest: u64,
}

/// The grid indices `k` (`k·step` in `k_lo..=k_hi`) inside any of `intervals` (q1 values, each
/// at most 2π wide) or a whole turn away from one, as sorted ranges in `out`; returns their
/// count. Ranges may overlap where shifted intervals do; the caller visits each k once.
fn grid_ranges(g: &JointGrid, intervals: &[(f64, f64)], out: &mut [(i64, i64); 8]) -> usize {
    let (wlo, whi) = (g.k_lo as f64 * g.step, g.k_hi as f64 * g.step);
    let mut n = 0;
    for &(a, b) in intervals {
        let mut sh = ((wlo - b) / TAU).ceil();
        while a + sh * TAU <= whi + 1e-12 {
            let lo = (((a + sh * TAU) / g.step).ceil() as i64).max(g.k_lo);
            let hi = (((b + sh * TAU) / g.step).floor() as i64).min(g.k_hi);
            if lo <= hi {
                assert!(n < out.len(), "q1 window wider than three turns");
                out[n] = (lo, hi);
                n += 1;
            }
            sh += 1.0;
        }
    }
    out[..n].sort_unstable();
    n
}

/// √(a² + b²) without `hypot`'s overflow care (lengths here are metres), several times faster
/// in the sampler's loops; every test that uses it has slack, and poses are checked exactly.
#[inline]
fn norm2(a: f64, b: f64) -> f64 {
    (a * a + b * b).sqrt()
}

/// SplitMix64 finaliser: a well-mixed 64-bit hash, identical on every platform.
fn splitmix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

struct Entry {
    key: u64,
    cand: Candidate,
}

impl PartialEq for Entry {
    fn eq(&self, o: &Self) -> bool {
        (self.key, self.cand.grid) == (o.key, o.cand.grid)
    }
}
impl Eq for Entry {}
impl PartialOrd for Entry {
    fn partial_cmp(&self, o: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(o))
    }
}
impl Ord for Entry {
    fn cmp(&self, o: &Self) -> std::cmp::Ordering {
        (self.key, self.cand.grid).cmp(&(o.key, o.cand.grid))
    }
}

/// Per-thread accumulator: counts and the bottom-K (by hash key) of the valid poses.
struct Acc<'s> {
    cap: usize,
    heap: BinaryHeap<Entry>,
    /// The smallest key any full accumulator's largest entry had: every accumulator that far
    /// holds `cap` poses with keys at most this, so a pose with a larger key is in no
    /// accumulator's bottom-K at the end (rayon's fold makes many accumulators, each of which
    /// would otherwise take every pose until it is full).
    shared: &'s AtomicU64,
    evaluated: u64,
    valid: u64,
    rejected: [u64; Reason::ALL.len()],
    range: [[f64; 2]; 6],
}

impl<'s> Acc<'s> {
    fn new(cap: usize, shared: &'s AtomicU64) -> Self {
        Acc {
            cap,
            heap: BinaryHeap::new(),
            shared,
            evaluated: 0,
            valid: 0,
            rejected: [0; Reason::ALL.len()],
            range: [[f64::INFINITY, f64::NEG_INFINITY]; 6],
        }
    }

    /// Would a pose with this key enter the bottom-K? (Cheap: no entry is built otherwise.)
    #[inline]
    fn takes(&self, key: u64, grid: u64) -> bool {
        key <= self.shared.load(Relaxed)
            && (self.heap.len() < self.cap
                || self
                    .heap
                    .peek()
                    .is_some_and(|top| (key, grid) < (top.key, top.cand.grid)))
    }

    #[inline]
    fn offer(&mut self, e: Entry) {
        if self.heap.len() < self.cap {
            self.heap.push(e);
        } else if let Some(mut top) = self.heap.peek_mut() {
            // Replacing the largest in place: one sift-down instead of a pop and a push.
            if e < *top {
                *top = e;
            }
        }
        if self.heap.len() == self.cap {
            if let Some(top) = self.heap.peek() {
                self.shared.fetch_min(top.key, Relaxed);
            }
        }
    }

    fn merge(mut self, mut other: Acc<'s>) -> Acc<'s> {
        if other.heap.len() > self.heap.len() {
            std::mem::swap(&mut self.heap, &mut other.heap);
        }
        for e in other.heap.into_vec() {
            self.offer(e);
        }
        self.evaluated += other.evaluated;
        self.valid += other.valid;
        for (a, b) in self.rejected.iter_mut().zip(other.rejected) {
            *a += b;
        }
        for i in 0..6 {
            self.range[i][0] = self.range[i][0].min(other.range[i][0]);
            self.range[i][1] = self.range[i][1].max(other.range[i][1]);
        }
        self
    }
}

impl SampleReport {
    /// `valid_range` with NaN for joints without valid poses (for reports).
    pub fn valid_range_or_nan(&self) -> [[f64; 2]; 6] {
        self.valid_range
            .map(|r| if r[0] > r[1] { [f64::NAN; 2] } else { r })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::units::{DEG, MM};

    fn setup(
        map: Vector3<f64>,
        fixture: Vector3<f64>,
        bar: (f64, f64),
    ) -> (Robot, MeasurementModel, Cell) {
        let robot = crate::robot::load(
            std::path::Path::new(concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/robots/comau_nj130/robot.dh.toml"
            )),
            &Default::default(),
        )
        .expect("bundled NJ-130");
        let model = MeasurementModel::new(&robot, fixture, map);
        let mut cell = Cell::shell_only(fixture, map, bar.0, bar.1, 0.0);
        // Real cones and harness limits, so the brute force checks them too.
        cell.fixture_cone_cos = (70.0 * DEG).cos();
        cell.tool_cone_cos = (75.0 * DEG).cos();
        cell.cables = [
            Some([-150.0 * DEG, 150.0 * DEG]),
            None,
            Some([-200.0 * DEG, 200.0 * DEG]),
        ];
        (robot, model, cell)
    }

    /// Every grid pose, FK'd from scratch through the measurement model.
    fn brute_force(model: &MeasurementModel, cell: &Cell, grids: &[JointGrid]) -> Vec<u64> {
        let mut out = Vec::new();
        let n: Vec<u64> = grids.iter().map(|g| g.len()).collect();
        let total: u64 = n.iter().product();
        for idx in 0..total {
            let mut rem = idx;
            let mut q = [0.0; 6];
            for i in (0..6).rev() {
                q[i] = grids[i].value(rem % n[i]);
                rem /= n[i];
            }
            let f = model.base.mul(&crate::robot::kinematics::flange_pose(
                &Frame::IDENTITY,
                &model.nominal.dh,
                &model.flange,
                &q,
            ));
            let cup = f.r * cell.tool_axis;
            if cell.verdict(&q, &f.apply(&model.nominal.map), &cup).is_ok() {
                out.push(idx);
            }
        }
        out
    }

    fn near_boundary(model: &MeasurementModel, cell: &Cell, grids: &[JointGrid], idx: u64) -> bool {
        let n: Vec<u64> = grids.iter().map(|g| g.len()).collect();
        let mut rem = idx;
        let mut q = [0.0; 6];
        for i in (0..6).rev() {
            q[i] = grids[i].value(rem % n[i]);
            rem /= n[i];
        }
        let p = model.map_position(&model.nominal, &q);
        let d = (p - cell.fixture).norm();
        (d - cell.bar_min).abs() < 1e-9
            || (d - cell.bar_max).abs() < 1e-9
            || (p.z - cell.floor_z).abs() < 1e-9
    }

    #[test]
    fn streaming_sampler_keeps_exactly_the_brute_force_poses() {
        let cases = [
            (
                Vector3::new(0.06, 0.03, 0.12),
                Vector3::new(0.258, 1.468, 0.708),
                (0.30, 0.52),
                [30.0; 6],
            ),
            (
                Vector3::new(0.0, 0.0, 0.12),
                Vector3::new(1.2, -0.4, 0.3),
                (0.25, 0.60),
                [25.0, 20.0, 20.0, 40.0, 30.0, 45.0],
            ),
            // Fixture on the joint-1 axis: q1 does not change L.
            (
                Vector3::new(0.05, 0.0, 0.1),
                Vector3::new(0.0, 0.0, 2.3),
                (0.5, 0.9),
                [30.0; 6],
            ),
            // A tilted socket and a floor above the base: the whole-circle and branch tests
            // for a socket axis off joint 1's axis and the floor.
            (
                Vector3::new(0.06, 0.03, 0.12),
                Vector3::new(0.9, 0.8, 0.5),
                (0.30, 0.60),
                [20.0, 20.0, 20.0, 40.0, 30.0, 45.0],
            ),
            // A cup axis off the flange axis and a narrow cup cone: the wrist-branch cup test
            // bounds a cup axis that joint 6 turns.
            (
                Vector3::new(0.06, 0.03, 0.12),
                Vector3::new(0.258, 1.468, 0.708),
                (0.30, 0.52),
                [20.0, 20.0, 20.0, 30.0, 30.0, 20.0],
            ),
        ];
        for (k, (map, fixture, bar, step_deg)) in cases.into_iter().enumerate() {
            let (robot, model, mut cell) = setup(map, fixture, bar);
            if k == 2 {
                // A fixture hanging above the robot: its socket opens downwards.
                cell.fixture_axis = -Vector3::z();
            }
            if k == 3 {
                cell.fixture_axis = Vector3::new(-0.5, -0.3, 0.8).normalize();
                cell.fixture_cone_cos = (50.0 * DEG).cos();
                cell.floor_z = 0.35;
            }
            if k == 4 {
                cell.tool_axis = Vector3::new(0.4, -0.3, 0.85).normalize();
                cell.tool_cone_cos = (45.0 * DEG).cos();
            }
            let cfg = SampleConfig {
                step: step_deg.map(|s| s * DEG),
                max_candidates: usize::MAX,
                seed: 1,
                movable: crate::model::movable_joints(&model, &robot),
            };
            let (pool, report) = run(&robot, &model, &cell, &cfg, &NoProgress);
            let want = brute_force(&model, &cell, &report.grids);
            let got: Vec<u64> = pool.candidates.iter().map(|c| c.grid).collect();
            assert!(!want.is_empty(), "test case must have valid poses");
            let missing: Vec<_> = want
                .iter()
                .filter(|i| !got.contains(i))
                .filter(|&&i| !near_boundary(&model, &cell, &report.grids, i))
                .collect();
            let extra: Vec<_> = got
                .iter()
                .filter(|i| !want.contains(i))
                .filter(|&&i| !near_boundary(&model, &cell, &report.grids, i))
                .collect();
            assert!(
                missing.is_empty() && extra.is_empty(),
                "missing {missing:?} extra {extra:?}"
            );
            assert_eq!(report.valid as usize, got.len());
            assert!(
                report.evaluated < report.grid_size / 3,
                "pruning should cut the grid: {} of {}",
                report.evaluated,
                report.grid_size
            );
            for c in &pool.candidates {
                let p = model.map_position(&model.nominal, &c.q);
                assert!((p - Vector3::from(c.map)).norm() < 1e-12);
                assert!(cell.admits(&p));
                assert!(cell.cables_admit(&c.q));
            }
        }
    }

    /// An arm whose six joints all turn ±360° (bench/arm360.dh.toml): most of its grid fails
    /// the cones, and the sampler must visit about as many poses as are valid, not the grid,
    /// while keeping exactly the brute-force set.
    #[test]
    fn a_full_turn_arm_costs_its_valid_poses_not_its_grid() {
        let robot = crate::robot::load(
            std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/bench/arm360.dh.toml")),
            &Default::default(),
        )
        .expect("bench arm");
        let fixture = Vector3::new(0.7, 0.3, 0.3);
        let map = robot.tool.expect("the bench arm has a tool");
        let model = MeasurementModel::new(&robot, fixture, map);
        let mut cell = Cell::shell_only(fixture, map, 0.30, 0.52, 0.0);
        cell.fixture_cone_cos = (60.0 * DEG).cos();
        cell.tool_cone_cos = (60.0 * DEG).cos();
        cell.floor_z = 0.05;
        let cfg = SampleConfig {
            step: [30.0 * DEG; 6],
            max_candidates: usize::MAX,
            seed: 1,
            movable: crate::model::movable_joints(&model, &robot),
        };
        let (pool, report) = run(&robot, &model, &cell, &cfg, &NoProgress);
        let want = brute_force(&model, &cell, &report.grids);
        let got: Vec<u64> = pool.candidates.iter().map(|c| c.grid).collect();
        assert!(want.len() > 50, "{} valid", want.len());
        let differ: Vec<_> = want
            .iter()
            .filter(|i| !got.contains(i))
            .chain(got.iter().filter(|i| !want.contains(i)))
            .filter(|&&i| !near_boundary(&model, &cell, &report.grids, i))
            .collect();
        assert!(differ.is_empty(), "differ from brute force: {differ:?}");
        assert!(
            report.evaluated < 2 * report.valid,
            "evaluated {} for {} valid of {} grid poses",
            report.evaluated,
            report.valid,
            report.grid_size
        );
    }

    #[test]
    fn pool_cap_keeps_a_thread_count_independent_subset() {
        let (robot, model, cell) = setup(
            Vector3::new(0.06, 0.03, 0.12),
            Vector3::new(0.258, 1.468, 0.708),
            (0.30, 0.52),
        );
        let cfg = SampleConfig {
            step: [20.0 * DEG; 6],
            max_candidates: 500,
            seed: 3,
            movable: [true; 6],
        };
        let run_on = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| run(&robot, &model, &cell, &cfg, &NoProgress))
        };
        let (a, ra) = run_on(1);
        let (b, _) = run_on(2);
        assert_eq!(a, b);
        assert_eq!(a.candidates.len(), 500);
        assert!(ra.valid > 500);
        let full = run(
            &robot,
            &model,
            &cell,
            &SampleConfig {
                max_candidates: usize::MAX,
                ..cfg.clone()
            },
            &NoProgress,
        )
        .0;
        assert!(a.candidates.iter().all(|c| full.candidates.contains(c)));
        let _ = MM;
    }

    #[test]
    fn one_turn_windows_and_held_joints() {
        let g = joint_grid(-2.0 * TAU / 2.0 * 2.0, TAU, 10.0 * DEG, true, true); // −360..360
        assert_eq!(g.len(), 36);
        assert!((g.first() + PI).abs() < 1e-12 && (g.last() - 170.0 * DEG).abs() < 1e-12);
        let g = joint_grid(-185.0 * DEG, 185.0 * DEG, 10.0 * DEG, true, true);
        assert_eq!(g.len(), 36);
        let g = joint_grid(-60.0 * DEG, 85.0 * DEG, 10.0 * DEG, true, false);
        assert_eq!((g.first() / DEG).round() as i64, -60);
        assert_eq!((g.last() / DEG).round() as i64, 80);
        // With ends: −59 (off the grid by 9°) and 84 (4°) join −50..80; 1.5° off is on it.
        let g = joint_grid(-59.0 * DEG, 84.0 * DEG, 10.0 * DEG, true, true);
        let v: Vec<i64> = (0..g.len())
            .map(|j| (g.value(j) / DEG).round() as i64)
            .collect();
        assert_eq!(
            v,
            [-59, -50, -40, -30, -20, -10, 0, 10, 20, 30, 40, 50, 60, 70, 80, 84]
        );
        let g = joint_grid(-61.5 * DEG, 81.5 * DEG, 10.0 * DEG, true, true);
        let v: Vec<i64> = (0..g.len())
            .map(|j| (g.value(j) / DEG).round() as i64)
            .collect();
        assert_eq!((v[0], v[v.len() - 1], v.len()), (-60, 80, 15));
        // Ends are printable values inside the range (the 0.001 deg grid of every dialect):
        // 1/3 deg margins print as x.666, inside.
        let g = joint_grid(
            (-60.0 + 1.0 / 3.0) * DEG,
            (85.0 - 1.0 / 3.0) * DEG,
            10.0 * DEG,
            true,
            true,
        );
        let (a, b) = (g.first() / DEG, g.last() / DEG);
        assert!(
            (a - -59.666).abs() < 1e-9 && (b - 84.666).abs() < 1e-9,
            "{a} {b}"
        );
        let g = joint_grid(0.2, 1.0, 0.1, false, true);
        assert_eq!((g.len(), g.value(0)), (1, 0.2));
    }
}
