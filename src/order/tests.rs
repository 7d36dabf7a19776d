use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::cost::{Costs, NEIGHBOURS};
use super::local::{improve, nearest_neighbour, perturb};
use super::*;

/// Joint speed limits of a mid-size robot (rad/s): unequal, so the slowest axis varies.
const SPEED: [f64; 6] = [2.0, 1.8, 2.2, 3.5, 3.5, 5.0];

fn random_poses(rng: &mut ChaCha8Rng, n: usize) -> Vec<[f64; 6]> {
    (0..n)
        .map(|_| std::array::from_fn(|_| rng.random_range(-3.0..3.0)))
        .collect()
}

/// Solve and check what every tour must satisfy: a permutation that starts at `start`, with the
/// reported times equal to [`path_time`] of the orders they describe.
fn solve_checked(poses: &[[f64; 6]], start: usize) -> Tour {
    let tour = solve(poses, start, &SPEED).unwrap();
    let n = poses.len();
    assert_eq!(tour.order.len(), n);
    assert_eq!(tour.order[0], start);
    let mut seen = vec![false; n];
    for &i in &tour.order {
        assert!(!seen[i], "pose {i} visited twice in {:?}", tour.order);
        seen[i] = true;
    }
    assert_eq!(tour.time_sorted, path_time(poses, &tour.order, &SPEED));
    let unsorted: Vec<usize> = std::iter::once(start)
        .chain((0..n).filter(|&i| i != start))
        .collect();
    assert_eq!(tour.time_unsorted, path_time(poses, &unsorted, &SPEED));
    tour
}

/// Shortest open path from `start` by trying every order of the other poses.
fn brute_force(poses: &[[f64; 6]], start: usize) -> f64 {
    fn go(poses: &[[f64; 6]], cur: usize, left: &mut Vec<usize>, sofar: f64, best: &mut f64) {
        if sofar >= *best {
            return;
        }
        if left.is_empty() {
            *best = sofar;
            return;
        }
        for k in 0..left.len() {
            let next = left.swap_remove(k);
            let step = move_time(&poses[cur], &poses[next], &SPEED);
            go(poses, next, left, sofar + step, best);
            left.push(next);
            let last = left.len() - 1;
            left.swap(k, last);
        }
    }
    let mut left: Vec<usize> = (0..poses.len()).filter(|&i| i != start).collect();
    let mut best = f64::INFINITY;
    go(poses, start, &mut left, 0.0, &mut best);
    best
}

/// Every 2-opt reversal and every Or-opt segment move (1..=3, both orientations) of `order`,
/// built naively, for checking that the search really stopped at a local optimum.
fn neighbourhood(order: &[usize]) -> Vec<Vec<usize>> {
    let n = order.len();
    let mut out = Vec::new();
    for i in 1..n {
        for j in i + 1..n {
            let mut o = order.to_vec();
            o[i..=j].reverse();
            out.push(o);
        }
    }
    for s in 1..n {
        for len in 1..=3 {
            if s + len > n {
                break;
            }
            let seg = &order[s..s + len];
            let rest: Vec<usize> = order[..s]
                .iter()
                .chain(&order[s + len..])
                .copied()
                .collect();
            for gap in 1..=rest.len() {
                for rev in [false, true] {
                    let mut o = rest[..gap].to_vec();
                    if rev {
                        o.extend(seg.iter().rev());
                    } else {
                        o.extend(seg);
                    }
                    o.extend(&rest[gap..]);
                    out.push(o);
                }
            }
        }
    }
    out
}

#[test]
fn move_time_is_the_slowest_axis_not_the_longest_move() {
    let a = [0.0; 6];
    // Joint 2 moves furthest (1.5 rad) but joint 6, slow and moving 0.75 rad, takes longest.
    let b = [0.5, 1.5, 0.0, 0.0, 0.0, -0.75];
    let w = [0.5, 2.0, 1.0, 1.0, 1.0, 0.25];
    assert_eq!(move_time(&a, &b, &w), 3.0);
    assert_eq!(move_time(&b, &a, &w), 3.0);
    assert_eq!(move_time(&b, &b, &w), 0.0);
}

