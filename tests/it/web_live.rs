//! The live page (`launch --web`) in a real headless browser (free ports on
//! 127.0.0.1, see `common::Ports`): Chromium from the distribution, driven
//! through chromedriver (WebDriver). Where neither is installed the test
//! says so and is skipped, unless FORMATION_BROWSER_REQUIRED is set (CI).
//!
//! What the page shows is read from the page itself (`window.formationView`,
//! its table and the pixels of its canvas) and compared with the run folder
//! the monitor wrote.

use crate::common;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use base64::Engine;
use common::{Group, LIMIT, SCENARIO};
use serde_json::{json, Value};

const CHROMIUM: &str = "/usr/bin/chromium";
const CHROMEDRIVER: &str = "/usr/bin/chromedriver";

/// The browser and its driver, or why the test cannot run.
fn browser_available() -> Result<(PathBuf, PathBuf), String> {
    let chromium = std::env::var_os("FORMATION_CHROMIUM").map_or_else(|| PathBuf::from(CHROMIUM), PathBuf::from);
    let driver = std::env::var_os("FORMATION_CHROMEDRIVER").map_or_else(|| PathBuf::from(CHROMEDRIVER), PathBuf::from);
    for p in [&chromium, &driver] {
        if !p.exists() {
            return Err(format!("{} not found (apt-get install chromium chromium-driver)", p.display()));
        }
    }
    Ok((chromium, driver))
}

/// Skips (returns None) where no browser can be had, unless CI requires one.
fn browser_or_skip(test: &str) -> Option<(PathBuf, PathBuf)> {
    match browser_available() {
        Ok(b) => Some(b),
        Err(why) if std::env::var_os("FORMATION_BROWSER_REQUIRED").is_none() => {
            common::skipped(&format!("{test}: {why}"));
            None
        }
        Err(why) => panic!("{test}: FORMATION_BROWSER_REQUIRED is set but {why}"),
    }
}

/// One headless Chromium through its own chromedriver; both end on drop.
struct Browser {
    driver: Child,
    url: String,
    session: Option<String>,
    _profile: tempfile::TempDir,
}

impl Browser {
    fn start(chromium: &Path, chromedriver: &Path, port: u16) -> Self {
        let driver = Command::new(chromedriver)
            .arg(format!("--port={port}"))
            .arg("--allowed-ips=127.0.0.1")
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("start chromedriver");
        let url = format!("http://127.0.0.1:{port}");
        let mut b = Browser { driver, url, session: None, _profile: tempfile::tempdir().expect("tempdir") };
        let t = Instant::now();
        while ureq::get(&format!("{}/status", b.url)).call().is_err() {
            assert!(
                t.elapsed() < common::GUARD,
                "chromedriver on port {port} did not answer within {:?}",
                common::GUARD
            );
            std::thread::sleep(Duration::from_millis(100));
        }
        let profile = b._profile.path().display().to_string();
        // As the machine notes say: no background networking (this
        // machine's network is closed), a fresh profile, no sandbox as root.
        let args = [
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--disable-dev-shm-usage",
            "--window-size=1280,800",
            "--force-device-scale-factor=1",
            &format!("--user-data-dir={profile}"),
        ];
        let caps = json!({"capabilities": {"alwaysMatch": {
            "browserName": "chrome",
            "goog:chromeOptions": {"binary": chromium.display().to_string(), "args": args},
        }}});
        let reply = b.post("/session", &caps);
        b.session = Some(reply["sessionId"].as_str().expect("a WebDriver session id").to_string());
        b
    }

    fn post(&self, path: &str, body: &Value) -> Value {
        let url = format!("{}{path}", self.url);
        let mut resp = ureq::post(&url).send_json(body).unwrap_or_else(|e| panic!("WebDriver POST {path}: {e}"));
        let v: Value = resp.body_mut().read_json().expect("WebDriver JSON");
        v["value"].clone()
    }

    fn session_path(&self, tail: &str) -> String {
        format!("/session/{}{tail}", self.session.as_deref().expect("session"))
    }

    fn goto(&self, url: &str) {
        self.post(&self.session_path("/url"), &json!({ "url": url }));
    }

