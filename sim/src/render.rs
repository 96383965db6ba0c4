//! Pictures of an episode: MuJoCo's own renderer, offscreen and headless
//! (mujoco-rs's `renderer`: an EGL pbuffer context on the first EGL device,
//! Mesa's software rasteriser where there is no GPU), on a copy of the
//! scene's model recoloured by role (table, tool, hand, fixture).
//!
//! An episode is recorded, then drawn: [`record`] runs a closure (e.g. one
//! seeded `sim place` episode, through the task's own functions, unchanged)
//! and returns what every [`crate::carry::EpisodeStepper`] on this thread
//! stepped: the model, and `qpos` and the mocap targets after the reset and
//! after every control step. The recording is thread-local and off unless
//! [`record`] is running, so that the tasks need no hook in their signatures
//! and the other callers pay one check per control step.
//!
//! [`EpisodeRenderer`] draws recorded states from a free camera aimed at the
//! tool's path, optionally with a translucent copy of the tool at the task's
//! goal; [`Picture`] holds RGB pixels, lays frames side by side and writes
//! PNG. [`make_strip`] is `sim strip`: one seeded episode, K frames evenly
//! spaced over it and the strip of them.
//!
//! Where no EGL library or device is found the renderer is
//! [`SimError::Offscreen`] (the tests that draw skip on it, saying so).

use std::cell::RefCell;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use mujoco_rs::prelude::{MjData, MjModel, MjtObjBase};
use mujoco_rs::renderer::{png, MjRenderer, RendererError};
use mujoco_rs::wrappers::mj_model::traits::ModelType;
use mujoco_rs::wrappers::mj_visualization::MjvCamera;
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use serde::Serialize;

use crate::engine::SimError;
use crate::scene::Scene;
use crate::task::Task;

/// What a geom shows, for its colour.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub enum GeomRole {
    Table,
    Tool,
    Hand,
    /// The nail (geoms named `nail_*`).
    Metal,
    /// Any other fixture (the nail's board).
    Fixture,
}

/// One recorded state of an episode.
#[derive(Clone, Debug)]
pub struct RecordedState {
    /// Simulated time, seconds.
    pub time_s: f64,
    pub qpos: Vec<f64>,
    pub mocap_pos: Vec<f64>,
    pub mocap_quat: Vec<f64>,
}

/// An episode as recorded by [`record`]: the scene's model, each geom's role,
/// and the states after the reset and after every control step.
#[derive(Clone, Debug)]
pub struct Recording {
    pub model: Arc<MjModel>,
    pub roles: Vec<GeomRole>,
    /// Body id and qpos address of each tool (the scene's order).
    pub tools: Vec<(usize, usize)>,
    pub states: Vec<RecordedState>,
}

impl Recording {
    /// The recording of `scene`, starting with the state of `data`.
    fn start<M: ModelType>(scene: &Scene, data: &MjData<M>) -> Self {
        let model = scene.model.clone();
        let tool_bodies: Vec<usize> = scene.tools.iter().map(|t| t.body).collect();
        let hand_bodies: Vec<usize> = scene.hand.as_ref().map_or_else(Vec::new, |h| h.link_bodies.clone());
        let table = scene.table.map(|(g, _)| g);
        let roles = model
            .geom_bodyid()
            .iter()
            .enumerate()
            .map(|(g, &b)| {
                let b = b as usize;
                if Some(g) == table {
                    GeomRole::Table
                } else if tool_bodies.contains(&b) {
                    GeomRole::Tool
                } else if hand_bodies.contains(&b) {
                    GeomRole::Hand
                } else if model.id_to_name(MjtObjBase::mjOBJ_GEOM, g).is_some_and(|n| n.starts_with("nail")) {
                    GeomRole::Metal
                } else {
                    GeomRole::Fixture
                }
            })
            .collect();
        let tools = scene.tools.iter().map(|t| (t.body, t.qpos)).collect();
        Self { model, roles, tools, states: vec![state_of(data)] }
    }

    /// Simulated duration, seconds (first to last state).
    pub fn duration_s(&self) -> f64 {
        match (self.states.first(), self.states.last()) {
            (Some(a), Some(b)) => b.time_s - a.time_s,
            _ => 0.0,
        }
    }

    /// The first tool's position (its frame's origin) in state `k`.
    pub fn tool_position(&self, k: usize) -> Option<Point3<f64>> {
        let (_, adr) = *self.tools.first()?;
        let q = self.states.get(k)?.qpos.get(adr..adr + 3)?;
        Some(Point3::new(q[0], q[1], q[2]))
    }

    /// Indices of `k` states evenly spaced in time over the recording, the
    /// first and the last included (the nearest recorded state to each time).
    pub fn evenly_spaced(&self, k: usize) -> Vec<usize> {
        let n = self.states.len();
        if n == 0 || k == 0 {
            return Vec::new();
        }
        let t0 = self.states[0].time_s;
        let span = self.duration_s();
        (0..k)
            .map(|i| {
                let t = t0 + if k == 1 { span } else { span * i as f64 / (k - 1) as f64 };
                // States are in time order: the first at or after t, or the one before it if nearer.
                let j = self.states.partition_point(|s| s.time_s < t).min(n - 1);
                if j > 0 && (t - self.states[j - 1].time_s) < (self.states[j].time_s - t) {
                    j - 1
                } else {
                    j
                }
            })
            .collect()
    }
}

