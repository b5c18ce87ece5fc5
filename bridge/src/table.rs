//! A site's members as a bridge tells other sites about them.
//!
//! Each active bridge puts its table on `<prefix>/@puli/site/<key>` when it
//! changes and answers queries for it there, so a bridge that joins (or
//! comes back after a cut) asks and gets every site at once. It is valid
//! while the bridge's liveliness token (`<prefix>/@puli/bridge/<key>`) is:
//! when Zenoh says the token is gone (the bridge stopped, or its link has
//! been silent for the lease), every member in the table fails on the other
//! sites.
//!
//! The encoding is `PBST`, a version byte (1), then [`SiteTable`] in
//! postcard.

use pulicast::{MemberInfo, MemberState};
use serde::{Deserialize, Serialize};

/// The table's first four bytes.
pub const MAGIC: [u8; 4] = *b"PBST";
const VERSION: u8 = 1;

/// Most bytes a table may have: a larger one is refused.
pub const MAX_TABLE_BYTES: usize = 8 << 20;

/// Most members one table may list.
pub const MAX_MEMBERS: usize = 4096;

/// Longest site name, in bytes (as the nodes take it).
pub use pulicast::MAX_SITE_LEN;

/// Longest bridge name, in bytes (a node name's bound).
pub const MAX_NAME_LEN: usize = 255;

/// One site's members.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SiteTable {
    /// The bridge's session key.
    pub bridge: i64,
    /// The bridge's node name.
    pub bridge_name: String,
    /// The site's name.
    pub site: String,
    /// Grows with every change, so an older table (a late answer to a
    /// query) does not replace a newer one.
    pub version: u64,
    /// The members.
    pub members: Vec<SiteMember>,
}

/// One member of a site.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct SiteMember {
    /// What it announces on its site (`data_port` is its own there).
    pub info: MemberInfo,
    /// Its incarnation.
    pub incarnation: u32,
    /// Alive or suspect.
    pub state: MemberState,
}

/// Why a table was refused.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum TableError {
    /// Not a table (magic or version).
    NotATable,
    /// Over [`MAX_TABLE_BYTES`] or [`MAX_MEMBERS`].
    TooLarge,
    /// The body did not decode.
    Malformed(String),
}

impl std::fmt::Display for TableError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            TableError::NotATable => f.write_str("not a site table"),
            TableError::TooLarge => f.write_str("site table too large"),
            TableError::Malformed(e) => write!(f, "malformed site table: {e}"),
        }
    }
}

impl SiteTable {
    /// The bytes.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = MAGIC.to_vec();
        out.push(VERSION);
        postcard::to_extend(self, out).unwrap_or_default()
    }

    /// Reads a table, refusing one over the bounds before it costs memory.
    pub fn decode(bytes: &[u8]) -> Result<Self, TableError> {
        if bytes.len() > MAX_TABLE_BYTES {
            return Err(TableError::TooLarge);
        }
        let body = bytes
            .strip_prefix(&MAGIC)
            .and_then(|rest| rest.strip_prefix(&[VERSION]))
            .ok_or(TableError::NotATable)?;
        let (table, rest) = postcard::take_from_bytes::<SiteTable>(body)
            .map_err(|e| TableError::Malformed(e.to_string()))?;
        if !rest.is_empty() {
            return Err(TableError::Malformed(format!(
                "{} trailing bytes",
                rest.len()
            )));
        }
        if table.members.len() > MAX_MEMBERS {
            return Err(TableError::TooLarge);
        }
        if table.site.len() > MAX_SITE_LEN || table.bridge_name.len() > MAX_NAME_LEN {
            return Err(TableError::Malformed("a name too long".into()));
        }
        Ok(table)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tables_round_trip_and_junk_is_refused() {
        let table = SiteTable {
            bridge: 3,
            bridge_name: "b".into(),
            site: "a".into(),
            version: 9,
            members: vec![SiteMember {
                info: MemberInfo {
                    session: [1; 16],
                    name: "n".into(),
                    namespace: String::new(),
                    host: "h".into(),
                    pid: 1,
                    start_time_ms: 2,
                    data_port: 3,
                    channels: vec![],
                    config: String::new(),
                    extensions: Vec::new(),
                },
                incarnation: 0,
                state: MemberState::Alive,
            }],
        };
        let bytes = table.encode();
        assert_eq!(SiteTable::decode(&bytes), Ok(table));
        assert_eq!(SiteTable::decode(b"PBSX\x01"), Err(TableError::NotATable));
        for len in 0..bytes.len() {
            assert!(SiteTable::decode(&bytes[..len]).is_err(), "cut at {len}");
        }
        assert_eq!(
            SiteTable::decode(&vec![0; MAX_TABLE_BYTES + 1]),
            Err(TableError::TooLarge)
        );
        let mut long = SiteTable::decode(&bytes).unwrap();
        long.site = "s".repeat(MAX_SITE_LEN + 1);
        assert!(SiteTable::decode(&long.encode()).is_err());
    }
}
