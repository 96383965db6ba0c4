//! The `sim` binary end to end: its JSON is what scripts read.

use std::process::Command;

fn sim(args: &[&str]) -> serde_json::Value {
    let out = Command::new(env!("CARGO_BIN_EXE_sim")).args(args).output().expect("sim runs");
    assert!(out.status.success(), "sim {args:?} failed: {}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("sim {args:?} printed no JSON ({e})"))
}

#[test]
fn info_names_the_linked_mujoco() {
    let v = sim(&["info", "--json"]);
    assert_eq!(v["mujoco_version"], "3.17.0");
}

#[test]
fn bench_reports_its_throughput() {
    let v = sim(&["bench", "--envs", "3", "--seconds", "0.5", "--threads", "2", "--json"]);
    assert_eq!(v["envs"], 3);
    assert_eq!(v["substeps"], 4);
    let rate = v["control_steps_per_s"].as_f64().unwrap();
    let us = v["physics_us_per_step"].as_f64().unwrap();
    assert!(rate > 0.0 && us > 0.0, "{v}");
    // Steps counted and time measured agree: n steps × 4 substeps × µs each
    // cannot exceed the threads' wall time.
    let physics_s = v["control_steps"].as_f64().unwrap() * 4.0 * us * 1e-6;
    assert!(physics_s <= 2.0 * v["seconds"].as_f64().unwrap() * 1.05, "{v}");
}

#[test]
fn bench_refuses_bad_arguments_with_a_message() {
    let out = Command::new(env!("CARGO_BIN_EXE_sim")).args(["bench", "--actions", "dance"]).output().unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("scripted"));
    let out =
        Command::new(env!("CARGO_BIN_EXE_sim")).args(["bench", "--envs", "0", "--seconds", "0.1"]).output().unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("environment"));
}

#[test]
fn lift_json_lists_each_episode() {
    let v = sim(&["lift", "--category", "mug", "--instances", "canonical", "--json"]);
    assert_eq!(v["episodes"], 1);
    let r = &v["results"][0];
    assert_eq!(r["instance"], "mug_canonical");
    assert_eq!(r["outcome"]["held"], true);
}

#[test]
fn position_json_reports_the_drill_task() {
    let v = sim(&["position", "--instances", "canonical", "--episodes", "2", "--json"]);
    assert_eq!(v["task"], "position_drill");
    assert_eq!(v["category"], "drill");
    assert_eq!(v["episodes"], 2);
    assert_eq!(v["successes"], 2);
    assert!(v["ranges"]["goal_height"].is_array(), "{v}");
    let e = &v["results"][0]["episodes"][0];
    assert!(e["final_distance_m"].as_f64().unwrap() < 0.03, "{e}");
    assert!(e["return_terms"]["pose"].as_f64().unwrap() > 0.0, "{e}");
}

#[test]
fn a_task_refuses_another_category_with_a_message() {
    let out = Command::new(env!("CARGO_BIN_EXE_sim")).args(["place", "--category", "drill"]).output().unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("mug"), "{}", String::from_utf8_lossy(&out.stderr));
}

#[test]
fn nail_json_reports_depth_and_the_fixture() {
    let v = sim(&["nail", "--instances", "canonical", "--episodes", "1", "--json"]);
    assert_eq!(v["task"], "drive_nail");
    assert_eq!(v["category"], "hammer");
    assert_eq!(v["episodes"], 1);
    assert_eq!(v["fixture"]["frictionloss_n"], 10.0);
    let e = &v["results"][0]["episodes"][0];
    assert_eq!(e["success"], true, "{e}");
    assert!(e["depth_m"].as_f64().unwrap() > 0.075, "{e}");
    // The strikes stop once the nail is home (3 of the 9 the episode has time for), the hammer still held.
    assert!(e["strikes"].as_u64().unwrap() >= 2, "{e}");
    assert!(e["stopped_striking_s"].as_f64().is_some(), "{e}");
    assert_eq!(e["held_at_end"], true, "{e}");
    let out =
        std::process::Command::new(env!("CARGO_BIN_EXE_sim")).args(["nail", "--category", "mug"]).output().unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("hammer"));
}

