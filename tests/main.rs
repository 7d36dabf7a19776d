//! The one integration-test binary: the CLI as users and CI call it.

// Joint loops index several arrays by joint number; `for i in 0..6` says that best.
#![allow(clippy::needless_range_loop)]

mod common;

mod architecture;
mod calibrate;
mod calibrate_real;
mod catalogue;
mod cli;
mod cli_errors;
mod compensate;
mod compile;
mod corners;
mod coupling;
mod delivered;
mod determinism;
mod diagnose;
mod dialects;
mod docs;
mod drift;
mod effects;
mod fuzz;
mod header_limits;
mod joint_logs;
mod ldbb;
mod linuxcnc;
mod logs;
mod model_cmd;
mod othersim;
mod own_programs;
mod passive;
mod place;
mod report;
mod safety;
mod snapshots;
mod structure;
mod ur10_tracker;
mod zero_length;
