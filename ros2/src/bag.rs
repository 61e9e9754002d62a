//! rosbag2 folders with one MCAP file, as `ros2 bag` (Jazzy) reads them.
//!
//! A bag is a folder `<dir>/` holding `<dir name>_0.mcap` and
//! `metadata.yaml`. The formats follow rosbag2 as rosbags 0.11.9 writes
//! it (`rosbag2/writer.py`, `storage_mcap.py`, `metadata.py`) and as
//! rosbag2_storage_mcap reads it:
//!
//! - MCAP profile `ros2`; one schema per type, named `pkg/msg/Name`, with
//!   encoding `ros2msg` and the type's [`Message::DEFINITION`]; one channel
//!   per topic with message encoding `cdr` and the metadata
//!   `offered_qos_profiles` (a YAML list) and `topic_type_hash`; messages
//!   are whole CDR payloads, header included, with publish time = log time;
//! - an MCAP metadata record `rosbag2` whose `serialized_metadata` is the
//!   body of metadata.yaml, as rosbag2_storage_mcap and rosbags write it;
//! - `metadata.yaml` version 9 (Jazzy), top key `rosbag2_bagfile_information`.
//!
//! Infinite QoS durations are written as rmw's `RMW_DURATION_INFINITE`
//! (9223372036 s, 854775807 ns), as Jazzy's rosbag2 does.

use crate::cdr::Reader;
use crate::msgs::Message;
use crate::rmw_keys::{validate_topic, Qos};
use std::collections::BTreeMap;
use std::fs::File;
use std::io::{self, BufWriter};
use std::path::{Path, PathBuf};

/// The rosbag2 metadata version Jazzy writes.
const VERSION: u32 = 9;

/// A topic added to a [`BagWriter`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TopicId(usize);

/// What a finished bag holds.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BagSummary {
    pub mcap_path: PathBuf,
    pub metadata_path: PathBuf,
    pub message_count: u64,
    /// The first message's log time, 0 if there is none.
    pub starting_time_ns: u64,
    /// Last log time minus first log time.
    pub duration_ns: u64,
}

struct Topic {
    name: String,
    type_: &'static str,
    hash: &'static str,
    qos: Qos,
    channel: u16,
    count: u64,
}

/// Writes one bag folder. Call [`BagWriter::finish`]: a writer dropped
/// without it leaves a readable MCAP file but no metadata.yaml.
pub struct BagWriter {
    dir: PathBuf,
    file_name: String,
    mcap: mcap::Writer<BufWriter<File>>,
    topics: Vec<Topic>,
    /// (first, last) log time.
    span: Option<(u64, u64)>,
}

fn invalid_input(msg: String) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidInput, msg)
}

fn mcap_error(context: &str, e: mcap::McapError) -> io::Error {
    io::Error::other(format!("{context}: {e}"))
}

impl BagWriter {
    /// Creates `dir` (or takes it if it exists and is empty) and starts
    /// `dir/<dir name>_0.mcap`. Refuses a non-empty `dir`, so a bag is never
    /// written over another one.
    pub fn create(dir: &Path) -> io::Result<Self> {
        let name = dir.file_name().and_then(|n| n.to_str()).filter(|n| !n.chars().any(char::is_control));
        let Some(name) = name else {
            return Err(invalid_input(format!("{}: a bag folder needs a printable UTF-8 name", dir.display())));
        };
        if dir.exists() && std::fs::read_dir(dir)?.next().is_some() {
            let msg =
                format!("{} exists and is not empty; a bag is written only into a new or empty folder", dir.display());
            return Err(io::Error::new(io::ErrorKind::AlreadyExists, msg));
        }
        std::fs::create_dir_all(dir)?;
        let file_name = format!("{name}_0.mcap");
        let file = File::create_new(dir.join(&file_name))?;
        let mcap = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .profile("ros2")
            .library(concat!("formation-ros2 ", env!("CARGO_PKG_VERSION")))
            .create(BufWriter::new(file))
            .map_err(|e| mcap_error("starting the MCAP file", e))?;
        Ok(Self { dir: dir.to_path_buf(), file_name, mcap, topics: Vec::new(), span: None })
    }

