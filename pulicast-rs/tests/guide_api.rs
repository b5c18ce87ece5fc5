//! The guide's API block (docs/guide.md, "API"), as a user writes it: every
//! name it uses comes from the crate root, and every call it shows runs.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::net::Ipv4Addr;
use std::time::Duration;

use pulicast::{Node, QueuePolicy, ReassemblyLimits, Schema};

#[derive(serde::Serialize, serde::Deserialize, Schema)]
struct Twist {
    linear: f64,
    angular: f64,
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_guides_api_block_runs_with_names_from_the_crate_root() {
    let node = Node::new("rover_controller")
        .namespace("rover1")
        .port(pulicast::unused_port().unwrap())
        .ttl(0)
        .interface(Ipv4Addr::LOCALHOST)
        .heartbeat_period(Duration::from_millis(100))
        .queue_capacity(1024)
        .queue_policy(QueuePolicy::DropOldest)
        .receive_buffer(4 << 20)
        .receive_spin(Duration::from_micros(50))
        .reassembly_limits(ReassemblyLimits::default())
        .start()
        .await
        .unwrap();
    let mut twists = node.channel("cmd").subscribe::<Twist>().unwrap();
    let mut ordered = node.channel("cmd").subscribe_ordered::<Twist>().unwrap();
    let mut raw = node.channel("blob").subscribe_raw().unwrap();
    node.channel("ctrl").publish(&"Go LEFT!").unwrap();
    node.channel("speed").publish(&1.5f64).unwrap();
    node.channel("cmd")
        .publish(&Twist {
            linear: 0.3,
            angular: 0.0,
        })
        .unwrap();
    node.channel("blob").publish_bytes(&[1, 2, 3]).unwrap();
    node.channel("imu")
        .enable_batching(Duration::from_millis(1))
        .unwrap();
    node.channel("imu").flush().unwrap();

    // A node hears its own messages, in order (lead 1).
    let m = tokio::time::timeout(Duration::from_secs(5), twists.recv())
        .await
        .unwrap()
        .unwrap();
    assert_eq!((m.value.linear, m.lead), (0.3, 1));
    assert!(ordered
        .recv_timeout(Duration::from_secs(5))
        .is_some_and(|m| m.value.linear == 0.3));
    assert_eq!(&raw.recv_blocking().unwrap().value[..], &[1, 2, 3]);
    assert!(twists.try_recv().is_none());

    // Draining and handlers.
    let (steered, steering) = std::sync::mpsc::channel();
    let steer = move |twist: Twist| steered.send(twist.angular).unwrap();
    let _cmds = node
        .channel("cmd")
        .subscribe_with(move |m: pulicast::Message<Twist>| steer(m.value))
        .unwrap();
    for angular in [0.1, 0.2] {
        let twist = Twist {
            linear: 0.0,
            angular,
        };
        node.channel("cmd").publish(&twist).unwrap();
    }
    let mut batch = Vec::new();
    let mut n = tokio::time::timeout(Duration::from_secs(5), twists.recv_many(&mut batch, 256))
        .await
        .unwrap();
    if n < 2 {
        // The second came after the first wake-up.
        n += twists.recv_many_timeout(&mut batch, 256, Duration::from_secs(5));
    }
    assert_eq!(n, 2);
    assert_eq!(
        batch.iter().map(|m| m.value.angular).collect::<Vec<_>>(),
        [0.1, 0.2]
    );
    let handled: Vec<f64> = (0..2)
        .map(|_| steering.recv_timeout(Duration::from_secs(5)).unwrap())
        .collect();
    assert_eq!(handled, [0.1, 0.2]);

    // It lists itself where others see it, not at the wildcard address.
    let me = node.channel("cmd").publishers();
    let me = me
        .iter()
        .find(|m| m.session == Some(node.session_id()))
        .unwrap();
    assert_eq!(me.address.ip(), Ipv4Addr::LOCALHOST);
    assert_eq!(me.data_address.unwrap().ip(), Ipv4Addr::LOCALHOST);

    let _ = (node.discovery(), node.peers(), node.stats());
    let _ = (node.session_id(), node.compat_session_id(), node.name());
    // Types in public signatures are named from the crate root too.
    let _: Option<pulicast::GossipStats> = node.discovery().stats();
    let _: pulicast::Uuid = node.session_id();
    let _: Option<pulicast::Uuid> = me.session;
    let _: Option<pulicast::postcard_schema::schema::owned::OwnedNamedType> =
        pulicast_proto::text::schema_of(&pulicast_proto::wire::type_info_of::<Twist>());
}
