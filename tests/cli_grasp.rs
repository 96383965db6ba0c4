//! End-to-end tests of the grasp commands: `graspd hand`, `retarget`,
//! `grasp`, `demo` and `eval grasp`, run as a separate process with --json.

use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn graspd(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_graspd")).args(args).env("GRASPD_LOG", "warn").output().expect("graspd runs")
}

/// Runs graspd, expects success, parses stdout as JSON.
fn json(args: &[&str]) -> Value {
    let out = graspd(args);
    assert!(
        out.status.success(),
        "graspd {args:?} failed: {}\n{}",
        String::from_utf8_lossy(&out.stderr),
        String::from_utf8_lossy(&out.stdout)
    );
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("graspd {args:?}: not JSON ({e})"))
}

/// Runs graspd, expects failure, returns stderr.
fn fails(args: &[&str]) -> String {
    let out = graspd(args);
    assert!(!out.status.success(), "graspd {args:?} should fail; stdout: {}", String::from_utf8_lossy(&out.stdout));
    String::from_utf8_lossy(&out.stderr).into_owned()
}

fn f(v: &Value) -> f64 {
    v.as_f64().unwrap_or_else(|| panic!("not a number: {v}"))
}

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// A bundled demonstration and its wrist pose as `--wrist` takes it.
fn bundled_demo(category: &str) -> (Value, String) {
    let path = repo().join(format!("assets/demos/{category}.json"));
    let demo: Value = serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    let p = &demo["wrist_pose_tool"];
    let numbers = p["translation"].as_array().unwrap().iter().chain(p["rotation_xyzw"].as_array().unwrap());
    let wrist = numbers.map(|x| format!("{}", f(x))).collect::<Vec<_>>().join(" ");
    (demo, wrist)
}

fn write(dir: &Path, name: &str, v: &Value) -> String {
    let p = dir.join(name);
    std::fs::write(&p, serde_json::to_string_pretty(v).unwrap()).unwrap();
    p.to_str().unwrap().to_owned()
}

#[test]
fn hand_info_lists_joints_couplings_limits_keypoints() {
    let v = json(&["hand", "info", "--json"]);
    assert_eq!(v["name"], "sih_right");
    assert_eq!(v["moving_joints"].as_array().unwrap().len(), 11);
    let actuated = v["actuated"].as_array().unwrap();
    assert_eq!(actuated.len(), 5);
    assert_eq!(actuated[0]["name"], "palm_to_if_proximal");
    assert_eq!(f(&actuated[0]["limits"][0]), -1.571);
    assert_eq!(f(&actuated[4]["limits"][1]), 1.571);
    let mimic = v["mimic"].as_array().unwrap();
    assert_eq!(mimic.len(), 6);
    assert!(mimic.iter().all(|m| f(&m["multiplier"]) == 1.0 && f(&m["offset"]) == 0.0));
    assert!(mimic.iter().any(|m| m["joint"] == "palm_to_lf_proximal" && m["mimics"] == "palm_to_rf_proximal"));
    let kps = v["keypoints"].as_array().unwrap();
    assert_eq!(kps.len(), 12);
    assert_eq!(kps[0]["name"], "palm");
    assert_eq!(kps[0]["link"], "palm");
    let joints = v["joints"].as_array().unwrap();
    let if_distal = joints.iter().find(|j| j["name"] == "if_proximal_to_if_distal").unwrap();
    assert_eq!(if_distal["drive"]["kind"], "mimic");
    assert_eq!(if_distal["type"], "revolute");
    // The URDF's 35 collision elements, each on its link with its shape.
    let collisions = v["collision_primitives"].as_array().unwrap();
    assert_eq!(collisions.len(), 35);
    let plate = collisions.iter().find(|c| c["name"] == "palm_plate").unwrap();
    assert_eq!(plate["link"], "palm");
    assert!(plate["shape"]["box"]["half_extents"].as_array().is_some_and(|h| h.len() == 3), "{plate}");
    let tip = collisions.iter().find(|c| c["name"] == "if_distal_sphere_tip").unwrap();
    assert!(f(&tip["shape"]["sphere"]["radius"]) > 0.0, "{tip}");
}