    /// Adds a topic of type `M` offered with `qos`. A topic name is added
    /// once, and must be a valid ROS 2 name.
    pub fn add_topic<M: Message>(&mut self, topic: &str, qos: Qos) -> io::Result<TopicId> {
        validate_topic(topic).map_err(|e| invalid_input(e.to_string()))?;
        if self.topics.iter().any(|t| t.name == topic) {
            return Err(invalid_input(format!("topic {topic} is already in the bag")));
        }
        let schema = self
            .mcap
            .add_schema(M::TYPE, "ros2msg", M::DEFINITION.as_bytes())
            .map_err(|e| mcap_error("adding a schema", e))?;
        let metadata = BTreeMap::from([
            ("offered_qos_profiles".to_string(), qos_yaml(qos)),
            ("topic_type_hash".to_string(), M::HASH.to_string()),
        ]);
        let channel =
            self.mcap.add_channel(schema, topic, "cdr", &metadata).map_err(|e| mcap_error("adding a channel", e))?;
        let t = Topic { name: topic.to_string(), type_: M::TYPE, hash: M::HASH, qos, channel, count: 0 };
        self.topics.push(t);
        Ok(TopicId(self.topics.len() - 1))
    }

    /// Writes one message: a whole CDR payload (as [`Message::encode`]
    /// makes) logged and published at `log_time_ns`.
    pub fn write(&mut self, topic: TopicId, log_time_ns: u64, cdr: &[u8]) -> io::Result<()> {
        Reader::new(cdr).map_err(|e| invalid_input(format!("not a CDR payload: {e}")))?;
        let Some(t) = self.topics.get_mut(topic.0) else {
            return Err(invalid_input(format!("{topic:?} was not added to this bag")));
        };
        let header = mcap::records::MessageHeader {
            channel_id: t.channel,
            sequence: u32::try_from(t.count + 1).unwrap_or(u32::MAX),
            log_time: log_time_ns,
            publish_time: log_time_ns,
        };
        self.mcap.write_to_known_channel(&header, cdr).map_err(|e| mcap_error("writing a message", e))?;
        t.count += 1;
        self.span = Some(match self.span {
            None => (log_time_ns, log_time_ns),
            Some((first, last)) => (first.min(log_time_ns), last.max(log_time_ns)),
        });
        Ok(())
    }

    /// Ends the MCAP file (with its `rosbag2` metadata record) and writes
    /// `metadata.yaml`.
    pub fn finish(mut self) -> io::Result<BagSummary> {
        let (start, end) = self.span.unwrap_or((0, 0));
        let summary = BagSummary {
            mcap_path: self.dir.join(&self.file_name),
            metadata_path: self.dir.join("metadata.yaml"),
            message_count: self.topics.iter().map(|t| t.count).sum(),
            starting_time_ns: start,
            duration_ns: end - start,
        };
        let body = self.metadata_body(&summary);
        let record = mcap::records::Metadata {
            name: "rosbag2".to_string(),
            metadata: BTreeMap::from([("serialized_metadata".to_string(), body.clone())]),
        };
        self.mcap.write_metadata(&record).map_err(|e| mcap_error("writing the rosbag2 metadata record", e))?;
        self.mcap.finish().map_err(|e| mcap_error("finishing the MCAP file", e))?;
        self.mcap.into_inner().into_inner().map_err(|e| e.into_error())?.sync_all()?;
        let yaml = format!("rosbag2_bagfile_information:\n{}", indent(&body, 2));
        std::fs::write(&summary.metadata_path, yaml)?;
        Ok(summary)
    }

    /// metadata.yaml's body (what goes under `rosbag2_bagfile_information`).
    fn metadata_body(&self, s: &BagSummary) -> String {
        let file = yaml_quote(&self.file_name);
        let (count, start, duration) = (s.message_count, s.starting_time_ns, s.duration_ns);
        let topics: String = self.topics.iter().map(topic_yaml).collect();
        let topics = if topics.is_empty() { " []\n".to_string() } else { format!("\n{}", indent(&topics, 2)) };
        format!(
            "version: {VERSION}\n\
             storage_identifier: mcap\n\
             duration:\n  nanoseconds: {duration}\n\
             starting_time:\n  nanoseconds_since_epoch: {start}\n\
             message_count: {count}\n\
             topics_with_message_count:{topics}\
             compression_format: ''\n\
             compression_mode: ''\n\
             relative_file_paths:\n  - {file}\n\
             files:\n  - path: {file}\n    starting_time:\n      nanoseconds_since_epoch: {start}\n    \
             duration:\n      nanoseconds: {duration}\n    message_count: {count}\n\
             custom_data: ~\n\
             ros_distro: jazzy\n"
        )
    }
}

