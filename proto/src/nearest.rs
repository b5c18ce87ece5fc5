//! The search for the nearest provider of a name, in DROS's order.
//!
//! DROS finds a server by its name, a configuration and a robot, and
//! tries `Server.Config.Robot`, then `Server.Config.*`, then
//! `Server.*.Robot`, then `Server.*.*`, instantiating the first listing
//! that exists and going on when that fails. Here the robot axis is the
//! namespace (`laser` from `rover1/arm` is `rover1/arm/laser`, then
//! `rover1/laser`, then `laser`, the fleet-wide entry) and the
//! configuration is what a node announces (empty: none, DROS's `*`). The
//! configuration is the outer axis: a user's own provider anywhere in
//! the namespace wins over everyone's, and a provider on the same robot
//! wins over a fleet-wide one.
//!
//! This module is pure: it orders what discovery knows. Trying the
//! candidates (a call that may find a server busy or silent, a
//! subscription that moves when its publisher stops) is the runtime's.

use crate::error::Result;
use crate::name::resolve_name;
use crate::view::MemberView;

/// One step of the search: providers of `channel` that run in
/// configuration `config` (empty: those of none).
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct Step {
    /// The configuration a provider must announce; empty for none.
    pub config: String,
    /// The resolved name it must provide.
    pub channel: String,
}

/// The steps of the search for `name` from `namespace` by a node in
/// configuration `config`, in order: the own configuration (if any) before
/// none, and within each, the namespace from the innermost to the root. A
/// name with a leading `/` is looked up only as given; `..` resolves from
/// each namespace in turn, and names that resolve alike are one step.
/// Fails if `name` resolves nowhere (bad characters, too long, the root).
///
/// ```
/// use pulicast_proto::nearest::{search_steps, Step};
/// let steps = search_steps("laser", "rover1/arm", "alice")?;
/// let order: Vec<(&str, &str)> =
///     steps.iter().map(|s| (s.config.as_str(), s.channel.as_str())).collect();
/// assert_eq!(order, [
///     ("alice", "rover1/arm/laser"), ("alice", "rover1/laser"), ("alice", "laser"),
///     ("", "rover1/arm/laser"), ("", "rover1/laser"), ("", "laser"),
/// ]);
/// # Ok::<(), pulicast_proto::Error>(())
/// ```
pub fn search_steps(name: &str, namespace: &str, config: &str) -> Result<Vec<Step>> {
    // The namespace itself must resolve, or no prefix of it means anything.
    let namespace = crate::name::resolve_path(namespace, "")?;
    let parts: Vec<&str> = namespace.split('/').filter(|p| !p.is_empty()).collect();
    let prefixes: Vec<String> = if name.starts_with('/') {
        vec![String::new()]
    } else {
        (0..=parts.len())
            .rev()
            .map(|n| parts[..n].join("/"))
            .collect()
    };
    let mut channels: Vec<String> = Vec::new();
    let mut first_error = None;
    for prefix in &prefixes {
        match resolve_name(name, prefix) {
            Ok(channel) if !channels.contains(&channel) => channels.push(channel),
            Ok(_) => {}
            Err(e) => {
                first_error.get_or_insert(e);
            }
        }
    }
    if channels.is_empty() {
        return Err(first_error.unwrap_or_else(|| crate::Error::InvalidName {
            name: name.to_string(),
            reason: crate::NameError::Empty,
        }));
    }
    let configs: &[&str] = if config.is_empty() {
        &[""]
    } else {
        &[config, ""]
    };
    Ok(configs
        .iter()
        .flat_map(|config| {
            channels.iter().map(|channel| Step {
                config: config.to_string(),
                channel: channel.clone(),
            })
        })
        .collect())
}

/// Who is asking: its key and host, so that ties at one step go to the
/// nearest first.
#[derive(Debug, Clone, Copy)]
pub struct Seeker<'a> {
    /// The asking node's key ([`MemberView::key`]).
    pub key: i64,
    /// The host it runs on.
    pub host: &'a str,
}

