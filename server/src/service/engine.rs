//! The engine behind the service: loaded categories, and the conversion of
//! wire requests into engine calls and of engine results into wire bodies.

use crate::shape::{builtin, RegisterOptions, Registrar};
use crate::tools::Category;
use graspd_proto::{self as proto, StatusCode};
use nalgebra::Point3;
use std::path::Path;
use std::time::Instant;

/// A status code with its message: what every failed request is answered with.
#[derive(Clone, Debug, PartialEq)]
pub struct Status {
    pub code: StatusCode,
    pub message: String,
}

impl Status {
    pub fn new(code: StatusCode, message: impl Into<String>) -> Self {
        Self { code, message: message.into() }
    }
    pub fn invalid(message: impl Into<String>) -> Self {
        Self::new(StatusCode::InvalidArgument, message)
    }
}

/// Whether this build serves Grasp. The hand grasp transfer (registration →
/// demonstration transfer → grasp → pre-grasp) is not part of the engine yet,
/// so Grasp is answered FAILED_PRECONDITION rather than with made-up results.
pub const GRASP_AVAILABLE: bool = false;
pub const GRASP_UNAVAILABLE_MESSAGE: &str = "grasp not available in this build";

pub struct LoadedCategory {
    pub category: Category,
    pub registrar: Registrar,
    pub info: proto::CategoryInfo,
}

pub struct Engine {
    pub categories: Vec<LoadedCategory>,
}

#[derive(Debug, thiserror::Error)]
pub enum EngineError {
    #[error("category {name}: {reason}")]
    Category { name: String, reason: String },
}

impl Engine {
    /// Loads (or builds and caches) the shape space of every category; returns
    /// the load time of each, milliseconds.
    pub fn load(names: &[String], cache_dir: &Path) -> Result<(Engine, Vec<(String, f64)>), EngineError> {
        let mut categories = Vec::new();
        let mut times = Vec::new();
        for name in names {
            let t0 = Instant::now();
            let err = |reason: String| EngineError::Category { name: name.clone(), reason };
            let category: Category = name.parse().map_err(|e: crate::tools::ToolsError| err(e.to_string()))?;
            let space = builtin::load_or_build(category, cache_dir, |_, _| {}).map_err(|e| err(e.to_string()))?;
            if space.modes() > proto::MAX_LATENT {
                return Err(err(format!("{} latent modes; the protocol carries at most {}", space.modes(), proto::MAX_LATENT)));
            }
            if space.keypoints.len() > proto::MAX_KEYPOINTS {
                return Err(err(format!("{} keypoints; the protocol carries at most {}", space.keypoints.len(), proto::MAX_KEYPOINTS)));
            }
            let mut info = proto::CategoryInfo::zeroed();
            info.name = proto::str_to_name(category.name()).map_err(|e| err(e.to_string()))?;
            info.latent_dim = space.modes() as u32;
            info.keypoint_count = space.keypoints.len() as u32;
            for (slot, k) in info.keypoint_names.iter_mut().zip(&space.keypoints) {
                *slot = proto::str_to_text(&k.name);
            }
            info.canonical_frame = proto::str_to_text(category.canonical_frame());
            let registrar = Registrar::new(space);
            times.push((name.clone(), 1e3 * t0.elapsed().as_secs_f64()));
            categories.push(LoadedCategory { category, registrar, info });
        }
        Ok((Engine { categories }, times))
    }

    pub fn find(&self, name: &str) -> Option<usize> {
        self.categories.iter().position(|c| c.category.name() == name)
    }

    pub fn names(&self) -> Vec<&'static str> {
        self.categories.iter().map(|c| c.category.name()).collect()
    }

    /// Register: the cloud (read once from the caller's memory, converted and
    /// checked here) → latent, pose, fit, keypoints.
    pub fn register(&self, category: usize, points: &[proto::Point], header: &proto::RequestHeader) -> Result<proto::RegisterResponse, Status> {
        let c = self.categories.get(category).ok_or_else(|| Status::new(StatusCode::Internal, "category index out of range"))?;
        let cloud = convert_cloud(points)?;
        let opts = register_options(header)?;
        let reg = c.registrar.register(&cloud, &opts).map_err(|e| Status::invalid(format!("cannot register the cloud: {e}")))?;
        Ok(proto::RegisterResponse { registration: registration_to_wire(&reg, points.len()) })
    }

    /// Grasp: not served by this build (see [`GRASP_AVAILABLE`]).
    pub fn grasp(&self, _category: usize, _points: &[proto::Point], _header: &proto::RequestHeader) -> Result<proto::GraspResponse, Status> {
        Err(Status::new(StatusCode::FailedPrecondition, GRASP_UNAVAILABLE_MESSAGE))
    }
}

