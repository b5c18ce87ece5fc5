//! Errors of the pulicast API.

use std::io;

use crate::wire::{DecodeError, EncodeError};

/// Everything the pulicast API can refuse or fail at.
///
/// # Example
///
/// ```no_run
/// # async fn demo(node: pulicast::Node) -> pulicast::Result<()> {
/// use pulicast::Error;
/// let plan = node.client::<f64, f64>("plan")?;
/// match plan.call(&1.0).await {
///     Ok(steps) => println!("{steps} steps"),
///     Err(Error::NoServer { service, .. }) => eprintln!("nobody serves {service}"),
///     Err(Error::CallFailed { code, message, .. }) => eprintln!("failed ({code}): {message}"),
///     Err(e) => return Err(e), // non_exhaustive: keep a catch-all
/// }
/// # Ok(()) }
/// ```
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
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
    /// The node was stopped (or all its [`crate::Node`] handles were dropped).
    #[error("the node has stopped")]
    NodeStopped,
    /// Nothing happened within the time given.
    #[error("timed out after {0:?}")]
    Timeout(std::time::Duration),
    /// A builder option, an environment setting or an argument is out of
    /// range.
    #[error("invalid {setting}: {reason}")]
    InvalidConfig {
        /// Which setting (`port`, `ttl`, `PULICAST_KEYS`, ...).
        setting: &'static str,
        /// What is wrong with it, for a person to read.
        reason: String,
    },
    /// A distributed setting's checks refused a value (its default, one
    /// its owner set, or one a [`crate::FleetSettings`] request asked
    /// for), or the value is not one of the setting's type.
    #[error("setting {name}: {reason}")]
    SettingRefused {
        /// The setting's fleet-wide name.
        name: String,
        /// Why, as its checks say.
        reason: String,
    },
    /// A distributed setting can't be read or changed: no node owns it,
    /// its owner did not answer in time, two nodes own it (locked), or its
    /// type is not one tools can write.
    #[error("setting {name} unavailable: {reason}")]
    SettingUnavailable {
        /// The setting's fleet-wide name.
        name: String,
        /// Why, for a person to read.
        reason: String,
    },
    /// A service call found no server: none in the fleet serves the
    /// service (within the call's deadline), or not the node it targets.
    #[error("no server of {service}: {reason}")]
    NoServer {
        /// The service's full name (with `@node` if the call targets one).
        service: String,
        /// Why, for a person to read.
        reason: String,
    },
    /// A service's server answered a call with a failure: its handler's
    /// own ([`crate::Fault`]), or one of pulicast's codes
    /// (the codes below [`crate::Fault::APPLICATION`]: cancelled,
    /// deadline, panicked, ...).
    #[error("{service} failed at {node}: {message} (code {code})")]
    CallFailed {
        /// The service's full name.
        service: String,
        /// The server node.
        node: String,
        /// The failure's code.
        code: u16,
        /// What the server said.
        message: String,
    },
    /// No answer came from the server before the call's deadline.
    #[error("{service}: no answer from {node} within {after:?}")]
    CallTimedOut {
        /// The service's full name.
        service: String,
        /// The server node the call went to.
        node: String,
        /// The call's deadline, from its start.
        after: std::time::Duration,
    },
    /// The server left the fleet or failed (discovery saw it go) before
    /// it answered.
    #[error("{service}: {node} left or failed before it answered")]
    ServerGone {
        /// The service's full name.
        service: String,
        /// The server node.
        node: String,
    },
    /// The server ran as many calls as it may, and refused this one.
    #[error("{service}: {node} is busy")]
    ServerBusy {
        /// The service's full name.
        service: String,
        /// The server node.
        node: String,
    },
    /// The request or the reply is not of the type the server announces
    /// (or the server could not decode the request).
    #[error("{service} at {node}: {reason}")]
    ServiceTypeMismatch {
        /// The service's full name.
        service: String,
        /// The server node.
        node: String,
        /// Which types, for a person to read.
        reason: String,
    },
    /// The service is sealed and this node lacks its key, or the other
    /// way round: the call could never be answered.
    #[error("{service}: not authorised: {reason}")]
    NotAuthorised {
        /// The service's full name.
        service: String,
        /// Why, for a person to read.
        reason: String,
    },
    /// A value could not be encoded as a message of its type.
    #[error("cannot encode a {type_name} message: {reason}")]
    Encode {
        /// The message type's name.
        type_name: &'static str,
        /// Why, for a person to read.
        reason: String,
    },
    /// A received payload could not be decoded.
    #[error(transparent)]
    Decode(#[from] DecodeError),
    /// The UDP port is held by a program that does not share it (pulicast
    /// nodes share their port with `SO_REUSEADDR`).
    #[error("UDP port {port} is in use by a program that does not share it")]
    PortInUse {
        /// The port.
        port: u16,
    },
    /// The operating system refused a socket operation.
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

    /// Like [`Error::io`] for binding the shared port, where "in use" has a
    /// meaning of its own.
    pub(crate) fn bind(op: &'static str, port: u16) -> impl FnOnce(io::Error) -> Self {
        move |source| match source.kind() {
            io::ErrorKind::AddrInUse => Error::PortInUse { port },
            _ => Error::Io { op, source },
        }
    }
}

// The core's errors become the API's with `?` inside the crate; their types
// are not public here, so the conversions are not shown to users either.
#[doc(hidden)]
impl From<pulicast_proto::Error> for Error {
    fn from(e: pulicast_proto::Error) -> Self {
        use pulicast_proto::Error as Core;
        match e {
            Core::InvalidName { name, reason } => Error::InvalidName { name, reason },
            Core::PayloadTooLarge { channel, size, max } => {
                Error::PayloadTooLarge { channel, size, max }
            }
            Core::InvalidConfig { setting, reason } => Error::InvalidConfig { setting, reason },
            Core::Io { op, source } => Error::Io { op, source },
        }
    }
}

#[doc(hidden)]
impl From<EncodeError> for Error {
    fn from(e: EncodeError) -> Self {
        Error::Encode {
            type_name: e.type_name,
            reason: e.reason,
        }
    }
}

/// Why a name was refused (the core decides).
pub use pulicast_proto::NameError;

/// Shorthand for results of the pulicast API.
pub type Result<T, E = Error> = std::result::Result<T, E>;
