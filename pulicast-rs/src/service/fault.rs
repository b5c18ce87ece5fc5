//! A server's own failure, as its caller sees it.

use crate::error::Error;
use crate::runtime::serving::Failure;
use crate::wire::service::code;

/// A server's own failure, sent back to the caller as its
/// [`Error::CallFailed`]: a code (use [`Fault::APPLICATION`] and above;
/// those below are pulicast's, as named by the constants here) and a
/// message for a person.
///
/// ```
/// use pulicast::Fault;
/// let f = Fault::new(1001, "no path to the goal");
/// assert_eq!(f.to_string(), "no path to the goal (code 1001)");
/// assert_eq!(Fault::msg("out of range").code, Fault::APPLICATION);
/// ```
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{message} (code {code})")]
pub struct Fault {
    /// The code.
    pub code: u16,
    /// What went wrong.
    pub message: String,
}

impl Fault {
    /// The request did not decode as the server's request type.
    pub const BAD_REQUEST: u16 = code::BAD_REQUEST;
    /// The handler panicked.
    pub const PANICKED: u16 = code::PANICKED;
    /// The caller cancelled the call.
    pub const CANCELLED: u16 = code::CANCELLED;
    /// The call's deadline passed at the server.
    pub const DEADLINE: u16 = code::DEADLINE;
    /// The call ran, and its answer was too large to keep for a
    /// retransmitted request (it is not run again).
    pub const LOST: u16 = code::LOST;
    /// The reply did not encode as the server's reply type.
    pub const BAD_REPLY: u16 = code::BAD_REPLY;
    /// The server left the fleet, or failed, before it answered: a
    /// caller's own conclusion from discovery, never sent.
    pub const SERVER_GONE: u16 = code::SERVER_GONE;
    /// A bridge could not run the call on the server's site: the site is
    /// out of reach, the server is not there (any more), busy, or refused
    /// the bridge's call (its types or keys).
    pub const UNREACHABLE: u16 = code::UNREACHABLE;
    /// The first code for handlers' own failures (and what [`Fault::msg`]
    /// uses).
    pub const APPLICATION: u16 = code::APPLICATION;

    /// A failure with a code of the handler's choosing.
    pub fn new(code: u16, message: impl Into<String>) -> Self {
        Self {
            code,
            message: message.into(),
        }
    }

    /// A failure with the first application code.
    pub fn msg(message: impl Into<String>) -> Self {
        Self::new(code::APPLICATION, message)
    }
}

impl Fault {
    /// The fault as the runtime sends it.
    pub(crate) fn into_failure(self) -> Failure {
        Failure::new(self.code, self.message)
    }
}

impl From<String> for Fault {
    fn from(message: String) -> Self {
        Self::msg(message)
    }
}

/// A pulicast error inside a handler (a progress message that would not
/// encode, say) fails the call with its text, so `?` works there.
impl From<Error> for Fault {
    fn from(e: Error) -> Self {
        Self::msg(e.to_string())
    }
}

impl From<&str> for Fault {
    fn from(message: &str) -> Self {
        Self::msg(message)
    }
}
