//! Where a run's rows go as they are recorded, besides its run folder: a
//! viewer of the live run (the Foxglove server) behind the one small trait
//! [`LiveSink`], so the recorder that writes the folder knows no server.

use formation_leader::LeaderState;

use crate::row::Row;

/// A viewer fed the run in step order per node, as it is recorded.
/// Calls must return at once (a viewer is on no control path: it drops
/// what it cannot keep up with).
pub trait LiveSink: Send + Sync {
    /// The leader's state of step k (`leader.csv`'s row).
    fn leader(&self, k: u64, state: &LeaderState);
    /// Follower `index`'s row of step k (`follower_<id>.csv`'s).
    fn follower(&self, index: usize, k: u64, row: &Row);
    /// A network event `node` noticed at step k.
    fn event(&self, node: &str, k: u64, what: &str);
    /// Viewers connected now.
    fn viewers(&self) -> usize;
}
