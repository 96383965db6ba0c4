//! Point clouds: PLY, PCD, XYZ (text columns) and NPY, read and written.
//!
//! A cloud is `Vec<Point3<f64>>` in metres; only x, y, z are read (colours,
//! normals, intensities are skipped). Binary writers store f32, which is what
//! every viewer reads and far finer than any depth sensor; XYZ stores f64 text.

use super::error::Result;
use super::{check_count, check_finite, extension, lines, parse_f64, point, read_file, text, write_all, write_file};
use super::{Encoding, IoError};
use nalgebra::Point3;
use std::io::{Read, Write};
use std::path::Path;

type Cloud = Vec<Point3<f64>>;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CloudFormat {
    Ply,
    Pcd,
    /// Text columns x y z [more...]; also `.txt` and `.csv`.
    Xyz,
    Npy,
}

impl CloudFormat {
    const EXPECTED: &'static str = ".ply, .pcd, .xyz/.txt/.csv or .npy for point clouds";

    pub fn from_path(path: &Path) -> Result<Self> {
        match extension(path).as_str() {
            "ply" => Ok(Self::Ply),
            "pcd" => Ok(Self::Pcd),
            "xyz" | "txt" | "csv" => Ok(Self::Xyz),
            "npy" => Ok(Self::Npy),
            _ => Err(IoError::Extension { path: Some(path.to_path_buf()), expected: Self::EXPECTED }),
        }
    }
}

/// Reads a point cloud, the format chosen by the extension.
pub fn read_cloud(path: impl AsRef<Path>) -> Result<Cloud> {
    let path = path.as_ref();
    let format = CloudFormat::from_path(path)?;
    parse_cloud(&read_file(path)?, format).map_err(|e| e.at(path))
}

pub fn read_cloud_from(mut r: impl Read, format: CloudFormat) -> Result<Cloud> {
    let mut bytes = Vec::new();
    r.read_to_end(&mut bytes)?;
    parse_cloud(&bytes, format)
}

pub fn parse_cloud(bytes: &[u8], format: CloudFormat) -> Result<Cloud> {
    match format {
        CloudFormat::Ply => parse_ply(bytes),
        CloudFormat::Pcd => parse_pcd(bytes),
        CloudFormat::Xyz => parse_xyz(bytes),
        CloudFormat::Npy => parse_npy(bytes),
    }
}

/// Writes binary PLY/PCD (XYZ is always text, NPY always binary).
pub fn write_cloud(path: impl AsRef<Path>, points: &[Point3<f64>]) -> Result<()> {
    write_cloud_with(path, points, Encoding::Binary)
}

pub fn write_cloud_with(path: impl AsRef<Path>, points: &[Point3<f64>], encoding: Encoding) -> Result<()> {
    let path = path.as_ref();
    let format = CloudFormat::from_path(path)?;
    if extension(path) == "csv" {
        return write_file(path, |w| write_columns(w, points, ","));
    }
    write_file(path, |w| write_cloud_to(w, points, format, encoding))
}

pub fn write_cloud_to(w: impl Write, points: &[Point3<f64>], format: CloudFormat, encoding: Encoding) -> Result<()> {
    match format {
        CloudFormat::Ply => write_ply(w, points, encoding),
        CloudFormat::Pcd => write_pcd(w, points, encoding),
        CloudFormat::Xyz => write_xyz(w, points),
        CloudFormat::Npy => write_npy(w, points),
    }
}

// ---------------------------------------------------------------- scalars

/// Binary scalar types of PLY and PCD.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    I64,
    U64,
    F32,
    F64,
}

impl Scalar {
    fn ply(name: &str) -> Option<Self> {
        use Scalar::*;
        Some(match name {
            "char" | "int8" => I8,
            "uchar" | "uint8" => U8,
            "short" | "int16" => I16,
            "ushort" | "uint16" => U16,
            "int" | "int32" => I32,
            "uint" | "uint32" => U32,
            "float" | "float32" => F32,
            "double" | "float64" => F64,
            _ => return None,
        })
    }

