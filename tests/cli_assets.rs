//! End-to-end: the `graspd` binary as a separate process, on the built-in assets.

use std::process::Command;

fn graspd(args: &[&str]) -> std::process::Output {
    let out =
        Command::new(env!("CARGO_BIN_EXE_graspd")).args(args).env("GRASPD_LOG", "warn").output().expect("graspd runs");
    out
}

fn json(args: &[&str]) -> serde_json::Value {
    let out = graspd(args);
    assert!(out.status.success(), "graspd {args:?} failed: {}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|e| panic!("graspd {args:?}: not JSON ({e}): {}", String::from_utf8_lossy(&out.stdout)))
}

#[test]
fn assets_list_reports_the_seeded_splits() {
    let v = json(&["assets", "list", "--json"]);
    let cats: Vec<&str> = v["categories"].as_array().unwrap().iter().map(|c| c["name"].as_str().unwrap()).collect();
    assert_eq!(cats, ["mug", "drill", "hammer"]);
    for c in cats {
        let count = |split: &str| {
            v["instances"].as_array().unwrap().iter().filter(|i| i["category"] == c && i["split"] == split).count()
        };
        assert_eq!((count("canonical"), count("train"), count("test")), (1, 10, 3), "{c}");
    }
}

#[test]
fn assets_generate_is_byte_for_byte_deterministic_and_matches_the_committed_assets() {
    let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    for d in [&a, &b] {
        let out = graspd(&["assets", "generate", "--out", d.path().to_str().unwrap()]);
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    }
    let committed = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../assets/tools");
    for rel in ["manifest.json", "mug/mug_canonical.obj", "drill/drill_test_02.obj", "hammer/hammer_train_07.obj"] {
        let x = std::fs::read(a.path().join(rel)).unwrap();
        assert_eq!(x, std::fs::read(b.path().join(rel)).unwrap(), "{rel} differs between runs");
        assert_eq!(
            x,
            std::fs::read(committed.join(rel)).unwrap(),
            "{rel} differs from the committed asset: run `graspd assets generate`"
        );
    }
}

#[test]
fn cloud_renders_a_partial_view_that_register_accepts() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../assets/tools/mug/mug_test_01.obj");
    let cloud = dir.path().join("view.ply");
    let v = json(&[
        "cloud",
        "--mesh",
        mesh.to_str().unwrap(),
        "--view",
        "3",
        "--seed",
        "5",
        "--out",
        cloud.to_str().unwrap(),
        "--json",
    ]);
    let n = v["points"].as_u64().unwrap();
    assert!(n > 2000, "{n} points");
    let shape = dir.path().join("shape.ply");
    let r = json(&[
        "register",
        "--category",
        "mug",
        "--cloud",
        cloud.to_str().unwrap(),
        "--shape-out",
        shape.to_str().unwrap(),
        "--json",
    ]);
    assert_eq!(r["keypoints"].as_array().unwrap().len(), 6);
    assert_eq!(r["pose"]["rotation_xyzw"].as_array().unwrap().len(), 4);
    assert!(r["fit"]["confident"].as_bool().unwrap(), "{}", r["fit"]);
    assert!(shape.exists());
}

#[test]
fn bad_input_is_a_clear_error_with_a_nonzero_exit() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.xyz");
    std::fs::write(&bad, "0 0 0\n1 nan 2\n").unwrap();
    let out = graspd(&["register", "--category", "mug", "--cloud", bad.to_str().unwrap()]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("bad.xyz") && err.to_lowercase().contains("nan"), "{err}");
    let out = graspd(&["register", "--category", "teapot", "--cloud", bad.to_str().unwrap()]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("teapot"));
}

/// `eval transfer --second-view` merges each view with a second camera's and
/// says so in its JSON; the calibration error it can add needs it, and must
/// be two non-negative numbers.
#[test]
fn eval_transfer_takes_a_second_view() {
    let v = json(&[
        "eval",
        "transfer",
        "--category",
        "hammer",
        "--views",
        "2",
        "--split",
        "test",
        "--second-view",
        "--second-view-misalign",
        "2,0.5",
        "--json",
    ]);
    assert_eq!(v["second_view"], true);
    assert_eq!(v["second_view_misalign_mm_deg"], serde_json::json!([2.0, 0.5]));
    let test = &v["test"];
    assert_eq!(test["trials"], 6, "{test}");
    // Two views of a hammer: about twice one view's points, and right.
    assert!(test["points_per_view"]["median"].as_f64().unwrap() > 4000.0, "{test}");
    assert!(test["ours"]["keypoint_error_mm"]["median"].as_f64().unwrap() < 5.0, "{test}");
    for (args, says) in [
        (&["--second-view-misalign", "2,0.5"][..], "needs --second-view"),
        (&["--second-view", "--second-view-misalign", "2"][..], "two non-negative numbers"),
        (&["--second-view", "--second-view-misalign", "2,-1"][..], "two non-negative numbers"),
    ] {
        let out = graspd(&[&["eval", "transfer", "--category", "hammer", "--views", "1"][..], args].concat());
        assert!(!out.status.success(), "{args:?}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(says), "{args:?}: {err}");
    }
}
