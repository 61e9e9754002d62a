//! Network namespaces for `formation lab`: every node (router, leader,
//! agents, monitor) runs in its own Linux network namespace with one `eth0`
//! on 10.77.0.0/16, cabled by a veth pair to a bridge that lives in a
//! dedicated switch namespace. Faults are then physical: a host's cable is
//! unplugged (its switch-side veth taken down) or an nftables table in its
//! namespace drops a share of its packets at random.
//!
//! Nothing is created in, or sent to, the machine's own namespace: the
//! bridge is in the switch namespace and each veth pair is created directly
//! between the switch and the host namespace. Namespaces are named
//! `flab-<pid>-<n>-<host>` and `flab-<pid>-<n>-sw`, so labs of several
//! threads and processes coexist and leftovers of dead processes can be
//! swept. Needs `ip` (iproute2) and, for [`Lab::set_loss`], `nft`.
//!
//! Without root, the lab runs inside `unshare --user --map-root-user --net
//! --mount` ([`reexec`], then [`prepare_unshared`] first thing inside): there
//! the process is root of its own user namespace, which is enough for `ip
//! netns`, veths, bridges and nftables once `/run/netns` is a private tmpfs.

use std::fs;
use std::net::Ipv4Addr;
use std::os::unix::fs::MetadataExt;
use std::path::Path;
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Once, OnceLock};
use std::time::Duration;

/// What went wrong building, changing or removing the lab's network: the
/// command and what it said.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct LabError(pub String);

impl From<LabError> for formation_exit::Error {
    /// The lab's network could not be built or changed: the run failed.
    fn from(e: LabError) -> Self {
        formation_exit::Error::Run(e.0)
    }
}

/// TCP's minimum retransmission timeout on the lab's subnet (Linux's
/// default is 200 ms, for the Internet). On a LAN with a round trip of
/// 0.1 ms, a lost segment is resent after 5 ms, then 10, 20, …: with 30 %
/// loss on a host's link a lock-step run was otherwise held for seconds,
/// once past its 60 s stall timeout, by TCP backing off from 200 ms (a
/// round trip fails with p ≈ 0.51 there: 9 failures in a row wait 102 s).
/// Hosts of a real control network can set the same per route:
/// `ip route replace <subnet> dev <if> rto_min 5ms`.
pub const RTO_MIN: &str = "5ms";

/// Prefix of every namespace a lab creates.
const PREFIX: &str = "flab-";
/// Where `ip netns` keeps the named namespaces (bind mounts of nsfs files).
const NETNS_DIR: &str = "/run/netns";
/// Longest host name accepted, so namespace names stay readable.
const MAX_NAME: usize = 20;
/// Hosts addressable as 10.77.(i/250).(i%250 + 2).
const MAX_HOSTS: usize = 250 * 256;
/// The `<n>` of the next lab of this process.
static NEXT_LAB: AtomicU32 = AtomicU32::new(0);

/// The command prefix that runs a program as root of its own user namespace,
/// with its own network and mount namespaces (mounts not propagated back).
pub const UNSHARE: [&str; 7] = ["unshare", "--user", "--map-root-user", "--net", "--mount", "--propagation", "private"];
/// Set by [`reexec`] on the re-run process, so it calls [`prepare_unshared`]
/// instead of re-running itself again.
pub const UNSHARED_ENV: &str = "FORMATION_LAB_UNSHARED";

/// How the lab can build namespaces.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Privilege {
    /// Effective uid 0 (real root, or root of a user namespace): build directly.
    Root,
    /// Not root, but unprivileged user namespaces work: re-run under [`reexec`].
    Unshare,
}

/// How this process can build a lab, or one line saying why it cannot.
pub fn privilege() -> Result<Privilege, LabError> {
    let why = |r: LabError| {
        LabError(format!(
            "formation lab needs root or unprivileged user namespaces (unshare --user --map-root-user --net): {r}"
        ))
    };
    let uid = euid().ok_or_else(|| why(LabError("cannot read the effective uid from /proc/self".into())))?;
    run(Command::new("ip").arg("-V")).map_err(why)?;
    if uid == 0 {
        return Ok(Privilege::Root);
    }
    run(Command::new(UNSHARE[0]).args(&UNSHARE[1..]).arg("true")).map_err(why)?;
    Ok(Privilege::Unshare)
}

