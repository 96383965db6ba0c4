//! Minimal point-cloud readers for graspctl (the client does not depend on the
//! engine crate): XYZ/CSV text, NPY (float32/float64, shape (N, 3)), PLY
//! (ascii, binary little/big endian; the x, y, z properties of `vertex`).

use std::path::Path;

#[derive(Debug)]
pub struct CloudError(pub String);

impl std::fmt::Display for CloudError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for CloudError {}

fn err<T>(path: &Path, m: impl std::fmt::Display) -> Result<T, CloudError> {
    Err(CloudError(format!("{}: {m}", path.display())))
}

/// Reads a cloud (metres) by file extension.
pub fn read_cloud(path: &Path) -> Result<Vec<[f32; 3]>, CloudError> {
    let bytes = std::fs::read(path).map_err(|e| CloudError(format!("{}: {e}", path.display())))?;
    let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
    match ext.as_str() {
        "xyz" | "csv" | "txt" => read_xyz(path, &bytes),
        "npy" => read_npy(path, &bytes),
        "ply" => read_ply(path, &bytes),
        _ => err(path, "unknown cloud format (expected .xyz, .csv, .npy or .ply)"),
    }
}

fn read_xyz(path: &Path, bytes: &[u8]) -> Result<Vec<[f32; 3]>, CloudError> {
    let text = std::str::from_utf8(bytes).map_err(|_| CloudError(format!("{}: not UTF-8 text", path.display())))?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let v: Vec<&str> = line.split(|c: char| c == ',' || c.is_whitespace()).filter(|s| !s.is_empty()).collect();
        if v.len() < 3 {
            return err(path, format!("line {}: expected x y z", i + 1));
        }
        let mut p = [0f32; 3];
        for k in 0..3 {
            match v[k].parse::<f32>() {
                Ok(x) => p[k] = x,
                // A header line (x,y,z) is allowed first.
                Err(_) if out.is_empty() && i == 0 => break,
                Err(_) => return err(path, format!("line {}: {:?} is not a number", i + 1, v[k])),
            }
            if k == 2 {
                out.push(p);
            }
        }
    }
    Ok(out)
}

fn read_npy(path: &Path, b: &[u8]) -> Result<Vec<[f32; 3]>, CloudError> {
    if b.len() < 10 || &b[..6] != b"\x93NUMPY" {
        return err(path, "not an NPY file");
    }
    let (hlen, start) = match b[6] {
        1 => (u16::from_le_bytes([b[8], b[9]]) as usize, 10),
        2 | 3 if b.len() >= 12 => (u32::from_le_bytes([b[8], b[9], b[10], b[11]]) as usize, 12),
        v => return err(path, format!("NPY version {v} is not supported")),
    };
    let Some(header) = b.get(start..start + hlen).and_then(|h| std::str::from_utf8(h).ok()) else {
        return err(path, "truncated NPY header");
    };
    let descr = if header.contains("'<f4'") {
        4
    } else if header.contains("'<f8'") {
        8
    } else {
        return err(path, "NPY dtype must be little-endian float32 or float64");
    };
    if header.contains("'fortran_order': True") {
        return err(path, "Fortran-ordered NPY is not supported");
    }
    let shape = header.split("'shape':").nth(1).and_then(|s| s.split(')').next()).unwrap_or("");
    let dims: Vec<usize> =
        shape.trim_start_matches([' ', '(']).split(',').filter_map(|s| s.trim().parse().ok()).collect();
    if dims.len() != 2 || dims[1] != 3 {
        return err(path, format!("NPY shape {dims:?}; expected (N, 3)"));
    }
    let data = &b[start + hlen..];
    if data.len() < dims[0] * 3 * descr {
        return err(path, "truncated NPY data");
    }
    Ok((0..dims[0])
        .map(|i| {
            let mut p = [0f32; 3];
            for (k, slot) in p.iter_mut().enumerate() {
                let o = (i * 3 + k) * descr;
                *slot = if descr == 4 {
                    f32::from_le_bytes(data[o..o + 4].try_into().expect("4 bytes"))
                } else {
                    f64::from_le_bytes(data[o..o + 8].try_into().expect("8 bytes")) as f32
                };
            }
            p
        })
        .collect())
}

fn ply_size(t: &str) -> Option<usize> {
    Some(match t {
        "char" | "uchar" | "int8" | "uint8" => 1,
        "short" | "ushort" | "int16" | "uint16" => 2,
        "int" | "uint" | "int32" | "uint32" | "float" | "float32" => 4,
        "double" | "float64" => 8,
        _ => return None,
    })
}

/// A PLY element: name, count, properties (name, type).
type PlyElement = (String, usize, Vec<(String, String)>);

