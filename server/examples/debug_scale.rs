use graspd::geometry::sample_points;
use graspd::shape::cpd::{self, EmOptions, NonRigidOptions};
use graspd::tools::{self, Category, Split};
fn main() {
    let fam = tools::family(Category::Mug).unwrap();
    let canon = fam.iter().find(|i| i.split == Split::Canonical).unwrap();
    let c = sample_points(&canon.mesh, 400, 1).unwrap();
    let kp: Vec<[f64; 3]> = canon.keypoints.iter().map(|k| k.position).collect();
    for (sx, sz) in [(1.0, 1.0), (1.1, 1.1), (1.0, 1.2), (1.15, 0.85)] {
        let mut m = canon.mesh.clone();
        m.map_vertices(|p| nalgebra::Point3::new(p.x * sx, p.y * sx, p.z * sz));
        let x = sample_points(&m, 1500, 3).unwrap();
        for w in [0.0, 0.1] {
            let opts = NonRigidOptions { beta: 0.6, lambda: 1.0, max_rank: 400, em: EmOptions { w, max_iters: 150, tol: 1e-6 }, ..Default::default() };
            let r = cpd::non_rigid(&c, &x, &opts).unwrap();
            let moved = r.field.apply(&kp);
            let err: Vec<f64> = moved.iter().zip(&kp).map(|(a, b)| ((a[0]-b[0]*sx).powi(2)+(a[1]-b[1]*sx).powi(2)+(a[2]-b[2]*sz).powi(2)).sqrt()*1e3).collect();
            println!("scale ({sx},{sz}) w {w}: iters {} sigma {:.2} mm kp err {:?}", r.report.iterations, r.report.sigma2.sqrt()*1e3, err.iter().map(|x| (x*10.0).round()/10.0).collect::<Vec<_>>());
        }
    }
}
