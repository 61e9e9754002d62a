//! rmw_zenoh's names on the Zenoh wire: the key expression a topic's data
//! travels on, and the liveliness tokens that make a node, a publisher or a
//! subscription appear in `ros2 node list` and `ros2 topic list`.
//!
//! The formats are those of rmw_zenoh's `liveliness_utils.cpp`
//! (`TopicInfo::TopicInfo`, `Entity::Entity`) and `qos.cpp`
//! (`qos_to_keyexpr`, the defaults), read for issue 32 at rmw_zenoh
//! commits 3411fde and 7efeee2; hiroz-protocol (0.2.0) writes the same strings.
//!
//! Every name is checked by ROS 2's rules for fully qualified names before
//! it goes into a key: a malformed one would be a key nobody matches, or a
//! token rmw_zenoh refuses ("invalid liveliness token with empty parts").

use crate::msgs::{dds_type_name, Message};
use thiserror::Error;

/// The liveliness key space rmw_zenoh's graph cache listens on.
pub const ADMIN_SPACE: &str = "@ros2_lv";

/// A name that ROS 2 (and so rmw_zenoh) would not accept.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
#[error("invalid {what} {name:?}: {why}")]
pub struct NameError {
    /// Which name: "topic", "namespace", "node name", …
    pub what: &'static str,
    pub name: String,
    pub why: &'static str,
}

fn invalid(what: &'static str, name: &str, why: &'static str) -> NameError {
    NameError { what, name: name.to_string(), why }
}

/// rmw_zenoh's `mangle_name`: every `/` becomes `%`, nothing else changes.
pub fn mangle(name: &str) -> String {
    name.replace('/', "%")
}

/// Checks the tokens of an absolute name (`/a/b_c`): letters, digits and
/// `_` only, none empty, none starting with a digit.
fn check_absolute(what: &'static str, name: &str) -> Result<(), NameError> {
    let Some(rest) = name.strip_prefix('/') else { return Err(invalid(what, name, "must start with '/'")) };
    if !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '/') {
        return Err(invalid(what, name, "may hold only letters, digits, '_' and '/'"));
    }
    for token in rest.split('/') {
        if token.is_empty() {
            return Err(invalid(what, name, "has an empty token ('//' or a trailing '/')"));
        }
        if token.starts_with(|c: char| c.is_ascii_digit()) {
            return Err(invalid(what, name, "has a token that starts with a digit"));
        }
    }
    Ok(())
}

/// A fully qualified topic name such as `/follower_1/odom`.
pub fn validate_topic(topic: &str) -> Result<(), NameError> {
    if topic == "/" {
        return Err(invalid("topic", topic, "names no topic"));
    }
    check_absolute("topic", topic)
}

/// A node namespace: `/`, empty (the same as `/`), or an absolute name
/// such as `/follower_1`.
pub fn validate_namespace(namespace: &str) -> Result<(), NameError> {
    match namespace {
        "" | "/" => Ok(()),
        _ => check_absolute("namespace", namespace),
    }
}

/// A node's base name such as `agent`: letters, digits and `_`, not
/// starting with a digit.
pub fn validate_node_name(node: &str) -> Result<(), NameError> {
    if node.is_empty() {
        return Err(invalid("node name", node, "is empty"));
    }
    if !node.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') {
        return Err(invalid("node name", node, "may hold only letters, digits and '_'"));
    }
    if node.starts_with(|c: char| c.is_ascii_digit()) {
        return Err(invalid("node name", node, "starts with a digit"));
    }
    Ok(())
}

/// A message type in the form `pkg/msg/Name`.
fn validate_type(type_: &str) -> Result<(), NameError> {
    let parts: Vec<&str> = type_.split('/').collect();
    let word = |s: &str| !s.is_empty() && s.chars().all(|c| c.is_ascii_alphanumeric() || c == '_');
    match parts.as_slice() {
        [pkg, "msg", name] if word(pkg) && word(name) => Ok(()),
        _ => Err(invalid("message type", type_, "is not of the form pkg/msg/Name")),
    }
}

