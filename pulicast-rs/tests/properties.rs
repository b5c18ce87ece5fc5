//! Randomized properties of the pure layers: decoders never panic on any
//! input, encodings round-trip, and name resolution obeys its laws.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use proptest::prelude::*;
use pulicast::{resolve_name, ChannelAnnouncement, Schema};
use pulicast_discovery::compat::Heartbeat;
use pulicast_proto::wire::batch::{Batch, BatchBuilder};
use pulicast_proto::wire::zcm::{self, Primitive};
use pulicast_proto::wire::{self, Packet};
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Schema, Debug, Clone, PartialEq)]
struct Pose {
    x: f64,
    label: String,
    waypoints: Vec<(i32, i32)>,
    mode: Option<u8>,
}

fn ascii_name(max: usize) -> impl Strategy<Value = String> {
    proptest::string::string_regex(&format!("[ -~]{{0,{max}}}")).unwrap()
}

fn primitive() -> impl Strategy<Value = Primitive> {
    prop_oneof![
        any::<bool>().prop_map(Primitive::Bool),
        any::<u8>().prop_map(Primitive::Byte),
        any::<i8>().prop_map(Primitive::I8),
        any::<i16>().prop_map(Primitive::I16),
        any::<i32>().prop_map(Primitive::I32),
        any::<i64>().prop_map(Primitive::I64),
        proptest::num::f64::NORMAL.prop_map(Primitive::Float),
        proptest::num::f64::NORMAL.prop_map(Primitive::Double),
        ".{0,40}".prop_map(Primitive::String),
    ]
}

fn heartbeat() -> impl Strategy<Value = Heartbeat> {
    let channel = (ascii_name(40), any::<i64>(), any::<bool>(), any::<bool>()).prop_map(
        |(name, period_ns, is_published, is_subscribed)| ChannelAnnouncement {
            name,
            period_ns,
            is_published,
            is_subscribed,
        },
    );
    (
        ".{0,30}",
        any::<i64>(),
        proptest::collection::vec(channel, 0..20),
    )
        .prop_map(|(name, session_id, channels)| Heartbeat {
            name,
            session_id,
            channels,
        })
}

/// A datagram that starts with one of the magics, or with random bytes.
fn datagram() -> impl Strategy<Value = Vec<u8>> {
    let magic = prop_oneof![
        Just(b"PULI".to_vec()),
        Just(b"PBAT".to_vec()),
        Just(b"PFRG".to_vec()),
        Just(b"PSEC".to_vec()),
        Just(b"PDSC".to_vec()),
        proptest::collection::vec(any::<u8>(), 0..4),
    ];
    (magic, proptest::collection::vec(any::<u8>(), 0..120)).prop_map(|(mut m, rest)| {
        m.extend(rest);
        m
    })
}

