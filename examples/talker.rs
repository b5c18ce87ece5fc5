//! Publishes a greeting on `chatter` twice a second. Run it beside `listener`:
//!
//! ```sh
//! cargo run --example listener &
//! cargo run --example talker -- --count 5
//! ```

use std::time::Duration;

use clap::Parser;
use pulicast_examples::{init_logging, NetFlags};

#[derive(Parser)]
struct Args {
    #[command(flatten)]
    net: NetFlags,
    /// How many messages to send.
    #[arg(long, default_value_t = 10)]
    count: u32,
}

#[tokio::main]
async fn main() -> pulicast::Result<()> {
    init_logging();
    let args = Args::parse();
    let node = args.net.node("talker").start().await?;
    let chatter = node.channel("chatter");
    for i in 0..args.count {
        let text = format!("hello #{i}");
        chatter.publish(text.as_str())?;
        println!("sent {text:?}");
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
    Ok(())
}
