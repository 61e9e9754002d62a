//! Hostile input, as a user or an attacker would give it: malformed and
//! out-of-bounds scenario files, files that are not files, and command lines
//! the project must refuse. Each case states its exit status and the words
//! its message must contain; none may panic, hang (every case has a
//! deadline), or run silently.
//!
//! Run with `cargo test --test it hostile_inputs::`; a failure lists every case
//! that did not answer as stated, with what it printed.

use std::io::Read;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// How long one case may take: refusing is immediate; 10 s is a hang.
const DEADLINE: Duration = Duration::from_secs(10);

fn paper() -> String {
    std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("scenarios/paper.toml")).unwrap()
}

/// The paper scenario with `from` replaced by `to` (which must be there).
fn edit(from: &str, to: &str) -> String {
    let t = paper();
    assert!(t.contains(from), "paper.toml has no {from:?}");
    t.replacen(from, to, 1)
}

/// The paper scenario with `text` put first (top-level keys must come
/// before the first table).
fn first(text: &str) -> String {
    format!("{text}\n{}", paper())
}

/// The paper scenario with `text` appended (new tables and fault rows).
fn last(text: &str) -> String {
    format!("{}\n{text}\n", paper())
}

/// The paper scenario without its `[name]` table.
fn without_table(name: &str) -> String {
    let mut skipping = false;
    let mut out = String::new();
    for line in paper().lines() {
        if line.starts_with('[') {
            skipping = line.starts_with(&format!("[{name}]"));
        }
        if !skipping {
            out.push_str(line);
            out.push('\n');
        }
    }
    out
}

/// One hostile input.
struct Case {
    name: &'static str,
    /// The scenario file's text, written to `s.toml` in the case's folder
    /// (`{file}` in `args` is its path).
    file: Option<String>,
    /// Arguments; `{file}` is the scenario, `{dir}` the case's folder,
    /// `{paper}` the paper scenario.
    args: Vec<String>,
    /// Exit status.
    code: i32,
    /// Words stderr must contain.
    words: Vec<&'static str>,
}

fn case(name: &'static str, file: Option<String>, args: &[&str], code: i32, words: &[&'static str]) -> Case {
    Case { name, file, args: args.iter().map(|s| s.to_string()).collect(), code, words: words.to_vec() }
}

/// `formation sim {file} --out {dir}/out -q` on a scenario text.
fn sim(name: &'static str, text: String, words: &[&'static str]) -> Case {
    case(name, Some(text), &["sim", "{file}", "--out", "{dir}/out", "-q"], 2, words)
}

/// `formation sim {paper} --set …` with the given extra arguments.
fn sim_paper(name: &'static str, extra: &[&str], words: &[&'static str]) -> Case {
    let mut args = vec!["sim", "{paper}", "--out", "{dir}/out", "-q"];
    args.extend_from_slice(extra);
    case(name, None, &args, 2, words)
}

