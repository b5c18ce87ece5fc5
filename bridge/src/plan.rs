//! What a bridge should be doing, given what it knows: a pure function of
//! the local fleet view and the other sites' tables, so every rule (which
//! channels cross, who is active, which members are relayed, what is a
//! loop) is tested without sockets or Zenoh.
//!
//! The rules:
//!
//! - **One active bridge per site and prefix.** A bridge publishes and
//!   subscribes the marker channel of its prefix
//!   ([`KeyMap::marker_channel`]); other nodes (a sniffer that subscribes
//!   every channel) don't do both. The active one also subscribes
//!   [`KeyMap::active_channel`]. A bridge stays active while no other
//!   active bridge of its prefix has a lower key; one standing by becomes
//!   active once it has watched its site for [`Inputs::settled`], no other
//!   is active, and no other standing by has a lower key. So the bridge
//!   that carries a site keeps carrying it when another starts, and a site
//!   imports a message once.
//! - **Exports**: channels that a local member publishes (not a bridge, not
//!   a member relayed from another site), that the out-filter passes and
//!   that have a key. Only messages from those members' data addresses go
//!   out ([`Plan::sources`]): what a bridge imported is never exported again.
//! - **Imports**: channels that a local member (not a bridge) subscribes,
//!   that the in-filter passes and that have a key. A sample exported by a
//!   bridge of this site is refused ([`Plan::local_bridges`]).
//! - **Members**: this site's members (not bridges, not relayed) go into
//!   its table; the members of other sites' tables are relayed here, except
//!   members this site hears itself and tables of bridges on this site.
//! - Service request channels (`.services`) and `__nodes` don't cross as
//!   channels.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::net::{IpAddr, SocketAddr};

use pulicast::{ChannelInfo, MemberInfo, MemberState, MemberView, RelayedMember, TypeInfo};

use crate::filter::Filter;
use crate::keys::{KeyMap, Unmappable};
use crate::table::{SiteMember, SiteTable};

/// What the plan is computed from.
#[derive(Debug, Clone, Copy)]
pub struct Inputs<'a> {
    /// This bridge's session key.
    pub me: i64,
    /// The members this bridge's node knows (its discovery's `members()`).
    pub local: &'a [MemberView],
    /// The other sites' tables, by their bridge's key (only bridges whose
    /// liveliness token is present).
    pub remote: &'a BTreeMap<i64, SiteTable>,
    /// The key map.
    pub keys: &'a KeyMap,
    /// Which channels go out.
    pub out: &'a Filter,
    /// Which channels come in.
    pub inn: &'a Filter,
    /// This bridge's data port: relayed members' messages come from it.
    pub data_port: u16,
    /// Whether this bridge is active now.
    pub active: bool,
    /// Whether it has watched its site long enough to know the other
    /// bridges there (a few gossip failure-detection times).
    pub settled: bool,
    /// Bridges seen on this site lately, gone or not: samples they
    /// exported, and their tables, are this site's, not another's.
    pub seen_bridges: &'a HashSet<i64>,
    /// The most channels of one member that cross (each way) and that its
    /// entry in the table lists: a member announcing thousands of names
    /// costs the plan, the table and the other sites no more.
    pub per_member: usize,
}

/// A channel going out.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Export {
    /// Its type, as its publishers here announce it.
    pub message_type: Option<TypeInfo>,
    /// The first member found publishing it (whose share it counts in).
    pub member: i64,
}

/// A channel coming in.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Import {
    /// The type to announce for it here: a remote publisher's.
    pub message_type: Option<TypeInfo>,
    /// The fingerprints its subscribers here expect (empty: any).
    pub fingerprints: Vec<[u8; 8]>,
    /// The first member found subscribing it (whose share it counts in).
    pub member: i64,
    /// Whether another site's table lists a live publisher of it. Imports
    /// that aren't (a plain Zenoh application may still publish them) take
    /// only the places left free ([`crate::slots::Slots::choose_listed`]).
    pub listed: bool,
}

