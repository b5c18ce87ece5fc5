//! Micro-benchmarks of the packet and message codecs: `cargo bench -p pulicast`.

#![allow(missing_docs, clippy::unwrap_used)] // a benchmark binary

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use pulicast::Schema;
use pulicast_proto::wire::zcm::{self, Primitive};
use pulicast_proto::wire::{decode_native, encode_native, Packet};
use serde::{Deserialize, Serialize};
use std::hint::black_box;

#[derive(Serialize, Deserialize, Schema, Clone)]
struct Pose {
    x: f64,
    y: f64,
    z: f64,
    heading: f32,
    frame: String,
}

fn packets(c: &mut Criterion) {
    let mut g = c.benchmark_group("packet");
    for size in [64usize, 8192, 60000] {
        let payload = vec![7u8; size];
        let mut buf = Vec::with_capacity(size + 64);
        Packet {
            channel: "rover1/left_arm/pose",
            seq: 42,
            payload: &payload,
        }
        .encode(&mut buf);
        g.throughput(Throughput::Bytes(size as u64));
        g.bench_function(format!("encode {size}"), |b| {
            let mut out = Vec::with_capacity(size + 64);
            b.iter(|| {
                out.clear();
                Packet {
                    channel: "rover1/left_arm/pose",
                    seq: black_box(42),
                    payload: &payload,
                }
                .encode(&mut out);
            })
        });
        g.bench_function(format!("decode {size}"), |b| {
            b.iter(|| Packet::decode(black_box(&buf)).unwrap().seq)
        });
    }
    g.finish();
}

fn messages(c: &mut Criterion) {
    let mut g = c.benchmark_group("message");
    let pose = Pose {
        x: 1.0,
        y: 2.0,
        z: 3.0,
        heading: 0.5,
        frame: "map".into(),
    };
    let mut native = Vec::new();
    encode_native(&pose, &mut native).unwrap();
    g.bench_function("native encode Pose", |b| {
        let mut out = Vec::with_capacity(128);
        b.iter(|| {
            out.clear();
            encode_native(black_box(&pose), &mut out).unwrap();
        })
    });
    g.bench_function("native decode Pose", |b| {
        b.iter(|| decode_native::<Pose>(black_box(&native)).unwrap().x)
    });
    let mut text = Vec::new();
    Primitive::String("Go LEFT!".into()).encode(&mut text);
    g.bench_function("zcm encode string_msg", |b| {
        let mut out = Vec::with_capacity(64);
        b.iter(|| {
            out.clear();
            encode_native(black_box("Go LEFT!"), &mut out).unwrap();
        })
    });
    g.bench_function("zcm decode string_msg", |b| {
        b.iter(|| decode_native::<String>(black_box(&text)).unwrap().len())
    });
    let hb = pulicast_discovery::compat::Heartbeat {
        name: "rover_controller".into(),
        session_id: 7,
        channels: (0..20)
            .map(|i| pulicast::ChannelAnnouncement {
                name: format!("rover1/sensor{i:02}"),
                period_ns: 0,
                is_published: true,
                is_subscribed: false,
            })
            .collect(),
    };
    let mut encoded = Vec::new();
    zcm::encode_heartbeat(&hb, &mut encoded);
    g.bench_function("heartbeat decode (20 channels)", |b| {
        b.iter(|| {
            zcm::decode_heartbeat(black_box(&encoded))
                .unwrap()
                .channels
                .len()
        })
    });
    g.finish();
}

criterion_group!(benches, packets, messages);
criterion_main!(benches);
