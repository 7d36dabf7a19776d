//! A convex hull with an O(√n) support function: in = hull vertices and triangles (from parry's
//! hull); out = a parry `SupportMap`. parry's `ConvexPolyhedron` scans every vertex per GJK
//! step, and the URDF hulls have up to ~4500 vertices; here the support point is found by
//! climbing the hull's vertex–edge graph from the best of a few seed vertices. On a convex
//! polytope a vertex no neighbour improves on maximises a linear function globally (the simplex
//! method's argument), so the result is exact, not approximate.

use nalgebra::{Point3, Vector3};
use parry3d_f64::shape::SupportMap;

pub(super) struct Hull {
    points: Vec<Point3<f64>>,
    /// CSR adjacency: the neighbours of vertex v are `adj[start[v]..start[v + 1]]`.
    start: Vec<u32>,
    adj: Vec<u32>,
    seeds: Vec<u32>,
}

impl Hull {
    pub(super) fn new(points: Vec<Point3<f64>>, triangles: &[[u32; 3]]) -> Hull {
        let n = points.len();
        let mut edges: Vec<(u32, u32)> = triangles
            .iter()
            .flat_map(|t| [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])])
            .flat_map(|(a, b)| [(a, b), (b, a)])
            .collect();
        edges.sort_unstable();
        edges.dedup();
        let mut start = vec![0u32; n + 1];
        for &(a, _) in &edges {
            start[a as usize + 1] += 1;
        }
        for v in 0..n {
            start[v + 1] += start[v];
        }
        let adj = edges.iter().map(|&(_, b)| b).collect();
        // Seeds: the extreme vertices along the 26 directions of a cube's faces, edges and corners.
        let mut seeds: Vec<u32> = Vec::new();
        for x in -1..=1 {
            for y in -1..=1 {
                for z in -1..=1 {
                    if (x, y, z) == (0, 0, 0) {
                        continue;
                    }
                    let d = Vector3::new(x as f64, y as f64, z as f64);
                    seeds.push(scan(&points, &d) as u32);
                }
            }
        }
        seeds.sort_unstable();
        seeds.dedup();
        Hull {
            points,
            start,
            adj,
            seeds,
        }
    }

    #[cfg(test)]
    pub(super) fn points(&self) -> &[Point3<f64>] {
        &self.points
    }
}

/// The linear scan (reference and seed finder).
pub(super) fn scan(points: &[Point3<f64>], dir: &Vector3<f64>) -> usize {
    let mut best = (f64::NEG_INFINITY, 0);
    for (i, p) in points.iter().enumerate() {
        let s = p.coords.dot(dir);
        if s > best.0 {
            best = (s, i);
        }
    }
    best.1
}

impl SupportMap for Hull {
    fn local_support_point(&self, dir: &Vector3<f64>) -> Point3<f64> {
        let dot = |v: u32| self.points[v as usize].coords.dot(dir);
        let mut v = self.seeds[0];
        let mut best = dot(v);
        for &s in &self.seeds[1..] {
            let d = dot(s);
            if d > best {
                (v, best) = (s, d);
            }
        }
        loop {
            let mut next = v;
            for &w in
                &self.adj[self.start[v as usize] as usize..self.start[v as usize + 1] as usize]
            {
                let d = dot(w);
                if d > best {
                    (next, best) = (w, d);
                }
            }
            if next == v {
                return self.points[v as usize];
            }
            v = next;
        }
    }
}
