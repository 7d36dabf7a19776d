use super::*;
use crate::cell::Shape as CellShape;
use crate::robot::{load, LoadOptions};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const SHARED: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/robots");
const NJ130_URDF: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/robots/comau_nj130/robot.urdf");
const NJ130_DH: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/robots/comau_nj130/robot.dh.toml"
);
const SHARED_ROBOTS: [&str; 4] = [
    "abb_irb6700_200_260",
    "fanuc_r2000ic_165f",
    "kuka_kr120_r2500pro",
    "kuka_kr210_l150",
];

fn all_robots() -> Vec<(String, Robot)> {
    let mut files: Vec<String> = SHARED_ROBOTS
        .iter()
        .map(|r| format!("{SHARED}/{r}/robot.urdf"))
        .collect();
    files.push(NJ130_URDF.into());
    files.push(NJ130_DH.into());
    files
        .into_iter()
        .map(|f| {
            let r = load(Path::new(&f), &LoadOptions::default()).expect(&f);
            (f, r)
        })
        .collect()
}

fn robot(file: &str) -> Robot {
    load(Path::new(file), &LoadOptions::default()).unwrap()
}

fn map_of(robot: &Robot) -> Vector3<f64> {
    robot.tool.unwrap_or(Vector3::new(0.06, 0.03, 0.12))
}

fn frames(robot: &Robot, q: &[f64; 6]) -> [Frame; 8] {
    chain_frames(&robot.base, &robot.dh, &robot.flange, q)
}

/// The fixture 0.4 m beyond the MAP along +x at q = 0 (every test robot points along +x there).
fn fixture_for(robot: &Robot) -> Vector3<f64> {
    frames(robot, &[0.0; 6])[7].apply(&map_of(robot)) + Vector3::new(0.4, 0.0, 0.0)
}

fn scene(robot: &Robot, cell: &CellSpec) -> (Scene, SceneReport) {
    build(robot, cell, &fixture_for(robot), &map_of(robot)).unwrap()
}

fn random_q(robot: &Robot, rng: &mut ChaCha8Rng) -> [f64; 6] {
    std::array::from_fn(|i| rng.random_range(robot.joints[i].lower..=robot.joints[i].upper))
}

/// A scene of world bodies only, every pair checked, no bar.
fn world_scene(shapes: Vec<(&str, Frame, Prim)>, floor_z: Option<f64>) -> Scene {
    let mut bodies: Vec<Body> = shapes
        .into_iter()
        .map(|(n, f, p)| {
            body(
                n.into(),
                Attach::World,
                Role::Environment,
                vec![part(&f, p, n).unwrap()],
            )
        })
        .collect();
    if let Some(z) = floor_z {
        let floor = Part {
            shape: SharedShape::new(HalfSpace::new(Unit::new_unchecked(Vector3::z()))),
            hull: None,
            local: Isometry3::translation(0.0, 0.0, z),
            center: Point3::new(0.0, 0.0, z),
            radius: 0.0,
            plane: true,
        };
        bodies.push(body(FLOOR.into(), Attach::World, Role::Floor, vec![floor]));
    }
    let n = bodies.len();
    let pairs = (0..n)
        .flat_map(|i| (i + 1..n).map(move |j| (i, j)))
        .collect();
    Scene {
        bodies,
        passive: Vec::new(),
        pairs,
        bar_pairs: Vec::new(),
        fixture: Vector3::zeros(),
        bar_radius: 0.0,
        ball_radius: 0.0,
        sweep: [0.0; 6],
        rates: Vec::new(),
    }
}

fn check_clearance(s: &Scene, want: f64, a: &str, b: &str) {
    let c = s.clearance(&[0.0; 6], &[Frame::IDENTITY; 8], &Vector3::zeros());
    assert!((c.distance - want).abs() < 1e-9, "{c:?}, want {want}");
    assert_eq!((c.a.as_str(), c.b.as_str()), (a, b));
    // The filter agrees with the clearance on both sides of it.
    let id = [Frame::IDENTITY; 8];
    assert!(s
        .violation(&[0.0; 6], &id, &Vector3::zeros(), want - 1e-6)
        .is_none());
    let v = s
        .violation(&[0.0; 6], &id, &Vector3::zeros(), want + 1e-6)
        .expect("violation");
    assert!((v.distance - want).abs() < 1e-9, "{v:?}");
}

#[test]
fn two_boxes_at_a_known_distance_and_overlapping() {
    let big = ("big", Frame::IDENTITY, Prim::Box([1.0, 1.0, 1.0]));
    let at = |x: f64| Frame::from_xyz_rpy([x, 0.1, 0.05], [0.0, 0.0, 0.0]);
    let s = world_scene(
        vec![big, ("small", at(1.2), Prim::Box([0.5, 0.5, 0.5]))],
        None,
    );
    check_clearance(&s, 0.45, "big", "small");
    let big = ("big", Frame::IDENTITY, Prim::Box([1.0, 1.0, 1.0]));
    let s = world_scene(
        vec![big, ("small", at(0.7), Prim::Box([0.5, 0.5, 0.5]))],
        None,
    );
    check_clearance(&s, -0.05, "big", "small");
}

