//! Pre-shared keys: the key type, how keys are read from text and files
//! without ever showing key material in an error or a log, and which of a
//! namespace's keys covers a channel. Sealing and opening only use them.

use chacha20poly1305::aead::KeyInit;
use chacha20poly1305::XChaCha20Poly1305;

/// A pre-shared key of 32 bytes. Its `Debug` shows no key material, and
/// the bytes are wiped when it is dropped.
#[derive(Clone)]
pub struct Key(pub(super) [u8; 32]);

impl std::fmt::Debug for Key {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Key(<redacted>)")
    }
}

impl Drop for Key {
    fn drop(&mut self) {
        // Volatile-free wipe: good enough against casual reuse of the
        // memory; the zeroize crate is what the AEAD itself uses.
        zeroize::Zeroize::zeroize(&mut self.0);
    }
}

/// Why a key could not be read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum KeyError {
    /// Not 64 hex digits.
    #[error("a key is 64 hex digits (32 bytes)")]
    Format,
    /// An entry of a key list is not `NAMESPACE=KEY`.
    #[error("key list entry {entry} is not NAMESPACE=KEY")]
    Entry {
        /// Its position, from 1.
        entry: usize,
    },
    /// The key of an entry is not 64 hex digits.
    #[error("the key of key list entry {entry}{namespace} is not 64 hex digits (32 bytes)")]
    Key {
        /// Its position, from 1.
        entry: usize,
        /// ` (namespace "...")`, or empty where what stands before the `=`
        /// might be key material itself (a base64 key holds `=`).
        namespace: String,
    },
    /// One `NAMESPACE=KEY` was expected, and the text holds none or more.
    #[error("one NAMESPACE=KEY is expected, not a list")]
    NotOne,
    /// A key file could not be read.
    #[error("key file {path}: {reason}")]
    File {
        /// The file.
        path: String,
        /// What went wrong.
        reason: String,
    },
}

/// The namespace of a key list entry as an error may show it: only a short
/// valid name, since a key written without a namespace (base64 ends in
/// `=`) would otherwise land in the message.
fn shown_namespace(namespace: &str) -> String {
    let valid = crate::name::resolve_path(namespace, "").is_ok();
    if valid && namespace.len() <= 24 {
        format!(" (namespace {namespace:?})")
    } else {
        String::new()
    }
}

/// Reads exactly one `NAMESPACE=KEY` (a command line's `--key`, say), as
/// [`parse_keys`] reads them; errors never repeat key material.
pub fn parse_key(text: &str) -> Result<(String, Key), KeyError> {
    let mut keys = parse_keys(text)?;
    match (keys.pop(), keys.is_empty()) {
        (Some(key), true) => Ok(key),
        _ => Err(KeyError::NotOne),
    }
}

/// One `NAMESPACE=KEY` as a command line gives it (`--key`), kept as text
/// until [`KeyArg::parse`] reads it. An argument parser's errors repeat
/// the value they failed on, and a derived `Debug` would print it: this
/// type does neither (its `Debug` is redacted, its text zeroed when
/// dropped), so a tool's flags can hold keys and be logged. clap takes it
/// through `From<String>`.
#[derive(Clone)]
pub struct KeyArg(String);

impl KeyArg {
    /// The namespace and key it names, read as [`parse_key`] reads them;
    /// the error never repeats key material.
    pub fn parse(&self) -> Result<(String, Key), KeyError> {
        parse_key(&self.0)
    }
}

impl From<String> for KeyArg {
    fn from(text: String) -> Self {
        Self(text)
    }
}

impl std::fmt::Debug for KeyArg {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("KeyArg(<redacted>)")
    }
}

impl Drop for KeyArg {
    fn drop(&mut self) {
        zeroize::Zeroize::zeroize(&mut self.0);
    }
}

/// Reads a key list: `NAMESPACE=KEY` entries separated by commas or white
/// space, as in `PULICAST_KEYS` and `--key`. A key is 64 hex digits, or
/// `@` and the path of a file that holds them (so the key stays out of
/// the environment and the process list). `/` or an empty namespace is
/// the root. Errors never contain key material.
pub fn parse_keys(text: &str) -> Result<Vec<(String, Key)>, KeyError> {
    let entries = text
        .split(|c: char| c == ',' || c.is_whitespace())
        .filter(|e| !e.is_empty());
    let mut keys = Vec::new();
    for (i, entry) in entries.enumerate() {
        let (namespace, value) = entry
            .split_once('=')
            .ok_or(KeyError::Entry { entry: i + 1 })?;
        let key = match value.strip_prefix('@') {
            Some(path) => {
                let mut text = std::fs::read_to_string(path).map_err(|e| KeyError::File {
                    path: path.to_string(),
                    reason: e.to_string(),
                })?;
                let key = Key::from_hex(&text);
                zeroize::Zeroize::zeroize(&mut text);
                key.map_err(|_| KeyError::File {
                    path: path.to_string(),
                    reason: "does not hold 64 hex digits".into(),
                })?
            }
            None => Key::from_hex(value).map_err(|_| KeyError::Key {
                entry: i + 1,
                namespace: shown_namespace(namespace),
            })?,
        };
        keys.push((namespace.to_string(), key));
    }
    Ok(keys)
}

impl Key {
    /// A key from its 32 bytes.
    pub fn from_bytes(bytes: [u8; 32]) -> Self {
        Self(bytes)
    }

