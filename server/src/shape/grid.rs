//! Fixed-radius neighbour search on a uniform grid.
//!
//! The truncated E-step asks, every iteration, for all data points within
//! r = kσ of each moving point, with r changing as σ shrinks. A k-d tree's
//! radius query (kiddo's goes through a sorted nearest-n search and allocates
//! per query) cost more than the Gaussians themselves. A grid with cells no
//! smaller than r answers the same query from 27 cells, is rebuilt in O(N)
//! by a counting sort whenever r changes, and never allocates per query.

use super::estep::P3;

#[derive(Clone, Default)]
pub struct RadiusGrid {
    origin: P3,
    inv_cell: f64,
    dims: [usize; 3],
    /// Start of each cell's items in `items` (length cells + 1).
    starts: Vec<u32>,
    items: Vec<u32>,
    /// The points' coordinates in `items` order (three columns): a query
    /// scans them contiguously instead of through the indices.
    sorted: [Vec<f64>; 3],
    /// The same coordinates in single precision, relative to `origin`, with
    /// `SLACK` far-away points after the end (so an 8-wide load at any run's
    /// start stays in bounds), and `items` likewise padded: for the AVX2 search.
    sorted32: [Vec<f32>; 3],
    items_padded: Vec<u32>,
    /// Cell keys of the points, reused between builds.
    keys: Vec<u32>,
}

/// Lanes of the vector search.
const SLACK: usize = 8;

/// For each 8-bit mask, the lanes whose bits are set, first (the permutation
/// that packs the kept candidates of an 8-wide compare to the front).
#[cfg(target_arch = "x86_64")]
static PACK: [[u32; 8]; 256] = {
    let mut table = [[0u32; 8]; 256];
    let mut m = 0;
    while m < 256 {
        let (mut k, mut lane) = (0, 0);
        while lane < 8 {
            if m & (1 << lane) != 0 {
                table[m][k] = lane as u32;
                k += 1;
            }
            lane += 1;
        }
        m += 1;
    }
    table
};

/// Most cells a grid may have (memory bound); coarser cells are still correct.
const MAX_CELLS: usize = 1 << 20;

impl RadiusGrid {
    /// (Re)builds the grid over `x` for queries of radius at most `radius`.
    pub fn build(&mut self, x: &[P3], radius: f64) {
        let (lo, hi) = x.iter().fold(([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]), |(mut lo, mut hi), p| {
            for d in 0..3 {
                lo[d] = lo[d].min(p[d]);
                hi[d] = hi[d].max(p[d]);
            }
            (lo, hi)
        });
        let extent = [(hi[0] - lo[0]).max(0.0), (hi[1] - lo[1]).max(0.0), (hi[2] - lo[2]).max(0.0)];
        let mut cell = radius.max(1e-12);
        let dims = loop {
            let dims = extent.map(|e| (e / cell).floor() as usize + 1);
            if dims.iter().product::<usize>() <= MAX_CELLS {
                break dims;
            }
            cell *= 1.5;
        };
        self.origin = lo;
        self.inv_cell = 1.0 / cell;
        self.dims = dims;
        let cells = dims.iter().product::<usize>();
        self.starts.clear();
        self.starts.resize(cells + 1, 0);
        self.keys.clear();
        for p in x {
            let c = self.cell_of(p);
            let key = (c[0] + dims[0] * (c[1] + dims[1] * c[2])) as u32;
            self.keys.push(key);
            self.starts[key as usize + 1] += 1;
        }
        for i in 0..cells {
            self.starts[i + 1] += self.starts[i];
        }
        self.items.clear();
        self.items.resize(x.len(), 0);
        let mut fill = self.starts.clone();
        for (i, &k) in self.keys.iter().enumerate() {
            self.items[fill[k as usize] as usize] = i as u32;
            fill[k as usize] += 1;
        }
        for (d, col) in self.sorted.iter_mut().enumerate() {
            col.clear();
            col.extend(self.items.iter().map(|&i| x[i as usize][d]));
        }
        for (d, col) in self.sorted32.iter_mut().enumerate() {
            col.clear();
            col.extend(self.sorted[d].iter().map(|&v| (v - lo[d]) as f32));
            col.extend([f32::MAX; SLACK]);
        }
        self.items_padded.clear();
        self.items_padded.extend_from_slice(&self.items);
        self.items_padded.extend([0; SLACK]);
    }

