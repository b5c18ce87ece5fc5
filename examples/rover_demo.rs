//! A small fleet: two rovers and a controller, each its own node in its own
//! process. Rovers publish their pose and drive by the velocity commands they
//! receive, within their settings (`max_speed`, `mode`), and serve
//! `distance_to` (how far they are from a point); the controller steers
//! each rover around its own circle and prints what it sees of the fleet,
//! asking each rover how far it is from where it started.
//!
//! ```sh
//! cargo run --example rover_demo                 # 10 s, watch the output
//! cargo run --example rover_demo -- --secs 60    # longer; watch with puli-sniffer
//! cargo run -p pulicast-tools --bin puli -- config set rover1/max_speed 0.1   # meanwhile
//! cargo run -p pulicast-tools --bin puli -- call rover1/distance_to '[0, 0]'    # meanwhile
//! ```
//!
//! Without `--role` the program starts the three processes and waits for them.

use std::process::{Child, Command, ExitCode};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use clap::{Parser, ValueEnum};
use pulicast::{Namespace, Node};
use pulicast_examples::{init_logging, NetFlags, Pose, Twist};

const ROVERS: [&str; 2] = ["rover1", "rover2"];

#[derive(Parser)]
struct Args {
    #[command(flatten)]
    net: NetFlags,
    /// How long the fleet runs, in seconds.
    #[arg(long, default_value_t = 10)]
    secs: u64,
    /// Run one member of the fleet instead of launching all of them.
    #[arg(long, value_enum)]
    role: Option<Role>,
    /// The rover's namespace (with `--role rover`).
    #[arg(long, default_value = "rover1")]
    name: String,
}

#[derive(Clone, Copy, ValueEnum)]
enum Role {
    Rover,
    Controller,
}

fn main() -> ExitCode {
    init_logging();
    let args = Args::parse();
    let result = match args.role {
        None => launch(&args),
        Some(role) => run_member(&args, role),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("rover_demo: {e}");
            ExitCode::FAILURE
        }
    }
}

