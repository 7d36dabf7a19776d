//! Mastering offsets: in = the calibrated joint zero offsets (the θ deviations), the controller
//! mapping and family; out = the change of every controller axis's zero (with its uncertainty),
//! written the way the controller family keeps it, and the accuracy the offsets alone give,
//! against full compensation, over the joint space.
//!
//! **Convention.** The calibration says joint i's link stands Δθᵢ further than the nominal model
//! believes at the same axis reading. Re-mastering fixes that by making the reading at every
//! physical position Δθᵢ larger: then the controller's nominal model and the arm agree on that
//! joint. Every delta here is that change of the reading (model joint Δθᵢ; on the controller's
//! axes c = sign·q + offset, J3 also + k·q2: Δcᵢ = signᵢ·Δθᵢ, Δc₃ += k·Δθ₂).
//!
//! **How the accuracy is predicted.** Over random joint poses within the limits (the same
//! seeded set as the calibration's prediction), the calibrated robot with the offsets only
//! (commanded q, arm at q − Δθ) and with nothing applied is compared with the nominal robot's
//! TCP at q after a best rigid registration (the calibration's convention: the bar never sees
//! the base frame). That is what the model says remains; the calibration's own predicted
//! uncertainty is added in quadrature (RMS² adds; p95 combined the same way, an approximation).
//! Full compensation leaves the calibration's uncertainty alone (its inverse kinematics residual
//! is below 0.001 µm).

use super::Compensator;
use crate::calibrate::predict::{self, Spread};
use crate::controller::{ControllerMap, Units};
use crate::robot::Robot;
use crate::units::{fmt_fixed, DEG, MM};
use nalgebra::Vector3;
use serde::Serialize;

/// Two DH tables describe the same chain joint by joint when no α differs by more than this
/// (rad) ...
const SAME_ALPHA: f64 = 1.0 * DEG;
/// ... and no a or d by more than this (m): then θ deviations are joint zero offsets.
const SAME_LENGTH: f64 = 10.0 * MM;

/// Where the joint zero offsets came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Source {
    /// `theta1..theta6` of the calibration report, with their standard uncertainties.
    CalibrationReport,
    /// The θ difference of the calibrated and the nominal robot file (no uncertainty).
    RobotFiles,
}

/// The joint zero offsets (model joints, rad) and their standard uncertainties.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct JointOffsets {
    pub delta: [f64; 6],
    pub std: [Option<f64>; 6],
    /// Which offsets the calibration determined (held ones are 0 ± their prior).
    pub determined: [bool; 6],
    pub source: Source,
}

/// The offsets from the θ difference of two robot files, when their DH tables describe the
/// same chain joint by joint (same base and flange transforms, α, a, d close): a calibrated
/// `.dh.toml` always; a calibrated URDF as long as its conversion kept the nominal's frames.
pub fn from_tables(nominal: &Robot, calibrated: &Robot) -> Result<JointOffsets, String> {
    let close = |a: &crate::robot::Frame, b: &crate::robot::Frame| {
        (a.r - b.r).norm() < 1e-6 && (a.t - b.t).norm() < SAME_LENGTH
    };
    if !close(&nominal.base, &calibrated.base) || !close(&nominal.flange, &calibrated.flange) {
        return Err("the two robot files place the chain differently (base or flange transform): their θ are not comparable".into());
    }
    for (i, (n, c)) in nominal.dh.iter().zip(&calibrated.dh).enumerate() {
        if (n.alpha - c.alpha).abs() > SAME_ALPHA
            || (n.a - c.a).abs() > SAME_LENGTH
            || (n.d - c.d).abs() > SAME_LENGTH
        {
            return Err(format!(
                "joint {}: the DH tables differ by more than a calibration (alpha {} / {} deg, a {} / {} mm, d {} / {} mm): their θ are not comparable",
                i + 1,
                fmt_fixed(n.alpha / DEG, 3),
                fmt_fixed(c.alpha / DEG, 3),
                fmt_fixed(n.a / MM, 3),
                fmt_fixed(c.a / MM, 3),
                fmt_fixed(n.d / MM, 3),
                fmt_fixed(c.d / MM, 3)
            ));
        }
    }
    let delta: [f64; 6] = std::array::from_fn(|i| {
        let d = calibrated.dh[i].theta - nominal.dh[i].theta;
        // The shortest way round: a table may write 180° where the other writes −180°.
        d - std::f64::consts::TAU * (d / std::f64::consts::TAU).round()
    });
    Ok(JointOffsets {
        delta,
        std: [None; 6],
        determined: delta.map(|d| d != 0.0),
        source: Source::RobotFiles,
    })
}