/// Whether every part of the lab can run here as root, namespaces built
/// directly and faults performed with nftables (what the lab's tests and
/// `formation verify` need), or one line saying why not.
pub fn root_lab() -> Result<(), LabError> {
    let nft = Command::new("nft").arg("--version").output().is_ok_and(|o| o.status.success());
    match privilege()? {
        Privilege::Root if nft => Ok(()),
        Privilege::Root => Err(LabError("`nft` (nftables) is missing".into())),
        Privilege::Unshare => Err(LabError("not root".into())),
    }
}

/// The effective uid: the second field of /proc/self/status's `Uid:` line,
/// else the owner of /proc/self.
fn euid() -> Option<u32> {
    let status = fs::read_to_string("/proc/self/status").ok();
    let line = status.as_deref().and_then(|s| s.lines().find(|l| l.starts_with("Uid:")).map(str::to_owned));
    match line.and_then(|l| l.split_whitespace().nth(2).and_then(|u| u.parse().ok())) {
        Some(uid) => Some(uid),
        None => fs::metadata("/proc/self").ok().map(|m| m.uid()),
    }
}

/// A Command re-running this executable with the same arguments under
/// [`UNSHARE`] and with [`UNSHARED_ENV`] set; the caller runs it and exits
/// with its status (used when [`privilege`] is [`Privilege::Unshare`]).
pub fn reexec() -> Result<Command, LabError> {
    let exe =
        std::env::current_exe().map_err(|e| LabError(format!("cannot find this executable to re-run it: {e}")))?;
    let mut cmd = Command::new(UNSHARE[0]);
    cmd.args(&UNSHARE[1..]).arg(exe).args(std::env::args_os().skip(1)).env(UNSHARED_ENV, "1");
    Ok(cmd)
}

/// Gives `ip netns` a private, writable /run/netns inside [`UNSHARE`]: a
/// tmpfs on it, or on /run when /run/netns does not exist (an unprivileged
/// user cannot create it; /run is then empty for this process tree only).
/// Refuses in the initial user namespace, where it would shadow the
/// machine's own mounts. Idempotent.
pub fn prepare_unshared() -> Result<(), LabError> {
    static DONE: OnceLock<Result<(), LabError>> = OnceLock::new();
    DONE.get_or_init(|| {
        let map = fs::read_to_string("/proc/self/uid_map").map_err(|e| LabError(format!("/proc/self/uid_map: {e}")))?;
        if map.split_whitespace().eq(["0", "0", "4294967295"]) {
            return Err(LabError(format!(
                "prepare_unshared must run inside `{}`, not in the initial user namespace",
                UNSHARE.join(" ")
            )));
        }
        if Path::new(NETNS_DIR).is_dir() {
            run(Command::new("mount").args(["-t", "tmpfs", "tmpfs", NETNS_DIR]))?;
        } else {
            run(Command::new("mount").args(["-t", "tmpfs", "tmpfs", "/run"]))?;
            fs::create_dir(NETNS_DIR).map_err(|e| LabError(format!("mkdir {NETNS_DIR}: {e}")))?;
        }
        Ok(())
    })
    .clone()
}

/// One host of a lab.
struct Host {
    name: String,
    ns: String,
    addr: Ipv4Addr,
}

/// A switch namespace with a bridge and one namespace per host; every
/// namespace (and so every process left in one) is removed on drop.
pub struct Lab {
    switch: String,
    hosts: Vec<Host>,
    /// Namespaces created and not yet removed.
    live: Vec<String>,
}

