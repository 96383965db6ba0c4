//! Category shape space (paper §II-A): the canonical instance's deformation
//! fields onto the training instances, reduced by PCA to q latent modes.
//!
//! W(ℓ) = mean + Σ_j ℓ_j·mode_j gives kernel weights for the canonical
//! centres C, and v(z) = G(z, C)·W(ℓ) moves ANY canonical point z: model
//! points, the dense completed shape, the demonstration's keypoints.
//! All stored geometry is in the canonical frame of the category; the kernel
//! acts in coordinates normalised by the canonical's centroid and RMS radius.

use super::cpd::{self, to_p3, EmOptions, NonRigidOptions, Normalization, RigidOptions};
use super::estep::P3;
use super::kernel::{gaussian, LowRankKernel};
use crate::geometry::{sample_points_even, TriMesh};
use crate::simd::clear_upper_state;
use faer::prelude::*;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::time::Instant;

/// Artefact format version; bump on any change of the stored fields'
/// meaning, or of the build's numerics, so that cached builds are redone
/// (4: the kernel factor by pivoted Cholesky, the CPD's E-step in single
/// precision and its M-step's Q in f32: values move in the sixth digit;
/// 5: the M-step's products fused on AVX2 and AVX-512, last-bit changes;
/// 6: the fingerprint of the build's inputs, `source`).
pub const FORMAT_VERSION: u32 = 6;
const MAGIC: &[u8; 8] = b"GRSPSPC\0";

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct NamedPoint {
    pub name: String,
    pub position: [f64; 3],
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ShapeSpace {
    pub category: String,
    pub norm: Normalization,
    /// Kernel centres C (normalised canonical coordinates), M points.
    pub centres: Vec<P3>,
    /// Kernel width, normalised units.
    pub beta: f64,
    pub lambda: f64,
    /// Mean of the flattened W_i (3M, row-major m·3 + d).
    pub mean: Vec<f64>,
    /// q modes of W (each 3M); mode j moves the centres by a unit-norm
    /// displacement G·mode_j, so ℓ_j is in normalised displacement units.
    pub modes: Vec<Vec<f64>>,
    /// Variance of the training latents along each mode (the prior of ℓ).
    pub variances: Vec<f64>,
    /// Cumulative explained variance fraction after each kept mode.
    pub explained_variance: Vec<f64>,
    /// Dense canonical surface samples (canonical frame, metres): the shape completed by a fit.
    pub surface: Vec<P3>,
    /// Outward unit normals of `surface` (for visibility from a viewpoint).
    pub surface_normals: Vec<P3>,
    /// Semantic keypoints of the canonical instance (canonical frame).
    pub keypoints: Vec<NamedPoint>,
    /// Names of the training instances, in the order of `train_latents`.
    pub instances: Vec<String>,
    /// The options it was built with (a cache built with other options is rebuilt).
    pub build: BuildOptions,
    /// Keypoints used as landmark correspondences in the build (0: surfaces only).
    pub landmarks: usize,
    /// Latent of each training instance (projection of its W_i).
    pub train_latents: Vec<Vec<f64>>,
    /// Fingerprint of what it was built from ([`source_fingerprint`]): a
    /// cached space whose family has changed since is rebuilt, not served.
    pub source: u64,
}

/// A fit whose smallest Jacobian determinant over the canonical surface is
/// at most this is a fold (or close to one: a part squeezed flat).
const FOLD_MARGIN: f64 = 0.05;
/// Stiffer refits (λ × 4 each) of a folding fit before it is kept as it is.
const FOLD_REFITS: usize = 2;

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct BuildOptions {
    /// Kernel centres sampled on the canonical.
    pub centres: usize,
    /// Points sampled on each training instance.
    pub instance_points: usize,
    pub surface_points: usize,
    /// Keep modes until this fraction of the variance is explained.
    pub explained: f64,
    pub max_modes: usize,
    /// Rigidly pre-align each instance to the canonical first. Off for meshes
    /// already in the category's canonical frame (the built-in families): on a
    /// near-symmetric tool (a mug) a rigid fit may turn the instance about its
    /// axis, and the latent would then describe a turned instance.
    pub prealign: bool,
    pub cpd: NonRigidOptions,
    /// Weight of each semantic keypoint of an annotated training instance as a
    /// landmark of its CPD fit, in units of the observations per centre
    /// (instance_points / centres); 0 ignores annotations. CPD alone matches
    /// surfaces and lets the canonical slide along them, so a transferred
    /// keypoint lands a few millimetres off its meaning (measured: 3.3 mm
    /// median on full training surfaces); landmarks pin what is known.
    pub landmark_weight: f64,
    pub seed: u64,
}

impl Default for BuildOptions {
    fn default() -> Self {
        Self {
            centres: 400,
            instance_points: 1600,
            surface_points: 3000,
            // 0.9999 keeps every mode 10 training instances give (9; the
            // wire carries up to `graspd_proto::MAX_LATENT`, 16 since protocol
            // 2; 0.995 kept 7 / 7 / 5 for mug / drill / hammer). The small
            // modes carry what tells tools apart at their keypoints: whole
            // test surfaces (eval transfer --full-surface, seed 7, all 9
            // modes) hammer keypoint median 2.27 -> 1.56 mm, drill 1.89 ->
            // 1.81, mug 1.56 either way; the latent's prior keeps them small
            // where a view says little. The 9th mode, which protocol 1's 8
            // slots cut, on partial views (eval transfer --views 12, test
            // median / p90 mm, seeds 7 / 11 / 23, 8 -> 9 modes, 2026-12-03):
            // drill 2.36 / 5.1, 2.41 / 5.1, 2.39 / 5.2 -> 2.24 / 4.9, 2.26 /
            // 4.8, 2.28 / 5.0; hammer 2.05 / 3.8, 1.85 / 3.6, 2.02 / 4.1 ->
            // 2.07 / 4.0, 1.86 / 3.5, 1.99 / 3.9.
            //
            // Since 2026-12-06 the space learns from 20 draws (the 10 training
            // tools and 10 shape-space-only ones), which give up to 19 modes;
            // 12 at most are kept (the built-in mug and hammer keep 9:
            // `builtin::options`). Test median / p90 mm (eval transfer --views 12,
            // means of seeds 7 / 11 / 23) with 9 / 12 / 16 modes: drill 1.86 /
            // 4.79, 1.63 / 4.19, 1.57 / 3.83; mug 1.72 / 8.68, 1.70 / 8.73,
            // 1.67 / 8.87; hammer 1.54 / 3.45, 1.51 / 3.43, 1.54 / 3.47 (on a
            // first draw of its extra instances; with the final one, 9 and 12
            // modes: 1.47 / 3.37, 1.45 / 3.41).
            // Registration p50 (bench_register, known viewpoint) mug 6.45 /
            // 6.79 / 7.4 ms, drill 5.4 / 5.7 / 6.2 (10 draws, 9 modes: 6.67,
            // 5.2): modes past 12 cost 0.6 ms for what only the drill gains.
            explained: 0.9999,
            max_modes: 12,
            prealign: false,
            // λ = 20 (was 3): the softer fields folded 7 of 10 hammers (handles
            // mirrored across their own plane) and squeezed mug walls flat.
            // Measured (eval transfer --views 8, test median / p90 mm; Table I cm):
            // hammer 4.2 / 8.7 -> 2.8 / 5.5, Table I 1.02 -> 0.29; drill 2.9 / 4.8
            // -> 2.8 / 5.1; mug 4.4 / 33.4 -> 4.1 / 16.5. β 1.5-2 was as good on
            // hammers, worse on mugs' unambiguous views.
            cpd: NonRigidOptions {
                beta: 1.0,
                lambda: 20.0,
                max_rank: 200,
                em: EmOptions { w: 0.0, max_iters: 100, tol: 1e-5 },
                ..Default::default()
            },
            landmark_weight: 5.0,
            seed: 1,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum SpaceError {
    #[error("shape space needs at least 2 training instances, got {0}")]
    TooFewInstances(usize),
    #[error("sampling {what}: {source}")]
    Sample { what: String, source: crate::geometry::sample::SampleError },
    #[error("registering the canonical to {instance}: {source}")]
    Cpd { instance: String, source: cpd::CpdError },
    #[error("PCA failed: {0}")]
    Pca(String),
    #[error("{path}: {reason}")]
    Artefact { path: String, reason: String },
}

/// One training instance: its mesh (the category's canonical frame, metres)
/// and its semantic keypoints when annotated (matched to the canonical's by name).
#[derive(Clone, Debug)]
pub struct TrainingShape {
    pub name: String,
    pub mesh: TriMesh,
    pub keypoints: Vec<NamedPoint>,
}

/// Report of a build, for the CLI.
#[derive(Clone, Debug, Serialize)]
pub struct BuildReport {
    pub category: String,
    pub instances: usize,
    pub points: usize,
    pub modes: usize,
    pub explained_variance: Vec<f64>,
    pub kernel_rank: usize,
    /// Canonical keypoints used as landmarks (0: none of the instances is annotated).
    pub landmarks: usize,
    pub mean_fit_residual_mm: f64,
    /// Smallest Jacobian determinant of the deformation over the canonical
    /// surface, at each training latent; ≤ 0 is a fold (a part turned inside out).
    pub min_jacobian_determinant: Vec<f64>,
    /// Instances whose first fit folded and were refitted with a larger λ.
    pub stiffened: Vec<String>,
    pub build_s: f64,
}

impl ShapeSpace {
    pub fn modes(&self) -> usize {
        self.modes.len()
    }

    /// Builds the space from the canonical mesh and the training meshes (all in
    /// the category's canonical frame, metres). `progress` is called after each instance.
    pub fn build(
        category: &str,
        canonical: &TriMesh,
        canonical_keypoints: Vec<NamedPoint>,
        training: &[TrainingShape],
        opts: &BuildOptions,
        progress: impl Fn(usize, usize) + Sync,
    ) -> Result<(Self, BuildReport), SpaceError> {
        let t0 = Instant::now();
        if training.len() < 2 {
            return Err(SpaceError::TooFewInstances(training.len()));
        }
        // Evenly spread samples on both sides: CPD follows point density, and
        // random samples' density noise makes the canonical slide along the
        // surface (measured: 10 mm median keypoint drift, 3.3 mm when even).
        let sample = |m: &TriMesh, n, seed, what: &str| {
            sample_points_even(m, n, seed)
                .map(|p| to_p3(&p))
                .map_err(|source| SpaceError::Sample { what: what.to_string(), source })
        };
        let mut c = sample(canonical, opts.centres, opts.seed, "canonical")?;
        // Canonical keypoints that some training instance also names become centres, pinned by landmarks.
        let landmark_kp: Vec<&NamedPoint> = if opts.landmark_weight > 0.0 {
            canonical_keypoints
                .iter()
                .filter(|k| training.iter().any(|t| t.keypoints.iter().any(|tk| tk.name == k.name)))
                .collect()
        } else {
            Vec::new()
        };
        let first_landmark = c.len();
        c.extend(landmark_kp.iter().map(|k| k.position));
        let surface_samples = crate::geometry::SurfaceSampler::new(canonical)
            .and_then(|s| s.sample(opts.surface_points, opts.seed + 1))
            .map_err(|source| SpaceError::Sample { what: "canonical surface".into(), source })?;
        let surface: Vec<P3> = surface_samples.iter().map(|s| [s.position.x, s.position.y, s.position.z]).collect();
        let surface_normals: Vec<P3> = surface_samples.iter().map(|s| [s.normal.x, s.normal.y, s.normal.z]).collect();
        let norm = Normalization::of(&c);
        let y0: Vec<P3> = c.iter().map(|p| norm.forward(p)).collect();
        let kernel = LowRankKernel::new(&y0, opts.cpd.beta, opts.cpd.max_rank, opts.cpd.rank_tol);
        let c_pts = cpd::to_points(&c);
        let m = c.len();
        let folds = cpd::JacobianKernel::new(norm, &y0, opts.cpd.beta, &surface);
        // Each instance independently (in parallel: the fits share only the kernel factor
        // and the fold check's Gaussians).
        let done = std::sync::atomic::AtomicUsize::new(0);
        // Per instance: flattened W, flattened G·W (the displacements), residual σ in mm, stiffened.
        type InstanceFit = Result<(Vec<f64>, Vec<f64>, f64, bool), SpaceError>;
        let fits: Vec<InstanceFit> = training
            .par_iter()
            .enumerate()
            .map(|(i, shape)| {
                let name = &shape.name;
                let x = cpd::to_points(&sample(&shape.mesh, opts.instance_points, opts.seed + 10 + i as u64, name)?);
                let mut landmarks: Vec<cpd::Landmark> = landmark_kp
                    .iter()
                    .enumerate()
                    .filter_map(|(j, k)| {
                        let t = shape.keypoints.iter().find(|tk| tk.name == k.name)?;
                        Some(cpd::Landmark { source: first_landmark + j, target: t.position })
                    })
                    .collect();
                let x = if opts.prealign {
                    let fit = cpd::rigid(
                        &x,
                        &c_pts,
                        &RigidOptions { em: EmOptions { w: 0.0, max_iters: 60, tol: 1e-6 }, scale: false },
                    )
                    .map_err(|source| SpaceError::Cpd { instance: name.clone(), source })?;
                    for l in &mut landmarks {
                        let p = fit.scale * (fit.rotation * nalgebra::Vector3::from(l.target)) + fit.translation;
                        l.target = [p.x, p.y, p.z];
                    }
                    fit.moved
                } else {
                    x
                };
                let weight = opts.landmark_weight * opts.instance_points as f64 / m as f64;
                let fit = |cpd_opts: &NonRigidOptions| {
                    cpd::non_rigid_with_landmarks(&y0, norm, &kernel, &x, &landmarks, weight, cpd_opts)
                        .map_err(|source| SpaceError::Cpd { instance: name.clone(), source })
                };
                // A fit that folds (see `DeformationField::jacobian_determinants`)
                // is refitted stiffer: landmarks far apart on a thin part can pull
                // a soft field through itself.
                let mut cpd_opts = opts.cpd;
                let mut res = fit(&cpd_opts)?;
                let mut stiffened = false;
                for _ in 0..FOLD_REFITS {
                    let det = folds.min_determinant(&res.field.weights);
                    if det > FOLD_MARGIN {
                        break;
                    }
                    cpd_opts.lambda *= 4.0;
                    stiffened = true;
                    tracing::warn!(
                        "{name}: the fit folds (min det J {det:.2}); refitting with λ = {}",
                        cpd_opts.lambda
                    );
                    res = fit(&cpd_opts)?;
                }
                let w = &res.field.weights;
                let gw = kernel.apply(w.as_ref());
                progress(done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1, training.len());
                Ok((
                    (0..m * 3).map(|k| w[(k / 3, k % 3)]).collect(),
                    (0..m * 3).map(|k| gw[(k / 3, k % 3)]).collect(),
                    res.report.sigma2.sqrt() * 1e3,
                    stiffened,
                ))
            })
            .collect();
        let mut w_rows = Vec::new();
        let mut v_rows = Vec::new();
        let mut residual_sum = 0.0;
        let mut stiffened = Vec::new();
        for (f, shape) in fits.into_iter().zip(training) {
            let (w, v, r, stiff) = f?;
            w_rows.push(w);
            v_rows.push(v);
            residual_sum += r;
            if stiff {
                stiffened.push(shape.name.clone());
            }
        }
        let pca = pca(&w_rows, &v_rows, opts.explained, opts.max_modes)?;
        let (mean, modes, variances, explained, train_latents) =
            (pca.mean_w, pca.modes_w, pca.variances, pca.explained, pca.latents);
        let space = ShapeSpace {
            category: category.to_string(),
            norm,
            centres: y0,
            beta: opts.cpd.beta,
            lambda: opts.cpd.lambda,
            mean,
            modes,
            variances,
            explained_variance: explained.clone(),
            surface,
            surface_normals,
            keypoints: canonical_keypoints.clone(),
            instances: training.iter().map(|t| t.name.clone()).collect(),
            train_latents,
            build: *opts,
            landmarks: landmark_kp.len(),
            source: source_fingerprint(canonical, &canonical_keypoints, training),
        };
        let report = BuildReport {
            category: category.to_string(),
            instances: training.len(),
            points: m,
            modes: space.modes(),
            explained_variance: explained,
            kernel_rank: kernel.rank(),
            landmarks: landmark_kp.len(),
            mean_fit_residual_mm: residual_sum / training.len() as f64,
            min_jacobian_determinant: space.training_fold_margins(),
            stiffened,
            build_s: t0.elapsed().as_secs_f64(),
        };
        Ok((space, report))
    }

    /// Kernel weights W(ℓ) (M×3) for a latent vector (missing entries are 0).
    pub fn weights(&self, latent: &[f64]) -> Mat<f64> {
        let m = self.centres.len();
        Mat::from_fn(m, 3, |i, d| {
            let k = i * 3 + d;
            self.mean[k] + self.modes.iter().zip(latent).map(|(md, l)| l * md[k]).sum::<f64>()
        })
    }

    /// The linear model of canonical points `z` (canonical frame, metres):
    /// y(ℓ) = base + basis·ℓ, in normalised coordinates.
    pub fn linear_model(&self, z: &[P3]) -> LinearModel {
        let zn: Vec<P3> = z.iter().map(|p| self.norm.forward(p)).collect();
        let g = gaussian(&zn, &self.centres, self.beta);
        let m = self.centres.len();
        let mean = Mat::from_fn(m, 3, |i, d| self.mean[i * 3 + d]);
        let gm = &g * &mean;
        clear_upper_state();
        let base: Vec<P3> =
            zn.iter().enumerate().map(|(i, p)| [p[0] + gm[(i, 0)], p[1] + gm[(i, 1)], p[2] + gm[(i, 2)]]).collect();
        let basis = self
            .modes
            .iter()
            .map(|md| {
                let mm = Mat::from_fn(m, 3, |i, d| md[i * 3 + d]);
                let b = &g * &mm;
                clear_upper_state();
                (0..zn.len()).map(|i| [b[(i, 0)], b[(i, 1)], b[(i, 2)]]).collect()
            })
            .collect();
        LinearModel::new(base, basis)
    }

    /// Canonical points moved by the deformation of `latent`, canonical frame, metres.
    pub fn deform(&self, z: &[P3], latent: &[f64]) -> Vec<P3> {
        self.linear_model(z).evaluate(latent).iter().map(|p| self.norm.inverse(p)).collect()
    }

    /// Jacobian determinant of the deformation of `latent` at canonical points
    /// `z` (canonical frame); ≤ 0 marks a fold ([`cpd::DeformationField::jacobian_determinants`]).
    pub fn jacobian_determinants(&self, z: &[P3], latent: &[f64]) -> Vec<f64> {
        self.field(latent).jacobian_determinants(z)
    }

    /// The deformation field of `latent`.
    pub fn field(&self, latent: &[f64]) -> cpd::DeformationField {
        cpd::DeformationField {
            norm: self.norm,
            centres: self.centres.clone(),
            weights: self.weights(latent),
            beta: self.beta,
        }
    }

    /// The smallest Jacobian determinant over the canonical surface samples
    /// for each training latent (see [`Self::jacobian_determinants`]).
    pub fn training_fold_margins(&self) -> Vec<f64> {
        let folds = cpd::JacobianKernel::new(self.norm, &self.centres, self.beta, &self.surface);
        self.train_latents.iter().map(|l| folds.min_determinant(&self.weights(l))).collect()
    }

    /// As `deform`, for points that may lie off the surface (a palm above a
    /// handle). The kernel field is fitted on the surface only; a few
    /// centimetres away it extrapolates (measured: a palm keypoint moved 44 mm
    /// while the fingers on the same handle moved 10). So a point follows the
    /// local similarity (rotation, scale, translation) of its nearest surface
    /// samples instead, blended with the field within 3-10 mm of the surface.
    pub fn deform_anchored(&self, z: &[P3], latent: &[f64]) -> Vec<P3> {
        self.anchored_model(z).evaluate(latent)
    }

    /// The part of [`Self::deform_anchored`] that does not depend on the
    /// latent, for points carried again and again (a category's mesh and
    /// demonstration keypoints, once per Grasp request): the Gaussian kernel
    /// against every centre and the nearest-sample search are done here once.
    pub fn anchored_model(&self, z: &[P3]) -> AnchoredModel {
        const NEAR: f64 = 0.003;
        const FAR: f64 = 0.010;
        let direct = self.linear_model(z);
        let empty = LinearModel::new(Vec::new(), Vec::new());
        let mut model = AnchoredModel {
            norm: self.norm,
            canonical: z.to_vec(),
            direct,
            anchor_points: Vec::new(),
            anchors: empty,
            off_surface: Vec::new(),
        };
        if self.surface.len() < 16 {
            return model;
        }
        let tree = crate::geometry::PointTree::new_from_slice(&self.surface);
        // The patch grows with the distance to the surface: a point 6 cm above a
        // thin handle needs a patch wide enough to pin the handle's roll, or the
        // fitted rotation swings it (measured: 13 cm off on hammers with 16 samples).
        let mut far: Vec<(usize, f64, Vec<usize>)> = Vec::new();
        for (i, p) in z.iter().enumerate() {
            let dist = tree.nearest_one::<kiddo::SquaredEuclidean>(p).distance.sqrt();
            if dist <= NEAR {
                continue;
            }
            let n = (16.0 * (1.0 + dist / 0.005).powi(2)).clamp(16.0, 400.0) as usize;
            let k = std::num::NonZero::new(n.min(self.surface.len())).expect("non-zero");
            let nbrs: Vec<usize> =
                tree.nearest_n::<kiddo::SquaredEuclidean>(p, k).iter().map(|nb| nb.item as usize).collect();
            let blend = ((dist - NEAR) / (FAR - NEAR)).clamp(0.0, 1.0);
            far.push((i, blend, nbrs));
        }
        let mut anchors: Vec<usize> = far.iter().flat_map(|(_, _, nb)| nb.iter().copied()).collect();
        anchors.sort_unstable();
        anchors.dedup();
        model.anchor_points = anchors.iter().map(|&i| self.surface[i]).collect();
        model.anchors = self.linear_model(&model.anchor_points);
        model.off_surface = far
            .into_iter()
            .map(|(point, blend, nbrs)| OffSurface {
                point,
                blend,
                neighbours: nbrs.iter().map(|i| anchors.binary_search(i).expect("anchor")).collect(),
            })
            .collect();
        model
    }

    // ------------------------------------------------------------ artefact

    /// Writes the versioned artefact: magic, version, payload length and
    /// checksum, then the payload (JSON). Written to a temporary file and renamed,
    /// so a crash never leaves a half-written artefact under the real name.
    pub fn save(&self, path: &Path) -> Result<(), SpaceError> {
        let err = |reason: String| SpaceError::Artefact { path: path.display().to_string(), reason };
        let payload = serde_json::to_vec(self).map_err(|e| err(e.to_string()))?;
        let mut bytes = Vec::with_capacity(payload.len() + 28);
        bytes.extend_from_slice(MAGIC);
        bytes.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        bytes.extend_from_slice(&(payload.len() as u64).to_le_bytes());
        bytes.extend_from_slice(&fnv1a(&payload).to_le_bytes());
        bytes.extend_from_slice(&payload);
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(|e| err(e.to_string()))?;
        }
        // A name of this writer's own: two processes building the same space
        // must not write into one temporary file.
        static COUNTER: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let n = COUNTER.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let tmp = path.with_extension(format!("tmp.{}.{n}", std::process::id()));
        std::fs::write(&tmp, &bytes).map_err(|e| err(e.to_string()))?;
        std::fs::rename(&tmp, path).map_err(|e| err(e.to_string()))
    }

    /// Loads an artefact, refusing (never half-loading) a corrupt or
    /// version-mismatched one.
    pub fn load(path: &Path) -> Result<Self, SpaceError> {
        let bytes = std::fs::read(path)
            .map_err(|e| SpaceError::Artefact { path: path.display().to_string(), reason: e.to_string() })?;
        Self::from_bytes(&bytes).map_err(|reason| SpaceError::Artefact { path: path.display().to_string(), reason })
    }

    pub fn from_bytes(bytes: &[u8]) -> Result<Self, String> {
        if bytes.len() < 28 || &bytes[..8] != MAGIC {
            return Err("not a graspd shape-space artefact (bad magic)".into());
        }
        let version = u32::from_le_bytes(bytes[8..12].try_into().expect("4 bytes"));
        if version != FORMAT_VERSION {
            return Err(format!("artefact format version {version}, this graspd reads version {FORMAT_VERSION}; rebuild it with `graspd space build`"));
        }
        let len = u64::from_le_bytes(bytes[12..20].try_into().expect("8 bytes"));
        let sum = u64::from_le_bytes(bytes[20..28].try_into().expect("8 bytes"));
        let payload = &bytes[28..];
        if payload.len() as u64 != len {
            return Err(format!("truncated or padded: payload {} bytes, header says {len}", payload.len()));
        }
        if fnv1a(payload) != sum {
            return Err("checksum mismatch: the artefact is corrupted".into());
        }
        let space: ShapeSpace = serde_json::from_slice(payload).map_err(|e| format!("payload: {e}"))?;
        space.validate()?;
        Ok(space)
    }

    fn validate(&self) -> Result<(), String> {
        let m3 = self.centres.len() * 3;
        if self.centres.is_empty() || self.mean.len() != m3 || self.modes.iter().any(|md| md.len() != m3) {
            return Err("inconsistent sizes of centres, mean and modes".into());
        }
        if self.surface_normals.len() != self.surface.len() {
            return Err("surface normals do not match the surface samples".into());
        }
        if self.variances.len() != self.modes.len() || !(self.beta > 0.0) || !(self.norm.scale > 0.0) {
            return Err("inconsistent variances, beta or normalisation".into());
        }
        let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
        if !finite(&self.mean) || !self.modes.iter().all(|m| finite(m)) || !finite(&self.variances) {
            return Err("non-finite numbers in the model".into());
        }
        Ok(())
    }
}

/// `p` moved by the similarity that best maps `src` onto `dst` (Umeyama).
fn local_similarity(src: &[P3], dst: &[P3], p: &P3) -> P3 {
    use nalgebra::{Matrix3, Vector3};
    let n = src.len() as f64;
    let ms = src.iter().fold(Vector3::zeros(), |a, q| a + Vector3::from(*q)) / n;
    let md = dst.iter().fold(Vector3::zeros(), |a, q| a + Vector3::from(*q)) / n;
    let mut cov = Matrix3::zeros();
    let mut var = 0.0;
    for (a, b) in src.iter().zip(dst) {
        let (da, db) = (Vector3::from(*a) - ms, Vector3::from(*b) - md);
        cov += db * da.transpose();
        var += da.norm_squared();
    }
    // The proper rotation maximising tr(RᵀC) (Kabsch), and the scale it
    // implies, tr(RᵀC)/var: the SVD's Σᵢ σᵢdᵢ without the SVD (a 3×3 SVD
    // per off-surface point was a fifth of a Grasp's transfer stage).
    let r = crate::shape::cpd::best_rotation(&cov);
    let scale = if var > 1e-18 { (r.transpose() * cov).trace() / var } else { 1.0 };
    let q = md + scale.clamp(0.5, 2.0) * (r * (Vector3::from(*p) - ms));
    [q.x, q.y, q.z]
}

/// Fixed canonical points carried by [`ShapeSpace::deform_anchored`]: the
/// field's linear model for all of them and, for those more than 3 mm off
/// the surface, the surface samples whose local similarity they follow
/// (blended with the field up to 10 mm). Evaluating it costs O(points ·
/// modes) plus a 3×3 SVD per off-surface point.
#[derive(Clone, Debug)]
pub struct AnchoredModel {
    norm: Normalization,
    /// The points, canonical frame, metres.
    canonical: Vec<P3>,
    direct: LinearModel,
    /// The surface samples some off-surface point follows (canonical frame)
    /// and their linear model.
    anchor_points: Vec<P3>,
    anchors: LinearModel,
    off_surface: Vec<OffSurface>,
}

#[derive(Clone, Debug)]
struct OffSurface {
    point: usize,
    /// Weight of the local similarity against the field, (0, 1].
    blend: f64,
    /// Indices into the anchors, nearest first.
    neighbours: Vec<usize>,
}

impl AnchoredModel {
    /// The points undeformed, canonical frame, metres.
    pub fn canonical(&self) -> &[P3] {
        &self.canonical
    }

    /// The points moved by the deformation of `latent`, canonical frame, metres.
    pub fn evaluate(&self, latent: &[f64]) -> Vec<P3> {
        let mut out: Vec<P3> = self.direct.evaluate(latent).iter().map(|p| self.norm.inverse(p)).collect();
        if self.off_surface.is_empty() {
            return out;
        }
        let moved: Vec<P3> = self.anchors.evaluate(latent).iter().map(|p| self.norm.inverse(p)).collect();
        let (mut src, mut dst) = (Vec::new(), Vec::new());
        for o in &self.off_surface {
            src.clear();
            dst.clear();
            src.extend(o.neighbours.iter().map(|&a| self.anchor_points[a]));
            dst.extend(o.neighbours.iter().map(|&a| moved[a]));
            let local = local_similarity(&src, &dst, &self.canonical[o.point]);
            let (d, t) = (out[o.point], o.blend);
            out[o.point] =
                [d[0] * (1.0 - t) + local[0] * t, d[1] * (1.0 - t) + local[1] * t, d[2] * (1.0 - t) + local[2] * t];
        }
        out
    }
}

/// Canonical points as an affine function of the latent, normalised coordinates.
#[derive(Clone, Debug)]
pub struct LinearModel {
    pub base: Vec<P3>,
    /// `basis[j][i]`: displacement of point i per unit of ℓ_j.
    pub basis: Vec<Vec<P3>>,
    /// The blocked E-step's order of the points, made on `base` at first use
    /// ([`crate::shape::estep::model_order`]).
    block_order: std::sync::OnceLock<Vec<usize>>,
}

impl LinearModel {
    pub fn new(base: Vec<P3>, basis: Vec<Vec<P3>>) -> Self {
        Self { base, basis, block_order: Default::default() }
    }
    /// The points in blocks of nearby ones, for `EStep::use_model_order`.
    pub fn block_order(&self) -> &[usize] {
        self.block_order.get_or_init(|| crate::shape::estep::model_order(&self.base))
    }
    pub fn len(&self) -> usize {
        self.base.len()
    }
    pub fn is_empty(&self) -> bool {
        self.base.is_empty()
    }
    pub fn evaluate(&self, latent: &[f64]) -> Vec<P3> {
        let mut out = Vec::with_capacity(self.len());
        self.evaluate_into(latent, &mut out);
        out
    }
    /// base + Σⱼ ℓⱼ basisⱼ into `out`, mode after mode (EM evaluates the
    /// model every iteration: 9 modes × 800 points on the polish level).
    /// Modes at exactly zero add nothing and are skipped: the race and the
    /// yaw sweep fit and score the mean shape, all of its modes zero.
    pub fn evaluate_into(&self, latent: &[f64], out: &mut Vec<P3>) {
        out.clear();
        out.extend_from_slice(&self.base);
        for (b, &l) in self.basis.iter().zip(latent) {
            if l != 0.0 {
                add_scaled(out.as_flattened_mut(), l, b.as_flattened());
            }
        }
    }
    /// The sub-model of the given point indices.
    pub fn select(&self, idx: &[usize]) -> LinearModel {
        LinearModel::new(
            idx.iter().map(|&i| self.base[i]).collect(),
            self.basis.iter().map(|b| idx.iter().map(|&i| b[i]).collect()).collect(),
        )
    }
}

/// out += l·b, element by element. The crate is built for baseline x86-64
/// (two-lane vectors); where the CPU has them the same loop is compiled for
/// AVX2 or AVX-512 too. Each element is one product and one sum, unfused, so
/// the result is the same bit for bit on every level.
fn add_scaled(out: &mut [f64], l: f64, b: &[f64]) {
    #[cfg(target_arch = "x86_64")]
    {
        use crate::simd::Simd;
        // SAFETY: `Simd::detect` found the features the functions are compiled for.
        match Simd::detect(Simd::Avx512) {
            Simd::Avx512 => return unsafe { add_scaled_avx512(out, l, b) },
            Simd::Avx2 => return unsafe { add_scaled_avx2(out, l, b) },
            Simd::Portable => {}
        }
    }
    add_scaled_body(out, l, b)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn add_scaled_avx512(out: &mut [f64], l: f64, b: &[f64]) {
    add_scaled_body(out, l, b)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn add_scaled_avx2(out: &mut [f64], l: f64, b: &[f64]) {
    add_scaled_body(out, l, b)
}

#[inline(always)]
fn add_scaled_body(out: &mut [f64], l: f64, b: &[f64]) {
    for (o, v) in out.iter_mut().zip(b) {
        *o += l * v;
    }
}

struct Pca {
    mean_w: Vec<f64>,
    modes_w: Vec<Vec<f64>>,
    variances: Vec<f64>,
    explained: Vec<f64>,
    latents: Vec<Vec<f64>>,
}

/// PCA of the deformations. Done on the displacements V_i = G·W_i, not on the
/// kernel weights W_i themselves: W is ill-conditioned (directions of G's small
/// eigenvalues carry large, meaningless weights), so PCA over W finds noise.
/// A displacement mode u_j = V_c·a_j / s_j (a_j a right singular vector of the
/// centred V_c) has the exact weight-space twin W_c·a_j / s_j, which is what
/// v(z) = G(z, C)·W needs to move arbitrary points.
fn pca(w_rows: &[Vec<f64>], v_rows: &[Vec<f64>], explained: f64, max_modes: usize) -> Result<Pca, SpaceError> {
    let n = w_rows.len();
    let d = w_rows[0].len();
    let mean = |rows: &[Vec<f64>]| {
        let mut m = vec![0.0; d];
        for r in rows {
            for (a, x) in m.iter_mut().zip(r) {
                *a += x / n as f64;
            }
        }
        m
    };
    let (mean_w, mean_v) = (mean(w_rows), mean(v_rows));
    let vc = Mat::from_fn(d, n, |k, i| v_rows[i][k] - mean_v[k]);
    let svd = vc.thin_svd().map_err(|e| SpaceError::Pca(format!("{e:?}")));
    clear_upper_state();
    let svd = svd?;
    let s: Vec<f64> = (0..svd.S().dim()).map(|i| svd.S().column_vector()[i]).collect();
    let total: f64 = s.iter().map(|x| x * x).sum::<f64>().max(1e-300);
    let (mut modes_w, mut variances, mut cumulative) = (Vec::new(), Vec::new(), Vec::new());
    let mut acc = 0.0;
    for (j, sj) in s.iter().enumerate() {
        if modes_w.len() >= max_modes.min(n - 1) || (acc >= explained && !modes_w.is_empty()) || *sj <= 1e-12 * s[0] {
            break;
        }
        acc += sj * sj / total;
        let a: Vec<f64> = (0..n).map(|i| svd.V()[(i, j)] / sj).collect();
        modes_w.push((0..d).map(|k| (0..n).map(|i| (w_rows[i][k] - mean_w[k]) * a[i]).sum()).collect());
        variances.push((sj * sj / (n - 1) as f64).max(1e-12));
        cumulative.push(acc);
    }
    // Latent of instance i along mode j: its displacement's projection, s_j·a_ij.
    let latents = (0..n).map(|i| (0..modes_w.len()).map(|j| svd.V()[(i, j)] * s[j]).collect()).collect();
    Ok(Pca { mean_w, modes_w, variances, explained: cumulative, latents })
}

/// FNV-1a over the canonical and training meshes (vertices, triangles) and
/// keypoints, in order: equal inputs, equal fingerprint, on every machine.
/// Hashed as it goes: the meshes are about a megabyte.
pub fn source_fingerprint(canonical: &TriMesh, canonical_keypoints: &[NamedPoint], training: &[TrainingShape]) -> u64 {
    let shape = |h: u64, name: &str, mesh: &TriMesh, keypoints: &[NamedPoint]| {
        let mut h = fnv1a_extend(fnv1a_extend(h, name.as_bytes()), &[0]);
        for v in &mesh.vertices {
            h = v.coords.iter().fold(h, |h, x| fnv1a_extend(h, &x.to_le_bytes()));
        }
        for t in &mesh.triangles {
            h = t.iter().fold(h, |h, i| fnv1a_extend(h, &i.to_le_bytes()));
        }
        for k in keypoints {
            h = fnv1a_extend(fnv1a_extend(h, k.name.as_bytes()), &[0]);
            h = k.position.iter().fold(h, |h, x| fnv1a_extend(h, &x.to_le_bytes()));
        }
        h
    };
    let h = shape(FNV1A_OFFSET, "", canonical, canonical_keypoints);
    training.iter().fold(h, |h, t| shape(h, &t.name, &t.mesh, &t.keypoints))
}

const FNV1A_OFFSET: u64 = 0xcbf29ce484222325;

/// FNV-1a, 64-bit: enough to catch corruption (not an authenticity check).
fn fnv1a(bytes: &[u8]) -> u64 {
    fnv1a_extend(FNV1A_OFFSET, bytes)
}

/// FNV-1a's state `h` carried over `bytes`.
fn fnv1a_extend(h: u64, bytes: &[u8]) -> u64 {
    bytes.iter().fold(h, |h, b| (h ^ *b as u64).wrapping_mul(0x100000001b3))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An off-surface point follows its anchors' similarity: recovered
    /// exactly from anchors moved by a known one (rotation, scale within the
    /// clamp, translation), also from a flat patch of anchors; anchors all
    /// at one point only translate it.
    #[test]
    fn an_off_surface_point_follows_its_anchors_similarity() {
        use nalgebra::{Rotation3, Vector3};
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(12);
        for case in 0..40 {
            let flat = case % 4 == 0;
            let src: Vec<P3> = (0..12)
                .map(|_| {
                    [
                        rng.random_range(-0.02..0.02),
                        rng.random_range(-0.02..0.02),
                        if flat { 0.0 } else { rng.random_range(-0.02..0.02) },
                    ]
                })
                .collect();
            let axis = Vector3::from_fn(|_, _| rng.random::<f64>() - 0.5).normalize();
            let r = Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(axis), rng.random_range(-3.0..3.0));
            let (scale, t) = (rng.random_range(0.6..1.8), Vector3::from_fn(|_, _| rng.random::<f64>() - 0.5));
            let move_ = |q: &P3| -> P3 { (scale * (r * Vector3::from(*q)) + t).into() };
            let dst: Vec<P3> = src.iter().map(move_).collect();
            let p = [0.03, -0.01, 0.04];
            let (got, want) = (local_similarity(&src, &dst, &p), move_(&p));
            let err = (Vector3::from(got) - Vector3::from(want)).norm();
            assert!(err < 1e-9, "case {case}: {got:?} vs {want:?}");
        }
        let same = vec![[0.01, 0.02, 0.03]; 5];
        let shifted: Vec<P3> = same.iter().map(|q| [q[0] + 0.1, q[1], q[2]]).collect();
        let got = local_similarity(&same, &shifted, &[0.0, 0.0, 0.0]);
        assert!((Vector3::from(got) - Vector3::new(0.1, 0.0, 0.0)).norm() < 1e-12, "{got:?}");
    }

    /// The model evaluates the same bit for bit on every vector level.
    #[test]
    fn scaled_sums_are_the_same_on_every_level() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(8);
        for n in [0, 3, 8, 31, 2400] {
            let base: Vec<f64> = (0..n).map(|_| rng.random::<f64>() - 0.5).collect();
            let b: Vec<f64> = (0..n).map(|_| rng.random::<f64>() * 0.1).collect();
            let l = rng.random::<f64>() * 3.0 - 1.5;
            let mut want = base.clone();
            add_scaled_body(&mut want, l, &b);
            let mut got = base.clone();
            add_scaled(&mut got, l, &b);
            assert_eq!(
                got.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                want.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
            );
            #[cfg(target_arch = "x86_64")]
            for level in crate::simd::Simd::available() {
                let mut got = base.clone();
                // SAFETY: `available` lists only levels this CPU runs.
                unsafe {
                    match level {
                        crate::simd::Simd::Avx512 => add_scaled_avx512(&mut got, l, &b),
                        crate::simd::Simd::Avx2 => add_scaled_avx2(&mut got, l, &b),
                        crate::simd::Simd::Portable => add_scaled_body(&mut got, l, &b),
                    }
                }
                assert_eq!(got, want, "{level:?}, n = {n}");
            }
        }
    }
}