#[test]
fn path_time_sums_consecutive_moves() {
    let w = [1.0; 6];
    let poses = [
        [0.0; 6],
        [1.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        [1.0, 0.0, 0.5, 0.0, 0.0, 0.0],
    ];
    assert_eq!(path_time(&poses, &[0, 1, 2], &w), 1.5);
    assert_eq!(path_time(&poses, &[2, 0, 1], &w), 2.0);
    assert_eq!(path_time(&poses, &[1], &w), 0.0);
    assert_eq!(path_time(&poses, &[], &w), 0.0);
}

#[test]
fn local_search_never_lengthens_a_tour() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    for case in 0..50 {
        let n = rng.random_range(2..=150);
        let start = rng.random_range(0..n);
        let poses = random_poses(&mut rng, n);
        let tour = solve_checked(&poses, start);

        let costs = Costs::new(&poses, &SPEED);
        let nbrs = costs.neighbours(NEIGHBOURS);
        let nn = nearest_neighbour(&costs, &nbrs, start);
        let time_nn = path_time(&poses, &nn, &SPEED);
        assert!(
            tour.time_sorted <= time_nn,
            "case {case}: {tour:?} vs {time_nn}"
        );
        // Not a theorem for arbitrary input orders, but random orders are far from local optima.
        assert!(
            tour.time_sorted <= tour.time_unsorted,
            "case {case}: {tour:?}"
        );

        // From a random order too, where the search has much more to do.
        let mut order: Vec<usize> = (0..n).filter(|&i| i != start).collect();
        order.shuffle(&mut rng);
        order.insert(0, start);
        let before = path_time(&poses, &order, &SPEED);
        improve(&costs, &nbrs, &mut order, EPS);
        assert_eq!(order[0], start);
        let improved = path_time(&poses, &order, &SPEED);
        assert!(improved <= before, "case {case}");
        perturb(&costs, &nbrs, &mut order, EPS, 3 * n, case);
        assert_eq!(order[0], start);
        assert!(path_time(&poses, &order, &SPEED) <= improved, "case {case}");
    }
}

#[test]
fn search_stops_only_at_a_local_optimum_when_candidate_lists_are_complete() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    for case in 0..40 {
        // n - 1 <= NEIGHBOURS: every pose is a candidate of every other.
        let n = rng.random_range(3..=NEIGHBOURS + 1);
        let start = rng.random_range(0..n);
        // Every other case on a coarse grid, where many moves tie and must be refused.
        let poses = if case % 2 == 0 {
            random_poses(&mut rng, n)
        } else {
            grid_poses(&mut rng, n)
        };
        let tour = solve_checked(&poses, start);
        for o in neighbourhood(&tour.order) {
            let t = path_time(&poses, &o, &SPEED);
            assert!(
                t >= tour.time_sorted - 1e-9,
                "case {case}: {o:?} ({t}) beats {:?} ({})",
                tour.order,
                tour.time_sorted
            );
        }
    }
}

#[test]
fn small_instances_are_near_optimal_and_tiny_ones_optimal() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut worst = 1.0_f64;
    for n in 1..=8 {
        let mut ratio_sum = 0.0;
        let cases = 40;
        for case in 0..cases {
            let start = rng.random_range(0..n);
            let poses = random_poses(&mut rng, n);
            let tour = solve_checked(&poses, start);
            let best = brute_force(&poses, start);
            let ratio = if best > 0.0 {
                tour.time_sorted / best
            } else {
                1.0
            };
            if n <= 5 {
                assert!(
                    tour.time_sorted <= best + 1e-12,
                    "n={n} case {case}: {} vs optimum {best}",
                    tour.time_sorted
                );
            }
            ratio_sum += ratio;
            worst = worst.max(ratio);
        }
        let mean = ratio_sum / cases as f64;
        println!("n={n}: mean ratio to optimum {mean:.5}, worst so far {worst:.5}");
        assert!(mean <= 1.05, "n={n}: mean ratio {mean}");
    }
}

#[test]
fn poses_on_a_line_are_visited_in_sorted_order() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let n = 60;
    let mut poses = vec![[0.0_f64; 6]; n];
    for p in poses.iter_mut() {
        p[2] = rng.random_range(-2.5..2.5);
    }
    let mut sorted: Vec<usize> = (0..n).collect();
    sorted.sort_by(|&a, &b| poses[a][2].total_cmp(&poses[b][2]));

    let from_low = solve_checked(&poses, sorted[0]);
    assert_eq!(from_low.order, sorted);
    let from_high = solve_checked(&poses, sorted[n - 1]);
    assert_eq!(
        from_high.order,
        sorted.iter().rev().copied().collect::<Vec<_>>()
    );

    // From inside the line: to the nearer end first, then sweep to the far end.
    let k = n / 3;
    let x = |i: usize| poses[sorted[i]][2];
    let (lo, hi) = (x(k) - x(0), x(n - 1) - x(k));
    let optimum = (2.0 * lo.min(hi) + lo.max(hi)) / SPEED[2];
    let from_inside = solve_checked(&poses, sorted[k]);
    assert!(
        (from_inside.time_sorted - optimum).abs() < 1e-9,
        "{} vs {optimum}",
        from_inside.time_sorted
    );
}