    fn cell_of(&self, p: &P3) -> [usize; 3] {
        let mut c = [0usize; 3];
        for d in 0..3 {
            let f = floor((p[d] - self.origin[d]) * self.inv_cell);
            c[d] = f.clamp(0.0, (self.dims[d] - 1) as f64) as usize;
        }
        c
    }

    /// The runs of `items` (and `sorted`) that hold the points of the 27
    /// cells around `q`: one run per row of three cells, at most nine.
    #[inline]
    fn runs_around(&self, q: &P3) -> ([(usize, usize); 9], usize) {
        let mut runs = [(0, 0); 9];
        let mut lo = [0usize; 3];
        let mut hi = [0usize; 3];
        for d in 0..3 {
            let c = floor((q[d] - self.origin[d]) * self.inv_cell);
            let (a, b) = (c - 1.0, c + 1.0);
            if b < 0.0 || a > (self.dims[d] - 1) as f64 {
                return (runs, 0);
            }
            lo[d] = a.max(0.0) as usize;
            hi[d] = b.min((self.dims[d] - 1) as f64) as usize;
        }
        let mut k = 0;
        for z in lo[2]..=hi[2] {
            for y in lo[1]..=hi[1] {
                let row = self.dims[0] * (y + self.dims[1] * z);
                runs[k] = (self.starts[row + lo[0]] as usize, self.starts[row + hi[0] + 1] as usize);
                k += 1;
            }
        }
        (runs, k)
    }

    /// For each query point in turn, appends to `data` the indices of the
    /// points within √`r2` of it and then `data`'s length to `starts` (the
    /// rows of a neighbour list). May list a point up to 1e-5 beyond the
    /// radius (the vector search compares in single precision, widened to
    /// never miss one); `r2` must not exceed the build radius².
    pub fn collect_rows(&self, queries: &[P3], r2: f64, allow_avx2: bool, starts: &mut Vec<u32>, data: &mut Vec<u32>) {
        #[cfg(target_arch = "x86_64")]
        {
            if allow_avx2 && std::is_x86_feature_detected!("avx2") {
                for q in queries {
                    // SAFETY: the CPU supports the features the function is compiled for.
                    unsafe { self.collect_within_avx2(q, r2, data) };
                    starts.push(data.len() as u32);
                }
                return;
            }
        }
        let _ = allow_avx2;
        for q in queries {
            self.collect_within(q, r2, data);
            starts.push(data.len() as u32);
        }
    }

