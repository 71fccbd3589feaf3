//! Damaged state files: a journal or outbox cut short or with bits flipped is either refused
//! with an error naming the file (never a panic, never altered by the refusal), or opens with
//! exactly what was committed (a flip in space the store does not use). Never different data.

use fleet_net::store::{Store, StoreError};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("hetfleet-damage-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

type Contents = (Vec<((String, u64), Vec<u8>)>, Vec<(String, Vec<u8>)>);

/// A store like a finished journal: 60 batches of 0.5-4 KB, a few removed (as acks do to an
/// outbox), and metadata.
fn realistic(path: &Path) -> Contents {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let mut s = Store::open(path).unwrap();
    for seq in 0..20u64 {
        for v in ["av-1", "boat-1", "boat-2"] {
            let n = rng.random_range(500..4000);
            let bytes: Vec<u8> = (0..n).map(|_| rng.random()).collect();
            s.commit(
                &[((v, seq), &bytes)],
                &[("state", format!("{v} after {seq}").as_bytes())],
            )
            .unwrap();
        }
        s.commit(&[], &[(&format!("epoch/{seq:010}"), &[seq as u8; 40])])
            .unwrap();
    }
    s.remove_through("av-1", 4, &[("acked", b"4")]).unwrap();
    (s.messages().unwrap(), s.meta_with_prefix("").unwrap())
}

/// Open `path` as a node does and read everything; `Ok` with the contents, or the error.
fn open_and_read(path: &Path) -> Result<Contents, StoreError> {
    let s = Store::open(path)?;
    Ok((s.messages()?, s.meta_with_prefix("")?))
}

/// One damaged file: refused cleanly and left as it is, or read back unchanged.
fn check(path: &Path, original: &Contents, what: &str) -> &'static str {
    let before = std::fs::read(path).unwrap();
    let got = std::panic::catch_unwind(|| open_and_read(path)).unwrap_or_else(|_| panic!("{what}: the store panicked"));
    match got {
        Ok(contents) => {
            assert_eq!(&contents, original, "{what}: opened with different data");
            "read back unchanged"
        }
        Err(e) => {
            assert!(e.is_bad_file(), "{what}: not reported as a bad file: {e}");
            let msg = e.to_string();
            assert!(
                msg.contains(&path.display().to_string()) && !msg.contains('\n'),
                "{what}: the error names the file on one line: {msg}"
            );
            assert_eq!(
                std::fs::read(path).unwrap(),
                before,
                "{what}: the refusal changed the file"
            );
            "refused"
        }
    }
}

#[test]
fn damaged_stores_are_refused_or_read_back_unchanged_never_altered() {
    let dir = scratch("store");
    let good = dir.join("good.redb");
    let original = realistic(&good);
    let bytes = std::fs::read(&good).unwrap();
    let mut outcomes: BTreeMap<(&str, &str), u32> = BTreeMap::new();
    let case = dir.join("case.redb");
    // Cut short anywhere, a third among them.
    for k in 0..=12 {
        let len = if k == 12 { bytes.len() / 3 } else { bytes.len() * k / 12 };
        std::fs::write(&case, &bytes[..len]).unwrap();
        *outcomes
            .entry((
                "truncated",
                check(
                    &case,
                    &original,
                    &format!("truncated to {len} of {} bytes", bytes.len()),
                ),
            ))
            .or_default() += 1;
    }
    // Bits flipped at random, 1 to 8 at a time.
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    for trial in 0..300 {
        let mut b = bytes.clone();
        for _ in 0..rng.random_range(1..=8) {
            let at = rng.random_range(0..b.len());
            b[at] ^= 1 << rng.random_range(0..8);
        }
        std::fs::write(&case, &b).unwrap();
        *outcomes
            .entry(("bit flips", check(&case, &original, &format!("flip trial {trial}"))))
            .or_default() += 1;
    }
    // Flips inside the records' bytes are always caught by their checksums.
    let payload = &original.0[7].1;
    let at = bytes
        .windows(64)
        .position(|w| w == &payload[100..164])
        .expect("a record's bytes are in the file");
    for bit in 0..8 {
        let mut b = bytes.clone();
        b[at + 10] ^= 1 << bit;
        std::fs::write(&case, &b).unwrap();
        assert_eq!(
            check(&case, &original, "a flip in a record"),
            "refused",
            "a flipped measurement must never replay"
        );
    }
    println!("damaged stores: {outcomes:?}");
    assert!(outcomes.get(&("bit flips", "refused")).copied().unwrap_or(0) > 0);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn an_empty_file_is_refused_and_a_missing_one_is_new() {
    let dir = scratch("empty");
    let path = dir.join("journal.redb");
    std::fs::write(&path, b"").unwrap();
    let e = Store::open(&path).err().expect("refused");
    assert!(
        matches!(e, StoreError::Empty { .. }) && e.to_string().contains("0 bytes"),
        "{e}"
    );
    std::fs::remove_file(&path).unwrap();
    let s = Store::open(&path).unwrap();
    assert_eq!(s.size(), (0, 0));
    let _ = std::fs::remove_dir_all(&dir);
}
