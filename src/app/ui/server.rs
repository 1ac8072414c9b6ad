//! The live page's HTTP server (axum on the service's tokio runtime) and its hub.
//!
//! The service hands its JSON lines to the hub ([`Feed::line`], from the writer of a JSON consumer
//! of its own, behind that consumer's bounded queue); the hub keeps the page's state
//! ([`super::live::UiState`]) and passes each line on to the connected pages through a bounded
//! broadcast channel. A page that falls behind loses lines (counted), never holds the hub or the
//! service. `GET /`: the page; `GET /api/state`: a snapshot (imucald.ui/1); `GET /api/events`:
//! Server-Sent Events, first the snapshot (`event: state`), then every line as it comes.
//! [`LiveUi::stop`] ends every event stream, so an open page cannot hold the service's exit.

use super::live::{StreamStats, UiState};
use crate::error::Error;
use axum::body::{Body, Bytes};
use axum::extract::State;
use axum::http::header;
use axum::response::{IntoResponse, Response};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::{broadcast, watch};

/// Lines the event stream buffers for a page that has not taken them yet; past that the page
/// misses the oldest (counted as `lagged_lines`).
pub(crate) const STREAM_BUFFER_LINES: usize = 256;
/// How long [`LiveUi::stop`] waits for the server to close its connections before dropping it.
pub(crate) const STOP_WAIT: Duration = Duration::from_millis(200);

/// The state and the stream, shared by the service's feed and the HTTP handlers.
pub(crate) struct Hub {
    start: Instant,
    state: Mutex<UiState>,
    tx: broadcast::Sender<Arc<str>>,
    stop: watch::Receiver<bool>,
    clients: AtomicU64,
    lagged: AtomicU64,
}

impl Hub {
    fn now_s(&self) -> f64 {
        self.start.elapsed().as_secs_f64()
    }

    fn stats(&self) -> StreamStats {
        StreamStats {
            clients: self.clients.load(Ordering::Relaxed),
            lagged_lines: self.lagged.load(Ordering::Relaxed),
        }
    }

    /// `/api/state`.
    pub(crate) fn snapshot_json(&self) -> String {
        let st = self.state.lock().unwrap_or_else(|p| p.into_inner());
        st.snapshot_json(self.now_s(), self.stats())
    }

    /// A snapshot and a receiver of every line after it (taken under the same lock as
    /// [`Feed::line`] updates the state, so none is missed or seen twice).
    fn subscribe(&self) -> (String, broadcast::Receiver<Arc<str>>) {
        let st = self.state.lock().unwrap_or_else(|p| p.into_inner());
        (
            st.snapshot_json(self.now_s(), self.stats()),
            self.tx.subscribe(),
        )
    }
}

/// Where the service hands its JSON lines (cheap to clone).
#[derive(Clone)]
pub(crate) struct Feed(Arc<Hub>);

impl Feed {
    /// Take one line: the state is updated and the line passed on to the connected pages (never
    /// waits: a page behind by [`STREAM_BUFFER_LINES`] loses the oldest).
    pub fn line(&self, line: &Arc<str>) {
        let hub = &self.0;
        let mut st = hub.state.lock().unwrap_or_else(|p| p.into_inner());
        st.apply_line(line, hub.now_s());
        // No page connected: nothing to pass on.
        let _ = hub.tx.send(line.clone());
    }
}

/// The running server.
pub struct LiveUi {
    hub: Arc<Hub>,
    stop: watch::Sender<bool>,
    task: tokio::task::JoinHandle<()>,
    /// The address it listens on (the port chosen when 0 was asked).
    pub addr: std::net::SocketAddr,
}

#[derive(Clone)]
struct App {
    hub: Arc<Hub>,
}

