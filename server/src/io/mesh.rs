//! Meshes: OBJ and STL in (with unit and frame sanity warnings), OBJ and STL out.
//!
//! Object meshes come from scanners and CAD exports in whatever units and
//! frames their authors used; the engine wants metres in the object frame.
//! Reading does not "fix" anything (a wrong guess is worse than none): it
//! loads faithfully and reports what looks wrong in `LoadedMesh::warnings`.

use super::error::Result;
use super::{extension, lines, parse_f64, point, read_file, text, write_all, write_file, Encoding, IoError};
use crate::geometry::TriMesh;
use nalgebra::Point3;
use std::collections::HashMap;
use std::io::Write;
use std::path::Path;

const OBJ: &str = "OBJ";
const STL: &str = "STL";

/// A mesh as read, with what looks wrong about it (units, frame, topology).
#[derive(Clone, Debug)]
pub struct LoadedMesh {
    pub mesh: TriMesh,
    pub warnings: Vec<String>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MeshFormat {
    Obj,
    Stl,
}

impl MeshFormat {
    pub fn from_path(path: &Path) -> Result<Self> {
        match extension(path).as_str() {
            "obj" => Ok(Self::Obj),
            "stl" => Ok(Self::Stl),
            _ => Err(IoError::Extension { path: Some(path.to_path_buf()), expected: ".obj or .stl for meshes" }),
        }
    }
}

/// Reads an OBJ or STL mesh, chosen by the extension.
pub fn read_mesh(path: impl AsRef<Path>) -> Result<LoadedMesh> {
    let path = path.as_ref();
    let format = MeshFormat::from_path(path)?;
    parse_mesh(&read_file(path)?, format).map_err(|e| e.at(path))
}

pub fn parse_mesh(bytes: &[u8], format: MeshFormat) -> Result<LoadedMesh> {
    match format {
        MeshFormat::Obj => parse_obj(bytes),
        MeshFormat::Stl => parse_stl(bytes),
    }
}

/// Adds the sanity warnings; a file without faces is an error (a point
/// cloud in disguise is better caught here than as an empty grasp search).
fn finish(format: &'static str, mesh: TriMesh, mut warnings: Vec<String>) -> Result<LoadedMesh> {
    if mesh.triangles.is_empty() {
        return Err(IoError::bad(format, "no faces (a point cloud? use read_cloud)"));
    }
    if mesh.vertices.len() > u32::MAX as usize {
        return Err(IoError::bad(format, "more than 2^32 vertices"));
    }
    warnings.extend(check_mesh(&mesh));
    Ok(LoadedMesh { mesh, warnings })
}

/// Unit, frame and topology warnings for a mesh in metres.
pub fn check_mesh(mesh: &TriMesh) -> Vec<String> {
    let Some((lo, hi)) = mesh.aabb() else { return vec!["mesh has no vertices".into()] };
    if let Some(i) = mesh.triangles.iter().position(|t| t.iter().any(|&v| v as usize >= mesh.vertices.len())) {
        return vec![format!("triangle {i} refers to a vertex that does not exist")];
    }
    let mut warnings = Vec::new();
    let (ext, largest) = (hi - lo, (hi - lo).max());
    let size = format!("extent {:.4} x {:.4} x {:.4}", ext.x, ext.y, ext.z);
    if largest > 5.0 {
        warnings.push(format!("{size}: over 5 m, looks like millimetres; pass a scale (0.001)"));
    } else if largest < 0.005 {
        warnings.push(format!("{size}: under 5 mm, wrong units? pass a scale"));
    }
    let centroid =
        mesh.vertices.iter().fold(nalgebra::Vector3::zeros(), |s, p| s + p.coords) / mesh.vertices.len() as f64;
    if centroid.norm() > 1.0 {
        warnings.push(format!(
            "centroid ({:.3}, {:.3}, {:.3}) is {:.3} from the origin: not in the object frame",
            centroid.x,
            centroid.y,
            centroid.z,
            centroid.norm()
        ));
    }
    // Relative threshold: a sliver 1e-6 of the object size across is no face.
    let tiny = 1e-12 * (hi - lo).norm_squared();
    let degenerate = (0..mesh.triangles.len())
        .filter(|&i| {
            let [a, b, c] = mesh.triangles[i];
            a == b || b == c || a == c || mesh.triangle_normal_area2(i).norm() <= tiny
        })
        .count();
    if degenerate > 0 {
        warnings.push(format!("{degenerate} degenerate (zero-area) triangles"));
    }
    // Topology once coincident vertices are welded (as trimesh and most tools
    // judge it): scans often stitch a pinch with distinct vertices at one
    // position, closed by index but not as a surface.
    let (welded, duplicates) = weld(mesh);
    if duplicates > 0 {
        warnings.push(format!("{duplicates} vertices share the position of another vertex"));
    }
    let (topo, by_index) = (welded.topology(), mesh.topology());
    if !topo.is_watertight() {
        warnings.push(format!(
            "not watertight{}: {} boundary edges, {} non-manifold edges, {} inconsistently wound edges",
            if by_index.is_watertight() { " once coincident vertices are merged (closed by index)" } else { "" },
            topo.boundary_edges,
            topo.non_manifold_edges,
            topo.inconsistent_edges
        ));
    }
    warnings
}

// ---------------------------------------------------------------- OBJ

/// Wavefront OBJ: `v` and `f` (any of i, i/t, i/t/n, i//n; negative indices
/// count back from the last vertex); polygons are fan-triangulated. Materials,
/// groups, texture coordinates and normals are ignored, so a missing .mtl
/// file does not matter.
pub fn parse_obj(bytes: &[u8]) -> Result<LoadedMesh> {
    let (mut vertices, mut triangles) = (Vec::new(), Vec::new());
    let mut max_ref: Option<(u64, usize)> = None; // highest vertex index used, and its line
    let (mut unknown, mut first_unknown) = (0usize, None);
    let mut poly = Vec::new();
    for (ln, raw) in lines(bytes, 1) {
        let line = text(OBJ, ln, raw)?;
        let mut tok = line.split('#').next().unwrap_or("").split_whitespace();
        match tok.next() {
            None => {}
            Some("v") => {
                let c: Vec<&str> = tok.collect();
                if c.len() < 3 {
                    return Err(IoError::at_line(OBJ, ln, format!("vertex needs 3 coordinates, found {}", c.len())));
                }
                let (x, y, z) = (parse_f64(OBJ, ln, c[0])?, parse_f64(OBJ, ln, c[1])?, parse_f64(OBJ, ln, c[2])?);
                vertices.push(point(OBJ, vertices.len(), Some(ln), x, y, z)?);
            }
            Some("f") => {
                poly.clear();
                for t in tok {
                    let head = t.split('/').next().unwrap_or("");
                    let i: i64 =
                        head.parse().map_err(|_| IoError::at_line(OBJ, ln, format!("bad face vertex '{t}'")))?;
                    // 1-based; negative counts back from the vertices read so far.
                    let idx = match i {
                        0 => return Err(IoError::at_line(OBJ, ln, "vertex index 0 (OBJ indices start at 1)")),
                        i if i > 0 => i as u64 - 1,
                        i => u64::try_from(vertices.len() as i64 + i).map_err(|_| {
                            IoError::at_line(OBJ, ln, format!("relative index {i} reaches before the first vertex"))
                        })?,
                    };
                    if idx >= u32::MAX as u64 {
                        return Err(IoError::at_line(OBJ, ln, format!("vertex index {i} out of range")));
                    }
                    if max_ref.is_none_or(|(m, _)| idx > m) {
                        max_ref = Some((idx, ln));
                    }
                    poly.push(idx as u32);
                }
                if poly.len() < 3 {
                    return Err(IoError::at_line(
                        OBJ,
                        ln,
                        format!("face needs 3 or more vertices, found {}", poly.len()),
                    ));
                }
                triangles.extend((1..poly.len() - 1).map(|k| [poly[0], poly[k], poly[k + 1]]));
            }
            Some("vt" | "vn" | "vp" | "o" | "g" | "s" | "usemtl" | "mtllib" | "l" | "p") => {}
            Some(k) => {
                unknown += 1;
                first_unknown.get_or_insert((k.to_string(), ln));
            }
        }
    }
    // Positive indices may legally point forward, so they are checked at the end.
    if let Some((idx, ln)) = max_ref.filter(|&(m, _)| m >= vertices.len() as u64) {
        let reason = format!("face uses vertex {} but the file has {} vertices", idx + 1, vertices.len());
        return Err(IoError::at_line(OBJ, ln, reason));
    }
    let mut warnings = Vec::new();
    if let Some((k, ln)) = first_unknown {
        warnings.push(format!("ignored {unknown} lines with unsupported keywords (first '{k}' at line {ln})"));
    }
    finish(OBJ, TriMesh::new(vertices, triangles), warnings)
}

/// Writes `v`/`f` lines with fixed `{:.6}` formatting (micrometres; the same
/// mesh always gives the same bytes). Each line of `header_comment` becomes a
/// `#` line.
pub fn write_obj_to(mut w: impl Write, mesh: &TriMesh, header_comment: &str) -> Result<()> {
    check_writable(OBJ, mesh)?;
    let mut out = String::with_capacity(40 * mesh.vertices.len() + 24 * mesh.triangles.len());
    for l in header_comment.lines() {
        out.push_str(&format!("# {l}\n"));
    }
    for v in &mesh.vertices {
        out.push_str(&format!("v {:.6} {:.6} {:.6}\n", v.x, v.y, v.z));
    }
    for t in &mesh.triangles {
        out.push_str(&format!("f {} {} {}\n", t[0] + 1, t[1] + 1, t[2] + 1));
    }
    write_all(&mut w, out.as_bytes())
}

pub fn write_obj(path: impl AsRef<Path>, mesh: &TriMesh, header_comment: &str) -> Result<()> {
    write_file(path.as_ref(), |w| write_obj_to(w, mesh, header_comment))
}

/// Writers refuse meshes their readers would reject.
fn check_writable(format: &'static str, mesh: &TriMesh) -> Result<()> {
    if let Some(i) = mesh.vertices.iter().position(|p| !p.coords.iter().all(|c| c.is_finite())) {
        return Err(IoError::bad(format, format!("cannot write vertex {i}: non-finite {:?}", mesh.vertices[i])));
    }
    let n = mesh.vertices.len();
    if let Some(i) = mesh.triangles.iter().position(|t| t.iter().any(|&v| v as usize >= n)) {
        return Err(IoError::bad(format, format!("cannot write triangle {i}: index out of range ({n} vertices)")));
    }
    Ok(())
}

// ---------------------------------------------------------------- STL

/// Binary or ASCII STL. Vertices are merged by exact value so that the
/// topology (watertightness) can be checked; coordinates are float32, as
/// the format defines them.
pub fn parse_stl(bytes: &[u8]) -> Result<LoadedMesh> {
    let count = bytes.get(80..84).map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as u64);
    let binary_size = count.map(|n| 84 + 50 * n);
    let mut warnings = Vec::new();
    // Many binary STLs start with "solid" too: the size formula decides,
    // unless the file is clean ASCII text that reads as an ASCII STL.
    let soup = if binary_size == Some(bytes.len() as u64) && !looks_ascii(bytes) {
        stl_binary(bytes, &mut warnings)?
    } else if starts_with_solid(bytes) {
        stl_ascii(bytes).map_err(|e| match (looks_ascii(bytes), count, e) {
            (false, Some(n), IoError::Format { reason, .. }) => IoError::bad(
                STL,
                format!(
                    "neither ASCII ({reason}) nor binary (header declares {n} triangles = {} bytes, file has {})",
                    84 + 50 * n,
                    bytes.len()
                ),
            ),
            (.., e) => e,
        })?
    } else {
        stl_binary(bytes, &mut warnings)?
    };
    finish(STL, merge_vertices(&soup)?, warnings)
}