/// The offsets from a calibration report (`edbbgen.calibrate/1`): `params.thetaN` (`value`,
/// `std`, degrees); a joint zero the calibration did not determine is 0 (held at nominal).
pub fn from_report(report: &serde_json::Value) -> Result<JointOffsets, String> {
    if report.get("schema").and_then(|s| s.as_str()) != Some("edbbgen.calibrate/1") {
        return Err("not a calibration report (schema edbbgen.calibrate/1)".into());
    }
    let params = report
        .get("params")
        .and_then(|p| p.as_object())
        .ok_or("the report has no params")?;
    let mut out = JointOffsets {
        delta: [0.0; 6],
        std: [None; 6],
        determined: [false; 6],
        source: Source::CalibrationReport,
    };
    for i in 0..6 {
        let name = format!("theta{}", i + 1);
        if let Some(p) = params.get(&name) {
            let v = p
                .get("value")
                .and_then(|v| v.as_f64())
                .ok_or(format!("params.{name}.value is not a number"))?;
            out.delta[i] = v * DEG;
            out.std[i] = p.get("std").and_then(|v| v.as_f64()).map(|s| s * DEG);
            out.determined[i] = true;
        }
    }
    Ok(out)
}

/// One controller axis's mastering change.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct AxisDelta {
    pub axis: String,
    /// The model joint's zero offset Δθ (deg) and its standard uncertainty.
    pub joint_delta_deg: f64,
    pub joint_std_deg: Option<f64>,
    /// The change of the axis's reading, in the program's units (deg or rad), and its std.
    pub delta: f64,
    pub std: Option<f64>,
    pub units: &'static str,
    /// FANUC: the change of the master count (`[controller] pulses_per_deg` given).
    pub master_count_delta: Option<i64>,
}

/// The mastering changes of the six controller axes, in the controller family's terms.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Mastering {
    pub source: Source,
    /// The dialect naming the controller family; None = the model joints themselves.
    pub family: Option<String>,
    pub controller: String,
    pub axes: Vec<AxisDelta>,
    /// What the deltas mean, and where the family keeps its zeros.
    pub convention: String,
    pub instructions: Vec<String>,
}

