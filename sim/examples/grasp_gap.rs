//! Diagnostic: the in-process grasp (training latent, true pose) beside the
//! grasp from the camera's view (registered as the daemon does), in the
//! tool's frame, and Drive-nail episodes with hybrids of the two.
//! `cargo run --release -p graspd-sim --example grasp_gap -- hammer_train_00 0`;
//! a mug (`mug_train_01`) runs Place-mug episodes instead.
//! `GAP_SENS=MM`: the in-process grasp moved ±MM mm or ±MM° along each of
//! the wrist's axes; `GAP_GRID=MM [GAP_GRID_CENTRE=x,y,z]`: success over a
//! 3×3×3 grid of wrist shifts of ±MM mm (about a centre, mm, wrist frame),
//! about the camera's grasp for a test tool or with `GAP_CAMERA=1`.

use graspd::grasp::transfer::{solve_transferred, Similarity, TransferModel, TransferredTool};
use graspd::grasp::{Demonstration, GraspSolver, PreGraspOptions, SolveOptions, ToolCollider};
use graspd::shape::builtin;
use graspd::tools::{self, Category, Split};
use graspd_sim::camera::{LabFrame, SceneCamera};
use graspd_sim::carry::TaskRig;
use graspd_sim::daemon::DaemonGrasper;
use graspd_sim::hand::HandAsset;
use graspd_sim::nail::{face_of, run_nail, NailFixture, NailSetup};
use graspd_sim::place::{run_place, PlaceSetup};
use graspd_sim::plan::{GraspPlan, GraspPlanner, HandStart};
use nalgebra::{Isometry3, Point3};

