//! C ABI of the tasks stepped by actions ([`graspd_sim::env::VecTaskEnv`]),
//! so that a trainer in another language drives the simulator in-process:
//! `sim/python/graspd_sim` wraps it with ctypes and NumPy (zero-copy views
//! of the batch buffers).
//!
//! A handle is made from a JSON configuration and owns N environments.
//! Every function returns 0 (or a non-null pointer) on success and -1 (or
//! null) on failure, with the reason in [`graspd_env_last_error`] (per
//! thread). Nothing unwinds across the boundary: a panic inside is caught
//! and reported as an error. Buffers returned by pointer belong to the
//! handle and stay valid, with their contents updated in place, until
//! [`graspd_env_free`]; JSON strings until the next call on the handle.
//! A handle must not be used from two threads at once.

use std::cell::RefCell;
use std::ffi::{c_char, CStr, CString};
use std::panic::{catch_unwind, AssertUnwindSafe};

use graspd::tools::{self, Category, Instance};
use graspd_sim::camera::{LabFrame, SceneCamera};
use graspd_sim::env::{EnvSetup, Expert, Task, VecTaskEnv};
use graspd_sim::hand::HandAsset;
use graspd_sim::plan::{choose_instances, GraspFrom, GraspPlanner, StartMode};
use serde::Deserialize;

thread_local! {
    static LAST_ERROR: RefCell<CString> = RefCell::new(CString::default());
}

fn set_error(message: impl Into<String>) {
    let text = message.into().replace('\0', " ");
    LAST_ERROR.with(|e| *e.borrow_mut() = CString::new(text).unwrap_or_default());
}

/// The configuration of [`graspd_env_new`] (JSON object; every key optional but `task`).
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Config {
    /// `place`, `position` or `nail`.
    task: String,
    /// `canonical`, `train`, `all` (canonical and train), `test` (needs
    /// `grasp_from` = `register`), one instance name, or a list of names.
    #[serde(default)]
    instances: Option<Instances>,
    #[serde(default = "default_envs")]
    envs: usize,
    /// Worker threads (0: the cores available).
    #[serde(default)]
    threads: usize,
    /// First episode seed (and the grasp solver's).
    #[serde(default)]
    seed: u64,
    /// `inprocess` or `register` (the scene camera's view registered in-process).
    #[serde(default)]
    grasp_from: Option<String>,
    /// `pregrasp`, `canonical` or `neutral`.
    #[serde(default)]
    start: Option<String>,
}

#[derive(Debug, Deserialize)]
#[serde(untagged)]
enum Instances {
    One(String),
    Many(Vec<String>),
}

fn default_envs() -> usize {
    16
}

fn choose(family: &[Instance], category: Category, which: &Instances) -> Result<Vec<Instance>, String> {
    let names = match which {
        Instances::One(name) => std::slice::from_ref(name),
        Instances::Many(names) => names.as_slice(),
    };
    let mut out = Vec::new();
    for name in names {
        out.extend(choose_instances(family, category, name).map_err(|e| e.to_string())?.into_iter().cloned());
    }
    if out.is_empty() {
        return Err("no instances chosen".into());
    }
    Ok(out)
}

/// N environments and the buffers the C side reads.
pub struct EnvHandle {
    envs: VecTaskEnv,
    experts: Vec<Option<Expert>>,
    dones: Vec<u8>,
    successes: Vec<u8>,
    info: CString,
    json: CString,
}

impl EnvHandle {
    fn new(config: &str) -> Result<Self, String> {
        let c: Config = serde_json::from_str(config).map_err(|e| format!("configuration: {e}"))?;
        let task: Task = c.task.parse().map_err(|e| format!("{e}"))?;
        let from: GraspFrom = c.grasp_from.as_deref().unwrap_or("inprocess").parse().map_err(|e| format!("{e}"))?;
        let start: StartMode = c.start.as_deref().unwrap_or("pregrasp").parse().map_err(|e| format!("{e}"))?;
        let category = task.category();
        let family = tools::family(category).map_err(|e| e.to_string())?;
        let instances = choose(&family, category, c.instances.as_ref().unwrap_or(&Instances::One("all".into())))?;
        let asset = HandAsset::default_sih().map_err(|e| e.to_string())?;
        let planner = GraspPlanner::new(asset.model(), category, c.seed).map_err(|e| e.to_string())?.with_start(start);
        let planner = match from {
            GraspFrom::InProcess => planner,
            GraspFrom::Register => {
                planner.with_engine_camera(SceneCamera::default(), LabFrame::default()).map_err(|e| e.to_string())?
            }
            GraspFrom::Daemon => return Err("grasp_from `daemon` is not offered here: use `register`".into()),
        };
        let threads =
            if c.threads == 0 { std::thread::available_parallelism().map_or(1, |n| n.get()) } else { c.threads };
        let envs = VecTaskEnv::new(&asset, planner, &instances, EnvSetup::new(task), c.envs, threads, c.seed)
            .map_err(|e| e.to_string())?;
        let n = envs.len();
        let info = serde_json::json!({
            "task": task.name(),
            "envs": n,
            "threads": threads,
            "instances": (0..n).filter_map(|i| envs.env(i).map(|e| e.instance().name.clone())).collect::<Vec<_>>(),
            "observation_len": envs.observation_layout().len(),
            "action_len": envs.action_layout().len(),
            "observation_layout": envs.observation_layout().segments(),
            "action_layout": envs.action_layout().segments(),
            "steps_per_episode": envs.env(0).map_or(0, |e| e.steps_per_episode()),
        });
        Ok(Self {
            experts: (0..n).map(|_| None).collect(),
            dones: vec![0; n],
            successes: vec![0; n],
            info: CString::new(info.to_string()).map_err(|e| e.to_string())?,
            json: CString::default(),
            envs,
        })
    }

