//! Golden tests: every vector the reference implementation produced must match.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::net::Ipv4Addr;
use std::path::PathBuf;

use pulicast::{group_for, resolve_name, ChannelAnnouncement};
use pulicast_discovery::compat::Heartbeat;
use pulicast_proto::wire::zcm::{self, fingerprint, Primitive};
use pulicast_proto::wire::{self, Fingerprint, Packet};
use serde_json::Value;

fn vectors() -> Value {
    // The project's own copy: see tests/vectors/README.md for its origin.
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/vectors/pulicast2.json");
    let text = std::fs::read_to_string(&path)
        .unwrap_or_else(|e| panic!("reading {}: {e}", path.display()));
    serde_json::from_str(&text).expect("vectors file is JSON")
}

fn hex(s: &str) -> Vec<u8> {
    assert!(s.len() % 2 == 0, "odd hex length");
    (0..s.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&s[i..i + 2], 16).expect("hex digit"))
        .collect()
}

fn entries(v: &Value, key: &str) -> Vec<(String, String)> {
    v[key]
        .as_object()
        .unwrap_or_else(|| panic!("{key} is an object"))
        .iter()
        .map(|(k, v)| (k.clone(), v.as_str().expect("string value").to_owned()))
        .collect()
}

#[test]
fn name_resolution() {
    let v = vectors();
    let rows = v["name_resolution"].as_array().expect("array");
    assert!(rows.len() >= 14);
    for row in rows {
        let (ns, name, want) = (
            row["namespace"].as_str().unwrap(),
            row["name"].as_str().unwrap(),
            row["resolved"].as_str().unwrap(),
        );
        assert_eq!(resolve_name(name, ns).unwrap(), want, "{name:?} in {ns:?}");
    }
}

#[test]
fn multicast_groups() {
    let v = vectors();
    for (name, group) in entries(&v, "multicast_groups") {
        let want: Ipv4Addr = group.parse().unwrap();
        assert_eq!(group_for(&name), want, "{name}");
    }
}

#[test]
fn fingerprints() {
    let v = vectors();
    let known = [
        ("boolean_msg", fingerprint::BOOLEAN_MSG),
        ("byte_msg", fingerprint::BYTE_MSG),
        ("double_msg", fingerprint::DOUBLE_MSG),
        ("float_msg", fingerprint::FLOAT_MSG),
        ("int8_msg", fingerprint::INT8_MSG),
        ("int16_msg", fingerprint::INT16_MSG),
        ("int32_msg", fingerprint::INT32_MSG),
        ("int64_msg", fingerprint::INT64_MSG),
        ("string_msg", fingerprint::STRING_MSG),
        ("pulicast_node", fingerprint::PULICAST_NODE),
        ("pulicast_channel", fingerprint::PULICAST_CHANNEL),
    ];
    let table = entries(&v, "fingerprints");
    assert_eq!(table.len(), wire::zcm_types::KNOWN.len());
    // Every fingerprint, computed from its ZCM definition.
    for (name, want) in &table {
        let def = wire::zcm_types::KNOWN
            .iter()
            .find(|s| s.name == name)
            .unwrap_or_else(|| panic!("no definition of {name}"));
        assert_eq!(def.fingerprint().to_string(), *want, "{name}");
    }
    for (name, fp) in known {
        let (_, want) = table.iter().find(|(n, _)| n == name).expect(name);
        assert_eq!(fp.to_string(), *want, "{name}");
    }
}

