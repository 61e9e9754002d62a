//! What a restarted agent needs to rejoin its formation (docs/model.md §14): its
//! robot's pose, written every [`PERIOD`] to a small file where the next
//! process with the same run, id and scenario finds it.

use formation_exit::Error;
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

/// A checkpoint on disk: its JSON padded with spaces to this many bytes
/// (JSON allows trailing white space), so that each write is one `pwrite`
/// over the last one in place.
const RECORD_BYTES: usize = 256;

/// Opens (or creates) the checkpoint file for writing in place: not
/// through a symbolic link, not a FIFO or a device (the folder is under the
/// shared temporary folder, where another user could plant either).
fn open_in_place(path: &Path) -> std::io::Result<std::fs::File> {
    use std::os::unix::fs::OpenOptionsExt;
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)?;
    }
    let file = std::fs::OpenOptions::new()
        .write(true)
        .create(true)
        .custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK)
        .open(path)?;
    if !file.metadata()?.is_file() {
        return Err(std::io::Error::other("not a regular file"));
    }
    file.set_len(RECORD_BYTES as u64)?;
    Ok(file)
}

/// The bytes of one checkpoint on disk (see [`RECORD_BYTES`]).
fn record(c: &Checkpoint) -> Vec<u8> {
    let mut bytes = serde_json::to_vec(c).unwrap_or_default();
    if bytes.len() < RECORD_BYTES {
        bytes.resize(RECORD_BYTES - 1, b' ');
        bytes.push(b'\n');
    }
    bytes
}

/// Writes `latest` to `path` every [`PERIOD`] until stopped: the file is
/// opened once and each checkpoint written over the last in place, one
/// `pwrite` of [`RECORD_BYTES`] (a process killed between two writes leaves
/// the last whole). Before, each write was a new temporary file renamed over
/// the old one: at 100 agents, 1,000 renames a second in one folder, each
/// of which made ext4 start writing the file to disk. Errors are said once.
pub fn start_writer(path: PathBuf, fingerprint: u64, epoch_unix_ns: u64, latest: Latest) -> Writer {
    start_writer_every(PERIOD, path, fingerprint, epoch_unix_ns, latest)
}

