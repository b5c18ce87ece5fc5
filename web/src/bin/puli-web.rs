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
    /// Also serve the fleet to Foxglove (or Lichtblick), on --ws-port,
    /// behind a token of its own.
    #[arg(long)]
    foxglove: bool,
    /// TCP port of the Foxglove server (0: any free one).
    #[arg(long, default_value_t = 8765)]
    ws_port: u16,
    /// Serve no page (with --foxglove: Foxglove only, as `puli foxglove`).
    #[arg(long)]
    no_page: bool,
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    // Warnings (a connection refused, a message of the wrong type, the
    // Foxglove crate's own) reach the operator on stderr; stdout stays
    // the startup line scripts read. RUST_LOG says more.
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                // The crate's sender logs an error for each message it
                // could not send to a client gone (hundreds, when one
                // closes): the gate counts those already.
                .unwrap_or_else(|_| {
                    tracing_subscriber::EnvFilter::new(
                        "warn,foxglove::websocket::connected_client::poller=off",
                    )
                }),
        )
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
    if args.no_page && !args.foxglove {
        anyhow::bail!("--no-page serves nothing without --foxglove");
    }
    let node = args.net.node("puli-web")?.start().await?;
    if !args.listen.is_loopback() {
        eprintln!(
            "puli web: warning: listening on {}: anyone who reaches it with the token drives the fleet, \
             and nothing is encrypted",
            args.listen
        );
    }
    let shown = match args.listen.is_unspecified() {
        true => IpAddr::V4(Ipv4Addr::LOCALHOST),
        false => args.listen,
    };
    let token = puli_web::guard::new_token()?;
    let (stop, stopping) = tokio::sync::watch::channel(false);
    let stopped = |mut rx: tokio::sync::watch::Receiver<bool>| async move {
        let _ = rx.wait_for(|s| *s).await;
    };
    let mut said = serde_json::Map::new();
    let mut serving = Vec::new();

    if !args.no_page {
        let listener =
            tokio::net::TcpListener::bind(SocketAddr::new(args.listen, args.http_port)).await?;
        let port = listener.local_addr()?.port();
        let guard = puli_web::guard::Guard::with_token(
            args.listen,
            port,
            &args.allow_origins,
            token.clone(),
        );
        let url = format!("http://{}/?token={token}", SocketAddr::new(shown, port));
        if !args.json {
            println!("puli web: open {url}");
        }
        said.insert("url".into(), url.into());
        said.insert("token".into(), token.clone().into());
        said.insert("port".into(), port.into());
        let app = puli_web::server::App::new(&node, guard);
        let until = stopped(stopping.clone());
        serving.push(tokio::spawn(
            async move { app.serve(listener, until).await },
        ));
    }

    // Kept while serving: dropped, the Foxglove server's task ends.
    let mut bridge = None;
    if args.foxglove {
        let inner = puli_web::foxglove_server::Bridge::start(&node).await?;
        let listener =
            tokio::net::TcpListener::bind(SocketAddr::new(args.listen, args.ws_port)).await?;
        let port = listener.local_addr()?.port();
        // A token of its own: Foxglove keeps the address (its token with
        // it) in its history and in its own page's address.
        let token = puli_web::guard::new_token()?;
        said.insert("foxglove_token".into(), token.clone().into());
        let guard = puli_web::guard::Guard::with_token(
            args.listen,
            port,
            &args.allow_origins,
            token.clone(),
        )
        .allowing_apps();
        let url = format!("ws://{}/?token={token}", SocketAddr::new(shown, port));
        if !args.json {
            println!("puli web: Foxglove: open a connection to {url}");
        }
        said.insert("foxglove_url".into(), url.into());
        said.insert("foxglove_port".into(), port.into());
        said.insert("foxglove_inner_port".into(), inner.port().into());
        let gate = puli_web::gate::Gate::new(
            guard,
            SocketAddr::new(IpAddr::V4(Ipv4Addr::LOCALHOST), inner.port()),
        );
        let stats = gate.stats();
        let bridge_stats = inner.stats();
        // What a slow client lost, said when it changed.
        tokio::spawn(async move {
            let mut last = (0, 0);
            loop {
                tokio::time::sleep(std::time::Duration::from_secs(10)).await;
                let now = (
                    stats.dropped.load(std::sync::atomic::Ordering::Relaxed),
                    bridge_stats
                        .events_dropped
                        .load(std::sync::atomic::Ordering::Relaxed),
                );
                if now != last {
                    eprintln!(
                        "puli web: Foxglove: {} messages dropped for clients reading slowly, {} events dropped",
                        now.0, now.1
                    );
                    last = now;
                }
            }
        });
        let until = stopped(stopping.clone());
        serving.push(tokio::spawn(
            async move { gate.serve(listener, until).await },
        ));
        bridge = Some(inner);
    }
    if args.json {
        println!("{}", serde_json::Value::Object(said));
    }
    tokio::signal::ctrl_c().await?;
    let _ = stop.send(true);
    // Connections that never finish their request don't hold the exit.
    let _ = tokio::time::timeout(
        std::time::Duration::from_secs(2),
        futures_util::future::join_all(serving),
    )
    .await;
    drop(bridge);
    node.stop();
    Ok(())
}
