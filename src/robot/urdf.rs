//! URDF loader: in = URDF text (this is the only module that imports urdf-rs); out = [`Robot`]:
//! the root link → flange chain re-expressed as an equivalent standard DH table between two fixed
//! transforms, the joint limits, the collision geometry of the chain's links (in DH frames) and
//! the optional EDBB MAP.
//!
//! The conversion is exact, not fitted: the DH frames are built from the joint axes at q = 0
//! (each axis taken as a line with its sign, so a positive q stays a positive rotation about the
//! DH z axis), and for every q, `FK_urdf(q) = base · Π dh_transform(dh[i], q[i]) · flange`.

use super::kinematics::dh_transform;
use super::{
    Dh, Frame, Geometry, Joint, LinkShape, LoadError, LoadOptions, PassiveLink, PassiveMotion,
    PassiveStep, Robot,
};
use nalgebra::{Matrix3, Vector3};
use std::collections::HashMap;
use std::f64::consts::TAU;
use std::path::{Path, PathBuf};
use urdf_rs::JointType;

/// The link edbbgen reads the EDBB MAP from: a URDF cannot declare one natively, so a link of
/// this name fixed to the flange's link marks the tool ball centre.
const MAP_LINK: &str = "edbb_map";

/// Two axes count as parallel when the sine of their angle is below this. Standard DH cannot
/// hold nearly parallel axes exactly and cheaply: treating them as parallel costs about
/// angle × reach, while their exact common normal lies ~spacing/angle away and the huge d
/// values that puts in the table cost about eps × spacing/angle in rounding. The two meet near
/// sqrt(eps); at this threshold neither exceeds ~3e-8 m on a 2 m arm (measured in
/// `nearly_parallel_axes_stay_close`); exactly parallel or clearly skew axes stay at ~1e-15 m.
const PARALLEL_SIN: f64 = 1.5e-8;

/// Lengths below `LENGTH_TOL × robot size` are zero (intersecting or collinear axes).
const LENGTH_TOL: f64 = 1e-9;

type V3 = Vector3<f64>;

pub fn from_str(text: &str, path: &Path, opts: &LoadOptions) -> Result<Robot, LoadError> {
    convert(text, path, opts).map_err(|msg| LoadError::invalid(path, one_line(&msg)))
}

/// Every message leaves as one line, whatever the XML parser put in it.
fn one_line(s: &str) -> String {
    s.split_whitespace().collect::<Vec<_>>().join(" ")
}

fn convert(text: &str, path: &Path, opts: &LoadOptions) -> Result<Robot, String> {
    // urdf-rs refuses a <limit> without a velocity; such a joint is a speed we do not know
    // (velocity 0), which `Robot::validate` turns into a request for speeds.
    let patched = with_default_velocity(text);
    let doc = urdf_rs::read_from_string(&patched).map_err(|e| format!("not a valid URDF: {e}"))?;
    let lay = layout(&doc, opts)?;
    let Layout {
        tree,
        flange_link,
        pose0,
        group,
        ..
    } = &lay;
    let (dh, frames, base, flange) =
        chain_of(&doc, tree, &lay.revolute, pose0, group, *flange_link, opts)?;
    let flange0 = pose0[*flange_link];
    let joints = joints(&doc, &lay.revolute);
    // Links behind a moving joint off the chain (a balancing cylinder, a parallelogram
    // linkage): each gets the chain of joints from its nearest rigid ancestor, so that its pose
    // is known for every q and its geometry joins the collision scene.
    let Passive {
        links: passive,
        of_link: passive_of,
        notes,
    } = passive_links(&doc, &lay, &frames)?;
    // Collision geometry of every link, in document order, then by frame: links rigid with a
    // DH frame in that frame, passive links in their own.
    let urdf_dir = path.parent().unwrap_or(Path::new(""));
    let shapes = link_shapes(&doc, &lay, &frames, (&passive, &passive_of), urdf_dir, opts)?;
    // Inertials of the same links, as point masses at their centres of mass in DH frames.
    let masses = point_masses(&doc, &lay, &frames)?;

    let tool = match tree.link_of.get(MAP_LINK) {
        None => None,
        Some(&m) if group[m] == Some(6) => Some(flange0.inverse().apply(&pose0[m].t)),
        Some(_) => {
            return Err(format!(
                "link {MAP_LINK} (the EDBB MAP) must be fixed to the flange link {} through fixed joints",
                doc.links[*flange_link].name
            ))
        }
    };

    Ok(Robot {
        name: doc.name.clone(),
        source: path
            .file_name()
            .map(|f| f.to_string_lossy().into_owned())
            .unwrap_or_default(),
        base,
        dh,
        flange,
        joints,
        tool,
        shapes,
        passive,
        notes,
        masses,
        effects: Default::default(),
        digest: String::new(),
    })
}

/// The six chain joints' limits and speeds.
fn joints(doc: &urdf_rs::Robot, revolute: &[usize]) -> [Joint; 6] {
    std::array::from_fn(|k| {
        let joint = &doc.joints[revolute[k]];
        let (lower, upper) = match joint.joint_type {
            JointType::Continuous => (-TAU, TAU),
            _ => (joint.limit.lower, joint.limit.upper),
        };
        let v = joint.limit.velocity;
        Joint {
            name: joint.name.clone(),
            lower,
            upper,
            // Missing, zero or unbounded: left for `Robot::validate` to reject with its message.
            max_speed: if v.is_finite() && v > 0.0 { v } else { 0.0 },
            // URDF states no acceleration: the cell's, else the documented default.
            max_acceleration: 0.0,
        }
    })
}

/// The links behind a moving joint off the chain, the passive link (index) of every link that
/// is one, and the notes on joints nothing drives.
struct Passive {
    links: Vec<PassiveLink>,
    of_link: Vec<Option<usize>>,
    notes: Vec<String>,
}

/// Each such link gets the chain of joints from its nearest rigid ancestor.
fn passive_links(
    doc: &urdf_rs::Robot,
    lay: &Layout,
    frames: &[Frame; 7],
) -> Result<Passive, String> {
    let Layout {
        tree,
        joint_number,
        pose0,
        group,
        ..
    } = lay;
    let n_links = doc.links.len();
    let mut notes = Vec::new();
    let mut passive: Vec<PassiveLink> = Vec::new();
    let mut passive_of: Vec<Option<usize>> = vec![None; n_links];
    let mut drives = Drives::new(doc, joint_number);
    let moving: Vec<usize> = (0..n_links)
        .filter(|&l| group[l].is_none() && !doc.links[l].collision.is_empty())
        .collect();
    for (i, &l) in moving.iter().enumerate() {
        passive_of[l] = Some(i);
    }
    for &l in &moving {
        let link = &doc.links[l];
        // Joints from the rigid ancestor down to l.
        let mut path_joints = Vec::new();
        let mut a = l;
        while group[a].is_none() {
            let j = tree.parent_joint[a].ok_or("unreachable: the root is rigid")?;
            path_joints.push(j);
            a = tree.link_of[doc.joints[j].parent.link.as_str()];
        }
        path_joints.reverse();
        let k = group[a].ok_or("unreachable: a rigid ancestor")?;
        let steps = passive_steps(doc, &path_joints, (&frames[k], &pose0[a]), &mut drives)?;
        // The nearest ancestor with a body of its own.
        let mut parent = None;
        let mut up = tree.link_of[doc.joints[path_joints[path_joints.len() - 1]]
            .parent
            .link
            .as_str()];
        while group[up].is_none() {
            if let Some(pi) = passive_of[up] {
                parent = Some(pi);
                break;
            }
            let j = tree.parent_joint[up].ok_or("unreachable: the root is rigid")?;
            up = tree.link_of[doc.joints[j].parent.link.as_str()];
        }
        passive.push(PassiveLink {
            name: link.name.clone(),
            frame: k,
            parent,
            steps,
        });
    }
    notes.extend(drives.notes);
    Ok(Passive {
        links: passive,
        of_link: passive_of,
        notes,
    })
}

/// The steps from a passive link's rigid ancestor (its DH `frame` and its `pose` at q = 0)
/// through `path_joints` down to the link.
fn passive_steps(
    doc: &urdf_rs::Robot,
    path_joints: &[usize],
    (frame, pose): (&Frame, &Frame),
    drives: &mut Drives,
) -> Result<Vec<PassiveStep>, String> {
    let mut steps = Vec::with_capacity(path_joints.len());
    for (n, &j) in path_joints.iter().enumerate() {
        let joint = &doc.joints[j];
        let mut origin = origin_frame(&joint.origin.xyz, &joint.origin.rpy)
            .ok_or_else(|| format!("joint {}: origin is not finite", joint.name))?;
        if n == 0 {
            origin = frame.inverse().mul(pose).mul(&origin);
        }
        let motion = match joint.joint_type {
            JointType::Fixed => PassiveMotion::Fixed,
            JointType::Revolute | JointType::Continuous => PassiveMotion::Revolute,
            JointType::Prismatic => PassiveMotion::Prismatic,
            ref t => {
                return Err(format!(
                    "joint {} ({}) moves link {} with more than one degree of freedom; edbbgen cannot place it (make it fixed, revolute or prismatic)",
                    joint.name,
                    type_name(t),
                    joint.child.link
                ))
            }
        };
        let axis = V3::from(joint.axis.xyz.0);
        let norm = axis.norm();
        if motion != PassiveMotion::Fixed && !(norm.is_finite() && norm > 1e-12) {
            return Err(format!("joint {}: axis is zero or not finite", joint.name));
        }
        let (source, multiplier, offset) = if motion == PassiveMotion::Fixed {
            (None, 0.0, 0.0)
        } else {
            drives.of(j)?
        };
        steps.push(PassiveStep {
            name: joint.name.clone(),
            origin,
            motion,
            axis: if motion == PassiveMotion::Fixed {
                V3::z()
            } else {
                axis / norm
            },
            joint: source,
            multiplier,
            offset,
        });
    }
    Ok(steps)
}

