//! The one integration-test binary: the CLI as users and CI call it.

mod common;

mod cli;
mod cli_errors;
mod compile;
mod diagnose;
mod fuzz;
mod linuxcnc;
mod model_cmd;
mod report;
mod safety;
mod snapshots;