    /// Runs a script in the page; its return value.
    fn exec(&self, script: &str) -> Value {
        self.post(&self.session_path("/execute/sync"), &json!({ "script": script, "args": [] }))
    }

    fn screenshot_png(&self) -> Vec<u8> {
        let url = format!("{}{}", self.url, self.session_path("/screenshot"));
        let mut resp = ureq::get(&url).call().expect("screenshot");
        let v: Value = resp.body_mut().read_json().expect("screenshot JSON");
        base64::engine::general_purpose::STANDARD.decode(v["value"].as_str().expect("base64 PNG")).expect("base64")
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        if let Some(s) = self.session.take() {
            let _ = ureq::delete(&format!("{}/session/{s}", self.url)).call();
        }
        let _ = self.driver.kill();
        let _ = self.driver.wait();
    }
}

/// What the page shows now, read from the page: its test hooks, its
/// status line, and for each follower it drew the canvas pixel at the
/// robot's place and the follower's colour.
const PROBE: &str = r#"
const v = window.formationView;
if (!v) return null;
const out = {frames: v.frames, state: v.state, ended: v.ended, connection: v.connection,
             shown: v.shown, robotsDrawn: v.robotsDrawn, viewers: v.lastFrame ? v.lastFrame.viewers : null,
             status: (document.getElementById('status') || {}).textContent || '', pixels: [],
             // Per follower row: the clock and latency cells' text.
             timing: [...document.querySelectorAll('#rows tr')].map((tr) => [...tr.children].slice(10, 12).map((td) => td.textContent))};
const c = v.planeCanvas;
if (c && v.drawn) {
  const ctx = c.getContext('2d');
  const r = c.width / c.getBoundingClientRect().width;
  for (const [id, p] of Object.entries(v.drawn)) {
    const [px, py] = v.toScreen(p[0], p[1]);
    const d = ctx.getImageData(Math.round(px * r), Math.round(py * r), 1, 1).data;
    const hex = '#' + [d[0], d[1], d[2]].map(x => x.toString(16).padStart(2, '0')).join('');
    out.pixels.push([Number(id), hex, v.colorOf(Number(id))]);
  }
}
return out;
"#;

/// A follower's CSV: formation and estimator error by step.
fn errors_by_step(dir: &Path, id: u32) -> Vec<(f64, f64)> {
    let path = dir.join(format!("follower_{id}.csv"));
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().expect("header").split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap_or_else(|| panic!("no {name} column"));
    let (ef, ee) = (col("formation_error"), col("estimator_error"));
    lines
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (f[ef].parse().expect("number"), f[ee].parse().expect("number"))
        })
        .collect()
}

