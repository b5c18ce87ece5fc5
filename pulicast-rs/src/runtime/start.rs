//! Starting a node: its sockets, its shared state and its tasks, from
//! settings the builder checked.

use std::collections::BTreeMap;
use std::net::{Ipv4Addr, SocketAddrV4};
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use fleet::DiscoveryOptions;
use pulicast_discovery::compat::Membership;
use pulicast_discovery::wire::{Extension, MemberInfo};
use uuid::Uuid;

use super::eligibility::Eligibility;
use super::fleet::{DiscoveryState, Fleet};
use super::{
    compat_session_id, drive, fleet, services, start_tasks, Channels, Identity, Inner, Lifecycle,
    Receiving, Sending, Tuning,
};
use crate::error::{Error, Result};
use crate::proto::fragment::ReassemblyLimits;
use crate::proto::receiver;
use crate::proto::setting::FileValue;
use crate::proto::Receiver;
use crate::queue::QueuePolicy;
use crate::security::Security;
use crate::security::SecurityOptions;
use crate::stats::Counters;
use crate::transport::NetConfig;
use crate::transport::{self, ReceivePool};
use crate::wire::DISCOVERY_CHANNEL;

/// A node's settings, as [`crate::NodeBuilder`] collects and checks them.
#[derive(Debug, Clone)]
pub(crate) struct Settings {
    pub(crate) name: String,
    /// As given; resolved by the builder's check.
    pub(crate) namespace: String,
    pub(crate) port: u16,
    pub(crate) ttl: u32,
    pub(crate) interface: Option<Ipv4Addr>,
    pub(crate) heartbeat_period: Duration,
    pub(crate) queue_capacity: usize,
    pub(crate) queue_policy: QueuePolicy,
    pub(crate) discovery: DiscoveryOptions,
    pub(crate) compat_heartbeat: bool,
    pub(crate) receive_spin: Duration,
    pub(crate) receive_buffer: usize,
    /// Bytes a second for messages in fragments; `None`: not paced.
    pub(crate) fragment_rate: Option<u64>,
    pub(crate) reassembly: ReassemblyLimits,
    pub(crate) security: SecurityOptions,
    pub(crate) settings_file: Option<std::path::PathBuf>,
    /// As given; `None` reads `PULICAST_CONFIG` (see `NodeBuilder::config`).
    pub(crate) config: Option<String>,
}

/// Start-up values of settings, read from [`Settings::settings_file`].
#[derive(Debug, Default)]
pub(crate) struct StartValues {
    /// The file, for messages.
    pub(crate) file: String,
    pub(crate) values: BTreeMap<String, Result<FileValue, String>>,
}

impl StartValues {
    fn read(path: &std::path::Path) -> Result<Self> {
        let bad = |reason: String| {
            Error::config("settings file", format!("{}: {reason}", path.display()))
        };
        let text = std::fs::read_to_string(path).map_err(|e| bad(e.to_string()))?;
        let values = crate::proto::setting::read_settings_file(&text).map_err(bad)?;
        Ok(Self {
            file: path.display().to_string(),
            values,
        })
    }
}

