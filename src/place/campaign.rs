//! The best campaign of K fixture positions: in = the scored candidates (their runs'
//! information); out = the K positions whose runs, calibrated together as `calibrate` does it
//! (shared robot parameters, one known fixture per run), predict the smallest MAP position
//! uncertainty over the joint space ([`predict::expected`] on the summed information).
//!
//! Search: greedy from the best single position (each step adds the candidate that helps the
//! joint prediction most), then exchange (swap a member for a non-member while that improves
//! it), first on the proxies of the best [`super::CAMPAIGN_POOL`] candidates, then again on
//! full estimates (a compile at every member and at the fully estimated candidates). Every
//! choice is an arg-min with ties broken by candidate index, evaluated in parallel and gathered
//! in order: the same campaign on any thread count.

use super::{Campaign, Candidate, PlaceError, PlaceOptions, Status};
use crate::calibrate::predict::{self, RunInformation};
use crate::model::MeasurementModel;
use crate::robot::Robot;
use crate::sample::Progress;
use rayon::prelude::*;

/// Rounds of exchange at most (each round takes the best single swap).
const EXCHANGE_ROUNDS: usize = 20;

/// The joint prediction's workspace RMS (m) of a set of runs.
fn joint_rms(
    model: &MeasurementModel,
    infos: &[&RunInformation],
    opts: &PlaceOptions,
    poses: &[[f64; 6]],
) -> f64 {
    let e = predict::expected(model, infos, opts.compile.bar_noise, &opts.prior, poses);
    predict::spread(&e.combined).rms
}

/// Greedy, then exchange, over `pool` (candidate indices), with each candidate's information
/// from `info`. Returns the members (in the order found) and the number of evaluations and
/// swaps.
fn optimise<'a>(
    model: &MeasurementModel,
    pool: &[usize],
    info: &(dyn Fn(usize) -> &'a RunInformation + Sync),
    start: Vec<usize>,
    k: usize,
    opts: &PlaceOptions,
    poses: &[[f64; 6]],
) -> (Vec<usize>, f64, usize, usize) {
    let eval = |set: &[usize]| -> f64 {
        let infos: Vec<&RunInformation> = set.iter().map(|&i| info(i)).collect();
        joint_rms(model, &infos, opts, poses)
    };
    // The best of a list of trial sets: (value, position in the list), ties to the first.
    let best_of = |trials: &[Vec<usize>]| -> (f64, usize) {
        trials
            .par_iter()
            .map(|s| eval(s))
            .collect::<Vec<f64>>()
            .into_iter()
            .enumerate()
            .fold((f64::INFINITY, usize::MAX), |b, (i, v)| {
                if v < b.0 {
                    (v, i)
                } else {
                    b
                }
            })
    };
    let mut set = start;
    let mut evals = 0;
    while set.len() < k {
        let trials: Vec<Vec<usize>> = pool
            .iter()
            .filter(|c| !set.contains(c))
            .map(|&c| {
                let mut s = set.clone();
                s.push(c);
                s
            })
            .collect();
        if trials.is_empty() {
            break;
        }
        evals += trials.len();
        let (_, i) = best_of(&trials);
        set = trials[i].clone();
    }
    let mut value = eval(&set);
    evals += 1;
    let mut swaps = 0;
    for _ in 0..EXCHANGE_ROUNDS {
        let mut trials = Vec::new();
        for m in 0..set.len() {
            for &c in pool {
                if !set.contains(&c) {
                    let mut s = set.clone();
                    s[m] = c;
                    trials.push(s);
                }
            }
        }
        if trials.is_empty() {
            break;
        }
        evals += trials.len();
        let (v, i) = best_of(&trials);
        // A swap must improve by more than rounding: no cycling between equals.
        let improves = v < value * (1.0 - 1e-9);
        if !improves {
            break;
        }
        value = v;
        set = trials[i].clone();
        swaps += 1;
    }
    (set, value, evals, swaps)
}

