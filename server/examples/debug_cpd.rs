use graspd::geometry::sample_points;
use graspd::shape::cpd::{self, EmOptions, NonRigidOptions};
use graspd::tools::{self, Category, Split};
fn main() {
    let args: Vec<f64> = std::env::args().skip(1).map(|a| a.parse().unwrap()).collect();
    let (beta, lambda) = (args[0], args[1]);
    let fam = tools::family(Category::Mug).unwrap();
    let canon = fam.iter().find(|i| i.split == Split::Canonical).unwrap();
    let c = sample_points(&canon.mesh, 400, 1).unwrap();
    let kp: Vec<[f64; 3]> = canon.keypoints.iter().map(|k| k.position).collect();
    let mut all = vec![];
    for inst in fam.iter().filter(|i| i.split == Split::Train).take(4) {
        let x = sample_points(&inst.mesh, 1500, 3).unwrap();
        let opts = NonRigidOptions { beta, lambda, max_rank: 400, em: EmOptions { w: 0.0, max_iters: 150, tol: 1e-6 }, ..Default::default() };
        let r = cpd::non_rigid(&c, &x, &opts).unwrap();
        let moved = r.field.apply(&kp);
        let cm = r.field.apply(&graspd::shape::cpd::to_p3(&c));
        let d = cm.iter().zip(&r.moved).map(|(a, b)| ((a[0]-b.x).powi(2)+(a[1]-b.y).powi(2)+(a[2]-b.z).powi(2)).sqrt()).fold(0.0, f64::max);
        // keypoint via nearest canonical sample's moved position
        let nn: Vec<f64> = kp.iter().zip(&inst.keypoints).map(|(k, b)| { let i = (0..c.len()).min_by(|&i, &j| ((c[i].coords - nalgebra::Vector3::from(*k)).norm()).total_cmp(&(c[j].coords - nalgebra::Vector3::from(*k)).norm())).unwrap(); (r.moved[i].coords - nalgebra::Vector3::from(b.position)).norm()*1e3 }).collect();
        println!("   field vs moved max {:.2} mm; nn-kp err {:?}", d*1e3, nn.iter().map(|x| x.round()).collect::<Vec<_>>());
        let err: Vec<f64> = moved.iter().zip(&inst.keypoints).map(|(a, b)| ((a[0]-b.position[0]).powi(2)+(a[1]-b.position[1]).powi(2)+(a[2]-b.position[2]).powi(2)).sqrt()*1e3).collect();
        println!("{} sigma {:.2} mm rank {} kp err {:?}", inst.name, r.report.sigma2.sqrt()*1e3, r.kernel_rank, err.iter().map(|x| x.round()).collect::<Vec<_>>());
        all.extend(err);
    }
    all.sort_by(f64::total_cmp);
    println!("median {:.1}", all[all.len()/2]);
}