impl Lab {
    /// Creates the switch namespace with a bridge and one namespace per host
    /// name (order = index for addresses); on failure removes what it made.
    pub fn create(names: &[&str]) -> Result<Lab, LabError> {
        validate(names)?;
        // A namespace of this pid before our first lab is a leftover of a dead
        // process that had the same pid; run once, before any lab of ours exists.
        static OWN_LEFTOVERS: Once = Once::new();
        OWN_LEFTOVERS.call_once(|| {
            let me = std::process::id();
            lab_namespaces().iter().filter(|(pid, _)| *pid == me).for_each(|(_, ns)| drop(remove(ns)));
        });
        let base = format!("{PREFIX}{}-{}", std::process::id(), NEXT_LAB.fetch_add(1, Ordering::Relaxed));
        let hosts = names
            .iter()
            .enumerate()
            .map(|(i, n)| Host { name: n.to_string(), ns: format!("{base}-{n}"), addr: host_addr(i) })
            .collect();
        let mut lab = Lab { switch: format!("{base}-sw"), hosts, live: Vec::new() };
        match lab.build() {
            Ok(()) => Ok(lab),
            Err(e) => Err(match lab.teardown() {
                Ok(()) => e,
                Err(t) => LabError(format!("{e}; and then: {t}")),
            }),
        }
    }

    fn build(&mut self) -> Result<(), LabError> {
        let sw = self.switch.clone();
        ip(&["netns", "add", &sw])?;
        self.live.push(sw.clone());
        ip(&["-n", &sw, "link", "add", "br0", "type", "bridge"])?;
        ip(&["-n", &sw, "link", "set", "br0", "up"])?;
        for i in 0..self.hosts.len() {
            let (ns, cidr, port) = (self.hosts[i].ns.clone(), format!("{}/16", self.hosts[i].addr), format!("v{i}"));
            ip(&["netns", "add", &ns])?;
            self.live.push(ns.clone());
            ip(&["-n", &sw, "link", "add", &port, "type", "veth", "peer", "name", "eth0", "netns", &ns])?;
            ip(&["-n", &sw, "link", "set", &port, "master", "br0", "up"])?;
            ip(&["-n", &ns, "addr", "add", &cidr, "dev", "eth0"])?;
            ip(&["-n", &ns, "link", "set", "eth0", "up"])?;
            ip(&["-n", &ns, "link", "set", "lo", "up"])?;
            // A LAN's TCP: see RTO_MIN.
            let (addr, net) = (self.hosts[i].addr.to_string(), format!("{}/16", Ipv4Addr::new(10, 77, 0, 0)));
            ip(&["-n", &ns, "route", "replace", &net, "dev", "eth0", "src", &addr, "rto_min", RTO_MIN])?;
        }
        Ok(())
    }

    fn host(&self, name: &str) -> Result<(usize, &Host), LabError> {
        self.hosts
            .iter()
            .enumerate()
            .find(|(_, h)| h.name == name)
            .ok_or_else(|| LabError(format!("no host {name:?} in this lab")))
    }

    /// The host's address on 10.77.0.0/16.
    pub fn addr(&self, name: &str) -> Option<Ipv4Addr> {
        self.host(name).ok().map(|(_, h)| h.addr)
    }

    /// The host's network namespace, as `ip netns` names it.
    pub fn namespace(&self, name: &str) -> Option<&str> {
        self.host(name).ok().map(|(_, h)| h.ns.as_str())
    }

    /// A Command that runs `program` inside the host's namespace (`ip netns
    /// exec NS program`, which execs it: the child's pid is the program's);
    /// the caller adds args. For an unknown host the command fails when run,
    /// `ip` naming the missing namespace.
    pub fn command(&self, name: &str, program: &Path) -> Command {
        let ns = self.namespace(name).map_or_else(|| format!("{PREFIX}no-such-host-{name}"), str::to_owned);
        let mut cmd = Command::new("ip");
        cmd.args(["netns", "exec", &ns]).arg(program);
        cmd
    }

    /// Takes the host's link down or up (its veth end in the switch
    /// namespace), like unplugging its cable: its `eth0` loses carrier.
    pub fn set_link(&self, name: &str, up: bool) -> Result<(), LabError> {
        let (i, _) = self.host(name)?;
        ip(&["-n", &self.switch, "link", "set", &format!("v{i}"), if up { "up" } else { "down" }]).map(drop)
    }