#[test]
fn retarget_recovers_sampled_configurations() {
    let dir = tempfile::tempdir().unwrap();
    let samples = json(&["hand", "sample", "--n", "30", "--seed", "5", "--json"]);
    assert_eq!(samples["sets"].as_array().unwrap().len(), 30);
    let file = write(dir.path(), "sets.json", &samples);
    let v = json(&["retarget", "--keypoints", &file, "--json"]);
    let results = v["results"].as_array().unwrap();
    assert_eq!(results.len(), 30);
    println!("retarget summary: {}", v["summary"]);
    // Reachable targets: essentially exact (issue: ≤ 1 mm mean).
    assert!(f(&v["summary"]["residual_mm"]["mean"]) < 0.01, "{}", v["summary"]);
    assert!(f(&v["summary"]["residual_mm"]["max"]) < 1.0, "{}", v["summary"]);
    assert!(f(&v["summary"]["elapsed_ms"]["p50"]) < 20.0, "{}", v["summary"]);
    let r = &results[0];
    for key in ["wrist_pose", "joints", "actuated", "residual_mm", "penetration_mm", "elapsed_ms"] {
        assert!(!r[key].is_null(), "missing {key}");
    }
    assert_eq!(r["wrist_pose"]["rotation_xyzw"].as_array().unwrap().len(), 4);
    assert_eq!(r["joints"].as_object().unwrap().len(), 11);
    assert_eq!(r["actuated"].as_object().unwrap().len(), 5);
    // Mimic joints follow their drivers.
    assert_eq!(r["joints"]["palm_to_lf_proximal"], r["actuated"]["palm_to_rf_proximal"]);

    // One set, keypoints named and listed in another order: same answer.
    let info = json(&["hand", "info", "--json"]);
    let names: Vec<&str> = info["keypoints"].as_array().unwrap().iter().map(|k| k["name"].as_str().unwrap()).collect();
    let kps = samples["sets"][0]["keypoints"].as_array().unwrap();
    let named: Vec<Value> =
        names.iter().zip(kps).rev().map(|(n, p)| serde_json::json!({"name": n, "position": p})).collect();
    let one = write(dir.path(), "one.json", &serde_json::json!({ "keypoints": named }));
    let single = json(&["retarget", "--keypoints", &one, "--json"]);
    assert!(f(&single["residual_mm"]["max"]) < 1.0);
    let truth = &samples["sets"][0]["truth"]["actuated"];
    let got: Vec<f64> = info["actuated"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| f(&single["actuated"][a["name"].as_str().unwrap()]))
        .collect();
    for (g, t) in got.iter().zip(truth.as_array().unwrap()) {
        assert!((g - f(t)).abs() < 1e-3, "joint {g} vs {t}");
    }
}

#[test]
fn retarget_bad_input_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let three = write(dir.path(), "three.json", &serde_json::json!([[0, 0, 0], [0, 0, 0.1], [0, 0.1, 0]]));
    let e = fails(&["retarget", "--keypoints", &three, "--json"]);
    assert!(e.contains("expected 12 keypoints") && e.contains("got 3"), "{e}");
    let mut pts = vec![serde_json::json!([0.0, 0.0, 0.0]); 12];
    pts[4] = serde_json::json!([0.0, null, 0.0]);
    let nan = write(dir.path(), "nan.json", &Value::Array(pts));
    let e = fails(&["retarget", "--keypoints", &nan]);
    assert!(e.contains("keypoint 4") && e.contains("not a number"), "{e}");
    let e = fails(&["retarget", "--keypoints", dir.path().join("missing.json").to_str().unwrap()]);
    assert!(e.contains("cannot read"), "{e}");
    let junk = dir.path().join("junk.json");
    std::fs::write(&junk, "not json").unwrap();
    let e = fails(&["retarget", "--keypoints", junk.to_str().unwrap()]);
    assert!(e.contains("is not JSON"), "{e}");

    // Unreachable (a hand stretched to three times its size): the best grasp
    // comes back, with its residual.
    let samples = json(&["hand", "sample", "--n", "1", "--seed", "9", "--json"]);
    let far: Vec<Value> = samples["sets"][0]["keypoints"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| serde_json::json!([3.0 * f(&p[0]), 3.0 * f(&p[1]), 3.0 * f(&p[2])]))
        .collect();
    let far = write(dir.path(), "far.json", &Value::Array(far));
    let v = json(&["retarget", "--keypoints", &far, "--json"]);
    assert!(f(&v["residual_mm"]["mean"]) > 10.0, "{v}");
    assert!(v["wrist_pose"]["translation"].as_array().unwrap().iter().all(|x| x.as_f64().unwrap().is_finite()));
}