/// parry 0.25's `query::distance` of two cuboids depends on their order and overstates the gap
/// (dimforge/parry#431): clearances go through closest points instead.
#[test]
fn two_boxes_of_different_sizes_in_either_order() {
    for (first, second) in [
        ([2.0, 2.0, 2.0], [2.0, 4.0, 2.0]),
        ([2.0, 4.0, 2.0], [2.0, 2.0, 2.0]),
    ] {
        let s = world_scene(
            vec![
                ("a", Frame::IDENTITY, Prim::Box(first)),
                (
                    "b",
                    Frame::translation(Vector3::new(-5.573167, 0.0, 0.0)),
                    Prim::Box(second),
                ),
            ],
            None,
        );
        check_clearance(&s, 3.573167, "a", "b");
    }
}

#[test]
fn sphere_and_floor_at_a_known_distance_and_below_it() {
    let ball = |z: f64| {
        (
            "ball",
            Frame::translation(Vector3::new(0.3, -0.2, z)),
            Prim::Sphere(0.1),
        )
    };
    check_clearance(
        &world_scene(vec![ball(0.3)], Some(0.05)),
        0.15,
        "ball",
        FLOOR,
    );
    check_clearance(
        &world_scene(vec![ball(0.1)], Some(0.05)),
        -0.05,
        "ball",
        FLOOR,
    );
}

#[test]
fn cylinders_run_along_local_z() {
    // Radius 0.1, length 1: along z its lowest point is 0.5 below the centre, lying down 0.1.
    let upright = ("cyl", Frame::IDENTITY, Prim::Cylinder(0.1, 1.0));
    check_clearance(&world_scene(vec![upright], Some(-0.6)), 0.1, "cyl", FLOOR);
    let lying = Frame::from_xyz_rpy([0.0; 3], [std::f64::consts::FRAC_PI_2, 0.0, 0.0]);
    let lying = ("cyl", lying, Prim::Cylinder(0.1, 1.0));
    check_clearance(&world_scene(vec![lying], Some(-0.6)), 0.5, "cyl", FLOOR);
    // And against a box beside its end cap: 0.5 along z to the cap, then 0.2 of air.
    let upright = ("cyl", Frame::IDENTITY, Prim::Cylinder(0.1, 1.0));
    let cube = (
        "cube",
        Frame::translation(Vector3::new(0.0, 0.0, 0.8)),
        Prim::Box([0.2; 3]),
    );
    check_clearance(&world_scene(vec![upright, cube], None), 0.2, "cyl", "cube");
}

#[test]
fn every_robot_builds_and_is_clear_at_home_and_lists_adjacent_links() {
    let cell = CellSpec::default();
    for (file, r) in all_robots() {
        let (s, rep) = scene(&r, &cell);
        let home = frames(&r, &[0.0; 6]);
        let map = home[7].apply(&map_of(&r));
        let c = s.clearance(&[0.0; 6], &home, &map);
        eprintln!(
            "{file}: {} bodies, {} pairs checked, {} excluded; home clearance {:.1} mm ({} / {})",
            rep.bodies.len(),
            rep.pairs_checked,
            rep.excluded.len(),
            c.distance * 1e3,
            c.a,
            c.b
        );
        for e in &rep.excluded {
            eprintln!("    {} / {}: {}", e.a, e.b, e.reason);
        }
        assert!(
            s.violation(&[0.0; 6], &home, &map, cell.margin).is_none(),
            "{file}: {c:?}"
        );
        assert!(c.distance >= cell.margin, "{file}: {c:?}");
        assert!(rep.pairs_checked > 0);
        let has = |a: &str, b: &str, why: &str| {
            rep.excluded
                .iter()
                .any(|e| e.a == a && e.b == b && e.reason.contains(why))
        };
        for k in 2..=6 {
            assert!(
                has(&link_name(k - 1), &link_name(k), "adjacent"),
                "{file}: link {} / {k} not listed",
                k - 1
            );
        }
        assert!(has(BAR, MAP_BALL, "tool cup") && has(BAR, FIXTURE_BALL, "fixture"));
        if rep.bodies.contains(&link_name(0)) {
            assert!(has(&link_name(0), FLOOR, "base on the floor"), "{file}");
        }
    }
}

