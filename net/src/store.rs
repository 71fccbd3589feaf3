//! The nodes' durable state: an embedded transactional store (redb, every commit durable when
//! it returns). A vehicle's outbox and the server's journal are both "messages by (vehicle,
//! seq)" plus a little metadata, so they share this one small layer.
//!
//! **Integrity.** redb checks its own commit slots, not the values it holds, and a damaged
//! file can make it panic. So every value is sealed with a CRC-32 over what it is (table, key
//! and bytes), checked on every read; and a file is checked whole before it is opened for
//! writing, on a copy and in a child process (a damaged page size can make redb ask for
//! terabytes, and the failed allocation aborts whoever asked). A damaged file is refused with
//! one error naming it and what is wrong, and is never changed by the refusal (opening a file
//! for writing may repair it). Each table's census (count, bytes, sum of checksums), committed
//! with every change, catches damage that leaves every remaining record sound but drops some,
//! or brings back an older page.

use redb::{Database, Durability, ReadableDatabase, ReadableTable, TableDefinition, TableHandle};
use std::path::{Path, PathBuf};

/// `(vehicle, seq) -> sealed message`.
const MESSAGES: TableDefinition<(&str, u64), &[u8]> = TableDefinition::new(TABLES[0]);
/// Small named values (a vehicle's state, the highest ack, the server's decisions), sealed.
const META: TableDefinition<&str, &[u8]> = TableDefinition::new(TABLES[1]);

/// `table name -> sealed census` of the two tables above (see [`Census`]).
const CENSUS: TableDefinition<&str, &[u8]> = TableDefinition::new(TABLES[2]);

/// A sealed value: `MAGIC`, then the CRC-32 (little-endian) of the table tag, the key and the
/// payload, then the payload.
const MAGIC: [u8; 3] = *b"hf\x01";
const HEADER: usize = MAGIC.len() + 4;

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The file cannot be trusted: a record fails its checksum, or the store itself is broken.
    #[error("{} is damaged: {what} (the file was left as it is)", path.display())]
    Damaged { path: PathBuf, what: String },
    #[error("{} is empty (0 bytes): it was created but never written, or cut off (the file was left as it \
        is)", path.display())]
    Empty { path: PathBuf },
    #[error("{} is in use by another process: one node per state file", path.display())]
    InUse { path: PathBuf },
    #[error("{}: {source}", path.display())]
    Io { path: PathBuf, source: std::io::Error },
    /// The store failed at run time (a full disk, an I/O error under a commit).
    #[error("{}: {what}", path.display())]
    Failed { path: PathBuf, what: String },
}

impl StoreError {
    /// Whether the file itself is bad (damaged or empty), as opposed to the machine failing.
    pub fn is_bad_file(&self) -> bool {
        matches!(self, Self::Damaged { .. } | Self::Empty { .. })
    }
}

type Result<T> = std::result::Result<T, StoreError>;

/// A message as stored: its key `(vehicle, seq)` and its bytes.
pub type Record = ((String, u64), Vec<u8>);

fn checksum(table: u8, key: &[u8], payload: &[u8]) -> u32 {
    let mut h = crc32fast::Hasher::new();
    h.update(&[table]);
    h.update(&(key.len() as u32).to_le_bytes());
    h.update(key);
    h.update(payload);
    h.finalize()
}

fn message_key(vehicle: &str, seq: u64) -> Vec<u8> {
    let mut k = vehicle.as_bytes().to_vec();
    k.push(0);
    k.extend_from_slice(&seq.to_le_bytes());
    k
}

fn seal(table: u8, key: &[u8], payload: &[u8]) -> Vec<u8> {
    let mut v = Vec::with_capacity(HEADER + payload.len());
    v.extend_from_slice(&MAGIC);
    v.extend_from_slice(&checksum(table, key, payload).to_le_bytes());
    v.extend_from_slice(payload);
    v
}

/// The checksum a sealed value carries (0 for one too short to carry any).
fn sealed_checksum(sealed: &[u8]) -> u32 {
    sealed
        .get(MAGIC.len()..HEADER)
        .map_or(0, |b| u32::from_le_bytes(b.try_into().expect("4 bytes")))
}

