//! The ROS 2 message types the formation speaks, as plain structs, with
//! their CDR encoding, their RIHS01 type hash and their `.msg` definition.
//!
//! The definitions are the ROS 2 Jazzy `.msg` files with the comments
//! left out (the field lines, including Quaternion's default values, are
//! the originals). [`Message::DEFINITION`] concatenates a type's text with
//! that of every type it uses, in the order of rosbags' `generate_msgdef`
//! (depth first, each type once), each after a line of 80 `=` and a line
//! `MSG: pkg/msg/Name`, as rosbag2's `ros2msg` schema encoding asks.
//! `type_hash`'s test recomputes every [`Message::HASH`] from these texts.

use crate::cdr::{DecodeError, Reader, Writer};

/// A ROS 2 message type: its names, hash and definition, and its CDR body.
pub trait Message: Sized {
    /// The ROS type name, e.g. `"nav_msgs/msg/Odometry"`.
    const TYPE: &'static str;
    /// The REP 2011 type hash, `"RIHS01_"` and 64 lowercase hex digits.
    const HASH: &'static str;
    /// The MCAP `ros2msg` schema text: this type's `.msg` text, then for
    /// each dependency `"=" * 80 + "\nMSG: pkg/msg/Name\n"` and its text.
    const DEFINITION: &'static str;

    /// Appends the fields, without the encapsulation header.
    fn encode_into(&self, w: &mut Writer);
    /// Reads the fields that [`Message::encode_into`] writes.
    fn decode_from(r: &mut Reader) -> Result<Self, DecodeError>;

    /// A whole payload, encapsulation header included, as rmw_zenoh sends it.
    fn encode(&self) -> Vec<u8> {
        let mut w = Writer::new();
        self.encode_into(&mut w);
        w.into_bytes()
    }

    /// Reads a whole payload: header, fields, and at most 3 bytes of padding.
    fn decode(bytes: &[u8]) -> Result<Self, DecodeError> {
        let mut r = Reader::new(bytes)?;
        let m = Self::decode_from(&mut r)?;
        r.finish()?;
        Ok(m)
    }
}

/// The DDS type name rmw_zenoh puts in keys and tokens
/// (`message_type_support.cpp`, `_create_type_name`):
/// `"nav_msgs/msg/Odometry"` becomes `"nav_msgs::msg::dds_::Odometry_"`.
pub fn dds_type_name(type_: &str) -> String {
    match type_.rsplit_once('/') {
        Some((namespace, name)) => format!("{}::dds_::{name}_", namespace.replace('/', "::")),
        None => format!("dds_::{type_}_"),
    }
}

/// builtin_interfaces/Time: seconds and nanoseconds since the Unix epoch
/// (or since the simulation's start on `/clock`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

impl Time {
    /// The time `ns` nanoseconds after the epoch. ROS time cannot be
    /// negative (rclcpp refuses it), so a negative `ns` gives 0; past
    /// `i32::MAX` seconds (the year 2038) it saturates at the last
    /// representable nanosecond.
    pub fn from_nanos(ns: i64) -> Self {
        let ns = ns.max(0);
        match i32::try_from(ns / 1_000_000_000) {
            Ok(sec) => Self { sec, nanosec: (ns % 1_000_000_000) as u32 },
            Err(_) => Self { sec: i32::MAX, nanosec: 999_999_999 },
        }
    }

    /// Nanoseconds since the epoch (exact for every `Time`, even one
    /// decoded with a negative `sec` or a `nanosec` above 10⁹).
    pub fn as_nanos(&self) -> i64 {
        i64::from(self.sec) * 1_000_000_000 + i64::from(self.nanosec)
    }
}

/// std_msgs/Header: when and in which frame.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

/// geometry_msgs/Vector3: a free vector.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct Vector3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

/// geometry_msgs/Point: a position.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct Point {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

/// geometry_msgs/Quaternion: an orientation. The default is the identity
/// (0, 0, 0, 1), as the `.msg` file's default values say.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Quaternion {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub w: f64,
}