fn cases() -> Vec<Case> {
    let many_followers = {
        let mut t = String::from("edges = []\n");
        for id in 1..=10_001 {
            t.push_str(&format!("[[followers]]\nid = {id}\noffset = [0.0, 0.0]\nbody_error = [0.0, 0.0, 0.0]\n"));
        }
        t
    };
    let many_faults = {
        let mut t = paper();
        for _ in 0..10_001 {
            t.push_str("[[faults]]\nnode = 2\nfrom = 1.0\nto = 2.0\n");
        }
        t
    };
    vec![
        // Types, in plain words, with the key and its line.
        sim("dt is a string", edit("dt = 0.001", "dt = \"x\""), &["s.toml:8:", "dt", "expected a number", "\"x\""]),
        sim("seed is negative", edit("seed = 1 ", "seed = -1 "), &["s.toml:7:", "seed", "whole number", "-1"]),
        sim("seed is a fraction", edit("seed = 1 ", "seed = 1.5 "), &["seed", "whole number", "1.5"]),
        sim("duration is a string", edit("duration = 30.0", "duration = \"long\""), &["duration", "a number"]),
        sim("noise is a word", edit("noise = true", "noise = \"yes\""), &["noise", "true or false"]),
        sim("kinematic is a number", edit("kinematic = \"bio\"", "kinematic = 3"), &["kinematic", "a name in quotes"]),
        sim("kinematic unknown", edit("kinematic = \"bio\"", "kinematic = \"pid\""), &["kinematic", "`pid`", "bio"]),
        sim("dynamic unknown", edit("dynamic = \"bio\"", "dynamic = \"lqr\""), &["dynamic", "`lqr`", "smc"]),
        sim("filter unknown", edit("filter = \"asif\"", "filter = \"ukf\""), &["filter", "`ukf`", "asif, kf, none"]),
        sim(
            "estimate_init unknown",
            edit("estimate_init = \"leader\"", "estimate_init = \"random\""),
            &["estimate_init", "random", "leader, zero"],
        ),
        sim(
            "timing unknown",
            edit("timing = \"lockstep\"", "timing = \"fast\""),
            &["timing", "fast", "lockstep, realtime"],
        ),
        sim("unknown top-level key", first("speed = 3"), &["s.toml:1:", "unknown key `speed`"]),
        sim("unknown key in a table", edit("mass = 10.0", "mass = 10.0\nmas = 3"), &["robot", "unknown key `mas`"]),
        sim("robot is a number", format!("robot = 3\n{}", without_table("robot")), &["s.toml:1:", "robot", "a table"]),
        sim("a fault row is a number", first("faults = [3]"), &["faults[0]", "fault row", "3"]),
        sim("follower id is a string", edit("id = 2", "id = \"two\""), &["followers[1].id", "whole number", "\"two\""]),
        sim("robot.mass is an array", edit("mass = 10.0", "mass = [1]"), &["robot.mass", "expected a number"]),
        sim("duplicate key", first("seed = 4"), &["duplicate key `seed`", "line 1"]),
        sim("duplicate table", last("[robot]\nmass = 3.0"), &["duplicate key `robot`", "line 72"]),
        sim("unclosed array", edit("edges = [[1, 2]", "edges = [[1, 2"), &["s.toml:22:", "expected"]),
        sim("empty file", String::new(), &["missing key `followers`"]),
        sim("missing edges", edit("edges = [[1, 2], [1, 3], [2, 4], [3, 4]]", ""), &["missing key `edges`"]),
        // Fixed-length arrays.
        sim(
            "link of three nodes",
            last("[[faults]]\nlink = [1, 2, 3]\nfrom = 1.0\nto = 2.0"),
            &["faults[0].link", "expected 2", "got 3"],
        ),
        sim("link of one node", last("[[faults]]\nlink = [1]\nfrom = 1.0\nto = 2.0"), &["faults[0].link", "got 1"]),
        sim(
            "offset of three numbers",
            edit("offset = [4.0, -4.0]", "offset = [4.0, -4.0, 1.0]"),
            &["followers[0].offset", "expected 2 numbers, got 3"],
        ),
        sim("edge of three ids", edit("edges = [[1, 2]", "edges = [[1, 2, 3]"), &["edges[0]", "got 3"]),
        // A speed whose square overflows (it ran to an `inf` formation error
        // with exit status 0), an offset beyond any formation.
        sim(
            "an initial speed of 1e300 m/s",
            edit("offset = [4.0, -4.0]", "offset = [4.0, -4.0]\nvelocity = [1e300, 0.0]"),
            &["followers[0].velocity", "1e300 is beyond ±1000"],
        ),
        sim(
            "an offset of 1e200 m",
            edit("offset = [4.0, -4.0]", "offset = [1e200, -4.0]"),
            &["followers[0].offset", "1e200 is beyond ±1e6 m"],
        ),
        // Values out of their domain.
        sim(
            "dt is 1e308",
            edit("dt = 0.001", "dt = 1e308"),
            &["s.toml:8:", "dt", "1e308 s", "longer than the whole run"],
        ),
        sim("dt is zero", edit("dt = 0.001", "dt = 0.0"), &["dt", "positive"]),
        sim("dt is negative", edit("dt = 0.001", "dt = -0.001"), &["dt", "positive"]),
        sim("duration is nan", edit("duration = 30.0", "duration = nan"), &["duration"]),
        sim("duration is inf", edit("duration = 30.0", "duration = inf"), &["duration"]),
        sim(
            "duration not a whole number of steps",
            edit("duration = 30.0", "duration = 30.0005"),
            &["duration", "whole number of steps"],
        ),
        sim("1e9 steps", edit("duration = 30.0", "duration = 1e6"), &["duration", "1e9 steps", "at most 1e8"]),
        sim(
            "no followers",
            edit("edges = [[1, 2], [1, 3], [2, 4], [3, 4]]", "edges = []\nfollowers = []")
                .split("[[followers]]")
                .next()
                .unwrap()
                .to_string(),
            &["followers", "at least one"],
        ),
        sim("follower id 0", edit("id = 2", "id = 0"), &["followers[1].id", "leader's id"]),
        sim("duplicate follower id", edit("id = 2", "id = 1"), &["duplicate follower id 1"]),
        sim(
            "pose and body_error",
            edit("body_error = [2.0, 0.0, 0.0]", "body_error = [2.0, 0.0, 0.0]\npose = [0.0, 0.0, 0.0]"),
            &["pose", "not both"],
        ),
        sim(
            "neither pose nor body_error",
            edit("body_error = [5.0, 0.0, 0.0]\n", ""),
            &["followers[3].pose", "missing"],
        ),
        sim("edge to an unknown follower", edit("[3, 4]]", "[3, 9]]"), &["edges[3]", "unknown follower 9"]),
        sim("self-loop", edit("[3, 4]]", "[3, 3]]"), &["self-loop"]),
        sim("duplicate edge", edit("[3, 4]]", "[4, 3], [3, 4]]"), &["duplicate edge"]),
        sim(
            "no follower hears the leader",
            edit("leader_link = true", ""),
            &["no follower hears the leader", "leader_link = true"],
        ),
        sim(
            "a follower cut off",
            edit("edges = [[1, 2], [1, 3], [2, 4], [3, 4]]", "edges = [[1, 2], [1, 3]]"),
            &["followers 4", "Lemma 1"],
        ),
        sim("mass zero", edit("mass = 10.0", "mass = 0.0"), &["robot.mass", "positive"]),
        sim("inertia infinite", edit("inertia = 5.0", "inertia = inf"), &["robot.inertia"]),
        sim("covariance r zero", edit("r = [1.6e-4, 1.0e-4]", "r = [0.0, 1.0e-4]"), &["covariance.r"]),
        sim(
            "rejoin_after beyond the run",
            edit("[network]", "[network]\nrejoin_after = 1e9"),
            &["network.rejoin_after", "1e9 s", "1e12 steps", "never rejoin"],
        ),
        sim(
            "rejoin unknown",
            edit("[network]", "[network]\nrejoin = \"vote\""),
            &["network.rejoin", "consensus, adopt"],
        ),
        sim(
            "telemetry_batch zero",
            edit("telemetry_batch = 50", "telemetry_batch = 0"),
            &["network.telemetry_batch", "at least 1"],
        ),
        sim(
            "delay_steps too many",
            edit("[network]", "[network]\ndelay_steps = 5000"),
            &["network.delay_steps", "more than 1000"],
        ),
        sim("name with a slash", edit("name = \"paper\"", "name = \"../etc\""), &["name", "letters, digits"]),
        sim(
            "trajectory unknown",
            edit("trajectory = \"paper\"", "trajectory = \"spiral\""),
            &["leader.trajectory", "spiral"],
        ),
        sim(
            "circle of radius 0",
            edit("trajectory = \"paper\"", "trajectory = \"circle\"\nradius = 0.0"),
            &["leader.radius", "zero"],
        ),
        // The fault table.
        // `node = 0` is the leader silent (a handover's gap): its window is checked as any.
        sim("fault node 0 backwards", last("[[faults]]\nnode = 0\nfrom = 2.0\nto = 1.0"), &["faults[0].to", "empty"]),
        sim(
            "fault node unknown",
            last("[[faults]]\nnode = 9\nfrom = 1.0\nto = 2.0"),
            &["faults[0].node", "follower 9"],
        ),
        sim(
            "fault with node and link",
            last("[[faults]]\nnode = 2\nlink = [1, 2]\nfrom = 1.0\nto = 2.0"),
            &["faults[0]", "not both"],
        ),
        sim("fault with neither", last("[[faults]]\nfrom = 1.0\nto = 2.0"), &["faults[0]", "node = ID"]),
        sim(
            "fault link not in the graph",
            last("[[faults]]\nlink = [1, 4]\nfrom = 1.0\nto = 2.0"),
            &["faults[0].link", "not a link"],
        ),
        sim(
            "fault link to itself",
            last("[[faults]]\nlink = [2, 2]\nfrom = 1.0\nto = 2.0"),
            &["faults[0].link", "both ends"],
        ),
        sim(
            "fault before the run",
            last("[[faults]]\nnode = 2\nfrom = -1.0\nto = 2.0"),
            &["faults[0].from", "before the run"],
        ),
        sim("fault window empty", last("[[faults]]\nnode = 2\nfrom = 2.0\nto = 2.0"), &["faults[0].to", "empty"]),
        sim(
            "fault window covers no step",
            last("[[faults]]\nnode = 2\nfrom = 1.0001\nto = 1.0004"),
            &["faults[0].to", "covers no step"],
        ),
        sim(
            "fault after the run",
            last("[[faults]]\nnode = 2\nfrom = 1.0\nto = 40.0"),
            &["faults[0].to", "after the end"],
        ),
        sim(
            "fault loss 1.5",
            last("[[faults]]\nnode = 2\nfrom = 1.0\nto = 2.0\nloss = 1.5"),
            &["faults[0].loss", "probability"],
        ),
        sim(
            "fault loss a string",
            last("[[faults]]\nnode = 2\nfrom = 1.0\nto = 2.0\nloss = \"half\""),
            &["loss", "a number"],
        ),
        sim("fault unknown key", last("[[faults]]\nnode = 2\nfrom = 1.0\nuntil = 2.0"), &["unknown key `until`"]),
        // Bounds.
        sim("10,001 followers", many_followers, &["10001 followers", "at most 10000"]),
        sim("10,001 fault rows", many_faults, &["10001 fault rows", "at most 10000"]),
        // Files that are not scenario files.
        case("not UTF-8", None, &["sim", "{dir}/binary.toml", "--out", "{dir}/out"], 2, &["not UTF-8"]),
        case("a FIFO", None, &["sim", "{dir}/fifo.toml", "--out", "{dir}/out"], 2, &["not a regular file"]),
        case("/dev/urandom", None, &["sim", "/dev/urandom", "--out", "{dir}/out"], 2, &["not a regular file"]),
        case("a folder", None, &["sim", "{dir}", "--out", "{dir}/out"], 2, &["is a folder"]),
        case(
            "a missing file",
            None,
            &["sim", "{dir}/nothing.toml", "--out", "{dir}/out"],
            2,
            &["nothing.toml", "cannot read"],
        ),
        case(
            "a file over 16 MB",
            None,
            &["sim", "{dir}/huge.toml", "--out", "{dir}/out"],
            2,
            &["bytes", "at most 16777216"],
        ),
        // --set.
        sim_paper(
            "--set with a missing bracket",
            &["--set", "edges=[[1,2]"],
            &["--set edges=[[1,2]", "not a TOML value"],
        ),
        sim_paper("--set without =", &["--set", "dt"], &["--set dt", "KEY=VALUE"]),
        sim_paper("--set with an empty key", &["--set", "=3"], &["--set =3", "empty key"]),
        sim_paper("--set unknown key", &["--set", "robot.weight=3"], &["--set robot.weight=3", "unknown key"]),
        sim_paper(
            "--set a seed beyond 64 bits",
            &["--set", "seed=9223372036854775808"],
            &["--set seed=9223372036854775808", "beyond the whole numbers"],
        ),
        // A key inside the value's table is named (the table itself was).
        sim_paper(
            "--set a table with an unknown key",
            &["--set", "backstepping.shunting={a=4,b=2,d=2,e=1}"],
            &["`backstepping.shunting`: unknown key `e`"],
        ),
        sim_paper("--set wrong type", &["--set", "dt=true"], &["--set dt=true", "a number"]),
        sim_paper("--set a table for a name", &["--set", "filter={}"], &["`filter`", "a name in quotes"]),
        sim_paper("--set an array for a name", &["--set", "kinematic=[1]"], &["`kinematic`", "a name in quotes"]),
        sim_paper("--set a number as a fault row", &["--set", "faults+=3"], &["`faults`:", "fault row"]),
        sim_paper("--set 1e9 steps", &["--set", "duration=1e6"], &["--set duration=1e6", "1e9 steps"]),
        // Values that ran to an `inf` or a 130 m error with exit status 0.
        sim_paper("a negative backstepping gain", &["--set", "backstepping.c1=-3"], &["backstepping.c1", "positive"]),
        sim_paper(
            "a negative mass factor without a fault time",
            &["--set", "fault.mass_factor=-1"],
            &["fault.mass_factor", "positive"],
        ),
        sim_paper(
            "--set a bad fault row",
            &["--set", "faults+={node=9, from=1, to=2}"],
            &["faults[0].node", "follower 9"],
        ),
        sim_paper("--set a disconnected graph", &["--set", "edges=[[1,2]]"], &["--set edges=[[1,2]]", "Lemma 1"]),
        // A late join (docs/model.md §14) is a follower's, absent from the start until a time given.
        sim_paper(
            "--set a join that starts late",
            &["--set", "faults+={node=3, from=1, to=8, join=true}"],
            &["faults[0].from", "absent from the start"],
        ),
        sim_paper(
            "--set a join without its time",
            &["--set", "faults+={node=3, from=0, join=true}"],
            &["faults[0].to", "a join needs `to`"],
        ),
        sim_paper(
            "--set a join of a link",
            &["--set", "faults+={link=[1,3], from=0, to=8, join=true}"],
            &["faults[0].link", "give `node = ID`"],
        ),
        sim_paper(
            "--set a join of the leader",
            &["--set", "faults+={node=0, from=0, to=3, join=true}"],
            &["faults[0].node", "the leader does not join"],
        ),
        sim_paper(
            "--set a join with loss",
            &["--set", "faults+={node=3, from=0, to=3, loss=0.5, join=true}"],
            &["faults[0].loss", "loss = 1"],
        ),
        sim_paper(
            "--set rejoin_after beyond the run",
            &["--set", "network.rejoin_after=1e9"],
            &["network.rejoin_after", "never rejoin"],
        ),
        // Command lines.
        sim_paper("--threads 1000", &["--threads", "1000"], &["--threads 1000", "at most 256"]),
        sim_paper("--every 0", &["--every", "0"], &["--every"]),
        sim_paper("--every not a number", &["--every", "ten"], &["--every", "ten"]),
        case(
            "generate 10 million followers",
            None,
            &["generate", "--followers", "10000000", "--graph", "ring", "--out", "{dir}/g.toml"],
            2,
            &["--followers 10000000", "at most 10000"],
        ),
        case(
            "generate 0 followers",
            None,
            &["generate", "--followers", "0", "--graph", "ring", "--out", "{dir}/g.toml"],
            2,
            &["at least 1"],
        ),
        case(
            "generate a complete graph of 5000",
            None,
            &["generate", "--followers", "5000", "--graph", "complete", "--out", "{dir}/g.toml"],
            2,
            &["12497500 edges", "at most 1000000"],
        ),
        case(
            "generate chords on a grid",
            None,
            &["generate", "--followers", "9", "--graph", "grid", "--chords", "2", "--out", "{dir}/g.toml"],
            2,
            &["--chords", "ring"],
        ),
        case(
            "generate a negative radius",
            None,
            &["generate", "--followers", "9", "--graph", "random-geometric", "--radius=-1", "--out", "{dir}/g.toml"],
            2,
            &["--radius"],
        ),
        case(
            "generate an unknown graph",
            None,
            &["generate", "--followers", "9", "--graph", "star", "--out", "{dir}/g.toml"],
            2,
            &["star"],
        ),
        case(
            "generate over a file",
            None,
            &["generate", "--followers", "9", "--graph", "ring", "--out", "{dir}/exists.toml"],
            2,
            &["exists", "--force"],
        ),
        case(
            "certs for 3,000,000 days",
            None,
            &["certs", "{paper}", "--out", "{dir}/c", "--days", "3000000"],
            2,
            &["--days 3000000", "36500"],
        ),
        case("certs for 0 days", None, &["certs", "{paper}", "--out", "{dir}/c", "--days", "0"], 2, &["--days 0"]),
        case(
            "certs from 9999-12-31",
            None,
            &["certs", "{paper}", "--out", "{dir}/c", "--not-before", "9999-12-31"],
            2,
            &["9999-12-31", "last date"],
        ),
        case(
            "certs from a non-date",
            None,
            &["certs", "{paper}", "--out", "{dir}/c", "--not-before", "yesterday"],
            2,
            &["--not-before", "YYYY-MM-DD"],
        ),
        case(
            "certs from year 0",
            None,
            &["certs", "{paper}", "--out", "{dir}/c", "--not-before", "0000-01-01"],
            2,
            &["--not-before", "1970"],
        ),
        case(
            "certs for a --san that is not a name",
            None,
            &["certs", "{paper}", "--out", "{dir}/c", "--san", "not a name!"],
            2,
            &["--san", "not an IP address or a DNS name"],
        ),
        case(
            "certs for an unknown node",
            None,
            &["certs", "{paper}", "--out", "{dir}/c", "--node", "agent-9"],
            2,
            &["--node agent-9", "agent-1"],
        ),
        case(
            "launch with a zero time scale",
            None,
            &["launch", "{paper}", "--time-scale", "0", "--out", "{dir}/out"],
            2,
            &["--time-scale"],
        ),
        case(
            "launch with a bad run name",
            None,
            &["launch", "{paper}", "--run", "a/b", "--out", "{dir}/out"],
            2,
            &["a/b"],
        ),
        case(
            "launch with --group 0",
            None,
            &["launch", "{paper}", "--group", "0", "--out", "{dir}/out"],
            2,
            &["--group 0"],
        ),
        case(
            "launch with delay_steps in lock-step",
            None,
            &["launch", "{paper}", "--set", "network.delay_steps=5", "--out", "{dir}/out"],
            2,
            &["delay_steps", "lock-step"],
        ),
        case(
            "stand-in robots for a torque-driven scenario, named as typed",
            None,
            &["launch", "{paper}", "--ros2", "--robots", "stand-in", "--out", "{dir}/out"],
            2,
            &["--robots stand-in: a robot driven through ROS 2 takes velocity commands"],
        ),
        case(
            "replay's --metric without --explain (it was ignored)",
            None,
            &["replay", "{dir}", "--metric", "vc_peak"],
            2,
            &["--metric goes with --explain"],
        ),
        case(
            "replay --explain listing nothing",
            None,
            &["replay", "{dir}", "--explain", "--top", "0"],
            2,
            &["--top", "at least 1"],
        ),
        case(
            "a run larger than the disk's free space (it started and filled the disk)",
            Some(
                formation_scenario::generate::toml(&formation_scenario::generate::Spec::new(
                    1000,
                    formation_scenario::generate::GraphKind::Ring,
                ))
                .expect("a ring of 1000"),
            ),
            // 5e7 samples of 1000 followers: about 21 TB of CSV.
            &["sim", "{file}", "--set", "dt=0.001", "--set", "duration=50000", "--out", "{dir}/out", "-q"],
            2,
            &["GB free", "--every N"],
        ),
        case(
            "generate into a folder that is not there",
            None,
            &["generate", "--followers", "3", "--graph", "ring", "--out", "{dir}/nope/x.toml"],
            2,
            &["there is no folder"],
        ),
        case("bench with 0 threads", None, &["bench", "--threads", "0"], 2, &["--threads", "0"]),
        case(
            "an option that does not exist",
            None,
            &["sim", "{paper}", "--no-such-option"],
            2,
            &["unexpected argument '--no-such-option'", "(formation sim --help)"],
        ),
        case(
            "bench-net with a long lock-step run no longer than the short one",
            None,
            &["bench-net", "--lockstep-duration", "1", "--agents", "", "--base-port", "1"],
            2,
            &["--lockstep-duration 1", "longer than the short one"],
        ),
        case(
            "bench-net with no real-time run",
            None,
            &["bench-net", "--realtime-duration", "0", "--agents", "", "--base-port", "1"],
            2,
            &["--realtime-duration 0", "positive"],
        ),
        case(
            "real-time priority for a lock-step run",
            None,
            &["launch", "{paper}", "--rt-priority", "10", "--out", "{dir}/out"],
            2,
            &["--rt-priority 10", "lock-step"],
        ),
        case(
            "a died row in a real-time run",
            None,
            &[
                "launch",
                "{paper}",
                "--set",
                "timing=realtime",
                "--set",
                "faults+={node=2, from=5, died=true}",
                "--out",
                "{dir}/out",
            ],
            2,
            &["killing follower 2 at 5 s", "a real-time run does not kill"],
        ),
        case(
            "real-time priority 0",
            None,
            &["launch", "{paper}", "--set", "timing=realtime", "--rt-priority", "0", "--out", "{dir}/out"],
            2,
            &["--rt-priority must be 1 to 99", "not 0"],
        ),
        // formation replay and playback (issue 25).
        case("replay of no folder", None, &["replay", "{dir}/missing"], 2, &["missing", "no such run folder"]),
        case("replay of a simulator's run", None, &["replay", "{dir}/simrun"], 2, &["no hearing.bin", "formation sim"]),
        case(
            "replay of a garbage record",
            None,
            &["replay", "{dir}/garbage"],
            2,
            &["hearing.bin", "not a hearing record"],
        ),
        case(
            "replay of another format's record",
            None,
            &["replay", "{dir}/format9"],
            2,
            &["hearing record format 9", "this build reads format 2"],
        ),
        case(
            "replay --explain of a garbage record",
            None,
            &["replay", "{dir}/garbage", "--explain"],
            2,
            &["not a hearing record"],
        ),
        case(
            "replay of a record declaring 2^62 bytes",
            None,
            &["replay", "{dir}/h-huge"],
            2,
            &["h-huge/hearing.bin", "not a hearing record"],
        ),
        case(
            "playback of a record declaring 2^62 bytes",
            None,
            &["play", "{dir}/h-huge", "--web", "127.0.0.1:0"],
            2,
            &["not a hearing record"],
        ),
        case("replay of a FIFO", None, &["replay", "{dir}/h-fifo"], 2, &["h-fifo/hearing.bin", "not a regular file"]),
        case(
            "replay of a link to /dev/zero",
            None,
            &["replay", "{dir}/h-zero"],
            2,
            &["h-zero/hearing.bin", "not a regular file"],
        ),
        case(
            "replay of a record with a flipped bit",
            None,
            &["replay", "{dir}/h-flipped"],
            2,
            &["h-flipped/hearing.bin", "damaged", "checksum"],
        ),
        case(
            "replay of another run's record",
            None,
            &["replay", "{dir}/h-foreign"],
            2,
            &["hearing.bin is another run's", "fingerprint 0000000000000bad"],
        ),
        case(
            "a lease too short to live",
            None,
            &["node", "agent", "--scenario", "{paper}", "--id", "1", "--lease-ms", "5"],
            2,
            &["--lease-ms", "5 is not in 100..=3600000"],
        ),
        case("playback without a page", None, &["play", "{dir}/garbage"], 2, &["--web, --foxglove"]),
        case(
            "playback by its old spelling, without a page",
            None,
            &["monitor", "--replay", "{dir}/garbage"],
            2,
            &["is now `formation play RUN_DIR`", "--web, --foxglove"],
        ),
        case(
            "playback at speed 0",
            None,
            &["play", "{dir}/garbage", "--web", "--speed", "0"],
            2,
            &["--speed", "not 0"],
        ),
        case("playback of no folder", None, &["play", "{dir}/missing", "--web"], 2, &["no such run folder"]),
        case(
            "a slow link in client mode",
            None,
            &["lab", "{paper}", "--slow-link", "2:4=30", "--out", "{dir}/out"],
            2,
            &["--slow-link 2:4=30", "--mode peer"],
        ),
        case(
            "a slow link to no follower",
            None,
            &["lab", "{paper}", "--mode", "peer", "--slow-link", "2:9=30", "--out", "{dir}/out"],
            2,
            &["--slow-link 2:9=30", "follower ids"],
        ),
        case(
            "a slow link of 300 %",
            None,
            &["lab", "{paper}", "--mode", "peer", "--slow-link", "2:4=300", "--out", "{dir}/out"],
            2,
            &["--slow-link 2:4=300", "less than 100"],
        ),
        case(
            "a slow link to itself",
            None,
            &["lab", "{paper}", "--mode", "peer", "--slow-link", "2:2=10", "--out", "{dir}/out"],
            2,
            &["--slow-link 2:2=10", "follower 2 to itself"],
        ),
        case(
            "a slow link between followers that are not neighbours",
            None,
            &["lab", "{paper}", "--mode", "peer", "--slow-link", "2:3=10", "--out", "{dir}/out"],
            2,
            &["--slow-link 2:3=10", "2 and 3 are not neighbours", "neighbours of 2: 1, 4"],
        ),
        // Small ones (issue 30, item 6): numbers out of range, negative
        // numbers taken for flags, names too long, damaged run folders.
        case(
            "playback at speed 1e-300",
            None,
            &["play", "{dir}/garbage", "--web", "--speed", "1e-300"],
            2,
            &["--speed 1e-300 is out of range", "0.01 to 1000"],
        ),
        case(
            "playback at speed 1e-12",
            None,
            &["play", "{dir}/garbage", "--web", "--speed", "1e-12"],
            2,
            &["--speed 1e-12 is out of range"],
        ),
        case(
            "playback at speed -1",
            None,
            &["play", "{dir}/garbage", "--web", "--speed", "-1"],
            2,
            &["--speed must be positive, not -1"],
        ),
        case(
            "playback lingering 1e300 s",
            None,
            &["play", "{dir}/garbage", "--web", "--linger", "1e300"],
            2,
            &["--linger must be 0 to 86400 seconds", "1e300"],
        ),
        case(
            "generate a radius of -1",
            None,
            &["generate", "--followers", "9", "--graph", "random-geometric", "--radius", "-1", "--out", "{dir}/g.toml"],
            2,
            &["--radius must be a positive number", "not -1"],
        ),
        sim_paper(
            "--set a table over a key set before",
            &["--set", "robot.mass=1", "--set", "robot={inertia=2}"],
            &["--set robot={inertia=2}", "conflicts with --set robot.mass=1", "robot.mass would be dropped"],
        ),
        sim(
            "a name of 120,000 characters",
            edit("name = \"paper\"", &format!("name = \"{}\"", "n".repeat(120_000))),
            &["name", "120000 characters long, at most 100"],
        ),
        case(
            "an --out of 120,000 characters",
            None,
            &["sim", "{paper}", "-q", "--out", &format!("{{dir}}/{}", "o".repeat(120_000))],
            2,
            &["--out", "120000 bytes long, at most 200"],
        ),
        case(
            "launch with a --run of 101 characters",
            None,
            &["launch", "{paper}", "--run", &"r".repeat(101), "--out", "{dir}/out"],
            2,
            &["run name", "101 characters long, at most 100"],
        ),
        case(
            "report of an empty summary.json",
            None,
            &["report", "{dir}/simrun", "--out", "{dir}/out"],
            2,
            &["simrun/summary.json:1:2: missing field"],
        ),
        case(
            "report of a summary.json with a word for dt",
            None,
            &["report", "{dir}/run-dt", "--out", "{dir}/out"],
            2,
            &["run-dt/summary.json:", "`dt`: invalid type: string \"x\""],
        ),
        case(
            "report of a summary.json cut short",
            None,
            &["report", "{dir}/run-cut", "--out", "{dir}/out"],
            2,
            &["run-cut/summary.json:", "cut short"],
        ),
        case(
            "report of a CSV with a short row",
            None,
            &["report", "{dir}/run-row", "--out", "{dir}/out"],
            2,
            &["run-row/follower_2.csv: line 4: 2 fields, where the header has 22"],
        ),
        case(
            "report of a CSV with NaN",
            None,
            &["report", "{dir}/run-nan", "--out", "{dir}/out"],
            2,
            &["run-nan/follower_2.csv: line 5: `x` is NaN, not a finite number"],
        ),
        case(
            "report of a folder without a follower's CSV",
            None,
            &["report", "{dir}/run-gone", "--out", "{dir}/out"],
            2,
            &["run-gone: follower_3.csv is missing", "damaged run folder"],
        ),
        case(
            "report into the folder it reads",
            None,
            &["report", "{dir}/run", "--out", "{dir}/run"],
            2,
            &["is the run folder", "choose another --out"],
        ),
        case("an unknown command", None, &["fly"], 2, &["fly"]),
        // A run that would write many gigabytes says so before it starts
        // (then stops here: its folder is not a run folder).
        case(
            "a 17.9 GB run is announced",
            None,
            &["sim", "{paper}", "--set", "duration=100000", "--set", "dt=0.01", "--out", "{dir}/notarun"],
            2,
            &["warning: this run will write about 17.9 GB", "notarun"],
        ),
    ]
}

