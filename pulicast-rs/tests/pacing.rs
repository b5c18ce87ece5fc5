//! Pacing a large message's fragments to its subscribers' receive
//! buffers (issue 34): a node announces the buffer its sockets were
//! granted, and a publisher's fragments leave at its fragment rate in
//! bursts of half the smallest buffer among the channel's subscribers.
//! The tests check the mechanism by lower bounds only (a publish takes
//! at least what its pacing says; a busy machine only makes it longer).
#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

mod common;

use std::time::Instant;

use common::{eventually, free_port, node, WAIT};

/// A subscriber of `channel` with a receive buffer of `buffer` bytes, and
/// its subscription.
async fn subscriber(
    port: u16,
    channel: &str,
    buffer: usize,
) -> (pulicast::Node, pulicast::Subscription<pulicast::Bytes>) {
    let n = node("camera-viewer", port)
        .receive_buffer(buffer)
        .start()
        .await
        .unwrap();
    let sub = n.channel(channel).subscribe_raw().unwrap();
    (n, sub)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_node_announces_the_receive_buffer_its_sockets_were_granted() {
    let port = free_port();
    let (viewer, _sub) = subscriber(port, "camera/image", 1 << 20).await;
    let camera = node("camera", port).start().await.unwrap();
    let channel = camera.channel("camera/image");
    eventually("the viewer subscribing, heard", || {
        !channel.subscribers().is_empty()
    })
    .await;
    let announced = channel.subscribers()[0].receive_buffer.unwrap();
    // Linux reports twice what it grants as payload; the machine's
    // rmem_max may grant less than asked, never nothing.
    assert!(
        (64 << 10..=2 << 20).contains(&(announced as usize)),
        "{announced}"
    );
    assert_eq!(viewer.discovery().local().receive_buffer, Some(announced));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_large_message_leaves_at_the_fragment_rate_after_a_burst_of_half_the_subscribers_buffer()
{
    let port = free_port();
    let (_viewer, mut sub) = subscriber(port, "camera/image", 1 << 20).await;
    let rate: u64 = 64 << 20; // 64 MiB/s
    let camera = node("camera", port)
        .fragment_rate(Some(rate))
        .start()
        .await
        .unwrap();
    let channel = camera.channel("camera/image");
    eventually("the viewer subscribing, heard", || {
        !channel.subscribers().is_empty()
    })
    .await;
    let buffer = channel.subscribers()[0].receive_buffer.unwrap() as f64;
    let image = vec![7u8; 8 << 20];
    // The message arrives whole (tried a few times: a subscriber starved
    // of the CPU for longer than a burst lasts may still lose one).
    let mut arrived = false;
    for _ in 0..5 {
        let before = camera.stats();
        let started = Instant::now();
        channel.publish_bytes(&image).unwrap();
        let took = started.elapsed();
        let after = camera.stats();
        // All but the first burst (half the buffer) at the rate, at least.
        let least = (image.len() as f64 - buffer / 2.0 - 64e3) / rate as f64;
        assert!(
            took.as_secs_f64() >= least,
            "{took:?} for 8 MiB at {rate} B/s after a burst of {}",
            buffer / 2.0
        );
        assert!(after.paced_datagrams > before.paced_datagrams);
        assert!(after.paced_wait > before.paced_wait);
        if let Ok(Some(m)) = tokio::time::timeout(WAIT, sub.recv()).await {
            assert_eq!(m.value.len(), image.len());
            arrived = true;
            break;
        }
    }
    assert!(arrived, "no paced 8 MiB message arrived in five");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_pacing_or_without_subscribers_nothing_waits() {
    let port = free_port();
    let image = vec![7u8; 8 << 20];
    // No subscriber: nothing to pace for.
    let alone = node("camera", port).start().await.unwrap();
    alone.channel("camera/image").publish_bytes(&image).unwrap();
    assert_eq!(alone.stats().paced_datagrams, 0);
    // Pacing off, with a subscriber.
    let (_viewer, _sub) = subscriber(port, "camera/image", 1 << 20).await;
    let unpaced = node("camera-unpaced", port)
        .fragment_rate(None)
        .start()
        .await
        .unwrap();
    let channel = unpaced.channel("camera/image");
    eventually("the viewer subscribing, heard", || {
        !channel.subscribers().is_empty()
    })
    .await;
    channel.publish_bytes(&image).unwrap();
    assert_eq!(unpaced.stats().paced_datagrams, 0);
    // One datagram never waits, however many.
    let paced = node("small", port)
        .fragment_rate(Some(pulicast::MIN_FRAGMENT_RATE))
        .start()
        .await
        .unwrap();
    let small = paced.channel("camera/image");
    eventually("the viewer subscribing, heard", || {
        !small.subscribers().is_empty()
    })
    .await;
    for _ in 0..100 {
        small.publish_bytes(&[1u8; 1000]).unwrap();
    }
    assert_eq!(paced.stats().paced_datagrams, 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fragment_rate_below_the_least_is_refused() {
    let refused = node("camera", free_port())
        .fragment_rate(Some(pulicast::MIN_FRAGMENT_RATE - 1))
        .start()
        .await;
    assert!(
        matches!(refused, Err(pulicast::Error::InvalidConfig { .. })),
        "{refused:?}"
    );
}
