//! Safety: in = robot, cell, collision scene and joint-space motions; out = verdicts that name
//! the first violation, or the extremes seen (bar length, cone angles, clearance).
//!
//! A pose is checked against joint limits, the wiring-harness limits, the bar range, the floor,
//! the socket and tool-cup cones, and collisions with the safety margin. A motion (a straight
//! joint move or a blend curve) is checked continuously:
//! - it is sampled so that no point of any body moves more than margin/4 between samples (the
//!   bound comes from the scene's per-joint sweep radii and the joints' total variation); every
//!   sample keeps the full margin, so between samples the clearance stays above margin/2 > 0;
//! - the bar length and the cone angles are then proven between samples with Lipschitz bounds
//!   (a function whose slope is at most K stays within (f(a)+f(b))/2 ± K·h/2 on [a, b]),
//!   bisecting where the bound is not yet tight enough, to 0.01 mm and 0.01°.

pub mod blend;
pub mod path;
pub mod roadmap;

use crate::collision::{Coherence, Contact, Scene};
use crate::ir::{Cell, Reason};
use crate::model::MeasurementModel;
use crate::robot::kinematics::chain_frames;
use crate::robot::Robot;
use crate::units::{fmt_fixed, to_deg, to_mm};
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

/// Tolerances of the continuous proof between samples.
pub const BAR_TOLERANCE: f64 = 1e-5; // 0.01 mm
pub const ANGLE_TOLERANCE: f64 = 0.01 * std::f64::consts::PI / 180.0;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Violation {
    pub reason: Reason,
    /// What hit what, or which limit, with the numbers (one line, mm and degrees).
    pub detail: String,
}

impl std::fmt::Display for Violation {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {}", self.reason.name(), self.detail)
    }
}

/// The quantities of one admitted pose that the continuous proof needs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseInfo {
    pub length: f64,
    pub socket: f64,
    pub cup: f64,
}

/// The extremes met along everything checked (for summaries and reports).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Extremes {
    pub min_length: f64,
    pub max_length: f64,
    pub max_socket_angle: f64,
    pub max_cup_angle: f64,
    pub samples: u64,
}

impl Default for Extremes {
    fn default() -> Self {
        Extremes {
            min_length: f64::INFINITY,
            max_length: 0.0,
            max_socket_angle: 0.0,
            max_cup_angle: 0.0,
            samples: 0,
        }
    }
}

impl Extremes {
    fn add(&mut self, p: &PoseInfo) {
        self.min_length = self.min_length.min(p.length);
        self.max_length = self.max_length.max(p.length);
        self.max_socket_angle = self.max_socket_angle.max(p.socket);
        self.max_cup_angle = self.max_cup_angle.max(p.cup);
        self.samples += 1;
    }

    pub fn merge(&mut self, o: &Extremes) {
        self.min_length = self.min_length.min(o.min_length);
        self.max_length = self.max_length.max(o.max_length);
        self.max_socket_angle = self.max_socket_angle.max(o.max_socket_angle);
        self.max_cup_angle = self.max_cup_angle.max(o.max_cup_angle);
        self.samples += o.samples;
    }
}

/// Everything a check needs; immutable and shareable across threads.
pub struct Checker<'a> {
    pub robot: &'a Robot,
    pub model: &'a MeasurementModel,
    pub cell: &'a Cell,
    pub scene: &'a Scene,
    pub margin: f64,
    /// The EDBB is in place: bar range, cones and the bar's collisions apply. Without it (a
    /// transit between sections) only limits, harness and the robot's collisions do.
    pub mounted: bool,
    sweep: [f64; 6],
    lo: [f64; 6],
    hi: [f64; 6],
    /// The planner's memory of straight moves already checked (see [`LineMemo`]); none for
    /// `verify`, which re-checks everything.
    memo: Option<&'a LineMemo>,
}