/// Scans q2 (forward) and q3 for the first pose that folds the arm into itself or the floor;
/// the reported bodies are robot bodies or the floor.
#[test]
fn folding_the_arm_is_a_violation_naming_the_bodies() {
    let cell = CellSpec::default();
    for (file, r) in all_robots() {
        let (s, rep) = scene(&r, &cell);
        let mut hit = None;
        'scan: for i in 0..=20 {
            for j in 0..=20 {
                let mut q = [0.0; 6];
                q[1] =
                    r.joints[1].lower + (r.joints[1].upper - r.joints[1].lower) * i as f64 / 20.0;
                q[2] =
                    r.joints[2].lower + (r.joints[2].upper - r.joints[2].lower) * j as f64 / 20.0;
                q[4] = 0.5 * r.joints[4].upper;
                let f = frames(&r, &q);
                let map = f[7].apply(&map_of(&r));
                if let Some(c) = s.violation(&q, &f, &map, cell.margin) {
                    let fold = |n: &str| n != BAR && n != FIXTURE_BALL;
                    if fold(&c.a) && fold(&c.b) {
                        hit = Some((q, c));
                        break 'scan;
                    }
                }
            }
        }
        let (q, c) = hit.unwrap_or_else(|| panic!("{file}: no folded pose collides"));
        eprintln!("{file}: q2 = {:.2}, q3 = {:.2}: {c:?}", q[1], q[2]);
        assert!(c.distance <= cell.margin);
        assert!(rep.bodies.contains(&c.a) && rep.bodies.contains(&c.b));
        // The clearance finds the same pose unsafe.
        let f = frames(&r, &q);
        assert!(s.clearance(&q, &f, &f[7].apply(&map_of(&r))).distance <= cell.margin);
    }
    // The auto-capsule NJ-130 with the upper arm leant fully forward: lowering the forearm puts
    // the wrist into the floor.
    let r = robot(NJ130_DH);
    let (s, _) = scene(&r, &cell);
    let floor_hit = (0..=40).find_map(|j| {
        let q3 = r.joints[2].lower + (r.joints[2].upper - r.joints[2].lower) * j as f64 / 40.0;
        let q = [0.0, r.joints[1].upper, q3, 0.0, 0.0, 0.0];
        let f = frames(&r, &q);
        eprintln!("q3 = {q3:.2}: wrist at z = {:.3}", f[5].t.z);
        s.violation(&q, &f, &f[7].apply(&map_of(&r)), cell.margin)
            .filter(|c| c.b == FLOOR)
    });
    let c = floor_hit.expect("the wrist reaches the floor");
    assert!(c.a.starts_with("link") || c.a == MAP_BALL, "{c:?}");
}

fn env_box(name: &str, at: Vector3<f64>, size: f64) -> CellShape {
    CellShape {
        name: name.into(),
        origin: Frame::translation(at),
        kind: ShapeKind::Box { size: [size; 3] },
    }
}

#[test]
fn a_box_on_the_map_path_and_a_box_across_the_bar() {
    let r = robot(NJ130_URDF);
    let q1 = [0.4, 0.2, -0.1, 0.0, 0.3, 0.0];
    let f1 = frames(&r, &q1);
    let map1 = f1[7].apply(&map_of(&r));
    let mut cell = CellSpec::default();
    cell.environment.push(env_box("crate", map1, 0.1));
    let (s, rep) = scene(&r, &cell);
    assert!(rep.bodies.contains(&"crate".to_string()));
    let home = frames(&r, &[0.0; 6]);
    let map0 = home[7].apply(&map_of(&r));
    assert!(s.violation(&[0.0; 6], &home, &map0, cell.margin).is_none());
    let c = s
        .violation(&q1, &f1, &map1, cell.margin)
        .expect("the MAP is in the crate");
    assert!(c.a == "crate" || c.b == "crate", "{c:?}");
    assert!(s.clearance(&q1, &f1, &map1).distance < 0.0);

    // A small box halfway along the bar at the home pose: only the bar reaches it.
    let mut cell = CellSpec::default();
    let fixture = fixture_for(&r);
    cell.environment
        .push(env_box("post", 0.5 * (map0 + fixture), 0.04));
    let (s, _) = scene(&r, &cell);
    let c = s
        .violation(&[0.0; 6], &home, &map0, cell.margin)
        .expect("the bar hits the post");
    assert_eq!((c.a.as_str(), c.b.as_str()), ("post", BAR), "{c:?}");
    assert!(c.distance < 0.0);
    let c = s.clearance(&[0.0; 6], &home, &map0);
    assert_eq!((c.a.as_str(), c.b.as_str()), ("post", BAR));
    // Moved off the bar by more than its radius + the margin: clear.
    let mut cell = CellSpec::default();
    cell.environment.push(env_box(
        "post",
        0.5 * (map0 + fixture) + Vector3::new(0.0, 0.0, -0.02 - 0.015 - 0.02),
        0.04,
    ));
    let (s, _) = scene(&r, &cell);
    assert!(s.violation(&[0.0; 6], &home, &map0, cell.margin).is_none());
}

