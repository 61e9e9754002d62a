//! The monitor's command-line arguments, and the live page's options that
//! `launch` and the lab pass on to it.

use std::net::SocketAddr;
use std::path::PathBuf;

use crate::node::NodeArgs;

/// `monitor` arguments.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct MonitorArgs {
    #[cfg_attr(feature = "clap", command(flatten))]
    pub node: NodeArgs,
    /// Run folder to write [default: runs/<run name>]. Replaced if it is a run folder; any other existing folder is refused.
    #[cfg_attr(feature = "clap", arg(long, value_name = "DIR"))]
    pub out: Option<PathBuf>,
    /// Write every N-th sample to the CSVs (metrics always use every sample).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 1, value_name = "N"))]
    pub every: u64,
    /// Also write run.mcap: the CSVs' rows as an MCAP recording that
    /// Foxglove and the mcap tools open (poses as foxglove.PoseInFrame, every
    /// column as numbers, network events). About 1.6 KB per follower row:
    /// combine with --every for long runs.
    #[cfg_attr(feature = "clap", arg(long))]
    pub mcap: bool,
    /// Also write rosbag2/: the CSVs' rows as a ROS 2 bag (metadata.yaml and
    /// an MCAP file of CDR messages: odom, cmd_vel, leader_estimate, /tf,
    /// /clock) that `ros2 bag` and Foxglove open (docs/ros2.md).
    #[cfg_attr(feature = "clap", arg(long))]
    pub rosbag2: bool,
    /// Give up when no telemetry arrives for this long (s).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 60.0, value_name = "SECONDS"))]
    pub idle_timeout: f64,
    /// No live line.
    #[cfg_attr(feature = "clap", arg(long, short))]
    pub quiet: bool,
    #[cfg_attr(feature = "clap", command(flatten))]
    pub web: WebArgs,
    /// Serve the live page on this Unix socket instead (the lab forwards a
    /// port of the machine's own namespace to it).
    #[cfg_attr(feature = "clap", arg(long, value_name = "PATH", hide = true, conflicts_with = "web"))]
    pub web_unix: Option<PathBuf>,
}

/// The live page's options (the monitor's, and `launch`'s and the lab's).
#[derive(Debug, Clone, Default)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct WebArgs {
    /// Serve a live page of the run at this address (open http://ADDR/ in a
    /// browser): the plane, errors against time, the network and its events.
    /// `--web` alone: 127.0.0.1:8765. Port 0: any free port (the line
    /// `live page: http://…` says which).
    #[cfg_attr(feature = "clap", arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = "127.0.0.1:8765"))]
    pub web: Option<SocketAddr>,
    /// With --web: keep the page served this long after the run ends, so
    /// that open pages get the end of the run.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 3.0, value_name = "SECONDS"))]
    pub web_linger: f64,
    /// Serve the run live to Foxglove (Foxglove WebSocket protocol) at this
    /// address: the channels of run.mcap (poses, estimates, every CSV
    /// column, network events) at up to 50 messages per channel and second
    /// of run time. In Foxglove: Open connection, Foxglove WebSocket,
    /// ws://ADDR. `--foxglove` alone: 127.0.0.1:8766; port 0: any free port.
    #[cfg_attr(feature = "clap", arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = "127.0.0.1:8766"))]
    pub foxglove: Option<SocketAddr>,
}

impl WebArgs {
    /// The same options on another node's command line.
    pub fn to_args(&self) -> Vec<String> {
        let mut args = match self.web {
            Some(addr) => vec!["--web".into(), addr.to_string(), "--web-linger".into(), self.web_linger.to_string()],
            None => Vec::new(),
        };
        if let Some(addr) = self.foxglove {
            args.extend(["--foxglove".to_string(), addr.to_string()]);
        }
        args
    }
}