impl Default for Quaternion {
    fn default() -> Self {
        Self { x: 0.0, y: 0.0, z: 0.0, w: 1.0 }
    }
}

impl Quaternion {
    /// The rotation by `theta` radians about z: (0, 0, sin θ/2, cos θ/2).
    pub fn from_yaw(theta: f64) -> Self {
        let (s, c) = (theta * 0.5).sin_cos();
        Self { x: 0.0, y: 0.0, z: s, w: c }
    }

    /// The heading about z, in radians. For a pure-yaw quaternion (x and y
    /// exactly 0, as [`Quaternion::from_yaw`] makes) it is exactly
    /// `2 atan2(z, w)`, so a simulator that stores θ this way reads back
    /// the same bits; its range is (−2π, 2π] when w may be negative, and
    /// [−π, π] for what `from_yaw` gives from θ in [−π, π]. Otherwise it is
    /// the Z-Y-X yaw `atan2(2(wz + xy), 1 − 2(y² + z²))`, in [−π, π].
    pub fn yaw(&self) -> f64 {
        if self.x == 0.0 && self.y == 0.0 {
            2.0 * self.z.atan2(self.w)
        } else {
            (2.0 * (self.w * self.z + self.x * self.y)).atan2(1.0 - 2.0 * (self.y * self.y + self.z * self.z))
        }
    }
}

/// geometry_msgs/Pose: a position and an orientation.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct Pose {
    pub position: Point,
    pub orientation: Quaternion,
}

/// geometry_msgs/Twist: linear and angular velocity.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct Twist {
    pub linear: Vector3,
    pub angular: Vector3,
}

/// geometry_msgs/PoseWithCovariance: a pose and its 6×6 row-major
/// covariance (x, y, z, rotation about x, y, z).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseWithCovariance {
    pub pose: Pose,
    pub covariance: [f64; 36],
}

impl Default for PoseWithCovariance {
    fn default() -> Self {
        Self { pose: Pose::default(), covariance: [0.0; 36] }
    }
}

/// geometry_msgs/TwistWithCovariance: a twist and its 6×6 covariance.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TwistWithCovariance {
    pub twist: Twist,
    pub covariance: [f64; 36],
}

impl Default for TwistWithCovariance {
    fn default() -> Self {
        Self { twist: Twist::default(), covariance: [0.0; 36] }
    }
}

/// geometry_msgs/PoseStamped: a pose in a frame at a time.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct PoseStamped {
    pub header: Header,
    pub pose: Pose,
}

/// geometry_msgs/Transform: a translation and a rotation.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct Transform {
    pub translation: Vector3,
    pub rotation: Quaternion,
}

/// geometry_msgs/TransformStamped: the transform from `header.frame_id`
/// to `child_frame_id`.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct TransformStamped {
    pub header: Header,
    pub child_frame_id: String,
    pub transform: Transform,
}

/// nav_msgs/Odometry: pose in `header.frame_id`, twist in `child_frame_id`.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct Odometry {
    pub header: Header,
    pub child_frame_id: String,
    pub pose: PoseWithCovariance,
    pub twist: TwistWithCovariance,
}

/// nav_msgs/Path: poses to follow, in `header.frame_id` (a planner's
/// answer, as Nav2 publishes it on `plan`).
#[derive(Clone, Debug, PartialEq, Default)]
pub struct Path {
    pub header: Header,
    pub poses: Vec<PoseStamped>,
}

/// tf2_msgs/TFMessage: the frames published on `/tf`.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct TFMessage {
    pub transforms: Vec<TransformStamped>,
}

/// rosgraph_msgs/Clock: the simulated time, published on `/clock`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct Clock {
    pub clock: Time,
}

/// A field's CDR form: primitives, strings, the covariance arrays, nested
/// messages and sequences of them.
trait Field: Sized {
    fn put(&self, w: &mut Writer);
    fn get(r: &mut Reader) -> Result<Self, DecodeError>;
}

