//! Narrowing an open yaw arc by the view's points the fitted shape leaves
//! unexplained.
//!
//! The yaw sweep scores turns by the mixture's likelihood averaged over the
//! race's 200 points of the mean shape; a handle that peeks past the body
//! (20-30 of 15,000 points) moves that average by less than the sweep's
//! margin, so the arc stays open where the image settles the turn. Once the
//! latent is fitted, the shape explains nearly every point of the view at
//! every turn of the arc but where such a part shows: counting, at each turn,
//! the points farther than [`REACH_M`] from the turned shape finds it. (With
//! the mean shape instead, 700-1,100 points of a mug far from it miss at
//! every turn and the count drifts with the turn: measured and dropped,
//! see the journal, session 49.)
//!
//! The count runs on all the view's points at 64 turns' resolution, so it
//! is made cheap: in cylindrical coordinates about the turning axis, the
//! shape's points mark, per (radius, height) cell, the azimuths they cover
//! (one bit per 5.625° bin, widened by the reach), and a view point is
//! explained at a turn when its cell's bit at its azimuth less the turn is
//! set. Turning the shape is shifting bits.

use crate::shape::estep::P3;
use nalgebra::{Unit, Vector3};

/// Azimuth bins of a turn's resolution: 5.625°, a quarter of the yaw
/// sweep's default step.
pub(super) const BINS: usize = 64;
/// A view point farther than this from the fitted shape is unexplained
/// (about twice σ at the polish's end on a mug; the box test below reaches
/// a little farther in the cells' corners).
pub(super) const REACH_M: f64 = 0.010;
/// Counts within this share of the view's points (at least
/// [`MIN_SLACK`]) of the least are as good as the least: depth noise and
/// the fitted shape's own misfit vary a few points from turn to turn.
pub(super) const SLACK_SHARE: f64 = 0.0005;
pub(super) const MIN_SLACK: usize = 3;

/// Cells of half the reach in radius and height.
const CELLS_PER_REACH: f64 = 2.0;

/// The fitted shape's azimuths per (radius, height) cell about an axis.
pub(super) struct AzimuthMasks {
    pivot: Vector3<f64>,
    axis: Vector3<f64>,
    e1: Vector3<f64>,
    e2: Vector3<f64>,
    cell: f64,
    z0: f64,
    r_cells: usize,
    z_cells: usize,
    masks: Vec<u64>,
}

impl AzimuthMasks {
    /// Masks of `shape` (posed points) about the line through `pivot` along `axis`.
    pub(super) fn new(shape: &[P3], pivot: Vector3<f64>, axis: Unit<Vector3<f64>>) -> Self {
        let axis = axis.into_inner();
        let helper = if axis.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
        let e1 = axis.cross(&helper).normalize();
        let e2 = axis.cross(&e1);
        let cell = REACH_M / CELLS_PER_REACH;
        let mut m = Self { pivot, axis, e1, e2, cell, z0: 0.0, r_cells: 0, z_cells: 0, masks: Vec::new() };
        let coords: Vec<(f64, f64, usize)> = shape.iter().map(|p| m.cylindrical(p)).collect();
        let (zmin, zmax) =
            coords.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), c| (lo.min(c.1), hi.max(c.1)));
        let rmax = coords.iter().fold(0.0f64, |a, c| a.max(c.0));
        if coords.is_empty() || !(zmax - zmin).is_finite() || !rmax.is_finite() {
            return m;
        }
        // One reach of margin around the shape, so every point a model point
        // can explain falls inside the grid.
        m.z0 = zmin - REACH_M;
        m.r_cells = ((rmax + REACH_M) / cell).ceil() as usize + 1;
        m.z_cells = ((zmax - zmin + 2.0 * REACH_M) / cell).ceil() as usize + 1;
        m.masks = vec![0u64; m.r_cells * m.z_cells];
        let reach_cells = CELLS_PER_REACH as i64;
        let bin_width = std::f64::consts::TAU / BINS as f64;
        for &(r, z, bin) in &coords {
            // The arc length within reach at this radius, in bins (all of
            // them near the axis).
            let half = (REACH_M / (r.max(1e-6) * bin_width)).ceil() as usize;
            let widened = if 2 * half + 1 >= BINS { u64::MAX } else { band(bin, half) };
            let (ir, iz) = ((r / cell) as i64, ((z - m.z0) / cell) as i64);
            for dr in -reach_cells..=reach_cells {
                for dz in -reach_cells..=reach_cells {
                    if let Some(k) = m.index(ir + dr, iz + dz) {
                        m.masks[k] |= widened;
                    }
                }
            }
        }
        m
    }

    /// For each turn of `offsets` bins (the shape turned about the axis by
    /// offset × 5.625°), how many of `view` lie out of the shape's reach.
    pub(super) fn unexplained(&self, view: &[P3], offsets: std::ops::RangeInclusive<i64>) -> Vec<usize> {
        let offsets: Vec<i64> = offsets.collect();
        let mut counts = vec![0usize; offsets.len()];
        for p in view {
            let (r, z, bin) = self.cylindrical(p);
            let mask =
                self.index((r / self.cell) as i64, ((z - self.z0) / self.cell) as i64).map_or(0, |k| self.masks[k]);
            if mask == u64::MAX {
                continue;
            }
            for (c, &o) in counts.iter_mut().zip(&offsets) {
                // Turned by o bins, the shape's bin j lies at j + o: this
                // point at `bin` meets the shape's bin `bin − o`.
                let j = (bin as i64 - o).rem_euclid(BINS as i64) as u32;
                *c += usize::from((mask >> j) & 1 == 0);
            }
        }
        counts
    }

    /// (radius, height along the axis, azimuth bin) of a point.
    fn cylindrical(&self, p: &P3) -> (f64, f64, usize) {
        let v = Vector3::from(*p) - self.pivot;
        let z = v.dot(&self.axis);
        let (x, y) = (v.dot(&self.e1), v.dot(&self.e2));
        let r = (x * x + y * y).sqrt();
        let a = y.atan2(x).rem_euclid(std::f64::consts::TAU);
        let bin = ((a / std::f64::consts::TAU * BINS as f64) as usize).min(BINS - 1);
        (r, z, bin)
    }

    fn index(&self, ir: i64, iz: i64) -> Option<usize> {
        (ir >= 0 && iz >= 0 && (ir as usize) < self.r_cells && (iz as usize) < self.z_cells)
            .then(|| iz as usize * self.r_cells + ir as usize)
    }
}

