//! Sections: in = the admitted poses (grid order), the safety checker and the joint speeds; out
//! = [`Sections`]: the pool (the poses of the groups kept), every pool pose's group and a
//! [`SectionsReport`]; and, for a selection, its poses split into ordered sections
//! ([`order`]).
//!
//! Poses that safe motions (bar mounted) connect form a group; the program measures one group
//! per section and the operator remounts the bar between sections. Groups too small to be
//! worth a remount are left out of the pool.

use super::PipelineError;
use crate::emit;
use crate::ir::{Candidate, Pool};
use crate::order;
use crate::safety::path::{Plan, Section};
use crate::safety::roadmap;
use crate::safety::Checker;
use serde::Serialize;

/// At most this many sections, each with at least this many admitted poses (and 2 % of the
/// pool); smaller groups are left out.
pub const MAX_SECTIONS: usize = 4;
pub const MIN_SECTION_POSES: usize = 10;
/// A section must hold at least this many measurement poses (the selection measures a section
/// with this many or not at all: a remount is not worth fewer).
pub const MIN_POSES_PER_SECTION: usize = 3;
/// Neighbours per pose in the connectivity graph of the pool (the graph the planner's complete
/// search walks, [`roadmap::route`]).
pub const COMPONENT_NEIGHBOURS: usize = roadmap::LINKS;
/// Group sizes listed in the report (the largest); the rest are counted.
const LISTED_GROUPS: usize = 10;

/// The pool split into groups that safe motions connect.
#[derive(Clone, Debug)]
pub struct Sections {
    /// The admitted poses in the groups kept, in grid order.
    pub pool: Pool,
    /// The group of every pool pose (0 = the largest).
    pub group: Vec<usize>,
    /// Groups kept: labels `0..kept`.
    pub kept: usize,
    pub report: SectionsReport,
}

/// What the sections stage found (`--json` key `sections`).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct SectionsReport {
    /// Connected groups among the admitted poses.
    pub groups: usize,
    /// Sizes of the largest groups (at most 10), largest first.
    pub largest_groups: Vec<usize>,
    /// Groups kept as sections and the poses a group needs to be kept.
    pub kept_groups: usize,
    pub min_group_poses: usize,
    /// Admitted poses outside the kept groups (left out of the pool).
    pub disconnected: usize,
    /// Neighbours each pose is linked to when the groups are found.
    pub neighbours: usize,
    /// Measurement poses of every section of the program, in program order (after planning).
    pub measured_per_section: Vec<usize>,
}

impl Sections {
    /// Groups `admitted` (grid order) and keeps the groups worth a section.
    pub fn group(ck: &Checker, admitted: &[Candidate], speeds: &[f64; 6]) -> Sections {
        let qs: Vec<[f64; 6]> = admitted.iter().map(|c| c.q).collect();
        let labels = roadmap::components(ck, &qs, speeds, COMPONENT_NEIGHBOURS);
        let groups = labels.iter().copied().max().map_or(0, |l| l + 1);
        let mut size = vec![0usize; groups];
        for &l in &labels {
            size[l] += 1;
        }
        let min_group = MIN_SECTION_POSES.max(admitted.len() / 50);
        let kept = size
            .iter()
            .take(MAX_SECTIONS)
            .filter(|&&n| n >= min_group)
            .count()
            .max(1);
        let keep: Vec<usize> = (0..admitted.len()).filter(|&i| labels[i] < kept).collect();
        let disconnected = admitted.len() - keep.len();
        Sections {
            pool: Pool {
                candidates: keep.iter().map(|&i| admitted[i]).collect(),
            },
            group: keep.iter().map(|&i| labels[i]).collect(),
            kept,
            report: SectionsReport {
                groups,
                largest_groups: size.iter().copied().take(LISTED_GROUPS).collect(),
                kept_groups: kept,
                min_group_poses: min_group,
                disconnected,
                neighbours: COMPONENT_NEIGHBOURS,
                measured_per_section: Vec::new(),
            },
        }
    }

    /// The warning for poses left out, if any.
    pub fn warning(&self) -> Option<String> {
        let d = self.report.disconnected;
        (d > 0).then(|| {
            format!(
                "{d} of {} admitted poses lie in small groups that safe motions do not connect to the rest; left out",
                self.pool.candidates.len() + d
            )
        })
    }

    /// Splits the chosen poses (pool indices) into sections by group and orders them: the
    /// section nearest to the current position first (Eq. 7), a time-optimal tour inside each,
    /// starting at its pose nearest to where the previous section ended. Returns the sections
    /// (on the joint values the program text carries) and the Eq. 7 time of the chosen poses
    /// in pool order (the "unsorted" time).
    pub fn order(
        &self,
        chosen: &[usize],
        start: &[f64; 6],
        speeds: &[f64; 6],
        accel: Option<&[f64; 6]>,
    ) -> Result<(Vec<Section>, f64), PipelineError> {
        let pool = &self.pool.candidates;
        let all: Vec<[f64; 6]> = chosen.iter().map(|&i| pool[i].q).collect();
        let identity: Vec<usize> = (0..all.len()).collect();
        let time_unsorted = order::path_time(&all, &identity, speeds);
        let mut left: Vec<usize> = (0..self.kept)
            .filter(|g| chosen.iter().any(|&i| self.group[i] == *g))
            .collect();
        let mut here = *start;
        let mut sections = Vec::new();
        while !left.is_empty() {
            // The group with the pose nearest to here.
            let (gi, _) = left
                .iter()
                .enumerate()
                .map(|(gi, &g)| {
                    let d = chosen
                        .iter()
                        .filter(|&&i| self.group[i] == g)
                        .map(|&i| order::move_time(&here, &pool[i].q, speeds))
                        .fold(f64::INFINITY, f64::min);
                    (gi, d)
                })
                .fold((0, f64::INFINITY), |b, c| if c.1 < b.1 { c } else { b });
            let g = left.remove(gi);
            let poses: Vec<[f64; 6]> = chosen
                .iter()
                .filter(|&&i| self.group[i] == g)
                .map(|&i| pool[i].q)
                .collect();
            let first = (0..poses.len())
                .map(|k| (k, order::move_time(&here, &poses[k], speeds)))
                .fold((0, f64::INFINITY), |b, c| if c.1 < b.1 { c } else { b })
                .0;
            let tour = order::solve_with(&poses, first, speeds, accel)?;
            // Plan on exactly the joint values the program text will carry.
            let ordered: Vec<[f64; 6]> = tour
                .order
                .iter()
                .map(|&k| emit::emitted(&poses[k]))
                .collect();
            if let Some(last) = ordered.last() {
                here = *last;
            }
            let support: Vec<[f64; 6]> = (0..pool.len())
                .filter(|&i| self.group[i] == g)
                .map(|i| emit::emitted(&pool[i].q))
                .collect();
            sections.push(Section {
                tour: ordered,
                pool: support,
            });
        }
        Ok((sections, time_unsorted))
    }
}

/// Measurement poses per section of a planned program, in program order: a section starts at
/// a transit's target that is not a support pose (the bar goes in there).
pub fn measured_per_section(plan: &Plan) -> Vec<usize> {
    let mut counts: Vec<usize> = Vec::new();
    for w in &plan.waypoints {
        if w.transit && !w.support {
            counts.push(0);
        }
        if !w.support {
            match counts.last_mut() {
                Some(c) => *c += 1,
                None => counts.push(1),
            }
        }
    }
    counts
}