fn starts_with_solid(bytes: &[u8]) -> bool {
    let start = bytes.iter().position(|b| !b.is_ascii_whitespace()).unwrap_or(bytes.len());
    bytes[start..].get(..5).is_some_and(|s| s.eq_ignore_ascii_case(b"solid"))
}

/// "solid", printable ASCII in the first kilobyte, and an STL keyword there.
fn looks_ascii(bytes: &[u8]) -> bool {
    let head = &bytes[..bytes.len().min(1024)];
    let has = |word: &[u8]| head.windows(word.len()).any(|w| w.eq_ignore_ascii_case(word));
    starts_with_solid(bytes)
        && head.iter().all(|&b| matches!(b, b'\t' | b'\n' | b'\r' | 0x20..=0x7e))
        && (has(b"facet") || has(b"endsolid"))
}

type Soup = Vec<[Point3<f64>; 3]>;

fn stl_binary(bytes: &[u8], warnings: &mut Vec<String>) -> Result<Soup> {
    let Some(count) = bytes.get(80..84).map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize) else {
        return Err(IoError::bad(
            STL,
            format!("{} bytes: too short for a binary STL (84-byte header) and not ASCII", bytes.len()),
        ));
    };
    let data = &bytes[84..];
    let need = 50 * count; // count < 2^32, cannot overflow on 64-bit
    if data.len() < need {
        return Err(IoError::bad(
            STL,
            format!(
                "truncated binary STL: expected {count} triangles, found {} ({} bytes)",
                data.len() / 50,
                bytes.len()
            ),
        ));
    }
    if data.len() > need {
        warnings.push(format!("{} bytes after the {count} triangles ignored", data.len() - need));
    }
    (0..count)
        .map(|i| {
            let rec = &data[50 * i + 12..50 * i + 48]; // skip the stored normal
            let c = |k: usize| f32::from_le_bytes([rec[4 * k], rec[4 * k + 1], rec[4 * k + 2], rec[4 * k + 3]]) as f64;
            let v = |j: usize| point(STL, 3 * i + j, None, c(3 * j), c(3 * j + 1), c(3 * j + 2));
            Ok([v(0)?, v(1)?, v(2)?])
        })
        .collect()
}

