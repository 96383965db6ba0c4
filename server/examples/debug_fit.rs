use graspd::geometry::sample_points;
use graspd::shape::{builtin, Registrar, RegisterOptions};
use graspd::tools::{self, Category, Split};
fn main() {
    let cat = Category::Mug;
    let space = builtin::load_or_build(cat, std::path::Path::new("assets/spaces"), |_, _| {}).unwrap();
    let fam = tools::family(cat).unwrap();
    // Deformation at training latents reproduces the training keypoints?
    for (i, inst) in fam.iter().filter(|i| i.split == Split::Train).enumerate().take(3) {
        let lat = &space.train_latents[i];
        let kp: Vec<[f64; 3]> = space.keypoints.iter().map(|k| k.position).collect();
        let moved = space.deform(&kp, lat);
        let err: Vec<f64> = moved.iter().zip(&inst.keypoints).map(|(a, b)| ((a[0]-b.position[0]).powi(2)+(a[1]-b.position[1]).powi(2)+(a[2]-b.position[2]).powi(2)).sqrt()*1e3).collect();
        println!("{} latent {:?}\n  kp err at train latent (mm) {:?}", inst.name, lat.iter().map(|x| (x*100.0).round()/100.0).collect::<Vec<_>>(), err.iter().map(|x| x.round()).collect::<Vec<_>>());
    }
    let reg = Registrar::new(space);
    for inst in fam.iter().filter(|i| i.split == Split::Train).take(3) {
        let pts = sample_points(&inst.mesh, 2000, 5).unwrap();
        let r = reg.register(&pts, &RegisterOptions::default()).unwrap();
        let err: Vec<f64> = r.keypoints.iter().zip(&inst.keypoints).map(|(a, b)| ((a.position[0]-b.position[0]).powi(2)+(a.position[1]-b.position[1]).powi(2)+(a.position[2]-b.position[2]).powi(2)).sqrt()*1e3).collect();
        println!("{} full-cloud fit: latent {:?} scale {:.3} rot {:?} t {:?} fit {:?}\n  kp err {:?}", inst.name, r.latent.iter().map(|x| (x*100.0).round()/100.0).collect::<Vec<_>>(), r.scale, r.rotation_cloud_from_canonical.euler_angles(), r.translation_cloud_from_canonical.as_slice(), r.fit, err.iter().map(|x| x.round()).collect::<Vec<_>>());
    }
}