/// Points on the surface of a part (its frame), for the sweep bound.
fn sample_points(p: &Part) -> Vec<Point3<f64>> {
    let s = p.shape.as_ref();
    let mut out = Vec::new();
    if let Some(h) = s.as_convex_polyhedron() {
        out.extend(h.points().iter().step_by(7).copied());
    } else if let Some(c) = s.as_cuboid() {
        let h = c.half_extents;
        for k in 0..8 {
            let sg = |b: usize| if k & b == 0 { 1.0 } else { -1.0 };
            out.push(Point3::new(sg(1) * h.x, sg(2) * h.y, sg(4) * h.z));
        }
    } else if let Some(b) = s.as_ball() {
        for a in 0..3 {
            let mut v = Vector3::zeros();
            v[a] = b.radius;
            out.push(Point3::from(v));
            out.push(Point3::from(-v));
        }
    } else if let Some(c) = s.as_cylinder() {
        for k in 0..8 {
            let t = k as f64 * std::f64::consts::FRAC_PI_4;
            for y in [-c.half_height, c.half_height] {
                out.push(Point3::new(c.radius * t.cos(), y, c.radius * t.sin()));
            }
        }
    } else if let Some(c) = s.as_capsule() {
        for e in [c.segment.a, c.segment.b] {
            for a in 0..3 {
                let mut v = Vector3::zeros();
                v[a] = c.radius;
                out.push(e + v);
                out.push(e - v);
            }
        }
    } else {
        panic!("no sample points for this shape");
    }
    out.into_iter().map(|x| p.local * x).collect()
}

#[test]
fn sweep_radius_bounds_the_motion_of_every_body_point() {
    let mut cell = CellSpec::default();
    cell.tool_shapes.push(CellShape {
        name: "cup".into(),
        origin: Frame::translation(Vector3::new(0.0, 0.0, 0.06)),
        kind: ShapeKind::Cylinder {
            radius: 0.05,
            length: 0.12,
        },
    });
    cell.hoses.push(crate::cell::AttachedShape {
        frame: 3,
        shape: CellShape {
            name: "hose".into(),
            origin: Frame::IDENTITY,
            kind: ShapeKind::Capsule {
                a: [0.0, -0.2, 0.0],
                b: [0.0, -0.2, 0.6],
                radius: 0.04,
            },
        },
    });
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    for (file, r) in all_robots() {
        let (s, _) = scene(&r, &cell);
        let sweep = s.sweep_radius();
        assert!(sweep.iter().all(|v| v.is_finite() && *v > 0.0), "{sweep:?}");
        let mut worst = 0.0f64;
        for _ in 0..100 {
            let q = random_q(&r, &mut rng);
            let dq: [f64; 6] = std::array::from_fn(|_| rng.random_range(-0.02..0.02));
            let q2: [f64; 6] = std::array::from_fn(|i| q[i] + dq[i]);
            let bound: f64 = (0..6).map(|i| sweep[i] * dq[i].abs()).sum();
            let (ffa, ffb) = (frames(&r, &q), frames(&r, &q2));
            let (fa, fb) = (
                Poses::new(&q, &ffa, &r.passive),
                Poses::new(&q2, &ffb, &r.passive),
            );
            for b in s.bodies.iter().filter(|b| b.attach != Attach::World) {
                for p in &b.parts {
                    for x in sample_points(p) {
                        let moved = (fa.of(b) * x - fb.of(b) * x).norm();
                        assert!(
                            moved <= bound + 1e-12,
                            "{file}: {} moved {moved} > {bound}",
                            b.name
                        );
                        worst = worst.max(moved / bound);
                    }
                }
            }
        }
        eprintln!("{file}: sweep {sweep:.3?}, worst use of the bound {worst:.2}");
    }
}

#[test]
fn results_do_not_depend_on_the_thread_count() {
    use rayon::prelude::*;
    let r = robot(&format!("{SHARED}/kuka_kr210_l150/robot.urdf"));
    let (s, _) = scene(&r, &CellSpec::default());
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let qs: Vec<[f64; 6]> = (0..300).map(|_| random_q(&r, &mut rng)).collect();
    let run = |threads: usize| -> Vec<(Contact, Option<Contact>)> {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                qs.par_iter()
                    .map(|q| {
                        let f = frames(&r, q);
                        let m = f[7].apply(&map_of(&r));
                        (s.clearance(q, &f, &m), s.violation(q, &f, &m, 0.01))
                    })
                    .collect()
            })
    };
    assert_eq!(run(1), run(2));
}