/// Line-based: `vertex` lines between `facet`/`outer loop` and
/// `endloop`/`endfacet` form a (fan-triangulated) polygon.
fn stl_ascii(bytes: &[u8]) -> Result<Soup> {
    let (mut soup, mut poly) = (Vec::new(), Vec::<Point3<f64>>::new());
    let mut nvert = 0;
    for (ln, raw) in lines(bytes, 1) {
        let line = text(STL, ln, raw)?;
        let mut tok = line.split_whitespace();
        match tok.next().map(str::to_ascii_lowercase).as_deref() {
            None | Some("solid" | "endsolid" | "outer") => {}
            Some("facet") => poly.clear(),
            Some("vertex") => {
                let c: Vec<&str> = tok.collect();
                if c.len() != 3 {
                    return Err(IoError::at_line(STL, ln, format!("vertex needs 3 coordinates, found {}", c.len())));
                }
                // float32 like binary STL, so both encodings read alike.
                let f = |t: &str| parse_f64(STL, ln, t).map(|v| v as f32 as f64);
                poly.push(point(STL, nvert, Some(ln), f(c[0])?, f(c[1])?, f(c[2])?)?);
                nvert += 1;
            }
            Some("endloop" | "endfacet") if !poly.is_empty() => {
                if poly.len() < 3 {
                    return Err(IoError::at_line(STL, ln, format!("facet with {} vertices", poly.len())));
                }
                soup.extend((1..poly.len() - 1).map(|k| [poly[0], poly[k], poly[k + 1]]));
                poly.clear();
            }
            Some("endloop" | "endfacet") => {}
            Some(k) => return Err(IoError::at_line(STL, ln, format!("unexpected '{k}'"))),
        }
    }
    if !poly.is_empty() {
        return Err(IoError::bad(STL, "file ends inside a facet (truncated?)"));
    }
    Ok(soup)
}

