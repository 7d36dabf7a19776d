//! Stand-in collision meshes for `bench/ur10/robot.urdf` (see its header): per link, the union
//! of cylinders with chamfered ends after the UR10's published link dimensions, written as
//! binary STL in the link's own frame. Shared by `examples/bench.rs`; the meshes are generated
//! (not shipped) because the source's could not be fetched as files.

use std::io::Write;
use std::path::Path;

/// Segments around a cylinder.
const SEGMENTS: usize = 64;

/// A cylinder from `a` to `b` (m) of radius `r`, its ends chamfered.
struct Cyl {
    a: [f64; 3],
    b: [f64; 3],
    r: f64,
}

const fn cyl(a: [f64; 3], b: [f64; 3], r: f64) -> Cyl {
    Cyl { a, b, r }
}

/// (file name, parts) per link, in the link frames of `bench/ur10/robot.urdf`.
fn links() -> Vec<(&'static str, Vec<Cyl>)> {
    vec![
        ("Base", vec![cyl([0.0, 0.0, 0.0], [0.0, 0.0, 0.09], 0.095)]),
        (
            "Shoulder",
            vec![
                cyl([0.0, 0.0, -0.075], [0.0, 0.0, 0.07], 0.077),
                cyl([0.0, 0.03, 0.0], [0.0, 0.235, 0.0], 0.077),
            ],
        ),
        (
            "UpperArm",
            vec![
                cyl([0.0, -0.065, 0.0], [0.0, 0.065, 0.0], 0.077),
                cyl([0.0, 0.0, 0.05], [0.0, 0.0, 0.55], 0.058),
                cyl([0.0, -0.07, 0.60186], [0.0, 0.06, 0.60186], 0.062),
            ],
        ),
        (
            "Forearm",
            vec![
                cyl([0.0, -0.055, 0.0], [0.0, 0.045, 0.0], 0.062),
                cyl([0.0, 0.0, 0.05], [0.0, 0.0, 0.52], 0.045),
                cyl([0.0, -0.05, 0.56415], [0.0, 0.045, 0.56415], 0.047),
            ],
        ),
        (
            "Wrist1",
            vec![
                cyl([0.0, 0.055, 0.0], [0.0, 0.16, 0.0], 0.047),
                cyl([0.0, 0.11279, -0.05], [0.0, 0.11279, 0.045], 0.047),
            ],
        ),
        (
            "Wrist2",
            vec![
                cyl([0.0, 0.0, 0.055], [0.0, 0.0, 0.16], 0.047),
                cyl([0.0, -0.05, 0.11279], [0.0, 0.04, 0.11279], 0.047),
            ],
        ),
        (
            "Wrist3",
            vec![cyl([0.0, 0.05, 0.0], [0.0, 0.0857, 0.0], 0.045)],
        ),
    ]
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn unit(a: [f64; 3]) -> [f64; 3] {
    let n = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
    [a[0] / n, a[1] / n, a[2] / n]
}

/// The triangles of one chamfered cylinder: 8 rings (the chamfers rounded in three steps)
/// joined by quads, closed by fans.
fn triangles(c: &Cyl, out: &mut Vec<[[f64; 3]; 3]>) {
    let axis = sub(c.b, c.a);
    let len = (axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2]).sqrt();
    let w = unit(axis);
    let helper = if w[0].abs() < 0.9 {
        [1.0, 0.0, 0.0]
    } else {
        [0.0, 1.0, 0.0]
    };
    let u = unit(cross(w, helper));
    let v = cross(w, u);
    let ch = (0.25 * c.r).min(0.3 * len);
    // (distance along the axis, radius) of each ring: a convex profile.
    let rings = [
        (0.0, 0.75 * c.r),
        (0.15 * ch, 0.9 * c.r),
        (0.5 * ch, 0.97 * c.r),
        (ch, c.r),
        (len - ch, c.r),
        (len - 0.5 * ch, 0.97 * c.r),
        (len - 0.15 * ch, 0.9 * c.r),
        (len, 0.75 * c.r),
    ];
    let point = |t: f64, r: f64, k: usize| {
        let phi = std::f64::consts::TAU * k as f64 / SEGMENTS as f64;
        let (s, co) = phi.sin_cos();
        std::array::from_fn(|i| c.a[i] + w[i] * t + r * (co * u[i] + s * v[i]))
    };
    for pair in rings.windows(2) {
        let ((t0, r0), (t1, r1)) = (pair[0], pair[1]);
        for k in 0..SEGMENTS {
            let k1 = (k + 1) % SEGMENTS;
            let (p00, p01) = (point(t0, r0, k), point(t0, r0, k1));
            let (p10, p11) = (point(t1, r1, k), point(t1, r1, k1));
            out.push([p00, p10, p11]);
            out.push([p00, p11, p01]);
        }
    }
    for (t, r, flip) in [(0.0, rings[0].1, true), (len, rings[7].1, false)] {
        let centre: [f64; 3] = std::array::from_fn(|i| c.a[i] + w[i] * t);
        for k in 0..SEGMENTS {
            let (p, q) = (point(t, r, k), point(t, r, (k + 1) % SEGMENTS));
            out.push(if flip { [centre, q, p] } else { [centre, p, q] });
        }
    }
}

/// Writes `<dir>/meshes/collision/<Link>.stl` for every link of the stand-in UR10.
pub fn write(dir: &Path) -> std::io::Result<()> {
    let meshes = dir.join("meshes/collision");
    std::fs::create_dir_all(&meshes)?;
    for (name, parts) in links() {
        let mut tris = Vec::new();
        for c in &parts {
            triangles(c, &mut tris);
        }
        let mut bytes = Vec::with_capacity(84 + 50 * tris.len());
        let mut header = [b' '; 80];
        let title = format!("edbbgen bench: UR10 stand-in {name}");
        header[..title.len()].copy_from_slice(title.as_bytes());
        bytes.extend_from_slice(&header);
        bytes.extend_from_slice(&(tris.len() as u32).to_le_bytes());
        for t in &tris {
            let n = unit(cross(sub(t[1], t[0]), sub(t[2], t[0])));
            for x in n.iter().chain(t.iter().flatten()) {
                bytes.extend_from_slice(&(*x as f32).to_le_bytes());
            }
            bytes.extend_from_slice(&0u16.to_le_bytes());
        }
        std::fs::File::create(meshes.join(format!("{name}.stl")))?.write_all(&bytes)?;
    }
    Ok(())
}
