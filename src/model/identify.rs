//! Identifiability (Section 2.1.2): in = identification-Jacobian rows over a rich pose set;
//! out = each parameter classified as identifiable, linearly dependent (on which), negligible or
//! held known; plus the observability indices of Table 2.
//!
//! Method: columns are scaled to unit norm (so metres and radians compare), then taken greedily
//! in a fixed preference order by modified Gram–Schmidt with re-orthogonalisation — a QR
//! factorisation whose pivot order is the preference order instead of the column norms. The
//! preference order (DH in Eq. 6 order, then MAP, then fixture) reproduces the paper's choices:
//! d3 is fixed against d2, θ6 against α6, a6, d6, the fixture against d1 and θ1.

use super::{N_PARAMS, PARAM_NAMES};
use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

/// A column whose RMS sensitivity is below this (metres of L per metre or radian of parameter)
/// cannot be seen by a 1 µm instrument: negligible.
pub const NEGLIGIBLE: f64 = 1e-6;
/// A unit column whose component orthogonal to the accepted ones is below this is dependent.
pub const DEPENDENT: f64 = 1e-6;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "status", rename_all = "snake_case")]
pub enum Status {
    Identifiable,
    /// Linearly dependent on the named identifiable parameters.
    Dependent {
        on: Vec<String>,
    },
    Negligible,
    /// Held at its nominal value by assumption (fixture or MAP known).
    Known,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ParamInfo {
    pub name: String,
    #[serde(flatten)]
    pub status: Status,
    /// RMS of ∂L/∂p over the pose set (m/m or m/rad).
    pub sensitivity: f64,
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct IdentifyOptions {
    pub fixture_known: bool,
    pub map_known: bool,
}

impl Default for IdentifyOptions {
    fn default() -> Self {
        // As in the paper: the fixture is not part of the robot, the MAP depends on α6, a6, d6.
        IdentifyOptions {
            fixture_known: true,
            map_known: true,
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Identifiability {
    pub params: Vec<ParamInfo>,
    /// Indices (Eq. 6 order) of the identifiable parameters: the columns used for selection.
    pub identifiable: Vec<usize>,
    pub poses: usize,
}

impl Identifiability {
    pub fn count(&self) -> usize {
        self.identifiable.len()
    }

    pub fn names_with(&self, pred: impl Fn(&Status) -> bool) -> Vec<&str> {
        self.params
            .iter()
            .filter(|p| pred(&p.status))
            .map(|p| p.name.as_str())
            .collect()
    }
}

/// Preference order for taking parameters into the identifiable set (see module docs).
fn preference_order() -> impl Iterator<Item = usize> {
    (super::ALPHA..super::MAP)
        .chain(super::MAP..N_PARAMS)
        .chain(super::FIX..super::ALPHA)
}

/// Classifies the 30 parameters from Jacobian rows (one row per pose).
pub fn analyse(rows: &[[f64; N_PARAMS]], opts: &IdentifyOptions) -> Identifiability {
    let names: Vec<String> = PARAM_NAMES.iter().map(|s| s.to_string()).collect();
    let known: Vec<bool> = (0..N_PARAMS)
        .map(|j| {
            (super::is_fixture(j) && opts.fixture_known) || (super::is_map(j) && opts.map_known)
        })
        .collect();
    let order: Vec<usize> = preference_order().collect();
    let cols = DMatrix::from_fn(rows.len(), N_PARAMS, |i, j| rows[i][j]);
    let (params, identifiable) = classify(&cols, &names, &order, &known);
    Identifiability {
        params,
        identifiable,
        poses: rows.len(),
    }
}

/// Classifies the columns of a Jacobian (rows = observations, one column per parameter named in
/// `names`), taken in the preference `order` (columns not in it are known): known, negligible,
/// dependent on the ones taken before, or identifiable. Returns every column's info and the
/// identifiable columns in ascending order. The same rule for one run's 30 parameters
/// ([`analyse`]) and for a campaign's shared geometry plus one fixture per run.
pub fn classify(
    cols: &DMatrix<f64>,
    names: &[String],
    order: &[usize],
    known: &[bool],
) -> (Vec<ParamInfo>, Vec<usize>) {
    let (n, m) = cols.shape();
    let norms: Vec<f64> = (0..m).map(|j| cols.column(j).norm()).collect();
    let rms = |j: usize| {
        if n > 0 {
            norms[j] / (n as f64).sqrt()
        } else {
            0.0
        }
    };

    let mut status: Vec<Option<Status>> = vec![None; m];
    let mut accepted: Vec<usize> = Vec::new();
    let mut basis: Vec<DVector<f64>> = Vec::new();
    for &j in order {
        if known[j] {
            status[j] = Some(Status::Known);
            continue;
        }
        if rms(j) < NEGLIGIBLE {
            status[j] = Some(Status::Negligible);
            continue;
        }
        let mut v: DVector<f64> = cols.column(j) / norms[j];
        // Twice is enough (Kahan–Parlett) to keep the basis orthogonal to working precision.
        for _ in 0..2 {
            for b in &basis {
                let c = b.dot(&v);
                v.axpy(-c, b, 1.0);
            }
        }
        let r = v.norm();
        if r > DEPENDENT {
            basis.push(v / r);
            accepted.push(j);
            status[j] = Some(Status::Identifiable);
        } else {
            let on = dependence(cols, &norms, &accepted, j);
            status[j] = Some(Status::Dependent {
                on: on.into_iter().map(|k| names[k].clone()).collect(),
            });
        }
    }
    let mut identifiable = accepted;
    identifiable.sort_unstable();
    let params = (0..m)
        .map(|j| ParamInfo {
            name: names[j].clone(),
            status: status[j].clone().unwrap_or(Status::Known),
            sensitivity: rms(j),
        })
        .collect();
    (params, identifiable)
}

/// The accepted columns that a dependent column is made of (least squares on unit columns).
fn dependence(cols: &DMatrix<f64>, norms: &[f64], accepted: &[usize], j: usize) -> Vec<usize> {
    if accepted.is_empty() {
        return Vec::new();
    }
    let a = DMatrix::from_fn(cols.nrows(), accepted.len(), |i, k| {
        cols[(i, accepted[k])] / norms[accepted[k]]
    });
    let b = cols.column(j) / norms[j];
    let Ok(beta) = a.svd(true, true).solve(&b, 1e-12) else {
        return Vec::new();
    };
    let big = beta.amax();
    let mut on: Vec<usize> = accepted
        .iter()
        .zip(beta.iter())
        .filter(|(_, c)| c.abs() > 1e-6 * big)
        .map(|(&k, _)| k)
        .collect();
    on.sort_unstable();
    on
}

/// Observability indices of Table 2 for a Jacobian with P rows (poses) and r columns.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Observability {
    /// O1 = (μ1···μr)^(1/r) / √P → max.
    pub o1: f64,
    /// O2 = μ1/μr, the condition number → min.
    pub o2: f64,
    /// O3 = μr, the minimum singular value → max.
    pub o3: f64,
    /// O4 = μr²/μ1, the noise amplification index → max.
    pub o4: f64,
}

/// Table 2 from the singular values of `j` (rows = poses).
pub fn observability(j: &DMatrix<f64>) -> Observability {
    let sv = j.singular_values();
    let r = sv.len();
    if r == 0 || j.nrows() == 0 {
        return Observability {
            o1: 0.0,
            o2: f64::INFINITY,
            o3: 0.0,
            o4: 0.0,
        };
    }
    let max = sv.max();
    let min = sv.min();
    let geo = (sv.iter().map(|s| s.ln()).sum::<f64>() / r as f64).exp();
    Observability {
        o1: geo / (j.nrows() as f64).sqrt(),
        o2: if min > 0.0 { max / min } else { f64::INFINITY },
        o3: min,
        o4: if max > 0.0 { min * min / max } else { 0.0 },
    }
}