/// Collision geometry of every link, in document order, then by frame: links rigid with a DH
/// frame in that frame, passive links in their own.
fn link_shapes(
    doc: &urdf_rs::Robot,
    lay: &Layout,
    frames: &[Frame; 7],
    (passive, passive_of): (&[PassiveLink], &[Option<usize>]),
    urdf_dir: &Path,
    opts: &LoadOptions,
) -> Result<Vec<LinkShape>, String> {
    let Layout { pose0, group, .. } = lay;
    let mut shapes = Vec::new();
    for (l, link) in doc.links.iter().enumerate() {
        let (k, to_link, pi) = match (group[l], passive_of[l]) {
            (Some(k), _) => (k, frames[k].inverse().mul(&pose0[l]), None),
            (None, Some(pi)) => (passive[pi].frame, Frame::IDENTITY, Some(pi)),
            (None, None) => continue,
        };
        for c in &link.collision {
            let origin = origin_frame(&c.origin.xyz, &c.origin.rpy)
                .ok_or_else(|| format!("link {}: collision origin is not finite", link.name))?;
            shapes.push(LinkShape {
                frame: k,
                origin: to_link.mul(&origin),
                geometry: geometry(&c.geometry, &link.name, urdf_dir, opts)?,
                passive: pi,
            });
        }
    }
    shapes.sort_by_key(|s| (s.passive.is_some(), s.frame));
    Ok(shapes)
}

/// Inertials of the links rigid with a DH frame, as point masses at their centres of mass in
/// DH frames.
fn point_masses(
    doc: &urdf_rs::Robot,
    lay: &Layout,
    frames: &[Frame; 7],
) -> Result<Vec<super::PointMass>, String> {
    let Layout { pose0, group, .. } = lay;
    let mut masses = Vec::new();
    for (l, link) in doc.links.iter().enumerate() {
        let Some(k) = group[l] else { continue };
        let m = link.inertial.mass.value;
        if !(m.is_finite() && m > 0.0) {
            continue;
        }
        let origin = origin_frame(&link.inertial.origin.xyz, &link.inertial.origin.rpy)
            .ok_or_else(|| format!("link {}: inertial origin is not finite", link.name))?;
        masses.push(super::PointMass {
            frame: k,
            com: frames[k].inverse().mul(&pose0[l]).mul(&origin).t,
            mass: m,
        });
    }
    masses.sort_by_key(|m| m.frame);
    Ok(masses)
}

/// The DH chain of a URDF's six joints: the DH table from the joint axes at q = 0 and the
/// fixed transforms base → DH frame 0 and DH frame 6 → flange.
#[allow(clippy::too_many_arguments)]
fn chain_of(
    doc: &urdf_rs::Robot,
    tree: &Tree,
    revolute: &[usize],
    pose0: &[Frame],
    group: &[Option<usize>],
    flange_link: usize,
    opts: &LoadOptions,
) -> Result<([Dh; 6], [Frame; 7], Frame, Frame), String> {
    // The six joint axes as lines in the root frame at q = 0, signs kept.
    let mut axes = [Line {
        p: V3::zeros(),
        z: V3::z(),
    }; 6];
    for (k, &j) in revolute.iter().enumerate() {
        let joint = &doc.joints[j];
        let a = V3::from(joint.axis.xyz.0);
        let n = a.norm();
        if !(n.is_finite() && n > 1e-12) {
            return Err(format!("joint {}: axis is zero or not finite", joint.name));
        }
        let child = &pose0[tree.link_of[joint.child.link.as_str()]];
        axes[k] = Line {
            p: child.t,
            z: child.r * (a / n),
        };
    }
    let flange0 = pose0[flange_link];
    let size = axes
        .iter()
        .map(|l| l.p.norm())
        .fold(flange0.t.norm(), f64::max)
        .max(1e-3);
    let (dh, frames) = dh_from_axes(&axes, &flange0, size);
    // The robot base frame: the root link's, or a link rigid with it (e.g. ROS-I `base`).
    let base = match &opts.base_link {
        None => frames[0],
        Some(name) => {
            let l = *tree
                .link_of
                .get(name.as_str())
                .ok_or_else(|| format!("base link {name}: no link of that name in the URDF"))?;
            if group[l] != Some(0) {
                return Err(format!(
                    "base link {name}: it moves with the joints; the base must be the root link {} or fixed to it",
                    doc.links[tree.root].name
                ));
            }
            pose0[l].inverse().mul(&frames[0])
        }
    };
    let flange = frames[6].inverse().mul(&flange0);
    Ok((dh, frames, base, flange))
}

/// The DH chain (base transform, DH table, flange transform) a URDF text loads to, without
/// its meshes: what a calibrated URDF's effects are referred to.
pub fn dh_chain(text: &str, opts: &LoadOptions) -> Result<(Frame, [Dh; 6], Frame), String> {
    let patched = with_default_velocity(text);
    let doc = urdf_rs::read_from_string(&patched).map_err(|e| format!("not a valid URDF: {e}"))?;
    let lay = layout(&doc, opts)?;
    let (dh, _, base, flange) = chain_of(
        &doc,
        &lay.tree,
        &lay.revolute,
        &lay.pose0,
        &lay.group,
        lay.flange_link,
        opts,
    )?;
    Ok((base, dh, flange))
}

/// The chain of a URDF: its tree, flange link, the six revolute joints on the root → flange
/// path, every link's pose at q = 0 and the DH frame each link is rigid with (None: it hangs
/// off the chain behind a moving joint).
struct Layout<'a> {
    tree: Tree<'a>,
    flange_link: usize,
    /// The chain's revolute joints (indices into the document's joints), root first.
    revolute: Vec<usize>,
    /// Which revolute joint (0-based) a chain joint is.
    joint_number: HashMap<usize, usize>,
    pose0: Vec<Frame>,
    group: Vec<Option<usize>>,
}

fn layout<'a>(doc: &'a urdf_rs::Robot, opts: &LoadOptions) -> Result<Layout<'a>, String> {
    let tree = Tree::new(doc)?;
    let flange_link = pick_flange(doc, &tree, opts)?;
    let chain = tree.path_from_root(doc, flange_link);
    let chain_name = format!(
        "{} -> {}",
        doc.links[tree.root].name, doc.links[flange_link].name
    );

    // Which revolute joint (0-based) each chain joint is, if it is one.
    let mut revolute: Vec<usize> = Vec::new();
    let mut joint_number: HashMap<usize, usize> = HashMap::new();
    for &j in &chain {
        let joint = &doc.joints[j];
        match joint.joint_type {
            JointType::Fixed => {}
            JointType::Revolute | JointType::Continuous => {
                if joint.mimic.is_some() {
                    return Err(format!(
                        "joint {} on the chain {chain_name} is a mimic joint; edbbgen needs 6 independent revolute joints",
                        joint.name
                    ));
                }
                joint_number.insert(j, revolute.len());
                revolute.push(j);
            }
            ref t => {
                return Err(format!(
                    "joint {} on the chain {chain_name} is {}; edbbgen supports only revolute and fixed joints on the chain",
                    joint.name,
                    type_name(t)
                ))
            }
        }
    }
    if revolute.len() != 6 {
        let names: Vec<&str> = revolute
            .iter()
            .map(|&j| doc.joints[j].name.as_str())
            .collect();
        return Err(format!(
            "chain {chain_name} has {} revolute joints ({}); edbbgen needs exactly 6",
            revolute.len(),
            names.join(", ")
        ));
    }

    // Link poses in the root frame at q = 0, and the DH frame each link is rigid with
    // (None: it hangs off the chain through a moving joint, e.g. a passive mimic cylinder).
    let n_links = doc.links.len();
    let mut pose0 = vec![Frame::IDENTITY; n_links];
    let mut group: Vec<Option<usize>> = vec![None; n_links];
    group[tree.root] = Some(0);
    for &j in &tree.order {
        let joint = &doc.joints[j];
        let (p, c) = (
            tree.link_of[joint.parent.link.as_str()],
            tree.link_of[joint.child.link.as_str()],
        );
        let origin = origin_frame(&joint.origin.xyz, &joint.origin.rpy)
            .ok_or_else(|| format!("joint {}: origin is not finite", joint.name))?;
        pose0[c] = pose0[p].mul(&origin);
        group[c] = match (joint_number.get(&j), &joint.joint_type) {
            (Some(&k), _) => Some(k + 1),
            (None, JointType::Fixed) => group[p],
            _ => None,
        };
    }

    Ok(Layout {
        tree,
        flange_link,
        revolute,
        joint_number,
        pose0,
        group,
    })
}