fn state_of<M: ModelType>(data: &MjData<M>) -> RecordedState {
    RecordedState {
        time_s: data.time(),
        qpos: data.qpos().to_vec(),
        mocap_pos: data.mocap_pos().iter().flatten().copied().collect(),
        mocap_quat: data.mocap_quat().iter().flatten().copied().collect(),
    }
}

enum Recorder {
    Off,
    On(Option<Recording>),
}

thread_local! {
    static RECORDER: RefCell<Recorder> = const { RefCell::new(Recorder::Off) };
}

/// Turns the recorder off again when [`record`]'s closure returns or unwinds.
struct RecorderGuard;

impl Drop for RecorderGuard {
    fn drop(&mut self) {
        RECORDER.with(|r| *r.borrow_mut() = Recorder::Off);
    }
}

/// Runs `f` with this thread's episodes recorded; returns its result and the
/// last episode started in it (each episode start begins a new recording),
/// `None` when none was.
pub fn record<R>(f: impl FnOnce() -> R) -> (R, Option<Recording>) {
    RECORDER.with(|r| *r.borrow_mut() = Recorder::On(None));
    let guard = RecorderGuard;
    let out = f();
    let recording = RECORDER.with(|r| match std::mem::replace(&mut *r.borrow_mut(), Recorder::Off) {
        Recorder::On(rec) => rec,
        Recorder::Off => None,
    });
    drop(guard);
    (out, recording)
}

/// An episode starts (called by [`crate::carry::EpisodeStepper::start`]).
pub(crate) fn record_start<M: ModelType>(scene: &Scene, data: &MjData<M>) {
    RECORDER.with(|r| {
        if let Recorder::On(rec) = &mut *r.borrow_mut() {
            *rec = Some(Recording::start(scene, data));
        }
    });
}

/// A control step ended (called by [`crate::carry::EpisodeStepper::step`]).
pub(crate) fn record_step<M: ModelType>(data: &MjData<M>) {
    RECORDER.with(|r| {
        if let Recorder::On(Some(rec)) = &mut *r.borrow_mut() {
            rec.states.push(state_of(data));
        }
    });
}

/// An RGB image, rows top to bottom.
#[derive(Clone, Debug, PartialEq)]
pub struct Picture {
    pub width: usize,
    pub height: usize,
    /// `3 * width * height` bytes.
    pub rgb: Vec<u8>,
}

impl Picture {
    pub fn filled(width: usize, height: usize, colour: [u8; 3]) -> Self {
        Self { width, height, rgb: colour.repeat(width * height) }
    }

    /// The pixel at column `x`, row `y` (`None` outside).
    pub fn pixel(&self, x: usize, y: usize) -> Option<[u8; 3]> {
        if x >= self.width || y >= self.height {
            return None;
        }
        let i = 3 * (y * self.width + x);
        Some([self.rgb[i], self.rgb[i + 1], self.rgb[i + 2]])
    }

    /// `pictures` side by side, top-aligned, `gap` columns of `background`
    /// between them (an empty list: a 0 × 0 picture).
    pub fn side_by_side(pictures: &[Picture], gap: usize, background: [u8; 3]) -> Self {
        let height = pictures.iter().map(|p| p.height).max().unwrap_or(0);
        let width = pictures.iter().map(|p| p.width).sum::<usize>() + gap * pictures.len().saturating_sub(1);
        let mut out = Self::filled(width, height, background);
        let mut x0 = 0;
        for p in pictures {
            for y in 0..p.height {
                let src = &p.rgb[3 * y * p.width..3 * (y + 1) * p.width];
                let start = 3 * (y * width + x0);
                out.rgb[start..start + src.len()].copy_from_slice(src);
            }
            x0 += p.width + gap;
        }
        out
    }

    /// Writes an 8-bit RGB PNG (best compression: these go into the repository).
    pub fn write_png(&self, path: &Path) -> Result<(), SimError> {
        let io = |source| SimError::Io { path: path.to_owned(), source };
        let file = std::fs::File::create(path).map_err(io)?;
        let (w, h) = (
            u32::try_from(self.width).map_err(|_| SimError::Config { reason: "picture too wide".into() })?,
            u32::try_from(self.height).map_err(|_| SimError::Config { reason: "picture too tall".into() })?,
        );
        let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), w, h);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        encoder.set_compression(png::Compression::High);
        let encode = |e: png::EncodingError| SimError::Io {
            path: path.to_owned(),
            source: match e {
                png::EncodingError::IoError(e) => e,
                other => std::io::Error::other(other.to_string()),
            },
        };
        let mut writer = encoder.write_header().map_err(encode)?;
        writer.write_image_data(&self.rgb).map_err(encode)?;
        writer.finish().map_err(encode)
    }
}