impl Field for i32 {
    fn put(&self, w: &mut Writer) {
        w.i32(*self)
    }
    fn get(r: &mut Reader) -> Result<Self, DecodeError> {
        r.i32()
    }
}

impl Field for u32 {
    fn put(&self, w: &mut Writer) {
        w.u32(*self)
    }
    fn get(r: &mut Reader) -> Result<Self, DecodeError> {
        r.u32()
    }
}

impl Field for f64 {
    fn put(&self, w: &mut Writer) {
        w.f64(*self)
    }
    fn get(r: &mut Reader) -> Result<Self, DecodeError> {
        r.f64()
    }
}

impl Field for String {
    fn put(&self, w: &mut Writer) {
        w.string(self)
    }
    fn get(r: &mut Reader) -> Result<Self, DecodeError> {
        r.string()
    }
}

impl Field for [f64; 36] {
    fn put(&self, w: &mut Writer) {
        w.f64_array(self)
    }
    fn get(r: &mut Reader) -> Result<Self, DecodeError> {
        r.f64_array()
    }
}

impl<T: Field> Field for Vec<T> {
    fn put(&self, w: &mut Writer) {
        w.sequence_len(self.len());
        self.iter().for_each(|x| x.put(w));
    }
    /// Grows as elements decode (no capacity from the untrusted count).
    fn get(r: &mut Reader) -> Result<Self, DecodeError> {
        let n = r.sequence_len()?;
        (0..n).map(|_| T::get(r)).collect()
    }
}

/// Each type's `.msg` text (Jazzy, comments left out).
#[rustfmt::skip]
macro_rules! text {
    (Time) => { "int32 sec\nuint32 nanosec\n" };
    (Header) => { "builtin_interfaces/Time stamp\nstring frame_id\n" };
    (Vector3) => { "float64 x\nfloat64 y\nfloat64 z\n" };
    (Point) => { "float64 x\nfloat64 y\nfloat64 z\n" };
    (Quaternion) => { "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n" };
    (Pose) => { "Point position\nQuaternion orientation\n" };
    (Twist) => { "Vector3  linear\nVector3  angular\n" };
    (PoseWithCovariance) => { "Pose pose\nfloat64[36] covariance\n" };
    (TwistWithCovariance) => { "Twist twist\nfloat64[36] covariance\n" };
    (PoseStamped) => { "std_msgs/Header header\nPose pose\n" };
    (Transform) => { "Vector3 translation\nQuaternion rotation\n" };
    (TransformStamped) => { "std_msgs/Header header\nstring child_frame_id\nTransform transform\n" };
    (Odometry) => {
        "std_msgs/Header header\nstring child_frame_id\n\
         geometry_msgs/PoseWithCovariance pose\ngeometry_msgs/TwistWithCovariance twist\n"
    };
    (TFMessage) => { "geometry_msgs/TransformStamped[] transforms\n" };
    (Path) => { "std_msgs/Header header\ngeometry_msgs/PoseStamped[] poses\n" };
    (Clock) => { "builtin_interfaces/Time clock\n" };
}

/// Each type's full ROS name.
#[rustfmt::skip]
macro_rules! name {
    (Time) => { "builtin_interfaces/msg/Time" };
    (Header) => { "std_msgs/msg/Header" };
    (Odometry) => { "nav_msgs/msg/Odometry" };
    (Path) => { "nav_msgs/msg/Path" };
    (TFMessage) => { "tf2_msgs/msg/TFMessage" };
    (Clock) => { "rosgraph_msgs/msg/Clock" };
    ($geometry:ident) => { concat!("geometry_msgs/msg/", stringify!($geometry)) };
}

