//! The monitor's live page (`monitor --web ADDR`): an HTTP server on the
//! monitor's runtime that serves one embedded page and the run as it goes.
//!
//! - `GET /`: the page (HTML, CSS and script in one file, embedded here).
//! - `GET /api/scene`: what does not change (followers, offsets, graph).
//! - `GET /api/history`: past frames, thinned to at most [`HISTORY`], for a
//!   viewer that joins late.
//! - `GET /api/events`: server-sent events, one `frame` each time the monitor
//!   publishes one (about [`FRAME_PERIOD`]).
//!
//! The monitor serialises each frame once and hands it over through a
//! `watch` channel: a slow viewer skips frames instead of queueing them, a
//! viewer never holds up the monitor, and a closed tab drops its receiver
//! (see [`Live::viewers`]).

use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::extract::State;
use axum::http::header;
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::IntoResponse;
use axum::routing::get;
use tokio::sync::watch;
use tokio_stream::StreamExt;

use formation_exit::Error;

/// How often the monitor publishes a frame (20 Hz).
pub const FRAME_PERIOD: Duration = Duration::from_millis(50);

/// Frames kept for late viewers; beyond this every other one is dropped.
pub const HISTORY: usize = 1000;

/// The page, embedded in the binary.
const PAGE: &str = include_str!("page.html");

/// Frames thinned evenly over the whole run: when full, every other frame
/// goes and only every `stride`-th new one is kept.
#[derive(Default)]
struct History {
    frames: Vec<Arc<str>>,
    stride: u64,
    offered: u64,
}

impl History {
    fn push(&mut self, frame: Arc<str>) {
        let stride = self.stride.max(1);
        self.offered += 1;
        if (self.offered - 1) % stride != 0 {
            return;
        }
        if self.frames.len() >= HISTORY {
            let mut i = 0;
            self.frames.retain(|_| {
                i += 1;
                i % 2 == 1
            });
            self.stride = stride * 2;
        }
        self.frames.push(frame);
    }

    fn json(&self) -> String {
        let mut s = String::with_capacity(self.frames.iter().map(|f| f.len() + 1).sum::<usize>() + 16);
        s.push_str("{\"frames\":[");
        for (i, f) in self.frames.iter().enumerate() {
            if i > 0 {
                s.push(',');
            }
            s.push_str(f);
        }
        s.push_str("]}");
        s
    }
}

/// What a playback does with a control request's body (`POST /api/control`):
/// whether it took it.
pub type ControlFn = Box<dyn Fn(&str) -> bool + Send + Sync>;

/// What the server shares with the monitor.
pub struct Live {
    scene: String,
    latest: watch::Sender<Arc<str>>,
    history: Mutex<History>,
    /// A playback's controls (pause, speed, seek); none for a live run.
    control: Mutex<Option<ControlFn>>,
}

impl Live {
    /// `scene`: the JSON of `GET /api/scene`.
    pub fn new(scene: String) -> Arc<Self> {
        let (latest, _) = watch::channel(Arc::from("{}"));
        Arc::new(Self { scene, latest, history: Mutex::new(History::default()), control: Mutex::new(None) })
    }

    /// A playback: `POST /api/control` bodies go to `f`.
    pub fn set_control(&self, f: ControlFn) {
        *self.control.lock().unwrap_or_else(|p| p.into_inner()) = Some(f);
    }

    /// Forgets the frames kept for late viewers (a playback that starts again).
    pub fn reset_history(&self) {
        *self.history.lock().unwrap_or_else(|p| p.into_inner()) = History::default();
    }

    /// Publishes a frame (JSON) to every viewer, and its lighter copy
    /// (`past`: without what only the newest frame needs) to the history.
    pub fn publish(&self, frame: String, past: String) {
        self.history.lock().unwrap_or_else(|p| p.into_inner()).push(Arc::from(past));
        self.latest.send_replace(Arc::from(frame));
    }

    /// Viewers connected to the event stream now.
    pub fn viewers(&self) -> usize {
        self.latest.receiver_count()
    }
}

/// Where the page is served.
#[derive(Clone, Debug)]
pub enum Bind {
    Tcp(SocketAddr),
    /// A Unix socket: the lab's monitor, in a network namespace of its own,
    /// serves here and the lab forwards a TCP port to it ([`forward`]).
    Unix(std::path::PathBuf),
}

