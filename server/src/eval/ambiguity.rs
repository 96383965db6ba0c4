//! What a view itself leaves open, whatever reads it.
//!
//! A mug seen with its handle behind its body gives the same image for every
//! turn about its axis that keeps the handle hidden. No registration can tell
//! those turns apart, so its keypoint error on such views has a floor. This
//! module finds, for one rendered view, the turns of the *true* tool about the
//! vertical line through its origin (the body's axis for the built-in
//! families) that leave the camera's clean image unchanged, and what an
//! estimator that knows the true shape and takes the middle of those turns
//! would score: the floor the eval reports beside each method's error.
//!
//! With the truth uniform over the turns a view allows (the eval draws yaw
//! uniformly), the middle of the allowed arc gives every quantile of the
//! error its least value, so no method's pooled p90 on the same views is
//! lower in expectation. Two approximations, both about a degree at an
//! arc's edge: images are compared without depth noise (which only helps
//! the estimator), and a turn counts as seen once more than [`SEEN_PIXELS`]
//! pixels in patches change by more than [`DEPTH_TOLERANCE_M`] (a handle
//! peeking a third of a pixel column past the body's edge passes unseen).
//! Shape is taken as known, so the floor leaves out every other error.

use crate::geometry::camera::{DepthCamera, DepthNoise, Scene};
use nalgebra::{Isometry3, UnitQuaternion, Vector3};

/// Depth change (m) that counts as a different image: about twice the
/// default camera's noise at half a metre (σ = 1 mm + 1.2e-3·z²).
pub const DEPTH_TOLERANCE_M: f64 = 0.003;

/// More changed pixels (in patches, see `changed_pixels`) than this make a
/// turn seen. A handle 6 cm tall peeking one pixel column out from behind
/// the body changes some 60.
pub const SEEN_PIXELS: usize = 20;

/// The turns (radians, `lo ≤ 0 ≤ hi`) of the tool about the vertical line
/// through its origin that change at most [`SEEN_PIXELS`] pixels (in
/// patches) of `camera`'s clean image of `scene`, found in 4° steps and
/// refined to 0.5° at each end; capped at half a turn either way. None
/// when the scene cannot be rendered.
pub fn unseen_turns(camera: &DepthCamera, scene: &mut Scene, world_from_tool: Isometry3<f64>) -> Option<(f64, f64)> {
    let clean = DepthCamera { noise: DepthNoise::NONE, ..camera.clone() };
    let width = clean.intrinsics.width as usize;
    let image = |scene: &Scene| -> Option<Vec<(usize, f64)>> {
        let view = clean.capture(scene, 0).ok()?;
        let mut px: Vec<(usize, f64)> = view
            .pixels
            .iter()
            .zip(&view.points_camera)
            .map(|([u, v], p)| (*v as usize * width + *u as usize, p.z))
            .collect();
        px.sort_unstable_by_key(|p| p.0);
        Some(px)
    };
    let truth = image(scene)?;
    let turned = |scene: &mut Scene, angle: f64| {
        let r = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), angle) * world_from_tool.rotation;
        scene.place(Isometry3::from_parts(world_from_tool.translation, r));
        image(scene).is_none_or(|img| changed_pixels(&truth, &img, width) > SEEN_PIXELS)
    };
    let (step, limit) = (4f64.to_radians(), std::f64::consts::PI);
    let mut ends = [0.0; 2];
    for (end, sign) in ends.iter_mut().zip([-1.0, 1.0]) {
        // The last unseen turn and the first seen one, outward from the truth.
        let (mut unseen, mut seen) = (0.0, None);
        while unseen + step <= limit + 1e-9 {
            if turned(scene, sign * (unseen + step)) {
                seen = Some(unseen + step);
                break;
            }
            unseen += step;
        }
        if let Some(mut seen) = seen {
            for _ in 0..3 {
                let mid = (unseen + seen) / 2.0;
                if turned(scene, sign * mid) {
                    seen = mid;
                } else {
                    unseen = mid;
                }
            }
        }
        *end = sign * unseen;
    }
    scene.place(world_from_tool);
    Some((ends[0], ends[1]))
}

/// Changed pixels that lie in a patch of change: in one image and not the
/// other, or in both with depths further apart than [`DEPTH_TOLERANCE_M`],
/// and with at least two of their eight neighbours changed too. Turning a
/// faceted body of revolution flips scattered single pixels along its
/// silhouette and rim (5-35 on a built-in mug at half a metre, by the
/// facets' phase); a handle coming into view changes a connected band.
/// Both images sorted by pixel index (a merge: an image is a few thousand
/// pixels of a 300,000-pixel sensor).
fn changed_pixels(a: &[(usize, f64)], b: &[(usize, f64)], width: usize) -> usize {
    let (mut i, mut j) = (0, 0);
    let mut changed = Vec::new();
    while i < a.len() || j < b.len() {
        let (pa, pb) = (a.get(i).map_or(usize::MAX, |p| p.0), b.get(j).map_or(usize::MAX, |p| p.0));
        if pa < pb {
            changed.push(pa);
            i += 1;
        } else if pb < pa {
            changed.push(pb);
            j += 1;
        } else {
            if (a[i].1 - b[j].1).abs() > DEPTH_TOLERANCE_M {
                changed.push(pa);
            }
            (i, j) = (i + 1, j + 1);
        }
    }
    let is_changed = |p: usize| changed.binary_search(&p).is_ok();
    let w = width as isize;
    changed
        .iter()
        .filter(|&&p| {
            let neighbours = [-w - 1, -w, -w + 1, -1, 1, w - 1, w, w + 1];
            neighbours.iter().filter(|&&d| p.checked_add_signed(d).is_some_and(is_changed)).count() >= 2
        })
        .count()
}

