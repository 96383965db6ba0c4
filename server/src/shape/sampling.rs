//! Subsets of a depth view for registration: stray points dropped, and
//! seeded subsets, uniform or spread evenly over the view's surface.

use rand::Rng;

use super::estep::P3;

/// A seeded subset of at most `n` points.
pub fn subsample(x: &[P3], n: usize, rng: &mut rand_chacha::ChaCha8Rng) -> Vec<P3> {
    if x.len() <= n {
        return x.to_vec();
    }
    let mut idx = rand::seq::index::sample(rng, x.len(), n).into_vec();
    idx.sort_unstable();
    idx.into_iter().map(|i| x[i]).collect()
}

/// An open-addressing hash map from voxel keys to small values, sized for
/// the points it will see (at most half full). Counting a view's cells by
/// sorting their keys was most of the time spent before the fit (measured:
/// stray removal and an even subsample 0.3 and 0.17 ms of a 2,500-point view).
struct CellMap<V> {
    keys: Vec<u64>,
    values: Vec<V>,
    shift: u32,
    len: usize,
}

impl<V: Copy + Default> CellMap<V> {
    /// Keys are at most 63 bits (21 per axis): this one is never a cell.
    const EMPTY: u64 = u64::MAX;

    fn for_points(points: usize) -> Self {
        let slots = (2 * points).next_power_of_two().max(16);
        Self {
            keys: vec![Self::EMPTY; slots],
            values: vec![V::default(); slots],
            shift: 64 - slots.trailing_zeros(),
            len: 0,
        }
    }

    /// The slot of `key`, or the empty slot where it would go.
    #[inline]
    fn slot(&self, key: u64) -> usize {
        let mask = self.keys.len() - 1;
        // Fibonacci hashing: the top bits of the product.
        let mut i = (key.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> self.shift) as usize;
        while self.keys[i] != key && self.keys[i] != Self::EMPTY {
            i = (i + 1) & mask;
        }
        i
    }

    /// The slot of `key`, which is inserted (with the default value) when
    /// absent, and whether it was.
    #[inline]
    fn occupy(&mut self, key: u64) -> (usize, bool) {
        let i = self.slot(key);
        let new = self.keys[i] == Self::EMPTY;
        if new {
            self.keys[i] = key;
            self.len += 1;
        }
        (i, new)
    }

    /// The value of `key`, inserted as the default first.
    #[inline]
    fn entry(&mut self, key: u64) -> &mut V {
        let (i, _) = self.occupy(key);
        &mut self.values[i]
    }

    /// Sets `key`'s value to `value` when it has none yet or a greater one.
    #[inline]
    fn keep_least(&mut self, key: u64, value: V)
    where
        V: PartialOrd,
    {
        let (i, new) = self.occupy(key);
        if new || value < self.values[i] {
            self.values[i] = value;
        }
    }

    #[inline]
    fn get(&self, key: u64) -> Option<V> {
        let i = self.slot(key);
        (self.keys[i] == key).then(|| self.values[i])
    }

    /// The occupied (key, value) pairs, in no particular order.
    fn iter(&self) -> impl Iterator<Item = (u64, V)> + '_ {
        self.keys.iter().zip(&self.values).filter(|(k, _)| **k != Self::EMPTY).map(|(k, v)| (*k, *v))
    }
}

/// The cells of a voxel grid that hold points, each with a small value: an
/// array over the grid's whole box when the box has few cells, the hash map
/// otherwise. A view's grids have 10³-10⁵ cells in their box, and indexing an
/// array skips the map's probe loop and its data-dependent branches. Far-flung
/// points (an absurd cloud) make the box huge: those grids keep the map. Both
/// give the same values for the same keys, so the points kept are the same.
/// Measured with `VoxelGrid::cell` through i64 (`bench_subsets`, the mug's
/// test views, alternating with the map-only build; 2-core Xeon): stray
/// removal, 400- and 800-point subsets 448 / 333 / 381 → 258 / 167 / 171 µs,
/// about 0.55 ms less before each fit.
enum Cells<V> {
    Dense(DenseCells<V>),
    Hashed(CellMap<V>),
}

/// Box cells allowed per point for the array (a view's surface fills a tenth
/// of its box or more).
const DENSE_CELLS_PER_POINT: u64 = 64;

struct DenseCells<V> {
    /// Cells along each axis of the grid's box.
    dims: [u64; 3],
    occupied: Vec<u64>,
    values: Vec<V>,
    len: usize,
}

impl<V: Copy + Default> Cells<V> {
    /// Cells of `grid` for about `points` points.
    fn for_grid(grid: &VoxelGrid, points: usize) -> Self {
        let dims = grid.dims();
        let cells = dims.iter().try_fold(1u64, |a, &d| a.checked_mul(d));
        match cells {
            Some(c) if c <= DENSE_CELLS_PER_POINT * points as u64 + 4096 => Self::Dense(DenseCells {
                dims,
                occupied: vec![0; (c as usize).div_ceil(64)],
                values: vec![V::default(); c as usize],
                len: 0,
            }),
            _ => Self::Hashed(CellMap::for_points(points)),
        }
    }

