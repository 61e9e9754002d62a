//! What a restarted agent needs to rejoin its formation (docs/model.md §14): its
//! robot's pose, written every [`PERIOD`] to a small file where the next
//! process with the same run, id and scenario finds it.

use crate::error::Error;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use formation_plant::Pose;
use serde::{Deserialize, Serialize};

/// How often the pose is written: a restarted robot resumes from a pose at
/// most this old (it stops while its agent is down).
pub const PERIOD: Duration = Duration::from_millis(100);

/// One checkpoint.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Checkpoint {
    /// The scenario's fingerprint and the run's epoch: a checkpoint of
    /// another scenario or another run is not used.
    pub fingerprint: u64,
    pub epoch_unix_ns: u64,
    pub k: u64,
    pub pose: [f64; 3],
}

impl Checkpoint {
    pub fn pose(&self) -> Pose {
        Pose::new(self.pose[0], self.pose[1], self.pose[2])
    }
}

/// The checkpoint file of follower `id` of run `run` under `dir`.
pub fn path(dir: &Path, run: &str, id: u32) -> PathBuf {
    dir.join(format!("{run}-follower-{id}.json"))
}

/// The default folder: `formation-checkpoints` in the system's temporary folder.
pub fn default_dir() -> PathBuf {
    std::env::temp_dir().join("formation-checkpoints")
}

/// A checkpoint is a few hundred bytes of JSON: a file larger than this is not one.
const MAX_BYTES: usize = 64 * 1024;

/// Reads a checkpoint; None if there is none, it cannot be read, or it
/// belongs to another scenario or run.
pub fn read(path: &Path, fingerprint: u64, epoch_unix_ns: u64) -> Result<Checkpoint, Error> {
    // A regular file of a checkpoint's size: the folder is under the shared
    // temporary folder, where another user could plant a FIFO or a link to
    // a device.
    let bytes = formation_record::hearing::read_regular(path, MAX_BYTES)
        .map_err(|e| Error::Input(format!("no checkpoint at {} ({e})", path.display())))?;
    let text = String::from_utf8(bytes).map_err(|_| Error::Input(format!("{}: not a checkpoint", path.display())))?;
    let c: Checkpoint =
        serde_json::from_str(&text).map_err(|e| Error::Input(format!("{}: not a checkpoint ({e})", path.display())))?;
    if c.fingerprint != fingerprint || c.epoch_unix_ns != epoch_unix_ns {
        return Err(Error::Input(format!("{}: a checkpoint of another run or scenario", path.display())));
    }
    if !c.pose.iter().all(|x| x.is_finite()) {
        return Err(Error::Input(format!("{}: a pose that is not finite", path.display())));
    }
    Ok(c)
}

/// The latest (step, pose), updated by the control loop.
pub type Latest = Arc<Mutex<Option<(u64, Pose)>>>;

/// The thread that writes a follower's checkpoint; [`Writer::stop`] ends it at once.
pub struct Writer {
    stop: std::sync::mpsc::Sender<()>,
    thread: std::thread::JoinHandle<()>,
}

impl Writer {
    /// Ends the writer (it is woken, not waited for a period) and joins it.
    pub fn stop(self) {
        drop(self.stop);
        let _ = self.thread.join();
    }
}

/// Writes `latest` to `path` every [`PERIOD`] (atomically: a temporary file
/// renamed over the old one) until stopped. Errors are said once.
pub fn start_writer(path: PathBuf, fingerprint: u64, epoch_unix_ns: u64, latest: Latest) -> Writer {
    let (stop, stopped) = std::sync::mpsc::channel::<()>();
    let thread = std::thread::spawn(move || {
        let mut said = false;
        let tmp = path.with_extension("json.tmp");
        let mut written = None;
        // Sleeps a period, or ends as soon as the sender is dropped.
        while let Err(std::sync::mpsc::RecvTimeoutError::Timeout) = stopped.recv_timeout(PERIOD) {
            let Some((k, pose)) = *latest.lock().unwrap_or_else(|p| p.into_inner()) else { continue };
            if written == Some(k) {
                continue;
            }
            let c = Checkpoint { fingerprint, epoch_unix_ns, k, pose: [pose.x, pose.y, pose.theta] };
            let result = path
                .parent()
                .map_or(Ok(()), std::fs::create_dir_all)
                .and_then(|()| std::fs::write(&tmp, serde_json::to_vec(&c).unwrap_or_default()))
                .and_then(|()| std::fs::rename(&tmp, &path));
            match result {
                Ok(()) => written = Some(k),
                Err(e) if !said => {
                    eprintln!(
                        "cannot write the checkpoint {}: {e} (a restart will begin from the initial pose)",
                        path.display()
                    );
                    said = true;
                }
                Err(_) => {}
            }
        }
    });
    Writer { stop, thread }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_checkpoint_is_used_only_by_its_own_run() {
        let dir = tempfile::tempdir().expect("tempdir");
        let p = path(dir.path(), "paper", 3);
        let latest: Latest = Arc::new(Mutex::new(Some((1234, Pose::new(1.0, 2.0, 0.5)))));
        let w = start_writer(p.clone(), 7, 99, latest);
        std::thread::sleep(PERIOD * 3);
        let stopping = std::time::Instant::now();
        w.stop();
        // A stop wakes the writer: it does not sleep out its period.
        assert!(stopping.elapsed() < PERIOD / 2, "stop took {:?}", stopping.elapsed());
        let c = read(&p, 7, 99).expect("the run's own checkpoint");
        assert_eq!((c.k, c.pose()), (1234, Pose::new(1.0, 2.0, 0.5)));
        assert!(read(&p, 8, 99).is_err(), "another scenario");
        assert!(read(&p, 7, 100).is_err(), "another run");
        assert!(read(&path(dir.path(), "paper", 4), 7, 99).is_err(), "no file");
    }
}
