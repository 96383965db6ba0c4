//! The view's preparation before a fit, on the mug's test views (about 2,000
//! points each): stray removal and the even 400- and 800-point subsets the
//! refine and the polish take, mean time over 20 passes, three times; first
//! a checksum of the points they keep (a change that means to keep the same
//! points must keep it). `cargo run --release --example bench_subsets`.
#[path = "common/views.rs"]
mod views;
use graspd::shape::sampling::{drop_stray_points, even_subsample};
use rand::SeedableRng;
fn main() -> Result<(), Box<dyn std::error::Error>> {
    let views = views::test_views(graspd::tools::Category::Mug)?;
    let clouds: Vec<Vec<[f64; 3]>> = views.iter().map(|v| v.cloud.iter().map(|p| [p.x, p.y, p.z]).collect()).collect();
    let mut sum = 0.0f64;
    let mut count = 0usize;
    for x in &clouds {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
        let all = drop_stray_points(x, &mut rng);
        let f = even_subsample(&all, 400, &mut rng);
        let p = even_subsample(&all, 800, &mut rng);
        for (i, q) in all.iter().chain(&f).chain(&p).enumerate() {
            sum += (i % 7) as f64 * q[0] + q[1] * 3.0 + q[2];
            count += 1;
        }
    }
    println!("checksum {sum:.12} {count}");
    for _ in 0..3 {
        let (mut a, mut b, mut c) = (0.0, 0.0, 0.0);
        for _ in 0..20 {
            for x in &clouds {
                let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
                let t = std::time::Instant::now();
                let all = drop_stray_points(x, &mut rng);
                a += t.elapsed().as_secs_f64();
                let t = std::time::Instant::now();
                let f = even_subsample(&all, 400, &mut rng);
                b += t.elapsed().as_secs_f64();
                let t = std::time::Instant::now();
                let p = even_subsample(&all, 800, &mut rng);
                c += t.elapsed().as_secs_f64();
                std::hint::black_box((f, p));
            }
        }
        let n = 20.0 * clouds.len() as f64;
        println!("stray {:.1} us, subset400 {:.1} us, subset800 {:.1} us", a / n * 1e6, b / n * 1e6, c / n * 1e6);
    }
    Ok(())
}
