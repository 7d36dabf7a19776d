//! STL (binary or ASCII) and OBJ mesh bytes, read through a URDF that names them and the
//! collision scene that hulls them: any bytes must give a scene or an error, never a panic.
#![no_main]
use libfuzzer_sys::fuzz_target;
use nalgebra::Vector3;

const URDF: &str = r#"<robot name="r">
<link name="l0"/><link name="l1"><collision><geometry><mesh filename="MESH"/></geometry></collision></link>
<link name="l2"/><link name="l3"/><link name="l4"/><link name="l5"/><link name="l6"/>
<joint name="j1" type="revolute"><parent link="l0"/><child link="l1"/><origin xyz="0 0 0.4"/><axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="2"/></joint>
<joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/><origin xyz="0.2 0 0.3"/><axis xyz="0 1 0"/><limit lower="-2" upper="2" effort="1" velocity="2"/></joint>
<joint name="j3" type="revolute"><parent link="l2"/><child link="l3"/><origin xyz="0 0 0.8"/><axis xyz="0 1 0"/><limit lower="-2" upper="2" effort="1" velocity="2"/></joint>
<joint name="j4" type="revolute"><parent link="l3"/><child link="l4"/><origin xyz="0.7 0 0.1"/><axis xyz="1 0 0"/><limit lower="-3" upper="3" effort="1" velocity="2"/></joint>
<joint name="j5" type="revolute"><parent link="l4"/><child link="l5"/><origin xyz="0.1 0 0"/><axis xyz="0 1 0"/><limit lower="-2" upper="2" effort="1" velocity="2"/></joint>
<joint name="j6" type="revolute"><parent link="l5"/><child link="l6"/><origin xyz="0.1 0 0"/><axis xyz="1 0 0"/><limit lower="-3" upper="3" effort="1" velocity="2"/></joint>
</robot>"#;

fuzz_target!(|data: &[u8]| {
    let Some((&kind, bytes)) = data.split_first() else {
        return;
    };
    let name = if kind % 2 == 0 { "m.stl" } else { "m.obj" };
    let Ok(dir) = tempfile::tempdir() else { return };
    let path = dir.path().join("robot.urdf");
    if std::fs::write(&path, URDF.replace("MESH", name)).is_err()
        || std::fs::write(dir.path().join(name), bytes).is_err()
    {
        return;
    }
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
