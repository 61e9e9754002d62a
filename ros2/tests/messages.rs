//! The CDR of every message type: golden sizes and bytes from the research
//! research for issue 32 (computed there with rosbags 0.11.9), round trips,
//! and refusals of
//! malformed payloads without a panic.

use formation_ros2::cdr::{Reader, ENCAPSULATION_LE};
use formation_ros2::msgs::*;
use formation_ros2::{DecodeError, Message};

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn header(sec: i32, nanosec: u32, frame: &str) -> Header {
    Header { stamp: Time { sec, nanosec }, frame_id: frame.to_string() }
}

/// Covariances whose every entry differs, so a misplaced one shows.
fn covariance(offset: f64) -> [f64; 36] {
    core::array::from_fn(|i| offset + i as f64 * 0.5)
}

fn odometry(frame: &str, child: &str) -> Odometry {
    Odometry {
        header: header(12, 345, frame),
        child_frame_id: child.to_string(),
        pose: PoseWithCovariance {
            pose: Pose { position: Point { x: 1.0, y: -2.0, z: 0.5 }, orientation: Quaternion::from_yaw(0.3) },
            covariance: covariance(100.0),
        },
        twist: TwistWithCovariance {
            twist: Twist { linear: Vector3 { x: 0.4, y: 0.0, z: 0.0 }, angular: Vector3 { x: 0.0, y: 0.0, z: -0.2 } },
            covariance: covariance(200.0),
        },
    }
}

fn pose_stamped() -> PoseStamped {
    PoseStamped {
        header: header(1, 2, "world"),
        pose: Pose {
            position: Point { x: 1.0, y: 2.0, z: 0.0 },
            orientation: Quaternion { x: 0.0, y: 0.0, z: 0.0, w: 1.0 },
        },
    }
}

fn transform(child: &str, x: f64) -> TransformStamped {
    TransformStamped {
        header: header(3, 4, "world"),
        child_frame_id: child.to_string(),
        transform: Transform { translation: Vector3 { x, y: 2.0 * x, z: 0.0 }, rotation: Quaternion::from_yaw(x) },
    }
}

fn tf() -> TFMessage {
    TFMessage { transforms: vec![transform("leader", 1.0), transform("follower_1", -1.5)] }
}

fn twist() -> Twist {
    Twist { linear: Vector3 { x: 0.5, y: 0.25, z: -1.0 }, angular: Vector3 { x: 3.0, y: -4.0, z: 1e-9 } }
}

/// Sizes with the 4-byte header (rosbags 0.11.9's `serialize_cdr`).
#[test]
fn golden_sizes() {
    let sizes = [
        ("Twist", twist().encode().len(), 52),
        ("Clock", Clock { clock: Time { sec: 5, nanosec: 6 } }.encode().len(), 12),
        ("PoseStamped 'world'", pose_stamped().encode().len(), 84),
        ("Odometry, empty strings", odometry("", "").encode().len(), 708),
        ("Odometry ('world', 'follower_1')", odometry("world", "follower_1").encode().len(), 724),
        ("Odometry ('odom', 'follower_1/base_link')", odometry("odom", "follower_1/base_link").encode().len(), 732),
    ];
    for (what, got, want) in sizes {
        assert_eq!(got, want, "{what}: {got} bytes, rosbags writes {want}");
    }
}

/// rosbags 0.11.9's bytes for PoseStamped{1 s 2 ns, "world", (1,2,0), (0,0,0,1)};
/// after "world\0" (body offset 18) six bytes pad to 24 before the doubles.
#[test]
fn golden_pose_stamped_bytes() {
    let bytes = pose_stamped().encode();
    let want_prefix = "00010000010000000200000006000000776f726c6400000000000000000000000000f03f";
    assert!(hex(&bytes).starts_with(want_prefix), "got {}", hex(&bytes));
    let mut tail = String::new();
    for v in [2.0f64, 0.0, 0.0, 0.0, 0.0, 1.0] {
        tail.push_str(&hex(&v.to_le_bytes()));
    }
    assert_eq!(&hex(&bytes)[want_prefix.len()..], tail);
}

