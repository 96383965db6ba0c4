//! File input/output: point clouds (PLY, PCD, XYZ, NPY) and meshes (OBJ, STL).
//!
//! Files come from scanners, Python scripts and CAD tools, so the readers are
//! defensive: every malformed input is an [`IoError`] naming the file, format
//! and reason; nothing panics, and no header field sizes an allocation before
//! it is checked against the bytes actually present. Parsers work on `&[u8]`
//! (unit-testable without files); `read_*`/`write_*` dispatch on the extension.

pub mod cloud;
pub mod error;
pub mod mesh;

pub use cloud::{parse_cloud, read_cloud, read_cloud_from, write_cloud, write_cloud_to, write_cloud_with, CloudFormat};
pub use error::IoError;
pub use mesh::{
    check_mesh, parse_mesh, read_mesh, write_obj, write_obj_to, write_stl, write_stl_to, LoadedMesh, MeshFormat,
};

use error::Result;
use nalgebra::Point3;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;

/// Binary or text flavour, for formats that have both (PLY, PCD, STL).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Encoding {
    #[default]
    Binary,
    Ascii,
}

/// Lowercased extension of `path` ("" when none).
fn extension(path: &Path) -> String {
    path.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase()
}

fn read_file(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| IoError::os(e).at(path))
}

/// Creates `path` and runs `body` on a buffered writer, naming the file on error.
fn write_file(path: &Path, body: impl FnOnce(&mut BufWriter<File>) -> Result<()>) -> Result<()> {
    let file = File::create(path).map_err(|e| IoError::os(e).at(path))?;
    let mut w = BufWriter::new(file);
    body(&mut w).and_then(|()| w.flush().map_err(IoError::os)).map_err(|e| e.at(path))
}

/// Lines of a text section with their 1-based file line numbers (`first` is
/// the number of the first line); a trailing `\r` is dropped.
fn lines(bytes: &[u8], first: usize) -> impl Iterator<Item = (usize, &[u8])> {
    // A final newline does not start another line.
    let body = bytes.strip_suffix(b"\n").unwrap_or(bytes);
    let empty = body.is_empty() && bytes.is_empty();
    body.split(|&b| b == b'\n')
        .filter(move |_| !empty)
        .enumerate()
        .map(move |(i, l)| (first + i, l.strip_suffix(b"\r").unwrap_or(l)))
}

fn text<'a>(format: &'static str, line: usize, bytes: &'a [u8]) -> Result<&'a str> {
    std::str::from_utf8(bytes).map_err(|_| IoError::at_line(format, line, "not text (binary data in a text section?)"))
}

fn parse_f64(format: &'static str, line: usize, token: &str) -> Result<f64> {
    token.parse().map_err(|_| IoError::at_line(format, line, format!("'{token}' is not a number")))
}

/// Rejects NaN/Inf: one bad coordinate poisons every later sum, so the
/// reader names the point instead of letting registration fail later.
fn point(format: &'static str, index: usize, line: Option<usize>, x: f64, y: f64, z: f64) -> Result<Point3<f64>> {
    if x.is_finite() && y.is_finite() && z.is_finite() {
        return Ok(Point3::new(x, y, z));
    }
    let what = format!("point {index} has a non-finite coordinate ({x}, {y}, {z})");
    Err(match line {
        Some(l) => IoError::at_line(format, l, what),
        None => IoError::bad(format, what),
    })
}

/// Checks a header count against the data present before anything is
/// allocated from it: `count` records of at least `min_record` bytes must fit
/// in `available` bytes. Returns the count as usize.
fn check_count(format: &'static str, what: &str, count: u64, min_record: u64, available: usize) -> Result<usize> {
    let need = count.checked_mul(min_record);
    match need {
        Some(n) if n <= available as u64 => Ok(count as usize),
        _ => Err(IoError::bad(
            format,
            format!(
                "truncated data or bad count in the header: expected {count} {what} (at least {} bytes), \
                 found {available} bytes (room for {})",
                need.map(|n| n.to_string()).unwrap_or_else(|| "> 2^64".into()),
                available as u64 / min_record.max(1)
            ),
        )),
    }
}

/// Writers refuse non-finite points: the readers would reject the file.
fn check_finite(format: &'static str, points: &[Point3<f64>]) -> Result<()> {
    match points.iter().position(|p| !p.coords.iter().all(|c| c.is_finite())) {
        None => Ok(()),
        Some(i) => Err(IoError::bad(format, format!("cannot write point {i}: non-finite coordinate {:?}", points[i]))),
    }
}

fn write_all(w: &mut impl Write, bytes: &[u8]) -> Result<()> {
    w.write_all(bytes).map_err(IoError::os)
}