/// The verdicts of straight moves already checked, with the extremes each met, so that the
/// planner checks a move once however often its searches reach it (the repair rounds, the
/// roadmap searches of neighbouring legs and the insertion of deferred poses go over the same
/// moves again and again: on a ±360° arm half of them were repeats). A verdict is a function of
/// the move and the checker (bar mounted or not), so replaying it changes nothing: the same
/// result and, merged, the same extremes. Shared by the planning threads; a move two threads
/// check at once is checked twice and stored once.
#[derive(Default)]
pub struct LineMemo {
    seen: std::sync::Mutex<std::collections::HashMap<LineKey, Checked>>,
}

/// A straight move: the checker's mode and the bits of both ends.
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
struct LineKey(bool, [u64; 12]);

impl LineKey {
    fn new(mounted: bool, a: &[f64; 6], b: &[f64; 6]) -> Self {
        LineKey(
            mounted,
            std::array::from_fn(|k| if k < 6 { a[k] } else { b[k - 6] }.to_bits()),
        )
    }
}

/// What a check of one move found: its extremes and its verdict.
type Checked = (Extremes, Result<(), (f64, Violation)>);

impl LineMemo {
    fn get(&self, key: &LineKey) -> Option<Checked> {
        self.lock().get(key).cloned()
    }

    fn put(&self, key: LineKey, checked: Checked) {
        self.lock().insert(key, checked);
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, std::collections::HashMap<LineKey, Checked>> {
        // A panic elsewhere cannot leave a half-written entry: insert is one call.
        self.seen.lock().unwrap_or_else(|e| e.into_inner())
    }
}

impl<'a> Checker<'a> {
    pub fn new(
        robot: &'a Robot,
        model: &'a MeasurementModel,
        cell: &'a Cell,
        scene: &'a Scene,
        margin: f64,
    ) -> Self {
        // Poses and motions keep the cell's joint margin from every limit.
        let (mut lo, mut hi) = robot.limits();
        for i in 0..6 {
            lo[i] += cell.joint_margin;
            hi[i] -= cell.joint_margin;
        }
        Checker {
            robot,
            model,
            cell,
            scene,
            margin,
            mounted: true,
            sweep: scene.sweep_radius(),
            lo,
            hi,
            memo: None,
        }
    }

    /// The same checker with the planner's memory of checked moves (for planning only).
    pub fn remembering<'m>(&self, memo: &'m LineMemo) -> Checker<'m>
    where
        'a: 'm,
    {
        Checker {
            memo: Some(memo),
            ..*self
        }
    }

    /// The joint range every pose and motion must keep: the robot's limits less the cell's
    /// joint margin.
    pub fn limits(&self) -> ([f64; 6], [f64; 6]) {
        (self.lo, self.hi)
    }

    /// The same checks with the bar removed.
    pub fn unmounted(&self) -> Self {
        Checker {
            mounted: false,
            ..*self
        }
    }

    /// The full check of one pose.
    pub fn pose(&self, q: &[f64; 6]) -> Result<PoseInfo, Violation> {
        self.pose_along(q, None)
    }

