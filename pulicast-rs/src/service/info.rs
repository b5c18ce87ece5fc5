//! Services as discovery shows them.

use crate::discovery::MemberView;
use crate::wire::service::{self as wire};
use pulicast_discovery::wire::TypeInfo;

/// One node's end of a service, as discovery announces it.
///
/// ```no_run
/// # fn demo(node: pulicast::Node) {
/// use pulicast::type_info_of;
/// // Before calling: which servers of the planner take what this node sends?
/// let mine = type_info_of::<(f64, f64)>();
/// for service in node.discovery().services().into_iter().filter(|s| s.name == "rover1/plan") {
///     for end in &service.servers {
///         let takes = end.request.as_ref().is_some_and(|t| t.fingerprint == mine.fingerprint);
///         let sealed = if end.sealed { ", sealed" } else { "" };
///         println!("{} (session {:x}{sealed}): {}", end.node, end.key, if takes { "ok" } else { "another type" });
///     }
/// }
/// # }
/// ```
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ServiceEnd {
    /// The node.
    pub node: String,
    /// Its session key (see [`MemberView::key`]).
    pub key: i64,
    /// The request type it announces.
    pub request: Option<TypeInfo>,
    /// The reply type.
    pub reply: Option<TypeInfo>,
    /// The progress type, if its handler (or its caller) uses progress.
    pub progress: Option<TypeInfo>,
    /// Whether a key seals the service there (servers only).
    pub sealed: bool,
}

/// A service as discovery shows it: made by [`services_of`] and
/// [`crate::Discovery::services`].
///
/// ```no_run
/// # async fn demo(node: pulicast::Node) {
/// let fleet = node.discovery();
/// fleet.settle(std::time::Duration::from_secs(2)).await;
/// for service in fleet.services() {
///     let types = service.server_types().map(|end| {
///         let name = |t: &Option<pulicast::TypeInfo>| t.as_ref().map_or("?".to_string(), |t| t.name.clone());
///         format!("{} -> {}", name(&end.request), name(&end.reply))
///     });
///     let (servers, clients) = (service.servers.len(), service.clients.len());
///     println!("{}: {servers} server(s), {clients} client(s), {types:?}", service.name);
/// }
/// # }
/// ```
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ServiceInfo {
    /// The service's full name (`rover1/plan`).
    pub name: String,
    /// The nodes that serve it.
    pub servers: Vec<ServiceEnd>,
    /// The nodes that have a client of it.
    pub clients: Vec<ServiceEnd>,
}

impl ServiceInfo {
    /// What a server announces beside its request channel `R`, as
    /// `R@reply` (published, with the reply type). A member that publishes
    /// one serves the service whose request channel is `R`.
    pub const REPLY_SUFFIX: &'static str = crate::wire::service::REPLY;

    /// The request channel of the service whose full name is `service`:
    /// the channel its servers subscribe and callers send requests on.
    ///
    /// ```
    /// use pulicast::ServiceInfo;
    /// assert_eq!(ServiceInfo::request_channel_of("rover1/arm/plan"), "rover1/arm/.services/plan");
    /// assert_eq!(ServiceInfo::service_of("rover1/arm/.services/plan").as_deref(), Some("rover1/arm/plan"));
    /// assert_eq!(ServiceInfo::service_of("rover1/arm/pose"), None);
    /// ```
    pub fn request_channel_of(service: &str) -> String {
        crate::wire::service::request_channel_of(service)
    }

    /// The service whose request channel `channel` is; `None` for any
    /// other channel (and for what is announced beside a request channel,
    /// such as [`ServiceInfo::REPLY_SUFFIX`]).
    pub fn service_of(channel: &str) -> Option<String> {
        crate::wire::service::service_of(channel)
    }

    /// The types its servers announce (the first server's, if they differ).
    pub fn server_types(&self) -> Option<&ServiceEnd> {
        self.servers.first()
    }
}

/// The services the live `members` serve or call, by name. Pure: what
/// discovery announces, read.
///
/// ```
/// # use pulicast::{services_of, ChannelInfo, MemberView};
/// # fn f(members: Vec<MemberView>) {
/// for service in services_of(&members) {
///     let servers: Vec<&str> = service.servers.iter().map(|s| s.node.as_str()).collect();
///     println!("{}: served by {}", service.name, servers.join(", "));
/// }
/// # }
/// ```
pub fn services_of(members: &[MemberView]) -> Vec<ServiceInfo> {
    let mut by_name: std::collections::BTreeMap<String, ServiceInfo> = Default::default();
    for member in members.iter().filter(|m| m.is_live()) {
        let beside = |request: &str, suffix: &str, publishes: bool| {
            let name = format!("{request}{suffix}");
            member
                .channels
                .iter()
                .find(|c| c.name == name && if publishes { c.publishes } else { c.subscribes })
        };
        for channel in &member.channels {
            let Some(service) = wire::service_of(&channel.name) else {
                continue;
            };
            let info = by_name
                .entry(service.clone())
                .or_insert_with(|| ServiceInfo {
                    name: service,
                    servers: Vec::new(),
                    clients: Vec::new(),
                });
            // A server announces the request channel subscribed and its
            // answers published beside it; a client the other way round. A
            // node that only subscribes the request channel (a tool that
            // watches everything, a 2.x sniffer) is neither.
            for serves in [true, false] {
                let announced = match serves {
                    true => channel.subscribes,
                    false => channel.publishes,
                };
                if !announced || beside(&channel.name, wire::REPLY, serves).is_none() {
                    continue;
                }
                let ty = |suffix| {
                    beside(&channel.name, suffix, serves).and_then(|c| c.message_type.clone())
                };
                let end = ServiceEnd {
                    node: member.name.clone(),
                    key: member.key,
                    request: channel.message_type.clone(),
                    reply: ty(wire::REPLY),
                    progress: ty(wire::PROGRESS),
                    sealed: serves && beside(&channel.name, wire::SEALED, true).is_some(),
                };
                match serves {
                    true => info.servers.push(end),
                    false => info.clients.push(end),
                }
            }
        }
    }
    by_name.into_values().collect()
}
