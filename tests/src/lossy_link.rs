//! A lossy radio link between this host and another network namespace, for kernels without
//! `netem` (these have no `sch_netem`, no tc actions, no iptables).
//!
//! Instead of a veth pair, each end of the link is a TUN device: one here, one inside the
//! other namespace (opened from a thread that has joined it with `setns`, since a TUN device
//! belongs to the namespace its file was opened in). Two relay threads carry the IP packets
//! between the two devices, dropping a seeded fraction of them and delaying the rest by a
//! random time (so later packets overtake earlier ones). The kernel's TCP on both sides sees
//! real loss and reordering, retransmits and backs off, exactly as over a netem qdisc.

use rand::{RngExt, SeedableRng};
use std::collections::BinaryHeap;
use std::fs::File;
use std::io;
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// How a link is degraded, each way.
#[derive(Clone, Copy, Debug)]
pub struct Degradation {
    /// Fraction of packets dropped.
    pub loss: f64,
    /// Every packet kept is delayed by `delay_ms` plus a uniform `0..=jitter_ms`.
    pub delay_ms: u64,
    pub jitter_ms: u64,
    pub seed: u64,
}

/// Packets carried and dropped on a link (both directions).
#[derive(Default, Debug)]
pub struct LinkCounts {
    pub passed: AtomicU64,
    pub dropped: AtomicU64,
    /// Packets delivered after one that was read later (reordered).
    pub overtaken: AtomicU64,
}

/// Another host behind a lossy link: a network namespace reached through a pair of TUN devices
/// and two relay threads. Torn down when dropped.
pub struct LossyHost {
    pub ns: String,
    /// This host's address on the link, and the other host's.
    pub here: String,
    pub there: String,
    pub counts: Arc<LinkCounts>,
    stop: Arc<AtomicBool>,
    relays: Vec<std::thread::JoinHandle<()>>,
}

impl LossyHost {
    pub fn new(tag: u32, how: Degradation) -> io::Result<Self> {
        let x = (std::process::id() + tag) % 200 + 20;
        let ns = format!("hfl{x}");
        let (here, there) = (format!("10.79.{x}.1"), format!("10.79.{x}.2"));
        let (near_name, far_name) = (format!("{ns}a"), format!("{ns}b"));
        super::sh(&["ip", "netns", "add", &ns]);
        let near = Arc::new(open_tun(&near_name)?);
        let far = Arc::new(open_tun_in(&ns, &far_name)?);
        super::sh(&["ip", "addr", "add", &format!("{here}/24"), "dev", &near_name]);
        super::sh(&["ip", "link", "set", &near_name, "up"]);
        let far_addr = format!("{there}/24");
        for cmd in [
            ["addr", "add", &far_addr, "dev", &far_name].as_slice(),
            &["link", "set", &far_name, "up"],
            &["link", "set", "lo", "up"],
        ] {
            super::sh(&[["ip", "-n", ns.as_str()].as_slice(), cmd].concat());
        }
        let (stop, counts) = (Arc::new(AtomicBool::new(false)), Arc::new(LinkCounts::default()));
        let relays = [(near.clone(), far.clone(), 0), (far, near, 1)]
            .into_iter()
            .map(|(from, to, dir)| {
                let (stop, counts) = (stop.clone(), counts.clone());
                let how = Degradation {
                    seed: how.seed * 2 + dir,
                    ..how
                };
                std::thread::spawn(move || relay(&from, &to, how, &stop, &counts))
            })
            .collect();
        Ok(LossyHost {
            ns,
            here,
            there,
            counts,
            stop,
            relays,
        })
    }

    /// (passed, dropped, overtaken) so far.
    pub fn totals(&self) -> (u64, u64, u64) {
        let c = &self.counts;
        (
            c.passed.load(Ordering::Relaxed),
            c.dropped.load(Ordering::Relaxed),
            c.overtaken.load(Ordering::Relaxed),
        )
    }
}

impl Drop for LossyHost {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        for r in self.relays.drain(..) {
            let _ = r.join();
        }
        // The devices went with their files (the relays held the last references).
        let _ = std::process::Command::new("ip")
            .args(["netns", "del", &self.ns])
            .output();
    }
}

