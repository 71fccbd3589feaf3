//! The nodes' durable state: an embedded transactional store (redb, every commit durable when
//! it returns). A vehicle's outbox and the server's journal are both "messages by (vehicle,
//! seq)" plus a little metadata, so they share this one small layer.

use anyhow::Context as _;
use redb::{Database, Durability, ReadableDatabase, ReadableTable, TableDefinition};
use std::path::{Path, PathBuf};

/// `(vehicle, seq) -> encoded message`.
const MESSAGES: TableDefinition<(&str, u64), &[u8]> = TableDefinition::new("messages");
/// Small named values (a vehicle's state, the highest ack).
const META: TableDefinition<&str, &[u8]> = TableDefinition::new("meta");

pub struct Store {
    db: Database,
    path: PathBuf,
    /// Bytes of the messages held (kept in step with every commit).
    bytes: u64,
    count: u64,
}

fn err<E: std::fmt::Display>(e: E) -> anyhow::Error {
    anyhow::anyhow!("{e}")
}

impl Store {
    /// Open (or create) the store at `path`, and count what it holds.
    pub fn open(path: &Path) -> anyhow::Result<Self> {
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        }
        let db = Database::create(path).map_err(err).with_context(|| format!("opening the store {}", path.display()))?;
        let tx = db.begin_write().map_err(err)?;
        tx.open_table(MESSAGES).map_err(err)?;
        tx.open_table(META).map_err(err)?;
        tx.commit().map_err(err)?;
        let mut s = Self { db, path: path.to_path_buf(), bytes: 0, count: 0 };
        for (_, v) in s.messages()? {
            s.bytes += v.len() as u64;
            s.count += 1;
        }
        Ok(s)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Bytes and number of the messages held.
    pub fn size(&self) -> (u64, u64) {
        (self.bytes, self.count)
    }

    /// One durable transaction: these messages (replacing any under the same key) and these
    /// metadata values, all or nothing.
    pub fn commit(&mut self, messages: &[((&str, u64), &[u8])], meta: &[(&str, &[u8])]) -> anyhow::Result<()> {
        let mut tx = self.db.begin_write().map_err(err)?;
        tx.set_durability(Durability::Immediate).map_err(err)?;
        let (mut bytes, mut count) = (self.bytes, self.count);
        {
            let mut t = tx.open_table(MESSAGES).map_err(err)?;
            for (k, v) in messages {
                match t.insert(*k, *v).map_err(err)? {
                    Some(old) => bytes -= old.value().len() as u64,
                    None => count += 1,
                }
                bytes += v.len() as u64;
            }
            let mut m = tx.open_table(META).map_err(err)?;
            for (k, v) in meta {
                m.insert(*k, *v).map_err(err)?;
            }
        }
        tx.commit().map_err(err)?;
        (self.bytes, self.count) = (bytes, count);
        Ok(())
    }

    /// Drop `vehicle`'s messages with seq `<= seq`, and record `meta` in the same transaction.
    pub fn remove_through(&mut self, vehicle: &str, seq: u64, meta: &[(&str, &[u8])]) -> anyhow::Result<u64> {
        let mut tx = self.db.begin_write().map_err(err)?;
        tx.set_durability(Durability::Immediate).map_err(err)?;
        let (mut bytes, mut count, mut removed) = (self.bytes, self.count, 0);
        {
            let mut t = tx.open_table(MESSAGES).map_err(err)?;
            let gone = t.extract_from_if((vehicle, 0)..=(vehicle, seq), |_, _| true).map_err(err)?;
            for item in gone {
                let (_, v) = item.map_err(err)?;
                bytes -= v.value().len() as u64;
                count -= 1;
                removed += 1;
            }
            let mut m = tx.open_table(META).map_err(err)?;
            for (k, v) in meta {
                m.insert(*k, *v).map_err(err)?;
            }
        }
        tx.commit().map_err(err)?;
        (self.bytes, self.count) = (bytes, count);
        Ok(removed)
    }

    /// Every message, in key order.
    pub fn messages(&self) -> anyhow::Result<Vec<((String, u64), Vec<u8>)>> {
        let tx = self.db.begin_read().map_err(err)?;
        let t = tx.open_table(MESSAGES).map_err(err)?;
        let mut out = vec![];
        for item in t.iter().map_err(err)? {
            let (k, v) = item.map_err(err)?;
            let (id, seq) = k.value();
            out.push(((id.to_string(), seq), v.value().to_vec()));
        }
        Ok(out)
    }

    pub fn meta(&self, key: &str) -> anyhow::Result<Option<Vec<u8>>> {
        let tx = self.db.begin_read().map_err(err)?;
        let t = tx.open_table(META).map_err(err)?;
        Ok(t.get(key).map_err(err)?.map(|v| v.value().to_vec()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keeps_what_was_committed_across_reopening() {
        let dir = std::env::temp_dir().join(format!("hetfleet-store-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let path = dir.join("s.redb");
        {
            let mut s = Store::open(&path).unwrap();
            s.commit(&[(("boat-1", 0), b"aa"), (("boat-1", 1), b"bbb"), (("av-1", 0), b"c")], &[("state", b"x")]).unwrap();
            s.commit(&[(("boat-1", 1), b"BBBB")], &[]).unwrap();
            assert_eq!(s.size(), (7, 3));
            assert_eq!(s.remove_through("boat-1", 0, &[("acked", b"0")]).unwrap(), 1);
        }
        let s = Store::open(&path).unwrap();
        assert_eq!(s.size(), (5, 2));
        let m = s.messages().unwrap();
        assert_eq!(m, vec![(("av-1".to_string(), 0), b"c".to_vec()), (("boat-1".to_string(), 1), b"BBBB".to_vec())]);
        assert_eq!(s.meta("state").unwrap().as_deref(), Some(&b"x"[..]));
        assert_eq!(s.meta("acked").unwrap().as_deref(), Some(&b"0"[..]));
        assert_eq!(s.meta("nothing").unwrap(), None);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