/// Distance (m) a point at `radius` from the turning axis moves when turned by `angle`.
pub fn chord(radius: f64, angle: f64) -> f64 {
    2.0 * radius * (angle.abs() / 2.0).min(std::f64::consts::FRAC_PI_2).sin()
}

/// The floor's keypoint errors (mm) for one view: the truth uniform over the
/// unseen turns `(lo, hi)`, the estimate their middle; `samples` turns per
/// keypoint, evenly spread over the half width (each view weighs the same).
pub fn floor_errors_mm(radii_m: &[f64], (lo, hi): (f64, f64), samples: usize) -> Vec<f64> {
    let half = (hi - lo) / 2.0;
    let samples = samples.max(1);
    radii_m
        .iter()
        .flat_map(|&r| (0..samples).map(move |j| 1e3 * chord(r, half * (j as f64 + 0.5) / samples as f64)))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::camera::{look_at, Intrinsics};
    use crate::tools::{instance, Category};
    use nalgebra::{Point3, Translation3};

    fn camera_at(eye: Point3<f64>, target: Point3<f64>) -> DepthCamera {
        DepthCamera {
            intrinsics: Intrinsics::default(),
            world_from_camera: look_at(eye, target, Vector3::z()).unwrap(),
            noise: DepthNoise::default(),
        }
    }

    #[test]
    fn a_mug_with_its_handle_behind_its_body_can_turn_unseen_and_one_with_it_in_view_cannot() {
        let mug = instance(Category::Mug, "mug_test_00").unwrap();
        let target = Point3::new(0.0, 0.0, 0.05);
        // The handle points along the canonical +x (the mug family's frame).
        let handle = mug.keypoint("handle_middle").expect("a mug has a handle").position;
        let yaw_to_handle = handle[1].atan2(handle[0]);
        let place = |yaw: f64| {
            Isometry3::from_parts(Translation3::identity(), UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw))
        };
        // Camera low on −x: the handle turned to +x sits behind the body.
        let camera = camera_at(Point3::new(-0.5, 0.0, 0.15), target);
        let hidden = place(-yaw_to_handle);
        let mut scene = Scene::new(&mug.mesh, hidden, Some(0.0)).unwrap();
        let (lo, hi) = unseen_turns(&camera, &mut scene, hidden).unwrap();
        assert!(
            lo < -5f64.to_radians() && hi > 5f64.to_radians(),
            "hidden handle: {:.1}..{:.1}°",
            lo.to_degrees(),
            hi.to_degrees()
        );
        assert!(
            hi - lo < 120f64.to_radians(),
            "the handle shows again well before half a turn: {:.1}..{:.1}°",
            lo.to_degrees(),
            hi.to_degrees()
        );
        // The handle side-on to the camera: a turn of a degree or two moves
        // it along the line of sight by less than the depth tolerance, no more.
        let side_on = place(std::f64::consts::FRAC_PI_2 - yaw_to_handle);
        scene.place(side_on);
        let (lo, hi) = unseen_turns(&camera, &mut scene, side_on).unwrap();
        assert!(hi - lo <= 4f64.to_radians(), "handle in view: {:.1}..{:.1}°", lo.to_degrees(), hi.to_degrees());
    }

    #[test]
    fn scattered_flipped_pixels_are_not_a_change_and_a_band_is() {
        let width = 100;
        let image = |px: &[usize]| px.iter().map(|&p| (p, 0.5)).collect::<Vec<_>>();
        let base: Vec<usize> = (0..50).flat_map(|v| (20..60).map(move |u| v * width + u)).collect();
        // Every tenth pixel of the silhouette's left column flipped off.
        let flicker: Vec<usize> =
            base.iter().copied().filter(|p| !(p % width == 20 && (p / width) % 10 == 0)).collect();
        assert_eq!(changed_pixels(&image(&base), &image(&flicker), width), 0);
        // A column one pixel wide and 30 tall appears beside the right edge.
        let mut band = base.clone();
        band.extend((10..40).map(|v| v * width + 60));
        band.sort_unstable();
        assert_eq!(changed_pixels(&image(&base), &image(&band), width), 28);
        // A depth change counts as a change.
        let mut moved = image(&base);
        moved.iter_mut().filter(|(p, _)| p / width < 5).for_each(|(_, d)| *d += 0.01);
        assert_eq!(changed_pixels(&image(&base), &moved, width), 5 * 40);
    }

    #[test]
    fn the_floor_grows_with_the_arc_and_the_keypoints_distance_from_the_axis() {
        assert_eq!(floor_errors_mm(&[0.05], (0.0, 0.0), 4), vec![0.0; 4]);
        let narrow: f64 = floor_errors_mm(&[0.05], (-0.2, 0.2), 8).iter().sum();
        let wide: f64 = floor_errors_mm(&[0.05], (-0.6, 0.2), 8).iter().sum();
        let far: f64 = floor_errors_mm(&[0.10], (-0.2, 0.2), 8).iter().sum();
        assert!(wide > narrow && (far - 2.0 * narrow).abs() < 1e-9);
        // Half a turn moves a point by its diameter, no more.
        assert!((chord(0.05, 4.0) - 0.1).abs() < 1e-12);
    }
}
