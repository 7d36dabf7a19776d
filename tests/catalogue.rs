//! The bad-input catalogue: every subcommand and every file kind, each case refused with exit 2
//! and one line on stderr that names the file, field or flag at fault; no panic, and nothing
//! written (the output directory stays empty: no partial file, no temp file).

use crate::common::*;
use std::path::{Path, PathBuf};

/// The inputs the cases draw on: good files (so that exactly one thing is wrong per case) and
/// bad ones, written into `fx`.
struct Fixtures {
    fx: PathBuf,
    out: PathBuf,
}

impl Fixtures {
    fn new(dir: &Path) -> Fixtures {
        let fx = dir.join("fx");
        let out = dir.join("out");
        std::fs::create_dir_all(&fx).unwrap();
        std::fs::create_dir_all(&out).unwrap();
        let f = Fixtures { fx, out };
        // A good program: the golden NJ-130 program without insta's front matter.
        let golden =
            std::fs::read_to_string(root().join("snapshots/gcode@nj130_default.snap")).unwrap();
        let body = golden.splitn(3, "---\n").nth(2).unwrap().to_string();
        f.write("prog.nc", &body);
        f.write(
            "measured.csv",
            "t_s,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,length_mm\n0,0,0,0,0,0,0,400\n",
        );
        f.write(
            "loaded.csv",
            "run,load_n,angle_deg,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,deflection_um\n1,125,0,,,,,,,1.0\n",
        );
        let setup = std::fs::read_to_string(root().join("examples/ldbb/setup.toml"))
            .unwrap()
            .replace(
                "../../../shared/robots/abb_irb6700_200_260/robot.urdf",
                shared_robot("abb_irb6700_200_260").to_str().unwrap(),
            );
        f.write("setup.toml", &setup);
        f.write(
            "ldbb_truth.toml",
            &std::fs::read_to_string(root().join("examples/ldbb/truth.toml")).unwrap(),
        );
        f.write("truth.toml", "noise_um = 1.0\n[geometric]\ntheta2 = 0.01\n");
        f
    }

    fn write(&self, name: &str, text: &str) -> String {
        let p = self.fx.join(name);
        std::fs::write(&p, text).unwrap();
        p.display().to_string()
    }

    fn path(&self, name: &str) -> String {
        self.fx.join(name).display().to_string()
    }

    fn out(&self, name: &str) -> String {
        self.out.join(name).display().to_string()
    }
}

struct Case {
    name: &'static str,
    args: Vec<String>,
    /// What the one line must name (a file, a field, a flag).
    needle: String,
}

fn case(name: &'static str, args: &[&str], needle: &str) -> Case {
    Case {
        name,
        args: args.iter().map(|s| s.to_string()).collect(),
        needle: needle.to_string(),
    }
}