    fn pcd(ty: &str, size: &str) -> Option<Self> {
        use Scalar::*;
        Some(match (ty, size) {
            ("I", "1") => I8,
            ("U", "1") => U8,
            ("I", "2") => I16,
            ("U", "2") => U16,
            ("I", "4") => I32,
            ("U", "4") => U32,
            ("I", "8") => I64,
            ("U", "8") => U64,
            ("F", "4") => F32,
            ("F", "8") => F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        use Scalar::*;
        match self {
            I8 | U8 => 1,
            I16 | U16 => 2,
            I32 | U32 | F32 => 4,
            I64 | U64 | F64 => 8,
        }
    }

    fn is_int(self) -> bool {
        !matches!(self, Scalar::F32 | Scalar::F64)
    }

    /// Decodes the first `size()` bytes; None when `b` is shorter.
    fn read(self, b: &[u8], big: bool) -> Option<f64> {
        macro_rules! rd {
            ($t:ty) => {{
                let a = b.get(..std::mem::size_of::<$t>())?.try_into().ok()?;
                if big {
                    <$t>::from_be_bytes(a) as f64
                } else {
                    <$t>::from_le_bytes(a) as f64
                }
            }};
        }
        use Scalar::*;
        Some(match self {
            I8 => rd!(i8),
            U8 => rd!(u8),
            I16 => rd!(i16),
            U16 => rd!(u16),
            I32 => rd!(i32),
            U32 => rd!(u32),
            I64 => rd!(i64),
            U64 => rd!(u64),
            F32 => rd!(f32),
            F64 => rd!(f64),
        })
    }

    /// Reads one value and advances `data`.
    fn take(self, data: &mut &[u8], big: bool) -> Option<f64> {
        let v = self.read(data, big)?;
        *data = &data[self.size()..];
        Some(v)
    }
}

/// One header line at a time, with its number, for the text headers of PLY
/// and PCD; returns the line and the offset just past it.
fn header_line(bytes: &[u8], pos: usize) -> Option<(&[u8], usize)> {
    let rest = bytes.get(pos..)?;
    let nl = rest.iter().position(|&b| b == b'\n')?;
    let line = &rest[..nl];
    Some((line.strip_suffix(b"\r").unwrap_or(line), pos + nl + 1))
}

/// Text records are checked as they are read (so a short file reports
/// "expected N, found M"); the header count only sizes the allocation up to
/// what the data could hold: each value takes a character and a separator.
fn text_capacity(count: u64, values: usize, available: usize) -> usize {
    count.min(available as u64 / (2 * values as u64).max(1)) as usize
}

// ---------------------------------------------------------------- PLY

const PLY: &str = "PLY";

#[derive(Debug)]
enum PlyProp {
    Scalar(Scalar),
    /// (count type, item type)
    List(Scalar, Scalar),
}

#[derive(Debug)]
struct PlyElement {
    name: String,
    count: u64,
    props: Vec<(String, PlyProp)>,
}

impl PlyElement {
    /// Bytes a binary record takes at least (lists may be empty).
    fn min_record(&self) -> u64 {
        self.props
            .iter()
            .map(|(_, p)| match p {
                PlyProp::Scalar(s) | PlyProp::List(s, _) => s.size() as u64,
            })
            .sum()
    }
}

enum PlyBody {
    Ascii,
    Binary { big: bool },
}

struct PlyHeader {
    body: PlyBody,
    elements: Vec<PlyElement>,
    /// Byte offset and line number where the data begin.
    offset: usize,
    line: usize,
}

fn ply_header(bytes: &[u8]) -> Result<PlyHeader> {
    let mut body = None;
    let mut elements: Vec<PlyElement> = Vec::new();
    let (mut pos, mut n) = (0, 0);
    loop {
        n += 1;
        let Some((raw, next)) = header_line(bytes, pos) else {
            let why = if n == 1 { "empty file or no 'ply' line" } else { "header has no 'end_header' line" };
            return Err(IoError::bad(PLY, why));
        };
        pos = next;
        let line = text(PLY, n, raw)?;
        let tok: Vec<&str> = line.split_whitespace().collect();
        if n == 1 {
            if tok != ["ply"] {
                return Err(IoError::bad(PLY, "not a PLY file: the first line is not 'ply'"));
            }
            continue;
        }
        match tok.as_slice() {
            [] | ["comment", ..] | ["obj_info", ..] => {}
            ["format", f, ..] => {
                body = Some(match *f {
                    "ascii" => PlyBody::Ascii,
                    "binary_little_endian" => PlyBody::Binary { big: false },
                    "binary_big_endian" => PlyBody::Binary { big: true },
                    _ => return Err(IoError::at_line(PLY, n, format!("unknown format '{f}'"))),
                })
            }
            ["element", name, count] => {
                let count = count
                    .parse()
                    .map_err(|_| IoError::at_line(PLY, n, format!("element count '{count}' is not a count")))?;
                elements.push(PlyElement { name: name.to_string(), count, props: Vec::new() });
            }
            ["property", rest @ ..] => {
                let prop = match rest {
                    ["list", c, i, name] => match (Scalar::ply(c), Scalar::ply(i)) {
                        (Some(c), Some(i)) if c.is_int() => (name, PlyProp::List(c, i)),
                        _ => return Err(IoError::at_line(PLY, n, format!("bad list types '{c} {i}'"))),
                    },
                    [ty, name] => match Scalar::ply(ty) {
                        Some(s) => (name, PlyProp::Scalar(s)),
                        None => return Err(IoError::at_line(PLY, n, format!("unknown property type '{ty}'"))),
                    },
                    _ => return Err(IoError::at_line(PLY, n, format!("malformed property line '{line}'"))),
                };
                let Some(e) = elements.last_mut() else {
                    return Err(IoError::at_line(PLY, n, "property before any element"));
                };
                e.props.push((prop.0.to_string(), prop.1));
            }
            ["end_header"] => break,
            _ => return Err(IoError::at_line(PLY, n, format!("unknown header line '{line}'"))),
        }
    }
    let body = body.ok_or_else(|| IoError::bad(PLY, "header has no 'format' line"))?;
    Ok(PlyHeader { body, elements, offset: pos, line: n + 1 })
}

pub fn parse_ply(bytes: &[u8]) -> Result<Cloud> {
    let h = ply_header(bytes)?;
    let vi = h
        .elements
        .iter()
        .position(|e| e.name == "vertex")
        .ok_or_else(|| IoError::bad(PLY, "no 'vertex' element in the header"))?;
    let vertex = &h.elements[vi];
    let mut want = [0; 3];
    for (k, axis) in ["x", "y", "z"].iter().enumerate() {
        want[k] = vertex
            .props
            .iter()
            .position(|(name, p)| name == axis && matches!(p, PlyProp::Scalar(_)))
            .ok_or_else(|| IoError::bad(PLY, format!("vertex element has no scalar property '{axis}'")))?;
    }
    let data = &bytes[h.offset..];
    match h.body {
        PlyBody::Binary { big } => {
            // Elements before the vertices (rare, but legal) are skipped
            // record by record; elements after them (faces) are never read.
            let mut data = data;
            for e in &h.elements[..vi] {
                data = ply_binary(e, data, big, None)?.1;
            }
            Ok(ply_binary(vertex, data, big, Some(want))?.0)
        }
        PlyBody::Ascii => ply_ascii(&h, vi, want, data),
    }
}

/// Walks the binary records of `e`; collects points when `want` names the
/// x, y, z property indices. Returns them and the bytes after the element.
fn ply_binary<'a>(
    e: &PlyElement,
    mut data: &'a [u8],
    big: bool,
    want: Option<[usize; 3]>,
) -> Result<(Cloud, &'a [u8])> {
    let min = e.min_record();
    let what = format!("'{}' records", e.name);
    let n = check_count(PLY, &what, e.count, min, data.len())?;
    if min == 0 {
        return Ok((Vec::new(), data)); // records without properties take no bytes
    }
    let truncated = |i: usize| IoError::bad(PLY, format!("truncated data: expected {n} {what}, found only {i}"));
    let mut out = Vec::with_capacity(if want.is_some() { n } else { 0 });
    for i in 0..n {
        let mut xyz = [0.0; 3];
        for (j, (_, p)) in e.props.iter().enumerate() {
            match p {
                PlyProp::Scalar(s) => {
                    let v = s.take(&mut data, big).ok_or_else(|| truncated(i))?;
                    if let Some(k) = want.and_then(|w| w.iter().position(|&w| w == j)) {
                        xyz[k] = v;
                    }
                }
                PlyProp::List(c, item) => {
                    let len = c.take(&mut data, big).ok_or_else(|| truncated(i))?;
                    if len < 0.0 {
                        return Err(IoError::bad(
                            PLY,
                            format!("record {i} of '{}' has a negative list length", e.name),
                        ));
                    }
                    let bytes = (len as usize).checked_mul(item.size()).filter(|&b| b <= data.len());
                    data = &data[bytes.ok_or_else(|| truncated(i))?..];
                }
            }
        }
        if want.is_some() {
            out.push(point(PLY, i, None, xyz[0], xyz[1], xyz[2])?);
        }
    }
    Ok((out, data))
}

/// ASCII body: one record per line (blank lines tolerated).
fn ply_ascii(h: &PlyHeader, vi: usize, want: [usize; 3], data: &[u8]) -> Result<Cloud> {
    let mut recs = lines(data, h.line).filter(|(_, l)| !l.iter().all(u8::is_ascii_whitespace));
    for e in &h.elements[..vi] {
        for i in 0..e.count {
            if recs.next().is_none() {
                return Err(IoError::bad(
                    PLY,
                    format!("truncated data: expected {} '{}' lines, found {i}", e.count, e.name),
                ));
            }
        }
    }
    let vertex = &h.elements[vi];
    let n = vertex.count;
    let mut out = Vec::with_capacity(text_capacity(n, vertex.props.len(), data.len()));
    for i in 0..n as usize {
        let Some((ln, raw)) = recs.next() else {
            return Err(IoError::bad(PLY, format!("truncated data: expected {n} vertices, found {i}")));
        };
        let tok: Vec<&str> = text(PLY, ln, raw)?.split_whitespace().collect();
        let (mut t, mut xyz) = (0, [0.0; 3]);
        let short = || IoError::at_line(PLY, ln, format!("vertex {i}: too few values ({} on the line)", tok.len()));
        for (j, (_, p)) in vertex.props.iter().enumerate() {
            let skip = match p {
                PlyProp::Scalar(_) => 1,
                PlyProp::List(..) => {
                    let c = tok.get(t).ok_or_else(short)?;
                    1 + c.parse::<usize>().map_err(|_| IoError::at_line(PLY, ln, format!("bad list length '{c}'")))?
                }
            };
            if let Some(k) = want.iter().position(|&w| w == j) {
                xyz[k] = parse_f64(PLY, ln, tok.get(t).ok_or_else(short)?)?;
            }
            t = t.saturating_add(skip);
        }
        if t != tok.len() {
            let reason = format!("vertex {i}: expected {t} values, found {}", tok.len());
            return Err(IoError::at_line(PLY, ln, reason));
        }
        out.push(point(PLY, i, Some(ln), xyz[0], xyz[1], xyz[2])?);
    }
    Ok(out)
}

/// Binary little endian float32, or ASCII double (text costs the same either way).
pub fn write_ply(mut w: impl Write, points: &[Point3<f64>], encoding: Encoding) -> Result<()> {
    check_finite(PLY, points)?;
    let (format, ty) = match encoding {
        Encoding::Binary => ("binary_little_endian", "float"),
        Encoding::Ascii => ("ascii", "double"),
    };
    let mut out = format!(
        "ply\nformat {format} 1.0\ncomment graspd point cloud, metres\nelement vertex {}\n\
         property {ty} x\nproperty {ty} y\nproperty {ty} z\nend_header\n",
        points.len()
    )
    .into_bytes();
    for p in points {
        match encoding {
            Encoding::Binary => p.iter().for_each(|&c| out.extend_from_slice(&(c as f32).to_le_bytes())),
            Encoding::Ascii => out.extend_from_slice(format!("{} {} {}\n", p.x, p.y, p.z).as_bytes()),
        }
    }
    write_all(&mut w, &out)
}

// ---------------------------------------------------------------- PCD

const PCD: &str = "PCD";

struct PcdField {
    name: String,
    ty: Scalar,
    count: usize,
}

pub fn parse_pcd(bytes: &[u8]) -> Result<Cloud> {
    // Header: KEY values... lines up to and including DATA.
    let mut keys: Vec<(&str, Vec<&str>, usize)> = Vec::new();
    let (mut pos, mut n) = (0, 0);
    let data_kind = loop {
        n += 1;
        let Some((raw, next)) = header_line(bytes, pos) else {
            return Err(IoError::bad(PCD, "header has no 'DATA' line (not a PCD file?)"));
        };
        pos = next;
        let line = text(PCD, n, raw)?;
        let mut tok = line.split_whitespace();
        match tok.next() {
            None => {}
            Some(c) if c.starts_with('#') => {}
            Some(k) if k.eq_ignore_ascii_case("DATA") => break tok.next().unwrap_or("").to_ascii_lowercase(),
            Some(k) => keys.push((k, tok.collect(), n)),
        }
    };
    let get = |key: &str| keys.iter().find(|(k, ..)| k.eq_ignore_ascii_case(key));
    let count_of = |key: &str| -> Result<Option<u64>> {
        match get(key) {
            None => Ok(None),
            Some((_, v, ln)) => match v.as_slice() {
                [c] => {
                    c.parse().map(Some).map_err(|_| IoError::at_line(PCD, *ln, format!("{key} '{c}' is not a count")))
                }
                _ => Err(IoError::at_line(PCD, *ln, format!("{key} takes one value"))),
            },
        }
    };
    let names =
        get("FIELDS").or_else(|| get("COLUMNS")).ok_or_else(|| IoError::bad(PCD, "header has no FIELDS line"))?;
    let list = |key: &str, default: Option<&'static str>| -> Result<Vec<&str>> {
        match (get(key), default) {
            (Some((_, v, ln)), _) if v.len() != names.1.len() => Err(IoError::at_line(
                PCD,
                *ln,
                format!("{key} has {} entries but FIELDS has {}", v.len(), names.1.len()),
            )),
            (Some((_, v, _)), _) => Ok(v.clone()),
            (None, Some(d)) => Ok(vec![d; names.1.len()]),
            (None, None) => Err(IoError::bad(PCD, format!("header has no {key} line"))),
        }
    };
    let (sizes, types, counts) = (list("SIZE", None)?, list("TYPE", None)?, list("COUNT", Some("1"))?);
    let mut fields = Vec::with_capacity(names.1.len());
    for (k, name) in names.1.iter().enumerate() {
        let ty = Scalar::pcd(&types[k].to_ascii_uppercase(), sizes[k]).ok_or_else(|| {
            IoError::bad(PCD, format!("field '{name}': unsupported TYPE {} SIZE {}", types[k], sizes[k]))
        })?;
        let count = counts[k]
            .parse()
            .ok()
            .filter(|c| (1..=1 << 20).contains(c))
            .ok_or_else(|| IoError::bad(PCD, format!("field '{name}': bad COUNT '{}'", counts[k])))?;
        fields.push(PcdField { name: name.to_string(), ty, count });
    }
    let wh = match (count_of("WIDTH")?, count_of("HEIGHT")?) {
        (Some(w), h) => w.checked_mul(h.unwrap_or(1)),
        (None, _) => None,
    };
    let points = match (count_of("POINTS")?, wh) {
        (Some(p), Some(wh)) if p != wh => {
            return Err(IoError::bad(PCD, format!("POINTS {p} disagrees with WIDTH x HEIGHT = {wh}")));
        }
        (Some(p), _) | (None, Some(p)) => p,
        (None, None) => return Err(IoError::bad(PCD, "header has neither POINTS nor WIDTH")),
    };
    let mut want = [0; 3];
    for (k, axis) in ["x", "y", "z"].iter().enumerate() {
        want[k] = fields
            .iter()
            .position(|f| f.name == *axis)
            .ok_or_else(|| IoError::bad(PCD, format!("no '{axis}' field (FIELDS: {})", names.1.join(" "))))?;
    }
    let data = &bytes[pos..];
    match data_kind.as_str() {
        "ascii" => pcd_ascii(&fields, want, points, data, n + 1),
        "binary" => pcd_binary(&fields, want, points, data),
        "binary_compressed" => pcd_compressed(&fields, want, points, data),
        other => Err(IoError::at_line(PCD, n, format!("unknown DATA kind '{other}'"))),
    }
}