impl LiveUi {
    /// Listen on `addr` (checked by the config: loopback unless allowed) and serve.
    pub async fn start(addr: &str) -> Result<LiveUi, Error> {
        let fail = |e: std::io::Error| Error::Config {
            key: "ui.listen".into(),
            message: format!("cannot listen on {addr}: {e}"),
        };
        let listener = tokio::net::TcpListener::bind(addr).await.map_err(fail)?;
        let bound = listener.local_addr().map_err(fail)?;
        tracing::info!(
            target: crate::types::STATUS_TARGET,
            "live page at http://{bound}/ (open it in a browser)"
        );
        let (stop_tx, stop_rx) = watch::channel(false);
        let (tx, _) = broadcast::channel(STREAM_BUFFER_LINES);
        let hub = Arc::new(Hub {
            start: Instant::now(),
            state: Mutex::new(UiState::default()),
            tx,
            stop: stop_rx.clone(),
            clients: AtomicU64::new(0),
            lagged: AtomicU64::new(0),
        });
        let app = axum::Router::new()
            .route("/", axum::routing::get(page))
            .route("/api/state", axum::routing::get(state))
            .route("/api/events", axum::routing::get(events))
            .with_state(App { hub: hub.clone() });
        let mut stop = stop_rx;
        let task = tokio::spawn(async move {
            let done = async move {
                let _ = stop.wait_for(|s| *s).await;
            };
            if let Err(e) = axum::serve(listener, app)
                .with_graceful_shutdown(done)
                .await
            {
                tracing::warn!("live page server: {e}");
            }
        });
        tracing::info!("live page at http://{bound}/");
        Ok(LiveUi {
            hub,
            stop: stop_tx,
            task,
            addr: bound,
        })
    }

    /// Where the service hands its lines.
    pub(crate) fn feed(&self) -> Feed {
        Feed(self.hub.clone())
    }

    /// End the event streams and the server; a connection still open after [`STOP_WAIT`] is
    /// dropped with the server's task.
    pub async fn stop(mut self) {
        let _ = self.stop.send(true);
        if tokio::time::timeout(STOP_WAIT, &mut self.task)
            .await
            .is_err()
        {
            self.task.abort();
        }
    }
}

