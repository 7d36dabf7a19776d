//! A slice of numbers in, its median out (None for an empty slice): the one median every module
//! uses, so that the logs' matcher, the plateau finder and the summaries agree on even lengths.

/// The median: the middle value of the sorted numbers, the mean of the two middle ones for an
/// even count; None when there are none. NaNs sort after every number (`f64::total_cmp`).
pub fn median(v: &[f64]) -> Option<f64> {
    median_in_place(&mut v.to_vec())
}

/// [`median`] without a copy: `v` is reordered (linear time, no full sort).
pub fn median_in_place(v: &mut [f64]) -> Option<f64> {
    let n = v.len();
    if n == 0 {
        return None;
    }
    let k = n / 2;
    let (lower, upper, _) = v.select_nth_unstable_by(k, f64::total_cmp);
    let upper = *upper;
    if n % 2 == 1 {
        return Some(upper);
    }
    // The largest of the lower half is the other middle value.
    let below = lower.iter().copied().max_by(f64::total_cmp)?;
    Some(0.5 * (below + upper))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// By the definition: sorted by repeated exchange of neighbours, then the middle (or the
    /// mean of the two middle values).
    fn reference(v: &[f64]) -> Option<f64> {
        let mut s = v.to_vec();
        for i in 0..s.len() {
            for j in 0..s.len() - 1 - i {
                if s[j] > s[j + 1] {
                    s.swap(j, j + 1);
                }
            }
        }
        let n = s.len();
        match n {
            0 => None,
            _ if n % 2 == 1 => Some(s[n / 2]),
            _ => Some((s[n / 2 - 1] + s[n / 2]) / 2.0),
        }
    }

    #[test]
    fn median_matches_the_definition_on_random_slices_with_ties() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for _ in 0..2000 {
            let n = rng.random_range(0..24);
            // Few distinct values, so that ties and repeated middles are common.
            let v: Vec<f64> = (0..n)
                .map(|_| f64::from(rng.random_range(-5i32..6)) * 0.25)
                .collect();
            assert_eq!(median(&v), reference(&v), "{v:?}");
            let mut w = v.clone();
            assert_eq!(median_in_place(&mut w), reference(&v), "{v:?}");
        }
        assert_eq!(median(&[]), None);
        assert_eq!(median(&[3.0]), Some(3.0));
        assert_eq!(median(&[4.0, 1.0]), Some(2.5));
        assert_eq!(median(&[5.0, 1.0, 3.0, 2.0]), Some(2.5));
    }
}