/// What a table holds, in sum: its records, their payload bytes and the sum of their checksums.
///
/// Why: redb checks its pages' checksums only after a crash, so one flipped bit in a cleanly
/// closed file can drop a table's records (they read as none: found by the fuzz test) or bring
/// back an older version of a page, and every record left still passes its own checksum. The
/// census is committed in the same transaction as every change, and a file whose tables
/// disagree with it is refused. Wrapping arithmetic: a census is compared, never trusted.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct Census {
    count: u64,
    bytes: u64,
    checksums: u64,
}

impl Census {
    /// Count one record of `payload` bytes and this checksum in (`+1`) or out (`-1`).
    fn tally(&mut self, sign: i64, payload: usize, checksum: u32) {
        self.count = self.count.wrapping_add_signed(sign);
        self.bytes = self.bytes.wrapping_add((payload as u64).wrapping_mul(sign as u64));
        self.checksums = self
            .checksums
            .wrapping_add(u64::from(checksum).wrapping_mul(sign as u64));
    }

    fn add(&mut self, sealed: &[u8]) {
        self.tally(1, sealed.len().saturating_sub(HEADER), sealed_checksum(sealed));
    }

    fn remove(&mut self, sealed: &[u8]) {
        self.tally(-1, sealed.len().saturating_sub(HEADER), sealed_checksum(sealed));
    }

    /// The census of records read back as `(key, payload)` (each already checked).
    fn of<K: AsRef<[u8]>, P: AsRef<[u8]>>(table: u8, records: impl Iterator<Item = (K, P)>) -> Self {
        let mut c = Self::default();
        for (key, payload) in records {
            let (key, payload) = (key.as_ref(), payload.as_ref());
            c.tally(1, payload.len(), checksum(table, key, payload));
        }
        c
    }

    fn to_bytes(self) -> Vec<u8> {
        [self.count, self.bytes, self.checksums]
            .iter()
            .flat_map(|x| x.to_le_bytes())
            .collect()
    }

    fn from_bytes(b: &[u8]) -> Option<Self> {
        let word = |i: usize| Some(u64::from_le_bytes(b.get(8 * i..8 * i + 8)?.try_into().ok()?));
        (b.len() == 24).then_some(())?;
        Some(Self {
            count: word(0)?,
            bytes: word(1)?,
            checksums: word(2)?,
        })
    }
}

/// The payload of a sealed value, or what is wrong with it.
fn unseal<'a>(table: u8, key: &[u8], sealed: &'a [u8]) -> std::result::Result<&'a [u8], &'static str> {
    if sealed.len() < HEADER || sealed[..MAGIC.len()] != MAGIC {
        return Err("has no integrity header (written by another program or an older hetfleet)");
    }
    let want = u32::from_le_bytes(sealed[MAGIC.len()..HEADER].try_into().expect("4 bytes"));
    let payload = &sealed[HEADER..];
    if checksum(table, key, payload) != want {
        return Err("fails its checksum");
    }
    Ok(payload)
}

/// Run `f`, turning a panic inside the store into an error (without the default hook's
/// report on stderr: the error says it in one line).
fn contained<T>(f: impl FnOnce() -> T) -> std::result::Result<T, String> {
    let hook = std::panic::take_hook();
    std::panic::set_hook(Box::new(|_| {}));
    let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(f));
    std::panic::set_hook(hook);
    r.map_err(|p| {
        p.downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| p.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "the store panicked".into())
    })
}

pub struct Store {
    db: Database,
    path: PathBuf,
    /// The census of each table (kept in step with every commit).
    messages: Census,
    meta: Census,
}

