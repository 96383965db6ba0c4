//! The baseline transport `graspctl bench` compares the shared-memory one
//! with: Register over a Unix-domain stream socket, the cloud serialised and
//! copied through the kernel (what a user would write without iceoryx2).
//! Off unless `uds_baseline` names a socket path; not meant for production.
//!
//! Frames (little-endian, the same byte layouts as the shared-memory messages):
//! request  = RequestHeader (160 bytes) | u32 point count n | n × (f32 x, f32 y, f32 z);
//! response = ResponseHeader (160 bytes) | RegisterResponse (768 bytes).
//! The connection stays open for further requests; a malformed frame closes it.

use super::engine::Status;
use graspd_proto::{self as proto, Plain, Point, RequestHeader, ResponseHeader, StatusCode};
use std::io::{Read, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Instant;

type RegisterFn = dyn Fn(&[Point], &RequestHeader) -> Result<proto::RegisterResponse, Status> + Send + Sync;

pub struct EngineHandle {
    pub max_points: usize,
    pub register: Box<RegisterFn>,
}

/// Removes the socket file when the daemon stops.
pub struct UdsGuard {
    path: PathBuf,
}

impl Drop for UdsGuard {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
    }
}

const MAX_CONNECTIONS: usize = 16;

pub fn start(path: &Path, engine: EngineHandle) -> std::io::Result<UdsGuard> {
    if path.exists() {
        // A socket left by a previous run; anything else is refused.
        use std::os::unix::fs::FileTypeExt;
        if std::fs::symlink_metadata(path)?.file_type().is_socket() {
            std::fs::remove_file(path)?;
        } else {
            return Err(std::io::Error::new(std::io::ErrorKind::AlreadyExists, "exists and is not a socket"));
        }
    }
    let listener = UnixListener::bind(path)?;
    let engine = Arc::new(engine);
    let open = Arc::new(AtomicUsize::new(0));
    tracing::info!("UDS baseline endpoint on {}", path.display());
    std::thread::Builder::new().name("graspd-uds".into()).spawn(move || {
        for stream in listener.incoming() {
            let Ok(stream) = stream else { continue };
            if open.load(Ordering::Relaxed) >= MAX_CONNECTIONS {
                continue; // dropped: the client sees the connection closed
            }
            open.fetch_add(1, Ordering::Relaxed);
            let (engine, open) = (engine.clone(), open.clone());
            let _ = std::thread::Builder::new().name("graspd-uds-conn".into()).spawn(move || {
                if let Err(e) = serve_connection(stream, &engine) {
                    tracing::debug!("UDS baseline connection closed: {e}");
                }
                open.fetch_sub(1, Ordering::Relaxed);
            });
        }
    })?;
    Ok(UdsGuard { path: path.to_owned() })
}

fn serve_connection(mut s: UnixStream, engine: &EngineHandle) -> std::io::Result<()> {
    let mut hdr = [0u8; std::mem::size_of::<RequestHeader>()];
    let mut buf: Vec<u8> = Vec::new();
    loop {
        match s.read_exact(&mut hdr) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => return Ok(()),
            Err(e) => return Err(e),
        }
        let t0 = Instant::now();
        let Some(h) = RequestHeader::from_bytes(&hdr) else { return Ok(()) };
        let mut n = [0u8; 4];
        s.read_exact(&mut n)?;
        let n = u32::from_le_bytes(n) as usize;
        let mut resp = ResponseHeader::zeroed();
        resp.request_id = h.request_id;
        resp.protocol_version = proto::PROTOCOL_VERSION;
        let mut body = proto::RegisterResponse::zeroed();
        if n > engine.max_points {
            resp.status = StatusCode::ResourceExhausted as u32;
            resp.message = proto::str_to_text(&format!("{n} points; at most {}", engine.max_points));
            s.write_all(resp.as_bytes())?;
            s.write_all(body.as_bytes())?;
            return Ok(());
        }
        buf.resize(n * 12, 0);
        s.read_exact(&mut buf)?;
        // Deserialise (a copy, as any socket protocol needs).
        let points: Vec<Point> = buf
            .chunks_exact(12)
            .map(|c| {
                let f = |i: usize| f32::from_le_bytes([c[i], c[i + 1], c[i + 2], c[i + 3]]);
                Point([f(0), f(4), f(8)])
            })
            .collect();
        let tc = Instant::now();
        let result = if h.protocol_version != proto::PROTOCOL_VERSION {
            Err(Status::invalid("protocol_version mismatch"))
        } else {
            std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| (engine.register)(&points, &h)))
                .unwrap_or_else(|_| Err(Status::new(StatusCode::Internal, "internal error")))
        };
        resp.compute_ns = tc.elapsed().as_nanos() as u64;
        match result {
            Ok(b) => body = b,
            Err(st) => {
                resp.status = st.code as u32;
                resp.message = proto::str_to_text(&st.message);
            }
        }
        resp.server_ns = t0.elapsed().as_nanos() as u64;
        s.write_all(resp.as_bytes())?;
        s.write_all(body.as_bytes())?;
    }
}