    fn len(&self) -> usize {
        match self {
            Self::Dense(d) => d.len,
            Self::Hashed(h) => h.len,
        }
    }

    /// The value of `key`, inserted as the default first. `key` must be a
    /// cell of the grid's box (every point the grid was bounded by has one).
    #[inline]
    fn entry(&mut self, key: u64) -> &mut V {
        match self {
            Self::Dense(d) => {
                let i = d.index(key).expect("a key of the grid's box");
                d.occupy(i);
                &mut d.values[i]
            }
            Self::Hashed(h) => h.entry(key),
        }
    }

    /// Sets `key`'s value to `value` when it has none yet or a greater one.
    #[inline]
    fn keep_least(&mut self, key: u64, value: V)
    where
        V: PartialOrd,
    {
        match self {
            Self::Dense(d) => {
                let i = d.index(key).expect("a key of the grid's box");
                if d.occupy(i) || value < d.values[i] {
                    d.values[i] = value;
                }
            }
            Self::Hashed(h) => h.keep_least(key, value),
        }
    }

    #[inline]
    fn get(&self, key: u64) -> Option<V> {
        match self {
            Self::Dense(d) => d.index(key).filter(|&i| d.occupied[i / 64] >> (i % 64) & 1 == 1).map(|i| d.values[i]),
            Self::Hashed(h) => h.get(key),
        }
    }

    /// The sum of `count` over the occupied cells of the 3×3×3 block around
    /// `key` (a key of the grid's box).
    fn block_sum(&self, key: u64, count: impl Fn(&V) -> usize) -> usize {
        match self {
            // Unoccupied cells hold the default: `count` must give it 0.
            Self::Dense(d) => d.block_sum(key, count),
            Self::Hashed(_) => VoxelGrid::block(key).filter_map(|b| self.get(b)).map(|v| count(&v)).sum(),
        }
    }

    /// The occupied cells' values in the order of their keys.
    fn values_by_key(&self) -> Vec<V> {
        match self {
            // Array order is key order (z, then y, then x, as the key's bits).
            Self::Dense(d) => d.occupied_indices().map(|i| d.values[i]).collect(),
            Self::Hashed(h) => {
                let mut pairs: Vec<(u64, V)> = h.iter().collect();
                pairs.sort_unstable_by_key(|&(k, _)| k);
                pairs.into_iter().map(|(_, v)| v).collect()
            }
        }
    }

    /// The occupied (key, value) pairs, in no particular order.
    fn iter(&self) -> Box<dyn Iterator<Item = (u64, V)> + '_> {
        match self {
            Self::Dense(d) => Box::new(d.occupied_indices().map(|i| (d.key(i), d.values[i]))),
            Self::Hashed(h) => Box::new(h.iter()),
        }
    }
}

impl<V> DenseCells<V> {
    /// The array index of `key`, None outside the box.
    #[inline]
    fn index(&self, key: u64) -> Option<usize> {
        let m = VoxelGrid::MAX_CELL;
        let c = [key & m, (key >> 21) & m, key >> 42];
        let [d0, d1, d2] = self.dims;
        (c[0] < d0 && c[1] < d1 && c[2] < d2).then(|| ((c[2] * d1 + c[1]) * d0 + c[0]) as usize)
    }

    #[inline]
    fn key(&self, i: usize) -> u64 {
        let i = i as u64;
        let [d0, d1, _] = self.dims;
        (i % d0) | ((i / d0 % d1) << 21) | ((i / (d0 * d1)) << 42)
    }

    /// The sum of `count` over the 3×3×3 cells around cell `key`, within
    /// the box, by array index (unoccupied cells hold the default, counted
    /// as `count` gives it).
    #[inline]
    fn block_sum(&self, key: u64, count: impl Fn(&V) -> usize) -> usize {
        let m = VoxelGrid::MAX_CELL;
        let c = [key & m, (key >> 21) & m, key >> 42];
        let [d0, d1, d2] = self.dims;
        // The block's span along each axis, clipped to the box.
        let span = |c: u64, d: u64| (c.saturating_sub(1), (c + 1).min(d.saturating_sub(1)));
        let ((x0, x1), (y0, y1), (z0, z1)) = (span(c[0], d0), span(c[1], d1), span(c[2], d2));
        // A key beyond the box (a point outside the probe the grid was
        // bounded by) has an empty block there.
        if x0 > x1 {
            return 0;
        }
        let mut sum = 0;
        for z in z0..=z1 {
            for y in y0..=y1 {
                let row = ((z * d1 + y) * d0) as usize;
                sum += self.values[row + x0 as usize..=row + x1 as usize].iter().map(&count).sum::<usize>();
            }
        }
        sum
    }

