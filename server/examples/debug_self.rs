use graspd::geometry::sample_points;
use graspd::shape::cpd::{self, EmOptions, NonRigidOptions};
use graspd::tools::{self, Category, Split};
fn main() {
    let fam = tools::family(Category::Mug).unwrap();
    let canon = fam.iter().find(|i| i.split == Split::Canonical).unwrap();
    let c = sample_points(&canon.mesh, 400, 1).unwrap();
    let kp: Vec<[f64; 3]> = canon.keypoints.iter().map(|k| k.position).collect();
    for (label, x) in [("same", c.clone()), ("other1500", sample_points(&canon.mesh, 1500, 3).unwrap())] {
        for (lambda, rank, iters) in [(1.0, 400, 150), (10.0, 400, 150), (1.0, 60, 150), (1.0, 400, 30)] {
            let opts = NonRigidOptions { beta: 0.6, lambda, max_rank: rank, em: EmOptions { w: 0.0, max_iters: iters, tol: 0.0 }, ..Default::default() };
            let r = cpd::non_rigid(&c, &x, &opts).unwrap();
            let moved = r.field.apply(&kp);
            let err: Vec<f64> = moved.iter().zip(&kp).map(|(a, b)| ((a[0]-b[0]).powi(2)+(a[1]-b[1]).powi(2)+(a[2]-b[2]).powi(2)).sqrt()*1e3).collect();
            let disp = r.moved.iter().zip(&c).map(|(a, b)| (a - b).norm()).fold(0.0, f64::max) * 1e3;
            println!("{label} lambda {lambda} rank {} iters {iters}: sigma {:.3} mm max disp {:.1} mm kp err {:?}", r.kernel_rank, r.report.sigma2.sqrt()*1e3, disp, err.iter().map(|x| (x*10.0).round()/10.0).collect::<Vec<_>>());
        }
    }
}