/// Exact-position key; -0 and +0 are one.
fn key(p: &Point3<f64>) -> [u64; 3] {
    [(p.x + 0.0).to_bits(), (p.y + 0.0).to_bits(), (p.z + 0.0).to_bits()]
}

/// Shares vertices with bit-identical coordinates.
fn merge_vertices(soup: &[[Point3<f64>; 3]]) -> Result<TriMesh> {
    let mut index: HashMap<[u64; 3], u32> = HashMap::with_capacity(soup.len());
    let mut vertices = Vec::with_capacity(soup.len() / 2 + 3);
    let mut triangles = Vec::with_capacity(soup.len());
    for tri in soup {
        let mut t = [0u32; 3];
        for (k, p) in tri.iter().enumerate() {
            let next = u32::try_from(vertices.len()).map_err(|_| IoError::bad(STL, "more than 2^32 vertices"))?;
            t[k] = *index.entry(key(p)).or_insert_with(|| {
                vertices.push(*p);
                next
            });
        }
        triangles.push(t);
    }
    Ok(TriMesh::new(vertices, triangles))
}

/// The mesh with coincident vertices merged, and how many were merged away.
fn weld(mesh: &TriMesh) -> (TriMesh, usize) {
    let mut index: HashMap<[u64; 3], u32> = HashMap::with_capacity(mesh.vertices.len());
    let remap: Vec<u32> = mesh
        .vertices
        .iter()
        .map(|p| {
            let n = index.len() as u32;
            *index.entry(key(p)).or_insert(n)
        })
        .collect();
    let triangles = mesh.triangles.iter().map(|t| t.map(|v| remap.get(v as usize).copied().unwrap_or(v))).collect();
    (TriMesh::new(Vec::new(), triangles), mesh.vertices.len() - index.len())
}