#[test]
fn every_payload_starts_with_the_little_endian_header() {
    for bytes in [
        twist().encode(),
        Clock::default().encode(),
        pose_stamped().encode(),
        odometry("a", "b").encode(),
        tf().encode(),
    ] {
        assert_eq!(bytes[..4], ENCAPSULATION_LE);
    }
}

fn round_trip<M: Message + PartialEq + std::fmt::Debug>(m: M) {
    let bytes = m.encode();
    assert_eq!(M::decode(&bytes).as_ref(), Ok(&m), "{}", M::TYPE);
}

#[test]
fn round_trips_of_every_type() {
    round_trip(Time { sec: -3, nanosec: 999_999_999 });
    round_trip(header(7, 8, "frame/with/slashes"));
    round_trip(Vector3 { x: f64::MAX, y: f64::MIN_POSITIVE, z: -0.0 });
    round_trip(Point { x: 1.0, y: 2.0, z: 3.0 });
    round_trip(Quaternion::from_yaw(-2.0));
    round_trip(Pose::default());
    round_trip(twist());
    round_trip(odometry("world", "follower_1").pose);
    round_trip(odometry("world", "follower_1").twist);
    round_trip(pose_stamped());
    round_trip(transform("x", 0.7).transform);
    round_trip(transform("ünïcode", 0.7));
    round_trip(odometry("odom", "follower_1/base_link"));
    round_trip(odometry("", ""));
    round_trip(tf());
    round_trip(TFMessage::default());
    round_trip(Clock { clock: Time::from_nanos(1_700_000_000_123_456_789) });
}

/// Every strict prefix of a payload is refused with an error (no panic):
/// all but the shortest are cut inside a field.
fn refuses_every_prefix<M: Message + std::fmt::Debug>(bytes: &[u8]) {
    for len in 0..bytes.len() {
        let cut = &bytes[..len];
        match M::decode(cut) {
            Err(_) => {}
            Ok(m) => panic!("{}: a {len}-byte prefix of {} bytes decoded as {m:?}", M::TYPE, bytes.len()),
        }
    }
}

#[test]
fn truncated_payloads_are_refused_at_every_length() {
    refuses_every_prefix::<Twist>(&twist().encode());
    refuses_every_prefix::<Clock>(&Clock::default().encode());
    refuses_every_prefix::<PoseStamped>(&pose_stamped().encode());
    refuses_every_prefix::<Odometry>(&odometry("world", "follower_1").encode());
    refuses_every_prefix::<TFMessage>(&tf().encode());
    let err = Odometry::decode(&odometry("", "").encode()[..100]).unwrap_err();
    assert!(matches!(err, DecodeError::Truncated { .. }), "{err}");
    assert!(err.to_string().starts_with("truncated: float64 needs 8 bytes at offset"), "{err}");
}

#[test]
fn a_huge_string_length_is_refused() {
    let mut bytes = pose_stamped().encode();
    bytes[12..16].copy_from_slice(&0xffff_fff0u32.to_le_bytes()); // frame_id's length
    let err = PoseStamped::decode(&bytes).unwrap_err();
    assert_eq!(err, DecodeError::StringLength { offset: 16, len: 0xffff_fff0, left: 68 });
}

#[test]
fn a_huge_sequence_count_is_refused() {
    let mut bytes = tf().encode();
    bytes[4..8].copy_from_slice(&u32::MAX.to_le_bytes());
    let err = TFMessage::decode(&bytes).unwrap_err();
    assert!(matches!(err, DecodeError::SequenceLength { count: u32::MAX, .. }), "{err}");
}

#[test]
fn wrong_headers_are_refused() {
    let mut bytes = twist().encode();
    bytes[1] = 0x00;
    assert_eq!(Twist::decode(&bytes), Err(DecodeError::BigEndian));
    bytes[1] = 0x07; // XCDR2 little-endian
    assert_eq!(Twist::decode(&bytes), Err(DecodeError::Encapsulation(0, 7)));
    // A body without its header: linear.x's low bytes read as 00 00.
    assert_eq!(Twist::decode(&bytes[4..]).err(), Some(DecodeError::BigEndian));
    assert!(Reader::new(&[]).is_err());
}

