//! `puli-web`: the fleet in a browser (`puli web` runs it). See
//! docs/web.md.

use std::net::{IpAddr, Ipv4Addr, SocketAddr};

use clap::Parser;
use pulicast_tools::flags::NetArgs;

/// Serves a live page of the fleet (its members, channels with their
/// rates, services, and who publishes and subscribes what) on loopback,
/// behind a random token printed at start.
#[derive(Parser, Debug)]
#[command(name = "puli-web", version)]
struct Args {
    #[command(flatten)]
    net: NetArgs,
    /// TCP port of the page (0: any free one).
    #[arg(long, default_value_t = 8780)]
    http_port: u16,
    /// Address to listen on. Anything but loopback lets other machines
    /// reach the page (with the token): a warning says so.
    #[arg(long, default_value_t = IpAddr::V4(Ipv4Addr::LOCALHOST))]
    listen: IpAddr,
    /// A further origin allowed to use the page (`http://robot.local:8780`),
    /// for a page reached by another name. May be repeated.
    #[arg(long = "allow-origin")]
    allow_origins: Vec<String>,
    /// Print the address as one JSON line (`{"url", "token"}`), for scripts.
    #[arg(long)]
    json: bool,
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let node = args.net.node("puli-web")?.start().await?;
    let listener =
        tokio::net::TcpListener::bind(SocketAddr::new(args.listen, args.http_port)).await?;
    let port = listener.local_addr()?.port();
    if !args.listen.is_loopback() {
        eprintln!(
            "puli web: warning: listening on {}: anyone who reaches it with the token drives the fleet, \
             and nothing is encrypted",
            args.listen
        );
    }
    let guard = puli_web::guard::Guard::new(args.listen, port, &args.allow_origins)?;
    let shown = match args.listen.is_unspecified() {
        true => IpAddr::V4(Ipv4Addr::LOCALHOST),
        false => args.listen,
    };
    let url = format!(
        "http://{}/?token={}",
        SocketAddr::new(shown, port),
        guard.token()
    );
    if args.json {
        println!(
            "{}",
            serde_json::json!({ "url": url, "token": guard.token(), "port": port })
        );
    } else {
        println!("puli web: open {url}");
    }
    let app = puli_web::server::App::new(&node, guard);
    let (stop, stopping) = tokio::sync::oneshot::channel::<()>();
    let serving = tokio::spawn(async move {
        app.serve(listener, async {
            let _ = stopping.await;
        })
        .await
    });
    tokio::signal::ctrl_c().await?;
    let _ = stop.send(());
    // Connections that never finish their request don't hold the exit.
    let _ = tokio::time::timeout(std::time::Duration::from_secs(2), serving).await;
    node.stop();
    Ok(())
}