/// What drives each joint off the chain: a chain joint through a (possibly nested) mimic, or
/// nothing (held at a value, with a note).
struct Drives<'a> {
    doc: &'a urdf_rs::Robot,
    chain: &'a HashMap<usize, usize>,
    by_name: HashMap<&'a str, usize>,
    notes: Vec<String>,
}

impl<'a> Drives<'a> {
    fn new(doc: &'a urdf_rs::Robot, chain: &'a HashMap<usize, usize>) -> Self {
        let by_name = doc
            .joints
            .iter()
            .enumerate()
            .map(|(j, joint)| (joint.name.as_str(), j))
            .collect();
        Drives {
            doc,
            chain,
            by_name,
            notes: Vec::new(),
        }
    }

    /// (chain joint, multiplier, offset) with value = multiplier · q[joint] + offset, following
    /// mimic tags through any number of levels. Cycles and unknown names are errors. A joint
    /// that is neither on the chain nor a mimic is held at 0 (or its nearest limit) and noted.
    fn of(&mut self, j: usize) -> Result<(Option<usize>, f64, f64), String> {
        let mut seen = vec![j];
        let (mut mult, mut off) = (1.0, 0.0);
        let mut cur = j;
        loop {
            if let Some(&k) = self.chain.get(&cur) {
                return Ok((Some(k), mult, off));
            }
            let joint = &self.doc.joints[cur];
            match &joint.mimic {
                Some(m) => {
                    let (mm, mo) = (m.multiplier.unwrap_or(1.0), m.offset.unwrap_or(0.0));
                    if !(mm.is_finite() && mo.is_finite()) {
                        return Err(format!(
                            "joint {}: mimic multiplier/offset is not finite",
                            joint.name
                        ));
                    }
                    // value(cur) = mm · value(src) + mo
                    off += mult * mo;
                    mult *= mm;
                    let src = *self.by_name.get(m.joint.as_str()).ok_or_else(|| {
                        format!(
                            "joint {} mimics joint {}, which is not defined",
                            joint.name, m.joint
                        )
                    })?;
                    if seen.contains(&src) {
                        let names: Vec<&str> = seen
                            .iter()
                            .chain([&src])
                            .map(|&x| self.doc.joints[x].name.as_str())
                            .collect();
                        return Err(format!(
                            "mimic joints form a cycle ({})",
                            names.join(" -> ")
                        ));
                    }
                    if self.doc.joints[src].joint_type == JointType::Fixed {
                        return Err(format!(
                            "joint {} mimics joint {}, which is fixed",
                            joint.name, m.joint
                        ));
                    }
                    seen.push(src);
                    cur = src;
                }
                None => {
                    // Undriven: no controller moves it, no mimic ties it to one that does.
                    let (lo, hi) = (joint.limit.lower, joint.limit.upper);
                    let held = if lo <= hi { 0.0f64.clamp(lo, hi) } else { 0.0 };
                    let unit = if joint.joint_type == JointType::Prismatic {
                        format!("{} mm", crate::units::fmt_fixed(held * 1e3, 1))
                    } else {
                        format!("{} deg", crate::units::fmt_fixed(held.to_degrees(), 1))
                    };
                    let note = format!(
                        "joint {} is off the chain and neither driven nor a mimic: link {} is held at {unit}",
                        joint.name, joint.child.link
                    );
                    if !self.notes.contains(&note) {
                        self.notes.push(note);
                    }
                    return Ok((None, 0.0, off + mult * held));
                }
            }
        }
    }
}

fn type_name(t: &JointType) -> &'static str {
    match t {
        JointType::Revolute => "revolute",
        JointType::Continuous => "continuous",
        JointType::Prismatic => "prismatic",
        JointType::Fixed => "fixed",
        JointType::Floating => "floating",
        JointType::Planar => "planar",
        JointType::Spherical => "spherical",
    }
}

fn origin_frame(xyz: &[f64; 3], rpy: &[f64; 3]) -> Option<Frame> {
    xyz.iter()
        .chain(rpy)
        .all(|v| v.is_finite())
        .then(|| Frame::from_xyz_rpy(*xyz, *rpy))
}

/// The link/joint graph, checked to be one tree.
struct Tree<'a> {
    link_of: HashMap<&'a str, usize>,
    /// The joint whose child each link is.
    parent_joint: Vec<Option<usize>>,
    /// Joints whose parent each link is, in document order.
    children: Vec<Vec<usize>>,
    root: usize,
    /// All joints, parents before children (breadth first, document order within a link).
    order: Vec<usize>,
}

impl<'a> Tree<'a> {
    fn new(doc: &'a urdf_rs::Robot) -> Result<Self, String> {
        let mut link_of = HashMap::new();
        for (i, l) in doc.links.iter().enumerate() {
            if link_of.insert(l.name.as_str(), i).is_some() {
                return Err(format!("link {} is defined twice", l.name));
            }
        }
        let mut parent_joint = vec![None; doc.links.len()];
        let mut children = vec![Vec::new(); doc.links.len()];
        for (j, joint) in doc.joints.iter().enumerate() {
            let find = |name: &str| {
                link_of.get(name).copied().ok_or_else(|| {
                    format!(
                        "joint {} refers to link {name}, which is not defined",
                        joint.name
                    )
                })
            };
            let (p, c) = (find(&joint.parent.link)?, find(&joint.child.link)?);
            if let Some(other) = parent_joint[c].replace(j) {
                let other: &urdf_rs::Joint = &doc.joints[other];
                return Err(format!(
                    "link {} is the child of two joints ({} and {})",
                    joint.child.link, other.name, joint.name
                ));
            }
            children[p].push(j);
        }
        let roots: Vec<usize> = (0..doc.links.len())
            .filter(|&l| parent_joint[l].is_none())
            .collect();
        let root = match roots[..] {
            [r] => r,
            [] => return Err("no root link (every link is some joint's child)".into()),
            _ => {
                let names: Vec<&str> = roots.iter().map(|&l| doc.links[l].name.as_str()).collect();
                return Err(format!(
                    "{} root links ({}); a URDF robot must be one tree",
                    roots.len(),
                    names.join(", ")
                ));
            }
        };
        let mut order = Vec::with_capacity(doc.joints.len());
        let mut queue = std::collections::VecDeque::from([root]);
        while let Some(l) = queue.pop_front() {
            for &j in &children[l] {
                order.push(j);
                queue.push_back(link_of[doc.joints[j].child.link.as_str()]);
            }
        }
        if order.len() != doc.joints.len() {
            return Err(
                "the joints form a cycle (some links cannot be reached from the root)".into(),
            );
        }
        Ok(Tree {
            link_of,
            parent_joint,
            children,
            root,
            order,
        })
    }

    /// Joints from the root to `link`, in that order (the tree is checked, so this ends).
    fn path_from_root(&self, doc: &urdf_rs::Robot, link: usize) -> Vec<usize> {
        let mut path = Vec::new();
        let mut l = link;
        while let Some(j) = self.parent_joint[l] {
            path.push(j);
            l = self.link_of[doc.joints[j].parent.link.as_str()];
        }
        path.reverse();
        path
    }
}

fn pick_flange(doc: &urdf_rs::Robot, tree: &Tree, opts: &LoadOptions) -> Result<usize, String> {
    if let Some(name) = &opts.flange_link {
        return tree
            .link_of
            .get(name.as_str())
            .copied()
            .ok_or_else(|| format!("--flange {name}: no link of that name in the URDF"));
    }
    for name in ["flange", "tool0"] {
        if let Some(&l) = tree.link_of.get(name) {
            return Ok(l);
        }
    }
    let mut l = tree.root;
    loop {
        match tree.children[l][..] {
            [] => return Ok(l),
            [j] => l = tree.link_of[doc.joints[j].child.link.as_str()],
            _ => {
                return Err(format!(
                    "no link named flange or tool0, and the tree branches at link {}; name the flange link with --flange LINK",
                    doc.links[l].name
                ))
            }
        }
    }
}

#[derive(Clone, Copy)]
struct Line {
    p: V3,
    /// Unit direction.
    z: V3,
}

impl Line {
    fn closest_to(&self, x: &V3) -> V3 {
        self.p + self.z * (x - self.p).dot(&self.z)
    }
}

fn frame_from(x: V3, z: V3, o: V3) -> Frame {
    // Re-orthogonalise x against z: exact in theory, a few ulps off in practice.
    let x = (x - z * x.dot(&z)).normalize();
    Frame::new(Matrix3::from_columns(&[x, z.cross(&x), z]), o)
}