    /// [`Checker::pose`] at the sample `s` of a motion whose memory is `along` (the same
    /// verdict; collision pairs the motion has proven clear are not queried again).
    fn pose_along(
        &self,
        q: &[f64; 6],
        along: Option<(f64, &mut Coherence)>,
    ) -> Result<PoseInfo, Violation> {
        for i in 0..6 {
            if !(q[i] >= self.lo[i] - 1e-9 && q[i] <= self.hi[i] + 1e-9) {
                return Err(Violation {
                    reason: Reason::JointLimit,
                    detail: format!(
                        "joint {} ({}) at {} deg outside {}..{} deg (limits {}..{} deg less the {} deg joint margin)",
                        i + 1,
                        self.robot.joints[i].name,
                        deg(q[i]),
                        deg(self.lo[i]),
                        deg(self.hi[i]),
                        deg(self.robot.joints[i].lower),
                        deg(self.robot.joints[i].upper),
                        deg(self.cell.joint_margin)
                    ),
                });
            }
        }
        let frames = chain_frames(
            &self.model.base,
            &self.model.nominal.dh,
            &self.model.flange,
            q,
        );
        let map = frames[7].apply(&self.model.nominal.map);
        let cup = frames[7].r * self.cell.tool_axis;
        if !self.mounted {
            if !self.cell.cables_admit(q) {
                let detail = self.describe(Reason::CableLimit, q, &map, &cup);
                return Err(Violation {
                    reason: Reason::CableLimit,
                    detail,
                });
            }
            let hit = match along {
                Some((s, co)) => self
                    .scene
                    .violation_along(q, &frames, None, self.margin, s, co),
                None => self.scene.violation_unmounted(q, &frames, self.margin),
            };
            if let Some(c) = hit {
                let detail = describe_contact(&c, self.margin);
                return Err(Violation {
                    reason: Reason::Collision,
                    detail,
                });
            }
            let length = (map - self.cell.fixture).norm();
            return Ok(PoseInfo {
                length,
                socket: 0.0,
                cup: 0.0,
            });
        }
        if let Err(reason) = self.cell.verdict(q, &map, &cup) {
            return Err(Violation {
                reason,
                detail: self.describe(reason, q, &map, &cup),
            });
        }
        let hit = match along {
            Some((s, co)) => self
                .scene
                .violation_along(q, &frames, Some(&map), self.margin, s, co),
            None => self.scene.violation(q, &frames, &map, self.margin),
        };
        if let Some(c) = hit {
            return Err(Violation {
                reason: Reason::Collision,
                detail: describe_contact(&c, self.margin),
            });
        }
        let length = (map - self.cell.fixture).norm();
        let (socket, cup) = self.cell.cone_angles(&map, &cup);
        Ok(PoseInfo {
            length,
            socket,
            cup,
        })
    }

    /// Minimum clearance at a pose (slower than the margin test: every pair is measured).
    pub fn clearance(&self, q: &[f64; 6]) -> Contact {
        let frames = chain_frames(
            &self.model.base,
            &self.model.nominal.dh,
            &self.model.flange,
            q,
        );
        let map = frames[7].apply(&self.model.nominal.map);
        self.scene.clearance(q, &frames, &map)
    }

    fn describe(
        &self,
        reason: Reason,
        q: &[f64; 6],
        map: &Vector3<f64>,
        cup: &Vector3<f64>,
    ) -> String {
        let c = self.cell;
        match reason {
            Reason::CableLimit => {
                let names = ["q4", "q6", "q4 + q6"];
                let vals = [q[3], q[5], q[3] + q[5]];
                (0..3)
                    .find_map(|k| {
                        c.cables[k]
                            .filter(|r| vals[k] < r[0] || vals[k] > r[1])
                            .map(|r| {
                                format!(
                                    "{} = {} deg outside the harness range {}..{} deg",
                                    names[k],
                                    deg(vals[k]),
                                    deg(r[0]),
                                    deg(r[1])
                                )
                            })
                    })
                    .unwrap_or_else(|| "harness limit".into())
            }
            Reason::BarLength => format!(
                "bar length {} mm outside {}..{} mm",
                fmt_fixed(to_mm((map - c.fixture).norm()), 3),
                fmt_fixed(to_mm(c.bar_min), 1),
                fmt_fixed(to_mm(c.bar_max), 1)
            ),
            Reason::Floor => format!(
                "MAP at z = {} mm, not above the floor at {} mm",
                fmt_fixed(to_mm(map.z), 1),
                fmt_fixed(to_mm(c.floor_z), 1)
            ),
            Reason::SocketCone => {
                let (s, _) = c.cone_angles(map, cup);
                format!(
                    "bar at {} deg from the socket axis (cone {} deg)",
                    fmt_fixed(to_deg(s), 2),
                    fmt_fixed(to_deg(c.fixture_cone_cos.acos()), 1)
                )
            }
            Reason::CupCone => {
                let (_, t) = c.cone_angles(map, cup);
                format!(
                    "bar at {} deg from the tool-cup axis (cone {} deg)",
                    fmt_fixed(to_deg(t), 2),
                    fmt_fixed(to_deg(c.tool_cone_cos.acos()), 1)
                )
            }
            Reason::JointLimit | Reason::JointSpeed | Reason::Collision | Reason::Program => {
                reason.name().to_string()
            }
        }
    }