proptest! {
    /// `Kind::of` is the one place that tells datagrams apart: each format's
    /// decoder accepts only datagrams of its own kind, so the dispatch on
    /// the kind never hands a datagram to a decoder that would read it as
    /// something it is not.
    #[test]
    fn each_decoder_accepts_only_its_own_kind(bytes in datagram()) {
        use pulicast_proto::fragment::Fragment;
        use pulicast_proto::wire::Kind;
        let kind = Kind::of(&bytes);
        if Packet::decode(&bytes).is_ok() {
            prop_assert_eq!(kind, Kind::Packet);
        }
        if Batch::decode(&bytes).is_ok() {
            prop_assert_eq!(kind, Kind::Batch);
        }
        if Fragment::decode(&bytes).is_ok() {
            prop_assert_eq!(kind, Kind::Fragment);
        }
        if pulicast_discovery::wire::Message::decode(&bytes).is_ok() {
            prop_assert_eq!(kind, Kind::Discovery);
        }
        // The one decode agrees with each format's own, and with the magic.
        match wire::Datagram::decode(&bytes) {
            Ok(view) => {
                prop_assert_eq!(view.kind(), kind);
                match kind {
                    Kind::Packet => prop_assert!(Packet::decode(&bytes).is_ok()),
                    Kind::Batch => prop_assert!(Batch::decode(&bytes).is_ok()),
                    Kind::Fragment => prop_assert!(Fragment::decode(&bytes).is_ok()),
                    _ => {}
                }
            }
            Err(_) => {
                prop_assert!(kind != Kind::Packet || Packet::decode(&bytes).is_err());
                prop_assert!(kind != Kind::Batch || Batch::decode(&bytes).is_err());
                prop_assert!(kind != Kind::Fragment || Fragment::decode(&bytes).is_err());
            }
        }
    }

    #[test]
    fn decoders_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..300)) {
        let _ = Packet::decode(&bytes);
        let _ = Primitive::decode(&bytes);
        let _ = zcm::decode_heartbeat(&bytes);
        let _ = wire::decode_native::<Pose>(&bytes);
        let _ = wire::decode_native::<String>(&bytes);
        let _ = wire::decode_native::<f32>(&bytes);
        if let Ok(batch) = Batch::decode(&bytes) {
            // A batch that passes its checks walks to exactly its count.
            prop_assert_eq!(batch.entries(&bytes).count(), usize::from(batch.count));
        }
    }

    #[test]
    fn batches_round_trip_and_every_cut_is_refused(
        name in ascii_name(255),
        first in any::<u32>(),
        messages in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 0..200), 1..30),
        cut in any::<prop::sample::Index>(),
    ) {
        let mut builder = BatchBuilder::new();
        builder.start(&name, first);
        for m in &messages {
            prop_assert!(builder.fits(m.len()));
            prop_assert!(builder.push(m));
        }
        let datagram = builder.finish().to_vec();
        let batch = Batch::decode(&datagram).unwrap();
        prop_assert_eq!((batch.channel, batch.first_seq), (name.as_str(), first));
        let decoded: Vec<(u32, &[u8])> = batch
            .entries(&datagram)
            .map(|(seq, range)| (seq, &datagram[range]))
            .collect();
        let expected: Vec<(u32, &[u8])> = messages
            .iter()
            .enumerate()
            .map(|(i, m)| (first.wrapping_add(i as u32), &m[..]))
            .collect();
        prop_assert_eq!(decoded, expected);
        let cut = cut.index(datagram.len());
        prop_assert!(Batch::decode(&datagram[..cut]).is_err());
    }

    #[test]
    fn hostile_fragments_never_panic_and_memory_stays_bounded(
        datagrams in proptest::collection::vec(
            (any::<u32>(), 0u32..200_000, any::<u16>(), 2u16..8, proptest::collection::vec(any::<u8>(), 0..300), any::<bool>()),
            1..40,
        )
    ) {
        use pulicast_proto::fragment::{Fragment, ReassemblyLimits, Reassembler, MAGIC};
        let limits = ReassemblyLimits { per_source: 300_000, per_channel: 500_000, total: 500_000, timeout: std::time::Duration::from_secs(1) };
        let mut r = Reassembler::new(limits);
        let channel: std::sync::Arc<str> = "x".into();
        let now = std::time::Instant::now();
        for (seq, total, index, count, chunk, raw) in datagrams {
            let mut d = Vec::new();
            if raw {
                d.extend_from_slice(&MAGIC);
                d.extend_from_slice(&chunk);
            } else {
                d.extend_from_slice(&MAGIC);
                d.push(1);
                d.push(b'x');
                d.extend_from_slice(&seq.to_be_bytes());
                d.extend_from_slice(&total.to_be_bytes());
                d.extend_from_slice(&(index % count).to_be_bytes());
                d.extend_from_slice(&count.to_be_bytes());
                d.extend_from_slice(&chunk);
            }
            if let Ok(f) = Fragment::decode(&d) {
                let _ = r.push(now, &channel, "127.0.0.1:1".parse().unwrap(), f.header(), f.chunk);
            }
            prop_assert!(r.bytes() <= limits.total);
        }
    }

    #[test]
    fn packets_round_trip(name in ascii_name(255), seq in any::<u32>(), payload in proptest::collection::vec(any::<u8>(), 0..100)) {
        let mut buf = Vec::new();
        let packet = Packet { channel: &name, seq, payload: &payload };
        packet.encode(&mut buf);
        prop_assert_eq!(Packet::decode(&buf).unwrap(), packet);
    }

    #[test]
    fn primitives_round_trip(p in primitive()) {
        let mut buf = Vec::new();
        p.encode(&mut buf);
        prop_assert_eq!(Primitive::decode(&buf).unwrap(), p);
    }

    #[test]
    fn heartbeats_round_trip_and_survive_corruption(hb in heartbeat(), flip in any::<(usize, u8)>()) {
        let mut buf = Vec::new();
        zcm::encode_heartbeat(&hb, &mut buf);
        prop_assert_eq!(zcm::decode_heartbeat(&buf).unwrap(), hb);
        let i = flip.0 % buf.len();
        buf[i] ^= flip.1 | 1;
        let _ = zcm::decode_heartbeat(&buf);
        buf.truncate(i);
        prop_assert!(zcm::decode_heartbeat(&buf).is_err());
    }

    #[test]
    fn native_messages_round_trip_and_survive_corruption(
        x in proptest::num::f64::NORMAL,
        label in ".{0,20}",
        waypoints in proptest::collection::vec(any::<(i32, i32)>(), 0..10),
        mode in any::<Option<u8>>(),
        flip in any::<(usize, u8)>(),
    ) {
        let pose = Pose { x, label, waypoints, mode };
        let mut buf = Vec::new();
        wire::encode_native(&pose, &mut buf).unwrap();
        prop_assert_eq!(wire::decode_native::<Pose>(&buf).unwrap(), pose);
        let i = flip.0 % buf.len();
        buf[i] ^= flip.1 | 1;
        let _ = wire::decode_native::<Pose>(&buf);
    }

    #[test]
    fn name_resolution_laws(
        parts in proptest::collection::vec(prop_oneof![Just("..".to_string()), Just(".".to_string()), Just(String::new()), "[a-z0-9_]{1,6}"], 0..8),
        ns_parts in proptest::collection::vec("[a-z0-9_]{1,6}", 0..5),
        absolute in any::<bool>(),
    ) {
        let name = format!("{}{}", if absolute { "/" } else { "" }, parts.join("/"));
        let ns = ns_parts.join("/");
        // An empty first part makes a relative-looking join absolute.
        let absolute = name.starts_with('/');
        if let Ok(resolved) = resolve_name(&name, &ns) {
            // Resolved names are canonical: no slashes at the ends, no dots, no empty parts.
            prop_assert!(!resolved.starts_with('/') && !resolved.ends_with('/'));
            prop_assert!(resolved.split('/').all(|p| !p.is_empty() && p != "." && p != ".."));
            // Idempotent, from any namespace once made absolute.
            prop_assert_eq!(resolve_name(&resolved, "").unwrap(), resolved.clone());
            prop_assert_eq!(resolve_name(&format!("/{resolved}"), "elsewhere").unwrap(), resolved.clone());
            // Absolute names ignore the namespace.
            if absolute {
                prop_assert_eq!(resolve_name(&name, "").unwrap(), resolved.clone());
            } else if !ns.is_empty() && !parts.iter().any(|p| p == "..") {
                // Relative names without ".." stay inside the namespace.
                let inside = resolved.starts_with(&format!("{ns}/")) || resolved == ns;
                prop_assert!(inside, "{} left {}", resolved, ns);
            }
        }
    }
}