/// This site's publishers whose messages may go out, found by where a
/// message comes from.
///
/// A node of ours sends every channel from its one data address, which
/// discovery announces. A Pulicast 2.x node sends each channel from a socket
/// of its own, on a port that nothing announces: its heartbeat tells only its
/// host's address and which channels it publishes. So a message from an
/// address no member of ours announces, on a 2.x publisher's host, on a
/// channel that publisher announces, is that publisher's. Addresses of our
/// members (bridges included) and this bridge's own data port are never
/// taken for a 2.x node: what a bridge imported must not go out again.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Sources {
    /// Our members' data addresses, with their member.
    pub by_address: HashMap<SocketAddr, i64>,
    /// 2.x publishers by channel and host address. Where two 2.x nodes of
    /// one host publish one channel, their messages can't be told apart:
    /// the lower key stands for both.
    pub compat: HashMap<String, HashMap<IpAddr, i64>>,
    /// Data addresses of the site's members that are not sources (bridges,
    /// this bridge), which a 2.x node can't be sending from.
    pub not_sources: HashSet<SocketAddr>,
    /// This bridge's data port (its imports come from it).
    pub own_port: u16,
    /// The keys of all sources: publishers this site hears itself.
    pub members: HashSet<i64>,
}

impl Sources {
    /// The member whose message on `channel` came from `source`, if it is a
    /// source of this site.
    pub fn of(&self, source: SocketAddr, channel: &str) -> Option<i64> {
        if let Some(key) = self.by_address.get(&source) {
            return Some(*key);
        }
        if source.port() == self.own_port || self.not_sources.contains(&source) {
            return None;
        }
        self.compat.get(channel)?.get(&source.ip()).copied()
    }

    fn add(&mut self, m: &MemberView, out: &Filter) {
        if let Some(data) = m.data_address {
            self.by_address.insert(data, m.key);
            self.members.insert(m.key);
        } else if m.compat {
            self.members.insert(m.key);
            for c in m
                .channels
                .iter()
                .filter(|c| c.publishes && out.passes(&c.name))
            {
                let hosts = self.compat.entry(c.name.clone()).or_default();
                let at = hosts.entry(m.address.ip()).or_insert(m.key);
                *at = (*at).min(m.key);
            }
        }
    }
}

/// What the bridge should be doing.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Plan {
    /// Whether this bridge is its site's active one.
    pub active: bool,
    /// Channels to export, by name.
    pub exports: BTreeMap<String, Export>,
    /// Channels to import, by name.
    pub imports: BTreeMap<String, Import>,
    /// Members of other sites to relay here.
    pub relayed: Vec<RelayedMember>,
    /// This site's members, for its table.
    pub table: Vec<SiteMember>,
    /// Whose messages may be exported: this site's publishers.
    pub sources: Sources,
    /// Bridges of this site, this one included.
    pub local_bridges: HashSet<i64>,
    /// Channels that would cross but have no key.
    pub unmappable: Vec<(String, Unmappable)>,
    /// Services of other sites' servers that this bridge answers for here:
    /// service name, then server node name, then the bridge of its site.
    pub services: BTreeMap<String, BTreeMap<String, i64>>,
}

/// Whether a member is a bridge (of any prefix): it publishes and
/// subscribes a marker.
fn is_bridge(member: &MemberView) -> bool {
    member
        .channels
        .iter()
        .any(|c| c.publishes && c.subscribes && c.name.starts_with(".puli-bridge/"))
}

/// The request channel a service channel belongs to (`NS/.services/NAME`
/// for itself and its `@reply`, `@progress`, `@sealed` companions); `None`
/// for other channels.
fn request_channel_of(name: &str) -> Option<&str> {
    name.split('/')
        .any(|part| part == ".services")
        .then(|| name.split_once('@').map_or(name, |(request, _)| request))
}

/// Channels that never cross as channels.
fn crosses_as_channel(name: &str) -> bool {
    name != "__nodes"
        && !name.starts_with(".puli-bridge")
        && !name.split('/').any(|part| part == ".services")
}

