//! The vehicle's instrument sources as byte streams cut into lines: a UDP socket (each datagram
//! one or more lines) or standard input, each read by a thread of its own that blocks on it and
//! hands lines to the node's loop over a bounded channel (a flood waits for the loop, or on UDP
//! is dropped by the kernel's buffer, never held without bound). A line longer than
//! [`MAX_LINE`] is not kept: the reader says how long it was and skips to the next newline.
//! What a line means is `fleet_mission::instrument`'s business.
//!
//! A `geotiff:DIR` source is a directory a camera pipeline writes frames into: a thread looks
//! at it every [`LOOK_EVERY`] (a directory on any filesystem, NFS and SD cards included, can be
//! listed; not every one can be watched), takes each new `.tif`/`.tiff` once its size has held
//! still between two looks (a writer should still write elsewhere and rename it in), and
//! resamples it onto the model grid there, so the node's loop receives a value per cell.

use fleet_math::grid::Grid;
use fleet_mission::instrument::raster;
use fleet_mission::instrument::{SensorSource, MAX_LINE};
use fleet_mission::site::Site;
use std::collections::{BTreeMap, BTreeSet};
use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::Duration;
use tokio::sync::mpsc;

/// How often a frame directory is looked at.
pub const LOOK_EVERY: Duration = Duration::from_millis(250);
/// The largest frame file read (bytes).
const MAX_FRAME_BYTES: u64 = 1 << 30;

/// A frame on the model grid: its file, its time (UTC seconds), a value per cell (`None`
/// where it has none); or why it was refused.
pub type Frame = Result<(String, f64, Vec<Option<f64>>), (String, String)>;

/// What a source delivers.
#[derive(Debug, Clone, PartialEq)]
pub enum Input {
    Line(Line),
    Frame(Frame),
    /// A reading decoded elsewhere (a MAVLink NAMED_VALUE_FLOAT, positioned and timed by the
    /// autopilot), or why it was refused.
    Reading(fleet_mission::instrument::named::Outcome),
    /// This many readings found the queue full and were dropped (counted as `overflow`).
    Lost(u64),
}

/// Lines waiting for the node's loop, at most.
pub const QUEUE: usize = 1024;

/// One line from a source.
#[derive(Debug, Clone, PartialEq)]
pub enum Line {
    Text(Vec<u8>),
    /// A line of this many bytes, longer than [`MAX_LINE`]: dropped unread.
    Oversized(usize),
}

/// Cuts a byte stream into lines of at most [`MAX_LINE`] bytes, holding at most that much.
#[derive(Debug, Default)]
pub struct Splitter {
    held: Vec<u8>,
    /// Bytes of the current line, when it is already over the limit (its bytes are not held).
    over: Option<usize>,
}

impl Splitter {
    /// Feed bytes; the lines they complete (empty lines and a trailing `\r` dropped).
    pub fn feed(&mut self, bytes: &[u8]) -> Vec<Line> {
        let mut lines = vec![];
        for piece in bytes.split_inclusive(|&b| b == b'\n') {
            let (body, ends) = match piece.strip_suffix(b"\n") {
                Some(b) => (b, true),
                None => (piece, false),
            };
            match &mut self.over {
                Some(n) => *n += body.len(),
                None if self.held.len() + body.len() > MAX_LINE => {
                    self.over = Some(self.held.len() + body.len());
                    self.held.clear();
                }
                None => self.held.extend_from_slice(body),
            }
            if ends {
                lines.extend(self.end_line());
            }
        }
        lines
    }

    /// The line in progress, ended (at the end of a datagram or of the stream).
    pub fn end_line(&mut self) -> Option<Line> {
        if let Some(n) = self.over.take() {
            return Some(Line::Oversized(n));
        }
        let mut line = std::mem::take(&mut self.held);
        if line.last() == Some(&b'\r') {
            line.pop();
        }
        (!line.iter().all(u8::is_ascii_whitespace)).then_some(Line::Text(line))
    }
}

/// Start reading `source` (`None` for `sim`, which has no stream); its lines or frames (on
/// `grid`, placed by `site`) come on the returned channel until the stream ends.
pub fn open(source: &SensorSource, site: Site, grid: Grid) -> std::io::Result<Option<mpsc::Receiver<Input>>> {
    let (tx, rx) = mpsc::channel(QUEUE);
    let name = format!("sensor {source}");
    match source {
        SensorSource::Geotiff(dir) => {
            std::fs::read_dir(dir)?;
            let dir = dir.clone();
            std::thread::Builder::new()
                .name(name)
                .spawn(move || watch_frames(&dir, site, grid, tx))?;
        }
        SensorSource::Udp(addr) => {
            let socket = std::net::UdpSocket::bind(addr)?;
            std::thread::Builder::new()
                .name(name)
                .spawn(move || read_udp(socket, tx))?;
        }
        SensorSource::Stdin => {
            std::thread::Builder::new()
                .name(name)
                .spawn(move || read_stream(std::io::stdin().lock(), tx))?;
        }
        _ => return Ok(None),
    }
    Ok(Some(rx))
}