    /// `collect_within`, eight candidates at a time: a compare in single
    /// precision, its mask packing the kept indices to the front of a vector
    /// (`PACK`), stored whole and advanced by the kept count. The scalar
    /// search's per-candidate work was most of a neighbour list's build,
    /// and builds cost ten E-steps over the list.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn collect_within_avx2(&self, q: &P3, r2: f64, out: &mut Vec<u32>) {
        use std::arch::x86_64::*;
        let [sx, sy, sz] = &self.sorted32;
        let items = &self.items_padded;
        let q32 = [0, 1, 2].map(|d| (q[d] - self.origin[d]) as f32);
        let (qx, qy, qz) = (_mm256_set1_ps(q32[0]), _mm256_set1_ps(q32[1]), _mm256_set1_ps(q32[2]));
        let rv = _mm256_set1_ps((r2 * (1.0 + 2e-5)) as f32);
        let lanes = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
        let (runs, count) = self.runs_around(q);
        for &(s, e) in &runs[..count] {
            let mut len = out.len();
            out.reserve(e - s + SLACK);
            let dst = out.as_mut_ptr();
            let mut p = s;
            while p < e {
                // SAFETY: p < e ≤ the points' count, and every column has SLACK
                // entries past it; `out` has room for e − s + SLACK more.
                let dx = _mm256_sub_ps(_mm256_loadu_ps(sx.as_ptr().add(p)), qx);
                let dy = _mm256_sub_ps(_mm256_loadu_ps(sy.as_ptr().add(p)), qy);
                let dz = _mm256_sub_ps(_mm256_loadu_ps(sz.as_ptr().add(p)), qz);
                let d2 =
                    _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(dx, dx), _mm256_mul_ps(dy, dy)), _mm256_mul_ps(dz, dz));
                let near = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_LE_OQ>(d2, rv));
                // Lanes past the run's end are not its candidates.
                let inside = _mm256_cmpgt_epi32(_mm256_set1_epi32((e - p) as i32), lanes);
                let mask = _mm256_movemask_ps(_mm256_castsi256_ps(_mm256_and_si256(near, inside))) as usize;
                let idx = _mm256_loadu_si256(items.as_ptr().add(p) as *const __m256i);
                let perm = _mm256_loadu_si256(PACK[mask].as_ptr() as *const __m256i);
                _mm256_storeu_si256(dst.add(len) as *mut __m256i, _mm256_permutevar8x32_epi32(idx, perm));
                len += mask.count_ones() as usize;
                p += 8;
            }
            // SAFETY: the first `len` entries are written (the kept ones packed in order).
            out.set_len(len);
        }
    }

    /// Appends to `out` the index of every point (of the set the grid was
    /// built on) within √`r2` of `q`; `r2` must not exceed the build radius².
    /// Branch-free: each candidate is written and kept only if near, since
    /// about half the candidates of a surface are, and mispredicted branches
    /// were most of the neighbour lists' build time.
    #[inline]
    pub fn collect_within(&self, q: &P3, r2: f64, out: &mut Vec<u32>) {
        let [sx, sy, sz] = &self.sorted;
        let (runs, count) = self.runs_around(q);
        for &(s, e) in &runs[..count] {
            let mut len = out.len();
            out.resize(len + (e - s), 0);
            for p in s..e {
                let (dx, dy, dz) = (sx[p] - q[0], sy[p] - q[1], sz[p] - q[2]);
                out[len] = self.items[p];
                len += (dx * dx + dy * dy + dz * dz <= r2) as usize;
            }
            out.truncate(len);
        }
    }

    /// The squared distance from `q` to the nearest point of the set the
    /// grid was built on, when one lies within √`r2` (which must not exceed
    /// the build radius²); None otherwise. Exact: every point that near is
    /// in the 27 cells around `q`.
    pub fn nearest_within(&self, q: &P3, r2: f64) -> Option<f64> {
        let [sx, sy, sz] = &self.sorted;
        let (runs, count) = self.runs_around(q);
        let mut best = f64::INFINITY;
        for &(s, e) in &runs[..count] {
            for p in s..e {
                let (dx, dy, dz) = (sx[p] - q[0], sy[p] - q[1], sz[p] - q[2]);
                best = best.min(dx * dx + dy * dy + dz * dz);
            }
        }
        (best <= r2).then_some(best)
    }
}

