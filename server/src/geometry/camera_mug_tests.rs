//! The virtual camera on a real asset: a mug's handle is seen from the side
//! and hidden from behind (issue "Foundations", done-when list).

use super::camera::{look_at, DepthCamera, DepthNoise, Intrinsics, Scene};
use crate::tools::{self, Category, Split};
use nalgebra::{Isometry3, Point3, Vector3};

fn handle_points(eye: Point3<f64>) -> (usize, usize) {
    let mug = tools::family(Category::Mug).unwrap().into_iter().find(|i| i.split == Split::Canonical).unwrap();
    let tools::ToolParams::Mug(p) = &mug.params else { panic!("a mug has mug parameters") };
    let scene = Scene::new(&mug.mesh, Isometry3::identity(), Some(0.0)).unwrap();
    let target = Point3::new(0.0, 0.0, 0.05);
    let cam = DepthCamera {
        intrinsics: Intrinsics::default(),
        world_from_camera: look_at(eye, target, Vector3::z()).unwrap(),
        noise: DepthNoise::NONE,
    };
    let view = cam.capture(&scene, 0).unwrap();
    // The handle is the only geometry beyond the body's outer radius (plus a margin) on the +x side.
    let body_r = p.radius * 1.15 + 0.002;
    let handle = view.points_world.iter().filter(|q| q.x > body_r).count();
    (handle, view.points_world.len())
}

#[test]
fn a_mug_handle_is_seen_from_the_side_and_not_from_behind() {
    // Side view: camera on the −y side, the handle (toward +x) in profile.
    let (side, total_side) = handle_points(Point3::new(0.0, -0.45, 0.15));
    assert!(side > 200, "side view sees {side} handle points of {total_side}");
    // From behind the body (camera on −x), the body hides the handle.
    let (behind, total_behind) = handle_points(Point3::new(-0.45, 0.0, 0.06));
    assert!(total_behind > 1000, "the body itself is visible ({total_behind} points)");
    assert_eq!(behind, 0, "handle seen through the body");
}