/// Colours and camera of the pictures.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct RenderOptions {
    pub width: usize,
    pub height: usize,
    /// Camera azimuth and elevation, degrees (MuJoCo's free camera: azimuth
    /// about z from +x, elevation negative looking down).
    pub azimuth_deg: f64,
    pub elevation_deg: f64,
    /// Distance from the point looked at, metres; `None`: from the tool's path.
    pub distance_m: Option<f64>,
    /// Vertical field of view, degrees.
    pub fovy_deg: f64,
    pub background: [u8; 3],
    pub table: [f32; 4],
    pub tool: [f32; 4],
    pub hand: [f32; 4],
    pub metal: [f32; 4],
    pub fixture: [f32; 4],
    /// The translucent tool at the goal.
    pub ghost: [f32; 4],
}

impl Default for RenderOptions {
    fn default() -> Self {
        Self {
            width: 320,
            height: 240,
            azimuth_deg: 270.0,
            elevation_deg: -35.0,
            distance_m: None,
            fovy_deg: 45.0,
            background: [236, 238, 242],
            table: [0.88, 0.82, 0.72, 1.0],
            tool: [0.20, 0.42, 0.78, 1.0],
            hand: [0.90, 0.80, 0.70, 1.0],
            metal: [0.55, 0.56, 0.60, 1.0],
            fixture: [0.55, 0.38, 0.22, 1.0],
            ghost: [0.20, 0.75, 0.35, 0.35],
        }
    }
}

impl RenderOptions {
    fn validate(&self) -> Result<(), SimError> {
        let bad = |reason: String| Err(SimError::Config { reason });
        if !(16..=4096).contains(&self.width) || !(16..=4096).contains(&self.height) {
            return bad(format!("picture size {} × {}: 16 to 4096 pixels each way", self.width, self.height));
        }
        if !(self.fovy_deg > 1.0 && self.fovy_deg < 170.0) {
            return bad(format!("field of view {}°: 1 to 170", self.fovy_deg));
        }
        if self.distance_m.is_some_and(|d| !(d.is_finite() && d > 0.0)) {
            return bad(format!("camera distance {:?} m: positive", self.distance_m));
        }
        if !(self.azimuth_deg.is_finite() && self.elevation_deg.is_finite()) {
            return bad("camera angles must be finite".into());
        }
        Ok(())
    }

    fn colour(&self, role: GeomRole) -> [f32; 4] {
        match role {
            GeomRole::Table => self.table,
            GeomRole::Tool => self.tool,
            GeomRole::Hand => self.hand,
            GeomRole::Metal => self.metal,
            GeomRole::Fixture => self.fixture,
        }
    }
}

fn offscreen_error(e: RendererError) -> SimError {
    match e {
        RendererError::GlutinError(g) => SimError::Offscreen { reason: g.to_string() },
        other => SimError::Render { reason: other.to_string() },
    }
}

/// Draws the states of a [`Recording`] (module docs).
pub struct EpisodeRenderer {
    model: Arc<MjModel>,
    data: MjData<Arc<MjModel>>,
    renderer: MjRenderer,
    options: RenderOptions,
    /// The depth of the far clipping plane, metres: deeper pixels are background.
    far_m: f64,
    tool_geoms: Vec<usize>,
}

impl EpisodeRenderer {
    /// A renderer for `recording`'s model, the camera fitted ([`Self::fit`])
    /// to every tenth state.
    pub fn new(recording: &Recording, options: &RenderOptions) -> Result<Self, SimError> {
        options.validate()?;
        let mut model: MjModel = (*recording.model).clone();
        let (w, h) = (options.width as i32, options.height as i32);
        {
            let vis = model.vis_mut();
            vis.global.offwidth = vis.global.offwidth.max(w);
            vis.global.offheight = vis.global.offheight.max(h);
            vis.global.fovy = options.fovy_deg as f32;
            vis.headlight.ambient = [0.45, 0.45, 0.45];
            vis.headlight.diffuse = [0.6, 0.6, 0.6];
            vis.headlight.specular = [0.15, 0.15, 0.15];
            vis.headlight.active = 1;
        }
        for (rgba, role) in model.geom_rgba_mut().iter_mut().zip(&recording.roles) {
            *rgba = options.colour(*role);
        }
        let tool_geoms = (0..recording.roles.len()).filter(|&g| recording.roles[g] == GeomRole::Tool).collect();
        let far_m = model.stat().extent * model.vis().map.zfar as f64;
        let model = Arc::new(model);
        let data = MjData::new(model.clone());
        let mut camera = MjvCamera::new_free(&model);
        camera.azimuth = options.azimuth_deg;
        camera.elevation = options.elevation_deg;

        let renderer = MjRenderer::builder()
            .width(w as u32)
            .height(h as u32)
            .rgb(true)
            .depth(true)
            .num_visual_user_geom(recording.roles.len() as u32 + 8)
            .png_compression(png::Compression::High)
            .camera(camera)
            .build(&model)
            .map_err(offscreen_error)?;
        let mut out = Self { model, data, renderer, options: options.clone(), far_m, tool_geoms };
        let every_tenth: Vec<usize> = (0..recording.states.len()).step_by(10).collect();
        out.fit(recording, &every_tenth);
        Ok(out)
    }