/// [`start_writer`] with a period of its own (a test's).
fn start_writer_every(period: Duration, path: PathBuf, fingerprint: u64, epoch_unix_ns: u64, latest: Latest) -> Writer {
    let (stop, stopped) = std::sync::mpsc::channel::<()>();
    let thread = std::thread::spawn(move || {
        use std::os::unix::fs::FileExt;
        let mut said = false;
        let mut file: Option<std::fs::File> = None;
        let mut written = None;
        // Sleeps a period, or ends as soon as the sender is dropped.
        while let Err(std::sync::mpsc::RecvTimeoutError::Timeout) = stopped.recv_timeout(period) {
            let Some((k, pose)) = *latest.lock().unwrap_or_else(|p| p.into_inner()) else { continue };
            if written == Some(k) {
                continue;
            }
            let c = Checkpoint { fingerprint, epoch_unix_ns, k, pose: [pose.x, pose.y, pose.theta] };
            let result = match &file {
                Some(f) => Ok(f),
                None => open_in_place(&path).map(|f| &*file.insert(f)),
            }
            .and_then(|f| f.write_all_at(&record(&c), 0));
            match result {
                Ok(()) => written = Some(k),
                Err(e) => {
                    file = None;
                    if !said {
                        crate::node::say(&format!(
                            "cannot write the checkpoint {}: {e} (a restart will begin from the initial pose)",
                            path.display()
                        ));
                        said = true;
                    }
                }
            }
        }
    });
    Writer { stop, thread }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// How long a test waits for what the writer must do: a guard against
    /// a hang, not a verdict on speed (a starved host takes longer).
    const GUARD: Duration = Duration::from_secs(60);

    /// Waits (bounded by [`GUARD`]) until `path` holds the checkpoint of step `k`.
    fn wait_for_step(path: &Path, fingerprint: u64, epoch: u64, k: u64) -> Checkpoint {
        let began = std::time::Instant::now();
        loop {
            match read(path, fingerprint, epoch) {
                Ok(c) if c.k == k => return c,
                _ if began.elapsed() > GUARD => panic!("no checkpoint of step {k} in {:?}", GUARD),
                _ => std::thread::sleep(PERIOD / 4),
            }
        }
    }

    #[test]
    fn a_checkpoint_is_used_only_by_its_own_run() {
        let dir = tempfile::tempdir().expect("tempdir");
        let p = path(dir.path(), "paper", 3);
        let latest: Latest = Arc::new(Mutex::new(Some((1234, Pose::new(1.0, 2.0, 0.5)))));
        let w = start_writer(p.clone(), 7, 99, latest);
        let c = wait_for_step(&p, 7, 99, 1234);
        w.stop();
        assert_eq!((c.k, c.pose()), (1234, Pose::new(1.0, 2.0, 0.5)));
        assert!(read(&p, 8, 99).is_err(), "another scenario");
        assert!(read(&p, 7, 100).is_err(), "another run");
        assert!(read(&path(dir.path(), "paper", 4), 7, 99).is_err(), "no file");
    }

    /// A stop wakes the writer: it does not sleep out its period (an hour
    /// here: a writer that slept it out would fail the guard).
    #[test]
    fn a_stop_wakes_the_writer() {
        let dir = tempfile::tempdir().expect("tempdir");
        let latest: Latest = Arc::new(Mutex::new(Some((1, Pose::new(1.0, 2.0, 0.5)))));
        let w = start_writer_every(Duration::from_secs(3600), path(dir.path(), "paper", 3), 7, 99, latest);
        let stopping = std::time::Instant::now();
        w.stop();
        assert!(stopping.elapsed() < GUARD, "stop took {:?} of an hour's period", stopping.elapsed());
    }

    /// Each checkpoint is written over the last in place: a shorter one
    /// leaves nothing of a longer one behind, and the file keeps its size.
    #[test]
    fn a_checkpoint_is_written_over_the_last_in_place() {
        let dir = tempfile::tempdir().expect("tempdir");
        let p = path(dir.path(), "paper", 3);
        let latest: Latest = Arc::new(Mutex::new(Some((123_456_789, Pose::new(-1.234567891234, 2.5e-7, 3.0)))));
        let w = start_writer(p.clone(), u64::MAX, u64::MAX - 1, latest.clone());
        wait_for_step(&p, u64::MAX, u64::MAX - 1, 123_456_789);
        *latest.lock().unwrap() = Some((7, Pose::new(0.0, 1.0, 0.5)));
        let c = wait_for_step(&p, u64::MAX, u64::MAX - 1, 7);
        w.stop();
        assert_eq!((c.k, c.pose()), (7, Pose::new(0.0, 1.0, 0.5)));
        let len = std::fs::metadata(&p).expect("the file").len();
        assert_eq!(len, RECORD_BYTES as u64, "one record, written in place");
    }

    /// Under the shared temporary folder another user may plant a link or
    /// a FIFO where the checkpoint goes: the writer neither follows the
    /// link nor waits on the FIFO.
    #[test]
    fn a_planted_link_or_fifo_is_not_written_through() {
        let dir = tempfile::tempdir().expect("tempdir");
        let target = dir.path().join("victim");
        std::fs::write(&target, b"keep").expect("target");
        let p = path(dir.path(), "paper", 1);
        std::os::unix::fs::symlink(&target, &p).expect("symlink");
        let latest: Latest = Arc::new(Mutex::new(Some((1, Pose::new(1.0, 2.0, 0.5)))));
        let w = start_writer(p.clone(), 7, 99, latest.clone());
        std::thread::sleep(PERIOD * 2);
        w.stop();
        assert_eq!(std::fs::read(&target).expect("target"), b"keep", "the link's target is untouched");

        let fifo = path(dir.path(), "paper", 2);
        let c = std::ffi::CString::new(fifo.as_os_str().as_encoded_bytes()).expect("path");
        // SAFETY: a valid NUL-terminated path.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0, "mkfifo");
        let w = start_writer(fifo.clone(), 7, 99, latest);
        std::thread::sleep(PERIOD * 2);
        // A writer stuck opening the FIFO would never end: the guard fails.
        let stopping = std::time::Instant::now();
        w.stop();
        assert!(stopping.elapsed() < GUARD, "the writer is stuck on the FIFO: {:?}", stopping.elapsed());
        assert!(read(&fifo, 7, 99).is_err(), "a FIFO is no checkpoint");
    }
}