fn read_ply(path: &Path, b: &[u8]) -> Result<Vec<[f32; 3]>, CloudError> {
    let Some(end) = b.windows(11).position(|w| w == b"end_header\n").map(|p| p + 11) else {
        return err(path, "no PLY end_header");
    };
    let header = String::from_utf8_lossy(&b[..end]);
    let mut lines = header.lines();
    if lines.next() != Some("ply") {
        return err(path, "not a PLY file");
    }
    let mut format = "";
    // Elements in order: (name, count, properties (name, type)).
    let mut elements: Vec<PlyElement> = Vec::new();
    for l in lines {
        let t: Vec<&str> = l.split_whitespace().collect();
        match t.as_slice() {
            ["format", f, ..] => {
                format = if *f == "ascii" {
                    "ascii"
                } else if *f == "binary_little_endian" {
                    "le"
                } else {
                    "be"
                }
            }
            ["element", name, n] => elements.push((
                name.to_string(),
                n.parse().map_err(|_| CloudError(format!("{}: bad element count", path.display())))?,
                Vec::new(),
            )),
            ["property", "list", ..] => match elements.last_mut() {
                Some(e) if e.0 == "vertex" => return err(path, "list properties on vertices are not supported"),
                Some(e) => e.2.push(("list".into(), "list".into())),
                None => {}
            },
            ["property", ty, name] => {
                if let Some(e) = elements.last_mut() {
                    e.2.push((name.to_string(), ty.to_string()));
                }
            }
            _ => {}
        }
    }
    let Some(vi) = elements.iter().position(|e| e.0 == "vertex") else { return err(path, "no vertex element") };
    if elements[..vi].iter().any(|e| e.1 > 0) {
        return err(path, "elements before the vertices are not supported");
    }
    let (_, n, props) = &elements[vi];
    let idx = |name: &str| props.iter().position(|p| p.0 == name);
    let (Some(ix), Some(iy), Some(iz)) = (idx("x"), idx("y"), idx("z")) else {
        return err(path, "vertices without x, y, z");
    };
    let data = &b[end..];
    let mut out = Vec::with_capacity(*n);
    if format == "ascii" {
        let text = String::from_utf8_lossy(data);
        for (i, l) in text.lines().take(*n).enumerate() {
            let v: Vec<f32> = l
                .split_whitespace()
                .map(|s| s.parse::<f32>())
                .collect::<Result<_, _>>()
                .map_err(|_| CloudError(format!("{}: vertex {i}: not numbers", path.display())))?;
            if v.len() < props.len() {
                return err(path, format!("vertex {i}: {} values, {} properties", v.len(), props.len()));
            }
            out.push([v[ix], v[iy], v[iz]]);
        }
    } else {
        let sizes: Vec<usize> = props
            .iter()
            .map(|p| ply_size(&p.1))
            .collect::<Option<_>>()
            .ok_or_else(|| CloudError(format!("{}: unknown property type", path.display())))?;
        let stride: usize = sizes.iter().sum();
        let offs: Vec<usize> = sizes
            .iter()
            .scan(0, |acc, s| {
                let o = *acc;
                *acc += s;
                Some(o)
            })
            .collect();
        if data.len() < n * stride {
            return err(path, "truncated PLY data");
        }
        let read = |rec: &[u8], k: usize| -> f32 {
            let o = offs[k];
            let raw = &rec[o..o + sizes[k]];
            let le = format == "le";
            match (props[k].1.as_str(), le) {
                ("float" | "float32", true) => f32::from_le_bytes(raw.try_into().expect("4")),
                ("float" | "float32", false) => f32::from_be_bytes(raw.try_into().expect("4")),
                ("double" | "float64", true) => f64::from_le_bytes(raw.try_into().expect("8")) as f32,
                ("double" | "float64", false) => f64::from_be_bytes(raw.try_into().expect("8")) as f32,
                _ => f32::NAN,
            }
        };
        for rec in data.chunks_exact(stride).take(*n) {
            out.push([read(rec, ix), read(rec, iy), read(rec, iz)]);
        }
    }
    Ok(out)
}

/// A deterministic synthetic partial view of a mug-sized cylinder (radius
/// 4 cm, height 10 cm, standing on z = 0, seen from +x): `n` points, metres.
/// For benchmarks when no recorded cloud is given.
pub fn synthetic_mug_view(n: usize) -> Vec<[f32; 3]> {
    let mut s: u64 = 0x9E37_79B9_7F4A_7C15;
    let mut rnd = || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 11) as f64 / (1u64 << 53) as f64
    };
    (0..n)
        .map(|_| {
            let a = (rnd() - 0.5) * std::f64::consts::PI * 0.9;
            let z = rnd() * 0.1;
            [(0.04 * a.cos()) as f32, (0.04 * a.sin()) as f32, z as f32]
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_xyz_npy_and_ply() {
        let dir = std::env::temp_dir().join(format!("graspctl-cloud-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let xyz = dir.join("a.xyz");
        std::fs::write(&xyz, "x,y,z\n1,2,3\n4 5 6\n").unwrap();
        assert_eq!(read_cloud(&xyz).unwrap(), vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
        let mut npy = b"\x93NUMPY\x01\x00".to_vec();
        let h = "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }";
        let mut h = h.to_string();
        while !(10 + h.len() + 1).is_multiple_of(64) {
            h.push(' ');
        }
        h.push('\n');
        npy.extend((h.len() as u16).to_le_bytes());
        npy.extend(h.as_bytes());
        for v in [1f32, 2., 3., 4., 5., 6.] {
            npy.extend(v.to_le_bytes());
        }
        let p = dir.join("a.npy");
        std::fs::write(&p, npy).unwrap();
        assert_eq!(read_cloud(&p).unwrap(), vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
        let mut ply = b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nend_header\n".to_vec();
        for v in [1f32, 2., 3.] {
            ply.extend(v.to_le_bytes());
        }
        ply.push(7);
        let p = dir.join("a.ply");
        std::fs::write(&p, ply).unwrap();
        assert_eq!(read_cloud(&p).unwrap(), vec![[1.0, 2.0, 3.0]]);
        std::fs::write(&p, "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n").unwrap();
        assert_eq!(read_cloud(&p).unwrap(), vec![[1.0, 2.0, 3.0]]);
        std::fs::write(&p, "garbage").unwrap();
        assert!(read_cloud(&p).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