    /// Continuous check of a curve q(s), s ∈ [0, 1], whose joints move at most `lipschitz[i]`
    /// radians per unit of s (for a straight move: the joints' travel). Returns the parameter
    /// and the violation of the first failure.
    pub fn curve(
        &self,
        q: &Curve,
        lipschitz: &[f64; 6],
        ext: &mut Extremes,
    ) -> Result<(), (f64, Violation)> {
        let motion: f64 = (0..6).map(|i| self.sweep[i] * lipschitz[i]).sum();
        let rotation: f64 = lipschitz.iter().sum();
        let step = if self.margin > 0.0 {
            self.margin / 4.0
        } else {
            1e-3
        };
        let n = ((motion / step).ceil() as usize).clamp(1, 1_000_000);
        let walk = Walk {
            q,
            lipschitz,
            n,
            m: motion / n as f64,
            w: rotation / n as f64,
            parallel: rayon::current_num_threads() > 1,
        };
        self.samples(&walk, 0, n, ext)
    }

    /// Samples `k0..=k1` of a walk along a curve: the pose at each, and between consecutive
    /// ones the proof of the bar range and cones. A long stretch is cut in two halves checked
    /// at once (`rayon::join`, when there is more than one thread): each sample's verdict is
    /// the full check's whatever the motion's memory ([`Coherence`]), so the halves find the
    /// same first failure, the same samples and the same extremes as one walk; the second
    /// half only starts its memory afresh. Sample `k0` counts in the extremes only at the
    /// curve's start (elsewhere it ends the stretch before).
    fn samples(
        &self,
        walk: &Walk,
        k0: usize,
        k1: usize,
        ext: &mut Extremes,
    ) -> Result<(), (f64, Violation)> {
        if walk.parallel && k1 - k0 >= 2 * CHUNK_SAMPLES {
            let mid = (k0 + k1) / 2;
            let (mut e0, mut e1) = (Extremes::default(), Extremes::default());
            let (r0, r1) = rayon::join(
                || self.samples(walk, k0, mid, &mut e0),
                || self.samples(walk, mid, k1, &mut e1),
            );
            ext.merge(&e0);
            r0?;
            ext.merge(&e1);
            return r1;
        }
        let at = |k: usize| k as f64 / walk.n as f64;
        let mut co = self.scene.coherence(walk.lipschitz);
        let mut prev_s = at(k0);
        let mut prev = self
            .pose_along(&(walk.q)(prev_s), Some((prev_s, &mut co)))
            .map_err(|v| (prev_s, v))?;
        if self.mounted && k0 == 0 {
            ext.add(&prev);
        }
        for k in k0 + 1..=k1 {
            let s = at(k);
            let cur = self
                .pose_along(&(walk.q)(s), Some((s, &mut co)))
                .map_err(|v| (s, v))?;
            if self.mounted {
                ext.add(&cur);
            }
            self.refine(
                walk.q, prev_s, prev, s, cur, walk.m, walk.w, 0, &mut co, ext,
            )?;
            prev_s = s;
            prev = cur;
        }
        Ok(())
    }