/// The start modes are reported and change what the hand does: from the
/// neutral pose the script reaches the grasp itself (the mug reaches its
/// goal 1 s later than from the pre-grasp, still lifted and placed); the
/// canonical start on the canonical mug is the demonstration's own grasp.
#[test]
fn start_modes_are_reported_per_episode() {
    let run = |start: &str| {
        let v = sim(&["place", "--instances", "canonical", "--episodes", "1", "--start", start, "--json"]);
        assert_eq!(v["start"], start, "{v}");
        assert_eq!(v["grasp_from"], "inprocess", "{v}");
        v["results"][0]["episodes"][0].clone()
    };
    let pre = run("pregrasp");
    let neutral = run("neutral");
    let canonical = run("canonical");
    assert_eq!(pre["grasp"]["source"], "demonstration");
    assert_eq!(canonical["grasp"]["source"], "canonical");
    assert_eq!(canonical["grasp"]["task_space_distance_cm"], 0.0);
    assert_eq!(neutral["grasp"]["start"], "neutral");
    assert!(neutral["grasp"]["latency_ms"].is_null(), "in-process: no round trip");
    for e in [&pre, &neutral, &canonical] {
        assert!(e["clearance_after_lift_m"].as_f64().unwrap() > 0.05, "{e}");
        assert_eq!(e["success"], true, "{e}");
    }
    let reached = |e: &serde_json::Value| e["first_reached_s"].as_f64().unwrap();
    assert!((reached(&neutral) - reached(&pre) - 1.0).abs() < 0.05, "{pre} {neutral}");
}

/// Test tools have no training latent: in-process planning refuses them
/// and says where their grasps come from.
#[test]
fn test_instances_need_the_daemon() {
    let out = Command::new(env!("CARGO_BIN_EXE_sim"))
        .args(["place", "--instances", "test", "--episodes", "1"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("--grasp-from daemon"), "{err}");
}

/// `--grasp-from register`: the camera's view registered and grasped in
/// this process as the daemon would, so a test tool (no training latent)
/// is grasped without a daemon; the episode reports the registration.
#[test]
fn the_register_path_grasps_a_test_tool_without_a_daemon() {
    let out = Command::new(env!("CARGO_BIN_EXE_sim"))
        .args(["place", "--grasp-from", "register", "--instances", "mug_test_01", "--episodes", "1", "--json"])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["grasp_from"], "register", "{v}");
    let row = &v["results"][0];
    assert_eq!(row["grasp_source"], "registered", "{row}");
    let g = &row["episodes"][0]["grasp"];
    assert!(g["cloud_points"].as_u64().is_some_and(|n| n > 1000), "{g}");
    assert!(g["registered_scale"].as_f64().is_some_and(|s| s > 0.5 && s < 2.0), "{g}");
    assert!(g["registered_offset_m"].as_f64().is_some_and(|m| m < 0.02), "{g}");
    assert!(g["daemon_engine_ms"].as_f64().is_some_and(|ms| ms > 0.0), "{g}");
}

/// A scene camera whose segmentation leaks 3 pixels onto the table: the
/// view holds the table's ring round the drill, and the grasp is as good
/// (the registration sets the ring aside). With the ring kept, Position
/// drill from the camera held 1 of 30 test episodes (30 of 30 now).
#[test]
fn a_leaking_camera_mask_still_positions_the_drill() {
    let run = |leak: &str| {
        let out = Command::new(env!("CARGO_BIN_EXE_sim"))
            .args(["position", "--grasp-from", "register", "--instances", "drill_test_00", "--episodes", "2"])
            .args(["--camera-mask-leak-px", leak, "--json"])
            .output()
            .unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        serde_json::from_slice::<serde_json::Value>(&out.stdout).unwrap()["results"][0]["episodes"].clone()
    };
    let (clean, leaky) = (run("0"), run("3"));
    for (c, l) in clean.as_array().unwrap().iter().zip(leaky.as_array().unwrap()) {
        let points = |e: &serde_json::Value| e["grasp"]["cloud_points"].as_u64().unwrap();
        assert!(points(l) > points(c) + points(c) / 20, "{} vs {} points", points(l), points(c));
        assert!(l["grasp"]["registered_offset_m"].as_f64().is_some_and(|m| m < 0.01), "{}", l["grasp"]);
        assert_eq!(l["success"], true, "{l}");
    }
}