    /// Aims the camera at the middle of what the tools, fixtures and hand
    /// sweep through in the recorded `states` (bounding spheres of their
    /// geoms), from the nearest distance that keeps all of it in the picture
    /// (`options.distance_m` when given).
    pub fn fit(&mut self, recording: &Recording, states: &[usize]) {
        let spheres = swept_spheres(&mut self.data, recording, states);
        if spheres.is_empty() {
            self.aim(&Point3::new(0.0, 0.0, 0.1), self.options.distance_m.unwrap_or(0.6));
            return;
        }
        let (mut lo, mut hi) = (Vector3::repeat(f64::INFINITY), Vector3::repeat(f64::NEG_INFINITY));
        for (c, r) in &spheres {
            lo = lo.inf(&c.add_scalar(-r));
            hi = hi.sup(&c.add_scalar(*r));
        }
        let centre = (lo + hi) / 2.0;
        // The nearest camera that holds every sphere inside the frustum, 10 % spare.
        let [forward, up, right] = camera_axes(self.options.azimuth_deg, self.options.elevation_deg);
        let tan_v = (0.5 * self.options.fovy_deg.to_radians()).tan();
        let tan_h = tan_v * self.options.width as f64 / self.options.height as f64;
        let fit = spheres
            .iter()
            .map(|(c, r)| {
                let v = c - centre;
                let depth = v.dot(&forward);
                ((v.dot(&right).abs() + r) / tan_h).max((v.dot(&up).abs() + r) / tan_v) - depth
            })
            .fold(0.0f64, f64::max);
        self.aim(&Point3::from(centre), self.options.distance_m.unwrap_or((1.1 * fit).clamp(0.15, 3.0)));
    }

    /// The camera's free-camera parameters (lookat, distance, azimuth, elevation).
    pub fn camera(&self) -> &MjvCamera {
        self.renderer.camera()
    }

    /// Aims the camera at `lookat` from `distance_m`.
    pub fn aim(&mut self, lookat: &Point3<f64>, distance_m: f64) {
        let mut camera = self.renderer.camera().clone();
        camera.lookat = lookat.coords.into();
        camera.distance = distance_m;
        self.renderer.set_camera(camera);
    }

    /// Draws a translucent copy of the (first) tool at `pose` (the tool
    /// frame in the world) in every later picture: the task's goal.
    pub fn add_ghost(&mut self, pose: &Isometry3<f64>) -> Result<(), SimError> {
        let m = &self.model;
        for &g in &self.tool_geoms {
            let local = Isometry3::from_parts(
                Translation3::from(Vector3::from(m.geom_pos()[g])),
                UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
                    m.geom_quat()[g][0],
                    m.geom_quat()[g][1],
                    m.geom_quat()[g][2],
                    m.geom_quat()[g][3],
                )),
            );
            let world = pose * local;
            let r = world.rotation.to_rotation_matrix();
            let mat: [f64; 9] = std::array::from_fn(|i| r[(i / 3, i % 3)]);
            let geom_type = mujoco_rs::wrappers::mj_model::MjtGeom::from(m.geom_type()[g]);
            let dataid = m.geom_dataid()[g];
            // SAFETY: matid and texid stay -1 (as mjv_initGeom leaves them)
            // and a mesh geom's dataid names a mesh of the model the context
            // was made for; no flex or skin geoms are made.
            let geom = unsafe {
                self.renderer.user_scene_mut().try_create_geom(
                    geom_type,
                    Some(m.geom_size()[g]),
                    Some(world.translation.vector.into()),
                    Some(mat),
                    Some(self.options.ghost),
                )
            }
            .map_err(|e| SimError::Render { reason: e.to_string() })?;
            // mjvGeom's mesh ids are 2 × the model's (odd: the convex hull).
            geom.dataid = if dataid >= 0 { 2 * dataid } else { -1 };
        }
        Ok(())
    }

    /// The picture of `state` (a state of the recording this renderer was made for).
    pub fn draw(&mut self, state: &RecordedState) -> Result<Picture, SimError> {
        set_state(&mut self.data, state)?;
        self.renderer.sync_data(&mut self.data).map_err(offscreen_error)?;
        self.renderer.render().map_err(offscreen_error)?;
        let (Some(rgb), Some(depth)) = (self.renderer.rgb_flat(), self.renderer.depth_flat()) else {
            return Err(SimError::Render { reason: "the renderer returned no pixels".into() });
        };
        let mut picture = Picture { width: self.options.width, height: self.options.height, rgb: rgb.to_vec() };
        // Nothing drawn there (the far plane): the background colour instead of black.
        let far = 0.98 * self.far_m as f32;
        for (px, &d) in picture.rgb.chunks_exact_mut(3).zip(depth) {
            if d >= far {
                px.copy_from_slice(&self.options.background);
            }
        }
        Ok(picture)
    }

    /// Where the world point `p` lands in the picture (column, row; pixel
    /// centres at half-integers), `None` behind the camera. For the last
    /// state drawn.
    pub fn project(&self, p: &Point3<f64>) -> Option<(f64, f64)> {
        let (head, forward, up, right) = self.renderer.camera().frame(&self.data);
        let v = p.coords - Vector3::from(head);
        let z = v.dot(&Vector3::from(forward));
        if z <= 0.0 {
            return None;
        }
        let f = 0.5 * self.options.height as f64 / (0.5 * self.options.fovy_deg.to_radians()).tan();
        let x = 0.5 * self.options.width as f64 + f * v.dot(&Vector3::from(right)) / z;
        let y = 0.5 * self.options.height as f64 - f * v.dot(&Vector3::from(up)) / z;
        Some((x, y))
    }
}