/// Implements [`Message`] (and [`Field`]) for a struct: its hash, its
/// dependencies in definition order, and its fields in wire order.
macro_rules! message {
    ($ty:ident, $hash:literal, [$($dep:ident),*], {$($field:ident),*}) => {
        impl Message for $ty {
            const TYPE: &'static str = name!($ty);
            const HASH: &'static str = $hash;
            const DEFINITION: &'static str = concat!(
                text!($ty)
                $(, "================================================================================\nMSG: ", name!($dep), "\n", text!($dep))*
            );
            fn encode_into(&self, w: &mut Writer) {
                $(Field::put(&self.$field, w);)*
            }
            fn decode_from(r: &mut Reader) -> Result<Self, DecodeError> {
                Ok(Self { $($field: Field::get(r)?),* })
            }
        }

        impl Field for $ty {
            fn put(&self, w: &mut Writer) {
                self.encode_into(w)
            }
            fn get(r: &mut Reader) -> Result<Self, DecodeError> {
                Self::decode_from(r)
            }
        }
    };
}

// Hashes: rosbags 0.11.9's `hash_rihs01` on its Jazzy store, recomputed
// from `DEFINITION` by `type_hash`'s test; Twist, Odometry and PoseStamped
// are also the values given in issue 32.
message!(Time, "RIHS01_b106235e25a4c5ed35098aa0a61a3ee9c9b18d197f398b0e4206cea9acf9c197", [], {sec, nanosec});
message!(Header, "RIHS01_f49fb3ae2cf070f793645ff749683ac6b06203e41c891e17701b1cb597ce6a01", [Time], {stamp, frame_id});
message!(Vector3, "RIHS01_cc12fe83e4c02719f1ce8070bfd14aecd40f75a96696a67a2a1f37f7dbb0765d", [], {x, y, z});
message!(Point, "RIHS01_6963084842a9b04494d6b2941d11444708d892da2f4b09843b9c43f42a7f6881", [], {x, y, z});
message!(Quaternion, "RIHS01_8a765f66778c8ff7c8ab94afcc590a2ed5325a1d9a076ffff38fbce36f458684", [], {x, y, z, w});
message!(
    Pose,
    "RIHS01_d501954e9476cea2996984e812054b68026ae0bfae789d9a10b23daf35cc90fa",
    [Point, Quaternion],
    {position, orientation}
);
message!(Twist, "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a", [Vector3], {linear, angular});
message!(
    PoseWithCovariance,
    "RIHS01_9a7c0fd234b7f45c6098745ecccd773ca1085670e64107135397aee31c02e1bb",
    [Pose, Point, Quaternion],
    {pose, covariance}
);
message!(
    TwistWithCovariance,
    "RIHS01_49f574f033f095d8b6cd1beaca5ca7925e296e84af1716d16c89d38b059c8c18",
    [Twist, Vector3],
    {twist, covariance}
);
message!(
    PoseStamped,
    "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8",
    [Header, Time, Pose, Point, Quaternion],
    {header, pose}
);
message!(
    Transform,
    "RIHS01_beb83fbe698636351461f6f35d1abb20010c43d55374d81bd041f1ba2581fddc",
    [Vector3, Quaternion],
    {translation, rotation}
);
message!(
    TransformStamped,
    "RIHS01_0a241f87d04668d94099cbb5ba11691d5ad32c2f29682e4eb5653424bd275206",
    [Header, Time, Transform, Vector3, Quaternion],
    {header, child_frame_id, transform}
);
message!(
    Odometry,
    "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
    [Header, Time, PoseWithCovariance, Pose, Point, Quaternion, TwistWithCovariance, Twist, Vector3],
    {header, child_frame_id, pose, twist}
);
message!(
    TFMessage,
    "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
    [TransformStamped, Header, Time, Transform, Vector3, Quaternion],
    { transforms }
);
message!(
    Path,
    "RIHS01_1957a5bb3cee5da65c4e52e52b65a93df227efce4c20f8458b36e73066ca334b",
    [Header, Time, PoseStamped, Pose, Point, Quaternion],
    {header, poses}
);
message!(Clock, "RIHS01_692f7a66e93a3c83e71765d033b60349ba68023a8c689a79e48078bcb5c58564", [Time], { clock });