#[test]
fn bundled_demonstrations_pass_their_checks() {
    for c in ["mug", "drill", "hammer"] {
        let file = repo().join(format!("assets/demos/{c}.json"));
        let v = json(&["demo", "check", "--file", file.to_str().unwrap(), "--json"]);
        assert_eq!(v["ok"], true, "{c}: {v}");
        assert_eq!(v["category"], c);
        let fingers = v["fingers"].as_array().unwrap();
        assert_eq!(fingers.len(), 5);
        // Every finger the file does not declare free touches the tool.
        let demo: Value = serde_json::from_str(&std::fs::read_to_string(&file).unwrap()).unwrap();
        let free: Vec<&str> =
            demo["free_fingers"].as_array().map_or(Vec::new(), |a| a.iter().filter_map(|x| x.as_str()).collect());
        assert!(free.len() <= 1, "{c}: at most one finger may be free: {free:?}");
        assert!(
            fingers.iter().all(|x| free.contains(&x["finger"].as_str().unwrap_or_default())
                || (x["contact"] == true && f(&x["clearance_mm"]) <= 3.0)),
            "{c}: {v}"
        );
        assert!(f(&v["penetration_mm"]) <= 1.0);
    }
}

#[test]
fn demo_author_reproduces_the_bundled_demo_and_refuses_bad_poses() {
    let dir = tempfile::tempdir().unwrap();
    let (bundled, wrist) = bundled_demo("drill");
    let out = dir.path().join("drill.json");
    let v =
        json(&["demo", "author", "--category", "drill", "--wrist", &wrist, "--out", out.to_str().unwrap(), "--json"]);
    assert_eq!(v["ok"], true, "{v}");
    assert_eq!(v["fingers"].as_array().unwrap().len(), 5);
    let authored: Value = serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    for (name, q) in bundled["actuated"].as_object().unwrap() {
        assert!((f(q) - f(&authored["actuated"][name])).abs() < 1e-9, "{name}");
    }
    // The written file passes `demo check`.
    assert_eq!(json(&["demo", "check", "--file", out.to_str().unwrap(), "--json"])["ok"], true);

    // Far from the drill: no finger touches, nothing is written.
    let nowhere = dir.path().join("nowhere.json");
    let e = fails(&[
        "demo",
        "author",
        "--category",
        "drill",
        "--wrist",
        "0.5 0.5 0.5 0 0 0 1",
        "--out",
        nowhere.to_str().unwrap(),
    ]);
    assert!(e.contains("does not touch"), "{e}");
    assert!(!nowhere.exists());
    // Inside it: refused before closing.
    let e = fails(&["demo", "author", "--category", "drill", "--wrist", "-0.01 0 0.08 0 0 0 1", "--dry-run"]);
    assert!(e.contains("already pierces"), "{e}");
    let e = fails(&["demo", "author", "--category", "drill", "--wrist", "0 0 0"]);
    assert!(e.contains("expected 7 numbers"), "{e}");
    let e = fails(&["demo", "author", "--category", "spoon", "--wrist", "0 0 0 0 0 0 1"]);
    assert!(e.contains("unknown tool category"), "{e}");
}

#[test]
fn demo_check_refuses_a_bad_import() {
    let dir = tempfile::tempdir().unwrap();
    let mut demo: Value =
        serde_json::from_str(&std::fs::read_to_string(repo().join("assets/demos/mug.json")).unwrap()).unwrap();
    // Keypoints that do not belong to the stated grasp (a glove's offset).
    let x = f(&demo["keypoints_tool"][2]["position"][0]);
    demo["keypoints_tool"][2]["position"][0] = serde_json::json!(x + 0.004);
    let file = write(dir.path(), "shifted.json", &demo);
    let out = graspd(&["demo", "check", "--file", &file, "--json"]);
    assert!(!out.status.success());
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["ok"], false);
    assert!(v["problems"][0].as_str().unwrap().contains("4.00 mm"), "{v}");
    // A looser tolerance accepts it.
    assert_eq!(json(&["demo", "check", "--file", &file, "--max-keypoint-mismatch-mm", "5", "--json"])["ok"], true);
    // Format errors name the problem.
    demo["gloves"] = serde_json::json!(true);
    let file = write(dir.path(), "extra.json", &demo);
    let e = fails(&["demo", "check", "--file", &file]);
    assert!(e.contains("unknown field `gloves`"), "{e}");
    let mut wrong = demo.clone();
    wrong.as_object_mut().unwrap().remove("gloves");
    wrong["hand"] = serde_json::json!("allegro");
    let file = write(dir.path(), "hand.json", &wrong);
    let e = fails(&["demo", "check", "--file", &file]);
    assert!(e.contains("hand `allegro`"), "{e}");
}