impl Store {
    /// Open (or create) the store at `path`, after checking every record of an existing file
    /// (on a copy: a damaged file is refused and left as it is).
    pub fn open(path: &Path) -> Result<Self> {
        let io = |source| StoreError::Io {
            path: path.to_path_buf(),
            source,
        };
        match std::fs::metadata(path) {
            Ok(m) if m.len() == 0 => return Err(StoreError::Empty { path: path.into() }),
            Ok(_) => verify_copy(path)?,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
                    std::fs::create_dir_all(dir).map_err(|source| StoreError::Io {
                        path: dir.into(),
                        source,
                    })?;
                }
            }
            Err(e) => return Err(io(e)),
        }
        let existing = path.exists();
        let (db, [messages, meta]) = open_checked(path, existing)?;
        Ok(Self {
            db,
            path: path.to_path_buf(),
            messages,
            meta,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Bytes and number of the messages held.
    pub fn size(&self) -> (u64, u64) {
        (self.messages.bytes, self.messages.count)
    }

    fn failed(&self, e: &dyn std::fmt::Display) -> StoreError {
        StoreError::Failed {
            path: self.path.clone(),
            what: e.to_string(),
        }
    }

    /// One durable transaction: these messages (replacing any under the same key) and these
    /// metadata values, all or nothing.
    pub fn commit(&mut self, messages: &[((&str, u64), &[u8])], meta: &[(&str, &[u8])]) -> Result<()> {
        let tx = self.begin().map_err(|e| self.failed(&e))?;
        let mut census = [self.messages, self.meta];
        {
            let mut t = tx.open_table(MESSAGES).map_err(|e| self.failed(&e))?;
            for ((vehicle, seq), v) in messages {
                let sealed = seal(b'M', &message_key(vehicle, *seq), v);
                if let Some(old) = t
                    .insert((*vehicle, *seq), sealed.as_slice())
                    .map_err(|e| self.failed(&e))?
                {
                    census[0].remove(old.value());
                }
                census[0].add(&sealed);
            }
        }
        self.finish(tx, meta, census)
    }

    fn begin(&self) -> std::result::Result<redb::WriteTransaction, redb::Error> {
        let mut tx = self.db.begin_write()?;
        tx.set_durability(Durability::Immediate)?;
        Ok(tx)
    }

    /// Write `meta` and the census into `tx` (whose messages `census[0]` counts), and commit.
    fn finish(&mut self, tx: redb::WriteTransaction, meta: &[(&str, &[u8])], mut census: [Census; 2]) -> Result<()> {
        {
            let mut m = tx.open_table(META).map_err(|e| self.failed(&e))?;
            for (k, v) in meta {
                let sealed = seal(b'T', k.as_bytes(), v);
                if let Some(old) = m.insert(*k, sealed.as_slice()).map_err(|e| self.failed(&e))? {
                    census[1].remove(old.value());
                }
                census[1].add(&sealed);
            }
        }
        write_census(&tx, census).map_err(|e| self.failed(&e))?;
        tx.commit().map_err(|e| self.failed(&e))?;
        [self.messages, self.meta] = census;
        Ok(())
    }

    /// Drop `vehicle`'s messages with seq `<= seq`, and record `meta` in the same transaction.
    pub fn remove_through(&mut self, vehicle: &str, seq: u64, meta: &[(&str, &[u8])]) -> Result<u64> {
        let tx = self.begin().map_err(|e| self.failed(&e))?;
        let mut census = [self.messages, self.meta];
        let mut removed = 0;
        {
            let mut t = tx.open_table(MESSAGES).map_err(|e| self.failed(&e))?;
            let gone = t
                .extract_from_if((vehicle, 0)..=(vehicle, seq), |_, _| true)
                .map_err(|e| self.failed(&e))?;
            for item in gone {
                let (_, v) = item.map_err(|e| self.failed(&e))?;
                census[0].remove(v.value());
                removed += 1;
            }
        }
        self.finish(tx, meta, census)?;
        Ok(removed)
    }

    /// Every message, in key order, each checked against its checksum.
    pub fn messages(&self) -> Result<Vec<Record>> {
        read_messages(&self.db, &self.path)
    }

    /// A metadata value, checked against its checksum.
    pub fn meta(&self, key: &str) -> Result<Option<Vec<u8>>> {
        let tx = self.db.begin_read().map_err(|e| self.failed(&e))?;
        let t = tx.open_table(META).map_err(|e| self.failed(&e))?;
        let Some(v) = t.get(key).map_err(|e| self.failed(&e))? else {
            return Ok(None);
        };
        let sealed = v.value();
        unseal(b'T', key.as_bytes(), sealed)
            .map(|p| Some(p.to_vec()))
            .map_err(|what| damaged(&self.path, format!("metadata {key:?} {what}")))
    }

    /// Every metadata value whose key starts with `prefix`, in key order, each checked.
    pub fn meta_with_prefix(&self, prefix: &str) -> Result<Vec<(String, Vec<u8>)>> {
        read_meta(&self.db, &self.path, prefix)
    }
}

fn damaged(path: &Path, what: String) -> StoreError {
    StoreError::Damaged {
        path: path.into(),
        what,
    }
}

fn read_messages(db: &impl ReadableDatabase, path: &Path) -> Result<Vec<Record>> {
    let bad = |e: &dyn std::fmt::Display| damaged(path, e.to_string());
    let tx = db.begin_read().map_err(|e| bad(&e))?;
    let t = tx.open_table(MESSAGES).map_err(|e| bad(&e))?;
    let mut out = vec![];
    for item in t.iter().map_err(|e| bad(&e))? {
        let (k, v) = item.map_err(|e| bad(&e))?;
        let (id, seq) = k.value();
        let payload = unseal(b'M', &message_key(id, seq), v.value())
            .map_err(|what| damaged(path, format!("record ({id}, {seq}) {what}")))?;
        out.push(((id.to_string(), seq), payload.to_vec()));
    }
    Ok(out)
}

fn read_meta(db: &impl ReadableDatabase, path: &Path, prefix: &str) -> Result<Vec<(String, Vec<u8>)>> {
    let bad = |e: &dyn std::fmt::Display| damaged(path, e.to_string());
    let tx = db.begin_read().map_err(|e| bad(&e))?;
    let t = tx.open_table(META).map_err(|e| bad(&e))?;
    let mut out = vec![];
    for item in t.range(prefix..).map_err(|e| bad(&e))? {
        let (k, v) = item.map_err(|e| bad(&e))?;
        let key = k.value();
        if !key.starts_with(prefix) {
            break;
        }
        let payload = unseal(b'T', key.as_bytes(), v.value())
            .map_err(|what| damaged(path, format!("metadata {key:?} {what}")))?;
        out.push((key.to_string(), payload.to_vec()));
    }
    Ok(out)
}

/// The tables of a store: the two that hold records, and their census.
const TABLES: [&str; 3] = ["messages", "meta", "census"];

/// Open `path` for writing (creating the tables of a new file; an existing file must have
/// exactly ours: a damaged table name would otherwise read as a missing table, created empty),
/// read every record back (checked) and hold it to the census; a panic inside the store is an
/// error. Returns the census of the messages and of the metadata.
fn open_checked(path: &Path, existing: bool) -> Result<(Database, [Census; 2])> {
    let opened = contained(|| -> Result<(Database, [Census; 2])> {
        let db = create(path)?;
        let bad = |e: &dyn std::fmt::Display| damaged(path, e.to_string());
        if existing {
            check_tables(&db, path)?;
        }
        let tx = db.begin_write().map_err(|e| bad(&e))?;
        tx.open_table(MESSAGES).map_err(|e| bad(&e))?;
        tx.open_table(META).map_err(|e| bad(&e))?;
        if !existing {
            write_census(&tx, [Census::default(); 2]).map_err(|e| bad(&e))?;
        }
        tx.commit().map_err(|e| bad(&e))?;
        let messages = read_messages(&db, path)?;
        let meta = read_meta(&db, path, "")?;
        let found = [
            Census::of(b'M', messages.iter().map(|((id, seq), p)| (message_key(id, *seq), p))),
            Census::of(b'T', meta.iter().map(|(k, p)| (k.as_bytes(), p))),
        ];
        check_census(&db, path, found)?;
        Ok((db, found))
    });
    opened.map_err(|panic| damaged(path, format!("the store could not read it ({panic})")))?
}

/// Open or create the database, naming damage as such.
fn create(path: &Path) -> Result<Database> {
    Database::create(path).map_err(|e| match e {
        redb::DatabaseError::DatabaseAlreadyOpen => StoreError::InUse { path: path.into() },
        // redb reports some damage as I/O errors of these kinds.
        redb::DatabaseError::Storage(redb::StorageError::Io(source))
            if matches!(
                source.kind(),
                std::io::ErrorKind::InvalidData | std::io::ErrorKind::UnexpectedEof
            ) =>
        {
            damaged(path, source.to_string())
        }
        redb::DatabaseError::Storage(redb::StorageError::Io(source)) => StoreError::Io {
            path: path.into(),
            source,
        },
        other => damaged(path, other.to_string()),
    })
}

/// An existing file holds exactly our tables.
fn check_tables(db: &Database, path: &Path) -> Result<()> {
    let bad = |e: &dyn std::fmt::Display| damaged(path, e.to_string());
    let tables: Vec<String> = db
        .begin_read()
        .map_err(|e| bad(&e))?
        .list_tables()
        .map_err(|e| bad(&e))?
        .map(|t| t.name().to_string())
        .collect();
    for want in TABLES {
        if !tables.iter().any(|t| t == want) {
            let older = if want == CENSUS.name() {
                " (an older hetfleet wrote none)"
            } else {
                ""
            };
            return Err(damaged(
                path,
                format!("its `{want}` table is missing{older} (tables: {tables:?})"),
            ));
        }
    }
    if let Some(other) = tables.iter().find(|t| !TABLES.contains(&t.as_str())) {
        return Err(damaged(
            path,
            format!("it has a table this store never writes, `{other}`"),
        ));
    }
    Ok(())
}

fn write_census(tx: &redb::WriteTransaction, census: [Census; 2]) -> std::result::Result<(), redb::Error> {
    let mut t = tx.open_table(CENSUS)?;
    for (name, c) in TABLES[..2].iter().zip(census) {
        t.insert(*name, seal(b'C', name.as_bytes(), &c.to_bytes()).as_slice())?;
    }
    Ok(())
}

/// The tables hold what the census says was committed.
fn check_census(db: &Database, path: &Path, found: [Census; 2]) -> Result<()> {
    let bad = |e: &dyn std::fmt::Display| damaged(path, e.to_string());
    let tx = db.begin_read().map_err(|e| bad(&e))?;
    let t = tx.open_table(CENSUS).map_err(|e| bad(&e))?;
    for (name, found) in TABLES[..2].iter().zip(found) {
        let sealed = t.get(*name).map_err(|e| bad(&e))?;
        let committed = sealed
            .as_ref()
            .and_then(|v| unseal(b'C', name.as_bytes(), v.value()).ok())
            .and_then(Census::from_bytes)
            .ok_or_else(|| damaged(path, format!("the census of its `{name}` table is missing or damaged")))?;
        if committed != found {
            let other = if committed.count == found.count {
                " (other records than those)"
            } else {
                ""
            };
            return Err(damaged(
                path,
                format!(
                    "its `{name}` table holds {} records ({} bytes) where {} ({} bytes) were committed{other}",
                    found.count, found.bytes, committed.count, committed.bytes
                ),
            ));
        }
    }
    Ok(())
}

/// Check an existing file whole, on a copy beside it (removed after), so the file itself is
/// opened for writing only once it is known to be sound.
fn verify_copy(path: &Path) -> Result<()> {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let copy = path.with_file_name(format!(".{name}.check-{}", std::process::id()));
    std::fs::copy(path, &copy).map_err(|source| StoreError::Io {
        path: path.into(),
        source,
    })?;
    // Closing it too: redb writes its allocator state when a database is dropped, and a
    // damaged one can panic there.
    let checked = in_child(&copy, || {
        contained(|| open_checked(&copy, true).map(drop))
            .unwrap_or_else(|panic| Err(damaged(&copy, format!("the store could not close it ({panic})"))))
    });
    let _ = std::fs::remove_file(&copy);
    // Errors name the file the operator gave, not the copy.
    checked.map_err(|e| match e {
        StoreError::Damaged { what, .. } => damaged(path, what),
        StoreError::Io { source, .. } => StoreError::Io {
            path: path.into(),
            source,
        },
        StoreError::Failed { what, .. } => StoreError::Failed {
            path: path.into(),
            what,
        },
        other => other,
    })
}

/// How long a check may take before it is given up (a store of a few hundred MB reads in
/// seconds; this only bounds a check that cannot finish).
const CHECK_LIMIT: std::time::Duration = std::time::Duration::from_secs(300);

/// Run `check` in a forked child and return its result. redb allocates a page as large as the
/// page number on disk says (up to 8 TiB) before it checks anything, and a failed allocation
/// aborts the process, past any `catch_unwind`: one damaged byte would take the node down.
/// In a child, that abort is only a refusal. The child runs nothing but the check and leaves
/// by `_exit` (no destructors, no flushing of the parent's buffers).
///
/// Long because the fork, the child's work and the parent's reading of its verdict must be read
/// together to see that an abort in the child is a refusal.
fn in_child(path: &Path, check: impl FnOnce() -> Result<()>) -> Result<()> {
    use std::io::{Read, Write};
    use std::os::fd::FromRawFd;
    let failed = |what: String| StoreError::Failed {
        path: path.into(),
        what,
    };
    let mut fds = [0; 2];
    // SAFETY: `fds` has room for the two descriptors pipe writes.
    if unsafe { libc::pipe2(fds.as_mut_ptr(), libc::O_CLOEXEC) } != 0 {
        return Err(failed(format!(
            "cannot check it: pipe: {}",
            std::io::Error::last_os_error()
        )));
    }
    // SAFETY: the child only runs `check` (file I/O and allocation) and `_exit`s.
    let pid = unsafe { libc::fork() };
    if pid < 0 {
        let e = std::io::Error::last_os_error();
        // SAFETY: both descriptors are ours and open.
        unsafe { (libc::close(fds[0]), libc::close(fds[1])) };
        return Err(failed(format!("cannot check it: fork: {e}")));
    }
    if pid == 0 {
        // The child's stderr is silenced: its abort message would read as the node's own.
        // SAFETY: plain descriptor calls on a path literal.
        unsafe {
            let null = libc::open(c"/dev/null".as_ptr(), libc::O_WRONLY);
            if null >= 0 {
                libc::dup2(null, 2);
            }
        }
        // SAFETY: the write end, ours alone in this process.
        let mut out = unsafe { std::fs::File::from_raw_fd(fds[1]) };
        let _ = out.write_all(&encode_outcome(&check()));
        // SAFETY: ends the child without running anything of the parent's.
        unsafe { libc::_exit(0) }
    }
    // SAFETY: the write end is the child's now; the read end is ours alone.
    unsafe { libc::close(fds[1]) };
    // SAFETY: the read end, ours alone; closed when `answer` drops.
    let mut answer = unsafe { std::fs::File::from_raw_fd(fds[0]) };
    let start = std::time::Instant::now();
    let mut status = 0;
    loop {
        // SAFETY: `pid` is our child; `status` is written by waitpid.
        match unsafe { libc::waitpid(pid, &mut status, libc::WNOHANG) } {
            0 if start.elapsed() < CHECK_LIMIT => std::thread::sleep(std::time::Duration::from_millis(5)),
            0 => {
                // SAFETY: our child, which has not been reaped.
                unsafe { (libc::kill(pid, libc::SIGKILL), libc::waitpid(pid, &mut status, 0)) };
                return Err(failed(format!(
                    "checking it did not finish within {} s",
                    CHECK_LIMIT.as_secs()
                )));
            }
            r if r < 0 && std::io::Error::last_os_error().kind() == std::io::ErrorKind::Interrupted => {}
            r if r < 0 => {
                return Err(failed(format!(
                    "cannot check it: waitpid: {}",
                    std::io::Error::last_os_error()
                )))
            }
            _ => break,
        }
    }
    if libc::WIFSIGNALED(status) {
        let sig = libc::WTERMSIG(status);
        let why = if sig == libc::SIGABRT {
            " (a damaged page asked for more memory than the machine has)"
        } else {
            ""
        };
        return Err(damaged(
            path,
            format!("reading it ended the check with signal {sig}{why}"),
        ));
    }
    // The answer is short (see `encode_outcome`), so it sat in the pipe while the child ended.
    let mut reply = vec![];
    answer
        .read_to_end(&mut reply)
        .map_err(|e| failed(format!("cannot check it: {e}")))?;
    decode_outcome(path, &reply).ok_or_else(|| {
        failed(format!(
            "the check of it ended without an answer (exit status {status})"
        ))
    })?
}

/// A check's outcome as the child sends it: empty for sound, else a tag and the message.
fn encode_outcome(r: &Result<()>) -> Vec<u8> {
    let (tag, what) = match r {
        Ok(()) => return b"ok".to_vec(),
        Err(StoreError::Damaged { what, .. }) => (b'D', what.clone()),
        Err(StoreError::Empty { .. }) => (b'E', String::new()),
        Err(StoreError::InUse { .. }) => (b'U', String::new()),
        Err(StoreError::Io { source, .. }) => (b'I', source.to_string()),
        Err(StoreError::Failed { what, .. }) => (b'F', what.clone()),
    };
    // Well under a pipe's buffer, so the child never waits for its parent to read.
    let mut out = vec![tag];
    out.extend_from_slice(what.as_bytes());
    out.truncate(4096);
    out
}

fn decode_outcome(path: &Path, reply: &[u8]) -> Option<Result<()>> {
    let path = path.to_path_buf();
    let what = String::from_utf8_lossy(reply.get(1..)?).into_owned();
    Some(Err(match reply.first()? {
        _ if reply == b"ok" => return Some(Ok(())),
        b'D' => StoreError::Damaged { path, what },
        b'E' => StoreError::Empty { path },
        b'U' => StoreError::InUse { path },
        b'I' => StoreError::Io {
            path,
            source: std::io::Error::other(what),
        },
        b'F' => StoreError::Failed { path, what },
        _ => return None,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("hetfleet-store-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    #[test]
    fn a_flipped_bit_in_a_page_header_is_refused_or_reads_the_same() {
        // Found by the fuzz test: one bit flipped in a page's entry count (byte 3) of a cleanly
        // closed file made every message read as none, and the store opened empty. redb checks
        // its pages' checksums only after a crash; the census catches it. Each page's header
        // (its first 8 bytes) is flipped in turn.
        let dir = scratch("page-header");
        let p = dir.join("s.redb");
        let mut s = Store::open(&p).unwrap();
        for seq in 0..6u64 {
            for v in ["av-1", "boat-1"] {
                s.commit(&[((v, seq), &[seq as u8; 160])], &[("epoch", v.as_bytes())])
                    .unwrap();
            }
        }
        s.remove_through("av-1", 1, &[]).unwrap();
        let want = (s.messages().unwrap(), s.meta_with_prefix("").unwrap());
        drop(s);
        let good = std::fs::read(&p).unwrap();
        let mut refused = 0;
        for i in (0..good.len()).filter(|i| i % 4096 < 8) {
            let mut bytes = good.clone();
            bytes[i] ^= 4;
            std::fs::write(&p, &bytes).unwrap();
            match Store::open(&p) {
                Ok(s) => assert_eq!(
                    (s.messages().unwrap(), s.meta_with_prefix("").unwrap()),
                    want,
                    "byte {i} (page {}, offset {}): opened with different data",
                    i / 4096,
                    i % 4096
                ),
                Err(e) => {
                    assert!(e.is_bad_file(), "byte {i}: {e}");
                    refused += 1;
                }
            }
        }
        assert!(refused > 0, "no damage was refused");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_file_without_a_census_is_refused_and_left_as_it_is() {
        // What an older hetfleet wrote: the two tables, every record sealed, no census. It
        // cannot be told from a file whose census a damaged page dropped, so it is refused.
        let dir = scratch("no-census");
        let p = dir.join("old.redb");
        {
            let db = Database::create(&p).unwrap();
            let tx = db.begin_write().unwrap();
            {
                let mut t = tx.open_table(MESSAGES).unwrap();
                let sealed = seal(b'M', &message_key("boat-1", 0), b"abc");
                t.insert(("boat-1", 0), sealed.as_slice()).unwrap();
                tx.open_table(META).unwrap();
            }
            tx.commit().unwrap();
        }
        let before = std::fs::read(&p).unwrap();
        let err = Store::open(&p).err().expect("refused");
        assert!(
            err.is_bad_file()
                && err
                    .to_string()
                    .contains("`census` table is missing (an older hetfleet wrote none)"),
            "{err}"
        );
        assert_eq!(std::fs::read(&p).unwrap(), before, "the refusal changed the file");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_damaged_table_name_is_refused_not_read_as_an_empty_table() {
        // Found by the fuzz test: one flipped byte in the name `messages` made the table look
        // missing, and opening created it anew, empty: every message silently gone.
        let dir = scratch("table-name");
        let p = dir.join("s.redb");
        let mut s = Store::open(&p).unwrap();
        s.commit(&[(("boat-1", 0), b"abc")], &[]).unwrap();
        drop(s);
        let mut bytes = std::fs::read(&p).unwrap();
        let at = bytes
            .windows(8)
            .position(|w| w == b"messages")
            .expect("the table name is in the file");
        bytes[at] ^= 0x20;
        std::fs::write(&p, &bytes).unwrap();
        let err = Store::open(&p).err().expect("refused");
        assert!(
            err.is_bad_file() && err.to_string().contains("`messages` table is missing"),
            "{err}"
        );
        assert_eq!(std::fs::read(&p).unwrap(), bytes, "the refusal changed the file");
    }

    #[test]
    fn a_page_size_claiming_terabytes_is_refused_not_an_abort() {
        // Found by the fuzz test: redb allocates a page as large as its page number says
        // (up to 8 TiB) before it checks anything, and a failed allocation aborts the
        // process, past any catch_unwind. The table definitions name each table's root
        // page, so raise the size bits of every byte near the name `messages` in turn.
        let dir = scratch("page-order");
        let p = dir.join("s.redb");
        let mut s = Store::open(&p).unwrap();
        s.commit(&[(("boat-1", 0), b"abc"), (("av-1", 3), b"defg")], &[("state", b"x")])
            .unwrap();
        let want = (s.messages().unwrap(), s.meta_with_prefix("").unwrap());
        drop(s);
        let good = std::fs::read(&p).unwrap();
        let at = good
            .windows(8)
            .position(|w| w == b"messages")
            .expect("the table name is in the file");
        let (mut refused, mut opened) = (0, 0);
        for i in at.saturating_sub(64)..(at + 96).min(good.len()) {
            let mut bytes = good.clone();
            bytes[i] = 0xE0 | (bytes[i] & 0x07);
            if bytes == good {
                continue;
            }
            std::fs::write(&p, &bytes).unwrap();
            match Store::open(&p) {
                Ok(s) => {
                    assert_eq!(
                        (s.messages().unwrap(), s.meta_with_prefix("").unwrap()),
                        want,
                        "byte {i}: opened with different data"
                    );
                    opened += 1;
                }
                Err(e) => {
                    assert!(e.is_bad_file(), "byte {i}: {e}");
                    assert_eq!(
                        std::fs::read(&p).unwrap(),
                        bytes,
                        "byte {i}: the refusal changed the file"
                    );
                    refused += 1;
                }
            }
        }
        assert!(refused > 0, "no damage was refused ({opened} opened)");
    }

    #[test]
    fn keeps_what_was_committed_across_reopening() {
        let dir = scratch("keep");
        let path = dir.join("s.redb");
        {
            let mut s = Store::open(&path).unwrap();
            s.commit(
                &[(("boat-1", 0), b"aa"), (("boat-1", 1), b"bbb"), (("av-1", 0), b"c")],
                &[("state", b"x")],
            )
            .unwrap();
            s.commit(&[(("boat-1", 1), b"BBBB")], &[]).unwrap();
            assert_eq!(s.size(), (7, 3));
            assert_eq!(s.remove_through("boat-1", 0, &[("acked", b"0")]).unwrap(), 1);
        }
        let s = Store::open(&path).unwrap();
        assert_eq!(s.size(), (5, 2));
        let m = s.messages().unwrap();
        assert_eq!(
            m,
            vec![
                (("av-1".to_string(), 0), b"c".to_vec()),
                (("boat-1".to_string(), 1), b"BBBB".to_vec())
            ]
        );
        assert_eq!(s.meta("state").unwrap().as_deref(), Some(&b"x"[..]));
        assert_eq!(s.meta("acked").unwrap().as_deref(), Some(&b"0"[..]));
        assert_eq!(s.meta("nothing").unwrap(), None);
        drop(s);
        // No copy left behind by the check.
        let left: Vec<_> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(left, vec![std::ffi::OsString::from("s.redb")]);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_record_is_bound_to_its_key() {
        // The same bytes under another key fail: a flip that moves a value is caught too.
        let sealed = seal(b'M', &message_key("boat-1", 3), b"payload");
        assert_eq!(unseal(b'M', &message_key("boat-1", 3), &sealed), Ok(&b"payload"[..]));
        assert!(unseal(b'M', &message_key("boat-1", 4), &sealed).is_err());
        assert!(unseal(b'M', &message_key("boat-2", 3), &sealed).is_err());
        assert!(unseal(b'T', &message_key("boat-1", 3), &sealed).is_err());
        let mut flipped = sealed.clone();
        *flipped.last_mut().unwrap() ^= 1;
        assert!(unseal(b'M', &message_key("boat-1", 3), &flipped).is_err());
        assert!(unseal(b'M', b"", b"hf").is_err(), "too short");
    }

    #[test]
    fn an_empty_file_and_a_second_opener_are_refused() {
        let dir = scratch("empty");
        let path = dir.join("e.redb");
        std::fs::write(&path, b"").unwrap();
        assert!(matches!(Store::open(&path), Err(StoreError::Empty { .. })));
        assert_eq!(std::fs::metadata(&path).unwrap().len(), 0, "left as it was");
        let other = dir.join("o.redb");
        let _first = Store::open(&other).unwrap();
        match Store::open(&other) {
            Err(StoreError::InUse { .. }) => {}
            Err(e) => panic!("expected in use, got {e}"),
            Ok(_) => panic!("opened twice"),
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
}