fn cases(f: &Fixtures) -> Vec<Case> {
    let nj = nj130_dh().display().to_string();
    let nj = nj.as_str();
    let abb = shared_robot("abb_irb6700_200_260").display().to_string();
    let abb = abb.as_str();
    let prog = f.path("prog.nc");
    let prog = prog.as_str();
    let nc = f.out("out.nc");
    let nc = nc.as_str();
    let fix = "258,1468,708";
    let cal = root().join("tests/cases/compensate/nj130.cal.dh.toml");
    let cal = cal.to_str().unwrap();
    let measured = f.path("measured.csv");
    let measured = measured.as_str();
    let setup = f.path("setup.toml");
    let setup = setup.as_str();
    let loaded = f.path("loaded.csv");
    let loaded = loaded.as_str();
    let w = |name: &str, text: &str| f.write(name, text);

    // Robot files.
    let urdf_bad = w("bad.urdf", "<robot name=\"r\"><link name=\"a\">");
    let urdf_five = w(
        "five.urdf",
        &std::fs::read_to_string(nj130_urdf()).unwrap().replacen(
            "type=\"revolute\"",
            "type=\"fixed\"",
            1,
        ),
    );
    let urdf_mesh = w(
        "mesh.urdf",
        &std::fs::read_to_string(nj130_urdf()).unwrap().replacen(
            "<link name=\"base_link\">",
            "<link name=\"base_link\"><collision><geometry><mesh filename=\"missing_part.stl\"/></geometry></collision>",
            1,
        ),
    );
    let dh_syntax = w("syntax.dh.toml", "name = \"r\"\n[[joint]\na = 1\n");
    let dh_text = std::fs::read_to_string(nj130_dh()).unwrap();
    let dh_value = w(
        "value.dh.toml",
        &dh_text.replacen("a = ", "a = \"wide\" #", 1),
    );
    let robot_ext = w("robot.xyz", "whatever");
    // Cells and meshes.
    let cell_syntax = w("syntax_cell.toml", "[fixture\nposition_mm = [1, 2, 3]\n");
    let cell_mesh = w(
        "mesh_cell.toml",
        "[[environment]]\nname = \"table\"\ntype = \"mesh\"\nfile = \"no_such_mesh.stl\"\n",
    );
    let stl = w(
        "broken.stl",
        "solid x\nfacet normal 0 0 1\nouter loop\nvertex 1 2\n",
    );
    let cell_stl = w(
        "stl_cell.toml",
        &format!("[[environment]]\nname = \"table\"\ntype = \"mesh\"\nfile = \"{stl}\"\n"),
    );
    let obj = w("broken.obj", "v 1 2 3\nv 4 5 6\nf 1 2 9\n");
    let cell_obj = w(
        "obj_cell.toml",
        &format!("[[environment]]\nname = \"table\"\ntype = \"mesh\"\nfile = \"{obj}\"\n"),
    );
    let cell_sign = w(
        "sign_cell.toml",
        "[controller]\nsign = [1, 2, 1, 1, 1, 1]\n",
    );
    let cell_margin = w("margin_cell.toml", "[safety]\njoint_margin = -3\n");
    // Templates.
    let tpl_missing = f.path("no_template.j2");
    let tpl_plain = w("plain.j2", "G21\n{% for m in moves %}G1{% endfor %}\n");
    let tpl_syntax = w("syntax.j2", "{% extends \"ngc\" %}{% block body %}{{ x \n");
    // Programs (verify, simulate).
    let prog_empty = w("empty.nc", "");
    let prog_word = w("word.nc", "G21 G90\nG1 X1 Y2 Z3 A4 B5 Q6 F10\n");
    let prog_fanuc = w(
        "LONG.LS",
        "/PROG  LONG\n/MN\n   1:  MESSAGE[this message is much longer than twenty-four] ;\n/POS\n/END\n",
    );
    let prog_rapid = w(
        "long.mod",
        "MODULE long\n  PROC main()\n    TPWrite \"1234567890123456789012345678901234567890123456789012345678901234567890123456789012345\";\n  ENDPROC\nENDMODULE\n",
    );
    let prog_krl = w("broken.src", "DEF broken( )\nPTP {A1 1, A2 2, A3\nEND\n");
    let prog_ur = w("broken.script", "def p():\n  movej([1, 2, 3], t=1)\nend\n");
    let prog_sin = w(
        "BROKEN.MPF",
        "G71 G90\nG1 X1=1 Y1=2 Z1=3 A1=4 B1=5 C1=6 F=abc\nM30\n",
    );
    // Measured data.
    let csv_header = w("header.csv", "time,q1,q2\n0,0,0\n");
    let csv_text = w(
        "text.csv",
        "t_s,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,length_mm\n0,0,0,zero,0,0,0,400\n",
    );
    let csv_nan = w(
        "nan.csv",
        "t_s,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,length_mm\n0,0,0,0,0,0,0,NaN\n",
    );
    let csv_empty = w("empty.csv", "");
    // Truths.
    let truth_syntax = w("syntax_truth.toml", "noise_um = \n");
    let truth_key = w("key_truth.toml", "[geometric]\ntheta9 = 0.01\n");
    // LDBB.
    let loaded_header = w("loaded_header.csv", "run,load,angle\n1,125,0\n");
    let loaded_text = w(
        "loaded_text.csv",
        "run,load_n,angle_deg,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,deflection_um\n1,heavy,0,,,,,,,1.0\n",
    );
    let reference = w("lt.csv", "angle_deg,error_um\n0,abc\n");
    let setup_syntax = w("syntax_setup.toml", "[circle\ncentre_mm = [0, 0, 0]\n");
    let setup_circle = w(
        "circle_setup.toml",
        &std::fs::read_to_string(setup)
            .unwrap()
            .replace("diameter_mm = 250.0", "diameter_mm = -250.0"),
    );
    let ldbb_truth_bad = w("bad_ldbb_truth.toml", "stiffness_nm_per_rad = [1, 2]\n");

    let o = |name: &str| f.out(name);
    vec![
        // ---- compile: the robot file
        case(
            "robot missing",
            &["/nonexistent/robot.urdf", "--fixture", fix, "-o", nc],
            "/nonexistent/robot.urdf",
        ),
        case(
            "robot extension",
            &[&robot_ext, "--fixture", fix, "-o", nc],
            "robot.xyz",
        ),
        case(
            "urdf malformed",
            &[&urdf_bad, "--fixture", fix, "-o", nc],
            "bad.urdf",
        ),
        case(
            "urdf five joints",
            &[&urdf_five, "--fixture", fix, "-o", nc],
            "five.urdf",
        ),
        case(
            "urdf mesh missing",
            &[&urdf_mesh, "--fixture", fix, "-o", nc],
            "missing_part.stl",
        ),
        case(
            "dh syntax",
            &[&dh_syntax, "--fixture", fix, "-o", nc],
            "syntax.dh.toml",
        ),
        case(
            "dh value",
            &[&dh_value, "--fixture", fix, "-o", nc],
            "value.dh.toml",
        ),
        case(
            "urdf flange unknown",
            &[
                abb,
                "--flange",
                "no_such_link",
                "--fixture",
                "1350,-125,1250",
                "-o",
                nc,
            ],
            "no_such_link",
        ),
        // ---- compile: flags
        case(
            "fixture text",
            &[nj, "--fixture", "a,b,c", "-o", nc],
            "--fixture",
        ),
        case(
            "fixture nan",
            &[nj, "--fixture", "nan,1,2", "-o", nc],
            "--fixture",
        ),
        case(
            "fixture two",
            &[nj, "--fixture", "1,2", "-o", nc],
            "--fixture",
        ),
        case(
            "fixture out of reach",
            &[nj, "--fixture", "90000,0,0", "-o", nc],
            "fixture",
        ),
        case(
            "tool text",
            &[nj, "--fixture", fix, "--tool", "x", "-o", nc],
            "--tool",
        ),
        case(
            "bar reversed",
            &[nj, "--fixture", fix, "--bar", "520..300", "-o", nc],
            "--bar",
        ),
        case(
            "bar text",
            &[nj, "--fixture", fix, "--bar", "short", "-o", nc],
            "--bar",
        ),
        case(
            "ball negative",
            &[nj, "--fixture", fix, "--ball", "-5", "-o", nc],
            "--ball",
        ),
        case(
            "floor text",
            &[nj, "--fixture", fix, "--floor", "low", "-o", nc],
            "--floor",
        ),
        case(
            "margin negative",
            &[nj, "--fixture", fix, "--margin", "-1", "-o", nc],
            "--margin",
        ),
        case(
            "joint margin large",
            &[nj, "--fixture", fix, "--joint-margin", "50", "-o", nc],
            "--joint-margin",
        ),
        case(
            "blend large",
            &[nj, "--fixture", fix, "--blend", "500", "-o", nc],
            "--blend",
        ),
        case(
            "step zero",
            &[nj, "--fixture", fix, "--step", "0", "-o", nc],
            "--step",
        ),
        case(
            "step grid too large",
            &[nj, "--fixture", fix, "--step", "0.1", "-o", nc],
            "--step",
        ),
        case(
            "step five values",
            &[nj, "--fixture", fix, "--step", "5,5,5,5,5", "-o", nc],
            "--step",
        ),
        case(
            "max candidates small",
            &[nj, "--fixture", fix, "--max-candidates", "5", "-o", nc],
            "--max-candidates",
        ),
        case(
            "poses too few",
            &[nj, "--fixture", fix, "--poses", "3", "-o", nc],
            "poses",
        ),
        case(
            "start short",
            &[nj, "--fixture", fix, "--start", "1,2", "-o", nc],
            "--start",
        ),
        case(
            "seed text",
            &[nj, "--fixture", fix, "--seed", "many", "-o", nc],
            "--seed",
        ),
        case(
            "bar noise negative",
            &[nj, "--fixture", fix, "--bar-noise", "-1", "-o", nc],
            "--bar-noise",
        ),
        case(
            "bar rate zero",
            &[nj, "--fixture", fix, "--bar-rate", "0", "-o", nc],
            "--bar-rate",
        ),
        case(
            "dialect unknown",
            &[nj, "--fixture", fix, "--dialect", "gcode9", "-o", nc],
            "--dialect",
        ),
        case(
            "emit unknown",
            &[nj, "--fixture", fix, "--emit", "everything", "-o", nc],
            "--emit",
        ),
        case(
            "krl name",
            &[
                nj,
                "--fixture",
                fix,
                "--dialect",
                "krl",
                "-o",
                &o("1 bad name.src"),
            ],
            "-o",
        ),
        case(
            "output dir missing",
            &[nj, "--fixture", fix, "-o", &o("no/such/dir/p.nc")],
            "p.nc",
        ),
        case(
            "unknown flag",
            &[nj, "--fixture", fix, "--fixtrue", "1", "-o", nc],
            "--fixtrue",
        ),
        // ---- compile: templates
        case(
            "template missing",
            &[nj, "--fixture", fix, "--template", &tpl_missing, "-o", nc],
            "no_template.j2",
        ),
        case(
            "template without dialect",
            &[nj, "--fixture", fix, "--template", &tpl_plain, "-o", nc],
            "plain.j2",
        ),
        case(
            "template syntax",
            &[nj, "--fixture", fix, "--template", &tpl_syntax, "-o", nc],
            "syntax.j2",
        ),
        // ---- compile: cells and meshes
        case(
            "cell syntax",
            &[nj, "--cell", &cell_syntax, "-o", nc],
            "syntax_cell.toml",
        ),
        case(
            "cell mesh missing",
            &[nj, "--fixture", fix, "--cell", &cell_mesh, "-o", nc],
            "no_such_mesh.stl",
        ),
        case(
            "stl broken",
            &[nj, "--fixture", fix, "--cell", &cell_stl, "-o", nc],
            "broken.stl",
        ),
        case(
            "obj broken",
            &[nj, "--fixture", fix, "--cell", &cell_obj, "-o", nc],
            "broken.obj",
        ),
        case(
            "cell controller sign",
            &[nj, "--fixture", fix, "--cell", &cell_sign, "-o", nc],
            "sign",
        ),
        case(
            "cell joint margin",
            &[nj, "--fixture", fix, "--cell", &cell_margin, "-o", nc],
            "joint_margin",
        ),
        // ---- verify
        case(
            "verify program missing",
            &["verify", nj, &f.path("none.nc")],
            "none.nc",
        ),
        case(
            "verify program empty",
            &["verify", nj, &prog_empty],
            "empty.nc",
        ),
        case("verify ngc word", &["verify", nj, &prog_word], "word.nc"),
        case(
            "verify fanuc message",
            &["verify", nj, &prog_fanuc],
            "LONG.LS",
        ),
        case(
            "verify rapid tpwrite",
            &["verify", nj, &prog_rapid],
            "long.mod",
        ),
        case("verify krl ptp", &["verify", nj, &prog_krl], "broken.src"),
        case(
            "verify urscript movej",
            &["verify", nj, &prog_ur],
            "broken.script",
        ),
        case(
            "verify sinumerik feed",
            &["verify", nj, &prog_sin],
            "BROKEN.MPF",
        ),
        case(
            "verify dialect unknown",
            &["verify", nj, prog, "--dialect", "basic"],
            "--dialect",
        ),
        case(
            "verify robot dh",
            &["verify", &dh_syntax, prog],
            "syntax.dh.toml",
        ),
        // ---- model
        case(
            "model samples zero",
            &["model", nj, "--fixture", fix, "--samples", "0"],
            "--samples",
        ),
        case(
            "model robot",
            &["model", &urdf_bad, "--fixture", fix],
            "bad.urdf",
        ),
        // ---- simulate
        case(
            "simulate truth syntax",
            &[
                "simulate",
                nj,
                prog,
                "--truth",
                &truth_syntax,
                "-o",
                &o("m.csv"),
            ],
            "syntax_truth.toml",
        ),
        case(
            "simulate truth key",
            &[
                "simulate",
                nj,
                prog,
                "--truth",
                &truth_key,
                "-o",
                &o("m.csv"),
            ],
            "theta9",
        ),
        case(
            "simulate rate",
            &[
                "simulate",
                nj,
                prog,
                "--truth",
                &f.path("truth.toml"),
                "--bar-rate",
                "0",
                "-o",
                &o("m.csv"),
            ],
            "--bar-rate",
        ),
        case(
            "simulate program",
            &[
                "simulate",
                nj,
                &prog_word,
                "--truth",
                &f.path("truth.toml"),
                "-o",
                &o("m.csv"),
            ],
            "word.nc",
        ),
        // ---- diagnose
        case(
            "diagnose header",
            &["diagnose", nj, "--fixture", fix, "--measured", &csv_header],
            "header.csv",
        ),
        case(
            "diagnose text",
            &["diagnose", nj, "--fixture", fix, "--measured", &csv_text],
            "text.csv",
        ),
        case(
            "diagnose nan",
            &["diagnose", nj, "--fixture", fix, "--measured", &csv_nan],
            "nan.csv",
        ),
        case(
            "diagnose empty",
            &["diagnose", nj, "--fixture", fix, "--measured", &csv_empty],
            "empty.csv",
        ),
        case(
            "diagnose fixture",
            &[
                "diagnose",
                nj,
                "--fixture",
                "1,2",
                "--measured",
                measured,
                "--json",
                &o("r.json"),
            ],
            "--fixture",
        ),
        // ---- circle
        case(
            "circle diameter",
            &[
                "circle",
                nj,
                "--fixture",
                fix,
                "--diameter",
                "-5",
                "-o",
                &o("c.nc"),
            ],
            "--diameter",
        ),
        case(
            "circle speed",
            &[
                "circle",
                nj,
                "--fixture",
                fix,
                "--speed",
                "0",
                "-o",
                &o("c.nc"),
            ],
            "--speed",
        ),
        // ---- calibrate
        case(
            "calibrate prior",
            &[
                "calibrate",
                nj,
                "--measured",
                measured,
                "--fixture",
                fix,
                "--prior",
                "big",
                "-o",
                &o("c.dh.toml"),
            ],
            "--prior",
        ),
        case(
            "calibrate effects",
            &[
                "calibrate",
                nj,
                "--measured",
                measured,
                "--fixture",
                fix,
                "--effects",
                "gremlins",
                "-o",
                &o("c.dh.toml"),
            ],
            "--effects",
        ),
        case(
            "calibrate pairs",
            &[
                "calibrate",
                nj,
                "--measured",
                measured,
                "--measured",
                measured,
                "--measured",
                measured,
                "--fixture",
                fix,
                "--fixture",
                fix,
                "-o",
                &o("c.dh.toml"),
            ],
            "--fixture",
        ),
        case(
            "calibrate output dir",
            &[
                "calibrate",
                nj,
                "--measured",
                measured,
                "--fixture",
                fix,
                "-o",
                &o("none/c.dh.toml"),
            ],
            "c.dh.toml",
        ),
        case(
            "calibrate output kind",
            &[
                "calibrate",
                nj,
                "--measured",
                measured,
                "--fixture",
                fix,
                "-o",
                &o("c.txt"),
            ],
            "c.txt",
        ),
        case(
            "calibrate csv",
            &[
                "calibrate",
                nj,
                "--measured",
                &csv_text,
                "--fixture",
                fix,
                "-o",
                &o("c.dh.toml"),
            ],
            "text.csv",
        ),
        case(
            "calibrate baseline",
            &[
                "calibrate",
                nj,
                "--measured",
                measured,
                "--fixture",
                fix,
                "--baseline",
                &w("baseline.json", "{\"schema\": \"edbbgen.diagnose/1\"}"),
                "-o",
                &o("c.dh.toml"),
            ],
            "baseline.json",
        ),
        case(
            "calibrate bar log of a program without a dwell",
            &[
                "calibrate",
                nj,
                "--bar-log",
                &w(
                    "bar.csv",
                    &(0..50).fold("t_s,length_mm\n".to_string(), |t, k| {
                        t + &format!("{:.2},400.0000\n", 0.02 * k as f64)
                    }),
                ),
                "--program",
                &f.path("prog.nc"),
                "--fixture",
                fix,
                "-o",
                &o("c.dh.toml"),
            ],
            "prog.nc: the program has no dwell (G4 P seconds)",
        ),
        // ---- compensate
        case(
            "compensate targets",
            &[
                "compensate",
                cal,
                "--nominal",
                nj,
                "--targets",
                &w("targets.csv", "q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg\n1,2,3,4,x,6\n"),
                "-o",
                &o("t.csv"),
            ],
            "targets.csv: line 2: column q5_deg",
        ),
        case(
            "compensate no output",
            &["compensate", cal, "--nominal", nj, "--targets", &f.path("targets.csv")],
            "-o",
        ),
        case(
            "compensate two inputs",
            &[
                "compensate",
                cal,
                "--nominal",
                nj,
                "--targets",
                &f.path("targets.csv"),
                "--program",
                prog,
                "-o",
                &o("t.csv"),
            ],
            "--program",
        ),
        case(
            "compensate tcp",
            &[
                "compensate",
                cal,
                "--nominal",
                nj,
                "--tcp",
                "1,2",
                "--json",
                &o("r.json"),
            ],
            "--tcp",
        ),
        case(
            "compensate dialect",
            &["compensate", cal, "--nominal", nj, "--dialect", "cobol"],
            "cobol",
        ),
        case(
            "compensate calibration",
            &[
                "compensate",
                cal,
                "--nominal",
                nj,
                "--calibration",
                &w("cal_report.json", "{not json"),
                "--json",
                &o("r.json"),
            ],
            "cal_report.json",
        ),
        case(
            "compensate not a calibration of it",
            &["compensate", abb, "--nominal", nj, "--json", &o("r.json")],
            "robot.urdf",
        ),
        case(
            "compensate incremental program",
            &[
                "compensate",
                cal,
                "--nominal",
                nj,
                "--program",
                &w("inc.nc", "G21 G90\nG0 X0 Y0 Z0 A0 B30 C0\nG91\nG0 X1\nM2\n"),
                "-o",
                &o("inc.nc"),
            ],
            "line 3: G91",
        ),
        case(
            "compile focus",
            &[nj, "--fixture", fix, "--focus", "theta7", "-o", nc],
            "--focus: 'theta7'",
        ),
        // ---- ldbb
        case(
            "ldbb header",
            &["ldbb", &loaded_header, "--setup", setup],
            "loaded_header.csv",
        ),
        case(
            "ldbb text",
            &["ldbb", &loaded_text, "--setup", setup],
            "loaded_text.csv",
        ),
        case(
            "ldbb setup syntax",
            &["ldbb", loaded, "--setup", &setup_syntax],
            "syntax_setup.toml",
        ),
        case(
            "ldbb setup circle",
            &["ldbb", loaded, "--setup", &setup_circle],
            "circle_setup.toml",
        ),
        case(
            "ldbb grid step",
            &["ldbb", loaded, "--setup", setup, "--grid-step", "7"],
            "--grid-step",
        ),
        case(
            "ldbb sine",
            &["ldbb", loaded, "--setup", setup, "--sine", "cubic"],
            "--sine",
        ),
        case(
            "ldbb reference",
            &[
                "ldbb",
                loaded,
                "--setup",
                setup,
                "--reference",
                &reference,
                "--json",
                &o("l.json"),
            ],
            "lt.csv",
        ),
        // ---- ldbb-circle
        case(
            "ldbb-circle step",
            &[
                "ldbb-circle",
                abb,
                "--setup",
                setup,
                "--step",
                "20",
                "-o",
                &o("l.nc"),
            ],
            "--step",
        ),
        case(
            "ldbb-circle dialect",
            &[
                "ldbb-circle",
                abb,
                "--setup",
                setup,
                "--dialect",
                "cobol",
                "-o",
                &o("l.nc"),
            ],
            "--dialect",
        ),
        case(
            "ldbb-circle robot",
            &["ldbb-circle", &urdf_bad, "--setup", setup, "-o", &o("l.nc")],
            "bad.urdf",
        ),
        // ---- simulate-ldbb
        case(
            "simulate-ldbb truth",
            &[
                "simulate-ldbb",
                "--setup",
                setup,
                "--truth",
                &ldbb_truth_bad,
                "-o",
                &o("l.csv"),
            ],
            "bad_ldbb_truth.toml",
        ),
        case(
            "simulate-ldbb setup",
            &[
                "simulate-ldbb",
                "--setup",
                &setup_syntax,
                "--truth",
                &f.path("ldbb_truth.toml"),
                "-o",
                &o("l.csv"),
            ],
            "syntax_setup.toml",
        ),
        // ---- place
        case(
            "place region out of reach",
            &[
                "place",
                nj,
                "--region",
                "9000..10000,0..500,0..500",
                "--grid",
                "2,2,2",
                "--json",
                &o("p.json"),
            ],
            "--region",
        ),
        case(
            "place cell without room",
            &[
                "place",
                nj,
                "--cell",
                &f.write(
                    "crowded.toml",
                    "[[environment]]\nname = \"slab\"\ntype = \"box\"\nsize = [6000.0, 12000.0, 4000.0]\norigin = [2950.0, 0.0, 2000.0]\n",
                ),
                "--grid",
                "3,3,2",
                "--json",
                &o("p.json"),
            ],
            "crowded.toml",
        ),
        case(
            "place grid",
            &["place", nj, "--grid", "0,2,2", "--json", &o("p.json")],
            "--grid",
        ),
        case(
            "place count",
            &["place", nj, "--count", "11", "--json", &o("p.json")],
            "--count",
        ),
        // ---- dialects, completions
        case("dialects flag", &["dialects", "--yaml"], "--yaml"),
        case("completions shell", &["completions", "cmd.exe"], "cmd.exe"),
    ]
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn every_bad_input_exits_2_with_one_line_naming_it_and_writes_nothing() {
    let dir = tempdir();
    let f = Fixtures::new(dir.path());
    let all = cases(&f);
    assert!(all.len() >= 60, "{} cases", all.len());
    let mut failures = Vec::new();
    for c in &all {
        let r = edbbgen(&c.args);
        let lines: Vec<&str> = r.stderr.lines().collect();
        let written: Vec<String> = std::fs::read_dir(&f.out)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        let ok = r.code == 2
            && lines.len() == 1
            && lines[0].starts_with("edbbgen: ")
            && lines[0].contains(&c.needle)
            && !r.stderr.contains("panicked")
            && written.is_empty();
        if !ok {
            failures.push(format!(
                "{}: exit {}, stderr {:?}, wanted '{}', wrote {written:?}",
                c.name, r.code, r.stderr, c.needle
            ));
        }
        for name in written {
            let _ = std::fs::remove_file(f.out.join(name));
        }
    }
    assert!(
        failures.is_empty(),
        "{} of {} cases fail:\n{}",
        failures.len(),
        all.len(),
        failures.join("\n")
    );
}