    /// Proves the bar length and the cone angles between two admitted samples, bisecting where
    /// the Lipschitz bound does not yet do it. `m`: bound on the MAP's motion over [s0, s1];
    /// `w`: bound on the flange's rotation (rad).
    #[allow(clippy::too_many_arguments)]
    fn refine(
        &self,
        q: &Curve,
        s0: f64,
        a: PoseInfo,
        s1: f64,
        b: PoseInfo,
        m: f64,
        w: f64,
        depth: u32,
        co: &mut Coherence,
        ext: &mut Extremes,
    ) -> Result<(), (f64, Violation)> {
        if !self.mounted {
            return Ok(());
        }
        let c = self.cell;
        let lmin = a.length.min(b.length) - m;
        let ang = if lmin > 0.0 { m / lmin } else { f64::INFINITY };
        let ok_len = (a.length + b.length) / 2.0 + m / 2.0 <= c.bar_max + BAR_TOLERANCE
            && (a.length + b.length) / 2.0 - m / 2.0 >= c.bar_min - BAR_TOLERANCE;
        let socket_limit = c.fixture_cone_cos.clamp(-1.0, 1.0).acos();
        let cup_limit = c.tool_cone_cos.clamp(-1.0, 1.0).acos();
        let ok_socket = c.fixture_cone_cos <= -1.0
            || (a.socket + b.socket) / 2.0 + ang / 2.0 <= socket_limit + ANGLE_TOLERANCE;
        let ok_cup = c.tool_cone_cos <= -1.0
            || (a.cup + b.cup) / 2.0 + (ang + w) / 2.0 <= cup_limit + ANGLE_TOLERANCE;
        if ok_len && ok_socket && ok_cup {
            return Ok(());
        }
        if depth >= 40 {
            let s = 0.5 * (s0 + s1);
            return Err((
                s,
                Violation {
                    reason: Reason::BarLength,
                    detail: "cannot prove the bar range and cones between samples".into(),
                },
            ));
        }
        let s = 0.5 * (s0 + s1);
        let mid = self
            .pose_along(&q(s), Some((s, &mut *co)))
            .map_err(|v| (s, v))?;
        if self.mounted {
            ext.add(&mid);
        }
        self.refine(q, s0, a, s, mid, m / 2.0, w / 2.0, depth + 1, co, ext)?;
        self.refine(q, s, mid, s1, b, m / 2.0, w / 2.0, depth + 1, co, ext)
    }

    /// Per joint, a bound on how far any body point (the MAP included) moves per radian.
    pub fn sweep_radius(&self) -> [f64; 6] {
        self.sweep
    }

    /// The grid a [`Checker::patch`] of this region checks: (n1 + 1)·(n2 + 1) poses, the
    /// cost the planner weighs before it tries a blend.
    pub fn patch_grid(&self, e1: &[f64; 6], e2: &[f64; 6]) -> (usize, usize) {
        let step = self.sample_step();
        let n = |e: &[f64; 6]| {
            let m: f64 = (0..6).map(|i| self.sweep[i] * e[i].abs()).sum();
            ((m / step).ceil() as usize).clamp(1, 100_000)
        };
        (n(e1), n(e2))
    }

    fn sample_step(&self) -> f64 {
        if self.margin > 0.0 {
            self.margin / 4.0
        } else {
            1e-3
        }
    }

