//! The Omni for a 3-D viewer: a URDF written from omnid's own geometry, and the transforms
//! that pose it at joint angles q (docs/MCAP.md, 3-D view). Viewers move a URDF's links from
//! `/tf`, so every joint's transform is published, as `robot_state_publisher` would.
//!
//! Frames: `world` (z up) → `omni_base` (the OpenHaptics frame: x right, y up, z toward the
//! user; a fixed +90° turn about x) → `waist` joint at the shoulder point → `yaw_link` →
//! `shoulder` → `upper_arm` → `elbow` → `lower_arm` → fixed → `stylus_tip`. The joints follow
//! the ROS driver's convention (waist = −q1, shoulder = q2, elbow = q3 − q2), so the URDF's
//! joint angles are what ROS users know.

use crate::omni::kinematics::Geometry;
use crate::ros2::msgs::{Header, Transform};
use std::f64::consts::FRAC_PI_2;

/// One joint of the chain: parent and child frames, origin (m), rotation axis (None: fixed).
struct Joint {
    name: &'static str,
    parent: &'static str,
    child: &'static str,
    xyz: [f64; 3],
    axis: Option<[f64; 3]>,
}

fn chain(g: &Geometry) -> [Joint; 5] {
    let mm = 1e-3;
    [
        Joint {
            name: "base",
            parent: "world",
            child: "omni_base",
            xyz: [0.0; 3],
            axis: None,
        },
        Joint {
            name: "waist",
            parent: "omni_base",
            child: "yaw_link",
            xyz: [0.0, g.y_offset_mm * mm, -g.z_offset_mm * mm],
            axis: Some([0.0, 1.0, 0.0]),
        },
        Joint {
            name: "shoulder",
            parent: "yaw_link",
            child: "upper_arm",
            xyz: [0.0; 3],
            axis: Some([-1.0, 0.0, 0.0]),
        },
        Joint {
            name: "elbow",
            parent: "upper_arm",
            child: "lower_arm",
            xyz: [0.0, 0.0, g.l1_mm * mm],
            axis: Some([-1.0, 0.0, 0.0]),
        },
        Joint {
            name: "tip",
            parent: "lower_arm",
            child: "stylus_tip",
            xyz: [0.0, -g.l2_mm * mm, 0.0],
            axis: None,
        },
    ]
}

/// The URDF joint angles (waist, shoulder, elbow) for OpenHaptics joint angles `q`.
pub(crate) fn urdf_angles(q: &[f64; 3]) -> [f64; 3] {
    [-q[0], q[1], q[2] - q[1]]
}

/// Quaternion (x, y, z, w) of a turn by `angle` about the unit `axis`.
fn quaternion(axis: [f64; 3], angle: f64) -> [f64; 4] {
    let (s, c) = (angle / 2.0).sin_cos();
    [axis[0] * s, axis[1] * s, axis[2] * s, c]
}

/// The transforms of every joint at `q`, stamped `stamp` (a `tf2_msgs/TFMessage`'s content).
pub(crate) fn transforms<'a>(g: &Geometry, q: &[f64; 3], header: Header<'a>) -> [Transform<'a>; 5] {
    let angles = urdf_angles(q);
    let mut out = [Transform {
        header,
        child_frame_id: "",
        translation: [0.0; 3],
        rotation: [0.0, 0.0, 0.0, 1.0],
    }; 5];
    for (i, j) in chain(g).iter().enumerate() {
        let rotation = match (i, j.axis) {
            (0, _) => quaternion([1.0, 0.0, 0.0], FRAC_PI_2),
            (_, Some(axis)) => quaternion(axis, angles[i - 1]),
            (_, None) => [0.0, 0.0, 0.0, 1.0],
        };
        out[i] = Transform {
            header: Header {
                frame_id: j.parent,
                ..header
            },
            child_frame_id: j.child,
            translation: j.xyz,
            rotation,
        };
    }
    out
}