#[test]
fn mesh_files_ascii_stl_obj_and_a_clear_error_for_dae() {
    let dir = tempfile::tempdir().unwrap();
    let stl = dir.path().join("tet.stl");
    std::fs::write(
        &stl,
        "solid t\nfacet normal 0 0 -1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\n\
         endloop\nendfacet\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 0 1 0\n\
         vertex 0 0 1\nendloop\nendfacet\nendsolid t\n",
    )
    .unwrap();
    let obj = dir.path().join("tet.obj");
    std::fs::write(&obj, "# tet\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\n").unwrap();
    for p in [&stl, &obj] {
        // Scaled by 2: the tetrahedron's apex at z = 2, so 1 m above a floor at z = 3 ... below.
        let part = part(&Frame::IDENTITY, Prim::Mesh(p, [2.0; 3]), "link 1").unwrap();
        let h = part.shape.as_convex_polyhedron().expect("hull");
        assert_eq!(h.points().len(), 4, "{}", p.display());
        let s = Scene {
            passive: Vec::new(),
            bodies: vec![
                body("tet".into(), Attach::World, Role::Environment, vec![part]),
                body(
                    "ball".into(),
                    Attach::World,
                    Role::Environment,
                    vec![super::part(
                        &Frame::translation(Vector3::new(0.0, 0.0, 3.0)),
                        Prim::Sphere(0.5),
                        "ball",
                    )
                    .unwrap()],
                ),
            ],
            pairs: vec![(0, 1)],
            bar_pairs: vec![],
            fixture: Vector3::zeros(),
            bar_radius: 0.0,
            ball_radius: 0.0,
            sweep: [0.0; 6],
            rates: Vec::new(),
        };
        let c = s.clearance(&[0.0; 6], &[Frame::IDENTITY; 8], &Vector3::zeros());
        assert!((c.distance - 0.5).abs() < 1e-9, "{c:?}");
    }
    let dae = dir.path().join("link.dae");
    std::fs::write(&dae, "<COLLADA/>").unwrap();
    let e = part(&Frame::IDENTITY, Prim::Mesh(&dae, [1.0; 3]), "link 2")
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("link.dae") && e.contains("convert to STL") && !e.contains('\n'),
        "{e}"
    );
    let missing = dir.path().join("gone.stl");
    let e = part(&Frame::IDENTITY, Prim::Mesh(&missing, [1.0; 3]), "link 2")
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("gone.stl") && !e.contains('\n'), "{e}");
}

/// Prints the filter's speed (poses/s, one thread) on random poses; asserts nothing about it.
#[test]
fn speed_of_the_filter() {
    let cell = CellSpec::default();
    for file in [
        NJ130_URDF.to_string(),
        format!("{SHARED}/kuka_kr120_r2500pro/robot.urdf"),
    ] {
        let r = robot(&file);
        let (s, rep) = scene(&r, &cell);
        let hull: Vec<usize> = s
            .bodies
            .iter()
            .flat_map(|b| &b.parts)
            .filter_map(|p| p.shape.as_convex_polyhedron().map(|h| h.points().len()))
            .collect();
        eprintln!("{file}: hull vertices {hull:?}");
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let qs: Vec<[f64; 6]> = (0..2000).map(|_| random_q(&r, &mut rng)).collect();
        let t = std::time::Instant::now();
        let mut hits = 0;
        for q in &qs {
            let f = frames(&r, q);
            hits += s
                .violation(q, &f, &f[7].apply(&map_of(&r)), cell.margin)
                .is_some() as usize;
        }
        let filter = qs.len() as f64 / t.elapsed().as_secs_f64();
        let t = std::time::Instant::now();
        let mut sum = 0.0;
        for q in &qs[..500] {
            let f = frames(&r, q);
            sum += s.clearance(q, &f, &f[7].apply(&map_of(&r))).distance;
        }
        let clear = 500.0 / t.elapsed().as_secs_f64();
        eprintln!(
            "{file}: {} pairs; violation {filter:.0} poses/s ({hits} of {} in collision), \
             clearance {clear:.0} poses/s (sum {sum:.3})",
            rep.pairs_checked,
            qs.len()
        );
    }
}

