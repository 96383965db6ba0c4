//! Lets the `sim` binary, tests and examples find libmujoco without
//! LD_LIBRARY_PATH: mujoco-rs links it dynamically from
//! MUJOCO_DYNAMIC_LINK_DIR (set in .cargo/config.toml to
//! third_party/mujoco/lib, filled by scripts/fetch-mujoco.sh), and the loader
//! finds it at run time through the rpath written here.

use std::path::Path;

fn main() {
    println!("cargo::rerun-if-env-changed=MUJOCO_DYNAMIC_LINK_DIR");
    println!("cargo::rerun-if-changed=build.rs");
    // No dynamic directory: mujoco-rs found MuJoCo elsewhere (static link or
    // pkg-config), where no rpath of ours is needed.
    let Ok(dir) = std::env::var("MUJOCO_DYNAMIC_LINK_DIR") else { return };
    let dir = Path::new(&dir);
    if !dir.join("libmujoco.so").is_file() {
        // mujoco-rs's own build script has already failed in this case; say
        // how to fix it in the project's words too.
        println!("cargo::warning=MuJoCo 3.17.0 is not in {} (run scripts/fetch-mujoco.sh)", dir.display());
    }
    // rustc-link-arg reaches every linked target of this package (the binary,
    // tests, examples, benches); crates that depend on graspd-sim and link
    // their own binaries emit their own.
    println!("cargo::rustc-link-arg=-Wl,-rpath,{}", dir.display());
}
