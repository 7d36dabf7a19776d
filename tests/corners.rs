//! Issue 21: for every dialect, `verify` checks the corner region its controller may execute by
//! the vendor's documentation, not edbbgen's old convention (the blend distance at the MAP,
//! a joint-space Bézier from where the MAP first comes within it). Each test builds by hand a
//! corner on the NJ-130 cell — two moves of 160 or 240 mm at the MAP, at right angles across the
//! bar — blends it with the value the old convention would write (60 or 110 mm, `CNT60`), and puts a
//! sphere where the controller's documented region reaches but the old convention's blend and
//! the two moves do not: the old convention passes the corner, `verify` must refuse it.

use crate::dialects::cell;
use edbbgen::cell::{Shape, ShapeKind};
use edbbgen::dialect::{self, CornerKind};
use edbbgen::ir::{Move, Program};
use edbbgen::robot::Frame;
use edbbgen::safety::{blend, path::check_blend, Checker, Extremes};
use nalgebra::{Matrix6, Vector3, Vector6};

fn hand_made_corner_fails(d: &str) {
    let c = cell("nj130_cell");
    let dl = dialect::by_name(d).unwrap();
    // A TCP-distance region reaches about 1.4 blend distances from the pose, the moves pass
    // one blend distance from that point: the tool's bodies need room there.
    let (move_mm, blend_mm): (f64, f64) = if dl.corner.kind == CornerKind::TcpDistance {
        (240.0, 110.0)
    } else {
        (160.0, 60.0)
    };
    let spec = c.opts.cell.clone();
    let fixture = spec.fixture.unwrap();
    let tool = c.compiled.cell.map;
    let cellv = c.compiled.cell.clone();
    let model = edbbgen::model::MeasurementModel::new(&c.robot, fixture, tool);
    let map = edbbgen::controller::ControllerMap::resolve(
        spec.controller.as_ref(),
        &dl.defaults(),
        d,
        &c.robot,
    )
    .unwrap();
    let emitted = |q: [f64; 6]| edbbgen::emit::emitted(&q);
    let map_at = |q: &[f64; 6]| model.map_position(&model.nominal, q);
    let flange = |q: &[f64; 6]| {
        edbbgen::robot::kinematics::chain_frames(&model.base, &model.nominal.dh, &model.flange, q)
            [7]
        .r
    };
    // The corner: a measurement pose of the program with its bar near mid-range and the bar
    // well inside both cones (the moves turn the bar by about 20 degrees).
    let program = c.program(d);
    let cones = |q: &[f64; 6]| {
        let (s, t) = cellv.cone_angles(&map_at(q), &(flange(q) * cellv.tool_axis));
        s.max(t)
    };
    let mut candidates: Vec<[f64; 6]> = program
        .moves
        .iter()
        .filter(|m| !m.support && !m.transit && (m.length_mm - 410.0).abs() < 80.0)
        .map(|m| m.q_deg.map(f64::to_radians))
        .collect();
    candidates.sort_by(|x, y| cones(x).total_cmp(&cones(y)));
    let deg = |q: &[f64; 6]| q.map(f64::to_degrees);
    let len = |x: [f64; 6], y: [f64; 6]| (0..6).map(|i| (x[i] - y[i]).powi(2)).sum::<f64>().sqrt();
    let (scene0, _) = edbbgen::pipeline::build_scene(&c.robot, &spec, &fixture, &tool).unwrap();
    let ck0 = Checker::new(&c.robot, &model, &cellv, &scene0, spec.margin);
    let corner = if dl.corner.kind == CornerKind::Unbounded {
        // CNT bounds nothing; the obstacle goes where a half-move blend would reach.
        dialect::Corner {
            kind: CornerKind::Moves,
            ..dl.corner.clone()
        }
    } else {
        dl.corner.clone()
    };
    // Search the corner: a pose, and a pair of directions across the bar (turned about it in
    // 30 degree steps), whose moves and old-convention blend pass, with a sphere at the far
    // corner of the documented region that still leaves them clear.
    let mut found = None;
    'search: for k in candidates.iter().take(6) {
        // The MAP's and the flange's Jacobian by central differences; the moves hold the tool's
        // orientation.
        let mut jac = Matrix6::zeros();
        for i in 0..6 {
            let (mut p, mut m) = (*k, *k);
            p[i] += 1e-6;
            m[i] -= 1e-6;
            let dp = (map_at(&p) - map_at(&m)) / 2e-6;
            let dr = (flange(&p) - flange(&m)) / 2e-6 * flange(k).transpose();
            let w = Vector3::new(dr[(2, 1)], dr[(0, 2)], dr[(1, 0)]);
            for r in 0..3 {
                jac[(r, i)] = dp[r];
                jac[(r + 3, i)] = w[r];
            }
        }
        let Some(inv) = jac.try_inverse() else {
            continue;
        };
        let r = (map_at(k) - fixture).normalize();
        let e1 = r.cross(&Vector3::z()).normalize();
        let e2 = r.cross(&e1);
        for turn in 0..12 {
            let phi = (turn as f64 * 30.0).to_radians();
            let u1 = e1 * phi.cos() + e2 * phi.sin();
            let u2 = r.cross(&u1);
            let step = |v: Vector3<f64>| -> [f64; 6] {
                let v = v * move_mm * 1e-3;
                let dq = inv * Vector6::new(v.x, v.y, v.z, 0.0, 0.0, 0.0);
                std::array::from_fn(|i| dq[i])
            };
            let (s1, s2) = (step(u1), step(u2));
            let a = emitted(std::array::from_fn(|i| k[i] - s1[i]));
            let b = emitted(std::array::from_fn(|i| k[i] + s2[i]));
            let k = emitted(*k);
            let axis_len = (
                len(map.apply(&deg(&a)), map.apply(&deg(&k))),
                len(map.apply(&deg(&k)), map.apply(&deg(&b))),
            );
            let region =
                blend::region(&ck0, &corner, None, &a, &k, &b, blend_mm, axis_len).unwrap();
            let far = region.point(1.0, 1.0);
            let mut spec = spec.clone();
            spec.environment.push(Shape {
                name: "obstacle".into(),
                origin: Frame::translation(map_at(&far)),
                kind: ShapeKind::Sphere { radius: 0.02 },
            });
            let (scene, _) =
                edbbgen::pipeline::build_scene(&c.robot, &spec, &fixture, &tool).unwrap();
            let ck = Checker::new(&c.robot, &model, &cellv, &scene, spec.margin);
            // The old convention passes: both moves and its Bézier blend keep every margin.
            let mut e = Extremes::default();
            let old = blend::geometry(&model, &a, &k, &b, blend_mm * 1e-3).unwrap();
            if ck.line(&a, &k, &mut e).is_ok()
                && ck.line(&k, &b, &mut e).is_ok()
                && check_blend(&ck, &old, &mut e).is_ok()
            {
                found = Some((a, k, b, scene));
                break 'search;
            }
        }
    }
    let (a, k, b, scene) = found.expect("a corner the old convention passes");
    let ck = Checker::new(&c.robot, &model, &cellv, &scene, spec.margin);
    // The program: approach to a, mount, a → k blended, k → b.
    let lim = edbbgen::timing::Limits::of(&c.robot);
    let mv = |q: [f64; 6], from: Option<[f64; 6]>, pose: usize| {
        let cruise = from.map_or(0.0, |f| edbbgen::timing::eq7(&f, &q, &lim.speed));
        Move {
            q_deg: deg(&q),
            support: false,
            transit: from.is_none(),
            pose,
            blend_mm: 0.0,
            time_s: from.map_or(0.0, |f| edbbgen::timing::move_time(&f, &q, &lim, 1.0)),
            cruise_s: cruise,
            blend_value: 0.0,
            length_mm: 1e3 * model.length(&model.nominal, &q),
            note: String::new(),
            pause: String::new(),
            pause_before: String::new(),
            section: 1,
            remove_before: false,
            mount_after: from.is_none(),
            axes: [0.0; 6],
            speed_pct: 0.0,
        }
    };
    let mut moves = vec![mv(a, None, 1), mv(k, Some(a), 2), mv(b, Some(k), 3)];
    moves[1].blend_mm = blend_mm;
    moves[1].blend_value = blend_mm;
    let mut hand = Program {
        header: program.header.clone(),
        moves,
    };
    hand.header.blend_mm = blend_mm;
    hand.header.poses = 3;
    hand.header.supports = 0;
    hand.header.sections = 1;
    let hand = edbbgen::emit::target(&hand, dl, &map, &c.robot.max_speeds());
    let template = dialect::Template::bundled(d).unwrap();
    let mut text = edbbgen::emit::render(&template, &hand).unwrap();
    if d == "fanuc" {
        // The old convention's FANUC form: CNTn for an n mm blend.
        text = text.replace(&format!("CR{blend_mm}"), &format!("CNT{blend_mm}"));
        assert!(text.contains(&format!("CNT{blend_mm}")), "{text}");
    }
    let f = edbbgen::verify::check_text(&ck, &c.robot, &text, dl, &map)
        .expect_err("verify passes a corner its controller may cut into the obstacle");
    assert!(f.violation.detail.contains("corner region"), "{d}: {f}");
    // Without the obstacle the same program passes: the region alone is what fails.
    if d != "fanuc" {
        edbbgen::verify::check_text(&ck0, &c.robot, &text, dl, &map)
            .unwrap_or_else(|f| panic!("{d} without the obstacle: {f}"));
    }
}

#[test]
fn ngc_corner_is_checked_as_linuxcnc_blends() {
    hand_made_corner_fails("ngc");
}

#[test]
fn sinumerik_corner_is_checked_as_adis_on_the_axis_path() {
    hand_made_corner_fails("sinumerik");
}

#[test]
fn krl_corner_is_checked_as_c_dis_approximates() {
    hand_made_corner_fails("krl");
}

#[test]
fn rapid_corner_is_checked_as_its_zone() {
    hand_made_corner_fails("rapid");
}

#[test]
fn urscript_corner_is_checked_as_its_blend_radius() {
    hand_made_corner_fails("urscript");
}

#[test]
fn fanuc_cnt_corner_is_refused() {
    hand_made_corner_fails("fanuc");
}
