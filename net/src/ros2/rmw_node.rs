//! A ROS 2 node on a zenoh session as rmw_zenoh makes one: a liveliness
//! token for the node and one per publisher and subscription (what `ros2
//! node list` and `ros2 topic list` read), samples on
//! `<domain>/<topic>/<type>/<hash>` with their CDR payload and the 33-byte
//! attachment (sequence number, source time, publisher GID) without which
//! rmw_zenoh drops a sample.

use std::marker::PhantomData;
use std::sync::atomic::{AtomicU32, Ordering};

use formation_ros2::attachment::{self, Attachment};
use formation_ros2::msgs::Message;
use formation_ros2::rmw_keys::{self, EntityKind, Qos};
use formation_ros2::DecodeError;
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::{Publisher, Subscriber};
use zenoh::qos::CongestionControl;
use zenoh::Wait;

use formation_exit::{zerr, Error};

/// Node and entity ids, unique in this process (its zenoh session id
/// tells processes apart), as rmw_zenoh's context counts them.
static NEXT_ID: AtomicU32 = AtomicU32::new(0);

fn next_id() -> u32 {
    NEXT_ID.fetch_add(1, Ordering::Relaxed)
}

/// The enclave every formation node is in (ROS 2's default).
const ENCLAVE: &str = "/";

/// One ROS 2 node: its name, namespace and liveliness token.
pub struct RosNode {
    session: zenoh::Session,
    domain: u32,
    zid: String,
    namespace: String,
    name: String,
    id: u32,
    _token: LivelinessToken,
}

impl RosNode {
    /// Declares node `name` in `namespace` (`/follower_1`) of ROS domain `domain`.
    pub async fn declare(session: &zenoh::Session, domain: u32, namespace: &str, name: &str) -> Result<Self, Error> {
        let zid = session.zid().to_string();
        let id = next_id();
        let key = rmw_keys::node_token(domain, &zid, id, ENCLAVE, namespace, name)
            .map_err(|e| Error::Input(e.to_string()))?;
        let token = session
            .liveliness()
            .declare_token(key)
            .await
            .map_err(|e| zerr("declaring the ROS 2 node's liveliness token", e))?;
        Ok(Self {
            session: session.clone(),
            domain,
            zid,
            namespace: namespace.to_string(),
            name: name.to_string(),
            id,
            _token: token,
        })
    }

    /// `topic` as ROS resolves it in this node: absolute as given, or
    /// relative to the namespace.
    pub fn resolve(&self, topic: &str) -> String {
        if topic.starts_with('/') {
            topic.to_string()
        } else {
            format!("{}/{topic}", self.namespace.trim_end_matches('/'))
        }
    }

    /// One endpoint of `M` on `topic` (resolved): its liveliness token,
    /// declared, with the token's key (a publisher's GID is made from it),
    /// and the data key its samples travel on.
    async fn endpoint<M: Message>(
        &self,
        kind: EntityKind,
        topic: &str,
        qos: Qos,
    ) -> Result<(LivelinessToken, String, String), Error> {
        let bad = |e: formation_ros2::rmw_keys::NameError| Error::Input(e.to_string());
        let token_key = rmw_keys::endpoint_token(
            self.domain,
            &self.zid,
            self.id,
            next_id(),
            kind,
            ENCLAVE,
            &self.namespace,
            &self.name,
            topic,
            M::TYPE,
            M::HASH,
            qos,
        )
        .map_err(bad)?;
        let token = self
            .session
            .liveliness()
            .declare_token(token_key.clone())
            .await
            .map_err(|e| zerr(&format!("declaring the liveliness token of {topic}"), e))?;
        let data_key = rmw_keys::data_key_of::<M>(self.domain, topic).map_err(bad)?;
        Ok((token, token_key, data_key))
    }

    /// A publisher of `M` on `topic`. `congestion`: `Drop` for a loop that
    /// must meet its period, `Block` in lock-step. `qos` is what the
    /// liveliness token announces (zenoh's link is reliable either way).
    pub async fn publisher<M: Message>(
        &self,
        topic: &str,
        qos: Qos,
        congestion: CongestionControl,
    ) -> Result<RosPublisher<M>, Error> {
        let topic = self.resolve(topic);
        let (token, token_key, key) = self.endpoint::<M>(EntityKind::Publisher, &topic, qos).await?;
        let publisher = self
            .session
            .declare_publisher(key)
            .congestion_control(congestion)
            .await
            .map_err(|e| zerr("declaring a ROS 2 publisher", e))?;
        Ok(RosPublisher {
            publisher,
            sequence: 1,
            gid: attachment::gid_of(&token_key),
            topic,
            _token: token,
            _m: PhantomData,
        })
    }

    /// A subscription to `M` on `topic`: `on_sample` gets each sample
    /// decoded (or why it could not be), with its attachment if it has a
    /// valid one.
    pub async fn subscribe<M, F>(&self, topic: &str, qos: Qos, on_sample: F) -> Result<RosSubscription, Error>
    where
        M: Message + Send + 'static,
        F: Fn(Result<M, DecodeError>, Option<Attachment>) + Send + Sync + 'static,
    {
        let topic = self.resolve(topic);
        let (token, _, key) = self.endpoint::<M>(EntityKind::Subscription, &topic, qos).await?;
        let subscriber = self
            .session
            .declare_subscriber(key)
            .callback(move |sample| {
                let attachment = sample.attachment().and_then(|a| attachment::decode(&a.to_bytes()).ok());
                on_sample(M::decode(&sample.payload().to_bytes()), attachment);
            })
            .await
            .map_err(|e| zerr("declaring a ROS 2 subscription", e))?;
        Ok(RosSubscription { _subscriber: subscriber, _token: token })
    }
}

/// A publisher of one message type on one topic, numbering its samples from 1.
pub struct RosPublisher<M> {
    publisher: Publisher<'static>,
    sequence: i64,
    gid: [u8; 16],
    topic: String,
    _token: LivelinessToken,
    _m: PhantomData<fn(&M)>,
}

impl<M: Message> RosPublisher<M> {
    /// Puts `msg` with its attachment; `source_ns` is the attachment's
    /// source time (ns; the step's stamp).
    pub fn put(&mut self, msg: &M, source_ns: i64) -> Result<(), Error> {
        self.put_encoded(msg.encode(), source_ns)
    }

    /// Puts a payload `M::encode` made (the same bytes again, for a repeat).
    pub fn put_encoded(&mut self, payload: Vec<u8>, source_ns: i64) -> Result<(), Error> {
        let att = attachment::encode(self.sequence, source_ns, self.gid);
        self.sequence += 1;
        self.publisher
            .put(payload)
            .attachment(att.to_vec())
            .wait()
            .map_err(|e| zerr(&format!("publishing {}", self.topic), e))
    }

    /// The topic, resolved.
    pub fn topic(&self) -> &str {
        &self.topic
    }
}

/// A subscription and its liveliness token (both undeclared on drop).
pub struct RosSubscription {
    _subscriber: Subscriber<()>,
    _token: LivelinessToken,
}