/// Starts every member as a child process and waits for all of them.
fn launch(args: &Args) -> Result<(), Box<dyn std::error::Error>> {
    let exe = std::env::current_exe()?;
    let mut common = args.net.to_args();
    common.extend(["--secs".into(), args.secs.to_string()]);
    println!(
        "fleet on port {} via {}: {} and a controller, for {} s",
        args.net.port,
        args.net.describe(),
        ROVERS.join(", "),
        args.secs
    );
    let mut children: Vec<(String, Child)> = Vec::new();
    for rover in ROVERS {
        let child = Command::new(&exe)
            .args(&common)
            .args(["--role", "rover", "--name", rover])
            .spawn()?;
        children.push((rover.into(), child));
    }
    let controller = Command::new(&exe)
        .args(&common)
        .args(["--role", "controller"])
        .spawn()?;
    children.push(("controller".into(), controller));

    let deadline = Instant::now() + Duration::from_secs(args.secs + 10);
    let mut failed = Vec::new();
    for (name, mut child) in children {
        loop {
            if let Some(status) = child.try_wait()? {
                if !status.success() {
                    failed.push(format!("{name} exited with {status}"));
                }
                break;
            }
            if Instant::now() > deadline {
                // Only our own child, by its handle.
                child.kill()?;
                child.wait()?;
                failed.push(format!("{name} did not finish in time"));
                break;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }
    if failed.is_empty() {
        println!("fleet finished");
        Ok(())
    } else {
        Err(failed.join("; ").into())
    }
}

fn run_member(args: &Args, role: Role) -> Result<(), Box<dyn std::error::Error>> {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    let run_for = Duration::from_secs(args.secs);
    runtime.block_on(async {
        match role {
            Role::Rover => {
                let node = args
                    .net
                    .node(&args.name)
                    .namespace(&args.name)
                    .start()
                    .await?;
                rover(&node, run_for).await
            }
            Role::Controller => {
                let node = args.net.node("controller").start().await?;
                controller(&node, run_for).await
            }
        }
    })?;
    Ok(())
}

/// Drives by the latest command, no faster than its `max_speed` setting
/// and only in `mode` "drive", and publishes its pose at 20 Hz. Change the
/// settings while it runs: `puli config set rover1/max_speed 0.1`.
async fn rover(ns: &Namespace, run_for: Duration) -> pulicast::Result<()> {
    let me = ns.path().to_string();
    let max_speed = ns
        .setting_builder("max_speed", 0.5f64)
        .describe("top speed, whatever the controller asks")
        .unit("m/s")
        .check(pulicast::Check::Range(0.0, 2.0))
        .build()?;
    let mode = ns
        .setting_builder("mode", "drive".to_string())
        .describe("drive, or stop where it is")
        .check(pulicast::Check::OneOf(vec!["drive".into(), "stop".into()]))
        .build()?;
    let who = me.clone();
    max_speed.on_change(move |v| println!("[{who}] max_speed is now {v:?}"));
    let who = me.clone();
    mode.on_change(move |v| println!("[{who}] mode is now {v:?}"));
    let pose_channel = ns.channel("pose");
    let mut commands = ns.channel("ctrl").subscribe_ordered::<Twist>()?;
    let mut pose = Pose::default();
    // How far the rover is from a point, for any node that asks:
    // `puli call rover1/distance_to '[0, 0]'`.
    let here = Arc::new(Mutex::new(pose));
    let asked = Arc::clone(&here);
    let _distance = ns.serve("distance_to", move |(x, y): (f64, f64)| {
        let p = *asked.lock().unwrap_or_else(|e| e.into_inner());
        async move { Ok::<f64, pulicast::Fault>((p.x - x).hypot(p.y - y)) }
    })?;
    let mut cmd = Twist::default();
    let (mut received, mut lost, mut sent) = (0u64, 0u64, 0u64);
    let dt = Duration::from_millis(50);
    let mut tick = tokio::time::interval(dt);
    let started = Instant::now();
    let mut last_print = Instant::now();
    while started.elapsed() < run_for {
        tokio::select! {
            _ = tick.tick() => {
                let t = dt.as_secs_f64();
                let driving = mode.get().as_deref() == Some("drive");
                let limit = max_speed.get().unwrap_or(0.0);
                let linear = if driving { cmd.linear.clamp(-limit, limit) } else { 0.0 };
                // Turning keeps the circle's radius at the speed allowed.
                let angular = match cmd.linear {
                    l if l != 0.0 => cmd.angular * linear / l,
                    _ => 0.0,
                };
                pose.heading += angular * t;
                pose.x += linear * pose.heading.cos() * t;
                pose.y += linear * pose.heading.sin() * t;
                pose_channel.publish(&pose)?;
                *here.lock().unwrap_or_else(|e| e.into_inner()) = pose;
                sent += 1;
                if last_print.elapsed() >= Duration::from_secs(1) {
                    last_print = Instant::now();
                    println!(
                        "[{me}] at ({:6.2}, {:6.2}) heading {:5.2} | command linear {:.2} angular {:.2}",
                        pose.x, pose.y, pose.heading, cmd.linear, cmd.angular
                    );
                }
            }
            Some(m) = commands.recv() => {
                received += 1;
                lost += u64::try_from(m.lead - 1).unwrap_or(0);
                cmd = m.value;
            }
        }
    }
    println!("[{me}] done: sent {sent} poses, received {received} commands, lost {lost}");
    Ok(())
}

/// Steers every rover around a circle of its own and reports the fleet.
async fn controller(node: &Node, run_for: Duration) -> pulicast::Result<()> {
    let mut poses = Vec::new();
    for rover in ROVERS {
        poses.push(
            node.make_namespace(rover)
                .channel("pose")
                .subscribe::<Pose>()?,
        );
    }
    let mut distances = Vec::new();
    for rover in ROVERS {
        distances.push(
            node.make_namespace(rover)
                .client::<(f64, f64), f64>("distance_to")?,
        );
    }
    let mut latest: Vec<Option<Pose>> = vec![None; ROVERS.len()];
    let mut received = vec![0u64; ROVERS.len()];
    let mut tick = tokio::time::interval(Duration::from_millis(100));
    let started = Instant::now();
    let mut last_print = Instant::now();
    while started.elapsed() < run_for {
        tick.tick().await;
        for (i, sub) in poses.iter_mut().enumerate() {
            while let Some(m) = sub.try_recv() {
                latest[i] = Some(m.value);
                received[i] += 1;
            }
        }
        for (i, rover) in ROVERS.iter().enumerate() {
            // Each rover circles with its own radius: speed / turn rate.
            let radius = 1.0 + i as f64;
            let twist = Twist {
                linear: 0.5,
                angular: 0.5 / radius,
            };
            node.make_namespace(rover).channel("ctrl").publish(&twist)?;
        }
        if last_print.elapsed() >= Duration::from_secs(1) {
            last_print = Instant::now();
            let mut peers: Vec<String> = node
                .peers()
                .iter()
                .map(|p| {
                    format!(
                        "{}({})",
                        p.name,
                        p.publishes()
                            .filter(|c| !pulicast::is_hidden_channel(c))
                            .collect::<Vec<_>>()
                            .join(",")
                    )
                })
                .collect();
            peers.sort();
            println!("[controller] peers: {}", peers.join(" "));
            for (i, rover) in ROVERS.iter().enumerate() {
                // A service call: the reply, or why there is none.
                let asked = distances[i]
                    .call_within(&(0.0, 0.0), Duration::from_millis(300))
                    .await;
                let distance = match asked {
                    Ok(d) => format!("{d:.2} m from the start"),
                    Err(e) => format!("distance unknown: {e}"),
                };
                match latest[i] {
                    Some(p) => println!(
                        "[controller] {rover} at ({:6.2}, {:6.2}), {distance}",
                        p.x, p.y
                    ),
                    None => println!("[controller] {rover}: no pose yet, {distance}"),
                }
            }
        }
    }
    for (i, rover) in ROVERS.iter().enumerate() {
        println!(
            "[controller] done: received {} poses from {rover}",
            received[i]
        );
    }
    Ok(())
}