fn wait_for_port(port: u16, limit: Duration) {
    let t = Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(t.elapsed() < limit, "nothing listening on port {port} within {limit:?}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// A page value as the page displays it ("0.1234"), checked against the
/// recorded value: the page rounds to 4 decimals.
fn close_to_display(shown: &str, recorded: f64) -> bool {
    shown.parse::<f64>().is_ok_and(|s| (s - recorded).abs() <= 0.5e-4 + 1e-12)
}

#[test]
fn two_browsers_watch_a_lockstep_run_that_still_equals_the_simulator() {
    let test = "two_browsers_watch_a_lockstep_run_that_still_equals_the_simulator";
    let Some((chromium, chromedriver)) = browser_or_skip(test) else { return };
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("run");
    // Long enough (about 10 s of wall-clock time) for both browsers to
    // start and one of them to close while the run goes on.
    let sets = ["duration=30"];
    let page_port = common::Ports::free(1).release();
    let web = format!("127.0.0.1:{page_port}");
    let base = common::Ports::free(common::LAUNCH_PORTS).release().to_string();
    let mut g =
        Group::launch(&out, &sets, &["--base-port", &base, "--run", "web-ls", "--web", &web, "--web-linger", "5"]);
    wait_for_port(page_port, LIMIT);
    let page = format!("http://{web}/");
    let a = Browser::start(&chromium, &chromedriver, common::Ports::free(1).release());
    let mut b = Some(Browser::start(&chromium, &chromedriver, common::Ports::free(1).release()));
    a.goto(&page);
    if let Some(b) = &b {
        b.goto(&page);
    }

    // Watch the run through browser A; close B half-way.
    let mut shown: Vec<(u32, f64, String, String)> = Vec::new();
    let mut most_viewers = 0;
    let mut viewers_after_close: Option<u64> = None;
    let mut pixels_checked = 0;
    let t = Instant::now();
    let status = loop {
        if let Some(s) = g.0.try_wait().expect("try_wait") {
            break s;
        }
        assert!(t.elapsed() < Duration::from_secs(180), "the run did not end within 180 s");
        let p = a.exec(PROBE);
        if !p.is_null() {
            let viewers = p["viewers"].as_u64().unwrap_or(0);
            most_viewers = most_viewers.max(viewers);
            if b.is_none() && p["state"] == "running" {
                viewers_after_close = Some(viewers);
            }
            if let Some(at) = p["shown"]["at"].as_object() {
                for (id, t) in at {
                    let (Some(t), Some(ef), Some(ee)) =
                        (t.as_f64(), p["shown"]["ef"][id].as_str(), p["shown"]["ee"][id].as_str())
                    else {
                        continue;
                    };
                    shown.push((id.parse().expect("id"), t, ef.to_string(), ee.to_string()));
                }
            }
            for px in p["pixels"].as_array().into_iter().flatten() {
                assert_eq!(px[1], px[2], "follower {} is not drawn at its place (pixel vs colour)", px[0]);
                pixels_checked += 1;
            }
            if b.is_some() && p["state"] == "running" && most_viewers >= 2 && shown.len() >= 8 {
                b = None; // closes the tab, the browser and its driver
            }
        }
        std::thread::sleep(Duration::from_millis(200));
    };
    assert!(status.success(), "formation launch --web failed: {status}");

    // The page says the run ended; the monitor is gone by now.
    let end = a.exec(PROBE);
    assert_eq!(end["state"], "complete", "the page's last state: {end}");
    assert_eq!(end["ended"], true, "{end}");
    let status_line = end["status"].as_str().unwrap_or_default().to_lowercase();
    assert!(status_line.contains("complete"), "the status line does not report the end: {status_line:?}");
    assert_eq!(end["robotsDrawn"], 4, "robots drawn at the end: {end}");
    // Each follower's row shows how well it knows the leader's clock and its
    // slowest link's latency (the leader's row has neither).
    let timing: Vec<Vec<String>> = serde_json::from_value(end["timing"].clone()).expect("timing cells");
    assert_eq!(timing.len(), 5, "the leader's and four followers' rows: {timing:?}");
    for cells in &timing[1..] {
        let clock = cells[0].strip_prefix('±').and_then(|x| x.parse::<u64>().ok());
        assert!(clock.is_some_and(|us| us > 0), "clock cell {:?}: ± the uncertainty in µs", cells[0]);
        assert!(cells[1].parse::<u64>().is_ok(), "latency cell {:?}: the slowest link's median in µs", cells[1]);
    }
    assert!(pixels_checked >= 4, "robots checked on the canvas: {pixels_checked}");
    assert!(most_viewers >= 2, "the frames never counted both browsers (most: {most_viewers})");
    assert_eq!(viewers_after_close, Some(1), "after one browser closed, the monitor still counts its viewer");
    if let Some(path) = std::env::var_os("FORMATION_SCREENSHOT") {
        std::fs::write(&path, a.screenshot_png()).expect("write the screenshot");
    }
    drop(a);

    eprintln!(
        "web_live: {} displayed follower values checked, {pixels_checked} robot pixels, at most {most_viewers} viewers",
        shown.len()
    );
    // What the page displayed is what the run recorded at that step.
    assert!(shown.len() >= 8, "the page displayed only {} follower values during the run", shown.len());
    let dt = 0.001;
    for id in 1..=4u32 {
        let rows = errors_by_step(&out, id);
        for (_, t, ef, ee) in shown.iter().filter(|s| s.0 == id) {
            let k = (t / dt).round() as usize;
            let (ref_ef, ref_ee) = rows[k];
            assert!(
                close_to_display(ef, ref_ef) && close_to_display(ee, ref_ee),
                "follower {id} at t = {t}: the page showed formation error {ef} and estimator error {ee}; \
                 the run recorded {ref_ef} and {ref_ee}"
            );
        }
    }

    // Two browsers did not disturb the run: byte for byte the simulator's.
    common::assert_equals_the_simulator(&out, &tmp.path().join("sim"), &sets, "the watched lock-step run");
    g.assert_group_empty();
}

#[test]
fn a_web_address_that_cannot_be_used_gets_one_clear_line() {
    // Held (listening) until the monitor has tried it.
    let taken = common::Ports::free(1);
    let addr = format!("127.0.0.1:{}", taken.base());
    let out = Command::new(env!("CARGO_BIN_EXE_formation"))
        .args(["node", "monitor", "--scenario", SCENARIO, "--web", &addr, "--open-timeout", "2"])
        .output()
        .expect("formation monitor");
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "exit status; stderr: {err}");
    assert!(err.contains(&format!("--web {addr}: cannot listen there")), "stderr: {err}");
    drop(taken);
    for (bad, says) in
        [("--web=localhost", "invalid value 'localhost' for '--web"), ("--web-linger=-1", "--web-linger")]
    {
        let out = Command::new(env!("CARGO_BIN_EXE_formation"))
            .args(["node", "monitor", "--scenario", SCENARIO, bad])
            .output()
            .expect("formation monitor");
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{bad}: exit status; stderr: {err}");
        let first = err.lines().next().unwrap_or_default();
        assert!(first.contains(says), "{bad}: the first line should name the option: {err}");
    }
}

/// Issue 50's membership on the live page: a lock-step quorum start
/// without follower 4 (`--absent 4`) in which follower 3 leaves at 1 s
/// (`--leave 3@1`): once the run is over the page's table marks follower
/// 4's row "absent at the start" and follower 3's "left at 1.000 s …",
/// both greyed (class `left`), and no other row.
#[test]
fn the_live_page_marks_the_rows_of_followers_absent_and_gone() {
    let test = "the_live_page_marks_the_rows_of_followers_absent_and_gone";
    let Some((chromium, chromedriver)) = browser_or_skip(test) else { return };
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("run");
    let page_port = common::Ports::free(1).release();
    let web = format!("127.0.0.1:{page_port}");
    let base = common::Ports::free(common::LAUNCH_PORTS).release().to_string();
    let members = ["--quorum", "3", "--quorum-wait", "1", "--absent", "4", "--leave", "3@1"];
    let page_flags = ["--base-port", &base, "--run", "web-members", "--web", &web, "--web-linger", "20"];
    let mut g = Group::launch(&out, &["duration=6"], &[&members[..], &page_flags[..]].concat());
    wait_for_port(page_port, LIMIT);
    let a = Browser::start(&chromium, &chromedriver, common::Ports::free(1).release());
    a.goto(&format!("http://{web}/"));
    const ROWS: &str = r#"
        const v = window.formationView;
        if (!v || !v.ended) return null;
        return [...document.querySelectorAll('#rows tr')].map((tr) =>
            [tr.children[0].textContent, tr.className, (tr.querySelector('.mark') || {}).textContent || '']);
    "#;
    let t = Instant::now();
    let rows = loop {
        let r = a.exec(ROWS);
        if !r.is_null() {
            break r;
        }
        assert!(t.elapsed() < Duration::from_secs(90), "the page did not see the run end");
        std::thread::sleep(Duration::from_millis(200));
    };
    let rows: Vec<[String; 3]> = serde_json::from_value(rows).expect("rows");
    let row = |name: &str| rows.iter().find(|r| r[0].starts_with(name)).unwrap_or_else(|| panic!("{rows:?}")).clone();
    let [_, class3, mark3] = row("follower 3");
    assert!(mark3.starts_with("left at 1.000 s (") && class3 == "left", "follower 3's row: {rows:?}");
    let [_, class4, mark4] = row("follower 4");
    assert!(mark4 == "absent at the start" && class4 == "left", "follower 4's row: {rows:?}");
    for name in ["leader", "follower 1", "follower 2"] {
        assert_eq!(row(name)[2], "", "{name}'s row is marked: {rows:?}");
    }
    drop(a);
    let status = g.wait(LIMIT);
    assert!(status.success(), "formation launch --web: {status}");
    g.assert_group_empty();
}