fn pcd_ascii(fields: &[PcdField], want: [usize; 3], points: u64, data: &[u8], first: usize) -> Result<Cloud> {
    let per_line: usize = fields.iter().map(|f| f.count).sum();
    let col = |k: usize| fields[..want[k]].iter().map(|f| f.count).sum::<usize>();
    let cols = [col(0), col(1), col(2)];
    let n = points as usize;
    let mut out = Vec::with_capacity(text_capacity(points, per_line, data.len()));
    for (ln, raw) in lines(data, first) {
        let tok: Vec<&str> = text(PCD, ln, raw)?.split_whitespace().collect();
        if tok.is_empty() {
            continue;
        }
        if out.len() == n {
            return Err(IoError::at_line(PCD, ln, format!("more data lines than the {n} POINTS of the header")));
        }
        if tok.len() != per_line {
            return Err(IoError::at_line(PCD, ln, format!("expected {per_line} values, found {}", tok.len())));
        }
        let v = |k: usize| parse_f64(PCD, ln, tok[cols[k]]);
        out.push(point(PCD, out.len(), Some(ln), v(0)?, v(1)?, v(2)?)?);
    }
    if out.len() < n {
        return Err(IoError::bad(PCD, format!("truncated data: expected {n} points, found {}", out.len())));
    }
    Ok(out)
}

