//! Identities and permissions for a secure deployment.
//!
//! `formation certs SCENARIO --out DIR` makes a certificate authority and,
//! for every node of the scenario (`router`, `leader`, `monitor`,
//! `agent-<id>`), a key and a certificate whose subject common name is the
//! node's name, valid for the addresses the node listens on (loopback, the
//! lab's, and any `--san`). It also writes `policy.json5`: zenoh access
//! control derived from the topology, so that a node may publish only its
//! own estimate and telemetry and receive only what its role needs.
//!
//! With `--tls DIR`, a node checks its files at start ([`identity`]), and
//! its session runs mutual TLS with the authority as the only trust root,
//! TLS-only links, and the policy ([`zenoh_tls`]).

use std::net::IpAddr;
use std::path::{Path, PathBuf};

use crate::error::Error;

use formation_net::identity::{policy, CA_CERT, CA_KEY, POLICY};
use formation_net::names::node_names;

/// `formation certs`.
#[derive(clap::Args, Debug, Clone)]
pub struct CertsArgs {
    #[command(flatten)]
    pub scenario: crate::args::ScenarioArgs,
    /// Folder for the authority, the nodes' keys and certificates and the
    /// policy. An authority already there is used, never replaced.
    #[arg(long, value_name = "DIR", required_unless_present = "policy")]
    pub out: Option<PathBuf>,
    /// Another address (IP or DNS name) that every node's certificate is
    /// valid for, e.g. the LAN address of the host that runs the router or a
    /// peer (repeatable). Loopback and the lab's addresses are always in.
    #[arg(long = "san", value_name = "ADDRESS")]
    pub san: Vec<String>,
    /// How long the certificates are valid, in days.
    #[arg(long, default_value_t = 365, value_name = "DAYS")]
    pub days: u32,
    /// First day of validity, YYYY-MM-DD [default: now]. With --days, makes
    /// expired or not-yet-valid certificates (for testing that they are refused).
    #[arg(long, value_name = "DATE")]
    pub not_before: Option<String>,
    /// Only (re)issue these nodes' certificates (repeatable) [default: every node].
    #[arg(long = "node", value_name = "NAME")]
    pub nodes: Vec<String>,
    /// Print the access-control policy derived from the topology and write nothing.
    #[arg(long)]
    pub policy: bool,
}

/// The lab's addresses of a node, in client mode (with a router, host
/// index i) and in peer mode (no router, index i − 1).
fn lab_addresses(index: usize) -> Vec<IpAddr> {
    let mut v = vec![IpAddr::V4(crate::lab::netns::host_addr(index))];
    if index > 0 {
        v.push(IpAddr::V4(crate::lab::netns::host_addr(index - 1)));
    }
    v
}

