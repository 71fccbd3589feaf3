//! MAVLink 2 signing keys on disk. A key is 32 secret bytes, kept as 64 hex characters in a
//! file only its owner may read. `fleet secure` makes each key from a fresh random passphrase
//! as MAVProxy (`signing key <passphrase>`) and QGroundControl do, the SHA-256 of the
//! passphrase, and keeps the passphrase beside it: those ground stations take the passphrase,
//! not the hex, so this is how the same key reaches them.

use sha2::{Digest, Sha256};
use std::io::Read;
use std::path::{Path, PathBuf};

/// A 32-byte MAVLink 2 signing secret.
#[derive(Clone, PartialEq, Eq)]
pub struct SigningKey(pub [u8; 32]);

impl std::fmt::Debug for SigningKey {
    /// Never printed: a log line must not carry the secret.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("SigningKey(..)")
    }
}

/// A key file that cannot be used, and why.
#[derive(Debug, thiserror::Error)]
pub enum KeyError {
    #[error("{path}: {source}")]
    Read { path: PathBuf, source: std::io::Error },
    #[error("{path}: {why}")]
    Bad { path: PathBuf, why: String },
}

impl SigningKey {
    /// The key MAVProxy and QGroundControl derive from a passphrase (its SHA-256).
    pub fn from_passphrase(passphrase: &str) -> Self {
        Self(Sha256::digest(passphrase.as_bytes()).into())
    }

    /// The 64 hex characters of the file.
    pub fn to_hex(&self) -> String {
        self.0.iter().map(|b| format!("{b:02x}")).collect()
    }

    /// A key from its 64 hex characters (surrounding white space ignored).
    pub fn from_hex(text: &str) -> Result<Self, String> {
        let t = text.trim();
        if t.len() != 64 || !t.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Err(format!(
                "a signing key is 64 hex characters (32 bytes); this file has {} characters{}",
                t.chars().count(),
                if t.is_ascii() { "" } else { ", not all ASCII" }
            ));
        }
        let mut k = [0u8; 32];
        for (i, b) in k.iter_mut().enumerate() {
            *b = u8::from_str_radix(&t[2 * i..2 * i + 2], 16).map_err(|e| e.to_string())?;
        }
        Ok(Self(k))
    }

    /// Read a key file. One readable by others than its owner is refused: whoever can read
    /// it can command the vehicles.
    pub fn read(path: &Path) -> Result<Self, KeyError> {
        use std::os::unix::fs::PermissionsExt;
        let read = |source| KeyError::Read {
            path: path.into(),
            source,
        };
        let file = std::fs::File::open(path).map_err(read)?;
        let meta = file.metadata().map_err(read)?;
        if !meta.is_file() {
            return Err(KeyError::Bad {
                path: path.into(),
                why: "not a regular file".into(),
            });
        }
        if meta.permissions().mode() & 0o077 != 0 {
            return Err(KeyError::Bad {
                path: path.into(),
                why: format!(
                    "readable by others (mode {:o}); chmod 600 it",
                    meta.permissions().mode() & 0o777
                ),
            });
        }
        let mut text = String::new();
        // A key file is 65 bytes; more is not a key (and is not read whole).
        file.take(4096).read_to_string(&mut text).map_err(|e| KeyError::Bad {
            path: path.into(),
            why: format!("not text: {e}"),
        })?;
        Self::from_hex(&text).map_err(|why| KeyError::Bad { path: path.into(), why })
    }

    /// A fresh passphrase (128 bits from the kernel's random source, as 32 hex characters:
    /// one word a ground station's command line takes) and its key.
    pub fn generate() -> std::io::Result<(String, Self)> {
        let mut b = [0u8; 16];
        std::fs::File::open("/dev/urandom")?.read_exact(&mut b)?;
        let passphrase: String = b.iter().map(|x| format!("{x:02x}")).collect();
        let key = Self::from_passphrase(&passphrase);
        Ok((passphrase, key))
    }

    /// Write `<dir>/<name>.key` (the hex) and `<dir>/<name>.passphrase`, both mode 0600.
    pub fn write_pair(dir: &Path, name: &str, passphrase: &str, key: &Self) -> std::io::Result<()> {
        write_private(&dir.join(format!("{name}.key")), &format!("{}\n", key.to_hex()))?;
        write_private(&dir.join(format!("{name}.passphrase")), &format!("{passphrase}\n"))
    }
}

/// Write a file readable by its owner only (never, even briefly, by others): keys, passwords.
pub fn write_private(path: &Path, text: &str) -> std::io::Result<()> {
    use std::io::Write;
    use std::os::unix::fs::OpenOptionsExt;
    use std::os::unix::fs::PermissionsExt;
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(true)
        .mode(0o600)
        .open(path)?;
    // An existing file keeps its mode on open: set it.
    f.set_permissions(std::fs::Permissions::from_mode(0o600))?;
    f.write_all(text.as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_key_is_the_sha256_of_the_passphrase_as_mavproxy_makes_it() {
        // Python: hashlib.sha256(b"hetfleet").hexdigest()
        let k = SigningKey::from_passphrase("hetfleet");
        assert_eq!(
            k.to_hex(),
            "df51dd7ee631e34f4d5b65a5639c2d44b6d2bd2a98838a8eaece5dbafb605d51"
        );
        assert_eq!(
            SigningKey::from_hex(&format!("  {}\n", k.to_hex().to_uppercase())).unwrap(),
            k
        );
    }

    #[test]
    fn key_files_are_written_private_and_bad_ones_refused_naming_the_file() {
        use std::os::unix::fs::PermissionsExt;
        let dir = std::env::temp_dir().join(format!("hetfleet-key-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (pass, key) = SigningKey::generate().unwrap();
        assert_eq!(pass.len(), 32);
        assert_ne!(SigningKey::generate().unwrap().1, key, "fresh each time");
        SigningKey::write_pair(&dir, "mavlink-signing", &pass, &key).unwrap();
        let file = dir.join("mavlink-signing.key");
        for f in [&file, &dir.join("mavlink-signing.passphrase")] {
            assert_eq!(std::fs::metadata(f).unwrap().permissions().mode() & 0o777, 0o600);
        }
        assert_eq!(SigningKey::read(&file).unwrap(), key);
        assert_eq!(
            SigningKey::from_passphrase(
                std::fs::read_to_string(dir.join("mavlink-signing.passphrase"))
                    .unwrap()
                    .trim()
            ),
            key
        );
        assert!(
            !format!("{key:?}").contains(&key.to_hex()[..8]),
            "the secret is never printed"
        );

        std::fs::set_permissions(&file, std::fs::Permissions::from_mode(0o644)).unwrap();
        let e = SigningKey::read(&file).unwrap_err().to_string();
        assert!(e.contains("mavlink-signing.key") && e.contains("chmod 600"), "{e}");
        for (text, why) in [
            ("abc", "64 hex"),
            (&"zz".repeat(32), "64 hex"),
            (&"é".repeat(64), "not all ASCII"),
        ] {
            SigningKey::write_pair(&dir, "mavlink-signing", "x", &key).unwrap();
            std::fs::write(&file, text).unwrap();
            let e = SigningKey::read(&file).unwrap_err().to_string();
            assert!(e.contains("mavlink-signing.key") && e.contains(why), "{text}: {e}");
        }
        assert!(SigningKey::read(&dir.join("nope.key"))
            .unwrap_err()
            .to_string()
            .contains("nope.key"));
        assert!(SigningKey::read(&dir)
            .unwrap_err()
            .to_string()
            .contains("not a regular file"));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
