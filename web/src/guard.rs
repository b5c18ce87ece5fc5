//! Who may use the page: a request needs the token printed at start (in
//! the query once, then in a cookie), a `Host` of the server's own, and,
//! if it has one, an `Origin` of the server's own. A web site open in the
//! operator's browser can't drive the fleet: its requests carry its own
//! origin, and never the token.

use std::net::IpAddr;

use axum::extract::{Request, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

/// The token, and the hosts and origins the server answers.
#[derive(Debug, Clone)]
pub struct Guard {
    token: String,
    cookie: String,
    hosts: Vec<String>,
    origins: Vec<String>,
}

impl Guard {
    /// A guard with a fresh random token for a server on `listen:port`;
    /// `origins` are further origins allowed (`http://robot.local:8780`).
    pub fn new(listen: IpAddr, port: u16, origins: &[String]) -> anyhow::Result<Self> {
        Ok(Self::with_token(listen, port, origins, new_token()?))
    }

    /// A guard with a given token (tests).
    pub fn with_token(listen: IpAddr, port: u16, origins: &[String], token: String) -> Self {
        let mut hosts = vec![
            format!("127.0.0.1:{port}"),
            format!("localhost:{port}"),
            format!("[::1]:{port}"),
        ];
        let own = match listen {
            IpAddr::V4(ip) => format!("{ip}:{port}"),
            IpAddr::V6(ip) => format!("[{ip}]:{port}"),
        };
        if !listen.is_unspecified() && !hosts.contains(&own) {
            hosts.push(own);
        }
        let mut allowed: Vec<String> = hosts.iter().map(|h| format!("http://{h}")).collect();
        allowed.extend(origins.iter().map(|o| o.trim_end_matches('/').to_string()));
        // An origin given as allowed names its host too.
        for origin in origins {
            if let Some(host) = origin
                .trim_end_matches('/')
                .split_once("://")
                .map(|(_, h)| h)
            {
                if !host.is_empty() {
                    hosts.push(host.to_string());
                }
            }
        }
        Self {
            token,
            // Cookies are not kept apart by port: the name is.
            cookie: format!("puli_web_{port}"),
            hosts,
            origins: allowed,
        }
    }

    /// Also lets in what desktop apps send as their origin: Foxglove's and
    /// Lichtblick's Electron pages come from `file://`, and browsers send
    /// `null` (or `file://`) for them. For the Foxglove gate, where the
    /// token is always needed (no cookie a page could ride on): a web
    /// site's page still has an origin of its own, refused.
    pub fn allowing_apps(mut self) -> Self {
        self.origins.push("null".into());
        self.origins.push("file://".into());
        self
    }

    /// The token (printed at start, in the page's address).
    pub fn token(&self) -> &str {
        &self.token
    }

    /// The cookie that carries the token once the page was opened.
    pub fn set_cookie(&self) -> String {
        format!(
            "{}={}; HttpOnly; SameSite=Strict; Path=/",
            self.cookie, self.token
        )
    }

    /// Whether `given` is the token, compared in constant time.
    pub fn is_token(&self, given: &str) -> bool {
        let (a, b) = (self.token.as_bytes(), given.as_bytes());
        a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
    }

    /// Why a request for `path` with `headers` and `query` is refused, if
    /// it is. The token is taken from the query on `/` (the address printed
    /// at start) and `/ws` (for scripts) only, from the cookie anywhere.
    pub fn refusal(
        &self,
        path: &str,
        headers: &HeaderMap,
        query: Option<&str>,
    ) -> Option<(StatusCode, &'static str)> {
        let host = headers.get(header::HOST).and_then(|h| h.to_str().ok());
        if !host.is_some_and(|h| self.hosts.iter().any(|ok| ok.eq_ignore_ascii_case(h))) {
            return Some((
                StatusCode::FORBIDDEN,
                "forbidden: not a host of this server\n",
            ));
        }
        if let Some(origin) = headers.get(header::ORIGIN) {
            let ok = origin
                .to_str()
                .is_ok_and(|o| self.origins.iter().any(|a| a.eq_ignore_ascii_case(o)));
            if !ok {
                return Some((StatusCode::FORBIDDEN, "forbidden: another site's page\n"));
            }
        }
        let in_query = query
            .filter(|_| path == "/" || path == "/ws")
            .into_iter()
            .flat_map(|q| q.split('&'))
            .filter_map(|kv| kv.strip_prefix("token="))
            .any(|t| self.is_token(t));
        let in_cookie = headers
            .get_all(header::COOKIE)
            .iter()
            .filter_map(|v| v.to_str().ok())
            .flat_map(|v| v.split(';'))
            .filter_map(|kv| kv.trim().split_once('='))
            .any(|(k, v)| k == self.cookie && self.is_token(v));
        if !(in_query || in_cookie) {
            return Some((
                StatusCode::UNAUTHORIZED,
                "unauthorized: open the address `puli web` printed, with its token\n",
            ));
        }
        None
    }
}

/// A new random token: 128 bits, in hex.
pub fn new_token() -> anyhow::Result<String> {
    let mut bytes = [0u8; 16];
    getrandom::fill(&mut bytes).map_err(|e| anyhow::anyhow!("no randomness for the token: {e}"))?;
    Ok(bytes.iter().map(|b| format!("{b:02x}")).collect())
}

/// `router` behind `guard`: every route needs what [`Guard::refusal`]
/// asks, and every answer carries the [`headers`].
pub fn guarded(router: axum::Router, guard: &std::sync::Arc<Guard>) -> axum::Router {
    router
        .layer(axum::middleware::from_fn_with_state(
            std::sync::Arc::clone(guard),
            check,
        ))
        .layer(axum::middleware::from_fn(headers))
}

/// The middleware in front of every route.
pub async fn check(
    State(guard): State<std::sync::Arc<Guard>>,
    request: Request,
    next: Next,
) -> Response {
    let uri = request.uri();
    if let Some((status, why)) = guard.refusal(uri.path(), request.headers(), uri.query()) {
        // Closed after the answer: a connection that has no token does
        // not keep its place to try again (crate::http).
        return (status, [(header::CONNECTION, "close")], why).into_response();
    }
    next.run(request).await
}

/// The headers every answer carries: no script but the page's own, no
/// framing, no sniffing, no caching.
pub async fn headers(request: Request, next: Next) -> Response {
    let mut response = next.run(request).await;
    let h = response.headers_mut();
    h.insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static(
            "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' data:; \
             connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'none'",
        ),
    );
    h.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    h.insert(
        header::REFERRER_POLICY,
        HeaderValue::from_static("no-referrer"),
    );
    // Another page of this machine can't even load the assets.
    h.insert(
        header::HeaderName::from_static("cross-origin-resource-policy"),
        HeaderValue::from_static("same-origin"),
    );
    response
}
