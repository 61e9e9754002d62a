//! `formation play RUN_DIR`: a finished networked run played on
//! the live page (`--web`) and to Foxglove (`--foxglove`) at a chosen
//! speed, with pause and seek, re-computed from its hearing record through
//! the monitor's recorder (so the page shows what the run recorded).
//!
//! The replay runs on a thread of its own and is paced by the wall clock:
//! step k is due `k Δt / speed` after the playback's anchor. A seek forward
//! runs on without pacing up to the target; a seek backward starts the
//! replay again (it takes about a tenth of a second for the paper scenario)
//! and the page, seeing a new playback epoch, reloads its history.

use std::sync::mpsc;
use std::sync::Arc;
use std::time::{Duration, Instant};

use formation_leader::LeaderState;
use formation_record::{FollowerSample, Heard, LiveSink, RecordOptions};
use formation_view::web::{Live, FRAME_PERIOD};

use crate::replay::{self, HearingSource, Loaded, Sink};
use formation_exit::Error;
use formation_recorder::Recorder;

/// What the page (or a test) asks of a playback.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Control {
    Pause,
    Play,
    /// Run seconds per wall-clock second.
    Speed(f64),
    /// Go to run time t (s).
    Seek(f64),
}

impl Control {
    /// `{"pause": true}`, `{"play": true}`, `{"speed": 2}`, `{"seek": 8.5}`.
    pub fn parse(body: &str) -> Option<Self> {
        let v: serde_json::Value = serde_json::from_str(body).ok()?;
        if v["pause"] == true {
            return Some(Control::Pause);
        }
        if v["play"] == true {
            return Some(Control::Play);
        }
        if let Some(s) = v["speed"].as_f64().filter(|s| (MIN_SPEED..=MAX_SPEED).contains(s)) {
            return Some(Control::Speed(s));
        }
        v["seek"].as_f64().filter(|t| t.is_finite() && *t >= 0.0).map(Control::Seek)
    }
}

/// The fastest playback asked for (run seconds per second).
pub const MAX_SPEED: f64 = 1000.0;
/// The slowest (a 30 s run then lasts 50 min; slower never ends in practice).
pub const MIN_SPEED: f64 = 0.01;

/// Where a playback goes: its frames to the live page, the recorder's
/// rows to the sinks (the Foxglove server).
pub struct Outputs {
    pub live: Option<Arc<Live>>,
    pub sinks: Vec<Arc<dyn LiveSink>>,
}

/// The state a playback keeps across restarts (seeks backward).
struct Clock {
    speed: f64,
    paused: bool,
    /// Wall time and run step of the anchor: step k is due at
    /// `at + (k − k0) Δt / speed`.
    at: Instant,
    k0: u64,
    seq: u64,
    epoch: u64,
    last_frame: Option<Instant>,
}

struct Player<'a> {
    recorder: Recorder,
    loaded: &'a Loaded,
    out: &'a Outputs,
    controls: &'a mpsc::Receiver<Control>,
    clock: &'a mut Clock,
    /// Run without pacing up to here (a seek forward, or the start after a seek backward).
    target: u64,
    /// A seek backward: start again and run up to this step.
    restart: Option<u64>,
    began: Instant,
}

impl Player<'_> {
    fn publish(&mut self, state: &str) {
        let Some(live) = &self.out.live else { return };
        let now = Instant::now();
        let c = &mut *self.clock;
        c.seq += 1;
        let (frame, past) =
            self.recorder.live_frame(now, c.seq, self.began.elapsed().as_secs_f64(), state, live.viewers());
        let add = |json: String| -> String {
            let Ok(mut v) = serde_json::from_str::<serde_json::Value>(&json) else { return json };
            v["playback"] = serde_json::json!({"paused": c.paused, "speed": c.speed, "epoch": c.epoch});
            v.to_string()
        };
        live.publish(add(frame), add(past));
        c.last_frame = Some(now);
    }

    /// Applies what was asked; whether to stop here (a seek backward).
    fn obey(&mut self, k: u64, c: Control) -> bool {
        let dt = self.loaded.scenario.dt_s;
        let steps = self.loaded.scenario.steps();
        match c {
            Control::Pause => self.clock.paused = true,
            Control::Play => {
                self.clock.paused = false;
                self.anchor(k);
            }
            Control::Speed(s) => {
                self.clock.speed = s;
                self.anchor(k);
            }
            Control::Seek(t) => {
                let to = ((t / dt).round() as u64).min(steps);
                if to >= k {
                    self.target = to;
                } else {
                    self.restart = Some(to);
                    return true;
                }
            }
        }
        false
    }

    fn anchor(&mut self, k: u64) {
        self.clock.at = Instant::now();
        self.clock.k0 = k;
    }
}