/// Computes the plan.
pub fn plan(inputs: Inputs<'_>) -> Plan {
    let Inputs {
        me,
        local,
        remote,
        keys,
        out,
        inn,
        data_port,
        active,
        settled,
        seen_bridges,
        per_member,
    } = inputs;
    let marker = keys.marker_channel();
    let active_marker = keys.active_channel();
    let here: Vec<&MemberView> = local
        .iter()
        .filter(|m| m.is_live() && m.remote.is_none())
        .collect();
    let mut plan = Plan::default();
    plan.local_bridges.insert(me);
    plan.local_bridges.extend(seen_bridges);
    let (mut lower_active, mut lower_standby, mut other_active) = (false, false, false);
    for m in &here {
        if is_bridge(m) {
            plan.local_bridges.insert(m.key);
            if m.subscribes(&marker) && m.publishes(&marker) {
                let is_active = m.subscribes(&active_marker);
                other_active |= is_active;
                lower_active |= is_active && m.key < me;
                lower_standby |= !is_active && m.key < me;
            }
        }
    }
    plan.active = if active {
        !lower_active
    } else {
        settled && !other_active && !lower_standby
    };
    if !plan.active {
        return plan;
    }
    let members: Vec<&MemberView> = here.iter().copied().filter(|m| !is_bridge(m)).collect();
    plan.sources.own_port = data_port;
    plan.sources.not_sources = here
        .iter()
        .filter(|m| is_bridge(m))
        .filter_map(|m| m.data_address)
        .collect();
    let heard: HashSet<i64> = here.iter().map(|m| m.key).collect();
    let names_here: HashSet<&str> = here.iter().map(|m| m.name.as_str()).collect();
    // Members that left or failed lately go in the table as such, so other
    // sites see a clean exit as one.
    for m in local
        .iter()
        .filter(|m| !m.is_live() && m.remote.is_none() && !is_bridge(m) && !heard.contains(&m.key))
    {
        plan.table.push(SiteMember {
            info: info_of(m, out, per_member),
            incarnation: m.incarnation,
            state: m.state,
        });
    }
    let mut unmappable = BTreeMap::new();
    for m in &members {
        plan.sources.add(m, out);
        let crossing = m.channels.iter().filter(|c| crosses_as_channel(&c.name));
        for c in crossing.take(per_member) {
            if let Err(e) = keys.key_of(&c.name) {
                if (c.publishes && out.passes(&c.name)) || (c.subscribes && inn.passes(&c.name)) {
                    unmappable.insert(c.name.clone(), e);
                }
                continue;
            }
            if c.publishes && out.passes(&c.name) {
                let export = plan.exports.entry(c.name.clone()).or_insert(Export {
                    message_type: None,
                    member: m.key,
                });
                if export.message_type.is_none() {
                    export.message_type = c.message_type.clone();
                }
            }
            if c.subscribes && inn.passes(&c.name) {
                let import = plan.imports.entry(c.name.clone()).or_insert(Import {
                    member: m.key,
                    ..Import::default()
                });
                if let Some(t) = &c.message_type {
                    if !import.fingerprints.contains(&t.fingerprint) {
                        import.fingerprints.push(t.fingerprint);
                    }
                }
            }
        }
        plan.table.push(SiteMember {
            info: info_of(m, out, per_member),
            incarnation: m.incarnation,
            state: m.state,
        });
    }
    plan.unmappable = unmappable.into_iter().collect();
    let mut relayed = HashSet::new();
    for (bridge, table) in remote {
        if plan.local_bridges.contains(bridge) {
            continue;
        }
        for member in &table.members {
            let key = member.info.key();
            if heard.contains(&key) || key == me || !relayed.insert(key) {
                continue;
            }
            let replies: HashSet<&str> = member
                .info
                .channels
                .iter()
                .filter(|c| c.publishes)
                .filter_map(|c| c.name.strip_suffix(pulicast::ServiceInfo::REPLY_SUFFIX))
                .collect();
            let live = matches!(member.state, MemberState::Alive | MemberState::Suspect);
            for c in &member.info.channels {
                if c.publishes {
                    if let Some(import) = plan.imports.get_mut(&c.name) {
                        import.listed |= live;
                        if import.message_type.is_none() {
                            import.message_type = c.message_type.clone();
                        }
                    }
                }
                // A server there: calls to it here go through this bridge,
                // unless a node of this site has its name (a call to that
                // name is that node's).
                let clash = names_here.contains(member.info.name.as_str());
                if c.subscribes && live && !clash && inn.passes(&c.name) {
                    // A server announces its answers beside the request
                    // channel; one that only subscribes it (a 2.x sniffer)
                    // never answers.
                    let answers = || replies.contains(c.name.as_str());
                    if let Some(service) = crate::call::service_of(&c.name).filter(|_| answers()) {
                        plan.services
                            .entry(service)
                            .or_default()
                            .entry(member.info.name.clone())
                            .or_insert(*bridge);
                    }
                }
            }
            let mut info = member.info.clone();
            info.data_port = data_port;
            // Services this site keeps out are not shown as callable here.
            info.channels
                .retain(|c| request_channel_of(&c.name).is_none_or(|r| inn.passes(r)));
            plan.relayed.push(RelayedMember {
                info,
                incarnation: member.incarnation,
                state: member.state,
                site: table.site.clone(),
            });
        }
    }
    plan
}