/// Open (and create) TUN device `name` in this thread's network namespace: IP packets, no
/// packet-information header.
fn open_tun(name: &str) -> io::Result<OwnedFd> {
    // SAFETY: a plain open(2) of a constant, NUL-terminated path.
    let raw = unsafe { libc::open(c"/dev/net/tun".as_ptr(), libc::O_RDWR | libc::O_CLOEXEC) };
    if raw < 0 {
        return Err(io::Error::last_os_error());
    }
    // SAFETY: `raw` is a file descriptor we just opened and own.
    let fd = unsafe { OwnedFd::from_raw_fd(raw) };
    // SAFETY: ifreq is plain old data; all-zero is a valid value.
    let mut ifr: libc::ifreq = unsafe { std::mem::zeroed() };
    if name.len() >= ifr.ifr_name.len() {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            format!("interface name {name:?} too long"),
        ));
    }
    for (d, s) in ifr.ifr_name.iter_mut().zip(name.bytes()) {
        *d = s as libc::c_char;
    }
    ifr.ifr_ifru.ifru_flags = (libc::IFF_TUN | libc::IFF_NO_PI) as libc::c_short;
    // SAFETY: TUNSETIFF reads (and may write) one ifreq, which outlives the call.
    if unsafe { libc::ioctl(fd.as_raw_fd(), libc::TUNSETIFF, &mut ifr as *mut libc::ifreq) } < 0 {
        return Err(io::Error::last_os_error());
    }
    Ok(fd)
}

/// [`open_tun`] inside network namespace `ns` (made by `ip netns add`): from a short-lived
/// thread that joins it, since `setns` changes only the calling thread.
fn open_tun_in(ns: &str, name: &str) -> io::Result<OwnedFd> {
    let (path, name) = (format!("/var/run/netns/{ns}"), name.to_string());
    std::thread::spawn(move || {
        let nsf = File::open(&path)?;
        // SAFETY: setns(2) on a namespace file we hold open; affects only this thread.
        if unsafe { libc::setns(nsf.as_raw_fd(), libc::CLONE_NEWNET) } != 0 {
            return Err(io::Error::last_os_error());
        }
        open_tun(&name)
    })
    .join()
    .map_err(|_| io::Error::other("the namespace thread panicked"))?
}

/// A packet waiting for its delivery time (earliest first in the heap).
struct Delayed {
    due: Instant,
    order: u64,
    bytes: Vec<u8>,
}

impl PartialEq for Delayed {
    fn eq(&self, o: &Self) -> bool {
        (self.due, self.order) == (o.due, o.order)
    }
}
impl Eq for Delayed {}
impl PartialOrd for Delayed {
    fn partial_cmp(&self, o: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(o))
    }
}
impl Ord for Delayed {
    fn cmp(&self, o: &Self) -> std::cmp::Ordering {
        (o.due, o.order).cmp(&(self.due, self.order))
    }
}

/// Carry packets `from` -> `to` until `stop`: drop some, delay the rest.
fn relay(from: &OwnedFd, to: &OwnedFd, how: Degradation, stop: &AtomicBool, counts: &LinkCounts) {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(how.seed);
    let mut queue = BinaryHeap::<Delayed>::new();
    let (mut read_order, mut last_sent) = (0u64, None::<u64>);
    let mut buf = vec![0u8; 65536];
    while !stop.load(Ordering::Relaxed) {
        let now = Instant::now();
        while queue.peek().is_some_and(|p| p.due <= now) {
            let p = queue.pop().expect("peeked");
            if last_sent.is_some_and(|l| l > p.order) {
                counts.overtaken.fetch_add(1, Ordering::Relaxed);
            }
            last_sent = Some(last_sent.map_or(p.order, |l| l.max(p.order)));
            // SAFETY: write(2) of an owned buffer to a descriptor we hold.
            unsafe { libc::write(to.as_raw_fd(), p.bytes.as_ptr().cast(), p.bytes.len()) };
        }
        let wait = queue
            .peek()
            .map_or(Duration::from_millis(50), |p| p.due.saturating_duration_since(now))
            .min(Duration::from_millis(50));
        let mut pfd = libc::pollfd {
            fd: from.as_raw_fd(),
            events: libc::POLLIN,
            revents: 0,
        };
        // SAFETY: poll(2) on one pollfd that lives on this stack frame.
        let ready = unsafe { libc::poll(&mut pfd, 1, wait.as_millis().max(1) as libc::c_int) };
        if ready <= 0 || pfd.revents & libc::POLLIN == 0 {
            continue;
        }
        // SAFETY: read(2) into a buffer we own, at most its length.
        let n = unsafe { libc::read(from.as_raw_fd(), buf.as_mut_ptr().cast(), buf.len()) };
        if n <= 0 {
            continue;
        }
        if rng.random::<f64>() < how.loss {
            counts.dropped.fetch_add(1, Ordering::Relaxed);
            continue;
        }
        counts.passed.fetch_add(1, Ordering::Relaxed);
        let delay = how.delay_ms + rng.random_range(0..=how.jitter_ms);
        queue.push(Delayed {
            due: Instant::now() + Duration::from_millis(delay),
            order: read_order,
            bytes: buf[..n as usize].to_vec(),
        });
        read_order += 1;
    }
}