/// Bits `centre − half ..= centre + half` (cyclic) of a 64-bin mask.
fn band(centre: usize, half: usize) -> u64 {
    let width = 2 * half + 1;
    let run = if width >= 64 { u64::MAX } else { (1u64 << width) - 1 };
    run.rotate_left(((centre + BINS - half % BINS) % BINS) as u32)
}

/// Where the counts (one per turn) say the shape belongs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct Narrowed {
    /// First and last index of the run of turns within the slack of the
    /// least count.
    pub first: usize,
    pub last: usize,
    /// No turn outside the run is within the slack: the counts name one
    /// run, not the nearest of several.
    pub alone: bool,
    /// The least count: points the shape leaves unexplained at its best turns.
    pub least: usize,
    /// The least count plus the slack: a turn whose count exceeds it
    /// leaves points unexplained that the run explains.
    pub bar: usize,
}

/// Where the counts (one per turn, `zero` the index of no turn) say the
/// shape belongs: None when no turn is needed (the fit's own turn leaves
/// within the slack of the fewest points unexplained); else the run of
/// turns within the slack around the least count nearest `zero`.
pub(super) fn narrowed(counts: &[usize], zero: usize, view_points: usize) -> Option<Narrowed> {
    let least = *counts.iter().min()?;
    let slack = ((SLACK_SHARE * view_points as f64) as usize).max(MIN_SLACK);
    let kept = |i: usize| counts[i] <= least + slack;
    if kept(zero) {
        return None;
    }
    let centre = (0..counts.len()).filter(|&i| counts[i] == least).min_by_key(|&i| i.abs_diff(zero))?;
    let (mut a, mut b) = (centre, centre);
    while a > 0 && kept(a - 1) {
        a -= 1;
    }
    while b + 1 < counts.len() && kept(b + 1) {
        b += 1;
    }
    let alone = (0..counts.len()).all(|i| (a..=b).contains(&i) || !kept(i));
    Some(Narrowed { first: a, last: b, alone, least, bar: least + slack })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A cylinder's wall (radius 4 cm) with a knob at azimuth 0 (5 cm out).
    fn mug_like(knob_at: f64) -> Vec<P3> {
        let mut pts = Vec::new();
        for i in 0..96 {
            let a = i as f64 / 96.0 * std::f64::consts::TAU;
            for k in 0..10 {
                pts.push([0.04 * a.cos(), 0.04 * a.sin(), 0.01 * k as f64]);
            }
        }
        for k in 0..10 {
            pts.push([0.065 * knob_at.cos(), 0.065 * knob_at.sin(), 0.03 + 0.003 * k as f64]);
        }
        pts
    }

    #[test]
    fn a_knob_seen_at_another_azimuth_is_unexplained_until_the_shape_turns_to_it() {
        let up = Unit::new_normalize(Vector3::z());
        let masks = AzimuthMasks::new(&mug_like(0.0), Vector3::zeros(), up);
        // The view: the same shape with its knob 45° (8 bins) round.
        let view = mug_like(std::f64::consts::FRAC_PI_4);
        let counts = masks.unexplained(&view, -16..=16);
        // Unturned, the knob's ten points miss; turned 8 bins, none does;
        // the wall is explained at every turn.
        assert_eq!(counts[16], 10, "{counts:?}");
        assert_eq!(counts[16 + 8], 0, "{counts:?}");
        assert!(counts.iter().all(|&c| c <= 10), "{counts:?}");
        let n = narrowed(&counts, 16, view.len()).expect("a turn is needed");
        let (a, b) = (n.first, n.last);
        assert!(a <= 16 + 8 && 16 + 8 <= b && b - a <= 6 && n.alone, "{n:?} of {counts:?}");
        // The view the shape already explains asks for no turn.
        let counts = masks.unexplained(&mug_like(0.0), -16..=16);
        assert_eq!(narrowed(&counts, 16, view.len()), None, "{counts:?}");
    }

    /// Two runs of turns explain the view as well: the nearer is taken, and
    /// said not to be alone.
    #[test]
    fn of_two_runs_the_nearer_is_taken_and_not_alone() {
        let mut counts = vec![20; 33];
        (counts[20], counts[21], counts[5]) = (0, 1, 0);
        let n = narrowed(&counts, 16, 1000).unwrap();
        assert_eq!(n, Narrowed { first: 20, last: 21, alone: false, least: 0, bar: 3 });
        counts[5] = 20;
        assert!(narrowed(&counts, 16, 1000).unwrap().alone);
    }

    #[test]
    fn the_band_wraps_round_the_circle() {
        assert_eq!(band(0, 1), 1 | 2 | (1 << 63));
        assert_eq!(band(63, 0), 1 << 63);
        assert_eq!(band(10, 40), u64::MAX);
    }
}