    /// Continuous check of a surface: every pose o + u·e1 + w·e2, u, w ∈ [0, 1] (a corner
    /// region, [`blend::Region`]). The grid is spaced like [`Checker::curve`]'s samples: every
    /// point of the surface lies within margin/4 of body motion from a grid pose, and every grid
    /// pose keeps the full margin, so the clearance stays above margin/2. Joint and harness limits
    /// are linear in (u, w): the corners of the grid bound them. The bar length and the cone
    /// angles are proven on every cell from its four poses and a Lipschitz bound, subdividing
    /// where that is not yet tight enough. Returns the (u, w) and the violation of a failure.
    pub fn patch(
        &self,
        o: &[f64; 6],
        e1: &[f64; 6],
        e2: &[f64; 6],
        ext: &mut Extremes,
    ) -> Result<(), ((f64, f64), Violation)> {
        let (n1, n2) = self.patch_grid(e1, e2);
        let at =
            |u: f64, w: f64| -> [f64; 6] { std::array::from_fn(|i| o[i] + u * e1[i] + w * e2[i]) };
        let check =
            |u: f64, w: f64, ext: &mut Extremes| -> Result<PoseInfo, ((f64, f64), Violation)> {
                let info = self.pose(&at(u, w)).map_err(|v| ((u, w), v))?;
                if self.mounted {
                    ext.add(&info);
                }
                Ok(info)
            };
        // One row of the grid at a time: memory O(n2).
        let mut prev: Vec<PoseInfo> = Vec::with_capacity(n2 + 1);
        for j in 0..=n2 {
            prev.push(check(0.0, j as f64 / n2 as f64, ext)?);
        }
        let m1: f64 = (0..6).map(|i| self.sweep[i] * e1[i].abs()).sum();
        let m2: f64 = (0..6).map(|i| self.sweep[i] * e2[i].abs()).sum();
        let r1: f64 = e1.iter().map(|x| x.abs()).sum();
        let r2: f64 = e2.iter().map(|x| x.abs()).sum();
        for i in 1..=n1 {
            let u = i as f64 / n1 as f64;
            let mut cur: Vec<PoseInfo> = Vec::with_capacity(n2 + 1);
            for j in 0..=n2 {
                cur.push(check(u, j as f64 / n2 as f64, ext)?);
            }
            for j in 0..n2 {
                let cell = GridCell {
                    u0: (i - 1) as f64 / n1 as f64,
                    w0: j as f64 / n2 as f64,
                    du: 1.0 / n1 as f64,
                    dw: 1.0 / n2 as f64,
                };
                let v = [prev[j], prev[j + 1], cur[j], cur[j + 1]];
                self.refine_cell(&at, &cell, v, (m1, m2), (r1, r2), 0, ext)?;
            }
            prev = cur;
        }
        Ok(())
    }

    /// Proves the bar length and the cones over one grid cell from its corner poses `v`
    /// ((u0, w0), (u0, w1), (u1, w0), (u1, w1)), subdividing into four where the bound is not
    /// tight enough. `m`: the MAP's motion per unit of u and of w; `r`: the flange's rotation.
    #[allow(clippy::too_many_arguments)]
    fn refine_cell(
        &self,
        at: &dyn Fn(f64, f64) -> [f64; 6],
        c: &GridCell,
        v: [PoseInfo; 4],
        m: (f64, f64),
        r: (f64, f64),
        depth: u32,
        ext: &mut Extremes,
    ) -> Result<(), ((f64, f64), Violation)> {
        if !self.mounted {
            return Ok(());
        }
        let cl = self.cell;
        // Every point of the cell is within h of some corner of it (MAP motion), w of rotation.
        let h = (m.0 * c.du + m.1 * c.dw) / 2.0;
        let w = (r.0 * c.du + r.1 * c.dw) / 2.0;
        let max = |f: &dyn Fn(&PoseInfo) -> f64| v.iter().map(f).fold(f64::NEG_INFINITY, f64::max);
        let min_len = v.iter().map(|p| p.length).fold(f64::INFINITY, f64::min);
        let max_len = max(&|p| p.length);
        let lmin = min_len - h;
        let ang = if lmin > 0.0 { h / lmin } else { f64::INFINITY };
        let ok_len =
            max_len + h <= cl.bar_max + BAR_TOLERANCE && min_len - h >= cl.bar_min - BAR_TOLERANCE;
        let socket_limit = cl.fixture_cone_cos.clamp(-1.0, 1.0).acos();
        let cup_limit = cl.tool_cone_cos.clamp(-1.0, 1.0).acos();
        let ok_socket = cl.fixture_cone_cos <= -1.0
            || max(&|p| p.socket) + ang <= socket_limit + ANGLE_TOLERANCE;
        let ok_cup =
            cl.tool_cone_cos <= -1.0 || max(&|p| p.cup) + ang + w <= cup_limit + ANGLE_TOLERANCE;
        if ok_len && ok_socket && ok_cup {
            return Ok(());
        }
        let (um, wm) = (c.u0 + c.du / 2.0, c.w0 + c.dw / 2.0);
        if depth >= 24 {
            return Err((
                (um, wm),
                Violation {
                    reason: Reason::BarLength,
                    detail: "cannot prove the bar range and cones over the corner region".into(),
                },
            ));
        }
        let probe =
            |u: f64, w: f64, ext: &mut Extremes| -> Result<PoseInfo, ((f64, f64), Violation)> {
                let info = self.pose(&at(u, w)).map_err(|v| ((u, w), v))?;
                ext.add(&info);
                Ok(info)
            };
        let (u1, w1) = (c.u0 + c.du, c.w0 + c.dw);
        let mid = probe(um, wm, ext)?;
        let left = probe(um, c.w0, ext)?; // (um, w0)
        let right = probe(um, w1, ext)?; // (um, w1)
        let low = probe(c.u0, wm, ext)?; // (u0, wm)
        let high = probe(u1, wm, ext)?; // (u1, wm)
        let (hu, hw) = (c.du / 2.0, c.dw / 2.0);
        let sub = |u0: f64, w0: f64| GridCell {
            u0,
            w0,
            du: hu,
            dw: hw,
        };
        self.refine_cell(
            at,
            &sub(c.u0, c.w0),
            [v[0], low, left, mid],
            m,
            r,
            depth + 1,
            ext,
        )?;
        self.refine_cell(
            at,
            &sub(c.u0, wm),
            [low, v[1], mid, right],
            m,
            r,
            depth + 1,
            ext,
        )?;
        self.refine_cell(
            at,
            &sub(um, c.w0),
            [left, mid, v[2], high],
            m,
            r,
            depth + 1,
            ext,
        )?;
        self.refine_cell(
            at,
            &sub(um, wm),
            [mid, right, high, v[3]],
            m,
            r,
            depth + 1,
            ext,
        )
    }