#[test]
fn grasp_from_a_partial_cloud() {
    let dir = tempfile::tempdir().unwrap();
    let cloud = dir.path().join("mug.ply");
    let mesh = repo().join("assets/tools/mug/mug_test_00.obj");
    let c = graspd(&[
        "cloud",
        "--mesh",
        mesh.to_str().unwrap(),
        "--view",
        "1",
        "--seed",
        "2",
        "--out",
        cloud.to_str().unwrap(),
    ]);
    assert!(c.status.success(), "{}", String::from_utf8_lossy(&c.stderr));
    let v = json(&["grasp", "--category", "mug", "--cloud", cloud.to_str().unwrap(), "--json"]);
    println!(
        "grasp: distance {} cm (CG {}, WP {}), penetration {} mm, stages {}",
        v["task_space_distance_cm"],
        v["baselines"]["cg"]["task_space_distance_cm"],
        v["baselines"]["wp"]["task_space_distance_cm"],
        v["penetration_mm"],
        v["stage_ms"]
    );
    assert!(!v["registration"]["latent"].as_array().unwrap().is_empty());
    assert_eq!(v["registration"]["pose"]["rotation_xyzw"].as_array().unwrap().len(), 4);
    assert!(f(&v["registration"]["scale"]) > 0.5);
    assert_eq!(v["grasp"]["joints"].as_object().unwrap().len(), 11);
    assert_eq!(v["grasp"]["actuated"].as_object().unwrap().len(), 5);
    assert_eq!(v["targets"].as_array().unwrap().len(), 12);
    assert_eq!(v["pregrasp"]["collision_free"], true);
    assert!(f(&v["penetration_mm"]) <= 2.0, "{v}");
    let ours = f(&v["task_space_distance_cm"]);
    assert!(ours < f(&v["baselines"]["cg"]["task_space_distance_cm"]), "{v}");
    assert!(ours < 2.0, "{v}");
    for stage in ["registration", "transfer", "solve", "pregrasp"] {
        assert!(f(&v["stage_ms"][stage]) >= 0.0);
    }
    assert!(f(&v["elapsed_ms"]) > 0.0);
    // The table is under the cloud; an explicit one is used as given.
    assert!(f(&v["table_z"]).abs() < 0.02, "{}", v["table_z"]);
    let v2 = json(&["grasp", "--category", "mug", "--cloud", cloud.to_str().unwrap(), "--table-z", "-0.5", "--json"]);
    assert_eq!(f(&v2["table_z"]), -0.5);
    let e = fails(&["grasp", "--category", "mug", "--cloud", dir.path().join("none.ply").to_str().unwrap()]);
    assert!(!e.is_empty());
}

#[test]
fn eval_grasp_prints_table_one() {
    let v = json(&["eval", "grasp", "--category", "drill", "--repeats", "1", "--json"]);
    println!("Table I drill: {}", v["task_space_distance_cm"]);
    assert_eq!(v["instances"], 10);
    assert_eq!(v["per_instance"].as_array().unwrap().len(), 10);
    let t = &v["task_space_distance_cm"];
    for m in ["ours", "wp", "cg"] {
        assert!(f(&t[m]["mean"]) > 0.0 && f(&t[m]["std"]) >= 0.0, "{m}");
    }
    assert!(f(&t["ours"]["mean"]) < f(&t["cg"]["mean"]));
    assert!(f(&v["penetration_mm"]["ours"]["max"]) <= 2.0, "{}", v["penetration_mm"]);
    assert!(f(&v["solve_ms"]["p50"]) > 0.0 && f(&v["solve_ms"]["p99"]) >= f(&v["solve_ms"]["p50"]));
}