/// The DH table of the six axis lines (q = 0) and the DH frames 0..6 in the root frame,
/// recomputed from the table so that the chain closes exactly at q = 0.
fn dh_from_axes(axes: &[Line; 6], flange0: &Frame, size: f64) -> ([Dh; 6], [Frame; 7]) {
    let tol = LENGTH_TOL * size;
    let mut f = [Frame::IDENTITY; 7];

    // Frame 0: on axis 1, nearest the root origin; x0 as close to the root x as possible.
    let z0 = axes[0].z;
    let mut x0 = V3::x() - z0 * z0.x;
    if x0.norm() < 1e-6 {
        x0 = V3::y() - z0 * z0.y;
    }
    f[0] = frame_from(x0, z0, axes[0].closest_to(&V3::zeros()));

    for i in 1..6 {
        let prev = f[i - 1];
        let (op, xp, zp) = (prev.t, prev.r.column(0).into_owned(), axes[i - 1].z);
        let next = axes[i];
        let n = zp.cross(&next.z);
        let s = n.norm();
        let (o, x) = if s < PARALLEL_SIN {
            // Parallel: the common normal through the previous origin (d_i = 0).
            let o = next.closest_to(&op);
            let w = o - op;
            let w = w - zp * w.dot(&zp);
            let x = if w.norm() < tol { xp } else { w / w.norm() };
            (o, x)
        } else {
            // Skew or intersecting: the common normal; its foot on axis i+1 is the origin.
            let n = n / s;
            let r = next.p - op;
            let t = r.cross(&zp).dot(&n) / s;
            let o = next.p + next.z * t;
            let dist = r.dot(&n);
            let x = if dist.abs() >= tol {
                n * dist.signum() // from axis i to axis i+1: a_i > 0
            } else {
                // Intersecting: either sign is a valid DH frame; prefer the one closest to
                // x_{i-1} (small theta), then +y_{i-1}.
                let c = n.dot(&xp);
                let y = zp.cross(&xp);
                if c > 1e-9 || (c.abs() <= 1e-9 && n.dot(&y) >= 0.0) {
                    n
                } else {
                    -n
                }
            };
            (o, x)
        };
        f[i] = frame_from(x, next.z, o);
    }
    // Frame 6: on axis 6 nearest the flange origin, x6 = x5 (a6 = alpha6 = theta6 = 0).
    f[6] = frame_from(
        f[5].r.column(0).into_owned(),
        axes[5].z,
        axes[5].closest_to(&flange0.t),
    );

    let dh: [Dh; 6] = std::array::from_fn(|i| {
        let (a, b) = (&f[i], &f[i + 1]);
        let (xa, za) = (a.r.column(0), a.r.column(2));
        let (xb, zb) = (b.r.column(0), b.r.column(2));
        let w = b.t - a.t;
        let clean_len = |v: f64| if v.abs() < tol { 0.0 } else { v };
        let clean_ang = |v: f64| if v.abs() < 1e-14 { 0.0 } else { v };
        Dh {
            theta: clean_ang(xa.cross(&xb).dot(&za).atan2(xa.dot(&xb))),
            d: clean_len(w.dot(&za)),
            a: clean_len(w.dot(&xb)),
            alpha: clean_ang(za.cross(&zb).dot(&xb).atan2(za.dot(&zb))),
        }
    });
    let mut frames = [f[0]; 7];
    for i in 0..6 {
        frames[i + 1] = frames[i].mul(&dh_transform(&dh[i], 0.0));
    }
    (dh, frames)
}

fn geometry(
    g: &urdf_rs::Geometry,
    link: &str,
    urdf_dir: &Path,
    opts: &LoadOptions,
) -> Result<Geometry, String> {
    Ok(match g {
        urdf_rs::Geometry::Box { size } => Geometry::Box { size: size.0 },
        urdf_rs::Geometry::Cylinder { radius, length } => Geometry::Cylinder {
            radius: *radius,
            length: *length,
        },
        // No capsule primitive downstream: the enclosing cylinder keeps collision checks safe.
        urdf_rs::Geometry::Capsule { radius, length } => Geometry::Cylinder {
            radius: *radius,
            length: length + 2.0 * radius,
        },
        urdf_rs::Geometry::Sphere { radius } => Geometry::Sphere { radius: *radius },
        urdf_rs::Geometry::Mesh { filename, scale } => Geometry::Mesh {
            path: resolve_mesh(filename, urdf_dir, opts)
                .map_err(|e| format!("link {link}: mesh {filename}: {e}"))?,
            scale: scale.map_or([1.0; 3], |s| s.0),
        },
    })
}

/// `package://NAME/rest` → `D/NAME/rest` or (when D is the package itself) `D/rest`, for each
/// package path D in order; `file://` and plain paths → relative to the URDF's folder.
fn resolve_mesh(filename: &str, urdf_dir: &Path, opts: &LoadOptions) -> Result<PathBuf, String> {
    if let Some(rest) = filename.strip_prefix("package://") {
        let (package, rel) = rest.split_once('/').unwrap_or((rest, ""));
        let mut tried = Vec::new();
        for d in &opts.package_paths {
            let mut candidates = vec![d.join(package).join(rel)];
            if d.file_name().is_some_and(|n| n == package) {
                candidates.push(d.join(rel));
            }
            for c in candidates {
                if c.is_file() {
                    return Ok(c);
                }
                tried.push(c.display().to_string());
            }
        }
        return Err(if tried.is_empty() {
            format!("no package path given to find package {package}")
        } else {
            format!("file not found (tried {})", tried.join(", "))
        });
    }
    let plain = filename.strip_prefix("file://").unwrap_or(filename);
    if plain.contains("://") {
        return Err("unsupported URI scheme (use package://, file:// or a path)".into());
    }
    let p = Path::new(plain);
    let p = if p.is_absolute() {
        p.to_path_buf()
    } else {
        urdf_dir.join(p)
    };
    if p.is_file() {
        Ok(p)
    } else {
        Err(format!("file not found ({})", p.display()))
    }
}

/// Adds `velocity="0"` to every `<limit .../>` element that has no velocity attribute.
fn with_default_velocity(text: &str) -> std::borrow::Cow<'_, str> {
    if !text.contains("<limit") {
        return std::borrow::Cow::Borrowed(text);
    }
    let mut out = String::with_capacity(text.len() + 64);
    let mut rest = text;
    let mut changed = false;
    while let Some(i) = rest.find("<limit") {
        let (head, tail) = rest.split_at(i);
        out.push_str(head);
        let end = tail.find('>').map_or(tail.len(), |e| e + 1);
        let elem = &tail[..end];
        // "<limit" must be the whole tag name (not e.g. "<limits").
        let is_limit = elem[6..].starts_with(|c: char| c.is_whitespace() || c == '/' || c == '>');
        if is_limit && !elem.contains("velocity") {
            out.push_str("<limit velocity=\"0\"");
            out.push_str(&elem[6..]);
            changed = true;
        } else {
            out.push_str(elem);
        }
        rest = &tail[end..];
    }
    out.push_str(rest);
    if changed {
        std::borrow::Cow::Owned(out)
    } else {
        std::borrow::Cow::Borrowed(text)
    }
}

// ---- the calibrated robot ------------------------------------------------------------------

/// Start of the comment edbbgen puts in a calibrated URDF (replaced on re-calibration).
const CALIBRATION_MARK: &str = "edbbgen calibration";

/// The input URDF with a calibrated chain: the six chain joints' origins (and the `edbb_map`
/// link's, added when missing) rewritten so that the file's forward kinematics is exactly the
/// calibrated DH chain `dh` with the MAP at `map` (flange frame); every other byte (meshes,
/// limits, names, comments, passive linkages) as in the input, plus `header` as a comment.
///
/// Why it is exact: a serial chain is fixed by its joint axes (lines, with sign) and its flange
/// at q = 0 (product of exponentials). The links rigid with DH frame k are moved by the rigid
/// correction D_{k−1} = F'_{k−1}(0) · F_{k−1}(0)⁻¹, which carries joint k's axis onto the
/// calibrated one; link 6's own DH deviations (dependent on the MAP for a bar) go into the MAP.
pub fn calibrated(
    text: &str,
    path: &Path,
    opts: &LoadOptions,
    nominal: &Robot,
    dh: &[Dh; 6],
    map: &V3,
    header: &[String],
) -> Result<String, LoadError> {
    calibrated_text(text, opts, nominal, dh, map, header)
        .map_err(|msg| LoadError::invalid(path, one_line(&msg)))
}

fn calibrated_text(
    text: &str,
    opts: &LoadOptions,
    nominal: &Robot,
    dh: &[Dh; 6],
    map: &V3,
    header: &[String],
) -> Result<String, String> {
    use crate::robot::kinematics::chain_frames;
    let patched = with_default_velocity(text);
    let doc = urdf_rs::read_from_string(&patched).map_err(|e| format!("not a valid URDF: {e}"))?;
    let lay = layout(&doc, opts)?;
    let zero = [0.0; 6];
    let f_nom = chain_frames(&nominal.base, &nominal.dh, &nominal.flange, &zero);
    let f_cal = chain_frames(&nominal.base, dh, &nominal.flange, &zero);
    // D_k for the links rigid with DH frame k+1 (k = 0..5); the root's links stay.
    let corr: [Frame; 6] = std::array::from_fn(|k| f_cal[k].mul(&f_nom[k].inverse()));
    let moved = |l: usize| -> Frame {
        match lay.group[l] {
            Some(g) if g >= 1 => corr[g - 1].mul(&lay.pose0[l]),
            _ => lay.pose0[l],
        }
    };
    // The new origins of the chain joints.
    let mut origins: Vec<(String, Frame)> = Vec::new();
    for &j in &lay.revolute {
        let joint = &doc.joints[j];
        let (p, c) = (
            lay.tree.link_of[joint.parent.link.as_str()],
            lay.tree.link_of[joint.child.link.as_str()],
        );
        let axis = V3::from(joint.axis.xyz.0).normalize();
        // The child frame rotates about the joint axis through its origin: keep that.
        let o = moved(p).inverse().mul(&moved(c));
        debug_assert!((o.r * axis).norm() > 0.5);
        origins.push((joint.name.clone(), o));
    }
    // The MAP: link 6's deviations from nominal move it (flange frame).
    let k6 = |d: &Dh| crate::robot::kinematics::dh_transform(d, 0.0);
    let map_urdf = nominal
        .flange
        .inverse()
        .mul(&k6(&nominal.dh[5]).inverse())
        .mul(&k6(&dh[5]))
        .mul(&nominal.flange)
        .apply(map);
    let flange = lay.flange_link;
    let map_joint = lay
        .tree
        .link_of
        .get(MAP_LINK)
        .and_then(|&m| lay.tree.parent_joint[m].map(|j| (m, j)));
    let mut insert_map = None;
    match map_joint {
        Some((m, j)) => {
            if lay.group[m] != Some(6) {
                return Err(format!(
                    "link {MAP_LINK} (the EDBB MAP) must be fixed to the flange link {} through fixed joints",
                    doc.links[flange].name
                ));
            }
            let joint = &doc.joints[j];
            let p = lay.tree.link_of[joint.parent.link.as_str()];
            // Its position in its parent's frame; the orientation of a point does not matter.
            let xyz = lay.pose0[p]
                .inverse()
                .mul(&lay.pose0[flange])
                .apply(&map_urdf);
            let rpy = joint.origin.rpy.0;
            origins.push((
                joint.name.clone(),
                Frame::from_xyz_rpy([xyz.x, xyz.y, xyz.z], rpy),
            ));
        }
        None => insert_map = Some(map_urdf),
    }
    edit_urdf(text, &origins, insert_map, &doc.links[flange].name, header)
}