    /// [`Checker::line`]'s verdict for searches that only need yes or no: a few poses along
    /// the move are checked first, so a move that fails far from `a` fails fast; a move that
    /// passes them gets the full continuous check (and its extremes).
    pub fn line_passes(&self, a: &[f64; 6], b: &[f64; 6], ext: &mut Extremes) -> bool {
        PROBES.iter().all(|&s| self.pose(&lerp(a, b, s)).is_ok()) && self.line(a, b, ext).is_ok()
    }

    /// Continuous check of the straight joint move a → b.
    pub fn line(
        &self,
        a: &[f64; 6],
        b: &[f64; 6],
        ext: &mut Extremes,
    ) -> Result<(), (f64, Violation)> {
        let var: [f64; 6] = std::array::from_fn(|i| (b[i] - a[i]).abs());
        let Some(memo) = self.memo else {
            return self.curve(&|s| lerp(a, b, s), &var, ext);
        };
        let key = LineKey::new(self.mounted, a, b);
        let (met, verdict) = memo.get(&key).unwrap_or_else(|| {
            let mut met = Extremes::default();
            let verdict = self.curve(&|s| lerp(a, b, s), &var, &mut met);
            memo.put(key, (met.clone(), verdict.clone()));
            (met, verdict)
        });
        // Extremes are minima, maxima and a count: merging what the move met is the same as
        // having met it sample by sample.
        ext.merge(&met);
        verdict
    }
}

/// A motion q(s), s ∈ [0, 1], as the continuous checks take it.
pub type Curve<'c> = dyn Fn(f64) -> [f64; 6] + Sync + 'c;

/// One continuous check's fixed quantities: the curve, its joints' Lipschitz bounds, the number
/// of samples, and the bounds on the MAP's motion and the flange's rotation between two.
struct Walk<'w> {
    q: &'w Curve<'w>,
    lipschitz: &'w [f64; 6],
    n: usize,
    m: f64,
    w: f64,
    parallel: bool,
}

/// A continuous check's stretch of at least twice this many samples is cut in two and checked
/// on two threads: long enough that the second half's fresh memory (every collision pair
/// measured once at its start) costs little next to it.
const CHUNK_SAMPLES: usize = 256;