impl Settings {
    /// Opens the sockets and starts the node's tasks on `runtime`, with
    /// `namespace` (resolved) as the node's namespace. A failure after the
    /// first task started stops what started.
    pub(crate) fn start(
        self,
        namespace: String,
        runtime: tokio::runtime::Handle,
        own_runtime: Option<Arc<drive::OwnRuntime>>,
    ) -> Result<Arc<Inner>> {
        let start_values = match &self.settings_file {
            Some(path) => StartValues::read(path)?,
            None => StartValues::default(),
        };
        let security = Security::new(&self.security)?;
        let config =
            crate::node::configuration(self.config.as_deref(), |name| std::env::var(name).ok())?;
        let net = NetConfig {
            port: self.port,
            ttl: self.ttl,
            interface: self.interface,
            receive_buffer: self.receive_buffer,
        };
        let send = transport::send_socket(&net).map_err(Error::io("opening the send socket"))?;
        transport::warn_pinned_to_loopback(&net);
        let data_port = send
            .local_addr()
            .map_err(Error::io("reading the send socket's address"))?
            .port();
        let session = Uuid::new_v4();
        let start_time_ms = fleet::unix_ms();
        let host = fleet::host_name();
        // What the node announces beyond the fixed fields: the receive
        // buffer its sockets get, which publishers pace fragments to.
        let extensions: Vec<_> = net
            .granted_receive_buffer()
            .map(|granted| Extension::receive_buffer(u32::try_from(granted).unwrap_or(u32::MAX)))
            .into_iter()
            .collect();
        let discovery_state = if self.discovery.enabled {
            let socket = transport::discovery_socket(&net, self.discovery.port)
                .map_err(Error::io("opening the discovery socket"))?;
            let info = MemberInfo {
                session: *session.as_bytes(),
                name: self.name.clone(),
                namespace: namespace.clone(),
                host: host.clone(),
                pid: std::process::id(),
                start_time_ms,
                data_port,
                channels: Vec::new(),
                config: config.clone(),
                extensions: extensions.clone(),
            };
            let port = socket
                .local_addr()
                .map_err(Error::io("reading the discovery socket's address"))?
                .port();
            // Multicast leaves from the interface's address; unicast may
            // take another route, or a NAT, so only multicast is bound to
            // an address.
            let multicast =
                SocketAddrV4::new(net.send_interface().unwrap_or(Ipv4Addr::UNSPECIFIED), port);
            let unbound = SocketAddrV4::new(Ipv4Addr::UNSPECIFIED, 0);
            let channel = DISCOVERY_CHANNEL;
            let sealers = security
                .as_ref()
                .and_then(|s| Some((s.sealer(channel, multicast)?, s.sealer(channel, unbound)?)));
            let state = DiscoveryState::new(
                socket,
                fleet::group(self.port),
                info,
                self.heartbeat_period,
                &self.discovery.seeds,
                sealers,
            )
            .map_err(Error::io("setting up discovery"))?;
            Some(state)
        } else {
            None
        };
        // Known for sure only when the node chose the interface; where the
        // routes choose, it is left open (and so unchecked by receivers).
        let origin = SocketAddrV4::new(
            net.send_interface().unwrap_or(Ipv4Addr::UNSPECIFIED),
            data_port,
        );
        let source_ip = net.source_ip();
        let discovery_sealed = security
            .as_ref()
            .is_some_and(|s| s.covers(DISCOVERY_CHANNEL));
        let mut own_ports = vec![data_port];
        own_ports.extend(discovery_state.as_ref().and_then(|d| d.local_port()));
        let receiver_config = receiver::ReceiverConfig {
            limits: self.reassembly,
            opener: security.as_ref().map(Security::opener),
            gossip: discovery_state.is_some(),
            gossip_sealed: discovery_sealed,
            own_ip: source_ip,
            own_ports,
        };
        let inner = Arc::new(Inner {
            identity: Identity {
                name: self.name,
                session,
                compat_session_id: compat_session_id(&session),
                namespace: namespace.clone(),
                host,
                start_time_ms,
                started: Instant::now(),
                port: self.port,
                data_port,
                origin,
                source_ip,
                config,
                extensions,
            },
            tuning: Tuning {
                heartbeat_period: self.heartbeat_period,
                queue_capacity: self.queue_capacity,
                queue_policy: self.queue_policy,
                receive_spin: self.receive_spin,
                compat_heartbeat: self.compat_heartbeat,
            },
            channels: Channels::new(),
            sending: Sending::new(
                send,
                Eligibility::new(compat_session_id(&session), super::fleet::COMPAT_GRACE),
                self.fragment_rate,
            ),
            receiving: Receiving::new(Receiver::new(receiver_config), ReceivePool::new(net)),
            fleet: Fleet::new(discovery_state),
            membership: Mutex::new(Membership::new(self.heartbeat_period)),
            counters: Counters::new(),
            security,
            start_values,
            services: services::Services::default(),
            lifecycle: Lifecycle {
                stopped: AtomicBool::new(false),
                stop_signal: tokio::sync::Notify::new(),
                runtime,
                own_runtime,
                tasks: Mutex::new(Vec::new()),
            },
        });
        // From here on the node runs: a failure must stop what started.
        if let Err(e) = start_tasks(&inner) {
            inner.stop();
            return Err(e);
        }
        tracing::debug!(node = %inner.identity.name, session = %inner.identity.session, "node started");
        Ok(inner)
    }

    /// Starts the node on a thread of its own, with a current-thread tokio
    /// runtime that hosts its tasks until it stops (for programs without
    /// async code).
    pub(crate) fn start_on_own_thread(self, namespace: String) -> Result<Arc<Inner>> {
        let (tx, rx) = std::sync::mpsc::channel();
        // A NUL in a thread's name panics the spawn: a node's name may hold
        // one (it is the user's), the thread's does not.
        let thread_name = format!(
            "pulicast-{}",
            self.name
                .chars()
                .take(16)
                .map(|c| if c == '\0' { '?' } else { c })
                .collect::<String>()
        );
        std::thread::Builder::new()
            .name(thread_name)
            .spawn(move || {
                let runtime = match tokio::runtime::Builder::new_current_thread()
                    .enable_all()
                    .build()
                {
                    Ok(rt) => rt,
                    Err(e) => {
                        let _ = tx.send(Err(Error::Io {
                            op: "creating the node's runtime",
                            source: e,
                        }));
                        return;
                    }
                };
                let handle = runtime.handle().clone();
                let runtime = Arc::new(runtime);
                let own = drive::OwnRuntime::new(&runtime);
                let started = runtime
                    .block_on(async { self.start(namespace, handle, Some(Arc::clone(&own))) });
                let inner = started.as_ref().ok().map(Arc::clone);
                if tx.send(started).is_err() {
                    return;
                }
                if let Some(inner) = inner {
                    own.run(&runtime, &inner);
                }
            })
            .map_err(Error::io("spawning the node's runtime thread"))?;
        rx.recv().unwrap_or(Err(Error::NodeStopped))
    }
}