fn iso_diff(a: &Isometry3<f64>, b: &Isometry3<f64>) -> String {
    let d = a.inverse() * b;
    format!(
        "Δt {:5.1} mm (in a's frame {:6.1} {:6.1} {:6.1}) Δr {:4.1}°",
        1e3 * (a.translation.vector - b.translation.vector).norm(),
        1e3 * d.translation.x,
        1e3 * d.translation.y,
        1e3 * d.translation.z,
        d.rotation.angle().to_degrees()
    )
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let name = args.get(1).cloned().unwrap_or("hammer_train_00".into());
    let seeds: Vec<u64> = args.get(2).map_or(vec![0], |s| s.split(',').map(|v| v.parse().unwrap()).collect());
    let asset = HandAsset::default_sih()?;
    let hand = asset.model().clone();
    let category = if name.starts_with("mug") { Category::Mug } else { Category::Hammer };
    let family = tools::family(category)?;
    let instance = family.iter().find(|i| i.name == name).unwrap().clone();
    let canonical = family.iter().find(|i| i.split == Split::Canonical).unwrap().clone();
    let space = builtin::load_or_build(category, &graspd_sim::plan::spaces_dir(), |_, _| {})?;
    let demo = Demonstration::builtin(category)?;
    let kp = demo.keypoints(&hand)?;
    let k = space.instances.iter().position(|n| n == &name).filter(|_| std::env::var_os("GAP_CAMERA").is_none());
    let Some(k) = k else {
        // A test tool has no training latent (or GAP_CAMERA is set): only
        // the grid, about the camera's grasp.
        return camera_grid(&asset, &instance, category, &space, &seeds);
    };
    let true_latent = space.train_latents[k].clone();

    let mut planner = GraspPlanner::new(&hand, category, 0)?;
    let base = planner.plan(&instance)?;
    let mut grasper =
        DaemonGrasper::in_process(&hand, category, space.clone(), SceneCamera::default(), LabFrame::default())?;
    let setup = NailSetup::default();
    let table_z = graspd_sim::scene::Table::default().top_z;
    let place = PlaceSetup::default();
    let is_mug = category == Category::Mug;
    let face = if is_mug { Default::default() } else { face_of(&instance)? };
    let board = setup.ranges.sample(0, table_z).board;
    let mut rig = if is_mug {
        TaskRig::build(&asset, &mut planner, &instance, &place.base, "place", Vec::new(), Vec::new())?
    } else {
        TaskRig::build(
            &asset,
            &mut planner,
            &instance,
            &setup.base,
            "nail",
            setup.fixture.bodies(&board),
            NailFixture::contact(),
        )?
    };
    let model = TransferModel::new(&space, &kp, &canonical.mesh);
    let true_tool = TransferredTool::from_latent(&model, &true_latent)?;
    println!("true registered-shape lowest z (tool frame) {:.4}", true_tool.lowest_z());
    println!("mode σ {:?}", space.variances.iter().map(|v| format!("{:.2}", v.sqrt())).collect::<Vec<_>>());
    for (i, l) in space.train_latents.iter().enumerate() {
        println!(
            "  train {:2} latent/σ {:?}",
            i,
            l.iter().zip(&space.variances).map(|(a, v)| format!("{:.2}", a / v.sqrt())).collect::<Vec<_>>()
        );
    }
    let posed = |latent: &[f64], pose: &Similarity| -> TransferredTool {
        let mut t = TransferredTool::from_latent(&model, latent).unwrap();
        for p in t.targets.iter_mut().chain(t.mesh.vertices.iter_mut()) {
            *p = pose.apply(p);
        }
        t.collider = ToolCollider::new(&t.mesh, Isometry3::identity()).unwrap();
        t.pose = *pose;
        t
    };
    let solve = |tool: &TransferredTool, table: Option<f64>| -> GraspPlan {
        let mut solver = GraspSolver::new(&hand, SolveOptions::default());
        let out = solve_transferred(&mut solver, &demo, tool, table, &PreGraspOptions::default()).unwrap();
        GraspPlan {
            grasp: out.grasp,
            pregrasp: out.pregrasp.grasp,
            pregrasp_collision_free: out.pregrasp.collision_free,
            source: "hybrid",
            task_space_distance_cm: out.task_space_distance_cm,
            demo_keypoints: base.demo_keypoints.clone(),
            latent: true_latent.clone(),
            start: HandStart::PreGrasp,
        }
    };
    {
        let b = instance.mesh.vertices.iter().fold(([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]), |(lo, hi), v| {
            ([lo[0].min(v.x), lo[1].min(v.y), lo[2].min(v.z)], [hi[0].max(v.x), hi[1].max(v.y), hi[2].max(v.z)])
        });
        println!("instance bbox {:?}", b);
        for k in instance.keypoints.iter() {
            println!(
                "  tool kp {:16} {:?}",
                k.name,
                k.position.iter().map(|v| format!("{:.3}", v)).collect::<Vec<_>>()
            );
        }
        let mut kin = graspd::hand::HandKinematics::new(&hand);
        kin.update(&hand, &base.grasp.wrist_pose_world, &base.grasp.actuated);
        for (i, p) in kin.keypoints().iter().enumerate() {
            println!("  hand kp {:12} ({:.3} {:.3} {:.3})", hand.keypoints()[i].name, p.x, p.y, p.z);
        }
        let r = base.grasp.wrist_pose_world.rotation.to_rotation_matrix();
        println!(
            "  palm axes in tool frame: x {:?} y {:?} z {:?}",
            r.matrix().column(0).as_slice(),
            r.matrix().column(1).as_slice(),
            r.matrix().column(2).as_slice()
        );
        println!("  wrist at {:?}", base.grasp.wrist_pose_world.translation.vector.as_slice());
    }
    for &seed in &seeds {
        let episode = setup.ranges.sample(seed, table_z);
        let place_episode = place.ranges.sample(seed, table_z);
        let start = if is_mug { place_episode.start } else { episode.start };
        let d = grasper.grasp(&hand, category, &instance.mesh, &start, table_z, demo.table, seed)?;
        let table_tool = (start.inverse() * Point3::new(0.0, 0.0, table_z)).z;
        let s = &d.tool_from_canonical;
        println!(
            "seed {seed}: reg offset {:.1} mm ({:.1} {:.1} {:.1}) turn {:.2}° scale {:.4}; table in tool frame {:.4}",
            1e3 * s.translation.norm(),
            1e3 * s.translation.x,
            1e3 * s.translation.y,
            1e3 * s.translation.z,
            s.rotation.angle().to_degrees(),
            s.scale,
            table_tool
        );
        println!("  latent true {:?}", true_latent.iter().map(|v| format!("{v:.2}")).collect::<Vec<_>>());
        println!("  latent reg  {:?}", d.latent.iter().map(|v| format!("{v:.2}")).collect::<Vec<_>>());
        println!("  grasp    wrist {}", iso_diff(&base.grasp.wrist_pose_world, &d.grasp.wrist_pose_world));
        println!("  pregrasp wrist {}", iso_diff(&base.pregrasp.wrist_pose_world, &d.pregrasp.wrist_pose_world));
        println!("  q grasp  inproc {:?}", base.grasp.actuated.iter().map(|v| format!("{v:.3}")).collect::<Vec<_>>());
        println!("  q grasp  camera {:?}", d.grasp.actuated.iter().map(|v| format!("{v:.3}")).collect::<Vec<_>>());
        println!(
            "  q pre    inproc {:?}",
            base.pregrasp.actuated.iter().map(|v| format!("{v:.3}")).collect::<Vec<_>>()
        );
        println!("  q pre    camera {:?}", d.pregrasp.actuated.iter().map(|v| format!("{v:.3}")).collect::<Vec<_>>());
        let reg_targets: Vec<Point3<f64>> = space
            .deform_anchored(&kp.iter().map(|p| [p.x, p.y, p.z]).collect::<Vec<_>>(), &d.latent)
            .into_iter()
            .map(|z| s.apply(&Point3::from(z)))
            .collect();
        let dk: Vec<f64> = reg_targets.iter().zip(&base.demo_keypoints).map(|(a, b)| 1e3 * (a - b).norm()).collect();
        println!("  target keypoints Δ mm {:?}", dk.iter().map(|v| format!("{v:.1}")).collect::<Vec<_>>());
        let palm = base.grasp.wrist_pose_world.inverse();
        for (i, (a, b)) in reg_targets.iter().zip(&base.demo_keypoints).enumerate() {
            let dv = palm.rotation * (a - b);
            println!(
                "    kp {:2} {:12} Δ palm frame ({:5.1} {:5.1} {:5.1}) mm",
                i,
                hand.keypoints()[i].name,
                1e3 * dv.x,
                1e3 * dv.y,
                1e3 * dv.z
            );
        }
        // Surface: registered shape vs the true instance mesh (both tool frame).
        let reg_tool = posed(&d.latent, s);
        let samples = graspd::geometry::sample::sample_points(&instance.mesh, 3000, 1).unwrap();
        let nearest = |p: &Point3<f64>, m: &graspd::geometry::TriMesh| {
            m.vertices.iter().map(|v| (v - p).norm()).fold(f64::INFINITY, f64::min)
        };
        let mut e: Vec<f64> = samples.iter().map(|p| 1e3 * nearest(p, &reg_tool.mesh)).collect();
        e.sort_by(f64::total_cmp);
        let mut e2: Vec<f64> = samples.iter().map(|p| 1e3 * nearest(p, &true_tool.mesh)).collect();
        e2.sort_by(f64::total_cmp);
        let grip = base.grasp.wrist_pose_world.translation.vector;
        for (label, tool) in [
            ("reg", &reg_tool),
            ("true-latent", &true_tool),
            ("reg latent scale1", &posed(&d.latent, &Similarity::identity())),
        ] {
            let mut sd: Vec<f64> = samples
                .iter()
                .filter(|p| (p.coords - grip).norm() < 0.06)
                .filter_map(|p| tool.collider.signed_distance(p, 0.05).map(|(d, _)| 1e3 * d))
                .collect();
            sd.sort_by(f64::total_cmp);
            let n = sd.len();
            if n == 0 {
                println!("  no true surface within 6 cm of the wrist ({label})");
                continue;
            }
            println!("  true surface within 6 cm of the wrist → {label} shape signed mm: p10 {:.1} p50 {:.1} p90 {:.1} (n {n})", sd[n / 10], sd[n / 2], sd[9 * n / 10]);
        }
        println!("  true surface → nearest vertex of reg shape mm p50 {:.1} p90 {:.1}; of true-latent shape p50 {:.1} p90 {:.1}", e[1500], e[2700], e2[1500], e2[2700]);
        let unit = Similarity { scale: 1.0, ..*s };
        // The registered shape, but the demonstration's offsets from the
        // surface kept at the hand's size (the scale moves the anchors only).
        let unscaled_offsets = {
            let canon = posed(&d.latent, &Similarity::identity());
            let mut t = posed(&d.latent, s);
            for (target, z) in t.targets.iter_mut().zip(&canon.targets) {
                let (dist, n) = canon.collider.signed_distance(z, 1.0).unwrap();
                let anchor = z - dist * n;
                *target = s.apply(&anchor) + s.rotation * (z - anchor);
            }
            t
        };
        let variants: Vec<(&str, GraspPlan)> = vec![
            ("reg, offsets unscaled, table true", solve(&unscaled_offsets, Some(table_tool))),
            ("inprocess", base.clone()),
            ("camera", GraspPlan { grasp: d.grasp.clone(), pregrasp: d.pregrasp.clone(), ..base.clone() }),
            ("true latent, reg pose+scale, table true", solve(&posed(&true_latent, s), Some(table_tool))),
            ("true latent, reg pose, scale 1, table true", solve(&posed(&true_latent, &unit), Some(table_tool))),
            (
                "reg latent+scale, true pose, table true",
                solve(&posed(&d.latent, &Similarity { scale: s.scale, ..Similarity::identity() }), Some(table_tool)),
            ),
            ("reg latent, true pose, table true", solve(&posed(&d.latent, &Similarity::identity()), Some(table_tool))),
            (
                "true latent, true pose, table true",
                solve(&posed(&true_latent, &Similarity::identity()), Some(table_tool)),
            ),
            ("true latent, true pose, table lowest", solve(&true_tool, Some(true_tool.lowest_z()))),
            ("reg all, table lowest", {
                let t = posed(&d.latent, s);
                let z = t.lowest_z();
                solve(&t, Some(z))
            }),
            ("reg all, table true", solve(&posed(&d.latent, s), Some(table_tool))),
        ];
        let trace_on = std::env::var_os("GAP_TRACE").is_some();
        // One episode of the tool's task with `plan`: success, clearance after the lift.
        let run_task = |rig: &mut TaskRig, plan: &GraspPlan| -> Result<(bool, f64), graspd_sim::engine::SimError> {
            let (scene, data, points) = (&rig.scene, &mut rig.data, &rig.height_points);
            Ok(if is_mug {
                let o = run_place(
                    scene,
                    data,
                    &hand,
                    plan,
                    points,
                    &place_episode,
                    &place.script,
                    place.base.physics.control_hz,
                )?;
                (o.success, o.clearance_after_lift_m)
            } else {
                let o = run_nail(
                    scene,
                    data,
                    &hand,
                    plan,
                    points,
                    &face,
                    &episode,
                    &setup.script,
                    setup.base.physics.control_hz,
                )?;
                (o.success, o.clearance_after_lift_m)
            })
        };
        if let Some(mm) = std::env::var("GAP_GRID").ok().and_then(|v| v.parse::<f64>().ok()) {
            // Success over a 3×3×3 grid of wrist shifts (wrist frame, ±mm),
            // the pre-grasp shifted with the grasp: where the basin lies.
            let c: Vec<f64> = std::env::var("GAP_GRID_CENTRE")
                .map_or(vec![0.0; 3], |v| v.split(',').map(|x| x.parse().unwrap()).collect());
            let mut line = String::new();
            for (i, dx) in [-mm, 0.0, mm].iter().enumerate() {
                for dy in [-mm, 0.0, mm] {
                    for dz in [-mm, 0.0, mm] {
                        let delta = Isometry3::translation(1e-3 * (dx + c[0]), 1e-3 * (dy + c[1]), 1e-3 * (dz + c[2]));
                        let mut plan = base.clone();
                        for g in [&mut plan.grasp, &mut plan.pregrasp] {
                            *g = graspd::grasp::Grasp::new(&hand, g.wrist_pose_world * delta, g.actuated.clone());
                        }
                        let (success, clearance) = run_task(&mut rig, &plan)?;
                        line.push(if success {
                            '#'
                        } else if clearance > 0.03 {
                            'l'
                        } else {
                            '.'
                        });
                    }
                    line.push(' ');
                }
                if i < 2 {
                    line.push_str("| ");
                }
            }
            println!("  grid ±{mm} mm (x: blocks, y: triples, z: within; #=success l=lifted .=not) {line}");
            continue;
        }
        if std::env::var_os("GAP_SENS").is_some() {
            let mm: f64 = std::env::var("GAP_SENS").unwrap().parse().unwrap_or(3.0);
            for axis in 0..6 {
                for sign in [-1.0, 1.0] {
                    let mut v = nalgebra::Vector3::zeros();
                    let mut plan = base.clone();
                    let delta = if axis < 3 {
                        v[axis] = sign * mm * 1e-3;
                        Isometry3::translation(v.x, v.y, v.z)
                    } else {
                        v[axis - 3] = sign * mm.to_radians();
                        Isometry3::rotation(v)
                    };
                    for g in [&mut plan.grasp, &mut plan.pregrasp] {
                        *g = graspd::grasp::Grasp::new(&hand, g.wrist_pose_world * delta, g.actuated.clone());
                    }
                    let (success, clearance) = run_task(&mut rig, &plan)?;
                    println!(
                        "  sens {} {:+} {mm}: success {:5} lift clear {:6.1} mm",
                        ["x", "y", "z", "rx", "ry", "rz"][axis],
                        sign,
                        success,
                        1e3 * clearance,
                    );
                }
            }
            continue;
        }
        let press_mm: f64 = std::env::var("GAP_PRESS_MM").ok().and_then(|v| v.parse().ok()).unwrap_or(0.0);
        let n = hand.palm_normal().into_inner();
        let variants: Vec<(&str, GraspPlan)> = variants
            .into_iter()
            .map(|(w, mut p)| {
                let g = &p.grasp;
                p.grasp = graspd::grasp::Grasp::new(
                    &hand,
                    g.wrist_pose_world * nalgebra::Translation3::from(1e-3 * press_mm * n),
                    g.actuated.clone(),
                );
                (w, p)
            })
            .collect();
        for (what, plan) in variants {
            if trace_on {
                trace_close(&rig, &hand, &plan, &episode.start, &setup)?;
            }
            if is_mug {
                let o = run_place(
                    &rig.scene,
                    &mut rig.data,
                    &hand,
                    &plan,
                    &rig.height_points,
                    &place_episode,
                    &place.script,
                    place.base.physics.control_hz,
                )?;
                println!(
                    "  {what:45} success {:5} dist {:5.1} mm lift clear {:6.1} mm  wristΔ {}",
                    o.success,
                    1e3 * o.final_distance_m,
                    1e3 * o.clearance_after_lift_m,
                    iso_diff(&base.grasp.wrist_pose_world, &plan.grasp.wrist_pose_world)
                );
                continue;
            }
            let o = run_nail(
                &rig.scene,
                &mut rig.data,
                &hand,
                &plan,
                &rig.height_points,
                &face,
                &episode,
                &setup.script,
                setup.base.physics.control_hz,
            )?;
            println!(
                "  {what:45} success {:5} depth {:5.1} mm lift clear {:6.1} mm held {:5}  wristΔ {}",
                o.success,
                1e3 * o.depth_m,
                1e3 * o.clearance_after_lift_m,
                o.held_at_end,
                iso_diff(&base.grasp.wrist_pose_world, &plan.grasp.wrist_pose_world)
            );
        }
    }
    Ok(())
}