/// A cell of a [`Checker::patch`] grid: [u0, u0 + du] × [w0, w0 + dw].
struct GridCell {
    u0: f64,
    w0: f64,
    du: f64,
    dw: f64,
}

/// Where [`Checker::line_passes`] looks before the full check.
const PROBES: [f64; 3] = [0.5, 0.25, 0.75];

pub fn lerp(a: &[f64; 6], b: &[f64; 6], s: f64) -> [f64; 6] {
    std::array::from_fn(|i| a[i] + (b[i] - a[i]) * s)
}

fn deg(rad: f64) -> String {
    fmt_fixed(to_deg(rad), 2)
}

pub fn describe_contact(c: &Contact, margin: f64) -> String {
    if c.distance < 0.0 {
        format!(
            "{} and {} intersect by {} mm",
            c.a,
            c.b,
            fmt_fixed(to_mm(-c.distance), 2)
        )
    } else {
        format!(
            "{} and {} are {} mm apart (margin {} mm)",
            c.a,
            c.b,
            fmt_fixed(to_mm(c.distance), 2),
            fmt_fixed(to_mm(margin), 1)
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline;
    use rand::{Rng, SeedableRng};

    #[test]
    fn a_long_check_cut_in_halves_on_two_threads_is_the_one_walk() {
        // The same verdicts, first failures and extremes (sample counts included) on one
        // thread (one walk) and on two (stretches checked at once), for moves short and long,
        // passing and failing, with the bar and without.
        let root = env!("CARGO_MANIFEST_DIR");
        let robot = crate::robot::load(
            std::path::Path::new(&format!("{root}/robots/comau_nj130/robot.dh.toml")),
            &Default::default(),
        )
        .unwrap();
        let spec = crate::cell::load(std::path::Path::new(&format!(
            "{root}/robots/comau_nj130/cell.toml"
        )))
        .unwrap();
        let fixture = spec.fixture.unwrap();
        let (map, _) = pipeline::resolve_map(&robot, spec.map);
        let cell = pipeline::make_cell(&robot, fixture, map, &spec).unwrap();
        let model = MeasurementModel::new(&robot, fixture, map);
        let (scene, _) = pipeline::build_scene(&robot, &spec, &fixture, &map).unwrap();
        let ck = Checker::new(&robot, &model, &cell, &scene, spec.margin);
        let (lo, hi) = ck.limits();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let (one, two) = (pool(1), pool(2));
        let (mut long, mut failed, mut passed) = (0, 0, 0);
        for _ in 0..40 {
            let a: [f64; 6] = std::array::from_fn(|i| rng.random_range(lo[i]..hi[i]));
            let scale = [0.05, 0.5, 1.0][rng.random_range(0..3)];
            let b: [f64; 6] = std::array::from_fn(|i| {
                (a[i] + scale * rng.random_range(-2.0..2.0)).clamp(lo[i], hi[i])
            });
            for c in [ck.unmounted(), Checker { ..ck }] {
                let run = || {
                    let mut e = Extremes::default();
                    let r = c.line(&a, &b, &mut e);
                    (r, e)
                };
                let (r1, e1) = one.install(run);
                let (r2, e2) = two.install(run);
                assert_eq!(r1, r2, "{a:?} -> {b:?}");
                assert_eq!(e1, e2, "{a:?} -> {b:?}");
                let n = (0..6)
                    .map(|i| c.sweep[i] * (b[i] - a[i]).abs())
                    .sum::<f64>()
                    / (c.margin / 4.0);
                if n > 4.0 * CHUNK_SAMPLES as f64 {
                    long += 1;
                    if r1.is_ok() {
                        passed += 1;
                    } else {
                        failed += 1;
                    }
                }
            }
        }
        assert!(
            long > 10 && passed > 2 && failed > 2,
            "{long} long: {passed} passed, {failed} failed"
        );
    }
}
