//! Times the CPD kernel factor (`LowRankKernel::new`) on even samples of the
//! canonical mug, normalised as CPD normalises them, β 0.5, rank tolerance
//! 1e-8 (`graspd cpd`'s defaults): best of 7 on pools of 1 and 2 threads.
//! `cargo run --release --example bench_kernel -- [points]`
use graspd::shape::cpd::Normalization;
use graspd::shape::kernel::LowRankKernel;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // As `graspd` runs faer: on one thread, so that its bits do not depend on the core count.
    faer::set_global_parallelism(faer::Par::Seq);
    let n: usize = std::env::args().nth(1).map_or(Ok(1024), |s| s.parse())?;
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../assets/tools/mug/mug_canonical.obj");
    let mesh = graspd::io::read_mesh(&root)?.mesh;
    let pts: Vec<[f64; 3]> =
        graspd::geometry::sample_points_even(&mesh, n, 7)?.iter().map(|p| [p.x, p.y, p.z]).collect();
    let norm = Normalization::of(&pts);
    let y: Vec<[f64; 3]> = pts.iter().map(|p| norm.forward(p)).collect();
    for threads in [1, 2] {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build()?;
        let (mut best, mut rank) = (f64::INFINITY, 0);
        for _ in 0..7 {
            let t = std::time::Instant::now();
            let k = pool.install(|| LowRankKernel::new(&y, 0.5, 1024, 1e-8));
            best = best.min(t.elapsed().as_secs_f64());
            rank = k.rank();
        }
        println!("{n} points, {threads} thread(s): rank {rank}, kernel factor {:.1} ms", best * 1e3);
    }
    Ok(())
}