    /// Indices of the occupied cells, ascending (a set bit at a time, not
    /// a test of all 64 a word).
    fn occupied_indices(&self) -> impl Iterator<Item = usize> + '_ {
        self.occupied.iter().enumerate().flat_map(|(w, &bits)| {
            std::iter::successors((bits != 0).then_some(bits), |&b| Some(b & (b - 1)).filter(|&b| b != 0))
                .map(move |b| w * 64 + b.trailing_zeros() as usize)
        })
    }

    /// Marks cell `i` occupied; whether it was not before.
    #[inline]
    fn occupy(&mut self, i: usize) -> bool {
        let (w, bit) = (i / 64, 1u64 << (i % 64));
        let new = self.occupied[w] & bit == 0;
        self.occupied[w] |= bit;
        self.len += new as usize;
        new
    }
}

/// A voxel grid over a cloud's bounding box (`lo` to `hi`), cells `h` wide,
/// each named by a packed key (21 bits per axis).
#[derive(Clone, Copy)]
struct VoxelGrid {
    lo: P3,
    hi: P3,
    h: f64,
    /// 1/h: the cells are found by a product, not a division (a division
    /// each coordinate, these grids were 3 % of a mug registration; a
    /// product and a quotient fall in different cells only for a point
    /// within a rounding of a cell's face).
    inv_h: f64,
}

impl VoxelGrid {
    const MAX_CELL: u64 = (1 << 21) - 1;

    fn bounds(x: &[P3]) -> (P3, P3) {
        let (mut lo, mut hi) = (x[0], x[0]);
        for p in x {
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        (lo, hi)
    }

    /// The grid whose cell is sized so that about `cells` cells are occupied.
    /// The size is found on a random subset of the cloud (a view is a
    /// surface: occupied cells grow as 1/h²).
    fn with_occupied_cells(x: &[P3], cells: usize, rng: &mut rand_chacha::ChaCha8Rng) -> Self {
        let (lo, hi) = Self::bounds(x);
        let probe = subsample(x, 2000.max(4 * cells), rng);
        let mut faces =
            [(hi[0] - lo[0]) * (hi[1] - lo[1]), (hi[1] - lo[1]) * (hi[2] - lo[2]), (hi[0] - lo[0]) * (hi[2] - lo[2])];
        faces.sort_by(f64::total_cmp);
        let h = (faces[2].max(1e-12) / cells.max(1) as f64).sqrt().max(1e-9);
        let mut grid = Self { lo, hi, h, inv_h: 1.0 / h };
        for _ in 0..6 {
            let mut occupied = Cells::<()>::for_grid(&grid, probe.len());
            for p in &probe {
                occupied.entry(grid.key(p));
            }
            let ratio = occupied.len() as f64 / cells.max(1) as f64;
            if (0.95..1.1).contains(&ratio) {
                break;
            }
            grid.h *= ratio.sqrt();
            grid.inv_h = 1.0 / grid.h;
        }
        grid
    }

    fn key(&self, p: &P3) -> u64 {
        let c = |k: usize| self.cell(p, k);
        c(0) | c(1) << 21 | c(2) << 42
    }

    /// The cell along axis `k`: below the box 0, beyond `MAX_CELL` that.
    /// (Through i64, which x86-64 converts in one instruction, where u64
    /// takes a compare and two more; the same value for every input.)
    #[inline]
    fn cell(&self, p: &P3, k: usize) -> u64 {
        (((p[k] - self.lo[k]) * self.inv_h) as i64).clamp(0, Self::MAX_CELL as i64) as u64
    }

    /// Cells along each axis of the box: every point within it has a key within these.
    fn dims(&self) -> [u64; 3] {
        [0, 1, 2].map(|k| self.cell(&self.hi, k) + 1)
    }

    /// Keys of the 27 cells around (and including) the cell `key`.
    fn block(key: u64) -> impl Iterator<Item = u64> {
        let c = [key & Self::MAX_CELL, (key >> 21) & Self::MAX_CELL, key >> 42];
        (0..27u64).filter_map(move |i| {
            let d = [i % 3, (i / 3) % 3, i / 9];
            let mut out = 0;
            for k in 0..3 {
                // c + d − 1 within [0, MAX_CELL].
                let v = (c[k] + d[k]).checked_sub(1).filter(|&v| v <= Self::MAX_CELL)?;
                out |= v << (21 * k);
            }
            Some(out)
        })
    }
}

/// Where the bulk of a cloud lies: per axis, its 1st to 99th percentile
/// (over every k-th point, at most [`Self::PROBE_POINTS`]: deterministic,
/// and a percentile needs no more). A few far points (a flying pixel on the
/// wall behind the tool, a leak of the segmentation into the floor) stretch
/// the plain bounding box to metres, where they move this not at all: one
/// point 6 m from a mug view made the view's extent 6 m (and the request
/// refused as not a hand-held tool's), and one 2 m off halved the stray
/// test's catch (its grid spans the box).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BulkBox {
    pub lo: P3,
    pub hi: P3,
}

