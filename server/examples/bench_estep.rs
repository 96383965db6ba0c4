use graspd::shape::estep::{EStep, Posteriors};
use rand::{Rng, SeedableRng};
fn main() {
    let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    for (n, m) in [(80usize, 100usize), (400, 400), (1024, 1024)] {
        let x: Vec<[f64; 3]> = (0..n).map(|_| [r.random(), r.random(), r.random()]).collect();
        let y: Vec<[f64; 3]> = (0..m).map(|_| [r.random(), r.random(), r.random()]).collect();
        let mut e = EStep::new(&x);
        let mut p = Posteriors::default();
        let reps = 20_000_000 / (n * m) + 1;
        let t = std::time::Instant::now();
        for _ in 0..reps {
            e.run(&y, 0.5, 0.1, &mut p);
        }
        let dt = t.elapsed().as_secs_f64() / reps as f64;
        println!("{n}x{m}: {:.1} us per E-step, {:.2} ns per pair", dt * 1e6, dt * 1e9 / (n * m) as f64);
    }
}