/// `formation certs`.
pub fn run(a: &CertsArgs) -> Result<(), Error> {
    let scenario = a.scenario.load().map_err(|e| Error::Input(e.to_string()))?;
    let policy = policy(&scenario);
    if a.policy {
        println!("{}", serde_json::to_string_pretty(&policy).unwrap_or_default());
        return Ok(());
    }
    let Some(dir) = a.out.as_deref() else {
        return Err(Error::Input("--out DIR is required (or --policy to print the policy)".into()));
    };
    if a.days == 0 || a.days > MAX_DAYS {
        return Err(Error::Input(format!("--days {}: must be from 1 to {MAX_DAYS} (100 years)", a.days)));
    }
    let not_before = match &a.not_before {
        None => time::OffsetDateTime::now_utc() - time::Duration::minutes(5),
        Some(d) => parse_date(d).ok_or_else(|| {
            Error::Input(format!(
                "--not-before {d:?}: expected a date YYYY-MM-DD from {FIRST_YEAR}-01-01 to {LAST_YEAR}-12-31"
            ))
        })?,
    };
    let not_after = not_before
        .checked_add(time::Duration::days(i64::from(a.days)))
        .filter(|t| t.year() <= LAST_YEAR)
        .ok_or_else(|| {
            Error::Input(format!(
                "--not-before {} with --days {}: the certificates would end after {LAST_YEAR}-12-31, the last date a certificate can hold",
                day(not_before),
                a.days
            ))
        })?;
    let names = node_names(&scenario);
    for n in &a.nodes {
        if !names.contains(n) {
            return Err(Error::Input(format!("--node {n}: the scenario's nodes are {}", names.join(", "))));
        }
    }
    let mut extra = Vec::new();
    for s in &a.san {
        extra.push(san(s)?);
    }
    std::fs::create_dir_all(dir).map_err(|e| Error::Run(format!("creating {}: {e}", dir.display())))?;

    let (issuer, made) = authority(dir, not_before)?;
    println!("{} authority {}", if made { "made the" } else { "using the existing" }, dir.join(CA_CERT).display());
    for (index, name) in names.iter().enumerate() {
        if !a.nodes.is_empty() && !a.nodes.contains(name) {
            continue;
        }
        let mut sans: Vec<rcgen::SanType> = vec![
            rcgen::SanType::IpAddress("127.0.0.1".parse().expect("an address")),
            rcgen::SanType::IpAddress("::1".parse().expect("an address")),
            san("localhost").expect("a name"),
        ];
        sans.extend(lab_addresses(index).into_iter().map(rcgen::SanType::IpAddress));
        sans.extend(extra.iter().cloned());
        let mut p = rcgen::CertificateParams::default();
        p.distinguished_name.push(rcgen::DnType::CommonName, name.as_str());
        p.subject_alt_names = sans;
        p.not_before = not_before;
        p.not_after = not_after;
        p.use_authority_key_identifier_extension = true;
        p.key_usages = vec![rcgen::KeyUsagePurpose::DigitalSignature];
        // A peer both listens and dials: it needs both.
        p.extended_key_usages =
            vec![rcgen::ExtendedKeyUsagePurpose::ServerAuth, rcgen::ExtendedKeyUsagePurpose::ClientAuth];
        let key = rcgen::KeyPair::generate().map_err(|e| Error::Run(format!("making {name}'s key: {e}")))?;
        let cert = p.signed_by(&key, &issuer).map_err(|e| Error::Run(format!("signing {name}'s certificate: {e}")))?;
        write_private(&dir.join(format!("{name}.key")), &key.serialize_pem())?;
        write(&dir.join(format!("{name}.pem")), &cert.pem())?;
        println!("  {name}: {name}.pem, {name}.key (valid {} to {})", day(not_before), day(not_after));
    }
    let text = format!(
        "// zenoh access control for scenario {:?}, made by `formation certs` from its topology.\n\
         // Every node loads it with --tls; edit the scenario and run `formation certs` again instead.\n{}\n",
        scenario.name,
        serde_json::to_string_pretty(&policy).unwrap_or_default()
    );
    write(&dir.join(POLICY), &text)?;
    println!("  {POLICY}: who may publish and receive what");
    Ok(())
}

/// Longest validity `--days` accepts.
const MAX_DAYS: u32 = 36_500;
/// The years a `--not-before` date and a certificate's end may fall in
/// (X.509 dates end at 9999-12-31).
const FIRST_YEAR: i32 = 1970;
const LAST_YEAR: i32 = 9999;

/// A `--san` value: an IP address, or a DNS name (labels of letters, digits
/// and '-', at most 63 characters each and 253 in all).
fn san(s: &str) -> Result<rcgen::SanType, Error> {
    if let Ok(ip) = s.parse::<IpAddr>() {
        return Ok(rcgen::SanType::IpAddress(ip));
    }
    let label_ok = |l: &str| {
        !l.is_empty()
            && l.len() <= 63
            && !l.starts_with('-')
            && !l.ends_with('-')
            && l.chars().all(|c| c.is_ascii_alphanumeric() || c == '-')
    };
    if s.is_empty() || s.len() > 253 || !s.split('.').all(label_ok) {
        return Err(Error::Input(format!(
            "--san {s:?}: not an IP address or a DNS name (letters, digits, '-' and '.', e.g. robot-3.lab or 192.168.1.20)"
        )));
    }
    s.to_string()
        .try_into()
        .map(rcgen::SanType::DnsName)
        .map_err(|e| Error::Input(format!("--san {s}: not an address or DNS name: {e}")))
}