    /// Drops `percent` (0..=100, may be fractional, resolution 0.01) of the
    /// host's packets at random in both directions on its `eth0` (an
    /// nftables table `inet flab` in its namespace; ARP is not affected, its
    /// own loopback neither); None removes the rule. Replaces atomically.
    pub fn set_loss(&self, name: &str, percent: Option<f64>) -> Result<(), LabError> {
        let (_, h) = self.host(name)?;
        // "table X; delete table X" removes it whether or not it exists.
        let mut script = String::from("table inet flab; delete table inet flab");
        if let Some(p) = percent {
            if !(0.0..=100.0).contains(&p) {
                return Err(LabError(format!("packet loss for {name} must be 0..=100 %, not {p}")));
            }
            let cut = (p * 100.0).round() as u32; // numgen draws 0..=9999
            let verdict =
                if cut >= 10_000 { "drop".to_string() } else { format!("numgen random mod 10000 < {cut} drop") };
            if cut > 0 {
                script += &format!(
                    "; add table inet flab\
                     ; add chain inet flab in {{ type filter hook input priority 0; }}\
                     ; add chain inet flab out {{ type filter hook output priority 0; }}\
                     ; add rule inet flab in iifname \"eth0\" {verdict}\
                     ; add rule inet flab out oifname \"eth0\" {verdict}"
                );
            }
        }
        run(Command::new("ip").args(["netns", "exec", &h.ns, "nft", &script])).map(drop)
    }

    /// Drops every packet between the host and `peer` (both directions, an
    /// nftables table `inet flabcut` in the host's namespace), or lets them
    /// through again: a partition between the two, the rest of the
    /// host's traffic untouched.
    pub fn set_cut(&self, name: &str, peer: &str, cut: bool) -> Result<(), LabError> {
        let (_, h) = self.host(name)?;
        let (_, p) = self.host(peer)?;
        let mut script = String::from("table inet flabcut; delete table inet flabcut");
        if cut {
            script += &format!(
                "; add table inet flabcut\
                 ; add chain inet flabcut in {{ type filter hook input priority 0; }}\
                 ; add chain inet flabcut out {{ type filter hook output priority 0; }}\
                 ; add rule inet flabcut in ip saddr {0} drop\
                 ; add rule inet flabcut out ip daddr {0} drop",
                p.addr
            );
        }
        run(Command::new("ip").args(["netns", "exec", &h.ns, "nft", &script])).map(drop)
    }

    /// Drops `percent` of the packets between the host and `peer` at random
    /// (both directions; an nftables table `inet flabslow` in the host's
    /// namespace): a bad cable between the two. Over TCP nothing is lost,
    /// but what the drops hold up arrives late.
    pub fn set_slow(&self, name: &str, peer: &str, percent: f64) -> Result<(), LabError> {
        let (_, h) = self.host(name)?;
        let (_, p) = self.host(peer)?;
        if !(0.0..=100.0).contains(&percent) {
            return Err(LabError(format!("packet loss between {name} and {peer} must be 0..=100 %, not {percent}")));
        }
        let cut = (percent * 100.0).round() as u32; // numgen draws 0..=9999
        let script = format!(
            "table inet flabslow; delete table inet flabslow\
             ; add table inet flabslow\
             ; add chain inet flabslow in {{ type filter hook input priority 0; }}\
             ; add chain inet flabslow out {{ type filter hook output priority 0; }}\
             ; add rule inet flabslow in ip saddr {0} numgen random mod 10000 < {cut} drop\
             ; add rule inet flabslow out ip daddr {0} numgen random mod 10000 < {cut} drop",
            p.addr
        );
        run(Command::new("ip").args(["netns", "exec", &h.ns, "nft", &script])).map(drop)
    }

