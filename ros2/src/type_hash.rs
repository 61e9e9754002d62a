//! REP 2011 type hashes (RIHS01), recomputed from the `.msg` definitions.
//!
//! Test only: at run time the hashes are the constants [`Message::HASH`].
//! This module parses each type's [`Message::DEFINITION`] into field
//! tables and hashes them by the rule of rosidl's
//! `rosidl_generator_type_description` (`calculate_type_hash`), which
//! rosbags' `hash_rihs01` also follows:
//!
//! 1. `{"type_description": T, "referenced_type_descriptions": [R…]}`, R
//!    being every type T uses, directly or not, sorted by name, each once;
//! 2. a type is `{"type_name": "pkg/msg/Name", "fields": [...]}`, a field
//!    `{"name": …, "type": {"type_id", "capacity", "string_capacity",
//!    "nested_type_name"}}` (default values are not hashed);
//! 3. type ids: 1 nested, 2–16 the primitives, 17 string; +48 for a fixed
//!    array (its size is the capacity), +144 for an unbounded sequence;
//! 4. Python's `json.dumps` with separators `", "` and `": "`, then
//!    `"RIHS01_"` + the SHA-256 in lowercase hex.
//!
//! So a definition and its hash cannot drift apart: a wrong field line
//! changes the recomputed hash.

use crate::msgs::*;
use sha2::{Digest, Sha256};
use std::collections::BTreeMap;

/// One field of a type description.
struct Field {
    name: String,
    type_id: u32,
    capacity: u64,
    nested: String,
}

/// The separator line between the definitions of a `ros2msg` schema.
const SEPARATOR: &str = "================================================================================";

/// rosidl's ids of the primitive `.msg` types.
fn primitive_id(t: &str) -> Option<u32> {
    Some(match t {
        "int8" => 2,
        "uint8" | "char" => 3,
        "int16" => 4,
        "uint16" => 5,
        "int32" => 6,
        "uint32" => 7,
        "int64" => 8,
        "uint64" => 9,
        "float32" => 10,
        "float64" => 11,
        "bool" => 15,
        "byte" => 16,
        "string" => 17,
        "wstring" => 18,
        _ => return None,
    })
}

/// Splits a schema into (type name, text) sections, the first being `top`.
fn sections(top: &str, definition: &str) -> Result<Vec<(String, String)>, String> {
    let mut out = vec![(top.to_string(), String::new())];
    let mut lines = definition.lines();
    while let Some(line) = lines.next() {
        if line == SEPARATOR {
            let header = lines.next().unwrap_or("");
            let name = header
                .strip_prefix("MSG: ")
                .ok_or(format!("{top}: expected 'MSG: <type>' after the separator, found {header:?}"))?;
            out.push((name.to_string(), String::new()));
        } else if let Some((_, text)) = out.last_mut() {
            text.push_str(line);
            text.push('\n');
        }
    }
    Ok(out)
}

/// The fields of one `.msg` text of package `pkg`: `type name [default]`
/// lines, `T[N]` arrays and `T[]` sequences; comments and blank lines skipped.
fn parse_fields(pkg: &str, text: &str) -> Result<Vec<Field>, String> {
    let mut fields = Vec::new();
    for line in text.lines() {
        let line = line.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let mut words = line.split_whitespace();
        let (Some(type_), Some(name)) = (words.next(), words.next()) else {
            return Err(format!("{pkg}: field line {line:?} has no name"));
        };
        if line.contains('=') || type_.contains("<=") {
            return Err(format!("{pkg}: constants and bounded types are not handled: {line:?}"));
        }
        let (base, suffix) = type_.split_once('[').map_or((type_, None), |(b, s)| (b, Some(s)));
        let (mut type_id, nested) = match primitive_id(base) {
            Some(id) => (id, String::new()),
            None => (1, nested_name(pkg, base)),
        };
        let capacity = match suffix {
            None => 0,
            Some("]") => {
                type_id += 144;
                0
            }
            Some(n) => {
                type_id += 48;
                n.trim_end_matches(']').parse().map_err(|_| format!("{pkg}: bad array size in {line:?}"))?
            }
        };
        fields.push(Field { name: name.to_string(), type_id, capacity, nested });
    }
    Ok(fields)
}

/// `pkg/Name` → `pkg/msg/Name`; a bare `Name` is in the same package.
fn nested_name(pkg: &str, t: &str) -> String {
    match t.split_once('/') {
        Some((p, name)) => format!("{p}/msg/{name}"),
        None => format!("{pkg}/msg/{t}"),
    }
}

fn type_json(name: &str, fields: &[Field]) -> String {
    let fields: Vec<String> = fields
        .iter()
        .map(|f| {
            format!(
                "{{\"name\": \"{}\", \"type\": {{\"type_id\": {}, \"capacity\": {}, \"string_capacity\": 0, \"nested_type_name\": \"{}\"}}}}",
                f.name, f.type_id, f.capacity, f.nested
            )
        })
        .collect();
    format!("{{\"type_name\": \"{name}\", \"fields\": [{}]}}", fields.join(", "))
}

