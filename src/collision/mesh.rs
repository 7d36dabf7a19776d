//! Mesh files → vertex clouds (in = a path and a scale; out = points in metres). Only the
//! vertices matter: every mesh becomes its convex hull (see the module docs for why).

use super::CollisionError;
use parry3d_f64::math::Point;
use std::path::Path;

/// Reads the vertices of a binary or ASCII STL, or of a Wavefront OBJ (`v x y z` lines only),
/// and multiplies them by `scale` per axis.
pub(super) fn vertices(path: &Path, scale: [f64; 3]) -> Result<Vec<Point<f64>>, CollisionError> {
    let shown = path.display().to_string();
    let bad = |msg: &str| CollisionError::Mesh {
        path: shown.clone(),
        msg: msg.to_string(),
    };
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    let bytes = crate::files::read(path, crate::files::Kind::Mesh).map_err(|e| match e {
        crate::files::ReadError::Io(source) => CollisionError::Io {
            path: shown.clone(),
            source,
        },
        other => bad(&other.to_string()),
    })?;
    let raw: Vec<[f64; 3]> = match ext.as_str() {
        "stl" => {
            let mesh = stl_io::read_stl(&mut std::io::Cursor::new(&bytes))
                .map_err(|e| bad(&format!("not a readable STL: {e}")))?;
            mesh.vertices
                .iter()
                .map(|v| v.0.map(|c| c as f64))
                .collect()
        }
        "obj" => obj_vertices(&bytes).map_err(|m| bad(&m))?,
        "dae" => {
            return Err(bad(
                "COLLADA (.dae) meshes are not supported; convert to STL",
            ))
        }
        _ => return Err(bad("unknown mesh type (expected .stl or .obj)")),
    };
    if raw.iter().flatten().any(|c| !c.is_finite()) {
        return Err(bad("vertex coordinates are not finite"));
    }
    Ok(raw
        .into_iter()
        .map(|v| Point::new(v[0] * scale[0], v[1] * scale[1], v[2] * scale[2]))
        .collect())
}

fn obj_vertices(bytes: &[u8]) -> Result<Vec<[f64; 3]>, String> {
    let text = std::str::from_utf8(bytes).map_err(|_| "OBJ is not UTF-8 text".to_string())?;
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let mut it = line.split_whitespace();
        if it.next() != Some("v") {
            continue;
        }
        let mut v = [0.0; 3];
        for c in &mut v {
            *c = it
                .next()
                .and_then(|s| s.parse().ok())
                .ok_or_else(|| format!("line {}: a vertex needs three numbers", n + 1))?;
        }
        out.push(v);
    }
    Ok(out)
}