/// `GAP_GRID` (default 3 mm, `GAP_GRID_CENTRE`) about the grasp from the
/// camera's view of a tool without a training latent (a test tool), Place
/// mug episodes (mugs) or Drive nail (hammers).
fn camera_grid(
    asset: &HandAsset,
    instance: &graspd::tools::Instance,
    category: Category,
    space: &graspd::shape::ShapeSpace,
    seeds: &[u64],
) -> Result<(), Box<dyn std::error::Error>> {
    let hand = asset.model().clone();
    let demo = Demonstration::builtin(category)?;
    let mm: f64 = std::env::var("GAP_GRID").ok().and_then(|v| v.parse().ok()).unwrap_or(3.0);
    let c: Vec<f64> =
        std::env::var("GAP_GRID_CENTRE").map_or(vec![0.0; 3], |v| v.split(',').map(|x| x.parse().unwrap()).collect());
    let mut planner =
        GraspPlanner::new(&hand, category, 0)?.with_engine_camera(SceneCamera::default(), LabFrame::default())?;
    let mut grasper =
        DaemonGrasper::in_process(&hand, category, space.clone(), SceneCamera::default(), LabFrame::default())?;
    let setup = NailSetup::default();
    let place = PlaceSetup::default();
    let table_z = graspd_sim::scene::Table::default().top_z;
    let is_mug = category == Category::Mug;
    let face = if is_mug { Default::default() } else { face_of(instance)? };
    let board = setup.ranges.sample(0, table_z).board;
    let mut rig = if is_mug {
        TaskRig::build(asset, &mut planner, instance, &place.base, "place", Vec::new(), Vec::new())?
    } else {
        let bodies = setup.fixture.bodies(&board);
        TaskRig::build(asset, &mut planner, instance, &setup.base, "nail", bodies, NailFixture::contact())?
    };
    for &seed in seeds {
        let episode = setup.ranges.sample(seed, table_z);
        let place_episode = place.ranges.sample(seed, table_z);
        let start = if is_mug { place_episode.start } else { episode.start };
        let d = grasper.grasp(&hand, category, &instance.mesh, &start, table_z, demo.table, seed)?;
        println!(
            "seed {seed}: scale {:.3}, q {:?}, tsd {:.2} cm",
            d.tool_from_canonical.scale,
            d.grasp.actuated.iter().map(|v| format!("{v:.3}")).collect::<Vec<_>>(),
            d.task_space_distance_cm
        );
        let mut line = String::new();
        for (i, dx) in [-mm, 0.0, mm].iter().enumerate() {
            for dy in [-mm, 0.0, mm] {
                for dz in [-mm, 0.0, mm] {
                    let delta = Isometry3::translation(1e-3 * (dx + c[0]), 1e-3 * (dy + c[1]), 1e-3 * (dz + c[2]));
                    let mut plan = GraspPlan {
                        grasp: d.grasp.clone(),
                        pregrasp: d.pregrasp.clone(),
                        pregrasp_collision_free: d.pregrasp_collision_free,
                        source: "camera",
                        task_space_distance_cm: d.task_space_distance_cm,
                        demo_keypoints: Vec::new(),
                        latent: d.latent.clone(),
                        start: HandStart::PreGrasp,
                    };
                    for g in [&mut plan.grasp, &mut plan.pregrasp] {
                        *g = graspd::grasp::Grasp::new(&hand, g.wrist_pose_world * delta, g.actuated.clone());
                    }
                    let (scene, data, points) = (&rig.scene, &mut rig.data, &rig.height_points);
                    let (success, clearance) = if is_mug {
                        let o = run_place(scene, data, &hand, &plan, points, &place_episode, &place.script, 30.0)?;
                        (o.success, o.clearance_after_lift_m)
                    } else {
                        let o = run_nail(scene, data, &hand, &plan, points, &face, &episode, &setup.script, 30.0)?;
                        (o.success, o.clearance_after_lift_m)
                    };
                    line.push(if success {
                        '#'
                    } else if clearance > 0.03 {
                        'l'
                    } else {
                        '.'
                    });
                }
                line.push(' ');
            }
            if i < 2 {
                line.push_str("| ");
            }
        }
        println!("  grid ±{mm} mm about {c:?} (x: blocks, y: triples, z: within) {line}");
    }
    Ok(())
}

