//! Authenticated channels as a node runs them: the keys it was given (by
//! the builder and the environment), and the sealers of its channels. The format itself is in
//! [`crate::proto::secure`]; `docs/security.md` has the threat model.

use std::net::SocketAddrV4;
use std::time::Duration;

use crate::error::{Error, Result};
use crate::proto::secure::{parse_keys, Key, Opener, Sealer};

/// The environment variable a node reads keys from: `NAMESPACE=KEY`
/// entries, separated by commas (see [`parse_keys`]).
pub const KEYS_ENV: &str = "PULICAST_KEYS";

/// The environment variable that turns payload encryption on (`1`,
/// `true`, `yes` or `on`) or off (`0`, `false`, `no`, `off` or empty).
pub const ENCRYPT_ENV: &str = "PULICAST_ENCRYPT";

/// How far the send time of a sealed datagram may be from the receiver's
/// clock by default: see [`crate::NodeBuilder::sealed_max_age`].
pub const DEFAULT_SEALED_MAX_AGE: Duration = Duration::from_secs(30);

/// The security options of a [`crate::NodeBuilder`].
#[derive(Debug, Clone)]
pub(crate) struct SecurityOptions {
    pub keys: Vec<(String, Key)>,
    pub encrypt: bool,
    pub max_age: Option<Duration>,
    pub from_env: bool,
}

impl Default for SecurityOptions {
    fn default() -> Self {
        Self {
            keys: Vec::new(),
            encrypt: false,
            max_age: Some(DEFAULT_SEALED_MAX_AGE),
            from_env: true,
        }
    }
}

/// The keys of a running node. Only nodes with at least one key have one.
/// (`Debug` shows the opener's namespaces, never its keys.) What received
/// datagrams meet is counted by the node's [`crate::proto::Receiver`],
/// which opens them with a copy of these keys ([`Security::opener`]).
#[derive(Debug)]
pub(crate) struct Security {
    encrypt: bool,
    /// The keys, for lookups only: it opens nothing.
    keys: Opener,
}

impl Security {
    /// The node's security from its options and, unless turned off, the
    /// environment; `None` when there are no keys, the default, which keeps
    /// the node a plain Pulicast 2.x node.
    pub(crate) fn new(options: &SecurityOptions) -> Result<Option<Self>> {
        Self::with_env(options, |name| std::env::var(name).ok())
    }

    /// As [`Security::new`], with `env` standing in for the environment.
    fn with_env(
        options: &SecurityOptions,
        env: impl Fn(&str) -> Option<String>,
    ) -> Result<Option<Self>> {
        let mut keys = options.keys.clone();
        let mut encrypt = options.encrypt;
        if options.from_env {
            if let Some(mut text) = env(KEYS_ENV) {
                let parsed = from_env_keys(&text);
                zeroize::Zeroize::zeroize(&mut text);
                keys.extend(parsed?);
            }
            if let Some(text) = env(ENCRYPT_ENV) {
                encrypt |= parse_switch(ENCRYPT_ENV, &text)?;
            }
        }
        Self::with_keys(&keys, encrypt, options.max_age)
    }

    fn with_keys(
        keys: &[(String, Key)],
        encrypt: bool,
        max_age: Option<Duration>,
    ) -> Result<Option<Self>> {
        if keys.is_empty() {
            return Ok(None);
        }
        if max_age.is_some_and(|age| age < Duration::from_millis(100)) {
            return Err(Error::config(
                "sealed max age",
                format!("{max_age:?} is below 100 ms: nothing would arrive in time"),
            ));
        }
        let mut opener = Opener::new(max_age);
        for (namespace, key) in keys {
            opener.add_key(namespace, key)?;
        }
        Ok(Some(Self {
            encrypt,
            keys: opener,
        }))
    }

    /// An opener with the node's keys, for its receiver.
    pub(crate) fn opener(&self) -> Opener {
        self.keys.with_same_keys()
    }

    /// A sealer for `channel` if a key covers it, for datagrams sent from
    /// `origin` (what is unspecified in it is not checked by receivers).
    pub(crate) fn sealer(&self, channel: &str, origin: SocketAddrV4) -> Option<Sealer> {
        let key = self.keys.key_for(channel)?;
        Some(Sealer::new(key, channel, self.encrypt).with_origin(origin))
    }

    /// Whether datagrams on `channel` must be sealed.
    pub(crate) fn covers(&self, channel: &str) -> bool {
        self.keys.covers(channel)
    }
}