/// A type hash: `RIHS01_` and 64 lowercase hex digits.
fn validate_hash(hash: &str) -> Result<(), NameError> {
    match hash.strip_prefix("RIHS01_") {
        Some(hex) if hex.len() == 64 && hex.chars().all(|c| matches!(c, '0'..='9' | 'a'..='f')) => Ok(()),
        _ => Err(invalid("type hash", hash, "is not RIHS01_ and 64 lowercase hex digits")),
    }
}

/// A Zenoh session id as `ZenohId`'s Display writes it (hex digits; any
/// letters and digits are accepted).
fn validate_zid(zid: &str) -> Result<(), NameError> {
    if zid.is_empty() || !zid.chars().all(|c| c.is_ascii_alphanumeric()) {
        return Err(invalid("zenoh id", zid, "is not a non-empty run of letters and digits"));
    }
    Ok(())
}

/// The key a topic's samples are put on:
/// `<domain>/<topic without its leading '/'>/<dds type>/<hash>`, e.g.
/// `0/follower_1/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_3cc9…`. Inner
/// slashes of the topic stay slashes here (they become `%` only in tokens).
/// `type_` is the ROS name, `"nav_msgs/msg/Odometry"`.
pub fn data_key(domain: u32, topic: &str, type_: &str, hash: &str) -> Result<String, NameError> {
    validate_topic(topic)?;
    validate_type(type_)?;
    validate_hash(hash)?;
    let stripped = topic.strip_prefix('/').unwrap_or(topic);
    let stripped = stripped.strip_suffix('/').unwrap_or(stripped);
    Ok(format!("{domain}/{stripped}/{}/{hash}", dds_type_name(type_)))
}

/// [`data_key`] for a [`Message`] type.
pub fn data_key_of<M: Message>(domain: u32, topic: &str) -> Result<String, NameError> {
    data_key(domain, topic, M::TYPE, M::HASH)
}

/// What a liveliness token announces (rmw_zenoh's `EntityType`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EntityKind {
    Node,
    Publisher,
    Subscription,
}

impl EntityKind {
    /// The token's kind field: `NN`, `MP` or `MS`.
    pub fn code(self) -> &'static str {
        match self {
            EntityKind::Node => "NN",
            EntityKind::Publisher => "MP",
            EntityKind::Subscription => "MS",
        }
    }
}

/// The QoS the formation offers: reliability, durability and the depth of
/// a keep-last history. Deadline, lifespan and liveliness are always ROS's
/// defaults (infinite, automatic).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Qos {
    /// Reliable, or best effort.
    pub reliable: bool,
    /// Transient local (late joiners get the last samples), or volatile.
    /// rmw_zenoh serves transient local through zenoh-ext's advanced
    /// publisher, which a plain `put` does not provide: keep it false on
    /// the wire.
    pub transient_local: bool,
    /// Keep-last depth.
    pub depth: u32,
}

impl Default for Qos {
    /// ROS 2's default profile: reliable, volatile, keep last 10.
    fn default() -> Self {
        Self { reliable: true, transient_local: false, depth: 10 }
    }
}

impl Qos {
    /// Best effort, volatile, keep last `depth`: the usual sensor and
    /// `/clock` profile.
    pub fn best_effort(depth: u32) -> Self {
        Self { reliable: false, transient_local: false, depth }
    }

    /// rmw_zenoh's `qos_to_keyexpr`:
    /// `<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:<liveliness>,<lease s>,<ns>`,
    /// each field empty when it equals rmw_zenoh's default (reliable,
    /// volatile, keep last, depth 42, infinite times, automatic). Enum
    /// values are rmw's: best effort 2, transient local 1.
    pub fn qos_key(&self) -> String {
        let reliability = if self.reliable { "" } else { "2" };
        let durability = if self.transient_local { "1" } else { "" };
        let depth = if self.depth == 42 { String::new() } else { self.depth.to_string() };
        format!("{reliability}:{durability}:,{depth}:,:,:,,")
    }
}

/// The namespace as it appears in a token: `%` for the root namespace
/// (empty or `/`), otherwise mangled (`/follower_1` → `%follower_1`).
fn mangled_namespace(namespace: &str) -> String {
    if namespace.is_empty() {
        "%".to_string()
    } else {
        mangle(namespace)
    }
}

