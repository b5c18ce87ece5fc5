//! A robot control loop with no async code: the node runs on its own runtime
//! thread (`start_blocking`), the loop polls with `try_recv` and waits with
//! `recv_timeout`.
//!
//! ```sh
//! cargo run --example blocking
//! ```

use std::time::{Duration, Instant};

use clap::Parser;
use pulicast_examples::{init_logging, NetFlags, Twist};

#[derive(Parser)]
struct Args {
    #[command(flatten)]
    net: NetFlags,
    /// Control loop iterations.
    #[arg(long, default_value_t = 20)]
    steps: u32,
}

fn main() -> pulicast::Result<()> {
    init_logging();
    let args = Args::parse();
    let node = args
        .net
        .node("blocking_loop")
        .namespace("rover1")
        .start_blocking()?;
    let mut commands = node.channel("ctrl").subscribe::<Twist>()?;
    let mut speeds = node.channel("speed").subscribe::<f64>()?;

    let period = Duration::from_millis(50);
    let mut speed = 0.0;
    for step in 0..args.steps {
        let started = Instant::now();
        // Whatever arrived since the last step, without waiting.
        while let Some(cmd) = commands.try_recv() {
            speed = cmd.value.linear;
        }
        node.channel("ctrl").publish(&Twist {
            linear: f64::from(step) * 0.1,
            angular: 0.0,
        })?;
        node.channel("speed").publish(&speed)?;
        // Wait for our own echo, but never longer than the loop period.
        if let Some(m) = speeds.recv_timeout(period) {
            println!("step {step:2}: speed {:.1} m/s (lead {})", m.value, m.lead);
        }
        std::thread::sleep(period.saturating_sub(started.elapsed()));
    }
    Ok(())
}