/// The keys in `PULICAST_KEYS`.
fn from_env_keys(text: &str) -> Result<Vec<(String, Key)>> {
    parse_keys(text).map_err(|e| Error::config(KEYS_ENV, e.to_string()))
}

/// A yes/no setting from the environment.
fn parse_switch(name: &'static str, text: &str) -> Result<bool> {
    match text.trim().to_ascii_lowercase().as_str() {
        "1" | "true" | "yes" | "on" => Ok(true),
        "" | "0" | "false" | "no" | "off" => Ok(false),
        _ => Err(Error::config(name, format!("{text:?}: expected 1 or 0"))),
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::proto::secure::Sealer;
    use std::net::SocketAddr;

    const ANY: SocketAddrV4 = SocketAddrV4::new(std::net::Ipv4Addr::UNSPECIFIED, 0);
    const FROM: SocketAddr = SocketAddr::V4(ANY);

    #[test]
    fn the_environment_adds_keys_after_the_builders_and_can_be_ignored() {
        let env = |name: &str| match name {
            KEYS_ENV => Some(format!("rover1={},/={}", "22".repeat(32), "33".repeat(32))),
            ENCRYPT_ENV => Some("on".to_string()),
            _ => None,
        };
        let mut options = SecurityOptions::default();
        options
            .keys
            .push(("rover1".into(), Key::from_bytes([0x11; 32])));
        let s = Security::with_env(&options, env).unwrap().unwrap();
        assert!(s.encrypt && s.covers("anything"));
        // The builder's key seals; the environment's is accepted too.
        let mut sealed = Sealer::new(&Key::from_bytes([0x11; 32]), "rover1/x", false)
            .seal(b"PULI\x08rover1/x\0\0\0\0", 0)
            .to_vec();
        assert!(s.opener().open_in_place(&mut sealed, FROM, 0).is_ok());
        let mut sealed = Sealer::new(&Key::from_bytes([0x22; 32]), "rover1/x", false)
            .seal(b"PULI\x08rover1/x\0\0\0\0", 0)
            .to_vec();
        assert!(s.opener().open_in_place(&mut sealed, FROM, 0).is_ok());
        let mut mine = s
            .sealer("rover1/x", ANY)
            .unwrap()
            .seal(b"PULI\x08rover1/x\0\0\0\0", 0)
            .to_vec();
        let only_builders = Security::with_env(
            &SecurityOptions {
                from_env: false,
                ..options.clone()
            },
            env,
        )
        .unwrap()
        .unwrap();
        assert!(!only_builders.encrypt && !only_builders.covers("elsewhere"));
        assert!(only_builders
            .opener()
            .open_in_place(&mut mine, FROM, 0)
            .is_ok());
        // Bad settings in the environment are errors that name the variable.
        let bad = |name: &'static str, value: &'static str| {
            move |n: &str| (n == name).then(|| value.to_string())
        };
        let err = Security::with_env(&options, bad(KEYS_ENV, "rover1")).unwrap_err();
        assert!(err.to_string().contains(KEYS_ENV));
        assert!(Security::with_env(&options, bad(ENCRYPT_ENV, "sometimes")).is_err());
    }

    #[test]
    fn no_keys_no_security_and_bad_settings_are_refused() {
        assert!(Security::with_keys(&[], true, None).unwrap().is_none());
        let key = Key::from_bytes([1; 32]);
        let one = [("rover1".to_string(), key.clone())];
        let s = Security::with_keys(&one, false, None).unwrap().unwrap();
        assert!(s.covers("rover1/a") && !s.covers("rover2/a"));
        assert!(s.sealer("rover1/a", ANY).is_some() && s.sealer("x", ANY).is_none());
        assert!(!format!("{s:?}").contains("01"));
        assert!(Security::with_keys(&one, false, Some(Duration::from_millis(1))).is_err());
        let bad = [("r\u{f6}ver".to_string(), key)];
        assert!(Security::with_keys(&bad, false, None).is_err());
        assert!(parse_switch("X", "yes").unwrap());
        assert!(!parse_switch("X", " 0 ").unwrap());
        assert!(parse_switch("X", "maybe").is_err());
        let err = from_env_keys(&format!("a={}", "f".repeat(63))).unwrap_err();
        assert!(err.to_string().contains(KEYS_ENV));
        assert!(!err.to_string().contains(&"f".repeat(63)));
    }
}