/// The hashed JSON of type `top` from its schema text. Also checks that the
/// schema holds exactly the types `top` uses, in rosbags' depth-first order.
fn description_json(top: &str, definition: &str) -> Result<String, String> {
    let mut types = BTreeMap::new();
    let mut order = Vec::new();
    for (name, text) in sections(top, definition)? {
        let pkg = name.split('/').next().unwrap_or("").to_string();
        order.push(name.clone());
        if types.insert(name.clone(), parse_fields(&pkg, &text)?).is_some() {
            return Err(format!("{top}: {name} is defined twice"));
        }
    }
    let mut used = Vec::new();
    depth_first(top, &types, &mut used)?;
    if used != order {
        return Err(format!("{top}: the definition holds {order:?}, but the type uses {used:?} (in that order)"));
    }
    let refs: Vec<String> = types.iter().filter(|(n, _)| *n != top).map(|(n, f)| type_json(n, f)).collect();
    Ok(format!(
        "{{\"type_description\": {}, \"referenced_type_descriptions\": [{}]}}",
        type_json(top, &types[top]),
        refs.join(", ")
    ))
}

/// rosbags' `generate_msgdef` order: the type, then what each field uses.
fn depth_first(name: &str, types: &BTreeMap<String, Vec<Field>>, seen: &mut Vec<String>) -> Result<(), String> {
    if seen.iter().any(|s| s == name) {
        return Ok(());
    }
    seen.push(name.to_string());
    let fields = types.get(name).ok_or(format!("{name} is used but not defined"))?;
    for f in fields.iter().filter(|f| !f.nested.is_empty()) {
        depth_first(&f.nested, types, seen)?;
    }
    Ok(())
}

fn rihs01(json: &str) -> String {
    let digest = Sha256::digest(json.as_bytes());
    let hex: String = digest.iter().map(|b| format!("{b:02x}")).collect();
    format!("RIHS01_{hex}")
}

/// `None` when `M::HASH` is the hash of `M::DEFINITION`, else why not.
fn mismatch<M: Message>() -> Option<String> {
    match description_json(M::TYPE, M::DEFINITION) {
        Err(e) => Some(e),
        Ok(json) if rihs01(&json) == M::HASH => None,
        Ok(json) => {
            Some(format!("{}: recomputed {} but HASH is {}; hashed text:\n{json}", M::TYPE, rihs01(&json), M::HASH))
        }
    }
}

#[test]
fn every_hash_is_recomputed_from_its_definition() {
    let failures: Vec<String> = [
        mismatch::<Time>(),
        mismatch::<Header>(),
        mismatch::<Vector3>(),
        mismatch::<Point>(),
        mismatch::<Quaternion>(),
        mismatch::<Pose>(),
        mismatch::<Twist>(),
        mismatch::<PoseWithCovariance>(),
        mismatch::<TwistWithCovariance>(),
        mismatch::<PoseStamped>(),
        mismatch::<Transform>(),
        mismatch::<TransformStamped>(),
        mismatch::<Odometry>(),
        mismatch::<TFMessage>(),
        mismatch::<Path>(),
        mismatch::<Clock>(),
    ]
    .into_iter()
    .flatten()
    .collect();
    assert!(failures.is_empty(), "{}", failures.join("\n\n"));
}

/// The values given in issue 32 (Twist, Odometry, PoseStamped) and the
/// research for it (TFMessage, Clock, and for issue 67 Path: rosbags
/// 0.11.9's Jazzy store).
#[test]
fn the_constants_are_the_reference_values() {
    let reference = [
        (Twist::HASH, "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"),
        (Odometry::HASH, "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0"),
        (PoseStamped::HASH, "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8"),
        (TFMessage::HASH, "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"),
        (Path::HASH, "RIHS01_1957a5bb3cee5da65c4e52e52b65a93df227efce4c20f8458b36e73066ca334b"),
        (Clock::HASH, "RIHS01_692f7a66e93a3c83e71765d033b60349ba68023a8c689a79e48078bcb5c58564"),
    ];
    for (ours, want) in reference {
        assert_eq!(ours, want);
    }
}

/// The exact text hashed for Twist, as rosbags 0.11.9 hashes it (issue 32's
/// research).
#[test]
fn twist_hashes_the_reference_json() {
    let want = r#"{"type_description": {"type_name": "geometry_msgs/msg/Twist", "fields": [{"name": "linear", "type": {"type_id": 1, "capacity": 0, "string_capacity": 0, "nested_type_name": "geometry_msgs/msg/Vector3"}}, {"name": "angular", "type": {"type_id": 1, "capacity": 0, "string_capacity": 0, "nested_type_name": "geometry_msgs/msg/Vector3"}}]}, "referenced_type_descriptions": [{"type_name": "geometry_msgs/msg/Vector3", "fields": [{"name": "x", "type": {"type_id": 11, "capacity": 0, "string_capacity": 0, "nested_type_name": ""}}, {"name": "y", "type": {"type_id": 11, "capacity": 0, "string_capacity": 0, "nested_type_name": ""}}, {"name": "z", "type": {"type_id": 11, "capacity": 0, "string_capacity": 0, "nested_type_name": ""}}]}]}"#;
    assert_eq!(description_json(Twist::TYPE, Twist::DEFINITION).unwrap(), want);
}

/// A definition missing a dependency, or holding one too many, is caught.
#[test]
fn a_definition_must_hold_exactly_the_types_used() {
    let missing = description_json(PoseStamped::TYPE, "std_msgs/Header header\n");
    assert!(missing.unwrap_err().contains("std_msgs/msg/Header is used but not defined"));
    let extra = format!("{}{SEPARATOR}\nMSG: geometry_msgs/msg/Point\nfloat64 x\n", Clock::DEFINITION);
    assert!(description_json(Clock::TYPE, &extra).unwrap_err().contains("the definition holds"));
}
