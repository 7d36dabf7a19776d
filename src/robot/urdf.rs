//! URDF loader (the only module that imports urdf-rs). Filled in by the URDF work.
use super::{LoadError, LoadOptions, Robot};
use std::path::Path;

pub fn from_str(_text: &str, path: &Path, _opts: &LoadOptions) -> Result<Robot, LoadError> {
    Err(LoadError::invalid(path, "URDF loading not built yet"))
}