    fn refresh_flags(&mut self) {
        for (o, &d) in self.dones.iter_mut().zip(self.envs.dones()) {
            *o = d as u8;
        }
        for (o, &s) in self.successes.iter_mut().zip(self.envs.successes()) {
            *o = s as u8;
        }
    }
}

/// Runs `f`, turning an error or a panic into -1 and the thread's last error.
fn guarded(f: impl FnOnce() -> Result<(), String>) -> i32 {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(Ok(())) => 0,
        Ok(Err(e)) => {
            set_error(e);
            -1
        }
        Err(p) => {
            let what = p.downcast_ref::<&str>().map(|s| s.to_string()).or_else(|| p.downcast_ref::<String>().cloned());
            set_error(format!("internal error (a panic): {}", what.unwrap_or_default()));
            -1
        }
    }
}

/// # Safety
/// `h` is null or a live handle (the exported functions' callers promise it).
unsafe fn handle<'a>(h: *mut EnvHandle) -> Result<&'a mut EnvHandle, String> {
    // SAFETY: the caller's promise above.
    unsafe { h.as_mut() }.ok_or_else(|| "null environment handle".to_owned())
}

/// The reason of this thread's last failure (empty when none), valid until the next failure.
#[no_mangle]
pub extern "C" fn graspd_env_last_error() -> *const c_char {
    LAST_ERROR.with(|e| e.borrow().as_ptr())
}

/// Makes the environments of a JSON configuration (module docs of the
/// `Config` keys) and resets them; null on failure.
///
/// # Safety
/// `config_json` is a NUL-terminated string.
#[no_mangle]
pub unsafe extern "C" fn graspd_env_new(config_json: *const c_char) -> *mut EnvHandle {
    let mut out = std::ptr::null_mut();
    guarded(|| {
        if config_json.is_null() {
            return Err("null configuration".into());
        }
        // SAFETY: the caller promises a NUL-terminated string.
        let text = unsafe { CStr::from_ptr(config_json) }.to_str().map_err(|e| format!("configuration: {e}"))?;
        out = Box::into_raw(Box::new(EnvHandle::new(text)?));
        Ok(())
    });
    out
}

/// Frees a handle (null is ignored).
///
/// # Safety
/// `h` is null or a handle from [`graspd_env_new`] not yet freed, used by one thread at a time.
#[no_mangle]
pub unsafe extern "C" fn graspd_env_free(h: *mut EnvHandle) {
    if !h.is_null() {
        // SAFETY: from graspd_env_new, not freed before (the caller's promise).
        let _ = catch_unwind(AssertUnwindSafe(|| drop(unsafe { Box::from_raw(h) })));
    }
}

/// JSON: task, envs, threads, instances (per environment), observation and
/// action lengths and layouts, steps per episode. Valid while the handle lives.
///
/// # Safety
/// `h` is null or a handle from [`graspd_env_new`] not yet freed, used by one thread at a time.
#[no_mangle]
pub unsafe extern "C" fn graspd_env_info(h: *mut EnvHandle) -> *const c_char {
    match unsafe { handle(h) } {
        Ok(h) => h.info.as_ptr(),
        Err(e) => {
            set_error(e);
            std::ptr::null()
        }
    }
}