/// No daemon under the prefix: the run stops at once with an error naming
/// the prefix and what to start.
#[test]
fn a_daemon_that_is_down_is_a_clear_error() {
    let prefix = format!("graspd_sim_cli_nobody_{}", std::process::id());
    let out = Command::new(env!("CARGO_BIN_EXE_sim"))
        .args(["place", "--grasp-from", "daemon", "--daemon-prefix", &prefix, "--instances", "canonical"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains(&prefix) && err.contains("graspd serve"), "{err}");
    let out = Command::new(env!("CARGO_BIN_EXE_sim")).args(["place", "--grasp-from", "cloud"]).output().unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("inprocess"));
}

/// Episodes with another hand and its demonstration (here the bundled hand
/// and mug demonstration under other names) are those of the bundled hand,
/// step for step; the bundled demonstration is refused for it.
#[test]
fn a_task_runs_with_another_hand_and_its_demonstration() {
    let dir = tempfile::tempdir().unwrap();
    let renamed = graspd::hand::renamed::write(dir.path()).unwrap();
    let base = ["place", "--instances", "mug_canonical", "--episodes", "2", "--json"];
    let hand = renamed.args();
    let demo = renamed.mug_demo.to_str().unwrap();
    let returns = |v: &serde_json::Value| -> Vec<f64> {
        v["results"][0]["episodes"].as_array().unwrap().iter().map(|e| e["episode_return"].as_f64().unwrap()).collect()
    };
    let bundled = sim(&base);
    let other = sim(&[&base[..], &hand, &["--demo", demo]].concat());
    assert_eq!(returns(&other), returns(&bundled));
    let out = Command::new(env!("CARGO_BIN_EXE_sim")).args([&base[..], &hand].concat()).output().unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("made with hand `sih_right`, not `sih_renamed`") && err.contains("--demo"), "{err}");
}

/// A task's finger servos take `--kp` / `--force-limit` (another hand's
/// fingers may want their own gains), the report says which, and a gain
/// that is not a positive number is refused naming the flag.
#[test]
fn a_tasks_finger_servos_take_the_given_gains() {
    let base = ["place", "--instances", "mug_canonical", "--episodes", "1", "--json"];
    let returns = |v: &serde_json::Value| -> Vec<f64> {
        v["results"][0]["episodes"].as_array().unwrap().iter().map(|e| e["episode_return"].as_f64().unwrap()).collect()
    };
    let bundled = sim(&base);
    assert_eq!((bundled["servo"]["kp"].as_f64(), bundled["servo"]["force_limit"].as_f64()), (Some(4.0), Some(2.0)));
    // Servos too weak to hold the mug: another episode, and the report says why.
    let weak = sim(&[&base[..], &["--kp", "0.5", "--force-limit", "0.2"]].concat());
    assert_eq!((weak["servo"]["kp"].as_f64(), weak["servo"]["force_limit"].as_f64()), (Some(0.5), Some(0.2)));
    assert_ne!(returns(&weak), returns(&bundled));
    for (flag, value) in [("--kp", "-1"), ("--force-limit", "nan"), ("--kp", "0")] {
        let out = Command::new(env!("CARGO_BIN_EXE_sim"))
            .args(["nail", "--instances", "hammer_canonical", "--episodes", "1", &format!("{flag}={value}")])
            .output()
            .unwrap();
        assert!(!out.status.success(), "{flag} {value}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(flag) && err.contains("positive"), "{err}");
    }
}