/// The node part shared by every token:
/// `@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<kind>/<enclave>/<namespace>/<node>`.
fn entity_prefix(
    domain: u32,
    zid: &str,
    (node_id, entity_id, kind): (u32, u32, EntityKind),
    enclave: &str,
    namespace: &str,
    node: &str,
) -> Result<String, NameError> {
    validate_zid(zid)?;
    validate_namespace(enclave).map_err(|e| NameError { what: "enclave", ..e })?;
    validate_namespace(namespace)?;
    validate_node_name(node)?;
    let (enclave, namespace, kind) = (mangled_namespace(enclave), mangled_namespace(namespace), kind.code());
    Ok(format!("{ADMIN_SPACE}/{domain}/{zid}/{node_id}/{entity_id}/{kind}/{enclave}/{namespace}/{node}"))
}

/// A node's liveliness token, e.g. `@ros2_lv/0/<zid>/0/0/NN/%/%follower_1/agent`
/// (the node id fills both id fields). `enclave` is `/` unless ROS security
/// enclaves are in use.
pub fn node_token(
    domain: u32,
    zid: &str,
    node_id: u32,
    enclave: &str,
    namespace: &str,
    node: &str,
) -> Result<String, NameError> {
    entity_prefix(domain, zid, (node_id, node_id, EntityKind::Node), enclave, namespace, node)
}

