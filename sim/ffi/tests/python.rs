//! The Python wrapper (sim/python/graspd_sim) over this crate's shared
//! library: its pytest suite, with the Python SDK's environment
//! (scripts/python-sdk.sh: NumPy, pytest). Without that environment this
//! test fails, naming the script.

use std::path::Path;
use std::process::Command;

#[test]
fn the_python_vecenv_drives_the_tasks() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let python = root.join("client/python/.venv/bin/python");
    assert!(
        python.exists(),
        "{} is missing: run scripts/python-sdk.sh (the README's test command does)",
        python.display()
    );
    // The shared library `cargo test` built for this test (target/<profile>/deps/,
    // beside the test binary: the copy in target/<profile>/ is only
    // refreshed by `cargo build`).
    let exe = std::env::current_exe().unwrap();
    let lib = exe.parent().unwrap().join("libgraspd_sim_ffi.so");
    assert!(lib.exists(), "{} is missing", lib.display());
    let out = Command::new(&python)
        .args(["-m", "pytest", "-q", "-p", "no:cacheprovider", "sim/python/tests"])
        .current_dir(&root)
        .env("PYTHONPATH", root.join("sim/python"))
        .env("GRASPD_SIM_LIB", &lib)
        .env("GRASPD_LOG", "warn")
        .output()
        .expect("python runs");
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "the Python VecEnv's tests failed:\n{text}");
    assert!(text.contains("4 passed") && !text.contains("skipped"), "{text}");
}