/// Model joint deltas → controller axis deltas (the linear part of the mapping), with their
/// uncertainties (J3 = q3 + k·q2 adds joint 2's).
pub fn mastering(
    offsets: &JointOffsets,
    map: &ControllerMap,
    family: Option<&str>,
    pulses_per_deg: Option<&[f64; 6]>,
) -> Mastering {
    let to_units = |deg: f64| match map.units {
        Units::Deg => deg,
        Units::Rad => deg * DEG,
    };
    let d: [f64; 6] = offsets.delta.map(|r| r / DEG);
    let s: [Option<f64>; 6] = offsets.std.map(|o| o.map(|r| r / DEG));
    let axes = (0..6)
        .map(|i| {
            let mut c = map.sign[i] * d[i];
            let mut var = s[i].map(|v| v * v);
            if i == 2 {
                c += map.j3_coupling * d[1];
                var = match (var, s[1]) {
                    (Some(a), Some(b)) => Some(a + (map.j3_coupling * b).powi(2)),
                    (a, _) => a,
                };
            }
            AxisDelta {
                axis: map.axis_names[i].clone(),
                joint_delta_deg: d[i],
                joint_std_deg: s[i],
                delta: to_units(c),
                std: var.map(|v| to_units(v.sqrt())),
                units: map.units.name(),
                master_count_delta: pulses_per_deg.map(|p| -(c * p[i]).round() as i64),
            }
        })
        .collect::<Vec<_>>();
    let convention = "delta = how much the axis's reading at a fixed physical position must grow so that the controller's nominal model and the arm agree (the calibrated joint zero offset on that axis); apply it to the controller's zero of that axis".to_string();
    let line = |f: &dyn Fn(&AxisDelta) -> String| -> Vec<String> { axes.iter().map(f).collect() };
    let num = |v: f64| fmt_fixed(v, 6);
    let instructions = match family {
        Some("krl") => line(&|a: &AxisDelta| {
            format!(
                "KUKA $MACHINE.DAT: $MAMES[{}] += {} deg (the axis counter takes $MAMES at the mastering mark)",
                &a.axis[1..],
                num(a.delta)
            )
        }),
        Some("fanuc") => line(&|a: &AxisDelta| {
            match a.master_count_delta {
            Some(n) => format!(
                "FANUC $DMR_GRP[1].$MASTER_COUN[{}] += {n} (position = (encoder - master count) / pulses per deg; {} deg)",
                &a.axis[1..],
                num(a.delta)
            ),
            None => format!(
                "FANUC {}: {} deg; give [controller] pulses_per_deg for the master count change ($DMR_GRP[1].$MASTER_COUN)",
                a.axis,
                num(a.delta)
            ),
        }
        }),
        Some("rapid") => line(&|a: &AxisDelta| {
            format!(
                "ABB {}: {} deg on the arm side; the motor calibration offset (MOC.cfg, motor side, rad) changes by this times the axis's transmission ratio, with the motor's direction",
                a.axis,
                num(a.delta)
            )
        }),
        Some("urscript") => line(&|a: &AxisDelta| {
            format!(
                "Universal Robots {}: calibration.conf [mounting] delta_theta += {} rad (the controller's own kinematic calibration)",
                a.axis,
                fmt_fixed(a.delta, 9)
            )
        }),
        Some("sinumerik") => line(&|a: &AxisDelta| {
            format!(
                "SINUMERIK {}: $MA_REFP_MOVE_DIST_CORR (MD34090, absolute encoder) += {} deg; check the sign on one axis (the offset's sign depends on the encoder's direction)",
                a.axis,
                num(a.delta)
            )
        }),
        Some("ngc") => line(&|a: &AxisDelta| {
            format!(
                "LinuxCNC [JOINT_{}] HOME_OFFSET += {} (the joint's position at its home switch or index pulse)",
                axes.iter().position(|x| x.axis == a.axis).unwrap_or(0),
                num(a.delta)
            )
        }),
        _ => line(&|a: &AxisDelta| format!("{}: zero offset {} {}", a.axis, num(a.delta), a.units)),
    };
    Mastering {
        source: offsets.source,
        family: family.map(str::to_string),
        controller: map.describe(),
        axes,
        convention,
        instructions,
    }
}

/// A spread in µm, for reports.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Um {
    pub rms: f64,
    pub p95: f64,
    pub max: f64,
}

impl From<Spread> for Um {
    fn from(s: Spread) -> Self {
        let r = |v: f64| (v * 1e3).round() / 1e3;
        Um {
            rms: r(s.rms),
            p95: r(s.p95),
            max: r(s.max),
        }
    }
}

/// A predicted RMS and 95th percentile over the joint space (µm).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Predicted {
    pub rms: f64,
    pub p95: f64,
}

/// The accuracy over the joint space (µm, after a best rigid registration; see the module's
/// doc for how).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Accuracy {
    pub poses: usize,
    pub how: String,
    /// The calibrated robot commanded with nominal joints, nothing applied.
    pub uncompensated_um: Um,
    /// The calibrated robot with the mastering offsets only (what the model says remains).
    pub offsets_only_model_um: Um,
    /// The calibration's own predicted uncertainty (`predicted_position_std_um`), when known.
    pub calibration_um: Option<Predicted>,
    /// Predicted: offsets only (model remainder and the calibration's uncertainty in
    /// quadrature), and full compensation (the calibration's uncertainty).
    pub predicted_offsets_only_um: Option<Predicted>,
    pub predicted_full_um: Option<Predicted>,
    /// Per pose, sorted ascending (µm), for the figure: nothing applied, offsets only.
    #[serde(skip)]
    pub sorted_um: (Vec<f64>, Vec<f64>),
}

/// Registered per-point distances (µm) of `reached` against `targets`.
pub fn registered_errors(reached: &[Vector3<f64>], targets: &[Vector3<f64>]) -> Vec<f64> {
    let (_, _, r, t) = predict::register(reached, targets);
    reached
        .iter()
        .zip(targets)
        .map(|(a, b)| (r * a + t - b).norm() * 1e6)
        .collect()
}