/// The candidates for `steps` among `members`, in the order to try them:
/// step by step, the live members in the step's configuration for which
/// `provides(member, channel)` holds. Several at one step are ordered
/// nearest first, and the same way every time: the seeker itself, then
/// members on its host, then the others, each group by name and key. A
/// member that provides several of the names (`rover1/laser` and `laser`)
/// is a candidate at each: they are different providers. Returns
/// (step index, member index) pairs.
///
/// ```
/// use pulicast_proto::nearest::{candidates, search_steps, Seeker};
/// use pulicast_proto::view::MemberView;
/// # fn server(name: &str, config: &str, key: i64) -> MemberView {
/// #     let info = pulicast_discovery::wire::MemberInfo {
/// #         session: [0; 16], name: name.into(), namespace: String::new(),
/// #         host: "h".into(), pid: 1, start_time_ms: 0, data_port: 1,
/// #         channels: vec![], config: config.into(), extensions: vec![],
/// #     };
/// #     let mut m = MemberView::from_info(&info, "127.0.0.1:1".parse().unwrap());
/// #     m.key = key;
/// #     m
/// # }
/// let fleet = vec![server("everyones", "", 1), server("alices", "alice", 2)];
/// let steps = search_steps("laser", "rover1", "alice")?;
/// let seeker = Seeker { key: 9, host: "h" };
/// let order = candidates(&steps, &fleet, seeker, |_, channel| channel == "laser");
/// // Alice's own server first, though both serve the fleet-wide `laser`.
/// assert_eq!(order.iter().map(|&(_, m)| fleet[m].name.as_str()).collect::<Vec<_>>(),
///            ["alices", "everyones"]);
/// # Ok::<(), pulicast_proto::Error>(())
/// ```
pub fn candidates(
    steps: &[Step],
    members: &[MemberView],
    seeker: Seeker<'_>,
    provides: impl Fn(&MemberView, &str) -> bool,
) -> Vec<(usize, usize)> {
    let mut order = Vec::new();
    for (s, step) in steps.iter().enumerate() {
        let mut here: Vec<usize> = members
            .iter()
            .enumerate()
            .filter(|(_, m)| m.is_live() && m.config == step.config && provides(m, &step.channel))
            .map(|(i, _)| i)
            .collect();
        here.sort_by(|&a, &b| {
            let rank = |m: &MemberView| (m.key != seeker.key, m.host != seeker.host);
            let (a, b) = (&members[a], &members[b]);
            (rank(a), &a.name, a.key).cmp(&(rank(b), &b.name, b.key))
        });
        order.extend(here.into_iter().map(|i| (s, i)));
    }
    order
}

#[cfg(test)]
mod tests {
    use super::*;
    use pulicast_discovery::wire::{ChannelInfo, MemberInfo, MemberState};

    fn steps(name: &str, namespace: &str, config: &str) -> Vec<(String, String)> {
        search_steps(name, namespace, config)
            .unwrap()
            .into_iter()
            .map(|s| (s.config, s.channel))
            .collect()
    }

    fn pairs(list: &[(&str, &str)]) -> Vec<(String, String)> {
        list.iter()
            .map(|(c, n)| (c.to_string(), n.to_string()))
            .collect()
    }

    #[test]
    fn the_order_is_configuration_outer_namespace_inner() {
        // DROS: Server.Config.Robot, Server.Config.*, Server.*.Robot, Server.*.*
        assert_eq!(
            steps("laser", "rover1", "alice"),
            pairs(&[
                ("alice", "rover1/laser"),
                ("alice", "laser"),
                ("", "rover1/laser"),
                ("", "laser"),
            ])
        );
        // Without a configuration only the `*` half is searched.
        assert_eq!(
            steps("laser", "rover1/arm", ""),
            pairs(&[
                ("", "rover1/arm/laser"),
                ("", "rover1/laser"),
                ("", "laser")
            ])
        );
        // From the root there is one namespace.
        assert_eq!(
            steps("laser", "", "alice"),
            pairs(&[("alice", "laser"), ("", "laser")])
        );
        // A path inside the name keeps its parts at every level.
        assert_eq!(
            steps("sensors/laser", "rover1", ""),
            pairs(&[("", "rover1/sensors/laser"), ("", "sensors/laser")])
        );
    }

    #[test]
    fn a_leading_slash_is_looked_up_as_given_and_dots_resolve_per_level() {
        assert_eq!(
            steps("/laser", "rover1/arm", "alice"),
            pairs(&[("alice", "laser"), ("", "laser")])
        );
        // `..` from rover1/arm is rover1/laser, from rover1 the root's
        // laser, and from the root it stays there: one step, not two.
        assert_eq!(
            steps("../laser", "rover1/arm", ""),
            pairs(&[("", "rover1/laser"), ("", "laser")])
        );
        assert_eq!(steps("./laser", "rover1", ""), steps("laser", "rover1", ""));
    }

    #[test]
    fn a_name_that_resolves_nowhere_fails() {
        assert!(search_steps("", "rover1", "").is_err());
        assert!(search_steps("..", "rover1", "").is_err());
        assert!(search_steps("läser", "rover1", "").is_err());
        assert!(search_steps("laser", "röver", "").is_err());
    }