/// Binary (80-byte header from `header_comment`, never starting with "solid"
/// so readers cannot mistake it for text) or ASCII; float32 either way.
pub fn write_stl_to(mut w: impl Write, mesh: &TriMesh, encoding: Encoding, header_comment: &str) -> Result<()> {
    check_writable(STL, mesh)?;
    let n32 = u32::try_from(mesh.triangles.len()).map_err(|_| IoError::bad(STL, "more than 2^32 triangles"))?;
    let f = |i: usize| {
        let [a, b, c] = mesh.triangle(i);
        let n = mesh.triangle_normal_area2(i).try_normalize(0.0).unwrap_or_else(nalgebra::Vector3::zeros);
        [n, a.coords, b.coords, c.coords].map(|v| [v.x as f32, v.y as f32, v.z as f32])
    };
    let name: String =
        header_comment.lines().next().unwrap_or("").chars().filter(|c| c.is_ascii_graphic() || *c == ' ').collect();
    let mut out = Vec::new();
    match encoding {
        Encoding::Binary => {
            let mut header = format!("graspd STL {name}").into_bytes();
            header.resize(80, b' ');
            out.extend_from_slice(&header);
            out.extend_from_slice(&n32.to_le_bytes());
            for i in 0..mesh.triangles.len() {
                f(i).iter().flatten().for_each(|c| out.extend_from_slice(&c.to_le_bytes()));
                out.extend_from_slice(&[0, 0]);
            }
        }
        Encoding::Ascii => {
            let mut s = format!("solid {name}\n");
            for i in 0..mesh.triangles.len() {
                let [n, a, b, c] = f(i);
                s.push_str(&format!("facet normal {:e} {:e} {:e}\n  outer loop\n", n[0], n[1], n[2]));
                for v in [a, b, c] {
                    s.push_str(&format!("    vertex {:e} {:e} {:e}\n", v[0], v[1], v[2]));
                }
                s.push_str("  endloop\nendfacet\n");
            }
            s.push_str(&format!("endsolid {name}\n"));
            out = s.into_bytes();
        }
    }
    write_all(&mut w, &out)
}

