//! A vehicle's outbox: the batches the server has not acknowledged yet, on disk. Each batch is
//! committed (with the vehicle's state after it, in one transaction) before it is sent, re-sent
//! until the server's ack covers it, and removed only then. It survives `kill -9`. Past its
//! bound the vehicle stops sensing until acks make room: no batch is ever dropped.
//!
//! Pure bookkeeping over [`Store`]: no network and no clock of its own (callers pass `now`), so
//! the bound, the trimming by acks and the restore after a crash are tested here directly.

use crate::store::{Store, StoreError};
use serde::{de::DeserializeOwned, Serialize};
use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::time::{Duration, Instant};

#[derive(Debug, thiserror::Error)]
pub enum OutboxError {
    #[error(transparent)]
    Store(#[from] StoreError),
    /// The vehicle state stored beside the batches does not decode (a different build wrote it).
    #[error("{path}: the vehicle state in it is unreadable ({why})")]
    State { path: String, why: String },
}

impl OutboxError {
    /// Whether the file itself is bad (the operator's to deal with) rather than the machine.
    pub fn is_bad_file(&self) -> bool {
        match self {
            Self::Store(e) => e.is_bad_file(),
            Self::State { .. } => true,
        }
    }
}

pub struct Outbox {
    store: Store,
    id: String,
    acked: Option<u64>,
    /// Seqs held on disk, and when each was last sent (restored ones: never, so they go at once).
    held: BTreeSet<u64>,
    sent: BTreeMap<u64, Instant>,
    /// Bound on the bytes of the batches held.
    limit: u64,
    warned: bool,
}

const STATE: &str = "state";
const ACKED: &str = "acked";

impl Outbox {
    /// Open (or create) the outbox of vehicle `id` at `path`, bounded to `limit` bytes of batches.
    pub fn open(path: &Path, id: &str, limit: u64) -> Result<Self, OutboxError> {
        let store = Store::open(path)?;
        let acked = store
            .meta(ACKED)?
            .and_then(|b| String::from_utf8(b).ok())
            .and_then(|s| s.parse().ok());
        let held = store
            .messages()?
            .into_iter()
            .filter(|((v, _), _)| v == id)
            .map(|((_, seq), _)| seq)
            .collect();
        Ok(Self {
            store,
            id: id.into(),
            acked,
            held,
            sent: BTreeMap::new(),
            limit,
            warned: false,
        })
    }

    pub fn path(&self) -> &Path {
        self.store.path()
    }

    /// The vehicle state committed with the newest batch (none before the first).
    pub fn state<T: DeserializeOwned>(&self) -> Result<Option<T>, OutboxError> {
        let Some(b) = self.store.meta(STATE)? else {
            return Ok(None);
        };
        ciborium::from_reader(&b[..]).map(Some).map_err(|e| OutboxError::State {
            path: self.path().display().to_string(),
            why: e.to_string(),
        })
    }

    /// Commit batch `seq` and the state after it, in one transaction. Returns true the first
    /// time the outbox passes 80% of its bound (so the caller can warn once).
    pub fn commit<T: Serialize>(&mut self, seq: u64, bytes: &[u8], state: &T) -> Result<bool, OutboxError> {
        let mut st = vec![];
        ciborium::into_writer(state, &mut st).map_err(|e| OutboxError::State {
            path: self.path().display().to_string(),
            why: e.to_string(),
        })?;
        self.store
            .commit(&[((self.id.as_str(), seq), bytes)], &[(STATE, &st)])?;
        self.held.insert(seq);
        let nearly_full = self.store.size().0 * 5 >= self.limit * 4;
        let first = nearly_full && !self.warned;
        self.warned |= nearly_full;
        Ok(first)
    }

    /// The server acknowledged every batch up to `seq`: drop them. Returns whether it advanced.
    pub fn ack(&mut self, seq: u64) -> Result<bool, OutboxError> {
        if self.covers(seq) {
            return Ok(false);
        }
        self.store
            .remove_through(&self.id, seq, &[(ACKED, seq.to_string().as_bytes())])?;
        self.acked = Some(seq);
        self.held.retain(|&s| s > seq);
        self.sent.retain(|&s, _| s > seq);
        if self.store.size().0 * 5 < self.limit * 4 {
            self.warned = false;
        }
        Ok(true)
    }

    /// The highest acknowledged seq.
    pub fn acked(&self) -> Option<u64> {
        self.acked
    }

    pub fn covers(&self, seq: u64) -> bool {
        self.acked.is_some_and(|a| a >= seq)
    }

    /// Batches held.
    pub fn depth(&self) -> u64 {
        self.store.size().1
    }

    /// At its bound: sense nothing more until acks make room.
    pub fn full(&self) -> bool {
        self.store.size().0 >= self.limit
    }

    /// Seqs held, oldest first.
    pub fn held(&self) -> impl Iterator<Item = u64> + '_ {
        self.held.iter().copied()
    }

    /// The batches due at `now` (never sent since the start, or last sent `resend` ago or
    /// more), oldest first, marked as sent at `now`.
    pub fn due(&mut self, now: Instant, resend: Duration) -> Result<Vec<(u64, Vec<u8>)>, OutboxError> {
        let due: BTreeSet<u64> = self
            .held
            .iter()
            .copied()
            .filter(|s| {
                self.sent
                    .get(s)
                    .is_none_or(|&t| now.saturating_duration_since(t) >= resend)
            })
            .collect();
        if due.is_empty() {
            return Ok(vec![]);
        }
        let out: Vec<(u64, Vec<u8>)> = self
            .store
            .messages()?
            .into_iter()
            .filter(|((v, s), _)| v == &self.id && due.contains(s))
            .map(|((_, s), b)| (s, b))
            .collect();
        for (s, _) in &out {
            self.sent.insert(*s, now);
        }
        Ok(out)
    }