#[test]
fn handles_are_send_and_sync() {
    fn assert_send_sync<T: Send + Sync>() {}
    fn assert_send<T: Send>() {}
    assert_send_sync::<pulicast::Node>();
    assert_send_sync::<pulicast::Namespace>();
    assert_send_sync::<pulicast::Channel>();
    assert_send::<pulicast::Subscription<Pose>>();
    assert_send_sync::<pulicast::Error>();
}

proptest! {
    /// A setting's confirmation and requests, from any bytes: an error or a
    /// value, never a panic; any confirmation we write reads back the same.
    #[test]
    fn settings_wire_never_panics_and_round_trips(
        bytes in proptest::collection::vec(any::<u8>(), 0..200),
        message in ".{0,40}",
        fingerprint in any::<[u8; 8]>(),
        value in proptest::collection::vec(any::<u8>(), 0..100),
    ) {
        use pulicast_proto::wire::setting::{Request, RocAck};
        let _ = RocAck::decode(&bytes);
        let _ = Request::decode(&bytes);
        // With the right fingerprint in front, the rest is what is random.
        let mut prefixed = pulicast_proto::wire::zcm_types::ROC_ACK.fingerprint().0.to_vec();
        prefixed.extend_from_slice(&bytes);
        let _ = RocAck::decode(&prefixed);
        let ack = RocAck { message: &message, fingerprint: wire::Fingerprint(fingerprint), value: &value };
        let mut out = Vec::new();
        ack.encode(&mut out).unwrap();
        prop_assert_eq!(RocAck::decode(&out).unwrap(), ack);
    }
}

#[derive(Serialize, Deserialize, Schema, Debug, Clone, PartialEq)]
struct Gains {
    p: f64,
    name: String,
}