/// `v.floor()` without the call: the baseline x86-64 target has no rounding
/// instruction (SSE4.1's `roundsd`), so `f64::floor` is a call into a
/// software routine, and the grid and range-image cell lookups were 2 % of a
/// registration without its camera position (perf, `bench_register mug`).
/// Exact for |v| < 2⁶³; NaN gives NaN.
#[inline(always)]
pub(crate) fn floor(v: f64) -> f64 {
    if !(v.abs() < 9.2e18) {
        return v;
    }
    let t = v as i64 as f64;
    if t > v {
        t - 1.0
    } else {
        t
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn floor_is_f64_floor() {
        let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let mut values = vec![0.0, -0.0, 1.0, -1.0, 0.5, -0.5, 2.999999, -2.000001, 1e17 + 0.5, -1e17, 9.3e18, -1e300];
        values.extend((0..10_000).map(|_| (r.random::<f64>() - 0.5) * 10f64.powi(r.random_range(-3..12))));
        for v in values {
            assert_eq!(floor(v), v.floor(), "{v}");
        }
        assert!(floor(f64::NAN).is_nan());
        assert_eq!(floor(f64::NEG_INFINITY), f64::NEG_INFINITY);
    }

    #[test]
    fn the_nearest_point_within_the_radius_is_the_brute_force_one() {
        let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(8);
        let x: Vec<P3> = (0..1500).map(|_| [r.random(), r.random::<f64>() * 0.5, r.random::<f64>() * 0.1]).collect();
        let mut g = RadiusGrid::default();
        let (mut near, mut far) = (0, 0);
        for radius in [0.01, 0.05, 0.3] {
            g.build(&x, radius);
            for _ in 0..200 {
                let q = [r.random::<f64>() * 1.4 - 0.2, r.random::<f64>() * 0.7 - 0.1, r.random::<f64>() * 0.3 - 0.1];
                let best = x.iter().map(|p| super::super::estep::dist2(p, &q)).fold(f64::INFINITY, f64::min);
                let want = (best <= radius * radius).then_some(best);
                assert_eq!(g.nearest_within(&q, radius * radius), want, "radius {radius}, query {q:?}");
                if want.is_some() {
                    near += 1;
                } else {
                    far += 1;
                }
            }
        }
        // Both answers were exercised.
        assert!(near > 50 && far > 50, "{near} near, {far} far");
    }

    #[test]
    fn finds_exactly_the_points_within_the_radius() {
        let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let x: Vec<P3> = (0..2000).map(|_| [r.random(), r.random::<f64>() * 0.5, r.random::<f64>() * 0.1]).collect();
        let mut g = RadiusGrid::default();
        for radius in [0.03, 0.1, 0.4] {
            g.build(&x, radius);
            let queries: Vec<P3> = (0..50)
                .map(|_| [r.random::<f64>() * 1.4 - 0.2, r.random::<f64>() * 0.7 - 0.1, r.random::<f64>() * 0.3 - 0.1])
                .collect();
            let within = |q: &P3, rad: f64| -> Vec<u32> {
                (0..x.len() as u32).filter(|&i| super::super::estep::dist2(&x[i as usize], q) <= rad * rad).collect()
            };
            for q in &queries {
                let mut got = Vec::new();
                g.collect_within(q, radius * radius, &mut got);
                got.sort_unstable();
                assert_eq!(got, within(q, radius));
            }
            // Rows of many queries, scalar and (where the CPU has it) vector:
            // every point within the radius, none beyond it by more than 1e-5.
            for avx2 in [false, true] {
                let (mut starts, mut data) = (vec![0], Vec::new());
                g.collect_rows(&queries, radius * radius, avx2, &mut starts, &mut data);
                assert_eq!(starts.len(), queries.len() + 1);
                for (i, q) in queries.iter().enumerate() {
                    let mut row = data[starts[i] as usize..starts[i + 1] as usize].to_vec();
                    row.sort_unstable();
                    let inner = within(q, radius);
                    assert!(
                        inner.iter().all(|j| row.binary_search(j).is_ok()),
                        "avx2 {avx2}: a point within is missing"
                    );
                    let outer = within(q, radius * (1.0 + 1e-5));
                    assert!(row.iter().all(|j| outer.binary_search(j).is_ok()), "avx2 {avx2}: a point far beyond");
                    assert!(row.windows(2).all(|w| w[0] < w[1]), "avx2 {avx2}: a point listed twice");
                }
            }
        }
    }
}