#[test]
fn message_encodings() {
    let v = vectors();
    let encodings = entries(&v, "message_encodings");
    let mut checked = 0;
    for (label, bytes) in &encodings {
        let bytes = hex(bytes);
        let primitive = match label.as_str() {
            "string_msg('Go LEFT!')" => Some(Primitive::String("Go LEFT!".into())),
            "int64_msg(-42)" => Some(Primitive::I64(-42)),
            "double_msg(3.5)" => Some(Primitive::Double(3.5)),
            "boolean_msg(True)" => Some(Primitive::Bool(true)),
            "int32_msg(7)" => Some(Primitive::I32(7)),
            "float_msg(1.25)" => Some(Primitive::Float(1.25)),
            "int8_msg(-1)" => Some(Primitive::I8(-1)),
            "int16_msg(300)" => Some(Primitive::I16(300)),
            "byte_msg(255)" => Some(Primitive::Byte(255)),
            _ => None,
        };
        if let Some(p) = primitive {
            let mut out = Vec::new();
            p.encode(&mut out);
            assert_eq!(out, bytes, "{label}");
            assert_eq!(Primitive::decode(&bytes).unwrap(), p, "{label}");
            checked += 1;
        } else if label.starts_with("pulicast_node(") {
            let hb = Heartbeat {
                name: "rover_controller".into(),
                session_id: -4967202353444692722,
                channels: vec![
                    ChannelAnnouncement {
                        name: "__nodes".into(),
                        period_ns: 100_000_000,
                        is_published: true,
                        is_subscribed: false,
                    },
                    ChannelAnnouncement {
                        name: "rover1/ctrl".into(),
                        period_ns: 0,
                        is_published: false,
                        is_subscribed: true,
                    },
                ],
            };
            let mut out = Vec::new();
            zcm::encode_heartbeat(&hb, &mut out);
            assert_eq!(out, bytes, "{label}");
            assert_eq!(zcm::decode_heartbeat(&bytes).unwrap(), hb);
            checked += 1;
        } else {
            panic!("a vector this test does not know: {label}");
        }
    }
    assert_eq!(checked, encodings.len());
}

#[test]
fn the_serde_path_produces_the_same_bytes() {
    let v = vectors();
    let encodings = entries(&v, "message_encodings");
    let want = |label: &str| hex(&encodings.iter().find(|(l, _)| l == label).expect(label).1);
    let enc = |f: &dyn Fn(&mut Vec<u8>)| {
        let mut out = Vec::new();
        f(&mut out);
        out
    };
    assert_eq!(
        enc(&|o| wire::encode_native("Go LEFT!", o).unwrap()),
        want("string_msg('Go LEFT!')")
    );
    assert_eq!(
        enc(&|o| wire::encode_native(&String::from("Go LEFT!"), o).unwrap()),
        want("string_msg('Go LEFT!')")
    );
    assert_eq!(
        enc(&|o| wire::encode_native(&-42i64, o).unwrap()),
        want("int64_msg(-42)")
    );
    assert_eq!(
        enc(&|o| wire::encode_native(&3.5f64, o).unwrap()),
        want("double_msg(3.5)")
    );
    assert_eq!(
        enc(&|o| wire::encode_native(&true, o).unwrap()),
        want("boolean_msg(True)")
    );
    assert_eq!(
        enc(&|o| wire::encode_native(&7i32, o).unwrap()),
        want("int32_msg(7)")
    );
    assert_eq!(
        enc(&|o| wire::encode_native(&1.25f32, o).unwrap()),
        want("float_msg(1.25)")
    );
    assert_eq!(
        enc(&|o| wire::encode_native(&-1i8, o).unwrap()),
        want("int8_msg(-1)")
    );
    assert_eq!(
        enc(&|o| wire::encode_native(&300i16, o).unwrap()),
        want("int16_msg(300)")
    );
    assert_eq!(
        enc(&|o| wire::encode_native(&255u8, o).unwrap()),
        want("byte_msg(255)")
    );
}

#[test]
fn packets() {
    let v = vectors();
    for (label, bytes) in entries(&v, "packets") {
        let bytes = hex(&bytes);
        let (channel, seq, payload) = match label.as_str() {
            "channel 'rover1/ctrl', seq 0, string_msg('Go LEFT!')" => {
                let mut p = Vec::new();
                Primitive::String("Go LEFT!".into()).encode(&mut p);
                ("rover1/ctrl", 0, p)
            }
            "channel 'a', seq 4294967295, raw bytes 010203" => ("a", u32::MAX, vec![1, 2, 3]),
            other => panic!("a vector this test does not know: {other}"),
        };
        let packet = Packet {
            channel,
            seq,
            payload: &payload,
        };
        let mut out = Vec::new();
        packet.encode(&mut out);
        assert_eq!(out, bytes, "{label}");
        assert_eq!(Packet::decode(&bytes).unwrap(), packet);
    }
}