/// Sets `data` to a recorded state and computes its positions.
fn set_state(data: &mut MjData<Arc<MjModel>>, state: &RecordedState) -> Result<(), SimError> {
    let mismatch = |what: &str| SimError::Render { reason: format!("a recorded state of another model ({what})") };
    if state.qpos.len() != data.qpos().len() {
        return Err(mismatch("qpos"));
    }
    if state.mocap_pos.len() != 3 * data.mocap_pos().len() || state.mocap_quat.len() != 4 * data.mocap_quat().len() {
        return Err(mismatch("mocap"));
    }
    data.qpos_mut().copy_from_slice(&state.qpos);
    for (p, s) in data.mocap_pos_mut().iter_mut().zip(state.mocap_pos.chunks_exact(3)) {
        p.copy_from_slice(s);
    }
    for (q, s) in data.mocap_quat_mut().iter_mut().zip(state.mocap_quat.chunks_exact(4)) {
        q.copy_from_slice(s);
    }
    data.forward();
    Ok(())
}

/// The bounding spheres (centre, radius) of every geom but the table's
/// (tools, fixtures, hand) in the recorded `states`.
fn swept_spheres(data: &mut MjData<Arc<MjModel>>, recording: &Recording, states: &[usize]) -> Vec<(Vector3<f64>, f64)> {
    let roles = &recording.roles;
    let shown: Vec<usize> = (0..roles.len()).filter(|&g| roles[g] != GeomRole::Table).collect();
    let mut spheres = Vec::new();
    for state in states.iter().filter_map(|&k| recording.states.get(k)) {
        if set_state(data, state).is_err() {
            continue;
        }
        let rbound = data.model().geom_rbound();
        spheres.extend(shown.iter().map(|&g| (Vector3::from(data.geom_xpos()[g]), rbound[g])));
    }
    spheres
}

/// The camera's forward, up and right axes at `azimuth_deg` and
/// `elevation_deg` (MuJoCo's free camera, mjv_cameraFrame).
fn camera_axes(azimuth_deg: f64, elevation_deg: f64) -> [Vector3<f64>; 3] {
    let (sa, ca) = azimuth_deg.to_radians().sin_cos();
    let (se, ce) = elevation_deg.to_radians().sin_cos();
    let forward = Vector3::new(ca * ce, sa * ce, se);
    let up = Vector3::new(-ca * se, -sa * se, ce);
    [forward, up, forward.cross(&up)]
}

/// What `sim strip` draws.
#[derive(Clone, Debug)]
pub struct StripRequest {
    pub task: Task,
    /// An instance of the task's category (default: its canonical).
    pub instance: Option<String>,
    pub seed: u64,
    /// Where the hand starts (crate::plan::StartMode).
    pub start: crate::plan::StartMode,
    /// The grasp from the scene camera's view of the tool, registered and
    /// grasped by graspd's engine in this process (`--grasp-from register`;
    /// test tools need it) instead of the tool's training latent.
    pub from_camera: bool,
    pub frames: usize,
    pub render: RenderOptions,
    /// Columns between the frames of the strip.
    pub gap: usize,
}

/// One frame written.
#[derive(Clone, Debug, Serialize)]
pub struct StripFrame {
    pub path: PathBuf,
    /// Simulated time of the frame, seconds from the episode's start.
    pub t_s: f64,
}

/// What `sim strip` wrote.
#[derive(Clone, Debug, Serialize)]
pub struct StripOutput {
    pub task: Task,
    pub instance: String,
    pub seed: u64,
    /// The episode's success by the task's rule.
    pub success: bool,
    pub frames: Vec<StripFrame>,
    pub strip: PathBuf,
    /// Width and height of a frame and of the strip, pixels.
    pub frame_size: [usize; 2],
    pub strip_size: [usize; 2],
    pub strip_bytes: u64,
    /// Planning, the scene and the episode, seconds.
    pub episode_s: f64,
    /// Setting up the renderer and drawing the frames, seconds.
    pub render_s: f64,
    pub elapsed_s: f64,
}