/// The climbing support function agrees with the full scan, and hull queries agree with parry's
/// own `ConvexPolyhedron` dispatch, on the densest robot.
#[test]
fn hull_support_is_exact() {
    let r = robot(&format!("{SHARED}/kuka_kr120_r2500pro/robot.urdf"));
    let (s, _) = scene(&r, &CellSpec::default());
    let mut rng = ChaCha8Rng::seed_from_u64(17);
    let parts: Vec<&Part> = s
        .bodies
        .iter()
        .flat_map(|b| &b.parts)
        .filter(|p| p.hull.is_some())
        .collect();
    assert!(parts.len() >= 6);
    for p in &parts {
        let h = p.hull.as_deref().unwrap();
        for _ in 0..2000 {
            let d = Vector3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            );
            let got = h.local_support_point(&d).coords.dot(&d);
            let want = h.points()[hull::scan(h.points(), &d)].coords.dot(&d);
            assert!(got >= want - 1e-12 * (1.0 + want.abs()), "{got} < {want}");
        }
    }
    // Random placements of two hulls: the same distance (or depth) both ways.
    let mut worst = 0.0f64;
    for _ in 0..300 {
        let (i, j) = (
            rng.random_range(0..parts.len()),
            rng.random_range(0..parts.len()),
        );
        let iso = |rng: &mut ChaCha8Rng| {
            Isometry3::new(
                Vector3::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                ),
                Vector3::new(
                    rng.random_range(-3.0..3.0),
                    rng.random_range(-3.0..3.0),
                    rng.random_range(-3.0..3.0),
                ),
            )
        };
        let (ia, ib) = (iso(&mut rng), iso(&mut rng));
        let (mut a, mut b) = (parts[i].place(&ia), parts[j].place(&ib));
        let fast = part_query(&a, &b, f64::INFINITY, Mode::Min).unwrap();
        let filt = part_query(&a, &b, fast + 1e-3, Mode::Filter).unwrap();
        (a.hull, b.hull) = (None, None);
        let slow = part_query(&a, &b, f64::INFINITY, Mode::Min).unwrap();
        worst = worst.max((fast - slow).abs()).max((filt - slow).abs());
    }
    eprintln!("hull vs ConvexPolyhedron: worst difference {worst:.2e} m");
    assert!(worst < 1e-6);
}

#[test]
fn a_moved_fixture_is_the_scene_built_there() {
    // The KR 210's convex hulls and a stand: the scene moved to another fixture answers every
    // query exactly as the scene built for that fixture does.
    let r = robot(&format!("{SHARED}/kuka_kr210_l150/robot.urdf"));
    let cell = CellSpec {
        stand_radius: 0.04,
        ..CellSpec::default()
    };
    let map = map_of(&r);
    let a = Vector3::new(1.4, 0.4, 0.7);
    let b = Vector3::new(0.9, -1.1, 0.45);
    let (built_a, _) = build(&r, &cell, &a, &map).unwrap();
    let (built_b, rep_b) = build(&r, &cell, &b, &map).unwrap();
    let moved = built_a.with_fixture(&cell, &b).unwrap();
    assert!(rep_b.bodies.contains(&STAND.to_string()));
    let mut rng = ChaCha8Rng::seed_from_u64(17);
    let mut hits = 0;
    for _ in 0..400 {
        let q = random_q(&r, &mut rng);
        let f = frames(&r, &q);
        let m = f[7].apply(&map);
        let (x, y) = (
            moved.violation(&q, &f, &m, 0.01),
            built_b.violation(&q, &f, &m, 0.01),
        );
        assert_eq!(x, y, "{q:?}");
        hits += x.is_some() as usize;
        assert_eq!(moved.clearance(&q, &f, &m), built_b.clearance(&q, &f, &m));
    }
    assert!(
        hits > 0,
        "some poses collide, so the comparison means something"
    );
    // A ball too low for a stand: refused rather than silently different.
    assert!(built_a
        .with_fixture(&cell, &Vector3::new(1.0, 0.0, 0.005))
        .is_err());
}

#[test]
fn fixture_room_finds_obstacles_the_base_and_the_floor() {
    let r = robot(NJ130_DH);
    let home = frames(&r, &[0.0; 6]);
    let map = map_of(&r);
    let mut cell = CellSpec {
        stand_radius: 0.04,
        ..CellSpec::default()
    };
    cell.environment
        .push(env_box("table", Vector3::new(1.2, -0.9, 0.35), 0.7));
    let room = |f: Vector3<f64>| {
        let (s, _) = build(&r, &cell, &f, &map).unwrap();
        s.fixture_room(&home, cell.margin)
    };
    // Clear of everything.
    assert_eq!(room(Vector3::new(0.258, 1.468, 0.708)), None);
    // Above the table: the stand goes through it.
    let c = room(Vector3::new(1.2, -0.9, 1.0)).expect("stand through the table");
    assert_eq!((c.a.as_str(), c.b.as_str()), (STAND, "table"), "{c:?}");
    // Beside the table by less than the stand radius + the margin (the table's face at x = 0.85).
    assert!(room(Vector3::new(0.85 - 0.045, -0.9, 0.9)).is_some());
    assert_eq!(room(Vector3::new(0.85 - 0.055, -0.9, 0.9)), None);
    // In the robot's base column (link 0 of a DH robot: a column from the floor to frame 0) —
    // only when the base stands above the floor; the NJ-130's frame 0 is on the floor, so its
    // first link (frame 1) is what a fixture on the axis meets, and that moves: not judged here.
    // The ball on the floor.
    let c = room(Vector3::new(1.5, 0.0, 0.0125 + 0.005)).expect("ball on the floor");
    assert_eq!(c.b, FLOOR, "{c:?}");
}