pub fn write_stl(path: impl AsRef<Path>, mesh: &TriMesh, encoding: Encoding, header_comment: &str) -> Result<()> {
    write_file(path.as_ref(), |w| write_stl_to(w, mesh, encoding, header_comment))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    /// Closed cube of side `s` at `at`, outward counter-clockwise triangles.
    fn cube(s: f64, at: Vector3<f64>) -> TriMesh {
        let v =
            (0..8).map(|i| Point3::new((i & 1) as f64, (i >> 1 & 1) as f64, (i >> 2 & 1) as f64) * s + at).collect();
        #[rustfmt::skip]
        let t = vec![
            [0, 2, 3], [0, 3, 1], [4, 5, 7], [4, 7, 6], [0, 1, 5], [0, 5, 4],
            [2, 6, 7], [2, 7, 3], [0, 4, 6], [0, 6, 2], [1, 3, 7], [1, 7, 5],
        ];
        TriMesh::new(v, t)
    }

    fn obj(text: &str) -> Result<LoadedMesh> {
        parse_obj(text.as_bytes())
    }

    fn assert_err(result: Result<LoadedMesh>, needles: &[&str]) {
        let msg = result.expect_err("bad input must be an error").to_string();
        for n in needles {
            assert!(msg.contains(n), "'{msg}' lacks '{n}'");
        }
    }

    fn same_geometry(a: &TriMesh, b: &TriMesh, tol: f64) {
        assert_eq!(a.triangles.len(), b.triangles.len());
        for i in 0..a.triangles.len() {
            for (p, q) in a.triangle(i).iter().zip(b.triangle(i)) {
                assert!((p - q).amax() <= tol, "triangle {i}: {p} vs {q}");
            }
        }
    }

    #[test]
    fn obj_face_forms_negative_indices_and_polygons() {
        let text = "# comment\nmtllib missing.mtl\no thing\ng grp\ns off\nusemtl red\n\
                    v 0 0 0\nv 1 0 0\nv 1 1 0 1.0\nv 0 1 0 0.5 0.5 0.5\nvt 0 0\nvn 0 0 1\n\
                    f 1 2 3\nf 1/1 3/1 4/1\nf 1/1/1 2/1/1 3/1/1 # trailing\nf 1//1 3//1 4//1\nf -4 -3 -2 -1\n";
        let m = obj(text).unwrap().mesh;
        assert_eq!(m.vertices.len(), 4);
        assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3], [0, 1, 2], [0, 2, 3], [0, 1, 2], [0, 2, 3]]);
        let w = obj("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\ncurv 0 1\n").unwrap().warnings;
        assert!(w.iter().any(|w| w.contains("'curv' at line 5")), "{w:?}");
    }

    #[test]
    fn obj_bad_files() {
        let tri = "v 0 0 0\nv 1 0 0\nv 0 1 0\n";
        assert_err(obj(&format!("{tri}f 1 2 0\n")), &["OBJ", "line 4", "index 0"]);
        assert_err(obj(&format!("{tri}f 1 2 3\nf 1 2 9\n")), &["line 5", "vertex 9", "has 3 vertices"]);
        assert_err(obj(&format!("{tri}f 1 -4 2\n")), &["line 4", "before the first vertex"]);
        assert_err(obj(&format!("{tri}f 1 2\n")), &["line 4", "3 or more"]);
        assert_err(obj(&format!("{tri}f 1 a 2\n")), &["line 4", "bad face vertex 'a'"]);
        assert_err(obj("v 0 0\n"), &["line 1", "3 coordinates"]);
        assert_err(obj("v 0 0 0\nv 0 NaN 0\n"), &["line 2", "point 1", "non-finite"]);
        assert_err(obj(tri), &["no faces"]);
        assert_err(obj(""), &["no faces"]);
        assert_err(parse_obj(b"v 0 0 0\n\xc3\x28 1 2\n"), &["line 2", "not text"]);
    }

    #[test]
    fn obj_writer_bytes_are_fixed() {
        let m = TriMesh::new(
            vec![Point3::new(0.1, -2.0, 1.0 / 3.0), Point3::origin(), Point3::new(1e-9, 5.0, 0.0)],
            vec![[0, 1, 2]],
        );
        let mut out = Vec::new();
        write_obj_to(&mut out, &m, "graspd test\nsecond line").unwrap();
        let want = "# graspd test\n# second line\nv 0.100000 -2.000000 0.333333\nv 0.000000 0.000000 0.000000\n\
                    v 0.000000 5.000000 0.000000\nf 1 2 3\n";
        assert_eq!(String::from_utf8(out).unwrap(), want);
        let bad = TriMesh::new(vec![Point3::origin()], vec![[0, 0, 1]]);
        assert!(write_obj_to(Vec::new(), &bad, "").is_err());
    }

    #[test]
    fn obj_and_stl_round_trips() {
        let m = cube(0.1, Vector3::new(-0.05, 0.02, 0.0));
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cube.obj");
        write_obj(&path, &m, "cube").unwrap();
        let back = read_mesh(&path).unwrap();
        assert!(back.warnings.is_empty(), "{:?}", back.warnings);
        same_geometry(&back.mesh, &m, 1e-6);
        for encoding in [Encoding::Binary, Encoding::Ascii] {
            let path = dir.path().join("cube.stl");
            write_stl(&path, &m, encoding, "solid-looking name").unwrap();
            let back = read_mesh(&path).unwrap();
            assert!(back.warnings.is_empty(), "{encoding:?}: {:?}", back.warnings);
            assert_eq!(back.mesh.vertices.len(), 8, "{encoding:?}: duplicates merged");
            assert!(back.mesh.is_watertight());
            same_geometry(&back.mesh, &m, 1e-7);
        }
    }

    fn binary_stl(header: &[u8], m: &TriMesh) -> Vec<u8> {
        let mut b = Vec::new();
        write_stl_to(&mut b, m, Encoding::Binary, "").unwrap();
        b[..header.len()].copy_from_slice(header);
        b
    }

    #[test]
    fn binary_stl_starting_with_solid() {
        let m = cube(0.05, Vector3::zeros());
        let b = binary_stl(b"solid exported by some CAD tool", &m);
        same_geometry(&parse_stl(&b).unwrap().mesh, &m, 1e-7);
        // Trailing bytes after the declared triangles: read, with a warning.
        let mut long = binary_stl(b"model", &m);
        long.extend_from_slice(&[0; 7]);
        assert!(parse_stl(&long).unwrap().warnings[0].contains("7 bytes after"));
    }

    #[test]
    fn stl_bad_files() {
        let m = cube(0.05, Vector3::zeros());
        let b = binary_stl(b"model", &m);
        assert_err(parse_stl(&b[..b.len() - 10]), &["STL", "truncated", "expected 12 triangles, found 11"]);
        let b = binary_stl(b"solid x", &m);
        assert_err(parse_stl(&b[..b.len() - 10]), &["neither ASCII", "12 triangles"]);
        assert_err(parse_stl(b"tiny"), &["too short"]);
        let mut huge = vec![b' '; 80];
        huge.extend_from_slice(&u32::MAX.to_le_bytes());
        assert_err(parse_stl(&huge), &["expected 4294967295 triangles, found 0"]);
        let facet = "facet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\nendloop\nendfacet\n";
        assert_err(
            parse_stl(format!("solid a\n{facet}banana\nendsolid a\n").as_bytes()),
            &["line 9", "unexpected 'banana'"],
        );
        let short = "solid a\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nendloop\nendfacet\n";
        assert_err(parse_stl(short.as_bytes()), &["line 6", "facet with 2 vertices"]);
        assert_err(parse_stl(b"solid a\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\n"), &["inside a facet"]);
        assert_err(parse_stl(b"solid a\nfacet normal 0 0 1\nouter loop\nvertex 0 nan 0\n"), &["line 4", "non-finite"]);
        assert_err(parse_stl(b"solid a\nendsolid a\n"), &["no faces"]);
    }

    #[test]
    fn mutated_and_truncated_files_never_panic() {
        let m = cube(0.05, Vector3::zeros());
        let mut ascii = Vec::new();
        write_stl_to(&mut ascii, &m, Encoding::Ascii, "x").unwrap();
        let mut obj_bytes = Vec::new();
        write_obj_to(&mut obj_bytes, &m, "x").unwrap();
        let obj_bytes = [obj_bytes, b"f -1 -2/1 -3//2 -4/2/1\n".to_vec()].concat();
        let mut seed: u64 = 0x2545_f491_4f6c_dd1d;
        let mut next = || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            seed
        };
        for (f, b) in
            [(MeshFormat::Stl, binary_stl(b"solid", &m)), (MeshFormat::Stl, ascii), (MeshFormat::Obj, obj_bytes)]
        {
            for cut in 0..b.len() {
                let _ = parse_mesh(&b[..cut], f);
            }
            for _ in 0..2000 {
                let mut bad = b.clone();
                for _ in 0..1 + next() % 4 {
                    let i = (next() % bad.len() as u64) as usize;
                    bad[i] = next() as u8;
                }
                let _ = parse_mesh(&bad, f);
            }
        }
    }

    #[test]
    fn warnings_for_units_frame_and_topology() {
        let has = |m: &TriMesh, s: &str| check_mesh(m).iter().any(|w| w.contains(s));
        assert!(check_mesh(&cube(0.1, Vector3::zeros())).is_empty());
        assert!(has(&cube(100.0, Vector3::zeros()), "millimetres"));
        assert!(has(&cube(0.001, Vector3::zeros()), "under 5 mm"));
        assert!(has(&cube(0.1, Vector3::new(2.0, 0.0, 0.0)), "not in the object frame"));
        let mut open = cube(0.1, Vector3::zeros());
        open.triangles.truncate(10);
        assert!(has(&open, "4 boundary edges"));
        let mut flat = cube(0.1, Vector3::zeros());
        flat.triangles.push([0, 1, 1]);
        assert!(has(&flat, "1 degenerate"));
    }

    /// The real scanned YCB meshes (outside the repository): they name a
    /// material file that is absent, and must load anyway.
    #[test]
    fn ycb_meshes_load_with_readme_extents() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/ycb");
        if !root.is_dir() {
            eprintln!("skipping: ../shared absent ({})", root.display());
            return;
        }
        for (name, extent, watertight) in [
            ("025_mug", [0.117, 0.093, 0.081], false),
            ("035_power_drill", [0.184, 0.188, 0.057], false),
            ("048_hammer", [0.182, 0.333, 0.033], true),
        ] {
            let loaded = read_mesh(root.join(name).join("mesh.obj")).unwrap();
            let m = &loaded.mesh;
            eprintln!("{name}: {} triangles, warnings {:?}", m.triangles.len(), loaded.warnings);
            assert!((15_000..=17_000).contains(&m.triangles.len()), "{name}: {} triangles", m.triangles.len());
            let (lo, hi) = m.aabb().unwrap();
            for k in 0..3 {
                assert!((hi[k] - lo[k] - extent[k]).abs() < 0.0015, "{name}: extent {} vs {}", hi - lo, extent[k]);
            }
            assert!(lo.z.abs() < 0.005, "{name} rests on z = 0 (scan noise aside)");
            let leaky = loaded.warnings.iter().any(|w| w.contains("not watertight"));
            assert_eq!(!leaky, watertight, "{name}: {:?}", loaded.warnings);
            assert!(
                !loaded.warnings.iter().any(|w| w.contains("mm") || w.contains("frame")),
                "{name}: {:?}",
                loaded.warnings
            );
        }
    }
}
