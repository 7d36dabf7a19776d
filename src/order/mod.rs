//! Temporary ordering stage (replaced by the helper's implementation at merge).
use serde::{Deserialize, Serialize};

pub fn move_time(a: &[f64; 6], b: &[f64; 6], w: &[f64; 6]) -> f64 {
    (0..6).map(|n| (a[n] - b[n]).abs() / w[n]).fold(0.0, f64::max)
}

pub fn path_time(poses: &[[f64; 6]], order: &[usize], w: &[f64; 6]) -> f64 {
    order.windows(2).map(|p| move_time(&poses[p[0]], &poses[p[1]], w)).sum()
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Tour {
    pub order: Vec<usize>,
    pub time_unsorted: f64,
    pub time_sorted: f64,
}

#[derive(Debug, thiserror::Error)]
pub enum OrderError {
    #[error("start index {start} out of range for {n} poses")]
    Start { start: usize, n: usize },
}

pub fn solve(poses: &[[f64; 6]], start: usize, w: &[f64; 6]) -> Result<Tour, OrderError> {
    let n = poses.len();
    if start >= n {
        return Err(OrderError::Start { start, n });
    }
    let mut order = vec![start];
    let mut left: Vec<usize> = (0..n).filter(|&i| i != start).collect();
    while !left.is_empty() {
        let cur = *order.last().unwrap_or(&start);
        let (k, _) = left.iter().enumerate().map(|(k, &i)| (k, move_time(&poses[cur], &poses[i], w))).fold((0, f64::INFINITY), |b, c| if c.1 < b.1 { c } else { b });
        order.push(left.remove(k));
    }
    let mut unsorted: Vec<usize> = vec![start];
    unsorted.extend((0..n).filter(|&i| i != start));
    Ok(Tour { time_unsorted: path_time(poses, &unsorted, w), time_sorted: path_time(poses, &order, w), order })
}