/// The arm's URDF, links drawn as cylinders of the real lengths.
pub(crate) fn urdf(g: &Geometry) -> String {
    let (l1, l2) = (g.l1_mm * 1e-3, g.l2_mm * 1e-3);
    let mut s = String::from("<?xml version=\"1.0\"?>\n<robot name=\"phantom_omni\">\n");
    s += "  <material name=\"grey\"><color rgba=\"0.6 0.6 0.65 1\"/></material>\n";
    s += "  <material name=\"blue\"><color rgba=\"0.2 0.4 0.8 1\"/></material>\n";
    s += "  <link name=\"world\"/>\n";
    s += &format!(
        "  <link name=\"omni_base\"><visual><origin xyz=\"0 {:.5} {:.5}\"/><geometry><box \
         size=\"0.16 0.03 0.16\"/></geometry><material name=\"grey\"/></visual></link>\n",
        g.y_offset_mm * 1e-3 - 0.07,
        -g.z_offset_mm * 1e-3
    );
    s += "  <link name=\"yaw_link\"><visual><origin xyz=\"0 -0.03 0\" rpy=\"1.5708 0 0\"/>\
          <geometry><cylinder radius=\"0.03\" length=\"0.06\"/></geometry>\
          <material name=\"grey\"/></visual></link>\n";
    s += &format!(
        "  <link name=\"upper_arm\"><visual><origin xyz=\"0 0 {:.5}\"/><geometry><cylinder \
         radius=\"0.008\" length=\"{l1:.5}\"/></geometry><material name=\"blue\"/></visual></link>\n",
        l1 / 2.0
    );
    s += &format!(
        "  <link name=\"lower_arm\"><visual><origin xyz=\"0 {:.5} 0\" rpy=\"1.5708 0 0\"/>\
         <geometry><cylinder radius=\"0.006\" length=\"{l2:.5}\"/></geometry>\
         <material name=\"blue\"/></visual></link>\n",
        -l2 / 2.0
    );
    s += "  <link name=\"stylus_tip\"><visual><geometry><sphere radius=\"0.006\"/></geometry>\
          <material name=\"grey\"/></visual></link>\n";
    for j in chain(g) {
        let (kind, axis) = match j.axis {
            Some(a) => (
                "revolute",
                format!("<axis xyz=\"{} {} {}\"/>", a[0], a[1], a[2]),
            ),
            None => ("fixed", String::new()),
        };
        let rpy = if j.name == "base" {
            "1.5708 0 0"
        } else {
            "0 0 0"
        };
        let limit = if j.axis.is_some() {
            "<limit lower=\"-3.1416\" upper=\"3.1416\" effort=\"1\" velocity=\"10\"/>"
        } else {
            ""
        };
        s += &format!(
            "  <joint name=\"{}\" type=\"{kind}\"><parent link=\"{}\"/><child link=\"{}\"/>\
             <origin xyz=\"{:.5} {:.5} {:.5}\" rpy=\"{rpy}\"/>{axis}{limit}</joint>\n",
            j.name, j.parent, j.child, j.xyz[0], j.xyz[1], j.xyz[2]
        );
    }
    s += "</robot>\n";
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ros2::msgs::Stamp;
    use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};

    /// The tip found by composing the published transforms is the tip the kinematics give
    /// (an independent path: `tip_position_mm` is the closed form of docs/DESIGN.md §4.1).
    #[test]
    fn composed_transforms_put_the_tip_where_the_kinematics_do() {
        let g = Geometry::default();
        let header = Header {
            stamp: Stamp::default(),
            frame_id: "",
        };
        for q in [[0.0, 0.0, 0.0], [0.4, -0.3, 0.9], [-1.0, 0.7, -0.2]] {
            let tf = transforms(&g, &q, header);
            // Skip `world → omni_base`: the kinematics are in the OpenHaptics frame.
            let mut pose = Isometry3::identity();
            for t in &tf[1..] {
                let r = t.rotation;
                pose *= Isometry3::from_parts(
                    Translation3::from(Vector3::from(t.translation)),
                    UnitQuaternion::from_quaternion(Quaternion::new(r[3], r[0], r[1], r[2])),
                );
            }
            let tip = crate::omni::kinematics::tip_position_mm(&g, &q.into()) * 1e-3;
            let p = pose.translation.vector;
            assert!((p - tip).norm() < 1e-12, "q {q:?}: {p} vs {tip}");
        }
        // The chain the transforms name is the URDF's.
        let u = urdf(&g);
        for t in transforms(&g, &[0.0; 3], header) {
            let joint = format!(
                "<parent link=\"{}\"/><child link=\"{}\"/>",
                t.header.frame_id, t.child_frame_id
            );
            assert!(u.contains(&joint), "{joint} not in the URDF");
        }
    }
}
