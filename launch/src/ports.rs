//! Loopback ports for the nodes of a launch, chosen so that launches and
//! tests running at once on one machine never pick the same one.
//!
//! A port the operating system picks (`bind 127.0.0.1:0`) comes from its
//! ephemeral range (`net.ipv4.ip_local_port_range`), where every outgoing
//! connection also takes its local port: between the moment a launch lets
//! go of its pick and the moment its node binds it, another process's
//! outgoing link can take it ("Address already in use", CI of stop 75). So:
//!
//! - ports come from below the ephemeral range (10,000 up), where only a
//!   listener takes a port;
//! - each is claimed by a lock on a file of its own in the temporary
//!   folder ([`claim`]), held for as long as the launch runs: another
//!   launch, or a test choosing ports for one, skips a claimed port even
//!   in the instant nothing listens on it;
//! - and each is bound once while it is chosen: a port some other program
//!   listens on fails and the next is tried.

use std::fs::{File, OpenOptions};
use std::net::TcpListener;
use std::path::PathBuf;

use formation_exit::Error;

/// The lowest port handed out: well-known and registered services below.
pub const LOWEST: u16 = 10_000;

/// The folder of the claim files, `formation-ports` in the temporary folder.
pub fn claims_folder() -> PathBuf {
    std::env::temp_dir().join("formation-ports")
}

/// The first port of the kernel's ephemeral range (32768 when it cannot be read).
pub fn ephemeral_low() -> u16 {
    std::fs::read_to_string("/proc/sys/net/ipv4/ip_local_port_range")
        .ok()
        .and_then(|t| t.split_whitespace().next().and_then(|x| x.parse::<u16>().ok()))
        .unwrap_or(32768)
}

/// A claim on `port`: its lock file, locked; None when another process
/// holds it. The claim lasts as long as the file is open. A folder this
/// process cannot write (another user's) claims nothing and refuses
/// nothing: the bind check alone then guards the port.
pub fn claim(port: u16) -> Option<Option<File>> {
    static MADE: std::sync::Once = std::sync::Once::new();
    let dir = claims_folder();
    MADE.call_once(|| {
        if std::fs::create_dir_all(&dir).is_ok() {
            use std::os::unix::fs::PermissionsExt;
            // Every user's launches share the folder, as they share the ports.
            let _ = std::fs::set_permissions(&dir, std::fs::Permissions::from_mode(0o1777));
        }
    });
    let Ok(file) = OpenOptions::new().create(true).truncate(false).write(true).open(dir.join(format!("{port}.lock")))
    else {
        return Some(None);
    };
    match file.try_lock() {
        Ok(()) => Some(Some(file)),
        Err(std::fs::TryLockError::WouldBlock) => None,
        Err(std::fs::TryLockError::Error(_)) => Some(None),
    }
}

/// Ports chosen for a launch, claimed until this value is dropped.
pub struct Lease {
    pub ports: Vec<u16>,
    _claims: Vec<File>,
}

impl Lease {
    /// Ports the user gave (`--base-port`): used as given, each claimed
    /// where no one else holds it (a test that chose them holds them).
    pub fn given(ports: Vec<u16>) -> Self {
        let claims = ports.iter().filter_map(|&p| claim(p).flatten()).collect();
        Lease { ports, _claims: claims }
    }
}

/// `count` free loopback ports below the ephemeral range, not necessarily
/// consecutive, claimed for as long as the [`Lease`] lives. The search
/// starts where this process's id says, so that launches started at once
/// do not all try the same ports first.
pub fn free(count: usize) -> Result<Lease, Error> {
    let high = ephemeral_low();
    if high <= LOWEST {
        return Err(Error::Run(format!("no loopback ports below the ephemeral range (it starts at {high})")));
    }
    let span = u32::from(high - LOWEST);
    let start = std::process::id() % span;
    let (mut ports, mut claims, mut held) = (Vec::new(), Vec::new(), Vec::new());
    for i in 0..span {
        if ports.len() == count {
            break;
        }
        let port = LOWEST + ((start + i) % span) as u16;
        let Some(lock) = claim(port) else { continue };
        // Held until every port is chosen: none is tried twice.
        let Ok(listener) = TcpListener::bind(("127.0.0.1", port)) else { continue };
        ports.push(port);
        claims.extend(lock);
        held.push(listener);
    }
    if ports.len() < count {
        return Err(Error::Run(format!(
            "finding free loopback ports: only {} of {count} free in {LOWEST}..{high} (give --base-port)",
            ports.len()
        )));
    }
    Ok(Lease { ports, _claims: claims })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two leases taken at once share no port, and a claimed port is
    /// refused to another claimant until its lease is dropped.
    #[test]
    fn leases_taken_at_once_share_no_port_and_a_claim_ends_with_its_lease() {
        let a = free(6).expect("lease a");
        let b = free(6).expect("lease b");
        assert_eq!(a.ports.len(), 6);
        let shared: Vec<u16> = a.ports.iter().filter(|p| b.ports.contains(p)).copied().collect();
        assert!(shared.is_empty(), "ports {shared:?} handed to both leases");
        assert!(a.ports.iter().all(|&p| (LOWEST..ephemeral_low()).contains(&p)), "{:?}", a.ports);
        // A lock is per open file: this process's second open is refused too.
        let p = a.ports[0];
        assert!(claim(p).is_none(), "port {p} claimed twice");
        drop(a);
        assert!(claim(p).is_some(), "port {p} still claimed after its lease ended");
    }
}
