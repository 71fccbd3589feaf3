//! Owning child processes (`fleet up`'s nodes): one process group for all of them, stopped
//! together (SIGTERM, then SIGKILL after a grace period), each with a parent-death signal so a
//! `kill -9` of the parent does not orphan them; a child that dies is reported with its own last
//! error line; and the parent's own stop signals caught so it can stop them first.

use anyhow::Context;
use std::os::unix::process::{CommandExt, ExitStatusExt};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdout, Command, ExitStatus};
use std::sync::atomic::{AtomicI32, Ordering};
use std::time::{Duration, Instant};

/// How long the nodes get to stop on SIGTERM before SIGKILL.
const GRACE: Duration = Duration::from_secs(5);

/// A child that exited before it was asked to.
pub struct Exited {
    pub name: String,
    pub status: ExitStatus,
    pub log: PathBuf,
}

impl Exited {
    /// The error `fleet up` ends with: the child's own last line, and its exit status kept (a
    /// node refusing its input makes `up` exit 2 too).
    pub fn into_error(self, last_line: Option<String>, consequence: &str) -> anyhow::Error {
        let why = last_line.map_or_else(|| format!("see {}", self.log.display()), |l| format!("it said: {l}"));
        let e = anyhow::anyhow!(
            "{} exited ({}) and {consequence}; {why} (log: {})",
            self.name,
            describe(self.status),
            self.log.display()
        );
        if self.status.code() == Some(fleet_exit::BAD_INPUT) {
            fleet_exit::bad_input(e)
        } else {
            e
        }
    }
}

fn describe(s: ExitStatus) -> String {
    match (s.code(), s.signal()) {
        (Some(c), _) => format!("status {c}"),
        (None, Some(sig)) => format!("killed by signal {sig}"),
        _ => s.to_string(),
    }
}

/// The last non-empty line of a log (a node's final error), without the log's own prefix.
pub fn last_line(log: &Path) -> Option<String> {
    let text = std::fs::read_to_string(log).ok()?;
    text.lines()
        .rev()
        .map(str::trim)
        .find(|l| !l.is_empty())
        .map(str::to_string)
}

#[derive(Default)]
pub struct Supervisor {
    /// The process group every child joins (the first child's pid).
    group: Option<i32>,
    children: Vec<(String, Child, PathBuf)>,
    /// Children the mission does not depend on (the live view): their end is news, not failure.
    optional: Vec<String>,
    stopped: bool,
}

impl Supervisor {
    /// Start `cmd` as `name` in the group (its log at `log`, for reports); returns its stdout
    /// if piped.
    pub fn spawn(&mut self, name: &str, mut cmd: Command, log: PathBuf) -> anyhow::Result<Option<ChildStdout>> {
        cmd.process_group(self.group.unwrap_or(0));
        let parent = std::process::id() as libc::pid_t;
        // SAFETY: only async-signal-safe calls between fork and exec.
        unsafe {
            cmd.pre_exec(move || {
                // Die with `fleet up`, however it ends; and if it is already gone, do not start.
                if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM as libc::c_ulong) != 0 || libc::getppid() != parent
                {
                    libc::_exit(1);
                }
                Ok(())
            });
        }
        let mut child = cmd.spawn().with_context(|| format!("starting {name}"))?;
        self.group.get_or_insert(child.id() as i32);
        let out = child.stdout.take();
        self.children.push((name.to_string(), child, log));
        Ok(out)
    }

    /// The first child that has exited with a failure, or that exited at all while `up`
    /// still needs it (every node must run until the mission is finished).
    pub fn exited(&mut self) -> Option<Exited> {
        for (name, c, log) in self.children.iter_mut().filter(|(n, _, _)| !self.optional.contains(n)) {
            if let Ok(Some(status)) = c.try_wait() {
                if !status.success() {
                    return Some(Exited {
                        name: name.clone(),
                        status,
                        log: log.clone(),
                    });
                }
            }
        }
        None
    }

    /// Mark a child as one the mission does not depend on: [`Self::exited`] skips it.
    pub fn optional(&mut self, name: &str) {
        self.optional.push(name.to_string());
    }

    /// An optional child that has ended (any status), taken off the list so it is told once.
    pub fn optional_exited(&mut self) -> Option<Exited> {
        let i = self
            .children
            .iter_mut()
            .position(|(n, c, _)| self.optional.contains(n) && matches!(c.try_wait(), Ok(Some(_))))?;
        let (name, mut c, log) = self.children.remove(i);
        let status = c.wait().ok()?;
        Some(Exited { name, status, log })
    }

    /// Wait until every node except `except` has exited successfully.
    pub fn wait_nodes(&mut self, within: Duration, except: &[&str]) -> anyhow::Result<()> {
        let until = Instant::now() + within;
        for (name, c, log) in self
            .children
            .iter_mut()
            .filter(|(n, _, _)| !except.contains(&n.as_str()))
        {
            loop {
                match c.try_wait()? {
                    Some(s) if s.success() => break,
                    Some(s) => {
                        let why = last_line(log);
                        return Err(Exited {
                            name: name.clone(),
                            status: s,
                            log: log.clone(),
                        }
                        .into_error(why, "the run is incomplete"));
                    }
                    None if Instant::now() > until => {
                        anyhow::bail!("{name} did not exit after the mission (log: {})", log.display())
                    }
                    None => std::thread::sleep(Duration::from_millis(50)),
                }
            }
        }
        Ok(())
    }

    /// Stop the whole group: SIGTERM, then SIGKILL for what is left after the grace period;
    /// every child reaped.
    pub fn stop(&mut self) {
        if self.stopped {
            return;
        }
        self.stopped = true;
        let Some(group) = self.group else { return };
        // SAFETY: kill(2) on our own children's process group.
        unsafe { libc::kill(-group, libc::SIGTERM) };
        let until = Instant::now() + GRACE;
        while Instant::now() < until
            && self
                .children
                .iter_mut()
                .any(|(_, c, _)| matches!(c.try_wait(), Ok(None)))
        {
            std::thread::sleep(Duration::from_millis(20));
        }
        // SAFETY: as above; the group may be gone already (ESRCH is fine).
        unsafe { libc::kill(-group, libc::SIGKILL) };
        for (_, c, _) in &mut self.children {
            let _ = c.wait();
        }
    }
}

impl Drop for Supervisor {
    fn drop(&mut self) {
        self.stop();
    }
}

/// The stop signal received (SIGTERM, SIGINT or SIGHUP), if any.
static RECEIVED: AtomicI32 = AtomicI32::new(0);

extern "C" fn on_signal(sig: libc::c_int) {
    RECEIVED.store(sig, Ordering::SeqCst);
}

/// Stop signals, caught: polled with [`StopSignals::received`].
pub struct StopSignals;

impl StopSignals {
    pub fn received(&self) -> Option<i32> {
        match RECEIVED.load(Ordering::SeqCst) {
            0 => None,
            s => Some(s),
        }
    }
}

/// Catch SIGTERM, SIGINT and SIGHUP (instead of dying at once and leaving the nodes behind).
pub fn catch_stop_signals() -> anyhow::Result<StopSignals> {
    for sig in [libc::SIGTERM, libc::SIGINT, libc::SIGHUP] {
        // SAFETY: the handler only stores to an atomic (async-signal-safe).
        let previous = unsafe { libc::signal(sig, on_signal as *const () as libc::sighandler_t) };
        if previous == libc::SIG_ERR {
            anyhow::bail!("cannot catch signal {sig}");
        }
    }
    Ok(StopSignals)
}
