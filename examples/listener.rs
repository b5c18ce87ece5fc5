//! Prints what arrives on `chatter`, with the lead that tells losses apart
//! from reordering. Stops after `--count` messages or `--secs` seconds.
//!
//! ```sh
//! cargo run --example listener -- --secs 30
//! ```

use std::time::Duration;

use clap::Parser;
use pulicast_examples::{init_logging, NetFlags};

#[derive(Parser)]
struct Args {
    #[command(flatten)]
    net: NetFlags,
    /// Stop after this many messages.
    #[arg(long, default_value_t = u32::MAX)]
    count: u32,
    /// Stop after this many seconds.
    #[arg(long, default_value_t = 60)]
    secs: u64,
}

#[tokio::main]
async fn main() -> pulicast::Result<()> {
    init_logging();
    let args = Args::parse();
    let node = args.net.node("listener").start().await?;
    let mut chatter = node.channel("chatter").subscribe::<String>()?;
    let listen = async {
        for _ in 0..args.count {
            let Some(m) = chatter.recv().await else { break };
            println!(
                "{:?} from {} (seq {}, lead {})",
                m.value, m.source, m.seq, m.lead
            );
        }
    };
    if tokio::time::timeout(Duration::from_secs(args.secs), listen)
        .await
        .is_err()
    {
        println!("no more messages after {} s", args.secs);
    }
    Ok(())
}