    /// Kills every process still in the lab's namespaces (SIGKILL via `ip
    /// netns pids`), deletes every namespace (which removes the veths and
    /// the bridge). Idempotent; returns what it could not remove.
    pub fn teardown(&mut self) -> Result<(), LabError> {
        let mut failed = Vec::new();
        self.live.retain(|ns| match remove(ns) {
            Ok(()) => false,
            Err(e) => {
                failed.push(e.0);
                true
            }
        });
        if failed.is_empty() {
            Ok(())
        } else {
            Err(LabError(failed.join("; ")))
        }
    }
}

impl Drop for Lab {
    fn drop(&mut self) {
        let _ = self.teardown();
    }
}

/// Removes namespaces left by a lab process that no longer exists (names
/// carry the owner's pid); returns the names removed.
pub fn sweep_stale() -> Vec<String> {
    let me = std::process::id();
    let mut gone: Vec<String> = lab_namespaces()
        .into_iter()
        .filter(|(pid, _)| *pid != me && !Path::new(&format!("/proc/{pid}")).exists())
        .filter_map(|(_, ns)| remove(&ns).ok().map(|()| ns))
        .collect();
    gone.sort();
    gone
}

/// Host i's address: 10.77.(i/250).(i%250 + 2).
pub fn host_addr(i: usize) -> Ipv4Addr {
    Ipv4Addr::new(10, 77, (i / 250) as u8, (i % 250 + 2) as u8)
}

/// Host names: [a-z0-9-], 1 to 20 characters, unique, not `sw` (the switch).
fn validate(names: &[&str]) -> Result<(), LabError> {
    if names.len() > MAX_HOSTS {
        return Err(LabError(format!("a lab has at most {MAX_HOSTS} hosts, not {}", names.len())));
    }
    for (i, n) in names.iter().enumerate() {
        let why = if n.is_empty()
            || n.len() > MAX_NAME
            || !n.bytes().all(|b| matches!(b, b'a'..=b'z' | b'0'..=b'9' | b'-'))
        {
            "use 1 to 20 of [a-z0-9-]"
        } else if *n == "sw" {
            "reserved for the switch"
        } else if names[..i].contains(n) {
            "given twice"
        } else {
            continue;
        };
        return Err(LabError(format!("bad lab host name {n:?}: {why}")));
    }
    Ok(())
}

/// Every lab namespace with its owner's pid.
fn lab_namespaces() -> Vec<(u32, String)> {
    let Ok(dir) = fs::read_dir(NETNS_DIR) else { return Vec::new() };
    dir.flatten()
        .filter_map(|e| {
            let ns = e.file_name().into_string().ok()?;
            let pid = ns.strip_prefix(PREFIX)?.split('-').next()?.parse().ok()?;
            Some((pid, ns))
        })
        .collect()
}

/// SIGKILLs the processes in `ns` (a few rounds, in case one forked) and
/// deletes it; a namespace already gone counts as removed.
fn remove(ns: &str) -> Result<(), LabError> {
    let me = std::process::id().to_string();
    for _ in 0..5 {
        let listed = ip(&["netns", "pids", ns]).unwrap_or_default();
        let pids: Vec<&str> = listed.split_whitespace().filter(|p| *p != me).collect();
        if pids.is_empty() {
            break;
        }
        let _ = run(Command::new("kill").arg("-KILL").args(&pids));
        std::thread::sleep(Duration::from_millis(20));
    }
    match ip(&["netns", "delete", ns]) {
        Err(e) if Path::new(NETNS_DIR).join(ns).exists() => Err(e),
        _ => Ok(()),
    }
}

fn ip(args: &[&str]) -> Result<String, LabError> {
    run(Command::new("ip").args(args))
}

