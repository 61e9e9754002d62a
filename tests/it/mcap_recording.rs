//! `run.mcap` (issue 13): one channel per kind of data, one message per CSV
//! row, timestamps in run time, and the CSVs' numbers when read back with
//! the `mcap` crate's reader.

use std::collections::BTreeMap;
use std::process::Command;

const SCENARIO: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/scenarios/paper.toml");

fn csv(path: &std::path::Path) -> (Vec<String>, Vec<Vec<f64>>) {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut lines = text.lines();
    let header = lines.next().expect("header").split(',').map(str::to_string).collect();
    let rows = lines.map(|l| l.split(',').map(|f| f.parse().expect("number")).collect()).collect();
    (header, rows)
}

#[test]
fn a_run_folder_holds_an_mcap_recording_with_the_csvs_numbers() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("run");
    let o = Command::new(env!("CARGO_BIN_EXE_formation"))
        .args(["sim", SCENARIO, "-q", "--set", "duration=2", "--every", "10", "--mcap", "--out"])
        .arg(&out)
        .output()
        .expect("formation sim");
    assert!(o.status.success(), "formation sim: {}", String::from_utf8_lossy(&o.stderr));

    let bytes = std::fs::read(out.join("run.mcap")).expect("run.mcap in the run folder");
    let mut by_topic: BTreeMap<String, Vec<(u64, serde_json::Value, String)>> = BTreeMap::new();
    for m in mcap::MessageStream::new(&bytes).expect("an MCAP file") {
        let m = m.expect("a readable message");
        let schema = m.channel.schema.as_ref().map(|s| s.name.clone()).unwrap_or_default();
        assert_eq!(m.channel.message_encoding, "json", "{}", m.channel.topic);
        let v: serde_json::Value = serde_json::from_slice(&m.data).expect("JSON message");
        by_topic.entry(m.channel.topic.clone()).or_default().push((m.log_time, v, schema));
    }
    let mut want: Vec<String> = vec!["/leader/pose".into(), "/leader/state".into()];
    for id in 1..=4 {
        for kind in ["pose", "estimate", "state"] {
            want.push(format!("/follower_{id}/{kind}"));
        }
    }
    want.sort();
    assert_eq!(by_topic.keys().cloned().collect::<Vec<_>>(), want, "one channel per kind of data");

    for id in 1..=4 {
        let (header, rows) = csv(&out.join(format!("follower_{id}.csv")));
        let col = |name: &str| header.iter().position(|h| h == name).expect(name);
        for kind in ["pose", "estimate", "state"] {
            let msgs = &by_topic[&format!("/follower_{id}/{kind}")];
            assert_eq!(
                msgs.len(),
                rows.len(),
                "follower {id} {kind}: {} messages, {} CSV rows",
                msgs.len(),
                rows.len()
            );
        }
        let states = &by_topic[&format!("/follower_{id}/state")];
        let poses = &by_topic[&format!("/follower_{id}/pose")];
        assert_eq!(poses[0].2, "foxglove.PoseInFrame");
        for (n, row) in rows.iter().enumerate() {
            let t = row[col("t")];
            let ns = (t * 1e9).round() as u64;
            assert_eq!(states[n].0, ns, "follower {id} row {n}: log time {} ns for t = {t} s", states[n].0);
            for (h, v) in header.iter().zip(row) {
                let got = states[n].1[h].as_f64().unwrap_or(f64::NAN);
                assert!(
                    got == *v || (got.is_nan() && v.is_nan()),
                    "follower {id} row {n} {h}: {got} in MCAP, {v} in CSV"
                );
            }
            let p = &poses[n].1["pose"];
            assert_eq!(p["position"]["x"].as_f64(), Some(row[col("x")]), "follower {id} row {n} pose x");
            let (qz, qw) = (p["orientation"]["z"].as_f64().unwrap(), p["orientation"]["w"].as_f64().unwrap());
            let theta = 2.0 * qz.atan2(qw);
            let d = (theta - row[col("theta")] + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU)
                - std::f64::consts::PI;
            assert!(
                d.abs() < 1e-12,
                "follower {id} row {n}: heading {theta} from the quaternion, {} in CSV",
                row[col("theta")]
            );
        }
    }
    let (_, leader) = csv(&out.join("leader.csv"));
    assert_eq!(by_topic["/leader/pose"].len(), leader.len(), "leader poses vs leader.csv rows");

    // `formation report` takes the folder as any other.
    let o = Command::new(env!("CARGO_BIN_EXE_formation"))
        .args(["report", "-q"])
        .arg(&out)
        .arg("--out")
        .arg(dir.path().join("report"))
        .output()
        .expect("formation report");
    assert!(o.status.success(), "formation report on a folder with run.mcap: {}", String::from_utf8_lossy(&o.stderr));
    assert!(dir.path().join("report").join("report.md").exists());

    // run.mcap is written from the CSVs: --no-csv with --mcap is refused.
    let o = Command::new(env!("CARGO_BIN_EXE_formation"))
        .args(["sim", SCENARIO, "-q", "--no-csv", "--mcap"])
        .output()
        .expect("formation sim");
    assert_eq!(o.status.code(), Some(2), "--no-csv --mcap: {}", String::from_utf8_lossy(&o.stderr));

    // Without --mcap: no recording (it costs about as much as the CSVs).
    let plain = dir.path().join("plain");
    let o = Command::new(env!("CARGO_BIN_EXE_formation"))
        .args(["sim", SCENARIO, "-q", "--set", "duration=0.5", "--out"])
        .arg(&plain)
        .output()
        .expect("formation sim");
    assert!(o.status.success(), "formation sim: {}", String::from_utf8_lossy(&o.stderr));
    assert!(!plain.join("run.mcap").exists(), "run.mcap written without --mcap");
}