/// Starts serving; what was bound (a TCP port 0 becomes the port taken).
/// The server lives as long as the runtime.
pub async fn serve(bind: Bind, live: Arc<Live>) -> Result<String, Error> {
    let app = axum::Router::new()
        .route("/", get(page))
        .route("/api/scene", get(scene))
        .route("/api/history", get(history))
        .route("/api/events", get(events))
        .route("/api/control", axum::routing::post(control))
        .with_state(live);
    match bind {
        Bind::Tcp(addr) => {
            let listener = tokio::net::TcpListener::bind(addr)
                .await
                .map_err(|e| Error::Input(format!("--web {addr}: cannot listen there: {e}")))?;
            let bound = listener.local_addr().map_err(|e| Error::Run(format!("--web {addr}: {e}")))?;
            tokio::spawn(async move {
                if let Err(e) = axum::serve(listener, app).await {
                    eprintln!("live page: the server stopped: {e}");
                }
            });
            Ok(format!("http://{bound}/"))
        }
        Bind::Unix(path) => {
            let _ = std::fs::remove_file(&path);
            let listener = tokio::net::UnixListener::bind(&path)
                .map_err(|e| Error::Run(format!("live page: listening on {}: {e}", path.display())))?;
            tokio::spawn(async move {
                if let Err(e) = axum::serve(listener, app).await {
                    eprintln!("live page: the server stopped: {e}");
                }
            });
            Ok(format!("unix:{}", path.display()))
        }
    }
}

/// Accepts TCP connections on `addr` and joins each to the Unix socket
/// `to` (the lab's monitor in its namespace); the address bound.
pub async fn forward(addr: SocketAddr, to: std::path::PathBuf) -> Result<SocketAddr, Error> {
    let listener = tokio::net::TcpListener::bind(addr)
        .await
        .map_err(|e| Error::Input(format!("--web {addr}: cannot listen there: {e}")))?;
    let bound = listener.local_addr().map_err(|e| Error::Run(format!("--web {addr}: {e}")))?;
    tokio::spawn(async move {
        while let Ok((mut tcp, _)) = listener.accept().await {
            let to = to.clone();
            tokio::spawn(async move {
                // The monitor may not be serving yet: the browser sees the connection close.
                if let Ok(mut unix) = tokio::net::UnixStream::connect(&to).await {
                    let _ = tokio::io::copy_bidirectional(&mut tcp, &mut unix).await;
                }
            });
        }
    });
    Ok(bound)
}

async fn page() -> impl IntoResponse {
    ([(header::CONTENT_TYPE, "text/html; charset=utf-8"), (header::CACHE_CONTROL, "no-store")], PAGE)
}

fn json(body: String) -> impl IntoResponse {
    ([(header::CONTENT_TYPE, "application/json"), (header::CACHE_CONTROL, "no-store")], body)
}

async fn scene(State(live): State<Arc<Live>>) -> impl IntoResponse {
    json(live.scene.clone())
}

async fn history(State(live): State<Arc<Live>>) -> impl IntoResponse {
    json(live.history.lock().unwrap_or_else(|p| p.into_inner()).json())
}

async fn events(State(live): State<Arc<Live>>) -> impl IntoResponse {
    // The current frame first, then each new one; frames published while
    // this viewer was busy are skipped, never queued.
    let frames = tokio_stream::wrappers::WatchStream::new(live.latest.subscribe())
        .filter(|f| f.len() > 2)
        .map(|f| Ok::<_, std::convert::Infallible>(Event::default().event("frame").data(&*f)));
    Sse::new(frames).keep_alive(KeepAlive::new().interval(Duration::from_secs(5)))
}

/// `POST /api/control`: a playback's pause, play, speed or seek.
async fn control(State(live): State<Arc<Live>>, body: String) -> axum::http::StatusCode {
    use axum::http::StatusCode;
    if body.len() > 1024 {
        return StatusCode::PAYLOAD_TOO_LARGE;
    }
    match &*live.control.lock().unwrap_or_else(|p| p.into_inner()) {
        None => StatusCode::NOT_FOUND,
        Some(f) if f(&body) => StatusCode::NO_CONTENT,
        Some(_) => StatusCode::BAD_REQUEST,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn history_thins_evenly_and_stays_bounded() {
        let mut h = History::default();
        for i in 0..10 * HISTORY as u64 {
            h.push(Arc::from(i.to_string()));
            assert!(h.frames.len() <= HISTORY, "{} frames after {i}", h.frames.len());
        }
        let kept: Vec<u64> = h.frames.iter().map(|f| f.parse().unwrap()).collect();
        assert_eq!(kept[0], 0);
        // Evenly spaced over the whole run.
        let gaps: std::collections::BTreeSet<u64> = kept.windows(2).map(|w| w[1] - w[0]).collect();
        assert_eq!(gaps.len(), 1, "uneven spacing: {gaps:?}");
        assert!(*kept.last().unwrap() >= 9 * HISTORY as u64, "{kept:?}");
        let json: serde_json::Value = serde_json::from_str(&h.json()).expect("valid JSON");
        assert_eq!(json["frames"].as_array().map(Vec::len), Some(kept.len()));
    }
}