#[test]
fn defaults() {
    let v = vectors();
    let d = &v["defaults"];
    assert_eq!(d["port"], u64::from(pulicast::DEFAULT_PORT));
    assert_eq!(d["ttl"], pulicast::DEFAULT_TTL);
    assert_eq!(d["max_udp_payload"], wire::MAX_DATAGRAM as u64);
    assert_eq!(
        d["discovery_channel"],
        pulicast_discovery::compat::NODES_CHANNEL
    );
    assert_eq!(
        d["node_dead_after_missed_heartbeats"],
        u64::from(pulicast_discovery::compat::MISSED_HEARTBEATS)
    );
    assert_eq!(
        d["heartbeat_period_s"].as_f64().unwrap(),
        pulicast::DEFAULT_HEARTBEAT_PERIOD.as_secs_f64()
    );
    assert_eq!(d["group_base"], pulicast::GROUP_BASE.to_string());
    assert_eq!(Fingerprint::of_payload(&[1; 8]).map(|f| f.0), Some([1; 8]));
}

/// What a reference `Setting` (puliconf) sends when it is made: our
/// decoder reads it, and our encoder writes the same bytes.
#[test]
fn setting_confirmations_requests_and_names_match_puliconf() {
    use pulicast_proto::wire::setting::{self, Request, RocAck};
    let v = vectors();
    let s = &v["settings"];
    let confirmations = s["confirmations"].as_object().unwrap();
    assert_eq!(confirmations.len(), 3);
    for (what, c) in confirmations {
        let payload = hex(c["payload"].as_str().unwrap());
        let ack = RocAck::decode(&payload).unwrap_or_else(|e| panic!("{what}: {e}"));
        let mut again = Vec::new();
        ack.encode(&mut again).unwrap();
        assert_eq!(again, payload, "{what}");
        let channel = c["channel"].as_str().unwrap();
        assert!(setting::is_confirmation(channel), "{what}");
        let (expected_type, expected_value, message): (Fingerprint, Vec<u8>, &str) =
            if what.starts_with("max_speed") {
                (
                    fingerprint::DOUBLE_MSG,
                    1.5f64.to_be_bytes().to_vec(),
                    "must be in [0.0, 2.0]",
                )
            } else if what.starts_with("mode") {
                (fingerprint::STRING_MSG, Vec::new(), "")
            } else {
                (fingerprint::INT64_MSG, 3i64.to_be_bytes().to_vec(), "")
            };
        assert_eq!(
            (ack.fingerprint, ack.value, ack.message, ack.is_set()),
            (
                expected_type,
                &expected_value[..],
                message,
                !expected_value.is_empty()
            ),
            "{what}"
        );
    }
    assert_eq!(
        setting::confirmation_channel("rover1", "arm/gain"),
        "rover1/.config/arm/gain"
    );
    for (name, expected) in [
        ("poke_setting", Request::Poke),
        ("unset_setting", Request::Unset),
        ("reset_setting_to_default", Request::Reset),
    ] {
        let bytes = hex(s["requests"][name].as_str().unwrap());
        assert_eq!(Request::decode(&bytes), Ok(expected), "{name}");
        let mut ours = Vec::new();
        expected.encode(&mut ours);
        assert_eq!(ours, bytes, "{name}");
    }
    for case in s["names"].as_array().unwrap() {
        let channel = case["channel"].as_str().unwrap();
        assert_eq!(
            setting::is_confirmation(channel),
            case["is_confirmation"].as_bool().unwrap(),
            "{channel}"
        );
        assert_eq!(
            setting::is_request(channel),
            case["is_request"].as_bool().unwrap(),
            "{channel}"
        );
        assert_eq!(
            setting::name_of_confirmation(channel).as_deref(),
            case["setting"].as_str(),
            "{channel}"
        );
    }
}
