//! Writing the tool families to disk (one OBJ per instance) and the manifest
//! that indexes them, and reading the manifest back.
//!
//! Layout under `out_dir` (conventionally `assets/tools`):
//! `manifest.json` and `<category>/<instance>.obj`; the manifest's paths are
//! relative to `out_dir`. Output is byte-for-byte reproducible: fixed float
//! formatting in the OBJs, fixed field order in the JSON.

use super::{family, Category, Instance, Keypoint, Split, ToolParams, ToolsError};
use crate::geometry::TriMesh;
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;
use std::fs;
use std::path::{Path, PathBuf};

pub const MANIFEST_FILE: &str = "manifest.json";
pub const FORMAT_VERSION: u32 = 1;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub format_version: u32,
    /// Always "metres".
    pub units: String,
    pub categories: Vec<CategoryInfo>,
    pub instances: Vec<InstanceRecord>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CategoryInfo {
    pub category: Category,
    /// The canonical frame in words.
    pub canonical_frame: String,
    /// Keypoint names, in the order every instance lists them.
    pub keypoints: Vec<String>,
    /// Name of the canonical instance.
    pub canonical: String,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct InstanceRecord {
    pub category: Category,
    pub name: String,
    pub split: Split,
    pub seed: Option<u64>,
    /// OBJ path relative to the manifest's directory, '/'-separated.
    pub path: String,
    pub params: ToolParams,
    pub keypoints: Vec<Keypoint>,
    pub vertices: usize,
    pub triangles: usize,
    /// Closed parts of the mesh (they may overlap).
    pub parts: usize,
    /// Sum of the parts' volumes (m³); overlaps are counted in each part.
    pub volume: f64,
    /// Axis-aligned extent (m).
    pub extent: [f64; 3],
}

impl Manifest {
    /// Reads a manifest written by [`generate`].
    pub fn load(path: &Path) -> Result<Self, ToolsError> {
        let text = fs::read_to_string(path).map_err(|source| ToolsError::Io { path: path.to_owned(), source })?;
        serde_json::from_str(&text).map_err(|source| ToolsError::Json { path: path.to_owned(), source })
    }

    pub fn instances_of(&self, category: Category) -> impl Iterator<Item = &InstanceRecord> {
        self.instances.iter().filter(move |r| r.category == category)
    }

    pub fn instance(&self, name: &str) -> Option<&InstanceRecord> {
        self.instances.iter().find(|r| r.name == name)
    }
}

impl InstanceRecord {
    fn new(inst: &Instance, path: String) -> Self {
        let extent = inst.mesh.aabb().map(|(lo, hi)| (hi - lo).into()).unwrap_or([0.0; 3]);
        Self {
            category: inst.category,
            name: inst.name.clone(),
            split: inst.split,
            seed: inst.seed,
            path,
            params: inst.params.clone(),
            keypoints: inst.keypoints.clone(),
            vertices: inst.mesh.vertices.len(),
            triangles: inst.mesh.triangles.len(),
            parts: inst.mesh.part_ranges().len(),
            volume: inst.mesh.signed_volume(),
            extent,
        }
    }
}

/// Builds all families and writes `out_dir/<category>/<name>.obj` for every
/// instance plus `out_dir/manifest.json`; returns the manifest.
pub fn generate(out_dir: &Path) -> Result<Manifest, ToolsError> {
    let mut manifest = Manifest {
        format_version: FORMAT_VERSION,
        units: "metres".into(),
        categories: Vec::new(),
        instances: Vec::new(),
    };
    for category in Category::ALL {
        let dir = out_dir.join(category.name());
        fs::create_dir_all(&dir).map_err(|source| ToolsError::Io { path: dir.clone(), source })?;
        manifest.categories.push(CategoryInfo {
            category,
            canonical_frame: category.canonical_frame().into(),
            keypoints: category.keypoint_names().iter().map(|s| s.to_string()).collect(),
            canonical: format!("{category}_canonical"),
        });
        for inst in family(category)? {
            let rel = format!("{}/{}.obj", category.name(), inst.name);
            write_obj(&inst.mesh, &obj_header(&inst), &out_dir.join(&rel))?;
            manifest.instances.push(InstanceRecord::new(&inst, rel));
        }
    }
    let path = out_dir.join(MANIFEST_FILE);
    let mut json =
        serde_json::to_string_pretty(&manifest).map_err(|source| ToolsError::Json { path: path.clone(), source })?;
    json.push('\n');
    write_file(&path, json.as_bytes())?;
    Ok(manifest)
}

fn obj_header(inst: &Instance) -> Vec<String> {
    let mut lines = vec![
        format!("graspd procedural tool {}", inst.name),
        format!(
            "category {}, split {}, seed {}",
            inst.category,
            inst.split,
            inst.seed.map_or("none".into(), |s| s.to_string())
        ),
        "units: metres".into(),
        format!("frame: {}", inst.category.canonical_frame()),
    ];
    for k in &inst.keypoints {
        let [x, y, z] = k.position;
        lines.push(format!("keypoint {} {} {} {}", k.name, fmt6(x), fmt6(y), fmt6(z)));
    }
    lines
}

/// `{:.6}`, without the sign on a rounded zero (so −1e-9 and 1e-9 print alike).
fn fmt6(v: f64) -> String {
    let s = format!("{v:.6}");
    if s == "-0.000000" {
        "0.000000".into()
    } else {
        s
    }
}

/// The mesh as Wavefront OBJ text: `#` header lines, one `# part` comment
/// per closed part (first and one-past-last triangle), `v` and 1-based `f`.
pub fn obj_string(mesh: &TriMesh, header: &[String]) -> String {
    let mut s = String::with_capacity(40 * (mesh.vertices.len() + mesh.triangles.len()) + 512);
    for line in header {
        // One comment per line even if a header line contains newlines.
        for l in line.lines() {
            let _ = writeln!(s, "# {l}");
        }
    }
    let _ = writeln!(s, "# vertices {} triangles {}", mesh.vertices.len(), mesh.triangles.len());
    for (k, r) in mesh.part_ranges().iter().enumerate() {
        let _ = writeln!(s, "# part {k} triangles {} {}", r.start, r.end);
    }
    for v in &mesh.vertices {
        let _ = writeln!(s, "v {} {} {}", fmt6(v.x), fmt6(v.y), fmt6(v.z));
    }
    for t in &mesh.triangles {
        let _ = writeln!(s, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1);
    }
    s
}

/// Writes a mesh as OBJ (see [`obj_string`]).
pub fn write_obj(mesh: &TriMesh, header: &[String], path: &Path) -> Result<(), ToolsError> {
    write_file(path, obj_string(mesh, header).as_bytes())
}

fn write_file(path: &Path, bytes: &[u8]) -> Result<(), ToolsError> {
    fs::write(path, bytes).map_err(|source| ToolsError::Io { path: PathBuf::from(path), source })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeMap;

    fn read_tree(root: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
        let mut out = BTreeMap::new();
        let mut stack = vec![root.to_path_buf()];
        while let Some(dir) = stack.pop() {
            for entry in fs::read_dir(&dir).unwrap() {
                let p = entry.unwrap().path();
                if p.is_dir() {
                    stack.push(p);
                } else {
                    out.insert(p.strip_prefix(root).unwrap().to_path_buf(), fs::read(&p).unwrap());
                }
            }
        }
        out
    }

    #[test]
    fn generate_is_byte_reproducible_and_loads_back() {
        let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
        let ma = generate(a.path()).unwrap();
        let mb = generate(b.path()).unwrap();
        assert_eq!(ma, mb);
        let (ta, tb) = (read_tree(a.path()), read_tree(b.path()));
        assert_eq!(ta.len(), 3 * 14 + 1);
        assert_eq!(ta, tb, "same seeds must give the same bytes");

        let loaded = Manifest::load(&a.path().join(MANIFEST_FILE)).unwrap();
        // serde_json (without its float_roundtrip feature) may parse a
        // float 1 ulp off, so compare numbers with a relative tolerance.
        let (ja, jb) = (serde_json::to_value(&loaded).unwrap(), serde_json::to_value(&ma).unwrap());
        assert!(json_close(&ja, &jb), "manifest changed on the way through JSON");
        assert_eq!(loaded.categories.len(), 3);
        for rec in &loaded.instances {
            let obj = String::from_utf8(ta[&PathBuf::from(&rec.path)].clone()).unwrap();
            assert!(obj.starts_with("# graspd procedural tool"));
            assert_eq!(obj.lines().filter(|l| l.starts_with("v ")).count(), rec.vertices);
            assert_eq!(obj.lines().filter(|l| l.starts_with("f ")).count(), rec.triangles);
            assert!(rec.volume > 0.0 && rec.parts >= 2);
            // Parameters read back rebuild the same mesh.
            assert_eq!(rec.params.mesh().unwrap().triangles.len(), rec.triangles);
        }
        let mugs: Vec<_> = loaded.instances_of(Category::Mug).collect();
        assert_eq!(mugs.len(), 14);
        assert_eq!(loaded.instance("hammer_test_01").unwrap().split, Split::Test);
    }

    fn json_close(a: &serde_json::Value, b: &serde_json::Value) -> bool {
        use serde_json::Value as V;
        match (a, b) {
            (V::Number(x), V::Number(y)) => match (x.as_f64(), y.as_f64()) {
                (Some(x), Some(y)) => (x - y).abs() <= 1e-14 * x.abs().max(y.abs()),
                _ => x == y,
            },
            (V::Array(x), V::Array(y)) => x.len() == y.len() && x.iter().zip(y).all(|(x, y)| json_close(x, y)),
            (V::Object(x), V::Object(y)) => {
                x.len() == y.len() && x.iter().all(|(k, v)| y.get(k).is_some_and(|w| json_close(v, w)))
            }
            _ => a == b,
        }
    }

    #[test]
    fn bad_or_missing_manifest_is_a_clear_error() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(MANIFEST_FILE);
        assert!(matches!(Manifest::load(&path), Err(ToolsError::Io { .. })));
        fs::write(&path, "{\"format_version\": 1, \"units\": ").unwrap();
        let err = Manifest::load(&path).unwrap_err();
        assert!(matches!(err, ToolsError::Json { .. }));
        assert!(err.to_string().contains("manifest.json"), "{err}");
    }

    #[test]
    fn obj_numbers_have_fixed_format() {
        let mesh = TriMesh::new(
            vec![[0.0, -1e-9, 1.0].into(), [0.1234567, 0.0, 0.0].into(), [0.0, 1.0, 0.0].into()],
            vec![[0, 1, 2]],
        );
        let s = obj_string(&mesh, &["a\nb".into()]);
        assert!(s.starts_with("# a\n# b\n"));
        assert!(s.contains("\nv 0.000000 0.000000 1.000000\n"));
        assert!(s.contains("\nv 0.123457 0.000000 0.000000\n"));
        assert!(s.ends_with("f 1 2 3\n"));
    }
}