/// Shortest round-trip decimal of a float (exact; no exponent).
fn num(v: f64) -> String {
    let v = if v == 0.0 { 0.0 } else { v };
    format!("{v}")
}

fn origin_xml(f: &Frame) -> String {
    let r = f.rpy();
    format!(
        "<origin xyz=\"{} {} {}\" rpy=\"{} {} {}\"/>",
        num(f.t.x),
        num(f.t.y),
        num(f.t.z),
        num(r[0]),
        num(r[1]),
        num(r[2])
    )
}

/// Rewrites the `<origin>` of each named joint (inserting one where a joint has none), adds
/// the `edbb_map` link when asked, and puts the header comment first (replacing an earlier
/// calibration comment).
fn edit_urdf(
    text: &str,
    origins: &[(String, Frame)],
    insert_map: Option<V3>,
    flange: &str,
    header: &[String],
) -> Result<String, String> {
    use quick_xml::events::Event;
    let mut reader = quick_xml::Reader::from_str(text);
    // (start, end, replacement) byte ranges.
    let mut edits: Vec<(usize, usize, String)> = Vec::new();
    let mut joint: Option<(String, usize, bool)> = None; // name, end of its start tag, origin seen
    let mut depth_in_joint = 0usize;
    let mut robot_end = None;
    let mut old_comment = None;
    let mut first_element = None;
    let mut edited: Vec<String> = Vec::new();
    loop {
        let before = reader.buffer_position() as usize;
        let ev = reader
            .read_event()
            .map_err(|e| format!("not a valid URDF: {e}"))?;
        let after = reader.buffer_position() as usize;
        match ev {
            Event::Eof => break,
            Event::Comment(c) => {
                let body = String::from_utf8_lossy(&c);
                if old_comment.is_none() && body.trim_start().starts_with(CALIBRATION_MARK) {
                    old_comment = Some((before, after));
                }
            }
            Event::Start(e) => {
                first_element.get_or_insert(before);
                match (&joint, e.name().as_ref()) {
                    (None, b"joint") => {
                        let name = attr(&e, "name")?;
                        joint = Some((name, after, false));
                        depth_in_joint = 0;
                    }
                    (Some(_), b"origin") if depth_in_joint == 0 => {
                        // <origin ...></origin>: replace through its end tag.
                        let end = skip_to_end(&mut reader)?;
                        if let Some((name, _, seen)) = joint.as_mut() {
                            *seen = true;
                            if let Some((_, f)) = origins.iter().find(|(n, _)| n == name) {
                                edits.push((before, end, origin_xml(f)));
                                edited.push(name.clone());
                            }
                        }
                    }
                    (Some(_), _) => depth_in_joint += 1,
                    _ => {}
                }
            }
            Event::Empty(e) => {
                first_element.get_or_insert(before);
                if let (Some((name, _, seen)), b"origin") = (joint.as_mut(), e.name().as_ref()) {
                    if depth_in_joint == 0 {
                        *seen = true;
                        if let Some((_, f)) = origins.iter().find(|(n, _)| n == name) {
                            edits.push((before, after, origin_xml(f)));
                            edited.push(name.clone());
                        }
                    }
                }
            }
            Event::End(e) => match (e.name().as_ref(), &joint) {
                (b"joint", Some((name, start_end, seen))) if depth_in_joint == 0 => {
                    if !seen {
                        if let Some((_, f)) = origins.iter().find(|(n, _)| n == name) {
                            edits.push((
                                *start_end,
                                *start_end,
                                format!("\n    {}", origin_xml(f)),
                            ));
                            edited.push(name.clone());
                        }
                    }
                    joint = None;
                }
                (b"robot", _) => robot_end = Some(before),
                (_, Some(_)) => depth_in_joint = depth_in_joint.saturating_sub(1),
                _ => {}
            },
            _ => {}
        }
    }
    let missing: Vec<&str> = origins
        .iter()
        .map(|(n, _)| n.as_str())
        .filter(|n| !edited.iter().any(|e| e == n))
        .collect();
    if !missing.is_empty() {
        return Err(format!(
            "joint {}: no such <joint> element found by the editor",
            missing.join(", ")
        ));
    }
    if let Some(m) = insert_map {
        let at = robot_end.ok_or("no </robot> end tag")?;
        edits.push((
            at,
            at,
            format!(
                "  <!-- edbbgen: the EDBB measurement application point (tool ball centre), fixed to the flange -->\n  <link name=\"{MAP_LINK}\"/>\n  <joint name=\"{MAP_LINK}_joint\" type=\"fixed\">\n    <parent link=\"{flange}\"/>\n    <child link=\"{MAP_LINK}\"/>\n    {}\n  </joint>\n",
                origin_xml(&Frame::translation(m))
            ),
        ));
    }
    let comment = format!(
        "<!-- {CALIBRATION_MARK}\n{}\n-->",
        header
            .iter()
            .map(|l| format!("     {}", l.replace("--", "- -")))
            .collect::<Vec<_>>()
            .join("\n")
    );
    match old_comment {
        Some((a, b)) => edits.push((a, b, comment)),
        None => {
            let at = first_element.ok_or("no <robot> element")?;
            edits.push((at, at, format!("{comment}\n")));
        }
    }
    edits.sort_by_key(|e| (e.0, e.1));
    let mut out = String::with_capacity(text.len() + 1024);
    let mut pos = 0;
    for (a, b, r) in edits {
        out.push_str(&text[pos..a]);
        out.push_str(&r);
        pos = b;
    }
    out.push_str(&text[pos..]);
    Ok(out)
}

fn attr(e: &quick_xml::events::BytesStart, name: &str) -> Result<String, String> {
    match e.try_get_attribute(name) {
        Ok(Some(a)) => a
            .unescape_value()
            .map(|v| v.into_owned())
            .map_err(|err| format!("attribute {name}: {err}")),
        Ok(None) => Err(format!("a <joint> without a {name} attribute")),
        Err(err) => Err(format!("attribute {name}: {err}")),
    }
}