#[test]
fn hand_info_loads_another_hand_and_refuses_a_broken_one() {
    let dir = tempfile::tempdir().unwrap();
    // A two-finger gripper with a 2:1 mimic coupling and an offset.
    let urdf = r#"<robot name="gripper">
      <link name="base"/><link name="left"/><link name="right"/>
      <joint name="left_joint" type="prismatic"><parent link="base"/><child link="left"/>
        <origin xyz="0 0.02 0.05"/><axis xyz="0 1 0"/><limit lower="0" upper="0.04" effort="1" velocity="1"/></joint>
      <joint name="right_joint" type="prismatic"><parent link="base"/><child link="right"/>
        <origin xyz="0 -0.02 0.05"/><axis xyz="0 -1 0"/><limit lower="-0.01" upper="0.09" effort="1" velocity="1"/>
        <mimic joint="left_joint" multiplier="2" offset="0.005"/></joint>
    </robot>"#;
    let kps = r#"{"keypoints": [{"name": "l", "link": "left", "offset": [0, 0, 0.01]},
                                {"name": "r", "link": "right", "offset": [0, 0, 0.01]}],
                  "palm_normal": [0, 0, 1]}"#;
    let (u, k) = (dir.path().join("g.urdf"), dir.path().join("g.json"));
    std::fs::write(&u, urdf).unwrap();
    std::fs::write(&k, kps).unwrap();
    let v = json(&["hand", "info", "--urdf", u.to_str().unwrap(), "--keypoints", k.to_str().unwrap(), "--json"]);
    assert_eq!(v["name"], "gripper");
    assert_eq!(v["actuated"].as_array().unwrap().len(), 1);
    assert_eq!(f(&v["mimic"][0]["multiplier"]), 2.0);
    assert_eq!(f(&v["mimic"][0]["offset"]), 0.005);
    // A joint naming a link that is not there.
    std::fs::write(&u, urdf.replace(r#"<child link="right"/>"#, r#"<child link="thumb"/>"#)).unwrap();
    let e = fails(&["hand", "info", "--urdf", u.to_str().unwrap(), "--keypoints", k.to_str().unwrap()]);
    assert!(e.contains("`thumb` is not defined"), "{e}");
}

/// Another hand (here the bundled one under other names) through the whole
/// offline path: a demonstration authored with it, checked, and a grasp
/// solved with it whose joints carry its names; the bundled demonstration,
/// made with another hand, is refused for it.
#[test]
fn another_hand_authors_its_demonstration_and_grasps_with_it() {
    let dir = tempfile::tempdir().unwrap();
    let renamed = graspd::hand::renamed::write(dir.path()).unwrap();
    let hand = renamed.args();
    let info = json(&[&["hand", "info", "--json"][..], &hand].concat());
    assert_eq!(info["name"], "sih_renamed", "{info}");

    let (_, wrist) = bundled_demo("mug");
    let demo = dir.path().join("authored.json");
    let demo = demo.to_str().unwrap();
    let authored = json(
        &[&["demo", "author", "--category", "mug", "--wrist", &wrist, "--out", demo, "--json"][..], &hand].concat(),
    );
    assert_eq!(authored["ok"], true, "{authored}");
    let file: Value = serde_json::from_str(&std::fs::read_to_string(demo).unwrap()).unwrap();
    assert_eq!(file["hand"], "sih_renamed");
    assert!(file["actuated"]["palm_to_index_base"].is_number(), "{file}");
    assert_eq!(json(&[&["demo", "check", "--file", demo, "--json"][..], &hand].concat())["ok"], true);

    let cloud = dir.path().join("view.ply");
    let mesh = repo().join("assets/tools/mug/mug_test_00.obj");
    json(&[
        "cloud",
        "--mesh",
        mesh.to_str().unwrap(),
        "--view",
        "0",
        "--seed",
        "1",
        "--out",
        cloud.to_str().unwrap(),
        "--json",
    ]);
    let cloud = cloud.to_str().unwrap();
    let g = json(&[&["grasp", "--category", "mug", "--cloud", cloud, "--demo", demo, "--json"][..], &hand].concat());
    assert!(g["grasp"]["actuated"]["palm_to_index_base"].is_number(), "{}", g["grasp"]);
    assert!(g["grasp"]["actuated"].get("palm_to_if_proximal").is_none());
    let e = fails(&[&["grasp", "--category", "mug", "--cloud", cloud][..], &hand].concat());
    assert!(e.contains("made with hand `sih_right`, not `sih_renamed`"), "{e}");
}
