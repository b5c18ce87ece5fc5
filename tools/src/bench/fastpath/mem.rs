//! `puli bench mem`: whether a subscriber's memory stays flat over many
//! messages; its own subscriber role, fed by the throughput publisher.

use anyhow::Result;
use serde_json::json;

use super::harness::{
    emit, end_signal, finish_sub, read_json, spawn_ready, spawn_role, status_kb, POLL_END,
};
use super::thr::thr_channel;
use super::{MemArgs, Path, RoleArgs, Setup};

/// The memory subscriber role: reports RSS after a tenth of `count`
/// messages and at the end (stdin `end`).
pub fn mem_sub(args: &RoleArgs) -> Result<()> {
    let end = end_signal();
    let node = args.builder("mem-sub").start_blocking()?;
    let mut sub = node.channel(&thr_channel(0)).subscribe_raw()?;
    emit(json!({"ready": true}));
    let mut received = 0u64;
    let mark = (args.count / 10).max(1);
    loop {
        match sub.recv_timeout(POLL_END) {
            Some(_) => {
                received += 1;
                if received == mark {
                    emit(json!({"received": received, "rss_kb": status_kb("VmRSS:")}));
                }
            }
            None if end.try_recv().is_ok() => break,
            None => {}
        }
    }
    emit(json!({"received": received, "rss_kb": status_kb("VmRSS:")}));
    Ok(())
}

/// Runs `puli bench mem`: subscriber memory after many messages.
pub fn mem(args: &MemArgs) -> Result<()> {
    let port = match args.port {
        Some(p) => p,
        None => pulicast::unused_port()?,
    };
    let setup = Setup {
        count: args.messages,
        ..Setup::new(port, args.size)
    };
    let mut sub = spawn_ready("mem-sub", Path::Timeout, setup)?;
    let mut publisher = spawn_role("thr-pub", Path::Timeout, setup)?;
    let first = read_json(&mut sub)?;
    let sent = read_json(&mut publisher)?;
    let _ = publisher.wait();
    let last = finish_sub(&mut sub)?;
    let (early, late) = (
        first["rss_kb"].as_f64().unwrap_or(0.0),
        last["rss_kb"].as_f64().unwrap_or(0.0),
    );
    crate::outln!(
        "subscriber RSS after {} messages: {:.1} MB; after {}: {:.1} MB ({:+.1} %); {} sent",
        first["received"],
        early / 1024.0,
        last["received"],
        late / 1024.0,
        (late / early.max(1.0) - 1.0) * 100.0,
        sent["sent"]
    );
    Ok(())
}