#[test]
fn equal_costs_are_broken_by_lowest_index() {
    let poses = vec![[0.25; 6]; 7];
    let tour = solve_checked(&poses, 4);
    assert_eq!(tour.order, vec![4, 0, 1, 2, 3, 5, 6]);
    assert_eq!(tour.time_sorted, 0.0);
}

#[test]
fn same_input_same_tour() {
    let mut rng = ChaCha8Rng::seed_from_u64(13);
    for poses in [random_poses(&mut rng, 400), grid_poses(&mut rng, 1500)] {
        let a = solve_checked(&poses, 17);
        let b = solve(&poses, 17, &SPEED).unwrap();
        assert_eq!(a.order, b.order);
        assert_eq!(a.time_sorted.to_bits(), b.time_sorted.to_bits());
    }
}

#[test]
fn zero_one_and_two_poses() {
    assert_eq!(
        solve(&[], 0, &SPEED).unwrap_err(),
        OrderError::StartOutOfRange { start: 0, len: 0 }
    );
    let one = solve_checked(&[[1.0; 6]], 0);
    assert_eq!((one.order, one.time_sorted), (vec![0], 0.0));
    let two = [[0.0; 6], [1.0; 6]];
    let t = solve_checked(&two, 1);
    assert_eq!(t.order, vec![1, 0]);
    assert_eq!(t.time_sorted, 1.0 / 1.8);
}

#[test]
fn bad_input_is_an_error_not_a_panic() {
    let poses = [[0.0; 6], [1.0; 6]];
    assert_eq!(
        solve(&poses, 2, &SPEED).unwrap_err(),
        OrderError::StartOutOfRange { start: 2, len: 2 }
    );
    let mut w = SPEED;
    w[3] = 0.0;
    let err = solve(&poses, 0, &w).unwrap_err();
    assert_eq!(
        err,
        OrderError::InvalidSpeed {
            joint: 4,
            value: 0.0
        }
    );
    assert_eq!(
        err.to_string(),
        "joint 4: max speed 0 rad/s must be finite and positive"
    );
    let mut bad = poses;
    bad[1][5] = f64::NAN;
    assert!(matches!(
        solve(&bad, 0, &SPEED),
        Err(OrderError::NonFinitePose {
            pose: 1,
            joint: 6,
            ..
        })
    ));
}

/// Poses on a coarse integer grid, so many costs tie and tie-breaking is exercised.
fn grid_poses(rng: &mut ChaCha8Rng, n: usize) -> Vec<[f64; 6]> {
    (0..n)
        .map(|_| std::array::from_fn(|_| rng.random_range(0..4) as f64 * 0.5))
        .collect()
}

#[test]
fn costs_and_candidate_lists_match_naive_definitions() {
    let mut rng = ChaCha8Rng::seed_from_u64(17);
    for poses in [random_poses(&mut rng, 90), grid_poses(&mut rng, 90)] {
        let n = poses.len();
        let costs = Costs::new(&poses, &SPEED);
        let nbrs = costs.neighbours(NEIGHBOURS);
        for i in 0..n {
            for j in 0..n {
                // Costs work on poses pre-divided by the speeds: equal up to rounding.
                let want = move_time(&poses[i], &poses[j], &SPEED);
                let got = costs.get(i, j);
                assert!(
                    (got - want).abs() <= 4.0 * f64::EPSILON * want.max(1.0),
                    "{got} vs {want}"
                );
                assert_eq!(costs.get(j, i).to_bits(), got.to_bits(), "symmetric");
            }
            let mut naive: Vec<usize> = (0..n).filter(|&j| j != i).collect();
            naive.sort_by(|&a, &b| costs.get(i, a).total_cmp(&costs.get(i, b)).then(a.cmp(&b)));
            assert_eq!(nbrs.of(i), &naive[..NEIGHBOURS], "pose {i}");
        }
        // Nearest neighbour through the candidate lists equals the plain full-scan definition.
        for start in [0, n / 2, n - 1] {
            let mut naive = vec![start];
            while naive.len() < n {
                let cur = *naive.last().unwrap();
                let next = (0..n)
                    .filter(|j| !naive.contains(j))
                    .min_by(|&a, &b| {
                        costs
                            .get(cur, a)
                            .total_cmp(&costs.get(cur, b))
                            .then(a.cmp(&b))
                    })
                    .unwrap();
                naive.push(next);
            }
            assert_eq!(nearest_neighbour(&costs, &nbrs, start), naive);
        }
    }
}

