//! Free-space evidence of a depth view.
//!
//! The likelihood of CPD only asks that observed points be explained; it does
//! not mind model surface where the camera saw nothing, or saw *through*. A
//! mug turned so its handle points at the camera fits the visible body just
//! as well as the true pose when the handle is hidden in the view. With the
//! viewpoint known, a coarse range image of the observed points tells which
//! posed model points are contradicted: those facing the camera that project
//! outside the tool's silhouette, or in front of a surface seen behind them.

use super::estep::P3;
use nalgebra::Vector3;

pub struct FreeSpace {
    viewpoint: Vector3<f64>,
    /// Camera-like frame: rows are the image axes and the optical axis.
    axes: [Vector3<f64>; 3],
    origin_uv: [f64; 2],
    inv_cell: f64,
    dims: [usize; 2],
    /// Nearest observed range per cell (∞: nothing observed there). The
    /// nearest, not the farthest: a stray point behind the tool must not make
    /// the true surface look "seen through"; only when everything the camera
    /// saw in a direction lies behind a model point did it look past it.
    min_range: Vec<f64>,
    margin: f64,
}

impl FreeSpace {
    /// Range image of `cloud` seen from `viewpoint`; `margin` (m) forgives noise.
    pub fn new(cloud: &[P3], viewpoint: Vector3<f64>, margin: f64) -> Option<Self> {
        Self::with_cells(cloud, viewpoint, margin, 3.0)
    }

    /// As [`Self::new`] with cells `spacings` point spacings wide. Finer
    /// cells leave holes between samples (empty cells, which
    /// [`Self::violation_fraction`] would take for seen-through space) but
    /// span less depth on a slanted surface, so [`Self::hidden_behind_seen`]
    /// flags fewer points that the camera did see.
    pub fn with_cells(cloud: &[P3], viewpoint: Vector3<f64>, margin: f64, spacings: f64) -> Option<Self> {
        if cloud.len() < 20 {
            return None;
        }
        let n = cloud.len() as f64;
        let centroid = cloud.iter().fold(Vector3::zeros(), |a, p| a + Vector3::from(*p)) / n;
        let z = (centroid - viewpoint).try_normalize(1e-9)?;
        let helper = if z.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
        let x = z.cross(&helper).normalize();
        let y = z.cross(&x);
        let axes = [x, y, z];
        let uv: Vec<Option<([f64; 2], f64)>> =
            cloud.iter().map(|p| project(&axes, &viewpoint, p).map(|(q, r2)| (q, r2.sqrt()))).collect();
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for (q, _) in uv.iter().flatten() {
            for d in 0..2 {
                lo[d] = lo[d].min(q[d]);
                hi[d] = hi[d].max(q[d]);
            }
        }
        if !(lo[0] < hi[0] && lo[1] < hi[1]) {
            return None;
        }
        // Cells a few point spacings wide (three for `new`): holes between samples do not count as empty.
        let area = (hi[0] - lo[0]) * (hi[1] - lo[1]);
        let cell = spacings * (area / n).sqrt();
        let pad = 2.0 * cell;
        let origin_uv = [lo[0] - pad, lo[1] - pad];
        let dims =
            [((hi[0] - lo[0] + 2.0 * pad) / cell) as usize + 1, ((hi[1] - lo[1] + 2.0 * pad) / cell) as usize + 1];
        if dims[0] * dims[1] > 1 << 20 {
            return None;
        }
        let mut fs = FreeSpace {
            viewpoint,
            axes,
            origin_uv,
            inv_cell: 1.0 / cell,
            dims,
            min_range: vec![f64::INFINITY; dims[0] * dims[1]],
            margin,
        };
        for (q, r) in uv.into_iter().flatten() {
            if let Some(c) = fs.cell(q) {
                fs.min_range[c] = fs.min_range[c].min(r);
            }
        }
        Some(fs)
    }

    fn cell(&self, q: [f64; 2]) -> Option<usize> {
        // In the image, floor is truncation: bounds first (NaN fails them too).
        let i = (q[0] - self.origin_uv[0]) * self.inv_cell;
        let j = (q[1] - self.origin_uv[1]) * self.inv_cell;
        if !(i >= 0.0 && j >= 0.0 && i < self.dims[0] as f64 && j < self.dims[1] as f64) {
            return None;
        }
        Some(j as usize * self.dims[0] + i as usize)
    }

    /// Whether the camera saw a surface in front of `p`, nearer by more than
    /// `tol` along its ray: `p` is hidden behind it and cannot have produced an
    /// observation (a mug's far wall behind its near one, a handle behind the body).
    pub fn hidden_behind_seen(&self, p: &P3, tol: f64) -> bool {
        let Some((q, r2)) = project(&self.axes, &self.viewpoint, p) else { return false };
        // min_range < r − tol, on squares (ranges are positive; no square root a point).
        self.cell(q).is_some_and(|c| {
            let near = self.min_range[c] + tol;
            near * near < r2
        })
    }

    /// Fraction of camera-facing model points that the view contradicts.
    /// `normals_world` are the points' outward normals in the cloud frame.
    pub fn violation_fraction(&self, points: &[P3], normals_world: impl Iterator<Item = Vector3<f64>>) -> f64 {
        let (mut facing, mut violated) = (0usize, 0usize);
        for (p, n) in points.iter().zip(normals_world) {
            let to_camera = self.viewpoint - Vector3::from(*p);
            if n.dot(&to_camera) <= 0.0 {
                continue;
            }
            let Some((q, r2)) = project(&self.axes, &self.viewpoint, p) else { continue };
            facing += 1;
            match self.cell(q).map(|c| self.min_range[c]) {
                // Outside the silhouette: the camera would have seen this surface.
                None => violated += 1,
                Some(seen) if seen.is_infinite() => violated += 1,
                // The camera saw something farther along this ray (seen > r +
                // margin, on squares): it looked through here.
                Some(seen) if seen - self.margin > 0.0 && (seen - self.margin).powi(2) > r2 => violated += 1,
                _ => {}
            }
        }
        if facing == 0 {
            0.0
        } else {
            violated as f64 / facing as f64
        }
    }
}

/// Image coordinates of `p` and its squared range from the viewpoint; None behind the camera.
fn project(axes: &[Vector3<f64>; 3], vp: &Vector3<f64>, p: &P3) -> Option<([f64; 2], f64)> {
    let d = Vector3::from(*p) - vp;
    let z = axes[2].dot(&d);
    if z <= 1e-6 {
        return None;
    }
    Some(([axes[0].dot(&d) / z, axes[1].dot(&d) / z], d.norm_squared()))
}
