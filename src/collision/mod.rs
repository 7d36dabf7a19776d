//! Temporary stub of the collision API (replaced by the parry implementation at merge).
#![allow(dead_code)]
use crate::cell::CellSpec;
use crate::robot::{Frame, Robot};
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

pub struct Scene {
    sweep: [f64; 6],
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ExcludedPair {
    pub a: String,
    pub b: String,
    pub reason: String,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SceneReport {
    pub bodies: Vec<String>,
    pub pairs_checked: usize,
    pub excluded: Vec<ExcludedPair>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Contact {
    pub distance: f64,
    pub a: String,
    pub b: String,
}

#[derive(Debug, thiserror::Error)]
pub enum CollisionError {
    #[error("{0}")]
    Invalid(String),
}

pub fn build(
    robot: &Robot,
    _cell: &CellSpec,
    _fixture: &Vector3<f64>,
    map: &Vector3<f64>,
) -> Result<(Scene, SceneReport), CollisionError> {
    let dh = &robot.dh;
    let tail = robot.flange.apply(map).norm() + 0.2;
    let sweep = std::array::from_fn(|i| {
        ((i + 1)..6).map(|k| dh[k].a.hypot(dh[k].d)).sum::<f64>() + tail + 0.2
    });
    Ok((
        Scene { sweep },
        SceneReport {
            bodies: vec![],
            pairs_checked: 0,
            excluded: vec![],
        },
    ))
}

impl Scene {
    pub fn violation(
        &self,
        _frames: &[Frame; 8],
        _map_world: &Vector3<f64>,
        _margin: f64,
    ) -> Option<Contact> {
        None
    }
    pub fn clearance(&self, _frames: &[Frame; 8], _map_world: &Vector3<f64>) -> Contact {
        Contact {
            distance: f64::INFINITY,
            a: String::new(),
            b: String::new(),
        }
    }
    pub fn sweep_radius(&self) -> [f64; 6] {
        self.sweep
    }
}