/// `sim strip`: one seeded episode of the task (its own functions, so the
/// same episode as `sim place|position|nail --seed S --episodes 1`),
/// recorded, then `frames` pictures evenly spaced over it (`frame_NN.png`)
/// and the strip of them (`strip.png`) written into `out`. `progress(done,
/// total)` after the episode and after each frame. The goal-pose tasks show
/// their goal as a translucent tool.
pub fn make_strip(
    request: &StripRequest,
    out: &Path,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<StripOutput, SimError> {
    use graspd::tools::{self, Split};
    let t0 = Instant::now();
    if request.frames == 0 || request.frames > 64 {
        return Err(SimError::Config { reason: format!("{} frames: 1 to 64", request.frames) });
    }
    request.render.validate()?;
    let category = request.task.category();
    let family = tools::family(category).map_err(|e| SimError::Tool { reason: e.to_string() })?;
    let instance = match &request.instance {
        Some(name) => family.iter().find(|i| &i.name == name),
        None => family.iter().find(|i| i.split == Split::Canonical),
    }
    .ok_or_else(|| SimError::Config {
        reason: format!("no {category} instance `{}`", request.instance.as_deref().unwrap_or("canonical")),
    })?;
    if instance.split == Split::Test && !request.from_camera {
        return Err(SimError::Config {
            reason: format!(
                "`{}` is a test instance: it has no latent, so its grasp comes from the camera (--grasp-from register)",
                instance.name
            ),
        });
    }
    std::fs::create_dir_all(out).map_err(|source| SimError::Io { path: out.to_owned(), source })?;
    let asset = crate::hand::HandAsset::default_sih()?;
    let mut planner = crate::plan::GraspPlanner::new(asset.model(), category, request.seed)?.with_start(request.start);
    if request.from_camera {
        planner =
            planner.with_engine_camera(crate::camera::SceneCamera::default(), crate::camera::LabFrame::default())?;
    }
    let table_z = crate::scene::Table::default().top_z;
    let total = request.frames + 1;

    let (run, recording) = record(|| -> Result<(bool, Option<Isometry3<f64>>), SimError> {
        Ok(match request.task {
            Task::PlaceMug => {
                let setup = crate::place::PlaceSetup::default();
                let goal = setup.ranges.sample(request.seed, table_z).goal;
                let o = crate::place::place_instance(&asset, &mut planner, instance, &setup, request.seed, 1)?;
                (o.first().is_some_and(|o| o.success), Some(goal))
            }
            Task::PositionDrill => {
                let setup = crate::position::DrillSetup::default();
                let goal = setup.ranges.sample(request.seed, table_z).goal;
                let o = crate::position::position_instance(&asset, &mut planner, instance, &setup, request.seed, 1)?;
                (o.first().is_some_and(|o| o.success), Some(goal))
            }
            Task::DriveNail => {
                let setup = crate::nail::NailSetup::default();
                let o = crate::nail::nail_instance(&asset, &mut planner, instance, &setup, request.seed, 1)?;
                (o.first().is_some_and(|o| o.success), None)
            }
        })
    });
    let (success, goal) = run?;
    let recording = recording.ok_or_else(|| SimError::Render { reason: "the episode recorded nothing".into() })?;
    let episode_s = t0.elapsed().as_secs_f64();
    progress(1, total);

    let t1 = Instant::now();
    let mut renderer = EpisodeRenderer::new(&recording, &request.render)?;
    if let Some(goal) = goal {
        renderer.add_ghost(&goal)?;
    }
    let drawn = recording.evenly_spaced(request.frames);
    renderer.fit(&recording, &drawn);
    let t_start = recording.states.first().map_or(0.0, |s| s.time_s);
    let mut pictures = Vec::with_capacity(request.frames);
    let mut frames = Vec::with_capacity(request.frames);
    for (i, &k) in drawn.iter().enumerate() {
        let state = &recording.states[k];
        let picture = renderer.draw(state)?;
        let path = out.join(format!("frame_{i:02}.png"));
        picture.write_png(&path)?;
        frames.push(StripFrame { path, t_s: state.time_s - t_start });
        pictures.push(picture);
        progress(i + 2, total);
    }
    let strip = Picture::side_by_side(&pictures, request.gap, request.render.background);
    let strip_path = out.join("strip.png");
    strip.write_png(&strip_path)?;
    let strip_bytes =
        std::fs::metadata(&strip_path).map_err(|source| SimError::Io { path: strip_path.clone(), source })?.len();
    Ok(StripOutput {
        task: request.task,
        instance: instance.name.clone(),
        seed: request.seed,
        success,
        frames,
        strip: strip_path,
        frame_size: [request.render.width, request.render.height],
        strip_size: [strip.width, strip.height],
        strip_bytes,
        episode_s,
        render_s: t1.elapsed().as_secs_f64(),
        elapsed_s: t0.elapsed().as_secs_f64(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{SceneSpec, Table};
    use graspd::tools::{self, Category};

    /// The renderer, or `None` (with a note on stderr) where this machine
    /// has no offscreen OpenGL: those tests skip instead of failing.
    fn renderer_or_skip(recording: &Recording, options: &RenderOptions) -> Option<EpisodeRenderer> {
        match EpisodeRenderer::new(recording, options) {
            Ok(r) => Some(r),
            Err(SimError::Offscreen { reason }) => {
                eprintln!("skipped: no offscreen rendering here ({reason})");
                None
            }
            Err(e) => panic!("{e}"),
        }
    }

    fn is_tool_blue(px: [u8; 3]) -> bool {
        let [r, g, b] = px.map(i32::from);
        b > r + 40 && b > g + 20
    }

    /// The canonical mug on the table, turned and off the origin, drawn from
    /// a camera aimed beside it: the pixel where its middle projects is the
    /// tool's colour, every tool-coloured pixel lies within the projection
    /// of its vertices, the table shows where the table projects, and the
    /// sky above the table's far edge is the background colour.
    #[test]
    fn a_frame_has_the_tool_where_it_is_and_background_elsewhere() {
        let (mug, body) = crate::tool::canonical_mug();
        let pose = Isometry3::from_parts(
            Translation3::new(0.07, -0.04, 0.0),
            UnitQuaternion::from_euler_angles(0.0, 0.0, 0.6),
        );
        let spec = SceneSpec {
            name: "mug_picture".into(),
            table: Some(Table::default()),
            tools: vec![(&body, pose)],
            ..Default::default()
        };
        let scene = spec.build().unwrap();
        let mut data = MjData::new(scene.model.clone());
        data.forward();
        let recording = Recording::start(&scene, &data);
        assert_eq!(recording.roles.iter().filter(|r| **r == GeomRole::Table).count(), 1);
        assert_eq!(recording.roles.iter().filter(|r| **r == GeomRole::Tool).count(), body.hulls.len());
        let options = RenderOptions { width: 160, height: 120, ..Default::default() };
        let Some(mut renderer) = renderer_or_skip(&recording, &options) else { return };
        // Aimed 6 cm to the side of the mug's middle and 4 cm above it: the
        // mug is off the centre of the picture both ways.
        let middle = pose * Point3::new(0.0, 0.0, 0.05);
        renderer.aim(&(middle + Vector3::new(0.06, 0.0, 0.04)), 0.45);
        let pic = renderer.draw(&recording.states[0]).unwrap();
        assert_eq!((pic.width, pic.height, pic.rgb.len()), (160, 120, 160 * 120 * 3));

        let (mx, my) = renderer.project(&middle).unwrap();
        assert!(mx > 90.0 && my > 70.0, "the mug's middle projects at ({mx}, {my}), not right of and below the centre");
        let px = pic.pixel(mx as usize, my as usize).unwrap();
        assert!(is_tool_blue(px), "at the mug's middle ({mx:.0}, {my:.0}): {px:?}");

        let projected: Vec<(f64, f64)> =
            mug.mesh.vertices.iter().map(|v| renderer.project(&(pose * v)).unwrap()).collect();
        let (x0, x1) = projected.iter().fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.0), b.max(p.0)));
        let (y0, y1) = projected.iter().fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.1), b.max(p.1)));
        let mut blue = 0;
        for y in 0..pic.height {
            for x in 0..pic.width {
                if is_tool_blue(pic.pixel(x, y).unwrap()) {
                    blue += 1;
                    let (fx, fy) = (x as f64 + 0.5, y as f64 + 0.5);
                    assert!(
                        fx > x0 - 2.0 && fx < x1 + 2.0 && fy > y0 - 2.0 && fy < y1 + 2.0,
                        "tool colour at ({x}, {y}), outside the mug's projection [{x0:.0}, {x1:.0}] × [{y0:.0}, {y1:.0}]"
                    );
                }
            }
        }
        let box_area = (x1 - x0) * (y1 - y0);
        assert!(blue as f64 > 0.3 * box_area, "{blue} tool pixels in a {box_area:.0} px² box");

        // The table 12 cm in front of the mug (toward the camera: at azimuth 270° it looks along −y).
        let (tx, ty) = renderer.project(&Point3::from(pose.translation.vector + Vector3::new(0.0, 0.12, 0.0))).unwrap();
        let table = pic.pixel(tx as usize, ty as usize).unwrap();
        assert!(table[0] > table[2] + 20 && !is_tool_blue(table), "table at ({tx:.0}, {ty:.0}): {table:?}");
        // Above the table's far edge: nothing drawn there.
        assert_eq!(pic.pixel(0, 0), Some(options.background));
        assert_eq!(pic.pixel(159, 0), Some(options.background));
    }

    /// Frames laid side by side: the sum of the widths and the gaps, the
    /// tallest height, each frame's pixels where it was put, background in
    /// the gaps and under a shorter frame.
    #[test]
    fn a_strip_is_the_frames_side_by_side() {
        let bg = [1, 2, 3];
        let frames = [
            Picture::filled(10, 8, [200, 0, 0]),
            Picture::filled(12, 6, [0, 200, 0]),
            Picture::filled(10, 8, [0, 0, 200]),
        ];
        let strip = Picture::side_by_side(&frames, 2, bg);
        assert_eq!((strip.width, strip.height), (10 + 2 + 12 + 2 + 10, 8));
        assert_eq!(strip.rgb.len(), 3 * strip.width * strip.height);
        assert_eq!(strip.pixel(0, 0), Some([200, 0, 0]));
        assert_eq!(strip.pixel(9, 7), Some([200, 0, 0]));
        assert_eq!(strip.pixel(10, 3), Some(bg));
        assert_eq!(strip.pixel(12, 5), Some([0, 200, 0]));
        assert_eq!(strip.pixel(12, 6), Some(bg));
        assert_eq!(strip.pixel(strip.width - 1, 7), Some([0, 0, 200]));
        assert_eq!(strip.pixel(strip.width, 0), None);
        assert_eq!(Picture::side_by_side(&[], 4, bg), Picture::filled(0, 0, bg));
    }

    /// Nothing is recorded outside [`record`]; inside it, an episode's reset
    /// and control steps are, and K frames are spread evenly over its 10 s.
    #[test]
    fn an_episode_is_recorded_and_its_frames_spread_over_it() {
        let (_, none) = record(|| ());
        assert!(none.is_none());
        let asset = crate::hand::HandAsset::default_sih().unwrap();
        let mut planner = crate::plan::GraspPlanner::new(asset.model(), Category::Mug, 0).unwrap();
        let mug = tools::instance(Category::Mug, "mug_canonical").unwrap();
        let setup = crate::place::PlaceSetup::default();
        let (outs, rec) = record(|| crate::place::place_instance(&asset, &mut planner, &mug, &setup, 3, 1).unwrap());
        let rec = rec.expect("a recording");
        let steps = outs[0].control_steps;
        assert_eq!(rec.states.len(), steps + 1);
        assert!((rec.duration_s() - crate::task::EPISODE_S).abs() < 1e-6, "{}", rec.duration_s());
        assert_eq!(rec.evenly_spaced(5), vec![0, steps / 4, steps / 2, 3 * steps / 4, steps]);
        assert_eq!(rec.evenly_spaced(1), vec![steps]);
        // The recorded end is the outcome's: the mug rests within 3 cm of its goal.
        let goal = setup.ranges.sample(3, 0.0).goal;
        let end = rec.tool_position(steps).unwrap();
        assert!((end.coords - goal.translation.vector).xy().norm() < 0.03, "{end} vs {goal}");
        // And the recorder is off again: a later episode leaves no trace.
        let _ = crate::place::place_instance(&asset, &mut planner, &mug, &setup, 4, 1).unwrap();
        RECORDER.with(|r| assert!(matches!(*r.borrow(), Recorder::Off)));
    }

    /// A test tool has no latent: its strip needs the grasp from the camera,
    /// and with it the episode runs (mug_test_01 is placed from its view).
    #[test]
    fn a_test_tool_is_drawn_with_its_grasp_from_the_camera() {
        let dir = tempfile::tempdir().unwrap();
        let mut request = StripRequest {
            task: Task::PlaceMug,
            instance: Some("mug_test_01".into()),
            seed: 0,
            start: crate::plan::StartMode::PreGrasp,
            from_camera: false,
            frames: 2,
            render: RenderOptions { width: 32, height: 24, ..Default::default() },
            gap: 2,
        };
        let err = make_strip(&request, dir.path(), &mut |_, _| {}).unwrap_err();
        assert!(err.to_string().contains("--grasp-from register"), "{err}");
        request.from_camera = true;
        let out = match make_strip(&request, dir.path(), &mut |_, _| {}) {
            Ok(out) => out,
            Err(SimError::Offscreen { reason }) => {
                eprintln!("skipped: no offscreen rendering here ({reason})");
                return;
            }
            Err(e) => panic!("{e}"),
        };
        assert_eq!(out.instance, "mug_test_01");
        assert!(out.success);
    }

    /// `sim strip` end to end, small: the frame files, the strip's size
    /// (K frames and K - 1 gaps wide) and the episode's success.
    #[test]
    fn make_strip_writes_the_frames_and_the_strip() {
        let dir = tempfile::tempdir().unwrap();
        let request = StripRequest {
            task: Task::PlaceMug,
            instance: None,
            seed: 0,
            start: crate::plan::StartMode::PreGrasp,
            from_camera: false,
            frames: 3,
            render: RenderOptions { width: 64, height: 48, ..Default::default() },
            gap: 4,
        };
        let mut calls = Vec::new();
        let out = match make_strip(&request, dir.path(), &mut |done, total| calls.push((done, total))) {
            Ok(out) => out,
            Err(SimError::Offscreen { reason }) => {
                eprintln!("skipped: no offscreen rendering here ({reason})");
                return;
            }
            Err(e) => panic!("{e}"),
        };
        assert!(out.success);
        assert_eq!(out.instance, "mug_canonical");
        assert_eq!(out.strip_size, [3 * 64 + 2 * 4, 48]);
        assert_eq!(out.frames.len(), 3);
        assert_eq!(calls, vec![(1, 4), (2, 4), (3, 4), (4, 4)]);
        let times: Vec<f64> = out.frames.iter().map(|f| f.t_s).collect();
        assert!(
            (times[0]).abs() < 1e-9 && (times[1] - 5.0).abs() < 0.02 && (times[2] - 10.0).abs() < 1e-6,
            "{times:?}"
        );
        for f in &out.frames {
            assert!(std::fs::metadata(&f.path).unwrap().len() > 100, "{}", f.path.display());
        }
        let bytes = std::fs::read(&out.strip).unwrap();
        assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n");
        // IHDR: width and height, big-endian, after the signature and the chunk header.
        assert_eq!(u32::from_be_bytes(bytes[16..20].try_into().unwrap()), 3 * 64 + 2 * 4);
        assert_eq!(u32::from_be_bytes(bytes[20..24].try_into().unwrap()), 48);
        assert_eq!(out.strip_bytes, bytes.len() as u64);
    }
}