/// The lift script alone on the rig's scene, printing the tool's motion and contacts.
fn trace_close(
    rig: &TaskRig,
    hand: &graspd::hand::HandModel,
    plan: &GraspPlan,
    start: &Isometry3<f64>,
    setup: &NailSetup,
) -> Result<(), Box<dyn std::error::Error>> {
    use graspd_sim::carry::EpisodeStepper;
    use graspd_sim::episode::LiftController;
    let mut data = mujoco_rs::prelude::MjData::new(rig.scene.model.clone());
    let plan = plan.carried(hand, start);
    let mut stepper = EpisodeStepper::start(&rig.scene, &mut data, hand, &plan, start, 30.0)?;
    let ctl = LiftController::new(hand, &plan, &setup.base.script);
    let mut q = plan.pregrasp.actuated.clone();
    let names: Vec<&str> = hand.links().iter().map(|l| l.name.as_str()).collect();
    for k in 0..(3.5f64 * 30.0) as usize {
        let t = (k + 1) as f64 / 30.0;
        let w = ctl.targets(t, &mut q);
        stepper.step(&mut data, &w, &q);
        if k % 3 == 2 {
            let pose = stepper.tool.pose(&data);
            let d = start.inverse() * pose;
            let on_tool: Vec<&str> = stepper
                .hand
                .link_bodies
                .iter()
                .enumerate()
                .filter(|(_, &b)| rig.scene.in_contact(&data, stepper.tool.body, b))
                .map(|(i, _)| names[i])
                .collect();
            let on_table: Vec<&str> = stepper
                .hand
                .link_bodies
                .iter()
                .enumerate()
                .filter(|(_, &b)| rig.scene.in_contact(&data, 0, b))
                .map(|(i, _)| names[i])
                .collect();
            let qa = stepper.hand.actuated_positions(&data, hand);
            println!(
                "    t {t:4.2} tool Δ ({:6.1} {:6.1} {:6.1}) mm {:5.1}° q {:?} tool-touch {:?} table-touch {:?}",
                1e3 * d.translation.x,
                1e3 * d.translation.y,
                1e3 * d.translation.z,
                d.rotation.angle().to_degrees(),
                qa.iter().map(|v| format!("{v:.2}")).collect::<Vec<_>>(),
                on_tool,
                on_table
            );
        }
    }
    Ok(())
}
