//! Serving a router over HTTP/1.1 with the limits a server on an
//! operator's machine needs before anyone has shown a token: a client
//! that opens connections and says nothing, or says a header a byte a
//! minute, holds a place for [`HEADER_READ_TIMEOUT`] at most, and no more
//! than [`MAX_CONNECTIONS`] places exist at once. A connection that
//! became a WebSocket leaves its place (the servers count their clients
//! apart, after the token was checked).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use axum::Router;
use hyper::server::conn::http1;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use tokio::net::TcpListener;
use tokio::sync::{watch, Semaphore};
use tokio::task::JoinSet;

/// How long a connection may take to send a request's headers, and how
/// long it may sit idle between requests.
pub const HEADER_READ_TIMEOUT: Duration = Duration::from_secs(10);

/// Most HTTP connections open at once, not counting WebSockets; one more
/// is closed as soon as it is accepted (and counted).
pub const MAX_CONNECTIONS: usize = 256;

/// How long requests under way may take to finish once the server
/// stops; then their connections are closed.
pub const DRAIN_FOR: Duration = Duration::from_secs(5);

/// Largest request head, in bytes.
pub const MAX_HEADER_BYTES: usize = 16 * 1024;

/// The limits [`serve`] holds to.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    /// See [`HEADER_READ_TIMEOUT`].
    pub header_read_timeout: Duration,
    /// See [`MAX_CONNECTIONS`].
    pub max_connections: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            header_read_timeout: HEADER_READ_TIMEOUT,
            max_connections: MAX_CONNECTIONS,
        }
    }
}

/// What [`serve`] turned away.
#[derive(Debug, Default)]
pub struct Refused {
    /// Connections closed at once because [`Limits::max_connections`]
    /// were open.
    pub over_capacity: AtomicU64,
}

/// Serves `router` on `listener` until `stop` resolves, then lets the
/// requests under way finish.
pub async fn serve(
    listener: TcpListener,
    router: Router,
    stop: impl std::future::Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    serve_with(listener, router, stop, Limits::default(), Arc::default()).await
}

/// [`serve`] with other limits, counting what it refuses in `refused`.
pub async fn serve_with(
    listener: TcpListener,
    router: Router,
    stop: impl std::future::Future<Output = ()> + Send + 'static,
    limits: Limits,
    refused: Arc<Refused>,
) -> std::io::Result<()> {
    let places = Arc::new(Semaphore::new(limits.max_connections));
    let (closing, closed) = watch::channel(false);
    let mut connections = JoinSet::new();
    let mut stop = std::pin::pin!(stop);
    loop {
        let (stream, _) = tokio::select! {
            () = &mut stop => break,
            accepted = listener.accept() => match accepted {
                Ok(accepted) => accepted,
                // Out of descriptors, or a connection reset before it
                // was taken: the listener itself is fine.
                Err(e) => {
                    tracing::debug!("accept: {e}");
                    tokio::time::sleep(Duration::from_millis(10)).await;
                    continue;
                }
            },
            // Finished connections leave the set as they go.
            Some(_) = connections.join_next(), if !connections.is_empty() => continue,
        };
        let Ok(place) = Arc::clone(&places).try_acquire_owned() else {
            let n = refused.over_capacity.fetch_add(1, Ordering::Relaxed) + 1;
            if n.is_power_of_two() {
                tracing::warn!(
                    "{n} connection(s) closed at once: {} were open",
                    limits.max_connections
                );
            }
            drop(stream);
            continue;
        };
        let service = TowerToHyperService::new(router.clone());
        let mut closed = closed.clone();
        connections.spawn(async move {
            let mut builder = http1::Builder::new();
            builder
                .timer(TokioTimer::new())
                .header_read_timeout(limits.header_read_timeout)
                .max_header_size(MAX_HEADER_BYTES);
            let connection = builder
                .serve_connection(TokioIo::new(stream), service)
                .with_upgrades();
            let mut connection = std::pin::pin!(connection);
            let mut closing = false;
            loop {
                tokio::select! {
                    result = connection.as_mut() => {
                        if let Err(e) = result {
                            tracing::trace!("connection: {e}");
                        }
                        break;
                    }
                    changed = closed.changed(), if !closing => {
                        closing = true;
                        if changed.is_ok() {
                            connection.as_mut().graceful_shutdown();
                        }
                    }
                }
            }
            drop(place);
        });
    }
    drop(listener);
    let _ = closing.send(true);
    // Requests under way get their answers; a client that never reads
    // its answer can't hold the stop for long.
    let drained = tokio::time::timeout(DRAIN_FOR, async {
        while connections.join_next().await.is_some() {}
    })
    .await;
    if drained.is_err() {
        connections.shutdown().await;
    }
    Ok(())
}
