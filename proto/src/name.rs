//! Channel names, namespaces and their multicast groups.
//!
//! Channels live in a hierarchy of namespaces, like files in folders. A name is
//! resolved against a namespace the way a POSIX path is resolved against a
//! working directory:
//!
//! | namespace          | name        | resolved               |
//! |--------------------|-------------|------------------------|
//! | `rover1/left_arm/` | `ctrl`      | `rover1/left_arm/ctrl` |
//! | `rover1/left_arm/` | `../ctrl`   | `rover1/ctrl`          |
//! | `rover1/left_arm/` | `/ctrl`     | `ctrl`                 |
//! | `/`                | `rover1/ctrl` | `rover1/ctrl`        |
//!
//! A leading `/` starts at the root, `..` goes up one level (never above the
//! root), `.` and empty components are ignored. Resolved names carry neither a
//! leading nor a trailing slash. Every channel maps to one multicast group
//! (see [`group_for`]); several names may share a group, which is why receivers
//! filter by the name in each packet.

use std::net::Ipv4Addr;

use crate::error::{Error, NameError};

/// Longest resolved channel name: its length travels in one byte.
pub const MAX_NAME_LEN: usize = 255;

/// The first address of the multicast range channels map into.
pub const GROUP_BASE: Ipv4Addr = Ipv4Addr::new(239, 0, 0, 0);

/// Resolves `name` against `namespace` into a full channel name.
///
/// Returns an error if the name or the result is empty, longer than [`MAX_NAME_LEN`] bytes,
/// or contains non-ASCII or control characters.
///
/// ```
/// use pulicast_proto::name::resolve_name;
/// assert_eq!(resolve_name("left_arm/pose", "rover1").unwrap(), "rover1/left_arm/pose");
/// assert_eq!(resolve_name("../rover2/pose", "rover1").unwrap(), "rover2/pose");
/// assert_eq!(resolve_name("/ctrl", "rover1/left_arm").unwrap(), "ctrl");
/// assert!(resolve_name("..", "rover1").is_err()); // that is the root, not a channel
/// ```
pub fn resolve_name(name: &str, namespace: &str) -> Result<String, Error> {
    let resolved = resolve_path(name, namespace)?;
    if name.is_empty() || resolved.is_empty() {
        return Err(Error::InvalidName {
            name: name.to_owned(),
            reason: NameError::Empty,
        });
    }
    Ok(resolved)
}

/// Resolves `path` against `namespace` like [`resolve_name`], but allows the
/// result to be the root namespace (the empty string).
pub fn resolve_path(path: &str, namespace: &str) -> Result<String, Error> {
    check_chars(path)?;
    check_chars(namespace)?;
    let mut parts: Vec<&str> = Vec::new();
    let base = if path.starts_with('/') { "" } else { namespace };
    for part in base.split('/').chain(path.split('/')) {
        match part {
            "" | "." => {}
            ".." => {
                parts.pop();
            }
            other => parts.push(other),
        }
    }
    let resolved = parts.join("/");
    if resolved.len() > MAX_NAME_LEN {
        return Err(Error::InvalidName {
            name: path.to_owned(),
            reason: NameError::TooLong {
                len: resolved.len(),
            },
        });
    }
    Ok(resolved)
}

fn check_chars(name: &str) -> Result<(), Error> {
    let bad = |reason| {
        Err(Error::InvalidName {
            name: name.to_owned(),
            reason,
        })
    };
    if !name.is_ascii() {
        return bad(NameError::NonAscii);
    }
    if name.bytes().any(|b| b.is_ascii_control()) {
        return bad(NameError::ControlCharacter);
    }
    Ok(())
}

/// Whether a channel is hidden from normal listings, as Pulicast 2.x
/// tells: `__nodes`, and any name with a part starting with `.`
/// (`rover1/.config/max_speed`, a setting's channel).
pub fn is_hidden_channel(name: &str) -> bool {
    name == "__nodes" || name.starts_with('.') || name.contains("/.")
}

/// Whether the resolved channel name `channel` lies in the resolved
/// namespace `namespace` (`""`, the root, holds every channel).
pub fn in_namespace(namespace: &str, channel: &str) -> bool {
    namespace.is_empty()
        || channel
            .strip_prefix(namespace)
            .is_some_and(|rest| rest.is_empty() || rest.starts_with('/'))
}

/// The sdbm hash of a name, as Pulicast 2.x computes it (wrapping arithmetic).
pub fn sdbm(name: &str) -> u64 {
    name.bytes().fold(0u64, |h, c| {
        u64::from(c)
            .wrapping_add(h << 6)
            .wrapping_add(h << 16)
            .wrapping_sub(h)
    })
}

/// The multicast group a channel's messages are sent to:
/// `239.0.0.0 + sdbm(name) mod 2^23`.
pub fn group_for(name: &str) -> Ipv4Addr {
    // The mask keeps the value below 2^23, so the cast cannot truncate.
    let offset = (sdbm(name) & ((1 << 23) - 1)) as u32;
    Ipv4Addr::from(u32::from(GROUP_BASE) + offset)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn edge_cases() {
        assert_eq!(resolve_name("a", "").unwrap(), "a");
        assert_eq!(resolve_name("a/", "ns").unwrap(), "ns/a");
        assert_eq!(resolve_name("./././a", "//ns//").unwrap(), "ns/a");
        assert_eq!(resolve_name("../a", "../../x").unwrap(), "a");
        assert_eq!(resolve_name("/../a", "ns").unwrap(), "a");
        assert!(matches!(
            resolve_name("", "ns"),
            Err(Error::InvalidName {
                reason: NameError::Empty,
                ..
            })
        ));
        assert!(matches!(
            resolve_name("pos\u{e9}", "ns"),
            Err(Error::InvalidName {
                reason: NameError::NonAscii,
                ..
            })
        ));
        assert!(matches!(
            resolve_name("a\nb", ""),
            Err(Error::InvalidName {
                reason: NameError::ControlCharacter,
                ..
            })
        ));
        let long = "x".repeat(250);
        assert!(resolve_name(&long, "abcd").is_ok()); // 255 bytes exactly
        assert!(matches!(
            resolve_name(&long, "abcde"),
            Err(Error::InvalidName {
                reason: NameError::TooLong { len: 256 },
                ..
            })
        ));
        // A long namespace that ".." brings back under the limit is fine.
        assert_eq!(
            resolve_name(&format!("{}/../a", "y".repeat(300)), "").unwrap(),
            "a"
        );
    }

    #[test]
    fn resolve_path_allows_root() {
        assert_eq!(resolve_path("..", "rover1").unwrap(), "");
        assert_eq!(resolve_path("/", "rover1").unwrap(), "");
    }
}