/// A cell with something of every kind near the arm: a tool, a hose on the forearm, two
/// environment boxes in reach, and the bar to a fixture in front of the robot.
fn busy_cell(r: &Robot) -> CellSpec {
    let mut cell = CellSpec::default();
    cell.tool_shapes.push(CellShape {
        name: "cup".into(),
        origin: Frame::translation(Vector3::new(0.0, 0.0, 0.06)),
        kind: ShapeKind::Cylinder {
            radius: 0.05,
            length: 0.12,
        },
    });
    cell.hoses.push(crate::cell::AttachedShape {
        frame: 3,
        shape: CellShape {
            name: "hose".into(),
            origin: Frame::IDENTITY,
            kind: ShapeKind::Capsule {
                a: [0.0, -0.2, 0.0],
                b: [0.0, -0.2, 0.6],
                radius: 0.04,
            },
        },
    });
    let home = frames(r, &[0.0; 6])[7].apply(&map_of(r));
    cell.environment
        .push(env_box("crate", home + Vector3::new(0.1, 0.5, -0.3), 0.3));
    cell.environment
        .push(env_box("post", home + Vector3::new(-0.2, -0.6, 0.1), 0.2));
    cell
}

/// Exact signed distance of checked pair k (body pairs, then bar pairs) at q.
fn pair_distance(s: &Scene, k: usize, q: &[f64; 6], f: &[Frame; 8], map: &Vector3<f64>) -> f64 {
    let poses = Poses::new(q, f, &s.passive);
    if k < s.pairs.len() {
        let (a, b) = s.pairs[k];
        let (ba, bb) = (&s.bodies[a], &s.bodies[b]);
        ba.pair(&poses.of(ba), bb, &poses.of(bb), f64::INFINITY, Mode::Min)
            .unwrap_or(f64::INFINITY)
    } else {
        let bb = &s.bodies[s.bar_pairs[k - s.pairs.len()]];
        let (cap, r) = s.bar(&s.fixture, map).expect("a bar");
        bb.against(
            &poses.of(bb),
            &Placed::bar(&cap, r),
            f64::INFINITY,
            Mode::Min,
        )
        .unwrap_or(f64::INFINITY)
    }
}

#[test]
fn pair_rates_bound_how_fast_every_pair_distance_changes() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    for (file, r) in all_robots() {
        let (s, _) = scene(&r, &busy_cell(&r));
        assert_eq!(s.rates.len(), s.pairs.len() + s.bar_pairs.len());
        let mut worst = 0.0f64;
        let mut tried = 0;
        for _ in 0..60 {
            let q = random_q(&r, &mut rng);
            let dq: [f64; 6] = std::array::from_fn(|_| rng.random_range(-0.02..0.02));
            let q2: [f64; 6] = std::array::from_fn(|i| q[i] + dq[i]);
            let (f1, f2) = (frames(&r, &q), frames(&r, &q2));
            let (m1, m2) = (f1[7].apply(&map_of(&r)), f2[7].apply(&map_of(&r)));
            if (m1 - s.fixture).norm() < 0.1 || (m2 - s.fixture).norm() < 0.1 {
                continue;
            }
            for k in 0..s.rates.len() {
                let (d1, d2) = (
                    pair_distance(&s, k, &q, &f1, &m1),
                    pair_distance(&s, k, &q2, &f2, &m2),
                );
                // Penetration depths come from EPA: only separated pairs are compared.
                if !(d1 > 0.0 && d2 > 0.0 && d1.is_finite() && d2.is_finite()) {
                    continue;
                }
                let bound: f64 = (0..6).map(|i| s.rates[k][i] * dq[i].abs()).sum();
                assert!(
                    (d2 - d1).abs() <= bound + 1e-9,
                    "{file}: pair {k} ({}) distance changed by {} > {bound} ({:?})",
                    if k < s.pairs.len() {
                        format!(
                            "{} / {}",
                            s.bodies[s.pairs[k].0].name, s.bodies[s.pairs[k].1].name
                        )
                    } else {
                        format!("bar / {}", s.bodies[s.bar_pairs[k - s.pairs.len()]].name)
                    },
                    (d2 - d1).abs(),
                    s.rates[k]
                );
                if bound > 0.0 {
                    worst = worst.max((d2 - d1).abs() / bound);
                }
                tried += 1;
            }
        }
        assert!(tried > 100, "{file}: only {tried} pairs compared");
        eprintln!("{file}: worst use of the pair rates {worst:.2}");
    }
}