/// The accuracy with nothing applied, with the offsets only and (from the calibration's
/// predicted workspace RMS and p95, µm) predicted for offsets only and full compensation.
pub fn accuracy(
    comp: &Compensator,
    offsets: &[f64; 6],
    poses: &[[f64; 6]],
    calibration: Option<(f64, f64)>,
) -> Accuracy {
    let targets: Vec<Vector3<f64>> = poses.iter().map(|q| comp.nominal.pose(q).t).collect();
    // The calibrated robot as its file has it (effects included; a backlash at the centre of
    // its play, the approach of a random pose being unknown).
    let plain: Vec<Vector3<f64>> = poses.iter().map(|q| comp.reached(q, &[0.0; 6]).t).collect();
    let shifted: Vec<Vector3<f64>> = poses
        .iter()
        .map(|q| {
            let c: [f64; 6] = std::array::from_fn(|i| q[i] - offsets[i]);
            comp.reached(&c, &[0.0; 6]).t
        })
        .collect();
    let mut e0 = registered_errors(&plain, &targets);
    let mut e1 = registered_errors(&shifted, &targets);
    let s0 = predict::spread(&e0);
    let s1 = predict::spread(&e1);
    e0.sort_by(f64::total_cmp);
    e1.sort_by(f64::total_cmp);
    let quad = |a: f64, b: f64| ((a.hypot(b)) * 1e3).round() / 1e3;
    Accuracy {
        poses: poses.len(),
        how: format!(
            "{} random joint poses within the limits (seeded); the TCP of the calibrated robot at the commanded joints (nothing applied) or at the commanded joints less the offsets (offsets only) against the nominal robot's, after a best rigid registration; the calibration's predicted uncertainty added in quadrature",
            poses.len()
        ),
        uncompensated_um: s0.into(),
        offsets_only_model_um: s1.into(),
        calibration_um: calibration.map(|(rms, p95)| Predicted { rms, p95 }),
        predicted_offsets_only_um: calibration.map(|(rms, p95)| Predicted {
            rms: quad(s1.rms, rms),
            p95: quad(s1.p95, p95),
        }),
        predicted_full_um: calibration.map(|(rms, p95)| Predicted { rms, p95 }),
        sorted_um: (e0, e1),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map(sign: [f64; 6], k: f64, units: Units) -> ControllerMap {
        ControllerMap {
            sign,
            offset_deg: [10.0, -90.0, 0.0, 0.0, 0.0, 0.0],
            j3_coupling: k,
            units,
            axis_names: ["J1", "J2", "J3", "J4", "J5", "J6"].map(str::to_string),
        }
    }

    #[test]
    fn axis_deltas_follow_sign_coupling_and_units() {
        let off = JointOffsets {
            delta: [0.01, 0.02, -0.03, 0.0, 0.005, 0.0].map(|d| d * DEG),
            std: [
                Some(0.001 * DEG),
                Some(0.002 * DEG),
                Some(0.001 * DEG),
                None,
                None,
                None,
            ],
            determined: [true, true, true, false, true, false],
            source: Source::CalibrationReport,
        };
        let m = mastering(
            &off,
            &map([1.0, -1.0, 1.0, 1.0, 1.0, 1.0], -1.0, Units::Deg),
            Some("fanuc"),
            Some(&[1000.0; 6]),
        );
        // Independent: the mapping applied to a pose and to the pose moved by the offsets.
        let q = [12.0, 30.0, -20.0, 5.0, 40.0, 60.0];
        let mp = map([1.0, -1.0, 1.0, 1.0, 1.0, 1.0], -1.0, Units::Deg);
        let moved: [f64; 6] = std::array::from_fn(|i| q[i] + off.delta[i] / DEG);
        let (a, b) = (mp.apply(&q), mp.apply(&moved));
        for i in 0..6 {
            assert!((m.axes[i].delta - (b[i] - a[i])).abs() < 1e-12, "axis {i}");
        }
        // J3 = q3 − q2: its uncertainty takes joint 2's.
        let s3 = m.axes[2].std.unwrap();
        assert!((s3 - (0.001f64.hypot(0.002))).abs() < 1e-12);
        assert_eq!(m.axes[0].master_count_delta, Some(-10));
        assert!(m.instructions[0].contains("$MASTER_COUN[1] += -10"));
        let r = mastering(
            &off,
            &map([1.0; 6], 0.0, Units::Rad),
            Some("urscript"),
            None,
        );
        assert!((r.axes[0].delta - 0.01 * DEG).abs() < 1e-15);
        assert!(r.instructions[0].contains("delta_theta"));
    }
}
