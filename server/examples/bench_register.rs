//! Registration time per stage on the test views of one category (the
//! 2,000-point target of the shape-engine issue is a subsample of these).
//! `cargo run --release --example bench_register -- mug [repeats]`; set
//! VIEWPOINT=known or VIEWPOINT=unknown to time one of the two cases only;
//! REGISTER_OPTIONS='{"race_points": 300}' lays options over the defaults;
//! FULL_VIEWS=1 registers the whole views instead of 2,000-point subsamples,
//! DENSE_VIEWS=K each point of the whole views K times (see common/views.rs);
//! SPACE=FILE registers with that shape-space artefact instead of the built-in one.
//! Besides the percentiles it prints the mean of each view's fastest fit
//! (the figure to compare builds by on a shared host).
#[path = "common/views.rs"]
mod views;

use graspd::eval::grasp::percentile;
use graspd::shape::{builtin, RegisterOptions, Registrar};
use graspd::tools::Category;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let category: Category = args.get(1).map_or("mug", |s| s.as_str()).parse()?;
    let repeats: usize = args.get(2).map_or(Ok(20), |s| s.parse())?;
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../assets/spaces");
    let space = match std::env::var_os("SPACE") {
        Some(path) => graspd::shape::ShapeSpace::load(std::path::Path::new(&path))?,
        None => builtin::load_or_build(category, &root, |_, _| {})?,
    };
    let registrar = Registrar::new(space);
    let views = views::test_views(category)?;
    let mut base = serde_json::to_value(RegisterOptions::default())?;
    if let Ok(over) = std::env::var("REGISTER_OPTIONS") {
        let over: serde_json::Map<String, serde_json::Value> = serde_json::from_str(&over)?;
        for (k, v) in over {
            base[k] = v;
        }
    }
    let base: RegisterOptions = serde_json::from_value(base)?;
    let modes: &[bool] = match std::env::var("VIEWPOINT").as_deref() {
        Ok("known") => &[true],
        Ok("unknown") => &[false],
        _ => &[false, true],
    };
    for &known_viewpoint in modes {
        let mut total = Vec::new();
        let mut iterations = 0usize;
        let mut stages = [Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new()];
        // Each view's fastest fit over the repeats: on a shared host other
        // tenants only ever add time, so the minima compare two builds run
        // an hour apart better than the percentiles do.
        let mut fastest = vec![f64::INFINITY; views.len()];
        for _ in 0..repeats {
            for (view, fastest) in views.iter().zip(fastest.iter_mut()) {
                let opts = RegisterOptions { viewpoint: known_viewpoint.then_some(view.viewpoint), ..base };
                let t0 = std::time::Instant::now();
                let r = registrar.register(&view.cloud, &opts)?;
                let ms = t0.elapsed().as_secs_f64() * 1e3;
                total.push(ms);
                *fastest = fastest.min(ms);
                iterations += r.iterations;
                let s = r.stage_ms;
                for (v, x) in stages.iter_mut().zip([s.coarse, s.race, s.refine, s.polish, s.quality]) {
                    v.push(x);
                }
            }
        }
        println!(
            "{} viewpoint {}: {} fits, total p50 {:.2} ms p99 {:.2} ms; stage p50 coarse {:.2} race {:.2} refine {:.2} polish {:.2} quality {:.2} ms; {:.1} EM iterations a fit",
            category.name(),
            if known_viewpoint { "known  " } else { "unknown" },
            total.len(),
            percentile(&total, 0.5),
            percentile(&total, 0.99),
            percentile(&stages[0], 0.5),
            percentile(&stages[1], 0.5),
            percentile(&stages[2], 0.5),
            percentile(&stages[3], 0.5),
            percentile(&stages[4], 0.5),
            iterations as f64 / (repeats * views.len()) as f64,
        );
        println!(
            "{} viewpoint {}: each view's fastest of {repeats} fits, mean over the {} views {:.2} ms",
            category.name(),
            if known_viewpoint { "known  " } else { "unknown" },
            views.len(),
            fastest.iter().sum::<f64>() / views.len() as f64,
        );
    }
    Ok(())
}