    fn member(name: &str, key: i64, host: &str, config: &str, serves: &[&str]) -> MemberView {
        let info = MemberInfo {
            session: [0; 16],
            name: name.into(),
            namespace: String::new(),
            host: host.into(),
            pid: 1,
            start_time_ms: 0,
            data_port: 1,
            channels: serves
                .iter()
                .map(|c| ChannelInfo {
                    name: c.to_string(),
                    publishes: true,
                    subscribes: false,
                    period_ns: 0,
                    message_type: None,
                })
                .collect(),
            config: config.into(),
            extensions: Vec::new(),
        };
        let mut m = MemberView::from_info(&info, "127.0.0.1:1".parse().unwrap());
        m.key = key;
        m
    }

    fn names(steps: &[Step], fleet: &[MemberView], seeker: Seeker<'_>) -> Vec<String> {
        candidates(steps, fleet, seeker, |m, c| m.publishes(c))
            .into_iter()
            .map(|(s, i)| format!("{}@{}", fleet[i].name, steps[s].channel))
            .collect()
    }

    #[test]
    fn each_step_of_the_order_wins_over_the_next() {
        let fleet = vec![
            member("none_root", 1, "a", "", &["laser"]),
            member("none_rover", 2, "a", "", &["rover1/laser"]),
            member("alice_root", 3, "a", "alice", &["laser"]),
            member("alice_rover", 4, "a", "alice", &["rover1/laser"]),
            // Another user's: never found from alice's configuration.
            member("bob_rover", 5, "a", "bob", &["rover1/laser"]),
        ];
        let seeker = Seeker { key: 99, host: "a" };
        let steps = search_steps("laser", "rover1", "alice").unwrap();
        assert_eq!(
            names(&steps, &fleet, seeker),
            [
                "alice_rover@rover1/laser",
                "alice_root@laser",
                "none_rover@rover1/laser",
                "none_root@laser"
            ]
        );
        // Gone from the fleet, a step is skipped; dead members are not
        // candidates.
        let mut fewer = fleet.clone();
        fewer[3].state = MemberState::Dead;
        assert_eq!(names(&steps, &fewer, seeker)[0], "alice_root@laser");
        // Without a configuration, configured providers are invisible.
        let steps = search_steps("laser", "rover1", "").unwrap();
        assert_eq!(
            names(&steps, &fleet, seeker),
            ["none_rover@rover1/laser", "none_root@laser"]
        );
    }

    #[test]
    fn ties_go_to_the_seeker_then_its_host_then_by_name() {
        let fleet = vec![
            member("b_far", 1, "far", "", &["laser"]),
            member("a_far", 2, "far", "", &["laser"]),
            member("z_near", 3, "here", "", &["laser"]),
            member("me", 4, "here", "", &["laser"]),
        ];
        let steps = search_steps("laser", "", "").unwrap();
        let seeker = Seeker {
            key: 4,
            host: "here",
        };
        let order = names(&steps, &fleet, seeker);
        assert_eq!(
            order,
            ["me@laser", "z_near@laser", "a_far@laser", "b_far@laser"]
        );
        // The same every time, whatever order discovery lists them in.
        let mut reversed = fleet.clone();
        reversed.reverse();
        assert_eq!(names(&steps, &reversed, seeker), order);
    }

    #[test]
    fn an_announced_configuration_matches_only_byte_for_byte() {
        // What a stranger may announce (the rule is the builder's, not the
        // wire's): near misses of `alice` and of none are nobody's.
        let long = "alice".repeat(2000);
        let hostile = [
            "alice ",
            "ALICE",
            "alice\u{200b}",
            "\u{0}",
            " ",
            "\u{1b}[2J",
            &long,
        ];
        let fleet: Vec<MemberView> = hostile
            .iter()
            .enumerate()
            .map(|(i, config)| member(&format!("m{i}"), i as i64, "a", config, &["laser"]))
            .collect();
        let seeker = Seeker { key: 99, host: "a" };
        for config in ["alice", ""] {
            let steps = search_steps("laser", "rover1", config).unwrap();
            assert!(names(&steps, &fleet, seeker).is_empty(), "{config:?}");
        }
    }

    #[test]
    fn a_member_providing_two_of_the_names_is_a_candidate_at_each() {
        let fleet = vec![member("both", 1, "a", "", &["rover1/laser", "laser"])];
        let steps = search_steps("laser", "rover1", "").unwrap();
        let seeker = Seeker { key: 9, host: "a" };
        assert_eq!(
            names(&steps, &fleet, seeker),
            ["both@rover1/laser", "both@laser"]
        );
    }
}