/// Byte offsets of x, y, z in a record, and the record size.
fn pcd_layout(fields: &[PcdField], want: [usize; 3]) -> ([usize; 3], usize) {
    let off = |k: usize| fields[..k].iter().map(|f| f.ty.size() * f.count).sum::<usize>();
    ([off(want[0]), off(want[1]), off(want[2])], off(fields.len()))
}

fn pcd_binary(fields: &[PcdField], want: [usize; 3], points: u64, data: &[u8]) -> Result<Cloud> {
    let (off, rec) = pcd_layout(fields, want);
    let n = check_count(PCD, "points", points, rec as u64, data.len())?;
    (0..n)
        .map(|i| {
            let v = |k: usize| fields[want[k]].ty.read(&data[i * rec + off[k]..], false).unwrap_or(f64::NAN);
            point(PCD, i, None, v(0), v(1), v(2))
        })
        .collect()
}

/// binary_compressed: u32 compressed size, u32 raw size, LZF data whose raw
/// form stores each field for all points in turn (structure of arrays).
fn pcd_compressed(fields: &[PcdField], want: [usize; 3], points: u64, data: &[u8]) -> Result<Cloud> {
    let word = |i: usize| data.get(i..i + 4).map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize);
    let (Some(packed), Some(raw)) = (word(0), word(4)) else {
        return Err(IoError::bad(PCD, "binary_compressed data shorter than its 8-byte size header"));
    };
    let input = data.get(8..8 + packed).ok_or_else(|| {
        IoError::bad(PCD, format!("truncated data: {packed} compressed bytes declared, {} present", data.len() - 8))
    })?;
    let (off, rec) = pcd_layout(fields, want);
    let n = check_count(PCD, "points", points, rec as u64, raw)?;
    if n * rec != raw {
        return Err(IoError::bad(PCD, format!("uncompressed size {raw} is not {n} points x {rec} bytes")));
    }
    // LZF expands at most ~88x (a 3-byte back reference yields 264 bytes):
    // a larger claim is a corrupt header, refused before allocating.
    if raw > packed.saturating_mul(90) + 64 {
        return Err(IoError::bad(PCD, format!("uncompressed size {raw} impossible for {packed} compressed bytes")));
    }
    let soa = lzf_decompress(input, raw).ok_or_else(|| IoError::bad(PCD, "corrupt LZF data in binary_compressed"))?;
    (0..n)
        .map(|i| {
            let v = |k: usize| {
                let f = &fields[want[k]];
                f.ty.read(&soa[off[k] * n + i * f.ty.size() * f.count..], false).unwrap_or(f64::NAN)
            };
            point(PCD, i, None, v(0), v(1), v(2))
        })
        .collect()
}

/// LZF (liblzf) decompression: control byte < 32 is a literal run of ctrl+1
/// bytes; otherwise a back reference of length (ctrl >> 5) + 2 (7 means an
/// extra length byte follows) at distance ((ctrl & 31) << 8 | next) + 1.
fn lzf_decompress(input: &[u8], raw: usize) -> Option<Vec<u8>> {
    let mut out = Vec::with_capacity(raw);
    let mut i = 0;
    while i < input.len() {
        let ctrl = input[i] as usize;
        i += 1;
        if ctrl < 32 {
            let lit = input.get(i..i + ctrl + 1)?;
            if out.len() + lit.len() > raw {
                return None;
            }
            out.extend_from_slice(lit);
            i += ctrl + 1;
        } else {
            let mut len = ctrl >> 5;
            if len == 7 {
                len += *input.get(i)? as usize;
                i += 1;
            }
            len += 2;
            let back = ((ctrl & 31) << 8 | *input.get(i)? as usize) + 1;
            i += 1;
            if back > out.len() || out.len() + len > raw {
                return None;
            }
            let start = out.len() - back;
            for k in 0..len {
                out.push(out[start + k]); // may overlap what it is writing
            }
        }
    }
    (out.len() == raw).then_some(out)
}

/// PCL's layout: float32 x y z, unorganised (HEIGHT 1).
pub fn write_pcd(mut w: impl Write, points: &[Point3<f64>], encoding: Encoding) -> Result<()> {
    check_finite(PCD, points)?;
    let n = points.len();
    let kind = if encoding == Encoding::Ascii { "ascii" } else { "binary" };
    let mut out = format!(
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\n\
         COUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {kind}\n"
    )
    .into_bytes();
    for p in points {
        let [x, y, z] = [p.x as f32, p.y as f32, p.z as f32];
        match encoding {
            Encoding::Binary => [x, y, z].iter().for_each(|c| out.extend_from_slice(&c.to_le_bytes())),
            Encoding::Ascii => out.extend_from_slice(format!("{x} {y} {z}\n").as_bytes()),
        }
    }
    write_all(&mut w, &out)
}

// ---------------------------------------------------------------- XYZ

const XYZ: &str = "XYZ";

/// Columns separated by whitespace and/or commas; the first three are x y z,
/// more are ignored; '#' starts a comment; blank lines are skipped.
pub fn parse_xyz(bytes: &[u8]) -> Result<Cloud> {
    let mut out = Vec::new();
    for (ln, raw) in lines(bytes, 1) {
        let line = text(XYZ, ln, raw)?;
        let line = line.split('#').next().unwrap_or("");
        let tok: Vec<&str> = line.split(|c: char| c == ',' || c.is_whitespace()).filter(|t| !t.is_empty()).collect();
        match tok.as_slice() {
            [] => continue,
            [x, y, z, ..] => {
                let v = |t: &str| {
                    parse_f64(XYZ, ln, t).map_err(|e| match tok.iter().all(|t| t.parse::<f64>().is_err()) {
                        true => {
                            IoError::at_line(XYZ, ln, "column names? XYZ files have no header row; prefix it with '#'")
                        }
                        false => e,
                    })
                };
                out.push(point(XYZ, out.len(), Some(ln), v(x)?, v(y)?, v(z)?)?);
            }
            _ => {
                return Err(IoError::at_line(
                    XYZ,
                    ln,
                    format!("expected at least 3 columns (x y z), found {}", tok.len()),
                ))
            }
        }
    }
    Ok(out)
}

/// "x y z" per line, shortest text that reads back the same f64.
pub fn write_xyz(w: impl Write, points: &[Point3<f64>]) -> Result<()> {
    write_columns(w, points, " ")
}