impl Sink for Player<'_> {
    fn leader(&mut self, k: u64, state: &LeaderState, recorded: bool) -> Result<(), Error> {
        self.recorder.leader(k, state, recorded)
    }
    fn follower(&mut self, index: usize, k: u64, sample: &FollowerSample, heard: &[Heard]) -> Result<(), Error> {
        self.recorder.follower(index, k, sample, heard)
    }
    fn step_done(&mut self, k: u64) -> Result<(), Error> {
        self.recorder.step_done(k)?;
        if k < self.target {
            return Ok(());
        }
        if k == self.target {
            self.anchor(k);
            self.publish("running");
        }
        let dt = self.loaded.scenario.dt_s;
        loop {
            while let Ok(c) = self.controls.try_recv() {
                if self.obey(k, c) {
                    return Ok(());
                }
            }
            if k < self.target {
                return Ok(());
            }
            let now = Instant::now();
            if self.clock.last_frame.is_none_or(|t| now.duration_since(t) >= FRAME_PERIOD) {
                self.publish("running");
            }
            if self.clock.paused {
                std::thread::sleep(Duration::from_millis(20));
                self.anchor(k);
                continue;
            }
            let due = self.clock.at + Duration::from_secs_f64((k - self.clock.k0) as f64 * dt / self.clock.speed);
            if now >= due {
                return Ok(());
            }
            // Sleep in short slices: controls are obeyed within 20 ms.
            std::thread::sleep((due - now).min(Duration::from_millis(20)));
        }
    }
    fn stop(&self) -> bool {
        self.restart.is_some()
    }
}

/// Plays `loaded` at `speed` until its end, to the live page and the sinks
/// of `out`; then keeps the page and its controls for `linger` (a seek or
/// play starts again). Blocking: run it on a thread of its own.
pub fn play(
    loaded: &Loaded,
    speed: f64,
    out: &Outputs,
    controls: &mpsc::Receiver<Control>,
    linger: Duration,
) -> Result<(), Error> {
    let tmp = TempDir::new()?;
    let tmp = &tmp.0;
    let mut clock = Clock { speed, paused: false, at: Instant::now(), k0: 0, seq: 0, epoch: 0, last_frame: None };
    let mut from = 0;
    let began = Instant::now();
    loop {
        let opts = RecordOptions {
            dir: tmp.join(format!("play-{}", clock.epoch)),
            every: 1,
            csv: false,
            mcap: false,
            rosbag2: false,
        };
        let mut recorder = Recorder::new(&loaded.scenario, &opts)?;
        for sink in &out.sinks {
            recorder.add_sink(sink.clone());
        }
        let mut p = Player { recorder, loaded, out, controls, clock: &mut clock, target: from, restart: None, began };
        replay::replay(loaded, HearingSource::Recorded, &mut p)?;
        let restart = p.restart;
        if restart.is_none() {
            p.publish("complete");
        }
        p.recorder.discard();
        if let Some(k) = restart {
            from = k;
            clock.epoch += 1;
            if let Some(live) = &out.live {
                live.reset_history();
            }
            continue;
        }
        // The end: keep the page; a seek (or play) starts again.
        let end = Instant::now() + linger;
        let mut again = None;
        while Instant::now() < end {
            match controls.recv_timeout(Duration::from_millis(50)) {
                Ok(Control::Seek(t)) => {
                    again = Some(((t / loaded.scenario.dt_s).round() as u64).min(loaded.scenario.steps()));
                    break;
                }
                Ok(Control::Play) => {
                    again = Some(0);
                    break;
                }
                Ok(Control::Speed(s)) => clock.speed = s,
                Ok(Control::Pause) => {}
                Err(mpsc::RecvTimeoutError::Timeout) => {}
                Err(mpsc::RecvTimeoutError::Disconnected) => break,
            }
        }
        match again {
            Some(k) => {
                from = k;
                clock.epoch += 1;
                clock.paused = false;
                if let Some(live) = &out.live {
                    live.reset_history();
                }
            }
            None => break,
        }
    }
    Ok(())
}

/// A folder of its own for the recorders' (empty) run folders, removed on
/// every path ([`remove_scratch`] when the process ends on a signal).
struct TempDir(std::path::PathBuf);

/// The start of this process's scratch folders' names.
fn scratch_prefix() -> String {
    format!("formation-playback-{}-", std::process::id())
}

/// Removes this process's scratch folders, for a playback that ends on a
/// signal while its thread still holds them.
pub fn remove_scratch() {
    let prefix = scratch_prefix();
    for e in std::fs::read_dir(std::env::temp_dir()).into_iter().flatten().flatten() {
        if e.file_name().to_string_lossy().starts_with(&prefix) {
            let _ = std::fs::remove_dir_all(e.path());
        }
    }
}

impl TempDir {
    fn new() -> Result<Self, Error> {
        static N: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let dir = std::env::temp_dir().join(format!("{}{n}", scratch_prefix()));
        std::fs::create_dir_all(&dir).map_err(|e| Error::Run(format!("{}: {e}", dir.display())))?;
        Ok(Self(dir))
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn controls_parse_and_refuse_nonsense() {
        assert_eq!(Control::parse(r#"{"pause": true}"#), Some(Control::Pause));
        assert_eq!(Control::parse(r#"{"play": true}"#), Some(Control::Play));
        assert_eq!(Control::parse(r#"{"speed": 4}"#), Some(Control::Speed(4.0)));
        assert_eq!(Control::parse(r#"{"seek": 8.5}"#), Some(Control::Seek(8.5)));
        for bad in [
            r#"{"speed": 0}"#,
            r#"{"speed": -1}"#,
            r#"{"speed": 1e9}"#,
            r#"{"speed": 1e-12}"#,
            r#"{"seek": -2}"#,
            "nonsense",
            "{}",
        ] {
            assert_eq!(Control::parse(bad), None, "{bad}");
        }
    }
}