#[test]
fn violation_along_is_the_full_check_at_every_sample() {
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    for (file, r) in all_robots() {
        let (s, _) = scene(&r, &busy_cell(&r));
        let mut found = [0usize; 2];
        for _ in 0..12 {
            let a = random_q(&r, &mut rng);
            // Moves of every length: a few degrees to across the range.
            let scale = [0.05, 0.3, 1.0][rng.random_range(0..3)];
            let b: [f64; 6] = std::array::from_fn(|i| {
                (a[i] + scale * rng.random_range(-2.0..2.0))
                    .clamp(r.joints[i].lower, r.joints[i].upper)
            });
            let lip: [f64; 6] = std::array::from_fn(|i| (b[i] - a[i]).abs());
            let mut co = s.coherence(&lip);
            // In order, then the bisection's out-of-order midpoints.
            let mut ss: Vec<f64> = (0..=100).map(|k| k as f64 / 100.0).collect();
            ss.extend((0..100).map(|k| (k as f64 + 0.5) / 100.0).rev());
            for &t in &ss {
                let q: [f64; 6] = std::array::from_fn(|i| a[i] + (b[i] - a[i]) * t);
                let f = frames(&r, &q);
                let map = f[7].apply(&map_of(&r));
                let mounted = rng.random_bool(0.8);
                let (full, along) = if mounted {
                    (
                        s.violation(&q, &f, &map, 0.01),
                        s.violation_along(&q, &f, Some(&map), 0.01, t, &mut co),
                    )
                } else {
                    (
                        s.violation_unmounted(&q, &f, 0.01),
                        s.violation_along(&q, &f, None, 0.01, t, &mut co),
                    )
                };
                assert_eq!(full, along, "{file}: {a:?} -> {b:?} at {t}");
                found[full.is_some() as usize] += 1;
            }
        }
        assert!(found[0] > 100 && found[1] > 100, "{file}: {found:?}");
    }
}

#[test]
fn a_remembered_direction_bounds_every_pair_from_below() {
    // Along slow moves, `bound_along` with the direction of its last exact measure never
    // exceeds the pair's true distance (a separating-axis bound is one whatever the direction),
    // whether it served without GJK or measured again.
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let mut total = nalgebra::Vector2::<usize>::zeros();
    for (file, r) in all_robots() {
        let (s, _) = scene(&r, &busy_cell(&r));
        let (mut served, mut measured, mut compared) = (0usize, 0usize, 0usize);
        for _ in 0..6 {
            let a = random_q(&r, &mut rng);
            let b: [f64; 6] = std::array::from_fn(|i| {
                (a[i] + 0.3 * rng.random_range(-1.0..1.0))
                    .clamp(r.joints[i].lower, r.joints[i].upper)
            });
            let mut warm = vec![Warm::NONE; s.pairs.len()];
            for k in 0..=200 {
                let t = k as f64 / 200.0;
                let q: [f64; 6] = std::array::from_fn(|i| a[i] + (b[i] - a[i]) * t);
                let f = frames(&r, &q);
                let poses = Poses::new(&q, &f, &s.passive);
                for (p, &(ia, ib)) in s.pairs.iter().enumerate() {
                    let (ba, bb) = (&s.bodies[ia], &s.bodies[ib]);
                    let (pa, pb) = (poses.of(ba), poses.of(bb));
                    let before = (warm[p].exact.to_bits(), warm[p].dir);
                    let bound = ba.bound_along(&pa, bb, &pb, 0.05, 0.01, &mut warm[p]);
                    // Pairs the bounding spheres keep apart never reach either.
                    let spheres = gap(
                        &(pa * ba.center),
                        ba.radius,
                        ba.plane,
                        &(pb * bb.center),
                        bb.radius,
                        bb.plane,
                    );
                    if spheres < 0.05 && !ba.plane && !bb.plane {
                        if before == (warm[p].exact.to_bits(), warm[p].dir) && before.1.is_some() {
                            served += 1;
                        } else {
                            measured += 1;
                        }
                    }
                    if let Some(d) = ba.pair(&pa, bb, &pb, FAR, Mode::Min) {
                        compared += 1;
                        assert!(
                            bound <= d + 1e-9,
                            "{file}: {} / {}: bound {bound} above the distance {d} at {q:?}",
                            ba.name,
                            bb.name
                        );
                    }
                }
            }
        }
        assert!(compared > 1000, "{file}: {compared}");
        total += nalgebra::Vector2::new(served, measured);
    }
    // The remembered direction does serve (on the mesh robots' hulls; how often is a matter of
    // speed, for the benchmarks): the bound above was checked on both paths.
    assert!(total[0] > 0 && total[1] > 0, "served, measured: {total:?}");
}
