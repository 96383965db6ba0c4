use graspd::geometry::{sample_points_even};
use graspd::shape::cpd::{self, EmOptions, NonRigidOptions};
use graspd::tools::{self, Category, Split};
fn main() {
    let fam = tools::family(Category::Mug).unwrap();
    let canon = fam.iter().find(|i| i.split == Split::Canonical).unwrap();
    let kp: Vec<[f64; 3]> = canon.keypoints.iter().map(|k| k.position).collect();
    for (m, n) in [(400, 1600), (400, 3200), (600, 2400)] {
        let c = sample_points_even(&canon.mesh, m, 1).unwrap();
        for (beta, lambda) in [(0.8, 3.0), (0.8, 10.0), (1.0, 3.0)] {
            let mut all = vec![];
            let mut idt = vec![];
            for inst in fam.iter().filter(|i| i.split != Split::Test).take(5) {
                let x = sample_points_even(&inst.mesh, n, 3).unwrap();
                let opts = NonRigidOptions { beta, lambda, max_rank: 400, em: EmOptions { w: 0.0, max_iters: 100, tol: 1e-5 }, ..Default::default() };
                let r = cpd::non_rigid(&c, &x, &opts).unwrap();
                let moved = r.field.apply(&kp);
                for (a, b) in moved.iter().zip(&inst.keypoints) {
                    let e = ((a[0]-b.position[0]).powi(2)+(a[1]-b.position[1]).powi(2)+(a[2]-b.position[2]).powi(2)).sqrt()*1e3;
                    if inst.split == Split::Canonical { idt.push(e) } else { all.push(e) }
                }
            }
            all.sort_by(f64::total_cmp);
            println!("M {m} N {n} beta {beta} lambda {lambda}: self max {:.1} mm; train median {:.1} p90 {:.1} max {:.1}", idt.iter().cloned().fold(0.0, f64::max), all[all.len()/2], all[all.len()*9/10], all[all.len()-1]);
        }
    }
}