/// Reads up to the end tag of the element just started; returns the byte after it.
fn skip_to_end(reader: &mut quick_xml::Reader<&[u8]>) -> Result<usize, String> {
    use quick_xml::events::Event;
    let mut depth = 1usize;
    loop {
        match reader
            .read_event()
            .map_err(|e| format!("not a valid URDF: {e}"))?
        {
            Event::Start(_) => depth += 1,
            Event::End(_) => {
                depth -= 1;
                if depth == 0 {
                    return Ok(reader.buffer_position() as usize);
                }
            }
            Event::Eof => return Err("unexpected end of file".into()),
            _ => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::robot::{axis_angle, load};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    const SHARED: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/robots");
    const NJ130_URDF: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/robots/comau_nj130/robot.urdf");
    const NJ130_DH: &str = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/robots/comau_nj130/robot.dh.toml"
    );

    /// Independent URDF forward kinematics: walk the urdf-rs joints from `link` up to the root,
    /// then compose origin · rotation(axis, q) down again. Joint values are taken by joint name.
    fn urdf_fk(doc: &urdf_rs::Robot, link: &str, q: &HashMap<&str, f64>) -> Option<Frame> {
        let mut path = Vec::new();
        let mut l = link;
        while let Some(j) = doc.joints.iter().find(|j| j.child.link == l) {
            path.push(j);
            l = &j.parent.link;
        }
        let mut t = Frame::IDENTITY;
        for j in path.iter().rev() {
            t = t.mul(&Frame::from_xyz_rpy(j.origin.xyz.0, j.origin.rpy.0));
            match j.joint_type {
                JointType::Fixed => {}
                JointType::Revolute | JointType::Continuous => {
                    let axis = V3::from(j.axis.xyz.0).normalize();
                    let qj = *q.get(j.name.as_str())?; // None: off the chain
                    t = t.mul(&Frame::new(axis_angle(&axis, qj), V3::zeros()));
                }
                JointType::Prismatic => {
                    let axis = V3::from(j.axis.xyz.0).normalize();
                    let qj = *q.get(j.name.as_str())?;
                    t = t.mul(&Frame::translation(axis * qj));
                }
                _ => return None,
            }
        }
        Some(t)
    }

    fn random_q(robot: &Robot, rng: &mut ChaCha8Rng) -> [f64; 6] {
        std::array::from_fn(|i| rng.random_range(robot.joints[i].lower..=robot.joints[i].upper))
    }

    /// Position and rotation disagreement of two frames.
    fn diff(a: &Frame, b: &Frame) -> (f64, f64) {
        ((a.t - b.t).norm(), (a.r - b.r).abs().max())
    }

    /// Loads `file`, then checks the DH chain against the independent URDF FK over 1000 random
    /// poses, and every collision shape's world pose at a few of them. Returns the worst errors.
    fn check_against_urdf_fk(file: &str, flange: &str) -> (f64, f64) {
        let robot = load(Path::new(file), &LoadOptions::default()).expect(file);
        let doc = urdf_rs::read_file(file).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let (mut dp, mut dr) = (0.0f64, 0.0f64);
        for n in 0..1000 {
            let q = random_q(&robot, &mut rng);
            let by_name: HashMap<&str, f64> = robot
                .joints
                .iter()
                .zip(q)
                .map(|(j, v)| (j.name.as_str(), v))
                .collect();
            let want = urdf_fk(&doc, flange, &by_name).unwrap();
            let (p, r) = diff(&want, &robot.fk(&q));
            (dp, dr) = (dp.max(p), dr.max(r));
            if n % 100 == 0 {
                check_shapes(file, &doc, &robot, &q, &by_name);
            }
        }
        eprintln!("{file}: max FK disagreement {dp:.3e} m, {dr:.3e} (rotation)");
        assert!(dp < 1e-9 && dr < 1e-9, "{file}: {dp:e} m, {dr:e}");
        (dp, dr)
    }

    /// Every collision element of a link rigid with the chain appears once among the shapes,
    /// at the same world pose.
    fn check_shapes(
        file: &str,
        doc: &urdf_rs::Robot,
        robot: &Robot,
        q: &[f64; 6],
        by_name: &HashMap<&str, f64>,
    ) {
        let frames =
            crate::robot::kinematics::chain_frames(&robot.base, &robot.dh, &robot.flange, q);
        let mut used = vec![false; robot.shapes.len()];
        let dir = Path::new(file).parent().unwrap();
        // Mimic joints take their values from their sources (the URDF rule, computed here).
        let mut by_name = by_name.clone();
        while let Some(j) = doc.joints.iter().find(|j| {
            !by_name.contains_key(j.name.as_str())
                && j.mimic
                    .as_ref()
                    .is_some_and(|m| by_name.contains_key(m.joint.as_str()))
        }) {
            let m = j.mimic.as_ref().unwrap();
            let v =
                m.multiplier.unwrap_or(1.0) * by_name[m.joint.as_str()] + m.offset.unwrap_or(0.0);
            by_name.insert(j.name.as_str(), v);
        }
        let by_name = &by_name;
        let placed = |s: &LinkShape| match s.passive {
            Some(pi) => robot.passive[pi].pose(&frames, q).mul(&s.origin),
            None => frames[s.frame].mul(&s.origin),
        };
        for link in &doc.links {
            let Some(at) = urdf_fk(doc, &link.name, by_name) else {
                continue;
            };
            for c in &link.collision {
                let want = at.mul(&Frame::from_xyz_rpy(c.origin.xyz.0, c.origin.rpy.0));
                let found = robot.shapes.iter().enumerate().position(|(i, s)| {
                    let (p, r) = diff(&want, &placed(s));
                    let same = match (&s.geometry, &c.geometry) {
                        (Geometry::Mesh { path, .. }, urdf_rs::Geometry::Mesh { filename, .. }) => {
                            *path == dir.join(filename)
                        }
                        (Geometry::Box { size }, urdf_rs::Geometry::Box { size: s2 }) => {
                            *size == s2.0
                        }
                        (Geometry::Sphere { .. }, urdf_rs::Geometry::Sphere { .. })
                        | (Geometry::Cylinder { .. }, urdf_rs::Geometry::Cylinder { .. }) => true,
                        _ => false,
                    };
                    !used[i] && same && p < 1e-9 && r < 1e-9
                });
                let i = found.unwrap_or_else(|| panic!("{file}: no shape for link {}", link.name));
                used[i] = true;
            }
        }
        assert!(
            used.iter().all(|&u| u),
            "{file}: shapes without a URDF collision"
        );
    }

    #[test]
    fn shared_robots_match_independent_urdf_fk() {
        // The ABB has passive mimic joints off the chain, the KR120 and the FANUC negative
        // axes, the KR210 CAD-derived origins: none needs special handling.
        for dir in [
            "abb_irb6700_200_260",
            "kuka_kr210_l150",
            "kuka_kr120_r2500pro",
            "fanuc_r2000ic_165f",
        ] {
            check_against_urdf_fk(&format!("{SHARED}/{dir}/robot.urdf"), "flange");
        }
    }

    #[test]
    fn shared_robots_keep_names_limits_and_place_passive_links() {
        let abb = load(
            Path::new(&format!("{SHARED}/abb_irb6700_200_260/robot.urdf")),
            &LoadOptions::default(),
        )
        .unwrap();
        assert_eq!(abb.name, "abb_irb6700_200_260");
        assert_eq!(abb.source, "robot.urdf");
        let names: Vec<&str> = abb.joints.iter().map(|j| j.name.as_str()).collect();
        assert_eq!(
            names,
            ["joint_1", "joint_2", "joint_3", "joint_4", "joint_5", "joint_6"]
        );
        assert!((abb.joints[1].lower - -1.13446).abs() < 1e-5);
        assert!((abb.joints[3].max_speed - 3.31613).abs() < 1e-5);
        // 9 collision meshes, two of them on the passive cylinder and piston (mimics of
        // joint_2: ×−0.25 revolute, ×0.15 prismatic).
        assert_eq!(abb.shapes.len(), 9);
        let passive: Vec<(&str, usize, Option<usize>)> = abb
            .passive
            .iter()
            .map(|p| {
                (
                    p.name.as_str(),
                    p.frame,
                    p.steps.last().and_then(|s| s.joint),
                )
            })
            .collect();
        assert_eq!(passive, [("cylinder", 1, Some(1)), ("piston", 1, Some(1))]);
        assert_eq!(
            abb.passive[1].parent,
            Some(0),
            "the piston hangs on the cylinder"
        );
        assert!((abb.passive[0].steps[0].multiplier + 0.25).abs() < 1e-15);
        assert!((abb.passive[1].steps[1].multiplier - 0.15).abs() < 1e-15);
        assert!(abb.notes.is_empty(), "{:?}", abb.notes);
        assert!(abb.tool.is_none());
        let p = abb.fk(&[0.0; 6]).t;
        assert!((p - V3::new(1.6625, 0.0, 2.105)).norm() < 1e-9);
    }

    #[test]
    fn nj130_urdf_matches_independent_fk_and_the_dh_file() {
        check_against_urdf_fk(NJ130_URDF, "flange");
        let u = load(Path::new(NJ130_URDF), &LoadOptions::default()).unwrap();
        let d = load(Path::new(NJ130_DH), &LoadOptions::default()).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let (mut dp, mut dr) = (0.0f64, 0.0f64);
        for _ in 0..1000 {
            let q = random_q(&d, &mut rng);
            let (p, r) = diff(&u.fk(&q), &d.fk(&q));
            (dp, dr) = (dp.max(p), dr.max(r));
        }
        eprintln!("NJ-130 URDF vs DH file: max {dp:.3e} m, {dr:.3e} (rotation)");
        assert!(dp < 1e-9 && dr < 1e-9);
        let (ut, dt) = (u.tool.unwrap(), d.tool.unwrap());
        assert!((ut - dt).norm() < 1e-12, "{ut:?} vs {dt:?}");
        for (a, b) in u.joints.iter().zip(&d.joints) {
            assert_eq!(a.name, b.name);
            assert!((a.lower - b.lower).abs() < 1e-12 && (a.upper - b.upper).abs() < 1e-12);
            assert!((a.max_speed - b.max_speed).abs() < 1e-12);
        }
        assert!(!u.shapes.is_empty());
    }

    /// A URDF of `n` revolute joints along a stretched arm, with an optional extra joint.
    fn arm(n: usize, extra: &str) -> String {
        let mut s = String::from("<robot name=\"arm\"><link name=\"l0\"/>");
        for i in 1..=n {
            s += &format!(
                "<link name=\"l{i}\"/><joint name=\"j{i}\" type=\"revolute\"><parent link=\"l{}\"/>\
                 <child link=\"l{i}\"/><origin xyz=\"0.1 0 0.2\"/><axis xyz=\"0 {} 1\"/>\
                 <limit lower=\"-1\" upper=\"1\" velocity=\"1\" effort=\"0\"/></joint>",
                i - 1,
                i % 2
            );
        }
        s + extra + "</robot>"
    }

    fn error(text: &str, opts: &LoadOptions) -> String {
        let path = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/inline.urdf"));
        let msg = match from_str(text, path, opts) {
            Ok(_) => panic!("accepted: {text}"),
            Err(e) => e.to_string(),
        };
        assert!(!msg.contains('\n'), "{msg}");
        msg
    }

    /// A 6R arm with passive links: `p1` on l2 turns with j3 (mimic ×0.5 + 0.1), `p2` on p1
    /// slides with p1's joint (a mimic of a mimic: ×2 + 0.01), `p3` on l1 hangs on a joint
    /// nothing drives.
    fn passive_arm(p1_mimic: &str, p2_mimic: &str) -> String {
        let shape = "<collision><origin xyz=\"0.02 0.01 0.03\" rpy=\"0.1 0.2 0.3\"/><geometry><box size=\"0.05 0.05 0.05\"/></geometry></collision>";
        arm(
            6,
            &format!(
                "<link name=\"p1\">{shape}</link><link name=\"p2\">{shape}</link><link name=\"p3\">{shape}</link>\
                 <joint name=\"pj1\" type=\"revolute\"><parent link=\"l2\"/><child link=\"p1\"/><origin xyz=\"0.05 0 0.1\" rpy=\"0.3 0 0\"/>\
                 <axis xyz=\"0 1 0\"/><limit lower=\"-3\" upper=\"3\" velocity=\"1\" effort=\"0\"/>{p1_mimic}</joint>\
                 <joint name=\"pj2\" type=\"prismatic\"><parent link=\"p1\"/><child link=\"p2\"/><origin xyz=\"0 0.02 0\"/>\
                 <axis xyz=\"1 0 0\"/><limit lower=\"-1\" upper=\"1\" velocity=\"1\" effort=\"0\"/>{p2_mimic}</joint>\
                 <joint name=\"free\" type=\"revolute\"><parent link=\"l1\"/><child link=\"p3\"/><origin xyz=\"0 0 0.05\"/>\
                 <axis xyz=\"0 0 1\"/><limit lower=\"0.2\" upper=\"1\" velocity=\"1\" effort=\"0\"/></joint>"
            ),
        )
    }

    #[test]
    fn passive_links_follow_nested_mimics_and_undriven_joints_are_held_and_noted() {
        let text = passive_arm(
            "<mimic joint=\"j3\" multiplier=\"0.5\" offset=\"0.1\"/>",
            "<mimic joint=\"pj1\" multiplier=\"2\" offset=\"0.01\"/>",
        );
        let path = Path::new("passive.urdf");
        let o = LoadOptions {
            flange_link: Some("l6".into()),
            ..LoadOptions::default()
        };
        let robot = from_str(&text, path, &o).expect("loads");
        let doc = urdf_rs::read_from_string(&text).unwrap();
        let names: Vec<&str> = robot.passive.iter().map(|p| p.name.as_str()).collect();
        assert_eq!(names, ["p1", "p2", "p3"]);
        assert_eq!(robot.passive[1].parent, Some(0), "p2 hangs on p1");
        assert_eq!(robot.passive[0].parent, None);
        // `free` has limits 0.2..1: held at 0.2 rad, and said so.
        assert!(
            robot
                .notes
                .iter()
                .any(|n| n.contains("joint free") && n.contains("held at 11.5 deg")),
            "{:?}",
            robot.notes
        );
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for _ in 0..200 {
            let q = random_q(&robot, &mut rng);
            let frames =
                crate::robot::kinematics::chain_frames(&robot.base, &robot.dh, &robot.flange, &q);
            // Independent: every joint value by name, the mimic arithmetic done here.
            let mut by_name: HashMap<&str, f64> = robot
                .joints
                .iter()
                .zip(q)
                .map(|(j, v)| (j.name.as_str(), v))
                .collect();
            let pj1 = 0.5 * q[2] + 0.1;
            by_name.insert("pj1", pj1);
            by_name.insert("pj2", 2.0 * pj1 + 0.01);
            by_name.insert("free", 0.2);
            for s in robot.shapes.iter().filter(|s| s.passive.is_some()) {
                let link = &robot.passive[s.passive.unwrap()];
                let got = link.pose(&frames, &q).mul(&s.origin);
                let c = &doc
                    .links
                    .iter()
                    .find(|l| l.name == link.name)
                    .unwrap()
                    .collision[0];
                let want = urdf_fk(&doc, &link.name, &by_name)
                    .unwrap()
                    .mul(&Frame::from_xyz_rpy(c.origin.xyz.0, c.origin.rpy.0));
                let (dp, dr) = diff(&got, &want);
                assert!(dp < 1e-12 && dr < 1e-12, "{}: {dp:e} m, {dr:e}", link.name);
            }
        }
    }

    #[test]
    fn mimic_cycles_and_unknown_sources_are_errors() {
        let o = LoadOptions {
            flange_link: Some("l6".into()),
            ..LoadOptions::default()
        };
        let m = error(
            &passive_arm("<mimic joint=\"pj2\"/>", "<mimic joint=\"pj1\"/>"),
            &o,
        );
        assert!(m.contains("mimic joints form a cycle (pj"), "{m}");
        let m = error(&passive_arm("<mimic joint=\"nope\"/>", ""), &o);
        assert!(
            m.contains("joint pj1 mimics joint nope, which is not defined"),
            "{m}"
        );
    }

    #[test]
    fn a_base_link_fixed_to_the_root_moves_the_base_frame() {
        // `world` is 1 m above the root and turned 90° about z: the same arm seen from it.
        let extra = "<link name=\"world\"/><joint name=\"w\" type=\"fixed\"><parent link=\"l0\"/>\
                     <child link=\"world\"/><origin xyz=\"0 0 1\" rpy=\"0 0 1.5707963267948966\"/></joint>";
        let path = Path::new("inline.urdf");
        let six = LoadOptions {
            flange_link: Some("l6".into()),
            ..LoadOptions::default()
        };
        let plain = from_str(&arm(6, extra), path, &six).unwrap();
        let moved = from_str(
            &arm(6, extra),
            path,
            &LoadOptions {
                base_link: Some("world".into()),
                ..six.clone()
            },
        )
        .unwrap();
        let q = [0.1, -0.2, 0.3, 0.4, -0.5, 0.6];
        let (a, b) = (plain.fk(&q).t, moved.fk(&q).t);
        // In the world frame: x_w = y_root, y_w = −x_root, z_w = z_root − 1.
        assert!(
            (b - V3::new(a.y, -a.x, a.z - 1.0)).norm() < 1e-12,
            "{a} {b}"
        );
        let m = error(
            &arm(6, extra),
            &LoadOptions {
                base_link: Some("l2".into()),
                ..six
            },
        );
        assert!(m.contains("base link l2: it moves with the joints"), "{m}");
    }

    #[test]
    fn errors_are_one_line_and_name_the_problem() {
        let o = LoadOptions::default();
        let m = error("<robot name=\"x\"><link name=\"a\">", &o);
        assert!(m.contains("inline.urdf: not a valid URDF"), "{m}");

        let m = error(&arm(5, ""), &o);
        assert!(
            m.ends_with("chain l0 -> l5 has 5 revolute joints (j1, j2, j3, j4, j5); edbbgen needs exactly 6"),
            "{m}"
        );

        let prismatic = "<link name=\"l7\"/><joint name=\"slide\" type=\"prismatic\"><parent link=\"l6\"/>\
            <child link=\"l7\"/><axis xyz=\"1 0 0\"/><limit lower=\"0\" upper=\"1\" velocity=\"1\" effort=\"0\"/></joint>";
        let m = error(&arm(6, prismatic), &o);
        assert!(
            m.contains("joint slide on the chain l0 -> l7 is prismatic"),
            "{m}"
        );

        let mimic = arm(6, "").replace(
            "<parent link=\"l2\"/>",
            "<parent link=\"l2\"/><mimic joint=\"j2\"/>",
        );
        let m = error(&mimic, &o);
        assert!(
            m.contains("joint j3 on the chain l0 -> l6 is a mimic joint"),
            "{m}"
        );

        let flange = LoadOptions {
            flange_link: Some("gripper".into()),
            ..LoadOptions::default()
        };
        let m = error(&arm(6, ""), &flange);
        assert!(m.contains("--flange gripper: no link of that name"), "{m}");

        let mesh = arm(6, "").replace(
            "<link name=\"l3\"/>",
            "<link name=\"l3\"><collision><geometry><mesh filename=\"meshes/nope.stl\"/></geometry></collision></link>",
        );
        let m = error(&mesh, &o);
        assert!(
            m.contains("link l3: mesh meshes/nope.stl: file not found"),
            "{m}"
        );

        let branch = arm(6, "<link name=\"side\"/><joint name=\"s\" type=\"fixed\"><parent link=\"l2\"/><child link=\"side\"/></joint>");
        let m = error(&branch, &o);
        assert!(
            m.contains("branches at link l2") && m.contains("--flange LINK"),
            "{m}"
        );

        // A <limit> without a velocity is a speed we do not know: loading asks for speeds.
        let path = Path::new("inline.urdf");
        let robot = from_str(&arm(6, "").replace("velocity=\"1\"", ""), path, &o).expect("parses");
        let m = robot.validate(path).unwrap_err().to_string();
        assert!(
            m.contains("max speed missing or zero") && m.contains("speeds"),
            "{m}"
        );
    }

    #[test]
    fn generated_arms_load_and_agree_with_urdf_fk() {
        let path = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/inline.urdf"));
        // Without a flange/tool0 link, the chain's end is the flange; --flange picks another.
        let r = from_str(&arm(6, ""), path, &LoadOptions::default()).unwrap();
        assert_eq!(r.joints[5].name, "j6");
        let r = from_str(
            &arm(7, ""),
            path,
            &LoadOptions {
                flange_link: Some("l6".into()),
                ..LoadOptions::default()
            },
        )
        .unwrap();
        assert_eq!(r.joints[0].name, "j1");
    }

    #[test]
    fn continuous_joints_misplaced_map_and_truncated_files() {
        let path = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/inline.urdf"));
        let o = LoadOptions::default();
        let cont = arm(6, "").replacen("type=\"revolute\"", "type=\"continuous\"", 1);
        let r = from_str(&cont, path, &o).unwrap();
        assert_eq!((r.joints[0].lower, r.joints[0].upper), (-TAU, TAU));

        let map = "<link name=\"edbb_map\"/><joint name=\"m\" type=\"fixed\"><parent link=\"l6\"/>\
            <child link=\"edbb_map\"/><origin xyz=\"0.01 0.02 0.03\"/></joint>";
        let r = from_str(
            &arm(6, map),
            path,
            &LoadOptions {
                flange_link: Some("l6".into()),
                ..o.clone()
            },
        );
        assert!((r.unwrap().tool.unwrap() - V3::new(0.01, 0.02, 0.03)).norm() < 1e-15);
        let m = error(
            &arm(6, &map.replace("\"l6\"", "\"l3\"")),
            &LoadOptions {
                flange_link: Some("l6".into()),
                ..o.clone()
            },
        );
        assert!(
            m.contains("link edbb_map (the EDBB MAP) must be fixed to the flange link l6"),
            "{m}"
        );

        // Bad input never panics: every prefix of a real file is an error or a robot.
        let text =
            std::fs::read_to_string(format!("{SHARED}/abb_irb6700_200_260/robot.urdf")).unwrap();
        let file = Path::new(SHARED).join("abb_irb6700_200_260/robot.urdf");
        for cut in (0..text.len()).step_by(97) {
            if text.is_char_boundary(cut) {
                if let Err(e) = from_str(&text[..cut], &file, &o) {
                    assert!(!e.to_string().contains('\n'));
                }
            }
        }
    }

    /// CAD axes that are almost but not exactly parallel: exact (1e-9 m) outside the window
    /// around `PARALLEL_SIN` where standard DH itself runs out of precision, within 5e-8 m in it.
    #[test]
    fn nearly_parallel_axes_stay_close() {
        let path = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/inline.urdf"));
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        for tilt in [
            0.0, 1e-13, 1e-11, 3e-10, 1e-9, 3e-9, 1e-8, 1.4e-8, 1.6e-8, 2e-8, 3e-8, 1e-7, 1e-6,
            1e-4,
        ] {
            // Two parallel-axis pairs (2-3 and 3-4) as in an arm, joint 3's axis tilted.
            let text = format!(
                "<robot name=\"p\"><link name=\"l0\"/>{}</robot>",
                [
                    ("0 0 0.5", "0 0 0", "0 0 1"),
                    ("0.3 0.02 0.2", "0 0 0", "0 1 0"),
                    ("0.01 -0.03 1.1", &format!("{tilt} 0 0") as &str, "0 1 0"),
                    ("0.2 0.01 0.2", "0 0 0", "0 1 0"),
                    ("1.0 0 0", "0 0 0", "1 0 0"),
                    ("0 0 0", "0 0 0", "0 1 0"),
                    ("0.2 0 0", "0 0 0", "1 0 0"),
                ]
                .iter()
                .enumerate()
                .map(|(i, (xyz, rpy, axis))| {
                    let (kind, n) = (if i < 6 { "revolute" } else { "fixed" }, i + 1);
                    format!(
                        "<link name=\"l{n}\"/><joint name=\"j{n}\" type=\"{kind}\"><parent link=\"l{i}\"/>\
                         <child link=\"l{n}\"/><origin xyz=\"{xyz}\" rpy=\"{rpy}\"/><axis xyz=\"{axis}\"/>\
                         <limit lower=\"-3\" upper=\"3\" velocity=\"1\"/></joint>"
                    )
                })
                .collect::<String>()
            );
            let robot = from_str(&text, path, &LoadOptions::default()).unwrap();
            let doc = urdf_rs::read_from_string(&text).unwrap();
            let mut worst = 0.0f64;
            for _ in 0..200 {
                let q = random_q(&robot, &mut rng);
                let by_name: HashMap<&str, f64> = robot
                    .joints
                    .iter()
                    .zip(q)
                    .map(|(j, v)| (j.name.as_str(), v))
                    .collect();
                let (p, r) = diff(&urdf_fk(&doc, "l7", &by_name).unwrap(), &robot.fk(&q));
                worst = worst.max(p).max(r);
            }
            eprintln!("tilt {tilt:e}: max FK disagreement {worst:.3e}");
            let bound = if (1e-9..=1e-7).contains(&tilt) {
                5e-8
            } else {
                1e-9
            };
            assert!(worst < bound, "tilt {tilt:e}: {worst:e}");
        }
    }

    /// Random arms, half of them with axis-aligned axes and offsets so that parallel,
    /// collinear and intersecting consecutive axes all occur, the rest fully skew.
    #[test]
    fn random_arms_agree_with_urdf_fk() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let path = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/inline.urdf"));
        let (mut dp, mut dr) = (0.0f64, 0.0f64);
        for case in 0..200 {
            let aligned = case % 2 == 0;
            let mut s = String::from("<robot name=\"r\"><link name=\"l0\"/>");
            for i in 1..=7 {
                let mut xyz = [0.0; 3];
                let mut rpy = [0.0; 3];
                let mut axis = [0.0; 3];
                if aligned {
                    for v in &mut xyz {
                        *v = [0.0, 0.0, 0.3, -0.2][rng.random_range(0..4)];
                    }
                    for v in &mut rpy {
                        *v = std::f64::consts::FRAC_PI_2 * rng.random_range(-2..=2) as f64;
                    }
                    axis[rng.random_range(0..3)] = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
                } else {
                    for v in xyz.iter_mut().chain(&mut axis) {
                        *v = rng.random_range(-0.5..0.5);
                    }
                    for v in &mut rpy {
                        *v = rng.random_range(-3.0..3.0);
                    }
                }
                let kind = if i == 7 { "fixed" } else { "revolute" };
                s += &format!(
                    "<link name=\"l{i}\"/><joint name=\"j{i}\" type=\"{kind}\"><parent link=\"l{}\"/>\
                     <child link=\"l{i}\"/><origin xyz=\"{} {} {}\" rpy=\"{} {} {}\"/>\
                     <axis xyz=\"{} {} {}\"/><limit lower=\"-3\" upper=\"3\" velocity=\"1\"/></joint>",
                    i - 1,
                    xyz[0],
                    xyz[1],
                    xyz[2],
                    rpy[0],
                    rpy[1],
                    rpy[2],
                    axis[0],
                    axis[1],
                    axis[2]
                );
            }
            s += "</robot>";
            let robot = from_str(&s, path, &LoadOptions::default()).expect(&s);
            let doc = urdf_rs::read_from_string(&s).unwrap();
            for _ in 0..50 {
                let q = random_q(&robot, &mut rng);
                let by_name: HashMap<&str, f64> = robot
                    .joints
                    .iter()
                    .zip(q)
                    .map(|(j, v)| (j.name.as_str(), v))
                    .collect();
                let (p, r) = diff(&urdf_fk(&doc, "l7", &by_name).unwrap(), &robot.fk(&q));
                assert!(p < 1e-9 && r < 1e-9, "case {case}: {p:e} m, {r:e}\n{s}");
                (dp, dr) = (dp.max(p), dr.max(r));
            }
        }
        eprintln!("random arms: max FK disagreement {dp:.3e} m, {dr:.3e} (rotation)");
    }

    #[test]
    fn package_paths_resolve_both_ways() {
        let tmp = tempfile::tempdir().unwrap();
        let pkg = tmp.path().join("pkg");
        std::fs::create_dir_all(pkg.join("meshes")).unwrap();
        std::fs::write(pkg.join("meshes/a.stl"), b"solid").unwrap();
        let want = pkg.join("meshes/a.stl");
        for dir in [tmp.path().to_path_buf(), pkg.clone()] {
            let opts = LoadOptions {
                package_paths: vec![dir],
                ..LoadOptions::default()
            };
            assert_eq!(
                resolve_mesh("package://pkg/meshes/a.stl", Path::new("/x"), &opts),
                Ok(want.clone())
            );
        }
        let none = resolve_mesh(
            "package://pkg/meshes/a.stl",
            Path::new("/x"),
            &LoadOptions::default(),
        );
        assert!(none.is_err());
        let rel = resolve_mesh("meshes/a.stl", &pkg, &LoadOptions::default());
        assert_eq!(rel, Ok(want.clone()));
        let file = resolve_mesh(
            &format!("file://{}", want.display()),
            Path::new("/x"),
            &LoadOptions::default(),
        );
        assert_eq!(file, Ok(want));
    }
}