/// Runs `cmd` to completion; its stdout, or one line with the command line,
/// its exit status and its stderr.
fn run(cmd: &mut Command) -> Result<String, LabError> {
    let line: Vec<_> = std::iter::once(cmd.get_program()).chain(cmd.get_args()).map(|a| a.to_string_lossy()).collect();
    let line = line.join(" ");
    let out = cmd.stdin(Stdio::null()).output().map_err(|e| LabError(format!("`{line}`: {e}")))?;
    if out.status.success() {
        return Ok(String::from_utf8_lossy(&out.stdout).into_owned());
    }
    let err = String::from_utf8_lossy(&out.stderr);
    let err: Vec<&str> = err.lines().map(str::trim).filter(|l| !l.is_empty()).collect();
    Err(LabError(format!("`{line}` failed ({}): {}", out.status, err.join(" / "))))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::process::Output;

    /// Whether a lab can be built here; prints why not. Under [`reexec`]-style
    /// runs ([`UNSHARED_ENV`] set) prepares the private /run/netns first.
    fn ready(test: &str) -> bool {
        let why = if std::env::var_os(UNSHARED_ENV).is_some() { prepare_unshared().err() } else { None };
        let why = why.or_else(|| match privilege() {
            Ok(Privilege::Root) => None,
            Ok(Privilege::Unshare) => {
                Some(LabError(format!("not root; run the test binary under `{UNSHARED_ENV}=1 {}`", UNSHARE.join(" "))))
            }
            Err(e) => Some(e),
        });
        let why =
            why.or_else(|| ["ping -V", "nft -v"].iter().find_map(|c| run(Command::new("sh").args(["-c", c])).err()));
        if let Some(why) = &why {
            eprintln!("{test}: skipped: {why}");
        }
        why.is_none()
    }

    fn ping(lab: &Lab, from: &str, to: &str, args: &[&str]) -> Output {
        let addr = lab.addr(to).expect("host").to_string();
        lab.command(from, Path::new("ping")).args(args).arg(addr).output().expect("ping runs")
    }

    fn pings(lab: &Lab, from: &str, to: &str) -> bool {
        ping(lab, from, to, &["-c1", "-W1"]).status.success()
    }

    /// Share of `count` fast pings lost, from ping's summary line.
    fn loss(lab: &Lab, from: &str, to: &str, count: u32) -> f64 {
        let out = ping(lab, from, to, &["-q", "-i", "0.01", "-W1", "-c", &count.to_string()]);
        let text = String::from_utf8_lossy(&out.stdout);
        let received: u32 = text
            .split(',')
            .find_map(|f| f.trim().strip_suffix(" received").and_then(|n| n.parse().ok()))
            .unwrap_or_else(|| panic!("no summary in {text:?}"));
        1.0 - received as f64 / count as f64
    }

    fn listed() -> String {
        String::from_utf8_lossy(&Command::new("ip").args(["netns", "list"]).output().expect("ip runs").stdout)
            .into_owned()
    }

    fn names(lab: &Lab) -> Vec<String> {
        lab.live.clone()
    }

    fn all_gone(names: &[String]) -> bool {
        let list = listed();
        names.iter().all(|n| !list.split_whitespace().any(|l| l == n))
    }

    #[test]
    fn addresses_and_names() {
        assert_eq!(host_addr(0), Ipv4Addr::new(10, 77, 0, 2));
        assert_eq!(host_addr(249), Ipv4Addr::new(10, 77, 0, 251));
        assert_eq!(host_addr(250), Ipv4Addr::new(10, 77, 1, 2));
        assert!(validate(&["router", "leader", "monitor", "agent-3"]).is_ok());
        for (bad, names) in [
            ("Leader", &["router", "Leader"][..]),
            ("agent_1", &["agent_1"]),
            ("", &[""]),
            ("a23456789012345678901", &["a23456789012345678901"]),
            ("agent-1", &["agent-1", "agent-1"]),
            ("sw", &["sw"]),
        ] {
            let e = validate(names).expect_err(bad);
            assert!(e.0.contains(&format!("{bad:?}")), "{e}");
        }
    }

    #[test]
    fn pings_links_and_loss() {
        if !ready("pings_links_and_loss") {
            return;
        }
        let hosts = ["router", "leader", "agent-1"];
        let lab = Lab::create(&hosts).expect("lab");
        assert_eq!(lab.addr("agent-1"), Some(Ipv4Addr::new(10, 77, 0, 4)));
        assert!(lab.namespace("leader").is_some_and(|ns| ns.starts_with(PREFIX) && ns.ends_with("-leader")));
        assert_eq!(lab.addr("nobody"), None);
        for from in hosts {
            for to in hosts {
                assert!(pings(&lab, from, to), "{from} -> {to}");
            }
        }
        lab.set_link("leader", false).expect("down");
        assert!(!pings(&lab, "router", "leader"));
        assert!(!pings(&lab, "leader", "agent-1"));
        assert!(pings(&lab, "router", "agent-1"));
        lab.set_link("leader", true).expect("up");
        assert!(pings(&lab, "router", "leader"));

        lab.set_loss("leader", Some(100.0)).expect("loss 100");
        assert!(!pings(&lab, "router", "leader"));
        assert!(pings(&lab, "router", "agent-1"));
        lab.set_loss("leader", None).expect("no loss");
        assert!(pings(&lab, "router", "leader"));
        lab.set_loss("leader", None).expect("no loss twice");

        // 30 % each way: a round trip survives with 0.7² = 49 %.
        lab.set_loss("leader", Some(30.0)).expect("loss 30");
        let lost = loss(&lab, "router", "leader", 200);
        assert!((0.35..=0.67).contains(&lost), "lost {lost}");
        lab.set_loss("leader", Some(0.0)).expect("loss 0");
        assert_eq!(loss(&lab, "router", "leader", 50), 0.0);
        assert!(lab.set_loss("leader", Some(101.0)).is_err());
        assert!(lab.set_loss("nobody", None).is_err());
        assert!(lab.set_link("nobody", true).is_err());
    }

    #[test]
    fn teardown_kills_and_removes() {
        if !ready("teardown_kills_and_removes") {
            return;
        }
        let mut lab = Lab::create(&["router", "monitor"]).expect("lab");
        let made = names(&lab);
        assert_eq!(made.len(), 3);
        let mut child = lab.command("monitor", Path::new("sleep")).arg("100").spawn().expect("sleep");
        std::thread::sleep(Duration::from_millis(200));
        let pids = ip(&["netns", "pids", lab.namespace("monitor").expect("ns")]).expect("pids");
        assert!(pids.split_whitespace().any(|p| p == child.id().to_string()), "{pids}");
        lab.teardown().expect("teardown");
        lab.teardown().expect("teardown twice");
        let status = child.wait().expect("wait");
        assert!(!status.success(), "{status}");
        assert!(all_gone(&made), "{}", listed());
        let mut gone = lab.command("monitor", Path::new("true"));
        assert!(!gone.stderr(Stdio::null()).status().expect("ip runs").success());
    }

    #[test]
    fn dropped_in_panicking_thread() {
        if !ready("dropped_in_panicking_thread") {
            return;
        }
        let (tx, rx) = std::sync::mpsc::channel();
        let joined = std::thread::spawn(move || {
            let lab = Lab::create(&["agent-1", "agent-2"]).expect("lab");
            tx.send(names(&lab)).expect("send");
            panic!("deliberate panic with a lab alive");
        })
        .join();
        assert!(joined.is_err());
        let made = rx.recv().expect("names");
        assert!(all_gone(&made), "{}", listed());
    }

    #[test]
    fn sweeps_dead_owners() {
        if !ready("sweeps_dead_owners") {
            return;
        }
        let mut child = Command::new("true").spawn().expect("true");
        let dead = child.id();
        child.wait().expect("wait");
        let stale = format!("{PREFIX}{dead}-0-router");
        ip(&["netns", "add", &stale]).expect("add");
        let mine = Lab::create(&["router"]).expect("lab");
        // Another test process sweeping at the same time may get it first.
        let swept = sweep_stale();
        assert!(all_gone(&[stale]), "{swept:?} {}", listed());
        assert!(!swept.iter().any(|n| n.starts_with(&format!("{PREFIX}{}-", std::process::id()))), "{swept:?}");
        assert!(!all_gone(&names(&mine)), "sweep removed a live lab");
    }

    #[test]
    fn create_rejects_bad_names_without_leftovers() {
        let e = Lab::create(&["router", "Router"]).err().expect("rejected");
        assert!(e.0.contains("\"Router\""), "{e}");
    }
}
