//! The one error type of file input/output.
//!
//! Every message names the file (when there is one), the format and the
//! reason, with a line number for text formats, so a user can fix the file
//! without reading our code. In-memory parsers (`parse_*` on `&[u8]`) have no
//! file name; the path-taking dispatchers attach it with [`IoError::at`].

use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum IoError {
    /// The operating system refused: missing file, permissions, disk full.
    #[error("{}{source}", prefix(.path))]
    Os { path: Option<PathBuf>, source: std::io::Error },
    /// The bytes are not a valid file of the format (or one we do not support).
    #[error("{}{format}: {reason}", prefix(.path))]
    Format { path: Option<PathBuf>, format: &'static str, reason: String },
    /// The extension does not name a format we know.
    #[error("{}unknown file extension (expected {expected})", prefix(.path))]
    Extension { path: Option<PathBuf>, expected: &'static str },
}

fn prefix(path: &Option<PathBuf>) -> String {
    path.as_ref().map(|p| format!("{}: ", p.display())).unwrap_or_default()
}

impl IoError {
    /// A format error without a file name yet.
    pub(crate) fn bad(format: &'static str, reason: impl Into<String>) -> Self {
        IoError::Format { path: None, format, reason: reason.into() }
    }

    /// A format error at a (1-based) line of a text file.
    pub(crate) fn at_line(format: &'static str, line: usize, reason: impl std::fmt::Display) -> Self {
        Self::bad(format, format!("line {line}: {reason}"))
    }

    pub(crate) fn os(source: std::io::Error) -> Self {
        IoError::Os { path: None, source }
    }

    /// Attaches the file name (keeps one that is already there).
    pub fn at(mut self, file: &Path) -> Self {
        let (IoError::Os { path, .. } | IoError::Format { path, .. } | IoError::Extension { path, .. }) = &mut self;
        if path.is_none() {
            *path = Some(file.to_path_buf());
        }
        self
    }

    pub fn path(&self) -> Option<&Path> {
        match self {
            IoError::Os { path, .. } | IoError::Format { path, .. } | IoError::Extension { path, .. } => {
                path.as_deref()
            }
        }
    }
}

impl From<std::io::Error> for IoError {
    fn from(e: std::io::Error) -> Self {
        IoError::os(e)
    }
}

pub type Result<T, E = IoError> = std::result::Result<T, E>;