/// A publisher's or subscription's liveliness token: the node's nine
/// parts (with this entity's id and kind), then the mangled topic, the DDS
/// type, the hash and the QoS, e.g.
/// `@ros2_lv/0/<zid>/0/1/MP/%/%follower_1/agent/%follower_1%odom/nav_msgs::msg::dds_::Odometry_/RIHS01_3cc9…/::,10:,:,:,,`.
/// `kind` must be [`EntityKind::Publisher`] or [`EntityKind::Subscription`].
#[allow(clippy::too_many_arguments)] // rmw_zenoh's 13 token parts, in their order
pub fn endpoint_token(
    domain: u32,
    zid: &str,
    node_id: u32,
    entity_id: u32,
    kind: EntityKind,
    enclave: &str,
    namespace: &str,
    node: &str,
    topic: &str,
    type_: &str,
    hash: &str,
    qos: Qos,
) -> Result<String, NameError> {
    if kind == EntityKind::Node {
        return Err(invalid("entity kind", kind.code(), "an endpoint token is MP or MS; use node_token"));
    }
    validate_topic(topic)?;
    validate_type(type_)?;
    validate_hash(hash)?;
    let prefix = entity_prefix(domain, zid, (node_id, entity_id, kind), enclave, namespace, node)?;
    let (topic, type_, qos) = (mangle(topic), mangle(&dds_type_name(type_)), qos.qos_key());
    Ok(format!("{prefix}/{topic}/{type_}/{hash}/{qos}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::{Clock, Odometry, Twist};

    const ODOM_HASH: &str = "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0";

    /// The data keys of the formation's topics, as issue 32's research wrote
    /// them out from rmw_zenoh's `TopicInfo`.
    #[test]
    fn data_keys_of_the_formations_topics() {
        assert_eq!(
            data_key_of::<Odometry>(0, "/follower_1/odom").unwrap(),
            format!("0/follower_1/odom/nav_msgs::msg::dds_::Odometry_/{ODOM_HASH}")
        );
        assert_eq!(
            data_key_of::<Twist>(0, "/follower_1/cmd_vel").unwrap(),
            "0/follower_1/cmd_vel/geometry_msgs::msg::dds_::Twist_/\
             RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"
        );
        assert_eq!(
            data_key(7, "/clock", "rosgraph_msgs/msg/Clock", Clock::HASH).unwrap(),
            "7/clock/rosgraph_msgs::msg::dds_::Clock_/\
             RIHS01_692f7a66e93a3c83e71765d033b60349ba68023a8c689a79e48078bcb5c58564"
        );
    }

    /// rmw_zenoh's `qos_to_keyexpr`: reliable volatile depth 10, and /clock's best
    /// effort depth 1.
    #[test]
    fn qos_keys_leave_rmw_zenoh_defaults_empty() {
        assert_eq!(Qos::default().qos_key(), "::,10:,:,:,,");
        assert_eq!(Qos::best_effort(1).qos_key(), "2::,1:,:,:,,");
        assert_eq!(Qos { reliable: true, transient_local: false, depth: 42 }.qos_key(), "::,:,:,:,,");
        assert_eq!(Qos { reliable: true, transient_local: true, depth: 1 }.qos_key(), ":1:,1:,:,:,,");
    }

    /// The node and publisher tokens of follower 1, as issue 32's research
    /// wrote them out from rmw_zenoh's `Entity::Entity`.
    #[test]
    fn tokens_of_follower_1() {
        let zid = "a1b2c3";
        assert_eq!(
            node_token(0, zid, 0, "/", "/follower_1", "agent").unwrap(),
            "@ros2_lv/0/a1b2c3/0/0/NN/%/%follower_1/agent"
        );
        let mp = endpoint_token(
            0,
            zid,
            0,
            1,
            EntityKind::Publisher,
            "/",
            "/follower_1",
            "agent",
            "/follower_1/odom",
            Odometry::TYPE,
            Odometry::HASH,
            Qos::default(),
        );
        assert_eq!(
            mp.unwrap(),
            format!("@ros2_lv/0/a1b2c3/0/1/MP/%/%follower_1/agent/%follower_1%odom/nav_msgs::msg::dds_::Odometry_/{ODOM_HASH}/::,10:,:,:,,")
        );
        let ms = endpoint_token(
            0,
            zid,
            0,
            2,
            EntityKind::Subscription,
            "/",
            "",
            "agent",
            "/cmd_vel",
            Twist::TYPE,
            Twist::HASH,
            Qos::best_effort(1),
        );
        let ms = ms.unwrap();
        assert!(
            ms.starts_with("@ros2_lv/0/a1b2c3/0/2/MS/%/%/agent/%cmd_vel/geometry_msgs::msg::dds_::Twist_/"),
            "{ms}"
        );
        assert!(ms.ends_with("/2::,1:,:,:,,"), "{ms}");
        assert_eq!(ms.split('/').count(), 13, "{ms}");
    }

    #[test]
    fn malformed_names_are_refused_with_the_reason() {
        let bad_topics = ["odom", "/", "/a//b", "/a/", "/1odom", "/od om", "/odöm", ""];
        for t in bad_topics {
            let err = data_key(0, t, Odometry::TYPE, Odometry::HASH).unwrap_err();
            assert_eq!(err.what, "topic", "{t:?}: {err}");
        }
        assert_eq!(validate_namespace("follower_1").unwrap_err().why, "must start with '/'");
        assert!(validate_node_name("my/agent").is_err());
        assert!(validate_node_name("").is_err());
        assert!(data_key(0, "/odom", "nav_msgs/Odometry", Odometry::HASH).is_err());
        assert!(data_key(0, "/odom", Odometry::TYPE, "RIHS01_3CC9").is_err());
        assert!(node_token(0, "", 0, "/", "/", "agent").is_err());
        assert!(node_token(0, "ab/cd", 0, "/", "/", "agent").is_err());
        let node_as_endpoint = endpoint_token(
            0,
            "ab",
            0,
            0,
            EntityKind::Node,
            "/",
            "/",
            "a",
            "/t",
            Twist::TYPE,
            Twist::HASH,
            Qos::default(),
        );
        assert!(node_as_endpoint.is_err());
        let msg = validate_topic("/a b").unwrap_err().to_string();
        assert_eq!(msg, "invalid topic \"/a b\": may hold only letters, digits, '_' and '/'");
    }

    #[test]
    fn mangling_and_dds_names() {
        assert_eq!(mangle("/follower_1/odom"), "%follower_1%odom");
        assert_eq!(dds_type_name("nav_msgs/msg/Odometry"), "nav_msgs::msg::dds_::Odometry_");
        assert_eq!(dds_type_name("tf2_msgs/msg/TFMessage"), "tf2_msgs::msg::dds_::TFMessage_");
    }
}