/// One entry of `topics_with_message_count`. Topic names passed
/// [`validate_topic`], so they are plain YAML scalars.
fn topic_yaml(t: &Topic) -> String {
    format!(
        "- topic_metadata:\n    name: {}\n    type: {}\n    serialization_format: cdr\n    \
         offered_qos_profiles:\n{}    type_description_hash: {}\n  message_count: {}\n",
        t.name,
        t.type_,
        indent(&qos_yaml(t.qos), 6),
        t.hash,
        t.count
    )
}

/// The v9 `offered_qos_profiles`: a list of one profile, enum values by
/// name, infinite times as `RMW_DURATION_INFINITE`.
fn qos_yaml(q: Qos) -> String {
    let infinite = "\n    sec: 9223372036\n    nsec: 854775807";
    let reliability = if q.reliable { "reliable" } else { "best_effort" };
    let durability = if q.transient_local { "transient_local" } else { "volatile" };
    format!(
        "- history: keep_last\n  depth: {}\n  reliability: {reliability}\n  durability: {durability}\n  \
         deadline:{infinite}\n  lifespan:{infinite}\n  liveliness: automatic\n  \
         liveliness_lease_duration:{infinite}\n  avoid_ros_namespace_conventions: false\n",
        q.depth
    )
}

/// `text` with every line indented by `n` spaces.
fn indent(text: &str, n: usize) -> String {
    let pad = " ".repeat(n);
    text.lines().map(|l| format!("{pad}{l}\n")).collect()
}

/// A single-quoted YAML scalar (quotes doubled inside).
fn yaml_quote(s: &str) -> String {
    format!("'{}'", s.replace('\'', "''"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::{Clock, Time, Twist};

    fn temp_dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("formation-ros2-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    #[test]
    fn a_bag_folder_holds_the_mcap_and_metadata_yaml() {
        let dir = temp_dir("bag").join("run_bag");
        let mut bag = BagWriter::create(&dir).unwrap();
        let clock = bag.add_topic::<Clock>("/clock", Qos::best_effort(1)).unwrap();
        let cmd = bag.add_topic::<Twist>("/follower_1/cmd_vel", Qos::default()).unwrap();
        for i in 0..3u64 {
            let t = 1_000_000_000 + i * 10_000_000;
            bag.write(clock, t, &Clock { clock: Time::from_nanos(t as i64) }.encode()).unwrap();
        }
        bag.write(cmd, 1_005_000_000, &Twist::default().encode()).unwrap();
        let s = bag.finish().unwrap();
        assert_eq!((s.message_count, s.starting_time_ns, s.duration_ns), (4, 1_000_000_000, 20_000_000));
        assert_eq!(s.mcap_path, dir.join("run_bag_0.mcap"));
        let yaml = std::fs::read_to_string(&s.metadata_path).unwrap();
        assert!(yaml.starts_with("rosbag2_bagfile_information:\n  version: 9\n  storage_identifier: mcap\n"), "{yaml}");
        assert!(yaml.contains("\n  relative_file_paths:\n    - 'run_bag_0.mcap'\n"), "{yaml}");
        assert!(yaml.contains("      message_count: 3\n"), "{yaml}");
        assert!(yaml.contains(&format!("      type_description_hash: {}\n", Twist::HASH)), "{yaml}");
        let bytes = std::fs::read(&s.mcap_path).unwrap();
        assert_eq!(&bytes[..8], b"\x89MCAP0\r\n");
        let _ = std::fs::remove_dir_all(dir.parent().unwrap());
    }

    #[test]
    fn a_non_empty_folder_and_bad_input_are_refused() {
        let dir = temp_dir("refuse");
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("x"), b"x").unwrap();
        let err = BagWriter::create(&dir).err().unwrap();
        assert_eq!(err.kind(), io::ErrorKind::AlreadyExists, "{err}");
        assert!(err.to_string().contains("not empty"), "{err}");

        let mut bag = BagWriter::create(&dir.join("b")).unwrap();
        assert!(bag.add_topic::<Clock>("clock", Qos::default()).is_err());
        let id = bag.add_topic::<Clock>("/clock", Qos::default()).unwrap();
        assert!(bag.add_topic::<Clock>("/clock", Qos::default()).is_err());
        assert!(bag.write(id, 0, &[0, 0, 0, 0]).is_err(), "a big-endian payload is not written");
        assert!(bag.write(TopicId(5), 0, &Clock::default().encode()).is_err());
        let s = bag.finish().unwrap();
        assert_eq!(s.message_count, 0);
        let yaml = std::fs::read_to_string(&s.metadata_path).unwrap();
        assert!(yaml.contains("  topics_with_message_count:\n    - topic_metadata:"), "{yaml}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