fn parse_date(s: &str) -> Option<time::OffsetDateTime> {
    let mut it = s.split('-');
    let (y, m, d) = (it.next()?.parse().ok()?, it.next()?.parse::<u8>().ok()?, it.next()?.parse().ok()?);
    if it.next().is_some() || !(FIRST_YEAR..=LAST_YEAR).contains(&y) {
        return None;
    }
    let date = time::Date::from_calendar_date(y, time::Month::try_from(m).ok()?, d).ok()?;
    Some(date.midnight().assume_utc())
}

fn day(t: time::OffsetDateTime) -> String {
    format!("{:04}-{:02}-{:02}", t.year(), u8::from(t.month()), t.day())
}

/// The folder's authority, made if there is none (`true`), used if there is
/// one with its key, refused if only half of it is there.
fn authority(
    dir: &Path,
    not_before: time::OffsetDateTime,
) -> Result<(rcgen::Issuer<'static, rcgen::KeyPair>, bool), Error> {
    let (cert_path, key_path) = (dir.join(CA_CERT), dir.join(CA_KEY));
    match (cert_path.exists(), key_path.exists()) {
        (true, true) => {
            let key = read(&key_path)?;
            let key = rcgen::KeyPair::from_pem(&key)
                .map_err(|e| Error::Input(format!("{}: not a private key: {e}", key_path.display())))?;
            let pem = read(&cert_path)?;
            let issuer = rcgen::Issuer::from_ca_cert_pem(&pem, key)
                .map_err(|e| Error::Input(format!("{}: not a certificate: {e}", cert_path.display())))?;
            Ok((issuer, false))
        }
        (false, false) => {
            let mut p = rcgen::CertificateParams::default();
            p.distinguished_name.push(rcgen::DnType::CommonName, "formation certificate authority");
            p.is_ca = rcgen::IsCa::Ca(rcgen::BasicConstraints::Unconstrained);
            p.key_usages = vec![
                rcgen::KeyUsagePurpose::KeyCertSign,
                rcgen::KeyUsagePurpose::CrlSign,
                rcgen::KeyUsagePurpose::DigitalSignature,
            ];
            p.not_before = not_before.min(time::OffsetDateTime::now_utc() - time::Duration::minutes(5));
            p.not_after = time::OffsetDateTime::now_utc() + time::Duration::days(10 * 365);
            let key = rcgen::KeyPair::generate().map_err(|e| Error::Run(format!("making the authority's key: {e}")))?;
            let cert = p.self_signed(&key).map_err(|e| Error::Run(format!("signing the authority: {e}")))?;
            write_private(&key_path, &key.serialize_pem())?;
            write(&cert_path, &cert.pem())?;
            Ok((rcgen::Issuer::new(p, key), true))
        }
        (true, false) => Err(Error::Input(format!(
            "{} is there without its key {}: not replacing an authority (move the folder away to make a new one)",
            cert_path.display(),
            key_path.display()
        ))),
        (false, true) => Err(Error::Input(format!(
            "{} is there without its certificate {}: not replacing an authority (move the folder away to make a new one)",
            key_path.display(),
            cert_path.display()
        ))),
    }
}

fn read(path: &Path) -> Result<String, Error> {
    std::fs::read_to_string(path).map_err(|e| Error::Input(format!("reading {}: {e}", path.display())))
}

fn write(path: &Path, text: &str) -> Result<(), Error> {
    std::fs::write(path, text).map_err(|e| Error::Run(format!("writing {}: {e}", path.display())))
}

/// Writes a private key readable by its owner only (created 0600, not
/// chmod-ed after the fact).
fn write_private(path: &Path, text: &str) -> Result<(), Error> {
    use std::io::Write;
    use std::os::unix::fs::OpenOptionsExt;
    let _ = std::fs::remove_file(path);
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(0o600)
        .open(path)
        .map_err(|e| Error::Run(format!("writing {}: {e}", path.display())))?;
    f.write_all(text.as_bytes()).map_err(|e| Error::Run(format!("writing {}: {e}", path.display())))
}