impl BulkBox {
    pub const PROBE_POINTS: usize = 4096;
    /// The share of the points left out at each end of each axis.
    pub const TAIL: f64 = 0.01;

    /// None for an empty cloud.
    pub fn of(x: &[P3]) -> Option<Self> {
        if x.is_empty() {
            return None;
        }
        let stride = x.len().div_ceil(Self::PROBE_POINTS);
        let mut lo = [0.0; 3];
        let mut hi = [0.0; 3];
        let mut axis: Vec<f64> = Vec::with_capacity(x.len() / stride + 1);
        for k in 0..3 {
            axis.clear();
            axis.extend(x.iter().step_by(stride).map(|p| p[k]));
            let n = axis.len();
            let tail = (Self::TAIL * (n - 1) as f64).round() as usize;
            lo[k] = *axis.select_nth_unstable_by(tail, f64::total_cmp).1;
            hi[k] = *axis.select_nth_unstable_by(n - 1 - tail, f64::total_cmp).1;
        }
        Some(Self { lo, hi })
    }

    /// Length of the box's diagonal: the cloud's extent without its far points.
    pub fn diagonal(&self) -> f64 {
        (0..3).map(|k| (self.hi[k] - self.lo[k]).powi(2)).sum::<f64>().sqrt()
    }

    /// Whether `p` lies within the box grown by its diagonal on every side:
    /// no point of a tool whose bulk this is lies further out (the bulk
    /// leaves out 2 % of each axis's points, a tool's last 2 % reach a
    /// fraction of its size beyond).
    pub fn near(&self, p: &P3) -> bool {
        let margin = self.diagonal();
        (0..3).all(|k| p[k] >= self.lo[k] - margin && p[k] <= self.hi[k] + margin)
    }
}

/// The cloud without the points far from its bulk ([`BulkBox::near`]),
/// in their order: the stray test's grid then spans the tool, not the room.
pub fn drop_far_points<'a>(x: &'a [P3], bulk: &BulkBox) -> std::borrow::Cow<'a, [P3]> {
    if x.iter().all(|p| bulk.near(p)) {
        return std::borrow::Cow::Borrowed(x);
    }
    std::borrow::Cow::Owned(x.iter().filter(|p| bulk.near(p)).copied().collect())
}

/// Which points near a given table are the table's. A segmentation that
/// leaks onto the table (its mask dilated by a few pixels) keeps a band of
/// it round the tool's foot and, past the tool's far edge, behind it:
/// dense, so no stray test takes it, and a fifth to a half as many points
/// as the tool's own. Kept, it wrecked the fits: `eval transfer --views 6
/// --seed 7 --mask-leak-px 2`, test keypoint median / p90 (mm): mug 2.05
/// / 12.5 → 3.8 / 97, drill 1.4 / 3.6 → 3.5 / 159, hammer 1.6 / 3.9 →
/// 12.1 / 35.
///
/// A point up to `soft_m` above the table (or below it) is the tool's
/// where the tool stands above it: within a `cell_m` grid cell, or the
/// eight around it, of a point higher than `soft_m`, seen from above. A
/// wall's foot keeps its points, the table beyond it does not: a table
/// the camera sees lies outside the tool's footprint, but where it sees
/// under an overhang (a mug's handle), and those few stay. When more
/// than `leak_share` of the cloud lies in the band beside the tool, the
/// mask leaks: those points, and every point lower than `hard_m` (a 2 mm
/// band holds 98 % of a table seen with 1 mm depth noise: the leak's
/// ring at the tool's very foot) are set aside. A view that does not
/// leak loses nothing: setting aside its lowest 2 mm cost the mug's
/// p90 (`eval transfer --views 12`, seeds 7 / 11 / 23: 10.8 / 6.8 / 8.5
/// → 17.7 / 5.2 / 12.5 mm), its lowest 4 mm more (27.6 / 6.4 / 24.0).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TableBand {
    pub hard_m: f64,
    pub soft_m: f64,
    pub cell_m: f64,
    /// A view leaks only when more of its points than this share lie in
    /// the band away from the tool; otherwise nothing is set aside.
    pub leak_share: f64,
}

impl Default for TableBand {
    fn default() -> Self {
        Self { hard_m: 0.002, soft_m: 0.005, cell_m: 0.002, leak_share: 0.01 }
    }
}