async fn page() -> Response {
    (
        [
            (header::CONTENT_TYPE, "text/html; charset=utf-8"),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        super::LIVE_PAGE,
    )
        .into_response()
}

async fn state(State(app): State<App>) -> Response {
    (
        [
            (header::CONTENT_TYPE, "application/json"),
            (header::CACHE_CONTROL, "no-store"),
        ],
        app.hub.snapshot_json(),
    )
        .into_response()
}

/// One page's event stream: counts itself while connected.
struct Stream {
    hub: Arc<Hub>,
    first: Option<String>,
    rx: broadcast::Receiver<Arc<str>>,
    stop: watch::Receiver<bool>,
}

impl Drop for Stream {
    fn drop(&mut self) {
        self.hub.clients.fetch_sub(1, Ordering::Relaxed);
    }
}

impl Stream {
    /// The next message of the stream; `None` ends it (the service stopping).
    async fn next(&mut self) -> Option<Bytes> {
        if let Some(s) = self.first.take() {
            return Some(Bytes::from(format!("event: state\ndata: {s}\n\n")));
        }
        loop {
            if *self.stop.borrow() {
                return None;
            }
            tokio::select! {
                _ = self.stop.changed() => {}
                r = self.rx.recv() => match r {
                    Ok(line) => return Some(Bytes::from(format!("data: {}\n\n", line.trim_end()))),
                    Err(broadcast::error::RecvError::Lagged(n)) => {
                        self.hub.lagged.fetch_add(n, Ordering::Relaxed);
                    }
                    Err(broadcast::error::RecvError::Closed) => return None,
                },
            }
        }
    }
}

async fn events(State(app): State<App>) -> Response {
    let hub = app.hub;
    hub.clients.fetch_add(1, Ordering::Relaxed);
    let (first, rx) = hub.subscribe();
    let stop = hub.stop.clone();
    let stream = Stream {
        hub,
        first: Some(first),
        rx,
        stop,
    };
    let body = futures_util::stream::unfold(stream, |mut s| async move {
        let b = s.next().await?;
        Some((Ok::<_, std::convert::Infallible>(b), s))
    });
    (
        [
            (header::CONTENT_TYPE, "text/event-stream"),
            (header::CACHE_CONTROL, "no-store"),
        ],
        Body::from_stream(body),
    )
        .into_response()
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    async fn get(addr: std::net::SocketAddr, path: &str) -> String {
        let mut c = tokio::net::TcpStream::connect(addr).await.unwrap();
        let req = format!("GET {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n");
        c.write_all(req.as_bytes()).await.unwrap();
        let mut out = String::new();
        c.read_to_string(&mut out).await.unwrap();
        out
    }

    /// The page, the snapshot, and an event stream that gets the snapshot then every line; a
    /// page that never reads loses lines (counted) without holding the feed; stopping ends the
    /// streams at once.
    #[tokio::test]
    async fn ui_server_serves_state_and_events_and_stops_with_a_page_open() {
        let ui = LiveUi::start("127.0.0.1:0").await.unwrap();
        let feed = ui.feed();
        let line = |pct: f64| -> Arc<str> {
            crate::io::mavout::json_line(&crate::io::mavout::LiveEvent::Progress {
                sensor: "mag".into(),
                instance: 0,
                completion_pct: pct,
                filled_regions: pct as usize,
                regions: String::new(),
                direction: [0.0; 3],
            })
            .into()
        };
        feed.line(&line(12.0));
        let page = get(ui.addr, "/").await;
        assert!(page.starts_with("HTTP/1.1 200"), "{page}");
        assert!(page.contains("<canvas"), "{page}");
        let st = get(ui.addr, "/api/state").await;
        let body = &st[st.find("\r\n\r\n").unwrap() + 4..];
        let v: serde_json::Value = serde_json::from_str(body).unwrap();
        assert_eq!(v["schema"], "imucald.ui/1");
        assert_eq!(v["progress"][0]["completion_pct"], 12.0);

        // A page reading its stream, and one that never reads.
        let mut reader = tokio::net::TcpStream::connect(ui.addr).await.unwrap();
        reader
            .write_all(b"GET /api/events HTTP/1.1\r\nHost: x\r\n\r\n")
            .await
            .unwrap();
        let mut stuck = tokio::net::TcpStream::connect(ui.addr).await.unwrap();
        stuck
            .write_all(b"GET /api/events HTTP/1.1\r\nHost: x\r\n\r\n")
            .await
            .unwrap();
        let mut got = String::new();
        let mut buf = vec![0u8; 65536];
        while !got.contains("event: state") {
            let n = reader.read(&mut buf).await.unwrap();
            got.push_str(&String::from_utf8_lossy(&buf[..n]));
        }
        assert!(hub_clients(&ui) >= 1);
        // 20 000 lines of ~2 kB each: far more than the stuck page's socket and buffer hold.
        let t0 = Instant::now();
        let big: Arc<str> = format!(
            "{{\"schema\":\"imucald.live/1\",\"type\":\"status\",\"level\":\"info\",\"text\":\"{}\"}}\n",
            "x".repeat(2000)
        )
        .into();
        for i in 0..20_000 {
            feed.line(&big);
            if i % 500 == 0 {
                tokio::task::yield_now().await;
            }
        }
        feed.line(&line(40.0));
        let fed_s = t0.elapsed().as_secs_f64();
        // The reading page gets the last line (it may have lagged too: it is read only now).
        let until = Instant::now() + Duration::from_secs(5);
        while !got.contains("\"completion_pct\":40.0") && Instant::now() < until {
            let n = tokio::time::timeout(Duration::from_secs(1), reader.read(&mut buf))
                .await
                .map_or(0, |r| r.unwrap_or(0));
            got.push_str(&String::from_utf8_lossy(&buf[..n]));
            let keep = got.len().saturating_sub(4096);
            got.drain(..keep);
        }
        assert!(got.contains("\"completion_pct\":40.0"));
        let lagged = ui.hub.stats().lagged_lines;
        assert_eq!(hub_clients(&ui), 2);
        // Measured: ~0.15 s to feed in debug builds; some thousands lagged on the stuck page.
        assert!(fed_s < 5.0, "{fed_s}");
        assert!(lagged > 1000, "{lagged}");
        let t1 = Instant::now();
        ui.stop().await;
        let stop_s = t1.elapsed().as_secs_f64();
        // Measured: under 1 ms; the bound is the drop after STOP_WAIT.
        assert!(stop_s < 0.5, "{stop_s}");
        drop(stuck);
    }

    fn hub_clients(ui: &LiveUi) -> u64 {
        ui.hub.stats().clients
    }
}