/// A member as this site's table tells it: channels it publishes that don't
/// go out are left out, so other sites don't wait for them.
fn info_of(m: &MemberView, out: &Filter, per_member: usize) -> MemberInfo {
    let session = match m.session {
        Some(s) => *s.as_bytes(),
        // A 2.x node: its key is all there is of its session.
        None => {
            let mut s = [0; 16];
            s[..8].copy_from_slice(&m.key.to_be_bytes());
            s
        }
    };
    // A service is offered to other sites if its request channel goes out.
    let channels: Vec<ChannelInfo> = m
        .channels
        .iter()
        .filter(|c| match request_channel_of(&c.name) {
            Some(request) => out.passes(request),
            None => c.subscribes || out.passes(&c.name),
        })
        .take(per_member)
        .cloned()
        .collect();
    MemberInfo {
        session,
        name: m.name.clone(),
        namespace: m.namespace.clone(),
        host: m.host.clone(),
        pid: 0,
        start_time_ms: m
            .start_time
            .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
            .map_or(0, |d| d.as_millis() as u64),
        data_port: m.data_address.map_or(0, |a| a.port()),
        channels,
        config: m.config.clone(),
        // What the view keeps of its extensions: the kinds this build
        // knows.
        extensions: m
            .receive_buffer
            .map(pulicast::Extension::receive_buffer)
            .into_iter()
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::Pattern;
    use pulicast::TypeEncoding;

    fn channel(name: &str, publishes: bool, fingerprint: u8) -> ChannelInfo {
        ChannelInfo {
            name: name.into(),
            publishes,
            subscribes: !publishes,
            period_ns: 0,
            message_type: (fingerprint != 0).then(|| TypeInfo {
                encoding: TypeEncoding::Native,
                name: format!("T{fingerprint}"),
                fingerprint: [fingerprint; 8],
                schema: vec![],
            }),
        }
    }

    fn member(key: i64, port: u16, channels: Vec<ChannelInfo>) -> MemberView {
        let mut session = [0u8; 16];
        session[..8].copy_from_slice(&key.to_be_bytes());
        let info = MemberInfo {
            session,
            name: format!("m{key}"),
            namespace: String::new(),
            host: "h".into(),
            pid: 1,
            start_time_ms: 0,
            data_port: port,
            channels,
            config: String::new(),
            extensions: Vec::new(),
        };
        MemberView::from_info(&info, SocketAddr::from(([10, 0, 0, 1], 1)))
    }

    fn bridge(key: i64, prefix: &str, active: bool) -> MemberView {
        let mut channels = vec![ChannelInfo {
            subscribes: true,
            publishes: true,
            ..channel(&format!(".puli-bridge/{prefix}"), false, 0)
        }];
        if active {
            channels.push(channel(&format!(".puli-bridge-active/{prefix}"), false, 0));
        }
        member(key, 9000, channels)
    }

    fn site(bridge: i64, members: Vec<MemberView>) -> SiteTable {
        SiteTable {
            bridge,
            bridge_name: "b".into(),
            site: "far".into(),
            version: 1,
            members: members
                .iter()
                .map(|m| SiteMember {
                    info: info_of(m, &Filter::default(), usize::MAX),
                    incarnation: 0,
                    state: MemberState::Alive,
                })
                .collect(),
        }
    }

    struct World {
        keys: KeyMap,
        out: Filter,
        inn: Filter,
        local: Vec<MemberView>,
        remote: BTreeMap<i64, SiteTable>,
        seen: HashSet<i64>,
        per_member: usize,
    }

    impl World {
        fn new(local: Vec<MemberView>) -> Self {
            Self {
                keys: KeyMap::new("fleet").unwrap(),
                out: Filter::default(),
                inn: Filter::default(),
                local,
                remote: BTreeMap::new(),
                seen: HashSet::new(),
                per_member: 1024,
            }
        }

        /// The plan of bridge `me`, active and settled.
        fn plan(&self, me: i64) -> Plan {
            self.plan_as(me, true, true)
        }

        fn plan_as(&self, me: i64, active: bool, settled: bool) -> Plan {
            plan(Inputs {
                me,
                local: &self.local,
                remote: &self.remote,
                keys: &self.keys,
                out: &self.out,
                inn: &self.inn,
                data_port: 5555,
                active,
                settled,
                seen_bridges: &self.seen,
                per_member: self.per_member,
            })
        }
    }

    #[test]
    fn a_member_announcing_thousands_of_names_crosses_with_its_share() {
        let many: Vec<ChannelInfo> = (0..5000)
            .map(|i| channel(&format!("fake/c{i}"), i % 2 == 0, 1))
            .collect();
        let mut world = World::new(vec![
            member(10, 1000, many),
            member(11, 1001, vec![channel("rover1/pose", true, 1)]),
        ]);
        world.per_member = 100;
        let plan = world.plan(1);
        let of = |member: i64| {
            let exports = plan.exports.values().filter(|e| e.member == member).count();
            let imports = plan.imports.values().filter(|i| i.member == member).count();
            exports + imports
        };
        assert_eq!(of(10), 100);
        assert_eq!(of(11), 1);
        let entry = plan
            .table
            .iter()
            .find(|m| m.info.name.contains("10"))
            .unwrap();
        assert!(
            entry.info.channels.len() <= 100,
            "{}",
            entry.info.channels.len()
        );
    }

    #[test]
    fn published_channels_go_out_and_subscribed_ones_come_in() {
        let mut world = World::new(vec![
            member(
                10,
                4000,
                vec![channel("a/pose", true, 1), channel("a/cmd", false, 2)],
            ),
            member(11, 4001, vec![channel("a/.services/go", true, 3)]),
            member(12, 4002, vec![channel("a/odd*", true, 0)]),
        ]);
        world.out.deny.push(Pattern::parse("**/secret").unwrap());
        world.local[0].channels.push(channel("a/secret", true, 0));
        let plan = world.plan(1);
        assert!(plan.active);
        assert_eq!(plan.exports.keys().collect::<Vec<_>>(), ["a/pose"]);
        assert_eq!(
            plan.exports["a/pose"]
                .message_type
                .as_ref()
                .unwrap()
                .fingerprint,
            [1; 8]
        );
        assert_eq!(plan.imports.keys().collect::<Vec<_>>(), ["a/cmd"]);
        assert_eq!(plan.imports["a/cmd"].fingerprints, vec![[2; 8]]);
        assert!(!plan.imports["a/cmd"].listed, "no other site publishes it");
        assert_eq!(plan.unmappable.len(), 1);
        assert_eq!(plan.sources.by_address.len(), 3);
        // The denied channel is not in the site's table either.
        let listed: Vec<&str> = plan.table[0]
            .info
            .channels
            .iter()
            .map(|c| c.name.as_str())
            .collect();
        assert_eq!(listed, ["a/pose", "a/cmd"]);
    }

    /// A 2.x node sends each channel from a socket of its own, on a port
    /// nothing announces: its messages are found by host and channel, and
    /// never confused with a bridge's or a node of ours.
    #[test]
    fn a_2x_publisher_is_a_source_by_host_and_channel() {
        let compat = |key: i64, ip: [u8; 4], channels: Vec<ChannelInfo>| {
            let mut m = member(key, 0, channels);
            m.session = None;
            m.compat = true;
            m.data_address = None;
            m.address = SocketAddr::from((ip, 50_000));
            m
        };
        let mut world = World::new(vec![
            compat(
                20,
                [10, 0, 0, 2],
                vec![channel("talk", true, 0), channel("hear", false, 0)],
            ),
            compat(21, [10, 0, 0, 3], vec![channel("talk", true, 0)]),
            compat(22, [10, 0, 0, 3], vec![channel("talk", true, 0)]),
            member(10, 4000, vec![channel("talk", true, 0)]),
            bridge(5, "other", true),
        ]);
        world.out.deny.push(Pattern::parse("secret").unwrap());
        world.local[0].channels.push(channel("secret", true, 0));
        let plan = world.plan_as(1, true, true);
        assert!(plan.exports.contains_key("talk"));
        assert!(plan.imports.contains_key("hear"));
        let s = &plan.sources;
        let at = |ip: [u8; 4], port: u16| SocketAddr::from((ip, port));
        // Any port of the 2.x node's host, on a channel it publishes.
        assert_eq!(s.of(at([10, 0, 0, 2], 41_234), "talk"), Some(20));
        assert_eq!(
            s.of(at([10, 0, 0, 2], 41_235), "hear"),
            None,
            "not published"
        );
        assert_eq!(
            s.of(at([10, 0, 0, 2], 41_236), "secret"),
            None,
            "not exported"
        );
        assert_eq!(
            s.of(at([10, 0, 0, 9], 41_234), "talk"),
            None,
            "another host"
        );
        // Two of one host on one channel: the lower key stands for both.
        assert_eq!(s.of(at([10, 0, 0, 3], 1234), "talk"), Some(21));
        // Ours by their announced address; bridges' and this bridge's
        // own port (what it imported) never, though on a 2.x host.
        world.local[3].data_address = Some(at([10, 0, 0, 2], 4000));
        world.local[4].data_address = Some(at([10, 0, 0, 2], 9000));
        let plan = world.plan_as(1, true, true);
        let s = &plan.sources;
        assert_eq!(s.of(at([10, 0, 0, 2], 4000), "talk"), Some(10));
        assert_eq!(s.of(at([10, 0, 0, 2], 9000), "talk"), None, "a bridge");
        let own = SocketAddr::from(([10, 0, 0, 2], s.own_port));
        assert_eq!(s.of(own, "talk"), None, "this bridge's imports");
        assert!(s.members.contains(&20) && s.members.contains(&10));
        assert!(!s.members.contains(&5));
    }

    #[test]
    fn one_bridge_of_a_prefix_is_active_and_bridges_are_never_sources() {
        let mut world = World::new(vec![
            bridge(5, "fleet", false),
            bridge(2, "other", true),
            member(10, 4000, vec![channel("a/pose", true, 0)]),
        ]);
        // Standing by: not before it has watched its site, not while a
        // bridge of a lower key stands by too.
        assert!(!world.plan_as(7, false, false).active);
        assert!(!world.plan_as(7, false, true).active, "5 is lower");
        let plan = world.plan_as(3, false, true);
        assert!(plan.active, "2 bridges another prefix");
        assert_eq!(plan.local_bridges, HashSet::from([3, 5, 2]));
        assert!(!plan.sources.members.contains(&5) && !plan.sources.members.contains(&2));
        let from =
            |key: i64| SocketAddr::from(([10, 0, 0, 1], if key == 10 { 4000 } else { 9000 }));
        assert_eq!(plan.sources.of(from(10), "a/pose"), Some(10));
        assert_eq!(plan.sources.of(from(5), "a/pose"), None);
        assert!(plan.table.iter().all(|m| m.info.key() == 10));
        // An active bridge keeps the site when one of a lower key starts.
        assert!(world.plan_as(7, true, true).active);
        // Two active at once (they started together): the lower one stays.
        world.local[0] = bridge(5, "fleet", true);
        assert!(!world.plan_as(7, true, true).active);
        assert!(world.plan_as(3, true, true).active);
        let standby = world.plan_as(9, false, true);
        assert!(!standby.active && standby.exports.is_empty() && standby.relayed.is_empty());
        // A bridge that failed stands nobody by.
        world.local[0].state = MemberState::Dead;
        assert!(world.plan_as(7, false, true).active);
        // A node that only subscribes the marker (a sniffer) is no bridge.
        let mut sniffer = member(1, 4001, vec![]);
        sniffer.channels.push(ChannelInfo {
            subscribes: true,
            ..channel(".puli-bridge/fleet", false, 0)
        });
        world.local.push(sniffer);
        let plan = world.plan_as(7, false, true);
        assert!(plan.active);
        assert!(!plan.local_bridges.contains(&1));
    }

    #[test]
    fn servers_of_other_sites_are_answered_for_here() {
        let mut world = World::new(vec![member(10, 4000, vec![])]);
        let server = |key, name: &str| {
            let mut m = member(
                key,
                7000,
                vec![
                    ChannelInfo {
                        subscribes: true,
                        ..channel("rover1/.services/plan", false, 3)
                    },
                    channel("rover1/.services/plan@reply", true, 4),
                ],
            );
            m.name = name.into();
            m
        };
        // A node that subscribes the request channel and announces no
        // answers (a 2.x sniffer, a recorder) is no server.
        let mut watcher = server(41, "sniffer");
        watcher.channels.pop();
        world
            .remote
            .insert(20, site(20, vec![server(21, "planner")]));
        world
            .remote
            .insert(30, site(30, vec![server(31, "planner2")]));
        world.remote.insert(40, site(40, vec![watcher]));
        let plan = world.plan(1);
        let nodes = &plan.services["rover1/plan"];
        assert_eq!(nodes.get("planner"), Some(&20));
        assert_eq!(nodes.get("planner2"), Some(&30));
        assert_eq!(nodes.get("sniffer"), None);
        // Not when the in-filter keeps the service out.
        world
            .inn
            .deny
            .push(Pattern::parse("**/.services/*").unwrap());
        assert!(world.plan(1).services.is_empty());
    }

    #[test]
    fn members_that_left_are_in_the_table_as_left() {
        let mut world = World::new(vec![member(10, 4000, vec![]), member(11, 4001, vec![])]);
        world.local[1].state = MemberState::Left;
        let plan = world.plan(1);
        let states: Vec<(i64, MemberState)> =
            plan.table.iter().map(|m| (m.info.key(), m.state)).collect();
        assert!(states.contains(&(11, MemberState::Left)));
        assert!(states.contains(&(10, MemberState::Alive)));
    }

    #[test]
    fn other_sites_are_relayed_but_not_this_sites_own_members_or_bridges() {
        let mut world = World::new(vec![
            bridge(8, "fleet", false),
            member(10, 4000, vec![channel("a/cmd", false, 2)]),
        ]);
        world.remote.insert(
            20,
            site(20, vec![member(21, 7000, vec![channel("a/cmd", true, 2)])]),
        );
        // A table from a bridge of this site (8), and one listing a member
        // heard here (10), and the same far member twice.
        world
            .remote
            .insert(8, site(8, vec![member(10, 4000, vec![])]));
        world.remote.insert(
            30,
            site(30, vec![member(10, 4000, vec![]), member(21, 7000, vec![])]),
        );
        let plan = world.plan(1);
        let relayed: Vec<i64> = plan.relayed.iter().map(|r| r.info.key()).collect();
        assert_eq!(relayed, [21]);
        assert!(plan.services.is_empty());
        assert_eq!(plan.relayed[0].info.data_port, 5555);
        assert_eq!(plan.relayed[0].site, "far");
        assert_eq!(
            plan.imports["a/cmd"]
                .message_type
                .as_ref()
                .unwrap()
                .fingerprint,
            [2; 8]
        );
        assert!(plan.imports["a/cmd"].listed, "site 20 lists its publisher");
        // Members relayed here by another bridge are not this site's.
        let mut relayed_view = member(21, 5555, vec![channel("a/cmd", true, 2)]);
        relayed_view.remote = Some(pulicast::Remote::new(1, "far"));
        world.local.push(relayed_view);
        let plan = world.plan(1);
        assert!(plan.exports.is_empty());
        assert!(plan.table.iter().all(|m| m.info.key() == 10));
    }
}