#[test]
fn kicks_return_the_best_path_seen_and_end_at_a_local_optimum() {
    // Uphill kicks are kept while the threshold is high and the pruned Or-opt runs during the
    // kicks, so neither the last kicked path nor the pruned search may decide the result: it must
    // be the shortest path seen, polished by the exact search. With complete candidate lists that
    // means no 2-opt or Or-opt (1..=3, both orientations) move improves it, and it is never longer
    // than the local optimum the kicks started from. (Every move's claimed gain is checked against
    // the recomputed path cost inside the search in test builds, pruned or not.)
    let mut rng = ChaCha8Rng::seed_from_u64(19);
    for case in 0..40 {
        let n = rng.random_range(4..=NEIGHBOURS + 1);
        let start = rng.random_range(0..n);
        let poses = if case % 2 == 0 {
            random_poses(&mut rng, n)
        } else {
            grid_poses(&mut rng, n)
        };
        let costs = Costs::new(&poses, &SPEED);
        let nbrs = costs.neighbours(NEIGHBOURS);
        let mut order: Vec<usize> = (0..n).filter(|&i| i != start).collect();
        order.shuffle(&mut rng);
        order.insert(0, start);
        improve(&costs, &nbrs, &mut order, EPS);
        let improved = path_time(&poses, &order, &SPEED);
        let kept = perturb(&costs, &nbrs, &mut order, EPS, 500, case);
        assert!(
            kept > 0,
            "case {case}: no kick kept, so the test exercised nothing"
        );
        assert_eq!(order[0], start);
        let mut sorted = order.clone();
        sorted.sort_unstable();
        assert_eq!(
            sorted,
            (0..n).collect::<Vec<_>>(),
            "case {case}: a permutation"
        );
        let t = path_time(&poses, &order, &SPEED);
        assert!(
            t <= improved,
            "case {case}: {t} after kicks vs {improved} before"
        );
        for o in neighbourhood(&order) {
            let u = path_time(&poses, &o, &SPEED);
            assert!(
                u >= t - 1e-9,
                "case {case}: {o:?} ({u}) beats {order:?} ({t})"
            );
        }
    }
}

/// The trapezoid cost: on small instances the tour equals the brute-force optimum of the sum of
/// [`crate::timing::move_time`] (an independent cost: the timing module's trapezoid), and its
/// reported times are those sums.
#[test]
fn trapezoid_cost_tours_match_brute_force() {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(21);
    let speed = [1.9, 1.7, 1.9, 3.1, 3.1, 4.5];
    let accel = [3.8, 3.4, 3.8, 6.2, 6.2, 9.0];
    let lim = crate::timing::Limits { speed, accel };
    for _ in 0..20 {
        let n = rng.random_range(3..8);
        // Short and long moves mixed: triangles and trapezoids.
        let poses: Vec<[f64; 6]> = (0..n)
            .map(|_| {
                std::array::from_fn(|_| rng.random_range(-1.0..1.0) * rng.random_range(0.02..2.0))
            })
            .collect();
        let tour = super::solve_with(&poses, 0, &speed, Some(&accel)).unwrap();
        let cost = |order: &[usize]| -> f64 {
            order
                .windows(2)
                .map(|w| crate::timing::move_time(&poses[w[0]], &poses[w[1]], &lim, 1.0))
                .sum()
        };
        let mut rest: Vec<usize> = (1..n).collect();
        let mut best = f64::INFINITY;
        permute(&mut rest, 0, &mut |p| {
            let mut order = vec![0];
            order.extend_from_slice(p);
            best = best.min(cost(&order));
        });
        assert!((tour.time_sorted - cost(&tour.order)).abs() < 1e-12);
        assert!(
            tour.time_sorted <= best * (1.0 + 1e-9),
            "{} vs {best}",
            tour.time_sorted
        );
    }
}

fn permute(v: &mut Vec<usize>, k: usize, f: &mut dyn FnMut(&[usize])) {
    if k == v.len() {
        f(v);
        return;
    }
    for i in k..v.len() {
        v.swap(k, i);
        permute(v, k + 1, f);
        v.swap(k, i);
    }
}
