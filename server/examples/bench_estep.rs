//! E-step kernels' time on fixed inputs, the fastest of many repeats (the
//! least disturbed by a shared host): the dense isotropic sums on random
//! points, and the surfel sums (`EStep::run_surfels`) on a mug-like view.
//! `cargo run --release --example bench_estep`; GRASPD_SIMD=avx2 or
//! portable caps the kernels.
use graspd::shape::estep::{EStep, Posteriors, Surfels, P3};
use rand::{Rng, SeedableRng};
use std::time::Instant;

/// The fastest of `reps` runs of `f`, seconds.
fn fastest(reps: usize, mut f: impl FnMut()) -> f64 {
    (0..reps)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

/// A mug without its handle: outer and inner walls and the floor, points and
/// outward normals, `n` points drawn uniformly by area.
fn mug(n: usize, rng: &mut impl Rng) -> (Vec<P3>, Vec<P3>) {
    let (ro, ri, h) = (0.040, 0.035, 0.095);
    let areas = [std::f64::consts::TAU * ro * h, std::f64::consts::TAU * ri * h, std::f64::consts::PI * ri * ri];
    let total: f64 = areas.iter().sum();
    (0..n)
        .map(|_| {
            let (a, z): (f64, f64) = (rng.random_range(0.0..std::f64::consts::TAU), rng.random_range(0.0..h));
            let u = rng.random_range(0.0..total);
            if u < areas[0] {
                ([ro * a.cos(), ro * a.sin(), z], [a.cos(), a.sin(), 0.0])
            } else if u < areas[0] + areas[1] {
                ([ri * a.cos(), ri * a.sin(), z], [-a.cos(), -a.sin(), 0.0])
            } else {
                let r = ri * rng.random_range(0.0f64..1.0).sqrt();
                ([r * a.cos(), r * a.sin(), 0.005], [0.0, 0.0, 1.0])
            }
        })
        .unzip()
}

fn main() {
    let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    for (n, m) in [(80usize, 100usize), (400, 400), (1024, 1024)] {
        let x: Vec<P3> = (0..n).map(|_| [r.random(), r.random(), r.random()]).collect();
        let y: Vec<P3> = (0..m).map(|_| [r.random(), r.random(), r.random()]).collect();
        let mut e = EStep::new(&x);
        e.single_precision = true;
        let mut p = Posteriors::default();
        let reps = 2_000_000 / (n * m) + 5;
        let dt = fastest(20, || (0..reps).for_each(|_| e.run(&y, 0.5, 0.1, &mut p))) / reps as f64;
        println!("dense f32 {n}x{m}: {:.1} us per E-step, {:.2} ns per pair", dt * 1e6, dt * 1e9 / (n * m) as f64);
    }
    // The polish's case: 800 model surfels, 800 observed points on the half
    // of the outer wall and floor a camera sees, 1 mm of depth noise.
    let (y, normals) = mug(800, &mut r);
    let (seen, _) = mug(4000, &mut r);
    let x: Vec<P3> = seen
        .iter()
        .filter(|p| p[0] > 0.0 && (p[0] * p[0] + p[1] * p[1]).sqrt() > 0.038)
        .take(800)
        .map(|p| [p[0] + r.random_range(-0.001..0.001), p[1], p[2]])
        .collect();
    let s = Surfels { normals: &normals, tangent_sigma2: 0.0054f64.powi(2), normal_sigma2: 0.0009f64.powi(2) };
    let mut e = EStep::new(&x);
    e.cutoff_sigmas = 4.0;
    let mut p = Posteriors::default();
    let dt = fastest(200, || {
        e.run_surfels(&y, &s, None, 0.1, &mut p);
    });
    println!("surfels {}x{}: {:.1} us per E-step", x.len(), y.len(), dt * 1e6);
    // The refine's case: 400 × 400, isotropic, cutoff 5σ: the dense sums, the
    // neighbour list (built once: here the model does not move) and the blocks.
    let x: Vec<P3> = x.iter().step_by(2).copied().collect();
    let (y, _) = mug(400, &mut r);
    for sigma in [0.003, 0.005, 0.008] {
        let s2: f64 = sigma * sigma;
        let mut times = Vec::new();
        for mode in 0..3 {
            let mut e = EStep::new(&x);
            e.single_precision = true;
            e.cutoff_sigmas = 5.0;
            e.truncate_below = if mode == 0 { 0.0 } else { 1.0 };
            e.blocked = mode == 2;
            times.push(fastest(200, || e.run_weighted(&y, None, s2, 0.1, &mut p)));
        }
        println!(
            "isotropic {}x{} sigma {:.0} mm: dense {:.1} us, listed {:.1} us, blocked {:.1} us",
            x.len(),
            y.len(),
            sigma * 1e3,
            times[0] * 1e6,
            times[1] * 1e6,
            times[2] * 1e6
        );
    }
}