impl TableBand {
    /// Which points of `x` are the table's (true), the table being the
    /// plane height = `table` (`heights`: each point's height along up,
    /// `up` a unit vector); None when the view does not leak and none is.
    pub fn table_points(&self, x: &[P3], heights: &[f64], up: [f64; 3], table: f64) -> Option<Vec<bool>> {
        let Some((band, beside)) = self.beside_the_tool(x, heights, up, table) else {
            // Nothing near the table, or a band no tool's foot spans: all above it or all of it the table's.
            let band = heights.iter().filter(|&&h| h - table <= self.soft_m).count();
            return (band > 0 && 2 * band >= x.len())
                .then(|| heights.iter().map(|&h| h - table <= self.soft_m).collect());
        };
        if (beside.iter().filter(|&&b| b).count() as f64) < self.leak_share * x.len() as f64 {
            return None;
        }
        let mut table_point = vec![false; x.len()];
        for (&i, &beside) in band.iter().zip(&beside) {
            table_point[i] = beside || heights[i] - table < self.hard_m;
        }
        Some(table_point)
    }

    /// The height of a leaking mask's table near `guess` (the median of the
    /// band's points beside the tool, the band taken about `guess`), or
    /// None when the cloud does not leak there.
    pub fn leaking_table(&self, x: &[P3], heights: &[f64], up: [f64; 3], guess: f64) -> Option<f64> {
        let (band, beside) = self.beside_the_tool(x, heights, up, guess)?;
        let mut table: Vec<f64> = band.iter().zip(&beside).filter(|(_, &b)| b).map(|(&i, _)| heights[i]).collect();
        if table.is_empty() || (table.len() as f64) < self.leak_share * x.len() as f64 {
            return None;
        }
        let k = table.len() / 2;
        Some(*table.select_nth_unstable_by(k, f64::total_cmp).1)
    }

    /// The points up to `soft_m` above the table (indices), and whether
    /// each lies beside the tool rather than under it; None when there are
    /// none or they span more than [`Occupancy::MAX_CELLS`].
    fn beside_the_tool(&self, x: &[P3], heights: &[f64], up: [f64; 3], table: f64) -> Option<(Vec<usize>, Vec<bool>)> {
        // Two horizontal axes.
        let u = nalgebra::Vector3::from(up);
        let a = u.cross(&if u.x.abs() < 0.9 { nalgebra::Vector3::x() } else { nalgebra::Vector3::y() }).normalize();
        let b = u.cross(&a);
        let cell = |p: &P3| {
            let v = nalgebra::Vector3::from(*p);
            [(v.dot(&a) / self.cell_m).floor(), (v.dot(&b) / self.cell_m).floor()]
        };
        // The band's cells, grown by one: the only cells asked about.
        let band: Vec<usize> = (0..x.len()).filter(|&i| heights[i] - table <= self.soft_m).collect();
        let mut tool_above = Occupancy::around(band.iter().map(|&i| cell(&x[i])))?;
        // Every point above the band marks the tool's footprint: a lying
        // mug's flank curves in under its bulge, so the points over its
        // contact are its top's, centimetres up (marking only the next
        // 2 cm above the band took that flank for the table).
        for (p, &h) in x.iter().zip(heights) {
            if h - table > self.soft_m {
                tool_above.mark(cell(p));
            }
        }
        let beside = band.iter().map(|&i| !tool_above.near(cell(&x[i]))).collect();
        Some((band, beside))
    }
}

/// A dense 2-D grid of marked cells over a rectangle of cell indices.
struct Occupancy {
    lo: [f64; 2],
    dims: [usize; 2],
    marked: Vec<bool>,
}

impl Occupancy {
    /// At most this many cells (a 2 m square at 2 mm): a band wider than
    /// that is no tool's foot, and has no grid (nothing in it is kept).
    const MAX_CELLS: usize = 1 << 20;

    /// Over the cells given, grown by one cell each way; None when there
    /// are none, or too many.
    fn around(cells: impl Iterator<Item = [f64; 2]>) -> Option<Self> {
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for c in cells {
            for k in 0..2 {
                lo[k] = lo[k].min(c[k] - 1.0);
                hi[k] = hi[k].max(c[k] + 1.0);
            }
        }
        if !(lo[0] <= hi[0] && lo[1] <= hi[1]) {
            return None;
        }
        let span = |k: usize| hi[k] - lo[k] + 1.0;
        if span(0) * span(1) > Self::MAX_CELLS as f64 {
            return None;
        }
        let dims = [span(0) as usize, span(1) as usize];
        Some(Self { lo, dims, marked: vec![false; dims[0] * dims[1]] })
    }

    fn index(&self, c: [f64; 2]) -> Option<usize> {
        let (i, j) = (c[0] - self.lo[0], c[1] - self.lo[1]);
        let inside = i >= 0.0 && j >= 0.0 && (i as usize) < self.dims[0] && (j as usize) < self.dims[1];
        inside.then(|| j as usize * self.dims[0] + i as usize)
    }

    fn mark(&mut self, c: [f64; 2]) {
        if let Some(k) = self.index(c) {
            self.marked[k] = true;
        }
    }