fn write_columns(mut w: impl Write, points: &[Point3<f64>], sep: &str) -> Result<()> {
    check_finite(XYZ, points)?;
    let mut out = String::with_capacity(points.len() * 32);
    for p in points {
        out.push_str(&format!("{}{sep}{}{sep}{}\n", p.x, p.y, p.z));
    }
    write_all(&mut w, out.as_bytes())
}

// ---------------------------------------------------------------- NPY

const NPY: &str = "NPY";
const NPY_MAGIC: &[u8] = b"\x93NUMPY";

/// NumPy `.npy` of shape (N, 3), dtype <f4, <f8, >f4 or >f8, either order.
pub fn parse_npy(bytes: &[u8]) -> Result<Cloud> {
    if !bytes.starts_with(NPY_MAGIC) || bytes.len() < 10 {
        return Err(IoError::bad(NPY, "not a .npy file (missing \\x93NUMPY magic)"));
    }
    let (len, start): (usize, usize) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 => match bytes.get(8..12) {
            Some(b) => (u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize, 12),
            None => return Err(IoError::bad(NPY, "truncated header")),
        },
        v => return Err(IoError::bad(NPY, format!("unsupported format version {v}"))),
    };
    let header = bytes
        .get(start..start.saturating_add(len))
        .and_then(|h| std::str::from_utf8(h).ok())
        .ok_or_else(|| IoError::bad(NPY, "truncated or non-text header"))?;
    let descr = npy_value(header, "descr")
        .and_then(|v| v.strip_prefix(['\'', '"']))
        .and_then(|v| v.split(['\'', '"']).next())
        .ok_or_else(|| IoError::bad(NPY, format!("header has no 'descr': {header}")))?;
    let (big, wide) = match descr {
        "<f4" => (false, false),
        "<f8" => (false, true),
        ">f4" => (true, false),
        ">f8" => (true, true),
        d => return Err(IoError::bad(NPY, format!("unsupported dtype '{d}' (expected <f4, <f8, >f4 or >f8)"))),
    };
    let fortran = match npy_value(header, "fortran_order") {
        Some(v) if v.starts_with("True") => true,
        Some(v) if v.starts_with("False") => false,
        _ => return Err(IoError::bad(NPY, format!("header has no fortran_order: {header}"))),
    };
    let shape: Option<Vec<u64>> = npy_value(header, "shape")
        .and_then(|v| v.strip_prefix('('))
        .and_then(|v| v.split(')').next())
        .and_then(|v| v.split(',').map(str::trim).filter(|s| !s.is_empty()).map(|s| s.parse().ok()).collect());
    let n = match shape.as_deref() {
        Some([n, 3]) => *n,
        Some(s) => return Err(IoError::bad(NPY, format!("shape {s:?} is not (N, 3)"))),
        None => return Err(IoError::bad(NPY, format!("header has no readable shape: {header}"))),
    };
    let ty = if wide { Scalar::F64 } else { Scalar::F32 };
    let data = &bytes[(start + len).min(bytes.len())..];
    let n = check_count(NPY, "points", n, 3 * ty.size() as u64, data.len())?;
    if data.len() != 3 * n * ty.size() {
        let extra = data.len() - 3 * n * ty.size();
        return Err(IoError::bad(NPY, format!("{extra} bytes after the {n} points of shape ({n}, 3)")));
    }
    // C order: x y z per row; Fortran order: all x, then all y, then all z.
    let at = |i: usize, k: usize| if fortran { k * n + i } else { 3 * i + k };
    (0..n)
        .map(|i| {
            let v = |k| ty.read(&data[at(i, k) * ty.size()..], big).unwrap_or(f64::NAN);
            point(NPY, i, None, v(0), v(1), v(2))
        })
        .collect()
}

/// The text after `'key':` in a NumPy header dict.
fn npy_value<'a>(header: &'a str, key: &str) -> Option<&'a str> {
    let i = header.find(&format!("'{key}'")).or_else(|| header.find(&format!("\"{key}\"")))?;
    let rest = header[i + key.len() + 2..].trim_start().strip_prefix(':')?;
    Some(rest.trim_start())
}