/// Finds the best campaign of `opts.count` positions among the ranked candidates; compiles at
/// every member that has no full estimate yet.
#[allow(clippy::too_many_arguments)]
pub fn search(
    robot: &Robot,
    opts: &PlaceOptions,
    space: &[[f64; 6]],
    search_poses: &[[f64; 6]],
    cands: &mut [Candidate],
    ranking: &[usize],
    proxy_scale: f64,
    progress: &dyn Progress,
) -> Result<Campaign, PlaceError> {
    let k = opts.count;
    if ranking.len() < k {
        return Err(PlaceError::Count {
            count: k,
            usable: ranking.len(),
        });
    }
    let (map, _) = crate::pipeline::resolve_map(robot, opts.compile.cell.map);
    // The MAP positions, the only thing the prediction takes from the model, do not depend on
    // the fixture.
    let model = MeasurementModel::new(robot, cands[ranking[0]].fixture, map);

    // 1. On proxies (a full estimate where there is one), the proxies' information scaled to
    //    the full estimates' level (prediction ∝ 1/√N).
    let pool: Vec<usize> = ranking
        .iter()
        .copied()
        .filter(|&i| cands[i].proxy_info.is_some() || cands[i].full_info.is_some())
        .take(super::CAMPAIGN_POOL.max(k))
        .collect();
    let w = 1.0 / (proxy_scale * proxy_scale);
    let scaled: Vec<Option<RunInformation>> = cands
        .iter()
        .map(|c| match (&c.full_info, &c.proxy_info) {
            (Some(_), _) => None,
            (None, Some(p)) => Some(RunInformation {
                normal: &p.normal * w,
                readings: p.readings,
                rows: p.rows.clone(),
            }),
            _ => None,
        })
        .collect();
    let info_of = |i: usize| -> &RunInformation {
        cands[i]
            .full_info
            .as_ref()
            .or(scaled[i].as_ref())
            .expect("pool members have information")
    };
    let (proxy_set, _, evals1, swaps1) = optimise(
        &model,
        &pool,
        &info_of,
        vec![ranking[0]],
        k,
        opts,
        search_poses,
    );
    drop(scaled);

    // 2. Full estimates for the members, then exchange again among everything fully estimated.
    let mut members = proxy_set;
    for &m in &members.clone() {
        if cands[m].full_info.is_none() {
            super::full_estimate(robot, opts, space, &mut cands[m]);
            progress.inc(1);
        }
    }
    members.retain(|&m| cands[m].full_info.is_some());
    let full_pool: Vec<usize> = (0..cands.len())
        .filter(|&i| cands[i].full_info.is_some() && cands[i].status == Status::Ok)
        .collect();
    if full_pool.len() < k {
        return Err(PlaceError::Count {
            count: k,
            usable: full_pool.len(),
        });
    }
    let full_of = |i: usize| -> &RunInformation { cands[i].full_info.as_ref().expect("full") };
    // Refill from the fully estimated candidates if a member's compile failed.
    let (mut members, _, evals2, swaps2) =
        optimise(&model, &full_pool, &full_of, members, k, opts, search_poses);

    // 3. The statement, over the whole prediction workspace.
    members.sort_by(|&a, &b| {
        let s = |i: usize| cands[i].score_um.unwrap_or(f64::INFINITY);
        s(a).total_cmp(&s(b)).then(a.cmp(&b))
    });
    let infos: Vec<&RunInformation> = members.iter().map(|&i| full_of(i)).collect();
    let e = predict::expected(&model, &infos, opts.compile.bar_noise, &opts.prior, space);
    let um = |v: &[f64]| -> Vec<f64> { v.iter().map(|x| x * 1e6).collect() };
    let total = predict::spread(&um(&e.combined));
    let best = ranking
        .iter()
        .copied()
        .find(|&i| cands[i].full_info.is_some())
        .unwrap_or(members[0]);
    let best_info = full_of(best);
    let repeated: Vec<&RunInformation> = (0..k).map(|_| best_info).collect();
    let rep = predict::expected(
        &model,
        &repeated,
        opts.compile.bar_noise,
        &opts.prior,
        space,
    );
    Ok(Campaign {
        members,
        predicted_um: total.rms,
        predicted_p95_um: total.p95,
        from_noise_um: predict::spread(&um(&e.from_noise)).rms,
        from_held_um: predict::spread(&um(&e.from_held)).rms,
        determined: e.determined.len(),
        best_single_um: cands[best]
            .full
            .as_ref()
            .map_or(f64::NAN, |f| f.predicted_um),
        best_single_repeated_um: predict::spread(&um(&rep.combined)).rms,
        search: format!(
            "greedy + exchange over {} candidates on proxies ({} evaluations, {} swaps), then over {} fully estimated ({} evaluations, {} swaps)",
            pool.len(),
            evals1,
            swaps1,
            full_pool.len(),
            evals2,
            swaps2
        ),
    })
}