/// Look at `dir` every [`LOOK_EVERY`] and hand on each new frame once its size holds still.
fn watch_frames(dir: &Path, site: Site, grid: Grid, tx: mpsc::Sender<Input>) {
    let (mut done, mut sizes): (BTreeSet<PathBuf>, BTreeMap<PathBuf, u64>) = Default::default();
    while !tx.is_closed() {
        let mut seen: BTreeMap<PathBuf, u64> = BTreeMap::new();
        for entry in std::fs::read_dir(dir).into_iter().flatten().flatten() {
            let path = entry.path();
            let tif = path
                .extension()
                .is_some_and(|e| e.eq_ignore_ascii_case("tif") || e.eq_ignore_ascii_case("tiff"));
            if tif && !done.contains(&path) {
                seen.insert(path, entry.metadata().map_or(u64::MAX, |m| m.len()));
            }
        }
        for (path, size) in &seen {
            if sizes.get(path) == Some(size) {
                done.insert(path.clone());
                if tx
                    .blocking_send(Input::Frame(read_frame(path, *size, &site, &grid)))
                    .is_err()
                {
                    return;
                }
            }
        }
        sizes = seen;
        std::thread::sleep(LOOK_EVERY);
    }
}

/// One frame file on the model grid, or why not.
fn read_frame(path: &Path, size: u64, site: &Site, grid: &Grid) -> Frame {
    let name = path.file_name().unwrap_or_default().to_string_lossy().to_string();
    let refuse = |why: String| Err((name.clone(), why));
    if size > MAX_FRAME_BYTES {
        return refuse(format!("{size} bytes (at most {MAX_FRAME_BYTES})"));
    }
    let bytes = match std::fs::read(path) {
        Ok(b) => b,
        Err(e) => return refuse(e.to_string()),
    };
    raster::frame_on_grid(&bytes, &name, site, grid)
        .map(|(t, values)| (name.clone(), t, values))
        .map_err(|why| (name, why))
}

fn read_udp(socket: std::net::UdpSocket, tx: mpsc::Sender<Input>) {
    let mut buf = vec![0u8; 65_536];
    while let Ok(n) = socket.recv(&mut buf) {
        let mut s = Splitter::default();
        let lines = s.feed(&buf[..n]).into_iter().chain(s.end_line());
        for line in lines {
            if tx.blocking_send(Input::Line(line)).is_err() {
                return;
            }
        }
    }
}

fn read_stream(mut input: impl Read, tx: mpsc::Sender<Input>) {
    let (mut s, mut buf) = (Splitter::default(), vec![0u8; 8192]);
    while let Ok(n) = input.read(&mut buf) {
        if n == 0 {
            break;
        }
        for line in s.feed(&buf[..n]) {
            if tx.blocking_send(Input::Line(line)).is_err() {
                return;
            }
        }
    }
    if let Some(line) = s.end_line() {
        let _ = tx.blocking_send(Input::Line(line));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_stream_is_cut_into_lines_whatever_its_chunks() {
        let mut s = Splitter::default();
        assert_eq!(s.feed(b"{\"a\":1}\r\n{\"b\""), vec![Line::Text(b"{\"a\":1}".to_vec())]);
        assert_eq!(s.feed(b":2}\n\n  \n"), vec![Line::Text(b"{\"b\":2}".to_vec())]);
        let long = vec![b'x'; MAX_LINE + 10];
        let mut lines = s.feed(&long[..100]);
        lines.extend(s.feed(&long[100..]));
        lines.extend(s.feed(b"\nok\n"));
        assert_eq!(lines, vec![Line::Oversized(MAX_LINE + 10), Line::Text(b"ok".to_vec())]);
        assert!(s.held.is_empty(), "nothing of an oversized line is held");
        assert_eq!(s.feed(b"tail"), vec![]);
        assert_eq!(s.end_line(), Some(Line::Text(b"tail".to_vec())));
    }

    #[test]
    fn a_megabyte_line_is_never_held() {
        let mut s = Splitter::default();
        let chunk = vec![b'{'; 65_536];
        for _ in 0..16 {
            assert!(s.feed(&chunk).is_empty());
            assert!(s.held.capacity() <= 2 * MAX_LINE + 65_536);
        }
        assert_eq!(s.feed(b"\n"), vec![Line::Oversized(16 * 65_536)]);
    }
}