/// Version 1.0, dtype <f4, shape (N, 3), header padded to 64 bytes.
pub fn write_npy(mut w: impl Write, points: &[Point3<f64>]) -> Result<()> {
    check_finite(NPY, points)?;
    let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': ({}, 3), }}", points.len());
    let total = 10 + header.len() + 1;
    header.push_str(&" ".repeat((64 - total % 64) % 64));
    header.push('\n');
    let mut out = Vec::with_capacity(10 + header.len() + 12 * points.len());
    out.extend_from_slice(NPY_MAGIC);
    out.extend_from_slice(&[1, 0]);
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    for p in points {
        p.iter().for_each(|&c| out.extend_from_slice(&(c as f32).to_le_bytes()));
    }
    write_all(&mut w, &out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Cloud {
        vec![
            Point3::new(0.0, 0.0, 0.0),
            Point3::new(0.123456789, -0.5, 1.25e-4),
            Point3::new(-1.5, 2.75, -0.0311),
            Point3::new(1e-7, 123.456, -7.0),
        ]
    }

    fn close(a: &[Point3<f64>], b: &[Point3<f64>], tol: f64) {
        assert_eq!(a.len(), b.len());
        for (p, q) in a.iter().zip(b) {
            assert!((p - q).amax() <= tol * (1.0 + p.coords.amax()), "{p} vs {q}");
        }
    }

    fn encode(points: &[Point3<f64>], format: CloudFormat, encoding: Encoding) -> Vec<u8> {
        let mut out = Vec::new();
        write_cloud_to(&mut out, points, format, encoding).unwrap();
        out
    }

    fn err(result: Result<Cloud>) -> String {
        result.expect_err("bad input must be an error").to_string()
    }

    fn assert_err(result: Result<Cloud>, needles: &[&str]) {
        let msg = err(result);
        for n in needles {
            assert!(msg.contains(n), "'{msg}' lacks '{n}'");
        }
    }

    #[test]
    fn round_trip_in_memory() {
        use CloudFormat::*;
        for (format, encoding, tol) in [
            (Ply, Encoding::Binary, 1e-7),
            (Ply, Encoding::Ascii, 0.0),
            (Pcd, Encoding::Binary, 1e-7),
            (Pcd, Encoding::Ascii, 1e-7),
            (Xyz, Encoding::Ascii, 0.0),
            (Npy, Encoding::Binary, 1e-7),
        ] {
            let bytes = encode(&sample(), format, encoding);
            close(&parse_cloud(&bytes, format).unwrap(), &sample(), tol);
            assert_eq!(parse_cloud(&encode(&[], format, encoding), format).unwrap(), vec![], "{format:?}");
        }
    }

    #[test]
    fn round_trip_files_by_extension() {
        let dir = tempfile::tempdir().unwrap();
        for name in ["a.ply", "b.PCD", "c.xyz", "d.csv", "e.npy"] {
            let path = dir.path().join(name);
            write_cloud(&path, &sample()).unwrap();
            close(&read_cloud(&path).unwrap(), &sample(), 1e-7);
            assert_eq!(name == "d.csv", std::fs::read_to_string(&path).unwrap_or_default().contains(','));
            write_cloud_with(&path, &sample(), Encoding::Ascii).unwrap();
            close(&read_cloud(&path).unwrap(), &sample(), 1e-7);
        }
        let msg = read_cloud(dir.path().join("f.las")).unwrap_err().to_string();
        assert!(msg.contains("f.las") && msg.contains("extension"), "{msg}");
        let msg = read_cloud(dir.path().join("missing.ply")).unwrap_err().to_string();
        assert!(msg.contains("missing.ply"), "{msg}");
    }

    #[test]
    fn bad_file_names_file_format_and_reason() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("scan.xyz");
        std::fs::write(&path, "1 2 3\n4 5\n").unwrap();
        let msg = read_cloud(&path).unwrap_err().to_string();
        assert!(msg.contains("scan.xyz") && msg.contains("XYZ") && msg.contains("line 2"), "{msg}");
    }

    #[test]
    fn writers_refuse_non_finite() {
        let bad = [Point3::new(0.0, f64::NAN, 0.0)];
        for f in [CloudFormat::Ply, CloudFormat::Pcd, CloudFormat::Xyz, CloudFormat::Npy] {
            assert!(write_cloud_to(Vec::new(), &bad, f, Encoding::Binary).is_err());
        }
    }

    /// Cheap deterministic xorshift, for the mutation test.
    fn xorshift(seed: &mut u64) -> u64 {
        *seed ^= *seed << 13;
        *seed ^= *seed >> 7;
        *seed ^= *seed << 17;
        *seed
    }

    /// Every prefix and thousands of random byte edits of valid files: the
    /// parsers may refuse them, but must not panic or allocate wildly.
    #[test]
    fn mutated_and_truncated_files_never_panic() {
        use CloudFormat::*;
        let mut samples = vec![
            (Ply, PLY_ASCII.as_bytes().to_vec()),
            (Ply, ply_binary(false, 0)),
            (Ply, ply_binary(true, 0)),
            (Pcd, [pcd_head("binary", "2").into_bytes(), pcd_records()].concat()),
            (Pcd, format!("{}1 0.5 7 8 9 -1 2 3\n1 3 7 8 9 0.125 -4 3\n", pcd_head("ascii", "2")).into_bytes()),
            (Xyz, b"# c\n1 2 3\n4,5,6\n".to_vec()),
        ];
        for f in [Ply, Pcd, Npy] {
            samples.push((f, encode(&sample(), f, Encoding::Binary)));
        }
        let mut seed = 0x9e37_79b9_7f4a_7c15;
        for (f, b) in samples {
            for cut in 0..b.len() {
                let _ = parse_cloud(&b[..cut], f);
            }
            for _ in 0..3000 {
                let mut m = b.clone();
                for _ in 0..1 + xorshift(&mut seed) % 4 {
                    let i = (xorshift(&mut seed) % m.len() as u64) as usize;
                    m[i] = xorshift(&mut seed) as u8;
                }
                let _ = parse_cloud(&m, f);
            }
        }
    }

    // ------------------------------------------------------------ PLY

    const PLY_ASCII: &str = "ply\r\nformat ascii 1.0\ncomment made by hand\nobj_info scanner 7\n\
        element vertex 3\nproperty float x\nproperty float32 y\nproperty float z\nproperty uchar red\n\
        property uchar green\nproperty uchar blue\nproperty list uchar int extra\n\
        element face 1\nproperty list uchar int vertex_indices\nend_header\n\
        0 0 0 255 0 0 0\n1 0 0.5 0 255 0 2 7 8\n\n0 1 -2 0 0 255 1 9\n3 0 1 2\n";

    #[test]
    fn ply_ascii_with_extra_properties_and_faces() {
        let p = parse_ply(PLY_ASCII.as_bytes()).unwrap();
        assert_eq!(p, vec![Point3::new(0.0, 0.0, 0.0), Point3::new(1.0, 0.0, 0.5), Point3::new(0.0, 1.0, -2.0)]);
    }

    /// Binary PLY: a list-bearing element before the vertices, extra
    /// properties of several types, faces after.
    fn ply_binary(big: bool, truncate: usize) -> Vec<u8> {
        let order = if big { "binary_big_endian" } else { "binary_little_endian" };
        let mut b = format!(
            "ply\nformat {order} 1.0\ncomment x\nelement camera 2\nproperty list uint8 float32 k\nproperty short id\n\
             element vertex 2\nproperty double z\nproperty uchar alpha\nproperty float64 x\nproperty int32 y\n\
             property ushort label\nelement face 1\nproperty list uchar uint vertex_indices\nend_header\n"
        )
        .into_bytes();
        macro_rules! put {
            ($v:expr) => {
                b.extend_from_slice(&if big { $v.to_be_bytes() } else { $v.to_le_bytes() })
            };
        }
        put!(2u8);
        put!(1.0f32);
        put!(2.0f32);
        put!(-1i16);
        put!(0u8);
        put!(5i16);
        for (x, y, z) in [(0.25f64, -3i32, 1.5f64), (-7.0, 4, 0.0)] {
            put!(z);
            put!(9u8);
            put!(x);
            put!(y);
            put!(65535u16);
        }
        put!(3u8);
        for i in 0..3u32 {
            put!(i);
        }
        b.truncate(b.len() - truncate);
        b
    }

    #[test]
    fn ply_binary_both_endians() {
        let want = vec![Point3::new(0.25, -3.0, 1.5), Point3::new(-7.0, 4.0, 0.0)];
        assert_eq!(parse_ply(&ply_binary(false, 0)).unwrap(), want);
        assert_eq!(parse_ply(&ply_binary(true, 0)).unwrap(), want);
        // Faces are never read, so cutting them off does not matter...
        assert_eq!(parse_ply(&ply_binary(true, 13)).unwrap(), want);
        // ...but cutting into the vertices does.
        assert_err(parse_ply(&ply_binary(false, 14)), &["truncated", "expected 2"]);
    }

    fn ply_head(format: &str, n: &str) -> String {
        format!("ply\nformat {format} 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\nend_header\n")
    }

    #[test]
    fn ply_bad_files() {
        assert_err(parse_ply(b""), &["PLY", "empty"]);
        assert_err(parse_ply(b"PLY\nformat ascii 1.0\n"), &["first line is not 'ply'"]);
        assert_err(parse_ply(b"ply\nformat ascii 1.0\nelement vertex 1\n"), &["end_header"]);
        assert_err(parse_ply(b"ply\nelement vertex 0\nend_header\n"), &["no 'format'"]);
        assert_err(parse_ply(b"ply\nformat ascii 1.0\nelement face 0\nend_header\n"), &["no 'vertex' element"]);
        assert_err(
            parse_ply(b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nend_header\n"),
            &["no scalar property 'z'"],
        );
        assert_err(
            parse_ply(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty half x\nend_header\n"),
            &["line 4", "half"],
        );
        assert_err(
            parse_ply(format!("{}1 2 3\nnan 0 0\n", ply_head("ascii", "2")).as_bytes()),
            &["line 9", "point 1", "non-finite"],
        );
        assert_err(
            parse_ply(format!("{}1 2 3\n1 2 3\n", ply_head("ascii", "3")).as_bytes()),
            &["truncated", "expected 3 vertices, found 2"],
        );
        assert_err(
            parse_ply(format!("{}1 2 3 4\n", ply_head("ascii", "1")).as_bytes()),
            &["line 8", "expected 3 values, found 4"],
        );
        assert_err(parse_ply(format!("{}1 2\n", ply_head("ascii", "1")).as_bytes()), &["line 8", "too few values"]);
        assert_err(
            parse_ply(format!("{}1 2 x\n", ply_head("ascii", "1")).as_bytes()),
            &["line 8", "'x' is not a number"],
        );
        assert_err(parse_ply(ply_head("ascii", "1000000000000").as_bytes()), &["expected 1000000000000 vertices"]);
        assert_err(
            parse_ply(ply_head("binary_little_endian", "1000000000000").as_bytes()),
            &["expected 1000000000000"],
        );
        assert_err(parse_ply(ply_head("binary_little_endian", "99999999999999999999999").as_bytes()), &["not a count"]);
        let mut nan = ply_head("binary_little_endian", "1").into_bytes();
        [0.0f32, f32::INFINITY, 0.0].iter().for_each(|c| nan.extend_from_slice(&c.to_le_bytes()));
        assert_err(parse_ply(&nan), &["point 0", "non-finite"]);
        let mut neg = b"ply\nformat binary_little_endian 1.0\nelement f 1\nproperty list char int v\n".to_vec();
        neg.extend_from_slice(
            b"element vertex 0\nproperty float x\nproperty float y\nproperty float z\nend_header\n\xff",
        );
        assert_err(parse_ply(&neg), &["negative list length"]);
        assert_eq!(parse_ply(ply_head("binary_big_endian", "0").as_bytes()).unwrap(), vec![]);
    }

    // ------------------------------------------------------------ PCD

    fn pcd_head(data: &str, points: &str) -> String {
        format!(
            "# .PCD v0.7\nVERSION 0.7\nFIELDS rgb x normal y z label\nSIZE 4 4 4 8 4 2\nTYPE F F F F F U\n\
             COUNT 1 1 3 1 1 1\nWIDTH {points}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {points}\nDATA {data}\n"
        )
    }

    fn pcd_records() -> Vec<u8> {
        let mut b = Vec::new();
        for (x, y, z) in [(0.5f32, -1.0f64, 2.0f32), (3.0, 0.125, -4.0)] {
            b.extend_from_slice(&1.0f32.to_le_bytes());
            b.extend_from_slice(&x.to_le_bytes());
            [7.0f32, 8.0, 9.0].iter().for_each(|c| b.extend_from_slice(&c.to_le_bytes()));
            b.extend_from_slice(&y.to_le_bytes());
            b.extend_from_slice(&z.to_le_bytes());
            b.extend_from_slice(&3u16.to_le_bytes());
        }
        b
    }

    fn pcd_want() -> Cloud {
        vec![Point3::new(0.5, -1.0, 2.0), Point3::new(3.0, 0.125, -4.0)]
    }

    #[test]
    fn pcd_binary_with_extra_fields() {
        let mut b = pcd_head("binary", "2").into_bytes();
        b.extend(pcd_records());
        assert_eq!(parse_pcd(&b).unwrap(), pcd_want());
        b.truncate(b.len() - 1);
        assert_err(parse_pcd(&b), &["PCD", "expected 2 points"]);
    }

    #[test]
    fn pcd_ascii_with_extra_fields() {
        let body = "1 0.5 7 8 9 -1 2 3\n\n1 3 7 8 9 0.125 -4 3\n";
        assert_eq!(parse_pcd(format!("{}{body}", pcd_head("ascii", "2")).as_bytes()).unwrap(), pcd_want());
        assert_err(parse_pcd(format!("{}{body}", pcd_head("ascii", "3")).as_bytes()), &["expected 3 points, found 2"]);
        assert_err(parse_pcd(format!("{}{body}", pcd_head("ascii", "1")).as_bytes()), &["line 14", "more data lines"]);
        let short = "1 0.5 7 8 9 -1 2\n";
        assert_err(
            parse_pcd(format!("{}{short}", pcd_head("ascii", "1")).as_bytes()),
            &["line 12", "expected 8 values, found 7"],
        );
        let nan = "1 0.5 7 8 9 nan 2 3\n";
        assert_err(
            parse_pcd(format!("{}{nan}", pcd_head("ascii", "1")).as_bytes()),
            &["line 12", "point 0", "non-finite"],
        );
    }

    /// LZF as literal runs only (valid, if uncompressed), for test data.
    fn lzf_literals(raw: &[u8]) -> Vec<u8> {
        raw.chunks(32).flat_map(|c| std::iter::once(c.len() as u8 - 1).chain(c.iter().copied())).collect()
    }

    #[test]
    fn lzf_back_references() {
        assert_eq!(lzf_decompress(&[2, b'a', b'b', b'c', 0x20, 2], 6).unwrap(), b"abcabc");
        assert_eq!(lzf_decompress(&[0, b'a', 0xe0, 3, 0], 13).unwrap(), vec![b'a'; 13]); // overlapping run
        assert!(lzf_decompress(&[0, b'a', 0x20, 5], 4).is_none()); // reaches before the start
        assert!(lzf_decompress(&[5, b'a'], 6).is_none()); // literal cut short
    }

    #[test]
    fn pcd_binary_compressed() {
        // Structure of arrays: each field for both points, in field order.
        let recs = pcd_records();
        let sizes = [4, 4, 12, 8, 4, 2];
        let mut soa = Vec::new();
        let mut off = 0;
        for s in sizes {
            soa.extend_from_slice(&recs[off..off + s]);
            soa.extend_from_slice(&recs[34 + off..34 + off + s]);
            off += s;
        }
        let packed = lzf_literals(&soa);
        let file = |raw: u32| {
            let mut b = pcd_head("binary_compressed", "2").into_bytes();
            b.extend_from_slice(&(packed.len() as u32).to_le_bytes());
            b.extend_from_slice(&raw.to_le_bytes());
            b.extend_from_slice(&packed);
            b
        };
        assert_eq!(parse_pcd(&file(soa.len() as u32)).unwrap(), pcd_want());
        assert_err(parse_pcd(&file(soa.len() as u32 + 1)), &["uncompressed size"]);
        let mut cut = file(soa.len() as u32);
        cut.truncate(cut.len() - 3);
        assert_err(parse_pcd(&cut), &["truncated"]);
    }

    #[test]
    fn pcd_bad_headers() {
        assert_err(parse_pcd(b"VERSION 0.7\nFIELDS x y z\n"), &["no 'DATA' line"]);
        assert_err(
            parse_pcd(b"FIELDS x y z\nSIZE 4 4\nTYPE F F F\nPOINTS 0\nDATA ascii\n"),
            &["line 2", "SIZE has 2 entries"],
        );
        assert_err(parse_pcd(b"FIELDS x y\nSIZE 4 4\nTYPE F F\nPOINTS 0\nDATA ascii\n"), &["no 'z' field"]);
        assert_err(parse_pcd(b"FIELDS x y z\nSIZE 4 4 2\nTYPE F F F\nPOINTS 0\nDATA ascii\n"), &["TYPE F SIZE 2"]);
        assert_err(parse_pcd(b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 2\nPOINTS 3\nDATA ascii\n"), &["disagrees"]);
        assert_err(parse_pcd(b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 3\nDATA lzma\n"), &["line 5", "lzma"]);
        let huge = b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 1000000000000\nDATA binary\n";
        assert_err(parse_pcd(huge), &["expected 1000000000000 points"]);
        let huge = b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 1000000000000\nDATA ascii\n1 2 3\n";
        assert_err(parse_pcd(huge), &["expected 1000000000000 points, found 1"]);
        let empty = b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 0\nHEIGHT 0\nDATA binary\n";
        assert_eq!(parse_pcd(empty).unwrap(), vec![]);
    }

    // ------------------------------------------------------------ XYZ

    #[test]
    fn xyz_separators_comments_extra_columns() {
        let text = "# x y z r g b\n\n1 2 3\n4,5,6, 255, 0\r\n  7\t8  9 # trailing comment\n-1e-3, 2.5E2 ,0\n";
        let p = parse_xyz(text.as_bytes()).unwrap();
        assert_eq!(p[1], Point3::new(4.0, 5.0, 6.0));
        assert_eq!(p[3], Point3::new(-1e-3, 250.0, 0.0));
        assert_eq!(p.len(), 4);
        assert_eq!(parse_xyz(b"").unwrap(), vec![]);
        assert_eq!(parse_xyz(b"# only a comment\n\n").unwrap(), vec![]);
    }

    #[test]
    fn xyz_bad_files() {
        assert_err(parse_xyz(b"1 2 3\n\n1 2\n"), &["XYZ", "line 3", "at least 3 columns", "found 2"]);
        assert_err(parse_xyz(b"1 2 3\n1 2 three\n"), &["line 2", "'three' is not a number"]);
        assert_err(parse_xyz(b"x,y,z\n1,2,3\n"), &["line 1", "no header row"]);
        assert_err(parse_xyz(b"1 2 3\ninf 0 0\n"), &["line 2", "point 1", "non-finite"]);
        assert_err(parse_xyz(b"1 2 3\n\xff\xfe 1 2\n"), &["line 2", "not text"]);
    }

    // ------------------------------------------------------------ NPY

    fn npy(version: u8, descr: &str, extra: &str, data: &[u8]) -> Vec<u8> {
        let mut h = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': (2, 3), {extra}}}");
        while (h.len() + 11) % 64 != 0 {
            h.push(' ');
        }
        h.push('\n');
        let mut b = b"\x93NUMPY".to_vec();
        b.push(version);
        b.push(0);
        if version == 1 {
            b.extend_from_slice(&(h.len() as u16).to_le_bytes());
        } else {
            b.extend_from_slice(&(h.len() as u32).to_le_bytes());
        }
        b.extend_from_slice(h.as_bytes());
        b.extend_from_slice(data);
        b
    }

    /// Replaces the first `from` in the header by `to` (same length keeps the padding valid).
    fn replace(mut b: Vec<u8>, from: &str, to: &str) -> Vec<u8> {
        let i = b.windows(from.len()).position(|w| w == from.as_bytes()).unwrap();
        b.splice(i..i + from.len(), to.bytes());
        b
    }

    const NPY_VALUES: [f64; 6] = [0.5, -1.0, 2.0, 3.0, 0.125, -4.0];

    #[test]
    fn npy_dtypes_and_versions() {
        let want = pcd_want();
        let f8: Vec<u8> = NPY_VALUES.iter().flat_map(|v| v.to_le_bytes()).collect();
        let f4: Vec<u8> = NPY_VALUES.iter().flat_map(|v| (*v as f32).to_le_bytes()).collect();
        let f8be: Vec<u8> = NPY_VALUES.iter().flat_map(|v| v.to_be_bytes()).collect();
        let f4be: Vec<u8> = NPY_VALUES.iter().flat_map(|v| (*v as f32).to_be_bytes()).collect();
        assert_eq!(parse_npy(&npy(1, "<f8", "", &f8)).unwrap(), want);
        assert_eq!(parse_npy(&npy(1, "<f4", "", &f4)).unwrap(), want);
        assert_eq!(parse_npy(&npy(2, ">f8", "", &f8be)).unwrap(), want);
        assert_eq!(parse_npy(&npy(3, ">f4", "", &f4be)).unwrap(), want);
        // Fortran order: columns x, y, z one after the other.
        let cols: Vec<u8> = [0, 3, 1, 4, 2, 5].iter().flat_map(|&i| NPY_VALUES[i].to_le_bytes()).collect();
        let fortran = replace(npy(1, "<f8", "", &cols), "False", "True ");
        assert_eq!(parse_npy(&fortran).unwrap(), want);
    }

    #[test]
    fn npy_writer_header_is_numpy_v1() {
        let b = encode(&sample(), CloudFormat::Npy, Encoding::Binary);
        let len = u16::from_le_bytes([b[8], b[9]]) as usize;
        assert_eq!((10 + len) % 64, 0);
        assert_eq!(b.len(), 10 + len + 4 * 12);
        assert!(std::str::from_utf8(&b[10..10 + len])
            .unwrap()
            .starts_with("{'descr': '<f4', 'fortran_order': False, 'shape': (4, 3), }"));
    }

    #[test]
    fn npy_bad_files() {
        let f8: Vec<u8> = NPY_VALUES.iter().flat_map(|v| v.to_le_bytes()).collect();
        assert_err(parse_npy(b"PK\x03\x04 not npy"), &["NPY", "magic"]);
        assert_err(parse_npy(&npy(1, "<i4", "", &f8[..24])), &["dtype '<i4'"]);
        assert_err(parse_npy(&npy(1, "<f8", "", &f8[..40])), &["expected 2 points"]);
        assert_err(parse_npy(&npy(1, "<f8", "", &[f8.clone(), vec![0; 8]].concat())), &["8 bytes after"]);
        let mut nan = f8.clone();
        nan[32..40].copy_from_slice(&f64::NAN.to_le_bytes());
        assert_err(parse_npy(&npy(1, "<f8", "", &nan)), &["point 1", "non-finite"]);
        let wide = replace(npy(1, "<f8", "", &f8), "(2, 3)", "(3, 2)");
        assert_err(parse_npy(&wide), &["shape [3, 2] is not (N, 3)"]);
        let huge = replace(npy(1, "<f8", "", &f8), "(2, 3),", "(1000000000000, 3)");
        assert_err(parse_npy(&huge), &["expected 1000000000000 points"]);
        assert_err(parse_npy(&npy(1, "<f8", "", &f8)[..20]), &["truncated"]);
        assert_err(parse_npy(b"\x93NUMPY\x09\x00\x00\x00"), &["version 9"]);
    }
}