    /// Whether `c` or one of the eight cells around it is marked.
    fn near(&self, c: [f64; 2]) -> bool {
        (-1..=1).any(|di| {
            (-1..=1).any(|dj| self.index([c[0] + di as f64, c[1] + dj as f64]).is_some_and(|k| self.marked[k]))
        })
    }
}

/// The cloud without its stray points: flying pixels at depth edges,
/// segmentation leaks, sensor speckle. A point counts as stray when the
/// 3×3×3 block of cells around it (cells holding about eight points of a
/// surface) holds less than an eighth of a typical point's block, and at
/// least two: a surface crosses several cells of any block, a lone point
/// fills one. Every later stage sees only what is left: stray points in a
/// subsample cost pose accuracy far beyond their share (measured on the test
/// hammers with 10 % outliers: half of a 400-point subsample were strays,
/// keypoint error 25 mm median), and in the free-space image they hide what
/// the camera saw through. The counts come from a random subset of at most
/// `STRAY_PROBE_POINTS` (scaled: a density test needs no more), and the
/// test is applied to every point. When it would drop more than half of the
/// cloud, the cloud is not a surface with some strays and is returned whole.
pub fn drop_stray_points(x: &[P3], rng: &mut rand_chacha::ChaCha8Rng) -> Vec<P3> {
    const POINTS_PER_CELL: usize = 8;
    const STRAY_PROBE_POINTS: usize = 6000;
    if x.len() < 4 * POINTS_PER_CELL {
        return x.to_vec();
    }
    let probe = subsample(x, STRAY_PROBE_POINTS, rng);
    let grid = VoxelGrid::with_occupied_cells(&probe, (probe.len() / POINTS_PER_CELL).max(8), rng);
    // Probe points per cell, then each cell's block total beside its count.
    let mut cells = Cells::<(usize, usize)>::for_grid(&grid, probe.len());
    for p in &probe {
        cells.entry(grid.key(p)).0 += 1;
    }
    // Block sums by array index where the grid is dense: through the key
    // iterator and a lookup a cell they were 70-85 µs of the 150-270 this
    // took on a 2,000-point drill view (`bench_subsets`, the mug's test
    // views, the same points kept: 166 → 126 µs).
    let block_of = |cells: &Cells<(usize, usize)>, k: u64| cells.block_sum(k, |c| c.0);
    let occupied: Vec<(u64, usize)> = cells.iter().map(|(k, (n, _))| (k, n)).collect();
    for &(k, _) in &occupied {
        let block = block_of(&cells, k);
        cells.entry(k).1 = block;
    }
    // The typical point's block: median weighted by points.
    let mut weighted: Vec<(usize, usize)> = cells.iter().map(|(_, (n, b))| (b, n)).collect();
    weighted.sort_unstable();
    let (mut seen, mut typical) = (0, 1);
    for &(b, n) in &weighted {
        seen += n;
        if 2 * seen >= probe.len() {
            typical = b;
            break;
        }
    }
    let threshold = (typical / 8).max(2);
    // A point of the cloud in a probed cell, or (rarely) in a cell the probe missed.
    let keep = |p: &P3| {
        let k = grid.key(p);
        let block = cells.get(k).map_or_else(|| block_of(&cells, k) + 1, |c| c.1);
        block >= threshold
    };
    let kept: Vec<P3> = x.iter().filter(|p| keep(p)).copied().collect();
    if 2 * kept.len() < x.len() {
        return x.to_vec();
    }
    kept
}