#[test]
fn trailing_bytes_beyond_padding_are_refused() {
    let mut bytes = Clock::default().encode();
    bytes.extend_from_slice(&[0; 3]);
    assert!(Clock::decode(&bytes).is_ok(), "3 bytes of padding");
    bytes.push(0);
    assert_eq!(Clock::decode(&bytes), Err(DecodeError::TrailingBytes { extra: 4 }));
}

/// Arbitrary bytes never panic the reader (a cheap deterministic fuzz).
#[test]
fn arbitrary_bytes_never_panic() {
    let mut state = 0x2545_f491_4f6c_dd1du64;
    for _ in 0..20_000 {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        let len = (state % 200) as usize;
        let mut bytes: Vec<u8> = (0..len).map(|i| (state.rotate_left(i as u32 % 64) >> 3) as u8).collect();
        if len >= 4 {
            bytes[..4].copy_from_slice(&ENCAPSULATION_LE);
        }
        let _ = Odometry::decode(&bytes);
        let _ = TFMessage::decode(&bytes);
        let _ = PoseStamped::decode(&bytes);
    }
}

#[test]
fn time_from_and_to_nanoseconds() {
    assert_eq!(Time::from_nanos(1_500_000_002), Time { sec: 1, nanosec: 500_000_002 });
    assert_eq!(Time::from_nanos(1_500_000_002).as_nanos(), 1_500_000_002);
    assert_eq!(Time::from_nanos(-5), Time { sec: 0, nanosec: 0 }, "negative clamps to 0");
    assert_eq!(Time::from_nanos(i64::MAX), Time { sec: i32::MAX, nanosec: 999_999_999 }, "saturates after 2038");
    assert_eq!(Time { sec: -1, nanosec: 0 }.as_nanos(), -1_000_000_000);
}

/// The pure-yaw path is bit for bit `2 atan2(z, w)`; the general path is
/// the Z-Y-X yaw, equal to it (within rounding) on pure-yaw quaternions.
#[test]
fn yaw_round_trips() {
    for i in -314..=314 {
        let theta = i as f64 * 0.01;
        let q = Quaternion::from_yaw(theta);
        let (s, c) = (theta * 0.5).sin_cos();
        assert_eq!((q.x, q.y, q.z, q.w), (0.0, 0.0, s, c));
        assert_eq!(q.yaw().to_bits(), (2.0 * s.atan2(c)).to_bits());
        assert!((q.yaw() - theta).abs() < 1e-12, "θ {theta}: yaw {}", q.yaw());
    }
    // 90° about x, then 30° about z: the Z-Y-X yaw is 30°.
    let (sx, cx) = (std::f64::consts::FRAC_PI_4).sin_cos();
    let (sz, cz) = (15f64.to_radians()).sin_cos();
    let q = Quaternion { x: cz * sx, y: sz * sx, z: sz * cx, w: cz * cx };
    assert!((q.yaw() - 30f64.to_radians()).abs() < 1e-12, "yaw {}", q.yaw().to_degrees());
    assert_eq!(Quaternion::default(), Quaternion { x: 0.0, y: 0.0, z: 0.0, w: 1.0 });
}

#[test]
fn definitions_name_their_dependencies() {
    assert_eq!(
        Clock::DEFINITION,
        format!(
            "builtin_interfaces/Time clock\n{}\nMSG: builtin_interfaces/msg/Time\nint32 sec\nuint32 nanosec\n",
            "=".repeat(80)
        )
    );
    assert_eq!(Odometry::DEFINITION.matches("\nMSG: ").count(), 9);
    assert_eq!(TFMessage::DEFINITION.matches("\nMSG: ").count(), 6);
    assert_eq!(Time::DEFINITION, "int32 sec\nuint32 nanosec\n");
    assert_eq!(dds_type_name(Odometry::TYPE), "nav_msgs::msg::dds_::Odometry_");
}
