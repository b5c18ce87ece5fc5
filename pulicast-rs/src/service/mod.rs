//! Services: calls with a reply, progress on the way, and cancel, between
//! nodes or inside one. The wire is [`crate::wire::service`]; what a call
//! and a server decide is [`crate::proto::call`] and
//! [`crate::proto::service`]; `docs/services.md` has the whole story.

mod call;
mod client;
mod fault;
mod info;
mod namespace;
mod nearest;
mod server;
mod typed;

pub use call::RawCall;
pub use client::{Answer, RawClient};
pub use fault::Fault;
pub use info::{services_of, ServiceEnd, ServiceInfo};
pub use server::{CallContext, Server, ServerBuilder, ServiceTypes};
pub use typed::{Client, OngoingCall};

use std::sync::{Arc, Weak};
use std::time::Duration;

use crate::channel::Namespace;
use crate::error::{Error, NameError, Result};
use crate::name::resolve_name;
use crate::runtime::{ChannelState, Inner};
use crate::wire::service::{self as wire};
use crate::wire::{self as codec};
use crate::Schema;
use pulicast_discovery::wire::TypeInfo;

/// How long a call waits for its reply unless told otherwise
/// ([`Client::with_deadline`], [`Client::call_within`]).
pub const DEFAULT_DEADLINE: Duration = Duration::from_secs(5);

/// How long the servers a client found serve its calls before it reads
/// discovery again (a server gone meanwhile is seen by the call).
const TARGETS_FRESH: Duration = Duration::from_millis(100);

/// Announcements a server or client holds in discovery, let go on drop.
struct Held {
    inner: Weak<Inner>,
    held: Vec<(Arc<ChannelState>, bool)>,
}

impl Held {
    fn new(inner: &Arc<Inner>) -> Self {
        Self {
            inner: Arc::downgrade(inner),
            held: Vec::new(),
        }
    }

    /// Announces `channel` as published (`publishes`) or subscribed, with
    /// type `ty` if given.
    fn hold(
        &mut self,
        inner: &Inner,
        channel: Arc<ChannelState>,
        publishes: bool,
        ty: Option<TypeInfo>,
    ) {
        let mut changed = channel.hold(publishes);
        if let Some(ty) = ty {
            changed |= channel.note_type(ty.fingerprint, || ty.clone());
        }
        if changed {
            inner.announce_change();
        }
        self.held.push((channel, publishes));
    }
}

impl Drop for Held {
    fn drop(&mut self) {
        let changed = self.held.drain(..).fold(false, |changed, (c, publishes)| {
            c.release(publishes) | changed
        });
        if let Some(inner) = self.inner.upgrade().filter(|_| changed) {
            inner.announce_change();
        }
    }
}

/// A service's full name and request channel from a name as given
/// (`plan`, `../rover2/plan`), resolved in `ns`.
fn service_names(ns: &Namespace, name: &str) -> Result<(String, String)> {
    if name.contains(wire::TARGET_MARK) {
        return Err(Error::InvalidName {
            name: name.to_string(),
            reason: NameError::Reserved,
        });
    }
    let full = resolve_name(name, ns.path())?;
    let request = wire::request_channel_of(&full);
    // Checked as any channel name (and so the service's name with it).
    resolve_name(&request, "")?;
    Ok((full, request))
}

/// The type announced for `T`; none for raw bytes, which carry none.
fn type_info<T: Schema + ?Sized>() -> Option<TypeInfo> {
    (!codec::is_raw_bytes(T::SCHEMA)).then(codec::type_info_of::<T>)
}

fn is_unit<T: Schema + ?Sized>() -> bool {
    matches!(T::SCHEMA.ty, postcard_schema::schema::DataModelType::Unit)
}
