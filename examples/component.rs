//! Components take a `&Namespace`, not a node and not channels.
//!
//! The `Odometer` below picks its own channel names (`ctrl`, `odometry`) inside
//! whatever namespace it is given, so `main` can run one per rover without the
//! component knowing about rovers at all. A `Node` is also a namespace (its
//! default one), so `Odometer::new(&node)` works too.
//!
//! ```sh
//! cargo run --example component
//! ```

use std::time::Duration;

use clap::Parser;
use pulicast::{Channel, Namespace, Subscription};
use pulicast_examples::{init_logging, NetFlags, Twist};

/// Integrates velocity commands into a travelled distance.
struct Odometer {
    commands: Subscription<Twist>,
    odometry: Channel,
    distance: f64,
}

impl Odometer {
    /// Subscribes `ctrl` and publishes `odometry`, both in `ns`.
    fn new(ns: &Namespace) -> pulicast::Result<Self> {
        Ok(Self {
            commands: ns.channel("ctrl").subscribe()?,
            odometry: ns.channel("odometry"),
            distance: 0.0,
        })
    }

    /// Applies the commands that have arrived, as if each lasted `dt`.
    fn step(&mut self, dt: Duration) -> pulicast::Result<()> {
        while let Some(cmd) = self.commands.try_recv() {
            self.distance += cmd.value.linear.abs() * dt.as_secs_f64();
        }
        self.odometry.publish(&self.distance)
    }
}

#[derive(Parser)]
struct Args {
    #[command(flatten)]
    net: NetFlags,
}

#[tokio::main]
async fn main() -> pulicast::Result<()> {
    init_logging();
    let args = Args::parse();
    let node = args.net.node("odometry").start().await?;

    // The same component, relocated by namespace alone.
    let mut odometers = vec![
        Odometer::new(&node.make_namespace("rover1"))?,
        Odometer::new(&node.make_namespace("rover2"))?,
    ];
    let mut readings = [
        node.channel("rover1/odometry").subscribe::<f64>()?,
        node.channel("rover2/odometry").subscribe::<f64>()?,
    ];

    let dt = Duration::from_millis(100);
    for step in 0..10 {
        node.channel("rover1/ctrl").publish(&Twist {
            linear: 1.0,
            angular: 0.0,
        })?;
        node.channel("rover2/ctrl").publish(&Twist {
            linear: 0.5,
            angular: 0.1,
        })?;
        tokio::time::sleep(dt).await;
        for odometer in &mut odometers {
            odometer.step(dt)?;
        }
        for (reading, rover) in readings.iter_mut().zip(["rover1", "rover2"]) {
            if let Ok(Some(m)) = tokio::time::timeout(Duration::from_secs(1), reading.recv()).await
            {
                println!("step {step}: {rover}/odometry = {:.2} m", m.value);
            }
        }
    }
    Ok(())
}