/// At most `n` points spread evenly over the cloud's surface: a voxel grid
/// whose cell is sized so that about `n` cells are occupied, one seeded
/// random point per cell (a seeded random subset of the cells when more).
/// O(N log N) for the sort; farthest-point sampling would be O(N·n). Stray
/// points are expected gone (`drop_stray_points`): each would win a cell of
/// its own, as many as the whole surface's.
pub fn even_subsample(x: &[P3], n: usize, rng: &mut rand_chacha::ChaCha8Rng) -> Vec<P3> {
    if x.len() <= n || n == 0 {
        return x.to_vec();
    }
    // Aim a little above n so the trim below keeps the cover even.
    let grid = VoxelGrid::with_occupied_cells(x, (1.15 * n as f64) as usize, rng);
    // One representative per cell: the point of least (random tag, index),
    // the cells in key order (what sorting (key, tag, index) would give).
    let mut best = Cells::<(u32, u32)>::for_grid(&grid, x.len());
    for (i, p) in x.iter().enumerate() {
        let tag: u32 = rng.random();
        best.keep_least(grid.key(p), (tag, i as u32));
    }
    let mut chosen: Vec<u32> = best.values_by_key().into_iter().map(|(_, i)| i).collect();
    if chosen.len() > n {
        let keep = rand::seq::index::sample(rng, chosen.len(), n).into_vec();
        chosen = keep.into_iter().map(|k| chosen[k]).collect();
    }
    chosen.sort_unstable();
    chosen.into_iter().map(|i| x[i as usize]).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    /// A cylinder's wall (radius 4 cm, 1 mm apart) standing on the table
    /// z = 0.01, with or without a ring of table round its foot (4-10 mm
    /// out): the ring is the table's and the wall's foot the tool's; a
    /// clean wall loses nothing, and the ring gives the table's height.
    #[test]
    fn table_band_takes_the_ring_round_a_foot_and_leaves_the_foot() {
        let mut wall: Vec<P3> = Vec::new();
        for k in 0..250 {
            let a = k as f64 * std::f64::consts::TAU / 250.0;
            for j in 0..80 {
                wall.push([0.04 * a.cos(), 0.04 * a.sin(), 0.01 + j as f64 * 0.001]);
            }
        }
        let mut ring = Vec::new();
        for k in 0..400 {
            let a = k as f64 * std::f64::consts::TAU / 400.0;
            for r in [0.044, 0.047, 0.05] {
                ring.push([r * a.cos(), r * a.sin(), 0.01 + 0.0005 * ((k % 5) as f64 - 2.0)]);
            }
        }
        let band = TableBand::default();
        let up = [0.0, 0.0, 1.0];
        let heights = |x: &[P3]| -> Vec<f64> { x.iter().map(|p| p[2]).collect() };
        assert_eq!(band.table_points(&wall, &heights(&wall), up, 0.01), None);
        assert_eq!(band.leaking_table(&wall, &heights(&wall), up, 0.01), None);
        let cloud: Vec<P3> = wall.iter().chain(&ring).copied().collect();
        let table = band.table_points(&cloud, &heights(&cloud), up, 0.01).unwrap();
        assert!(table[wall.len()..].iter().all(|&t| t), "the ring is the table's");
        // The wall's points from 2 mm up are kept; its lowest two rows go with the ring.
        let lost: Vec<f64> = wall.iter().zip(&table).filter(|(_, &t)| t).map(|(p, _)| p[2] - 0.01).collect();
        assert!(lost.iter().all(|&h| h < band.hard_m), "lost {:?}", &lost[..lost.len().min(5)]);
        let found = band.leaking_table(&cloud, &heights(&cloud), up, 0.009).unwrap();
        assert!((found - 0.01).abs() < 1e-3, "table at {found}");
    }

    #[test]
    fn cell_map_counts_and_keeps_the_least_like_an_ordered_map() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(21);
        // Few distinct keys among many (collisions in the table's probe runs too).
        let keys: Vec<u64> = (0..3000).map(|_| rng.random_range(0..700u64) * 0x1_0000_0001).collect();
        let mut counts = CellMap::<usize>::for_points(keys.len());
        let mut least = CellMap::<(u32, u32)>::for_points(keys.len());
        let mut want: std::collections::BTreeMap<u64, (usize, (u32, u32))> = Default::default();
        for (i, &k) in keys.iter().enumerate() {
            let v = (rng.random::<u32>(), i as u32);
            *counts.entry(k) += 1;
            least.keep_least(k, v);
            let e = want.entry(k).or_insert((0, v));
            e.0 += 1;
            e.1 = e.1.min(v);
        }
        assert_eq!(counts.len, want.len());
        assert_eq!(least.len, want.len());
        for (&k, &(n, v)) in &want {
            assert_eq!(counts.get(k), Some(n));
            assert_eq!(least.get(k), Some(v));
        }
        assert_eq!(counts.get(u64::MAX - 1), None);
        let mut listed: Vec<u64> = counts.iter().map(|(k, _)| k).collect();
        listed.sort_unstable();
        assert_eq!(listed, want.keys().copied().collect::<Vec<_>>());
    }

    /// The array over a grid's box answers as the hash map does: counts,
    /// least values, lookups inside and outside the box, and the listing.
    #[test]
    fn dense_cells_answer_as_the_hash_map_does() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
        let x = surface_with_outliers(3000, &mut rng);
        let grid = VoxelGrid::with_occupied_cells(&x, 400, &mut rng);
        let mut dense = Cells::<(u32, u32)>::for_grid(&grid, x.len());
        let mut hashed = Cells::Hashed(CellMap::<(u32, u32)>::for_points(x.len()));
        assert!(matches!(dense, Cells::Dense(_)), "a view's grid has few cells in its box");
        for (i, p) in x.iter().enumerate() {
            let v = (rng.random::<u32>() % 50, i as u32);
            dense.keep_least(grid.key(p), v);
            hashed.keep_least(grid.key(p), v);
            dense.entry(grid.key(&x[i / 2])).0 += 1;
            hashed.entry(grid.key(&x[i / 2])).0 += 1;
        }
        assert_eq!(dense.len(), hashed.len());
        let listed = |c: &Cells<(u32, u32)>| {
            let mut v: Vec<(u64, (u32, u32))> = c.iter().collect();
            v.sort_unstable();
            v
        };
        assert_eq!(listed(&dense), listed(&hashed));
        // Points off the box (clamped or past its far side) and their neighbours.
        let off: Vec<P3> = vec![[-1.0, 0.0, 0.0], [0.5, 0.5, 0.5], [0.0, 0.0, 2e3]];
        for p in x.iter().chain(&off) {
            for k in VoxelGrid::block(grid.key(p)) {
                assert_eq!(dense.get(k), hashed.get(k), "key {k:#x}");
            }
            let k = grid.key(p);
            assert_eq!(dense.block_sum(k, |c| c.0 as usize), hashed.block_sum(k, |c| c.0 as usize), "key {k:#x}");
        }
        // Past the far side by one cell and by more (a point outside the probe).
        let [d0, d1, d2] = grid.dims();
        for k in [d0 | d1 << 21 | d2 << 42, (d0 + 5) | 2 << 21 | 2 << 42, 2 | (d1 + 3) << 21 | 1 << 42] {
            assert_eq!(dense.block_sum(k, |c| c.0 as usize), hashed.block_sum(k, |c| c.0 as usize), "key {k:#x}");
        }
        // A box too large for an array (a point kilometres away) takes the map.
        let far: Vec<P3> = x.iter().copied().chain([[3e3, 0.0, 0.0]]).collect();
        let grid = VoxelGrid::with_occupied_cells(&far, 400, &mut rng);
        assert!(matches!(Cells::<()>::for_grid(&grid, far.len()), Cells::Hashed(_)));
    }

    /// A patch of surface (a 10 cm half-cylinder, `n` points) with 10 % points
    /// scattered uniformly through its bounding box grown by 20 %.
    fn surface_with_outliers(n: usize, rng: &mut rand_chacha::ChaCha8Rng) -> Vec<P3> {
        let mut x: Vec<P3> = (0..n)
            .map(|_| {
                let (a, z) = (rng.random::<f64>() * std::f64::consts::PI, rng.random::<f64>() * 0.1);
                [0.04 * a.cos(), 0.04 * a.sin(), z]
            })
            .collect();
        for _ in 0..n / 10 {
            x.push([
                rng.random::<f64>() * 0.096 - 0.048,
                rng.random::<f64>() * 0.048 - 0.004,
                rng.random::<f64>() * 0.12 - 0.01,
            ]);
        }
        x
    }

    fn on_surface(p: &P3) -> bool {
        ((p[0] * p[0] + p[1] * p[1]).sqrt() - 0.04).abs() < 1e-9
    }

    /// Dense (30 points a subsample cell) and sparse views (8 a cell, a
    /// hammer's depth view: there the strays won as many cells as the surface).
    #[test]
    fn stray_points_are_dropped_and_the_subsample_covers_the_surface() {
        for n in [12000, 3500] {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
            let x = surface_with_outliers(n, &mut rng);
            let kept = drop_stray_points(&x, &mut rng);
            let sub = even_subsample(&kept, 400, &mut rng);
            // Scatter within a cell or so of the surface is indistinguishable from depth noise and harmless.
            let far = |p: &P3| {
                ((p[0] * p[0] + p[1] * p[1]).sqrt() - 0.04).abs() > 0.01
                    || !(-0.01..=0.11).contains(&p[2])
                    || p[1] < -0.01
            };
            let stray = kept.iter().filter(|p| far(p)).count();
            let surface = kept.iter().filter(|p| on_surface(p)).count();
            assert!(stray * 100 <= kept.len(), "{n}: {stray} far stray points of {} kept", kept.len());
            assert!(surface * 100 >= 99 * n, "{n}: {surface} of {n} surface points kept");
            assert!(sub.len() >= 350, "{n}: only {} points in the subsample", sub.len());
            // Even: both ends of the arc and of the height are represented.
            let (lo_a, hi_a) = sub.iter().filter(|p| on_surface(p)).fold((f64::MAX, f64::MIN), |(lo, hi), p| {
                let a = p[1].atan2(p[0]);
                (lo.min(a), hi.max(a))
            });
            assert!(lo_a < 0.1 && hi_a > std::f64::consts::PI - 0.1, "{n}: arc {lo_a}..{hi_a}");
            let (lo_z, hi_z) = sub.iter().fold((f64::MAX, f64::MIN), |(lo, hi), p| (lo.min(p[2]), hi.max(p[2])));
            assert!(lo_z < 0.005 && hi_z > 0.095, "{n}: height {lo_z}..{hi_z}");
        }
    }

    /// A cloud that is mostly scatter is not thinned to the little that clusters.
    #[test]
    fn a_cloud_of_scatter_is_kept_whole() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let x: Vec<P3> = (0..3000).map(|_| [rng.random(), rng.random(), rng.random()]).collect();
        assert_eq!(drop_stray_points(&x, &mut rng).len(), x.len());
    }
}
