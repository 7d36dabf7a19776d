//! URDF through the loader and the collision scene (meshes resolved next to the file): any
//! text must give a robot and a scene, or an error, never a panic.
#![no_main]
use libfuzzer_sys::fuzz_target;
use nalgebra::Vector3;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(dir) = tempfile::tempdir() else { return };
    let path = dir.path().join("robot.urdf");
    if std::fs::write(&path, text).is_err() {
        return;
    }
    // A small valid mesh the fuzzed URDF may name.
    let _ = std::fs::write(
        dir.path().join("m.obj"),
        "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\n",
    );
    if let Ok(robot) = edbbgen::robot::load(&path, &Default::default()) {
        let cell = edbbgen::cell::CellSpec::default();
        let _ = edbbgen::collision::build(
            &robot,
            &cell,
            &Vector3::new(1.0, 0.5, 0.5),
            &Vector3::new(0.0, 0.0, 0.1),
        );
    }
});