/// A short run of the paper scenario, made once for every case that reads one.
fn short_run() -> &'static Path {
    static RUN: std::sync::OnceLock<std::path::PathBuf> = std::sync::OnceLock::new();
    RUN.get_or_init(|| {
        let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("hostile_inputs_run");
        let paper = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenarios/paper.toml");
        let status = Command::new(env!("CARGO_BIN_EXE_formation"))
            .arg("sim")
            .arg(&paper)
            .args(["--set", "duration=0.1", "-q", "--out"])
            .arg(&dir)
            .status()
            .unwrap();
        assert!(status.success(), "the short run failed");
        dir
    })
}

/// Replaces line `n` (from 1) of the file at `path` by `f` of it.
fn edit_line(path: &Path, n: usize, f: impl Fn(&str) -> String) {
    let text = std::fs::read_to_string(path).unwrap();
    let lines: Vec<String> =
        text.lines().enumerate().map(|(k, l)| if k + 1 == n { f(l) } else { l.to_string() }).collect();
    std::fs::write(path, lines.join("\n") + "\n").unwrap();
}

/// Copies of [`short_run`] in `d`: `run` as it is, and damaged ones.
fn damaged_runs(d: &Path) {
    let copy = |name: &str| {
        let to = d.join(name);
        std::fs::create_dir(&to).unwrap();
        for e in std::fs::read_dir(short_run()).unwrap() {
            let e = e.unwrap();
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
        to
    };
    copy("run");
    // summary.json: a word for a number, and the file cut short.
    let path = copy("run-dt").join("summary.json");
    let text = std::fs::read_to_string(&path).unwrap();
    assert!(text.contains("\"dt\": 0.001"), "summary.json has no dt: {text}");
    std::fs::write(&path, text.replacen("\"dt\": 0.001", "\"dt\": \"x\"", 1)).unwrap();
    std::fs::write(copy("run-cut").join("summary.json"), &text[..text.len() / 2]).unwrap();
    // follower_2.csv: line 4 of two fields; NaN for x on line 5.
    edit_line(&copy("run-row").join("follower_2.csv"), 4, |_| "0.003,1".into());
    edit_line(&copy("run-nan").join("follower_2.csv"), 5, |l| {
        let mut fields: Vec<&str> = l.split(',').collect();
        fields[1] = "NaN";
        fields.join(",")
    });
    std::fs::remove_file(copy("run-gone").join("follower_3.csv")).unwrap();
}

/// Runs one case in its own folder; `Err` says how it failed.
fn check(c: &Case) -> Result<(), String> {
    let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
    let d = dir.path();
    std::fs::write(d.join("binary.toml"), [0xff, 0xfe, 0x00, 0x80]).unwrap();
    std::fs::write(d.join("exists.toml"), "x").unwrap();
    std::fs::create_dir(d.join("notarun")).unwrap();
    std::fs::write(d.join("notarun/keep.txt"), "mine").unwrap();
    let fifo = d.join("fifo.toml");
    let _ = Command::new("mkfifo").arg(&fifo).status();
    let huge = std::fs::File::create(d.join("huge.toml")).unwrap();
    huge.set_len(17 << 20).unwrap();
    if let Some(text) = &c.file {
        std::fs::write(d.join("s.toml"), text).unwrap();
    }
    // Run folders for `formation replay`: a simulator's, a garbage record, another format's.
    for (folder, file, bytes) in [
        ("simrun", "summary.json", b"{}".to_vec()),
        ("garbage", "hearing.bin", vec![1, 2, 3]),
        ("format9", "hearing.bin", vec![9, 1, 2]),
    ] {
        std::fs::create_dir(d.join(folder)).unwrap();
        std::fs::write(d.join(folder).join(file), bytes).unwrap();
    }
    if c.args.iter().any(|a| a.contains("{dir}/run")) {
        damaged_runs(d);
    }
    if c.args.iter().any(|a| a.contains("{dir}/h-")) {
        hearing_folders(d);
    }
    let paper = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenarios/paper.toml");
    let args: Vec<String> = c
        .args
        .iter()
        .map(|a| {
            a.replace("{file}", &d.join("s.toml").display().to_string())
                .replace("{dir}", &d.display().to_string())
                .replace("{paper}", &paper.display().to_string())
        })
        .collect();
    let mut child = Command::new(env!("CARGO_BIN_EXE_formation"))
        .args(&args)
        .current_dir(d)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|e| format!("cannot start: {e}"))?;
    let start = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().map_err(|e| e.to_string())? {
            break s;
        }
        if start.elapsed() > DEADLINE {
            let _ = child.kill();
            let _ = child.wait();
            return Err(format!("still running after {DEADLINE:?} (a hang)"));
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let mut stderr = String::new();
    child.stderr.take().unwrap().read_to_string(&mut stderr).unwrap();
    let first_lines: String = stderr.lines().take(4).collect::<Vec<_>>().join(" | ");
    if stderr.contains("panicked") || status.code() == Some(101) {
        return Err(format!("panicked: {first_lines}"));
    }
    if status.code() != Some(c.code) {
        return Err(format!("exit status {:?}, expected {}: {first_lines}", status.code(), c.code));
    }
    let missing: Vec<&str> = c.words.iter().copied().filter(|w| !stderr.contains(w)).collect();
    if !missing.is_empty() {
        return Err(format!("message lacks {missing:?}: {first_lines}"));
    }
    if stderr.lines().filter(|l| l.starts_with("error:")).count() != 1 {
        return Err(format!("expected one error line: {first_lines}"));
    }
    // Nothing but that line and warnings (clap's errors took 3-5 lines).
    let lines = stderr.lines().filter(|l| !l.trim().is_empty() && !l.starts_with("warning:")).count();
    if lines != 1 {
        return Err(format!("{lines} lines, expected the error's one: {first_lines}"));
    }
    if d.join("out").exists() {
        return Err("a run folder was left behind".into());
    }
    if std::fs::read_to_string(d.join("notarun/keep.txt")).ok().as_deref() != Some("mine") {
        return Err("a folder that is not a run folder was touched".into());
    }
    Ok(())
}

/// Run folders whose hearing.bin is hostile: a first length field of 2^62,
/// a FIFO, a link to /dev/zero, a genuine record with one bit flipped, and
/// a genuine record beside another run's network.json.
fn hearing_folders(d: &Path) {
    use formation_record::hearing::{Density, HearingRecord, ScenarioSource, HEARING_FORMAT};
    let dir = |name: &str| {
        let p = d.join(name);
        std::fs::create_dir_all(&p).unwrap();
        p
    };
    let mut huge = vec![HEARING_FORMAT as u8, 253];
    huge.extend_from_slice(&(1u64 << 62).to_le_bytes());
    huge.extend_from_slice(&[0; 12]);
    std::fs::write(dir("h-huge").join("hearing.bin"), huge).unwrap();
    let fifo = dir("h-fifo").join("hearing.bin");
    let made = Command::new("mkfifo").arg(&fifo).status().expect("mkfifo");
    assert!(made.success(), "mkfifo {}", fifo.display());
    std::os::unix::fs::symlink("/dev/zero", dir("h-zero").join("hearing.bin")).unwrap();
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenarios/paper.toml");
    let scenario = formation_scenario::Scenario::load(&path, &[]).expect("paper.toml");
    let record = HearingRecord {
        format: HEARING_FORMAT,
        scenario: ScenarioSource { label: path.display().to_string(), text: paper(), overrides: vec![] },
        fingerprint: formation_protocol::barrier::fingerprint(&scenario),
        density: Density { every: 1, csv: true, mcap: false },
        leader: vec![],
        followers: vec![],
        rescued: vec![],
    };
    let mut bytes = record.encode();
    std::fs::write(dir("h-foreign").join("hearing.bin"), &bytes).unwrap();
    let foreign = format!(
        "{{\"scenario\": \"{}\", \"steps\": {}, \"fingerprint\": \"0000000000000bad\"}}",
        scenario.name,
        scenario.steps()
    );
    std::fs::write(d.join("h-foreign").join("network.json"), foreign).unwrap();
    let middle = bytes.len() / 2;
    bytes[middle] ^= 0x10;
    std::fs::write(dir("h-flipped").join("hearing.bin"), &bytes).unwrap();
}

#[test]
fn every_hostile_input_is_refused_in_plain_words() {
    let cases = cases();
    assert!(cases.len() >= 60, "the issue asks for at least 60 hostile inputs; there are {}", cases.len());
    let names: std::collections::HashSet<&str> = cases.iter().map(|c| c.name).collect();
    assert_eq!(names.len(), cases.len(), "two cases share a name");
    // Two at a time: each is a short process.
    let (a, b) = cases.split_at(cases.len() / 2);
    let run = |part: &[Case]| -> Vec<String> {
        part.iter().filter_map(|c| check(c).err().map(|e| format!("{}: {e}", c.name))).collect()
    };
    // Two at a time: each is a short process.
    let failures: Vec<String> = std::thread::scope(|s| {
        let h = s.spawn(|| run(a));
        let mut out = run(b);
        out.extend(h.join().unwrap());
        out
    });
    assert!(
        failures.is_empty(),
        "{} of {} hostile inputs were not refused as stated:\n{}",
        failures.len(),
        cases.len(),
        failures.join("\n")
    );
}
