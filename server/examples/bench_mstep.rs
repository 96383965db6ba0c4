//! Times the M-step's normal operator Qᵀ(p1 ⊙ Q v) + reg ⊙ v on each SIMD
//! level, at the peer benchmark's size (1,024 points, rank 369), one thread.
//! `cargo run --release --example bench_mstep`
use graspd::shape::mstep::LowRankFactor;
use graspd::simd::Simd;
use rand::{Rng, SeedableRng};

fn main() {
    let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let m: usize = std::env::var("M").ok().and_then(|s| s.parse().ok()).unwrap_or(1024);
    let k: usize = std::env::var("K").ok().and_then(|s| s.parse().ok()).unwrap_or(369);
    let q = faer::Mat::from_fn(m, k, |_, _| r.random::<f64>() - 0.5);
    let p1: Vec<f64> = (0..m).map(|_| r.random()).collect();
    let reg: Vec<f64> = (0..k).map(|_| r.random()).collect();
    let v: Vec<[f64; 3]> = (0..k).map(|_| [r.random(), r.random(), r.random()]).collect();
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().expect("a one-thread pool");
    for level in Simd::available() {
        let f = LowRankFactor::with_level(q.as_ref(), level);
        let best = pool.install(|| {
            (0..7)
                .map(|_| {
                    let t = std::time::Instant::now();
                    for _ in 0..200 {
                        std::hint::black_box(f.normal_times(&p1, &reg, &v));
                    }
                    t.elapsed().as_secs_f64() / 200.0
                })
                .fold(f64::INFINITY, f64::min)
        });
        let flops = (4 * 3 * m * k) as f64;
        println!("{level:?}: {:.1} us per normal product ({:.1} GFLOP/s)", best * 1e6, flops / best * 1e-9);
    }
}