proptest! {
    /// Whatever bytes a request holds, the owner answers with a
    /// confirmation of its own type, and its value still passes its checks.
    #[test]
    fn owners_answer_any_request_and_keep_their_checks(
        bytes in proptest::collection::vec(any::<u8>(), 0..120),
        fingerprinted in any::<bool>(),
        which in 0..3u8,
    ) {
        use pulicast_proto::setting::{Check, Native, Owner, SettingValue};
        use pulicast_proto::wire::setting::RocAck;
        fn run<T: SettingValue>(owner: &mut Owner<T>, request: &[u8], ok: impl Fn(&T) -> bool) -> Result<(), TestCaseError> {
            let mut out = Vec::new();
            owner.handle(request, &mut out);
            let ack = RocAck::decode(&out).map_err(|e| TestCaseError::fail(e.to_string()))?;
            prop_assert_eq!(ack.fingerprint, T::fingerprint());
            prop_assert!(owner.value().is_some_and(&ok));
            Ok(())
        }
        let mut request = Vec::new();
        match (which, fingerprinted) {
            (0, true) => request.extend_from_slice(&wire::zcm::fingerprint::DOUBLE_MSG.0),
            (1, true) => request.extend_from_slice(&wire::zcm::fingerprint::STRING_MSG.0),
            (_, true) => request.extend_from_slice(&Native::<Gains>::fingerprint().0),
            _ => {}
        }
        request.extend_from_slice(&bytes);
        match which {
            0 => {
                let mut o = Owner::new(1.0f64, vec![Check::Range(0.0, 2.0)]).unwrap();
                run(&mut o, &request, |v| (0.0..=2.0).contains(v))?;
            }
            1 => {
                let mut o = Owner::new("a".to_string(), vec![Check::OneOf(vec!["a".into(), "b".into()])]).unwrap();
                run(&mut o, &request, |v| v == "a" || v == "b")?;
            }
            _ => {
                let check = Check::Custom(Box::new(|g: &Native<Gains>| {
                    if g.0.p >= 0.0 { Ok(()) } else { Err("negative".into()) }
                }));
                let start = Native(Gains { p: 1.0, name: "x".into() });
                let mut o = Owner::new(start, vec![check]).unwrap();
                run(&mut o, &request, |g| g.0.p >= 0.0)?;
            }
        }
    }

    /// A client's catalog takes any bytes on a setting's channel without
    /// panicking, and shows a value for whatever it kept.
    #[test]
    fn a_catalog_takes_any_confirmation(
        bytes in proptest::collection::vec(any::<u8>(), 0..200),
        native in any::<bool>(),
    ) {
        use pulicast_proto::catalog::{Catalog, Member};
        use pulicast_proto::setting::{Native, SettingValue};
        use pulicast::ChannelInfo;
        let part = if native { ".settings" } else { ".config" };
        let channel = format!("r/{part}/s");
        let channels = [
            ChannelInfo { name: channel.clone(), publishes: true, subscribes: false, period_ns: 0, message_type: None },
            ChannelInfo {
                name: format!("{channel}.r"), publishes: false, subscribes: true, period_ns: 0,
                message_type: native.then(Native::<Gains>::type_info).flatten(),
            },
        ];
        let mut catalog = Catalog::default();
        let at = std::net::SocketAddr::from(([127, 0, 0, 1], 4001));
        let owner = Member { key: 1, node: "n", live: true, channels: &channels, address: at, data_address: Some(at) };
        catalog.update([owner]);
        let mut prefixed = wire::zcm_types::ROC_ACK.fingerprint().0.to_vec();
        prefixed.extend_from_slice(&bytes);
        // A well-formed confirmation whose value is the random bytes.
        let fingerprint = match native {
            true => Native::<Gains>::fingerprint(),
            false => wire::zcm::fingerprint::DOUBLE_MSG,
        };
        let mut framed = Vec::new();
        pulicast_proto::wire::setting::RocAck { message: "", fingerprint, value: &bytes }
            .encode(&mut framed)
            .unwrap();
        for payload in [&bytes, &prefixed, &framed] {
            if let Ok(Some(info)) = catalog.hear(&channel, payload, at, std::time::Instant::now()) {
                prop_assert!(info.value_text().is_some());
                let _ = info.value_json();
            }
        }
    }
}

proptest! {
    /// Service frames: any bytes decode or are refused without a panic,
    /// and every frame written reads back as written.
    #[test]
    fn service_frames_never_panic_and_round_trip(
        bytes in proptest::collection::vec(any::<u8>(), 0..120),
        session in any::<i64>(),
        counter in any::<u64>(),
        kind in 0..7u8,
        number in any::<u32>(),
        text in ".{0,30}",
        message in proptest::collection::vec(any::<u8>(), 0..60),
    ) {
        use pulicast_proto::wire::service::{CallId, Frame, MAGIC};
        let _ = Frame::decode(&bytes);
        let mut prefixed = MAGIC.to_vec();
        prefixed.push(1);
        prefixed.extend_from_slice(&bytes);
        let _ = Frame::decode(&prefixed);
        let call = CallId { session, counter };
        let frame = match kind {
            0 => Frame::Request { call, target: &text, deadline_ms: number, message: &message },
            1 => Frame::Progress { call, seq: number, message: &message },
            2 => Frame::Reply { call, progress: number, message: &message },
            3 => Frame::Failure { call, code: number as u16, message: &text, node: &text },
            4 => Frame::Cancel { call },
            5 => Frame::Busy { call },
            _ => Frame::Running { call },
        };
        let mut out = Vec::new();
        frame.encode(&mut out).unwrap();
        prop_assert_eq!(Frame::decode(&out).unwrap(), frame);
    }
}
