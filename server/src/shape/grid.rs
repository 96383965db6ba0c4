//! Fixed-radius neighbour search on a uniform grid.
//!
//! The truncated E-step asks, every iteration, for all data points within
//! r = kσ of each moving point, with r changing as σ shrinks. A k-d tree's
//! radius query (kiddo's goes through a sorted nearest-n search and allocates
//! per query) cost more than the Gaussians themselves. A grid with cells no
//! smaller than r answers the same query from 27 cells, is rebuilt in O(N)
//! by a counting sort whenever r changes, and never allocates per query.

use super::estep::P3;

#[derive(Default)]
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
    /// Cell keys of the points, reused between builds.
    keys: Vec<u32>,
}

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
    }

    fn cell_of(&self, p: &P3) -> [usize; 3] {
        let mut c = [0usize; 3];
        for d in 0..3 {
            let f = ((p[d] - self.origin[d]) * self.inv_cell).floor();
            c[d] = f.clamp(0.0, (self.dims[d] - 1) as f64) as usize;
        }
        c
    }

    /// Calls `f(start, end)` for the runs of `items` (and `sorted`) that
    /// hold the points of the 27 cells around `q`: one run per row of three cells.
    #[inline]
    fn runs_around(&self, q: &P3, mut f: impl FnMut(usize, usize)) {
        let mut lo = [0usize; 3];
        let mut hi = [0usize; 3];
        for d in 0..3 {
            let c = ((q[d] - self.origin[d]) * self.inv_cell).floor();
            let (a, b) = (c - 1.0, c + 1.0);
            if b < 0.0 || a > (self.dims[d] - 1) as f64 {
                return;
            }
            lo[d] = a.max(0.0) as usize;
            hi[d] = b.min((self.dims[d] - 1) as f64) as usize;
        }
        for z in lo[2]..=hi[2] {
            for y in lo[1]..=hi[1] {
                let row = self.dims[0] * (y + self.dims[1] * z);
                f(self.starts[row + lo[0]] as usize, self.starts[row + hi[0] + 1] as usize);
            }
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
        self.runs_around(q, |s, e| {
            let mut len = out.len();
            out.resize(len + (e - s), 0);
            for p in s..e {
                let (dx, dy, dz) = (sx[p] - q[0], sy[p] - q[1], sz[p] - q[2]);
                out[len] = self.items[p];
                len += (dx * dx + dy * dy + dz * dz <= r2) as usize;
            }
            out.truncate(len);
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn finds_exactly_the_points_within_the_radius() {
        let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let x: Vec<P3> = (0..2000).map(|_| [r.random(), r.random::<f64>() * 0.5, r.random::<f64>() * 0.1]).collect();
        let mut g = RadiusGrid::default();
        for radius in [0.03, 0.1, 0.4] {
            g.build(&x, radius);
            for _ in 0..50 {
                let q: P3 =
                    [r.random::<f64>() * 1.4 - 0.2, r.random::<f64>() * 0.7 - 0.1, r.random::<f64>() * 0.3 - 0.1];
                let mut got = Vec::new();
                g.collect_within(&q, radius * radius, &mut got);
                got.sort_unstable();
                let want: Vec<u32> = (0..x.len() as u32)
                    .filter(|&i| super::super::estep::dist2(&x[i as usize], &q) <= radius * radius)
                    .collect();
                assert_eq!(got, want);
            }
        }
    }
}