    /// A key from 64 hex digits, as in `PULICAST_KEYS` and `--key`.
    pub fn from_hex(hex: &str) -> Result<Self, KeyError> {
        let hex = hex.trim();
        if hex.len() != 64 || !hex.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Err(KeyError::Format);
        }
        let mut bytes = [0u8; 32];
        for (i, byte) in bytes.iter_mut().enumerate() {
            *byte = u8::from_str_radix(&hex[2 * i..2 * i + 2], 16).map_err(|_| KeyError::Format)?;
        }
        Ok(Self(bytes))
    }

    /// The key of one channel: HKDF-SHA256 of this key over its name.
    pub(super) fn for_channel(&self, channel: &str) -> XChaCha20Poly1305 {
        let hkdf = hkdf::Hkdf::<sha2::Sha256>::new(Some(b"pulicast channel key v1"), &self.0);
        let mut okm = [0u8; 32];
        // 32 bytes is far below HKDF-SHA256's limit of 8160: cannot fail.
        let _ = hkdf.expand(channel.as_bytes(), &mut okm);
        let cipher = XChaCha20Poly1305::new(&okm.into());
        zeroize::Zeroize::zeroize(&mut okm);
        cipher
    }
}

/// The keys of the most specific namespace containing `channel`, the
/// sealing key first.
pub(super) fn keys_for<'k>(
    keys: &'k [(String, Key)],
    channel: &str,
) -> impl Iterator<Item = &'k Key> {
    let most_specific = most_specific(keys, channel);
    keys.iter()
        .filter(move |(ns, _)| most_specific == Some(ns.as_str()))
        .map(|(_, key)| key)
}

/// The most specific namespace of `keys` that contains `channel`.
fn most_specific<'k>(keys: &'k [(String, Key)], channel: &str) -> Option<&'k str> {
    keys.iter()
        .filter(|(ns, _)| crate::name::in_namespace(ns, channel))
        .map(|(ns, _)| ns.as_str())
        .max_by_key(|ns| ns.len())
}

/// The key that seals `channel`: the first of its most specific namespace.
pub(super) fn key_for<'k>(keys: &'k [(String, Key)], channel: &str) -> Option<&'k Key> {
    keys_for(keys, channel).next()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn key(b: u8) -> Key {
        Key::from_bytes([b; 32])
    }

    #[test]
    fn the_most_specific_namespace_key_applies() {
        let keys = vec![
            (String::new(), key(1)),
            ("rover1".to_string(), key(2)),
            ("rover1/arm".to_string(), key(3)),
        ];
        let which = |c: &str| key_for(&keys, c).map(|k| k.0[0]);
        assert_eq!(which("rover1/arm/pose"), Some(3));
        assert_eq!(which("rover1/armor"), Some(2));
        assert_eq!(which("rover1"), Some(2));
        assert_eq!(which("rover2/x"), Some(1));
        assert_eq!(key_for(&keys[1..], "rover2/x").map(|k| k.0[0]), None);
    }

    #[test]
    fn key_lists_parse_without_showing_keys() {
        let a = "ab".repeat(32);
        let keys = parse_keys(&format!(" /={a},rover1={a}\nrover1={}\n", "cd".repeat(32))).unwrap();
        let names: Vec<&str> = keys.iter().map(|(n, _)| n.as_str()).collect();
        assert_eq!(names, ["/", "rover1", "rover1"]);
        assert_eq!(keys[2].1 .0[0], 0xcd);
        assert_eq!(parse_keys("").unwrap().len(), 0);
        assert_eq!(parse_keys("x").err(), Some(KeyError::Entry { entry: 1 }));
        let secretish = "a".repeat(63);
        let err = parse_keys(&format!("rover1={secretish}")).unwrap_err();
        assert!(!err.to_string().contains(&secretish));
        assert!(err.to_string().contains("\"rover1\""), "{err}");
        // A base64 key given without a namespace: what precedes its `=`
        // is key material, and is not shown.
        let base64 = "q83vASNFZ4mrze8BI0VniavN7wEjRWeJq83vASNFZ4k=";
        let err = parse_keys(&format!("/={},{base64}", "ab".repeat(32))).unwrap_err();
        assert!(err.to_string().contains("entry 2"), "{err}");
        assert!(!err.to_string().contains(&base64[..20]), "{err}");
        let dir = std::env::temp_dir().join(format!("pulicast-keys-{}", std::process::id()));
        std::fs::write(&dir, format!("{a}\n")).unwrap();
        let keys = parse_keys(&format!("r=@{}", dir.display())).unwrap();
        assert_eq!(keys[0].1 .0[0], 0xab);
        std::fs::write(&dir, "not a key").unwrap();
        assert!(matches!(
            parse_keys(&format!("r=@{}", dir.display())),
            Err(KeyError::File { .. })
        ));
        std::fs::remove_file(&dir).unwrap();
        // Said as the system says it for any other missing file.
        let missing = parse_keys("r=@/nonexistent/pulicast-key").unwrap_err();
        assert!(
            matches!(missing, KeyError::File { .. })
                && missing.to_string().contains("No such file or directory"),
            "{missing}"
        );
    }

    #[test]
    fn keys_read_from_hex() {
        assert!(Key::from_hex(&"ab".repeat(32)).is_ok());
        assert_eq!(Key::from_hex("abc").err(), Some(KeyError::Format));
        assert_eq!(
            Key::from_hex(&"zz".repeat(32)).err(),
            Some(KeyError::Format)
        );
    }
}
