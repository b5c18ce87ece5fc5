//! Channel names to Zenoh key expressions and back.
//!
//! A channel `rover1/pose` is the key `<prefix>/rover1/pose`. The bridge's
//! own traffic lives under `<prefix>/@puli/...`: a chunk starting with `@`
//! is verbatim in Zenoh (only matched by itself, never by `*` or `**`), so
//! a plain Zenoh subscriber on `<prefix>/**` gets channels only, and no
//! channel can collide with the bridge's keys.
//!
//! Channel names that have no key are not bridged: Zenoh reserves `*`,
//! `$`, `#` and `?`, a chunk can't be empty, and chunks starting with `@`
//! are ours.

use std::fmt;

use zenoh::key_expr::KeyExpr;

/// Why a name has no key.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Unmappable {
    /// A character Zenoh reserves (`*`, `$`, `#`, `?`).
    Reserved(char),
    /// An empty part (`a//b`, a leading or trailing `/`).
    EmptyPart,
    /// A part starting with `@`, kept for the bridge's own keys.
    AtPart,
    /// Not a key expression for another reason Zenoh gives.
    Zenoh(String),
}

impl fmt::Display for Unmappable {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Unmappable::Reserved(c) => write!(f, "'{c}' is reserved in Zenoh key expressions"),
            Unmappable::EmptyPart => f.write_str("it has an empty part"),
            Unmappable::AtPart => f.write_str("a part starting with '@' is kept for the bridge"),
            Unmappable::Zenoh(e) => write!(f, "not a Zenoh key expression: {e}"),
        }
    }
}

/// The keys of one bridged fleet: its data under `<prefix>/`, the bridges'
/// own keys under `<prefix>/@puli/`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct KeyMap {
    prefix: String,
}

impl KeyMap {
    /// The key map for `prefix` (`fleet`, `acme/fleet`): a key expression
    /// without wildcards, so several fleets share one Zenoh network.
    pub fn new(prefix: &str) -> Result<Self, Unmappable> {
        check(prefix)?;
        Ok(Self {
            prefix: prefix.to_owned(),
        })
    }

    /// The prefix.
    pub fn prefix(&self) -> &str {
        &self.prefix
    }

    /// The key of a channel.
    pub fn key_of(&self, channel: &str) -> Result<String, Unmappable> {
        check(channel)?;
        Ok(format!("{}/{channel}", self.prefix))
    }

    /// The channel of a data key, if it is one of this fleet's.
    pub fn channel_of<'k>(&self, key: &'k str) -> Option<&'k str> {
        let rest = key.strip_prefix(&self.prefix)?.strip_prefix('/')?;
        check(rest).ok().map(|()| rest)
    }

    /// The liveliness token of a bridge (by its session key).
    pub fn bridge_token(&self, bridge: i64) -> String {
        format!("{}/@puli/bridge/{}", self.prefix, hex(bridge))
    }

    /// Every bridge's liveliness token.
    pub fn bridge_tokens(&self) -> String {
        format!("{}/@puli/bridge/*", self.prefix)
    }

    /// The bridge a token key names.
    pub fn bridge_of_token(&self, key: &str) -> Option<i64> {
        let hex = key.strip_prefix(&self.bridge_tokens()[..self.bridge_tokens().len() - 1])?;
        u64::from_str_radix(hex, 16).ok().map(|k| k as i64)
    }

    /// Where a bridge publishes its site's members (and answers queries
    /// for them).
    pub fn site_table(&self, bridge: i64) -> String {
        format!("{}/@puli/site/{}", self.prefix, hex(bridge))
    }

    /// Every bridge's site table.
    pub fn site_tables(&self) -> String {
        format!("{}/@puli/site/*", self.prefix)
    }

    /// Where a bridge takes calls for the servers of its site.
    pub fn calls(&self, bridge: i64) -> String {
        format!("{}/@puli/call/{}", self.prefix, hex(bridge))
    }

    /// Where a bridge takes cancels of those calls.
    pub fn cancels(&self, bridge: i64) -> String {
        format!("{}/@puli/cancel/{}", self.prefix, hex(bridge))
    }

    /// The local marker channel: bridges of this prefix on one site find
    /// each other by publishing and subscribing it (see [`crate::plan`]).
    pub fn marker_channel(&self) -> String {
        format!(".puli-bridge/{}", self.prefix)
    }

    /// The channel the active bridge of this prefix on a site subscribes.
    pub fn active_channel(&self) -> String {
        format!(".puli-bridge-active/{}", self.prefix)
    }
}

/// A key's text for a session key: 16 hex digits.
fn hex(key: i64) -> String {
    format!("{:016x}", key as u64)
}

fn check(name: &str) -> Result<(), Unmappable> {
    if let Some(c) = name.chars().find(|c| matches!(c, '*' | '$' | '#' | '?')) {
        return Err(Unmappable::Reserved(c));
    }
    if name.split('/').any(str::is_empty) {
        return Err(Unmappable::EmptyPart);
    }
    if name.split('/').any(|p| p.starts_with('@')) {
        return Err(Unmappable::AtPart);
    }
    KeyExpr::try_from(name).map_err(|e| Unmappable::Zenoh(e.to_string()))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn channels_map_to_keys_under_the_prefix_and_back() {
        let map = KeyMap::new("acme/fleet").unwrap();
        assert_eq!(map.key_of("rover1/pose").unwrap(), "acme/fleet/rover1/pose");
        assert_eq!(
            map.channel_of("acme/fleet/rover1/.config/speed.r"),
            Some("rover1/.config/speed.r")
        );
        assert_eq!(map.channel_of("acme/fleetx/pose"), None);
        assert_eq!(map.channel_of("acme/fleet/@puli/site/00"), None);
        assert_eq!(map.channel_of("acme/fleet"), None);
        assert_eq!(map.channel_of("acme/fleet/rover1/*"), None, "a wildcard");
        assert_eq!(map.channel_of("acme/fleet/**"), None);
    }

    #[test]
    fn names_zenoh_reserves_have_no_key() {
        let map = KeyMap::new("f").unwrap();
        assert_eq!(map.key_of("a/*/b"), Err(Unmappable::Reserved('*')));
        assert_eq!(map.key_of("cost$"), Err(Unmappable::Reserved('$')));
        assert_eq!(map.key_of("a//b"), Err(Unmappable::EmptyPart));
        assert_eq!(map.key_of("/a"), Err(Unmappable::EmptyPart));
        assert_eq!(map.key_of("a/@puli/x"), Err(Unmappable::AtPart));
        assert!(KeyMap::new("f/**").is_err());
        assert!(KeyMap::new("").is_err());
    }

    #[test]
    fn bridge_keys_round_trip() {
        let map = KeyMap::new("f").unwrap();
        for key in [0, 1, -1, i64::MIN, 0x1234_5678_9abc_def0] {
            let token = map.bridge_token(key);
            assert_eq!(map.bridge_of_token(&token), Some(key), "{token}");
            assert!(KeyExpr::try_from(token.as_str()).is_ok());
        }
        assert_eq!(map.bridge_of_token("f/@puli/bridge/zz"), None);
        assert_eq!(map.bridge_of_token("g/@puli/bridge/00"), None);
    }
}