/// Resets every environment: environment i with seed `first_seed + i`.
///
/// # Safety
/// `h` is null or a handle from [`graspd_env_new`] not yet freed, used by one thread at a time.
#[no_mangle]
pub unsafe extern "C" fn graspd_env_reset(h: *mut EnvHandle, first_seed: u64) -> i32 {
    guarded(|| {
        let h = unsafe { handle(h) }?;
        h.envs.reset_all(first_seed).map_err(|e| e.to_string())?;
        h.refresh_flags();
        Ok(())
    })
}

/// One control step with `len` action values (N rows of the action layout).
///
/// # Safety
/// `h` as for [`graspd_env_reset`]; `actions` points at `len` floats.
#[no_mangle]
pub unsafe extern "C" fn graspd_env_step(h: *mut EnvHandle, actions: *const f32, len: usize) -> i32 {
    guarded(|| {
        let h = unsafe { handle(h) }?;
        if actions.is_null() {
            return Err("null actions".into());
        }
        // SAFETY: the caller promises `len` floats at `actions`.
        let actions = unsafe { std::slice::from_raw_parts(actions, len) };
        h.envs.step(actions).map_err(|e| e.to_string())?;
        h.refresh_flags();
        Ok(())
    })
}

/// The scripted experts' actions for the next step into `out` (`len` floats: N rows).
///
/// # Safety
/// `h` as for [`graspd_env_reset`]; `out` points at `len` writable floats.
#[no_mangle]
pub unsafe extern "C" fn graspd_env_expert_actions(h: *mut EnvHandle, out: *mut f32, len: usize) -> i32 {
    guarded(|| {
        let h = unsafe { handle(h) }?;
        if out.is_null() {
            return Err("null output".into());
        }
        // SAFETY: the caller promises `len` writable floats at `out`.
        let out = unsafe { std::slice::from_raw_parts_mut(out, len) };
        h.envs.expert_actions(&mut h.experts, out).map_err(|e| e.to_string())
    })
}

/// N × observation length floats: the observations after the last step or reset.
///
/// # Safety
/// `h` is null or a handle from [`graspd_env_new`] not yet freed, used by one thread at a time.
#[no_mangle]
pub unsafe extern "C" fn graspd_env_observations(h: *mut EnvHandle) -> *const f32 {
    unsafe { handle(h) }.map_or(std::ptr::null(), |h| h.envs.observations().as_ptr())
}

/// N × observation length floats: the last observation of the episodes that ended at the last step.
///
/// # Safety
/// `h` is null or a handle from [`graspd_env_new`] not yet freed, used by one thread at a time.
#[no_mangle]
pub unsafe extern "C" fn graspd_env_final_observations(h: *mut EnvHandle) -> *const f32 {
    unsafe { handle(h) }.map_or(std::ptr::null(), |h| h.envs.final_observations().as_ptr())
}

/// N floats: the rewards of the last step.
///
/// # Safety
/// `h` is null or a handle from [`graspd_env_new`] not yet freed, used by one thread at a time.
#[no_mangle]
pub unsafe extern "C" fn graspd_env_rewards(h: *mut EnvHandle) -> *const f32 {
    unsafe { handle(h) }.map_or(std::ptr::null(), |h| h.envs.rewards().as_ptr())
}

/// N bytes: 1 where the episode ended at the last step (and was reset).
///
/// # Safety
/// `h` is null or a handle from [`graspd_env_new`] not yet freed, used by one thread at a time.
#[no_mangle]
pub unsafe extern "C" fn graspd_env_dones(h: *mut EnvHandle) -> *const u8 {
    unsafe { handle(h) }.map_or(std::ptr::null(), |h| h.dones.as_ptr())
}

/// N bytes: 1 where the task's success rule held after the last step.
///
/// # Safety
/// `h` is null or a handle from [`graspd_env_new`] not yet freed, used by one thread at a time.
#[no_mangle]
pub unsafe extern "C" fn graspd_env_successes(h: *mut EnvHandle) -> *const u8 {
    unsafe { handle(h) }.map_or(std::ptr::null(), |h| h.successes.as_ptr())
}

/// JSON array of the episodes finished since the last call (environment,
/// instance, seed, success, return, steps, grasp); valid until the next call.
///
/// # Safety
/// `h` is null or a handle from [`graspd_env_new`] not yet freed, used by one thread at a time.
#[no_mangle]
pub unsafe extern "C" fn graspd_env_drain_finished(h: *mut EnvHandle) -> *const c_char {
    let mut out = std::ptr::null();
    guarded(|| {
        let h = unsafe { handle(h) }?;
        let text = serde_json::to_string(&h.envs.drain_finished()).map_err(|e| e.to_string())?;
        h.json = CString::new(text).map_err(|e| e.to_string())?;
        out = h.json.as_ptr();
        Ok(())
    });
    out
}
