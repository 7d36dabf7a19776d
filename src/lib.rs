//! edbbgen compiles error-sensitive Extended Double Ball Bar (EDBB) measurement programs.
//!
//! The pipeline (one stage, one module; only [`pipeline`] chains them):
//!
//! ```text
//! load ─▶ model ─▶ sample ─▶ select ─▶ order ─▶ emit ─▶ verify
//! robot   L(q,p), J  joint grid,  cond(J)   TSP      template  re-read
//! ```
//!
//! - [`robot`]: `.dh.toml` / `.urdf` → [`robot::Robot`] (standard DH between fixed transforms).
//! - [`model`]: the measurement model L(q,p) (Eq. 1-2), its identification Jacobian (Eq. 3-5),
//!   identifiability (Section 2.1.2) and the observability indices O1..O4 (Table 2).
//! - [`sample`]: streaming joint-space grid → candidate poses whose MAP lies in the EDBB shell.
//! - [`select`]: condition-number pruning of the candidates (Section 2.1.3, Fig. 5).
//! - [`order`]: time-optimal open tour (Eq. 7).
//! - [`emit`]: dialect templates → program text.
//! - [`twin`]: the digital twin (truth model, effects library, program timing, simulation) and
//!   the ISO 230-4 circle test; [`diagnose`]: measured vs simulated, calibration, effect
//!   selection, report.
//! - [`place`]: where the fixture goes: candidate positions scored by the MAP position
//!   uncertainty a calibration from a program compiled there would reach; campaigns of K.
//! - [`ldbb`]: the loaded double ball bar (Sections 2.2, 3.2, 4.2): compliance along the bar,
//!   Eq. 8 and 9, the kinematic remainder, joint stiffness; its circle program and simulator.
//!
//! Internally everything is SI (m, rad, s); millimetres and degrees exist only at the edges.

// Joint loops index several arrays by joint number; `for i in 0..6` says that best.
#![allow(clippy::needless_range_loop)]

pub mod calibrate;
pub mod cell;
pub mod cli;
pub mod collision;
pub mod compensate;
pub mod controller;
pub mod diagnose;
pub mod dialect;
pub mod emit;
pub mod files;
pub mod ir;
pub mod ldbb;
pub mod logs;
pub mod model;
pub mod order;
pub mod pipeline;
pub mod place;
pub mod plot;
pub mod report;
pub mod robot;
pub mod safety;
pub mod sample;
pub mod select;
pub mod stats;
pub mod timing;
pub mod twin;
pub mod units;
pub mod verify;