/// f32 wire points → f64 engine points; rejects NaN/Inf. The caller's memory
/// is read exactly once (a client writing into it meanwhile cannot make the
/// checked and the used values differ).
pub fn convert_cloud(points: &[proto::Point]) -> Result<Vec<Point3<f64>>, Status> {
    if points.is_empty() {
        return Err(Status::invalid("empty cloud"));
    }
    let mut out = Vec::with_capacity(points.len());
    for (i, p) in points.iter().enumerate() {
        let [x, y, z] = p.0;
        if !(x.is_finite() && y.is_finite() && z.is_finite()) {
            return Err(Status::invalid(format!("point {i} has a non-finite coordinate ({x}, {y}, {z})")));
        }
        out.push(Point3::new(x as f64, y as f64, z as f64));
    }
    Ok(out)
}

/// Registration options from the request header (the rest: the engine's defaults).
pub fn register_options(h: &proto::RequestHeader) -> Result<RegisterOptions, Status> {
    let [x, y, z] = h.up_in_cloud;
    if !(x.is_finite() && y.is_finite() && z.is_finite()) {
        return Err(Status::invalid(format!("up_in_cloud ({x}, {y}, {z}) is not finite")));
    }
    let n2 = (x as f64).powi(2) + (y as f64).powi(2) + (z as f64).powi(2);
    let up = if n2 == 0.0 {
        None
    } else if n2 < 1e-12 {
        return Err(Status::invalid("up_in_cloud is too short to give a direction (all zero means unknown)"));
    } else {
        Some([x as f64, y as f64, z as f64])
    };
    Ok(RegisterOptions { up, seed: h.seed, ..Default::default() })
}

pub fn registration_to_wire(reg: &crate::shape::Registration, points: usize) -> proto::Registration {
    let mut r = proto::Registration::zeroed();
    for (slot, v) in r.latent.iter_mut().zip(&reg.latent) {
        *slot = *v;
    }
    let q = reg.rotation_cloud_from_canonical.coords;
    r.rotation_cloud_from_canonical_xyzw = [q.x, q.y, q.z, q.w];
    let t = reg.translation_cloud_from_canonical;
    r.translation_cloud_from_canonical_m = [t.x, t.y, t.z];
    r.scale = reg.scale;
    r.sigma2_m2 = reg.sigma2;
    r.inlier_fraction = reg.fit.inlier_fraction;
    r.residual_m = reg.fit.residual_mm * 1e-3;
    r.inlier_threshold_m = reg.fit.inlier_mm * 1e-3;
    r.latent_dim = reg.latent.len().min(proto::MAX_LATENT) as u32;
    r.keypoint_count = reg.keypoints.len().min(proto::MAX_KEYPOINTS) as u32;
    r.confident = reg.fit.confident as u32;
    r.points = points.min(u32::MAX as usize) as u32;
    for (slot, k) in r.keypoints.iter_mut().zip(&reg.keypoints) {
        slot.name = proto::str_to_text(&k.name);
        slot.position_cloud_m = k.position;
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clouds_with_nan_inf_or_nothing_are_invalid_arguments() {
        assert_eq!(convert_cloud(&[]).unwrap_err().code, StatusCode::InvalidArgument);
        let e = convert_cloud(&[proto::Point([0.0, 0.0, 0.0]), proto::Point([f32::NAN, 0.0, 0.0])]).unwrap_err();
        assert!(e.message.contains("point 1"), "{}", e.message);
        assert!(convert_cloud(&[proto::Point([f32::INFINITY, 0.0, 0.0])]).is_err());
        assert_eq!(convert_cloud(&[proto::Point([1.0, 2.0, 3.0])]).unwrap()[0], Point3::new(1.0, 2.0, 3.0));
    }

    #[test]
    fn up_in_cloud_zero_is_unknown_and_nan_is_invalid() {
        let mut h = proto::RequestHeader::zeroed();
        assert_eq!(register_options(&h).unwrap().up, None);
        h.up_in_cloud = [0.0, 0.0, 2.0];
        assert_eq!(register_options(&h).unwrap().up, Some([0.0, 0.0, 2.0]));
        h.up_in_cloud = [f32::NAN, 0.0, 1.0];
        assert_eq!(register_options(&h).unwrap_err().code, StatusCode::InvalidArgument);
    }
}