    /// Whether a batch that went out has waited `resend` or more at `now` (its ack is late:
    /// the resend's wait ran out, rather than the link coming back).
    pub fn overdue(&self, now: Instant, resend: Duration) -> bool {
        self.held
            .iter()
            .filter_map(|s| self.sent.get(s))
            .any(|&t| now.saturating_duration_since(t) >= resend)
    }

    /// Batch `seq` just went out (the first send, right after its commit).
    pub fn mark_sent(&mut self, seq: u64, now: Instant) {
        self.sent.insert(seq, now);
    }

    /// The link came back: the whole backlog is due now.
    pub fn resend_all(&mut self) {
        self.sent.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn path(name: &str) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!("hetfleet-outbox-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir.join("boat-1.redb")
    }

    #[test]
    fn the_bound_holds_sensing_until_acks_make_room_and_warns_once() {
        let mut o = Outbox::open(&path("bound"), "boat-1", 1000).unwrap();
        let batch = [7u8; 300];
        let warnings: Vec<bool> = (1..=3).map(|s| o.commit(s, &batch, &s).unwrap()).collect();
        // 600 bytes < 800 (80%); 900 bytes: the first warning; not full until 1000.
        assert_eq!(warnings, [false, false, true]);
        assert!(!o.full());
        assert!(!o.commit(4, &batch, &4u64).unwrap(), "warned once only");
        assert!(o.full(), "1200 bytes held over a bound of 1000");
        assert_eq!(o.depth(), 4);
        assert!(o.ack(2).unwrap());
        assert!(!o.full(), "600 bytes after the ack of 1 and 2");
        // Below 80% again: the next crossing warns again.
        assert!(o.commit(5, &batch, &5u64).unwrap());
    }

    #[test]
    fn acks_trim_exactly_what_they_cover_and_old_acks_change_nothing() {
        let mut o = Outbox::open(&path("acks"), "boat-1", 1 << 20).unwrap();
        for s in 1..=5u64 {
            o.commit(s, &[s as u8; 10], &s).unwrap();
        }
        assert!(o.ack(3).unwrap());
        assert_eq!(o.held().collect::<Vec<_>>(), [4, 5]);
        assert!(!o.ack(2).unwrap(), "an older ack is a no-op");
        assert!(!o.ack(3).unwrap(), "a repeated ack is a no-op");
        assert_eq!(o.held().collect::<Vec<_>>(), [4, 5]);
        assert!(o.covers(3) && !o.covers(4));
        let due = o.due(Instant::now(), Duration::from_secs(1)).unwrap();
        assert_eq!(due, vec![(4, vec![4u8; 10]), (5, vec![5u8; 10])]);
        assert!(o.ack(5).unwrap());
        assert_eq!(o.depth(), 0);
    }

    #[test]
    fn resends_are_due_after_the_interval_or_when_the_link_returns() {
        let mut o = Outbox::open(&path("due"), "boat-1", 1 << 20).unwrap();
        let t0 = Instant::now();
        o.commit(1, b"one", &1u64).unwrap();
        o.mark_sent(1, t0);
        let every = Duration::from_millis(500);
        assert!(o.due(t0 + Duration::from_millis(100), every).unwrap().is_empty());
        assert_eq!(o.due(t0 + every, every).unwrap().len(), 1);
        assert!(o.due(t0 + every, every).unwrap().is_empty(), "marked as sent by due()");
        o.resend_all();
        assert_eq!(
            o.due(t0 + every, every).unwrap().len(),
            1,
            "link back: everything at once"
        );
    }

    #[test]
    fn a_restart_restores_the_held_batches_the_ack_and_the_state() {
        let p = path("restore");
        {
            let mut o = Outbox::open(&p, "boat-1", 1 << 20).unwrap();
            for s in 1..=4u64 {
                o.commit(s, &[s as u8; 8], &("state after", s)).unwrap();
            }
            o.ack(2).unwrap();
            o.mark_sent(3, Instant::now());
            // Dropped without a goodbye: what a crash after the last commit leaves.
        }
        let mut o = Outbox::open(&p, "boat-1", 1 << 20).unwrap();
        assert_eq!(o.acked(), Some(2));
        assert_eq!(o.held().collect::<Vec<_>>(), [3, 4]);
        assert_eq!(
            o.state::<(String, u64)>().unwrap(),
            Some(("state after".to_string(), 4))
        );
        // Nothing was sent by this process yet: both go at once.
        assert_eq!(o.due(Instant::now(), Duration::from_secs(3600)).unwrap().len(), 2);
    }

    #[test]
    fn a_fresh_outbox_has_no_state_and_a_foreign_state_is_a_bad_file() {
        let p = path("state");
        let mut o = Outbox::open(&p, "boat-1", 1 << 20).unwrap();
        assert_eq!(o.state::<u64>().unwrap(), None);
        o.commit(1, b"x", &"not a number").unwrap();
        let e = o.state::<u64>().unwrap_err();
        assert!(e.is_bad_file(), "{e}");
        assert!(
            e.to_string().contains("boat-1.redb") && e.to_string().contains("unreadable"),
            "{e}"
        );
    }
}
