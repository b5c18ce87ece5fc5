//! The errors of the core's fallible operations. The `pulicast` crate
//! turns each into its own `Error` of the same name.

use std::io;

/// What a core operation refused or failed at. Exhaustive on purpose:
/// `pulicast::Error` maps each variant, so a new one must get its mapping.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A channel or namespace name can't be used.
    #[error("invalid name {name:?}: {reason}")]
    InvalidName {
        /// The name as given.
        name: String,
        /// Why it was refused.
        reason: NameError,
    },
    /// The encoded message is larger than pulicast sends (64 MiB).
    #[error("message for {channel:?} is {size} bytes, at most {max} can be sent")]
    PayloadTooLarge {
        /// The channel it was meant for.
        channel: String,
        /// Encoded payload size in bytes.
        size: usize,
        /// Largest message size.
        max: usize,
    },
    /// An argument or a setting is out of range.
    #[error("invalid {setting}: {reason}")]
    InvalidConfig {
        /// Which setting (`batching delay`, `key`, ...).
        setting: &'static str,
        /// What is wrong with it, for a person to read.
        reason: String,
    },
    /// The caller's `send` failed.
    #[error("{op} failed")]
    Io {
        /// What we tried, in words.
        op: &'static str,
        /// The underlying error.
        #[source]
        source: io::Error,
    },
}

impl Error {
    pub(crate) fn config(setting: &'static str, reason: impl Into<String>) -> Self {
        Error::InvalidConfig {
            setting,
            reason: reason.into(),
        }
    }

    pub(crate) fn io(op: &'static str) -> impl FnOnce(io::Error) -> Self {
        move |source| Error::Io { op, source }
    }
}

/// Why a name was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum NameError {
    /// The name resolves to the root namespace, which is not a channel.
    #[error("resolves to the empty name")]
    Empty,
    /// The name contains a character outside ASCII.
    #[error("contains non-ASCII characters")]
    NonAscii,
    /// The name contains an ASCII control character.
    #[error("contains a control character")]
    ControlCharacter,
    /// The channel is reserved for the node itself (`__nodes`).
    #[error("is reserved for the node's heartbeat")]
    Reserved,
    /// The resolved name is longer than 255 bytes.
    #[error("resolves to {len} bytes, at most 255 are allowed")]
    TooLong {
        /// Length of the resolved name.
        len: usize,
    },
}

/// Shorthand for results of the core.
pub type Result<T, E = Error> = std::result::Result<T, E>;
