//! Writing a certificate folder (`formation certs`): an authority and,
//! for every node, a key and a certificate whose subject common name is the
//! node's name, valid for the addresses the node listens on (loopback, the
//! lab's, and any `--san`); the access-control policy, signed by the
//! authority; and the authority's revocation list.
//!
//! Nothing in DIR changes before everything has been checked ([`plan`]: no
//! symbolic link, no file where a folder goes, folders this user can read
//! and write), and the new `ca/` and node folders are written beside the
//! old ones (in `DIR/.certs-new-<pid>`) and replace them, one rename per
//! folder, only once all are complete; the old ones are removed last.

use std::net::IpAddr;
use std::path::{Path, PathBuf};

use formation_exit::Error;

use crate::identity::{policy_digest_name, CA_CERT, CA_DIR, CA_KEY, CRL, POLICY, POLICY_CERT, POLICY_SUBJECT};

/// One node of the folder.
#[derive(Clone, Debug)]
pub struct NodeCert {
    /// The node's name: its certificate's common name and its folder.
    pub name: String,
    /// Addresses its certificate is valid for besides loopback and the
    /// request's `san` (the lab's).
    pub addresses: Vec<IpAddr>,
}

/// What to write: the options of `formation certs`.
#[derive(Clone, Debug)]
pub struct Request<'a> {
    /// The folder to write.
    pub dir: &'a Path,
    /// Every node of the scenario, in the lab's host order.
    pub nodes: &'a [NodeCert],
    /// The scenario's name, for the policy file's header.
    pub scenario: &'a str,
    /// The access-control policy of the scenario's topology.
    pub policy: &'a serde_json::Value,
    /// `--san`: more addresses every node's certificate is valid for.
    pub san: &'a [String],
    /// `--days`.
    pub days: u32,
    /// `--not-before`, YYYY-MM-DD (None: now).
    pub not_before: Option<&'a str>,
    /// `--node`: only these nodes are issued certificates again.
    pub reissue: &'a [String],
    /// `--revoke`.
    pub revoke: &'a [String],
    /// `--force`: a new authority and new keys for every node.
    pub force: bool,
}

/// What was written, to tell the user.
#[derive(Clone, Debug, Default)]
pub struct Report {
    /// One line each: the authority, the revocations, every node issued.
    pub lines: Vec<String>,
    /// Something to warn about that did not stop the writing.
    pub warnings: Vec<String>,
}

/// Writes the folder `r` asks for: everything is checked before anything
/// is written, and the new folders are written beside the old ones, which
/// they replace only once all of them are complete.
pub fn write_folder(r: &Request<'_>) -> Result<Report, Error> {
    let validity = Validity::of(r.days, r.not_before)?;
    let names: Vec<String> = r.nodes.iter().map(|n| n.name.clone()).collect();
    for n in r.reissue.iter().chain(r.revoke) {
        if !names.contains(n) {
            let flag = if r.reissue.contains(n) { "--node" } else { "--revoke" };
            return Err(Error::Input(format!("{flag} {n}: the scenario's nodes are {}", names.join(", "))));
        }
    }
    let extra = r.san.iter().map(|s| san(s)).collect::<Result<Vec<_>, _>>()?;
    let changing = !r.reissue.is_empty() || !r.revoke.is_empty();
    if r.force && changing {
        return Err(Error::Input(
            "--force makes everything new: leave out --node and --revoke (or --force to change a few nodes)".into(),
        ));
    }
    let plan = plan(r.dir, &names, r.force, changing)?;
    let stage = Staging::new(r.dir, !plan.out_exists)?;
    let ca_old = r.dir.join(CA_DIR);
    let ca_new = stage.path.join(CA_DIR);
    make_dir(&ca_new)?;
    let (issuer, ca_pem) =
        if changing { existing_authority(&ca_old)? } else { new_authority(&ca_new, validity.not_before)? };
    let mut report = Report::default();
    report.lines.push(format!(
        "{} authority {} (keep {}/{CA_KEY} off the nodes' hosts)",
        if changing { "using the existing" } else { "made the" },
        ca_old.join(CA_CERT).display(),
        CA_DIR
    ));
    let now = time::OffsetDateTime::now_utc();
    let revoked = revocations(r, &ca_old, changing, now, &mut report.lines)?;
    write_revoked(&ca_new, &revoked)?;
    let crl = revocation_list(&issuer, &revoked, now)?;
    write(&ca_new.join(CRL), &crl)?;
    carry(&ca_old, &ca_new)?;
    let policy_text = format!(
        "// zenoh access control for scenario {:?}, made by `formation certs` from its topology and\n\
         // signed by the authority ({POLICY_CERT}): nodes refuse it once edited. Edit the scenario and run\n\
         // `formation certs` again instead.\n{}\n",
        r.scenario,
        serde_json::to_string_pretty(r.policy).unwrap_or_default()
    );
    let policy_cert = sign_policy(&issuer, policy_text.as_bytes(), validity.not_after)?;
    // A fresh or forced folder: every node; --node: those; --revoke alone: none.
    for node in r.nodes {
        let (name, folder) = (&node.name, stage.path.join(&node.name));
        make_dir(&folder)?;
        if !changing || r.reissue.contains(name) {
            issue(&folder, node, &extra, &validity, &issuer)?;
            report.lines.push(format!(
                "  {name}/: {name}.pem, {name}.key (valid {} to {})",
                day(validity.not_before),
                day(validity.not_after)
            ));
        }
        write(&folder.join(CA_CERT), &ca_pem)?;
        write(&folder.join(POLICY), &policy_text)?;
        write(&folder.join(POLICY_CERT), &policy_cert)?;
        write(&folder.join(CRL), &crl)?;
        carry(&r.dir.join(name), &folder)?;
    }
    report.warnings.extend(swap(r.dir, &stage.path, &plan.folders)?);
    stage.keep_out();
    report.lines.push(format!(
        "  every node's folder: {CA_CERT}, {POLICY} (who may publish and receive what) signed in {POLICY_CERT}, \
         {CRL} ({} revoked)",
        revoked.len()
    ));
    Ok(report)
}

/// The certificates' first and last moments.
struct Validity {
    not_before: time::OffsetDateTime,
    not_after: time::OffsetDateTime,
}

impl Validity {
    /// From `--days` and `--not-before` (None: five minutes ago).
    fn of(days: u32, not_before: Option<&str>) -> Result<Validity, Error> {
        if days == 0 || days > MAX_DAYS {
            return Err(Error::Input(format!("--days {days}: must be from 1 to {MAX_DAYS} (100 years)")));
        }
        let not_before = match not_before {
            None => time::OffsetDateTime::now_utc() - time::Duration::minutes(5),
            Some(d) => parse_date(d).ok_or_else(|| {
                Error::Input(format!(
                    "--not-before {d:?}: expected a date YYYY-MM-DD from {FIRST_YEAR}-01-01 to {LAST_YEAR}-12-31"
                ))
            })?,
        };
        let not_after = not_before
            .checked_add(time::Duration::days(i64::from(days)))
            .filter(|t| t.year() <= LAST_YEAR)
            .ok_or_else(|| {
                Error::Input(format!(
                    "--not-before {} with --days {days}: the certificates would end after {LAST_YEAR}-12-31, the last date a certificate can hold",
                    day(not_before),
                ))
            })?;
        Ok(Validity { not_before, not_after })
    }
}

/// The authority's revocations: those it had (a new authority has none),
/// the nodes `--revoke` names, and the previous certificate of every node
/// issued again; a line in `said` for each new one.
fn revocations(
    r: &Request<'_>,
    ca_old: &Path,
    changing: bool,
    now: time::OffsetDateTime,
    said: &mut Vec<String>,
) -> Result<Vec<Revoked>, Error> {
    let mut revoked = if changing { read_revoked(ca_old)? } else { Vec::new() };
    for name in r.revoke.iter().chain(r.reissue) {
        let cert = r.dir.join(name).join(format!("{name}.pem"));
        if let Some(serial) = serial_of(&cert)? {
            if !revoked.iter().any(|r| r.serial == serial) {
                revoked.push(Revoked { serial, name: name.clone(), at: now });
                said.push(format!("  revoked {name}'s certificate"));
            }
        }
    }
    Ok(revoked)
}

/// A new key and certificate for `node`, in `folder`.
fn issue(
    folder: &Path,
    node: &NodeCert,
    extra: &[rcgen::SanType],
    validity: &Validity,
    issuer: &rcgen::Issuer<'static, rcgen::KeyPair>,
) -> Result<(), Error> {
    let name = &node.name;
    let mut sans: Vec<rcgen::SanType> = vec![
        rcgen::SanType::IpAddress("127.0.0.1".parse().expect("an address")),
        rcgen::SanType::IpAddress("::1".parse().expect("an address")),
        san("localhost").expect("a name"),
    ];
    sans.extend(node.addresses.iter().copied().map(rcgen::SanType::IpAddress));
    sans.extend(extra.iter().cloned());
    let mut p = rcgen::CertificateParams::default();
    p.distinguished_name.push(rcgen::DnType::CommonName, name.as_str());
    p.subject_alt_names = sans;
    p.not_before = validity.not_before;
    p.not_after = validity.not_after;
    p.use_authority_key_identifier_extension = true;
    p.key_usages = vec![rcgen::KeyUsagePurpose::DigitalSignature];
    // A peer both listens and dials: it needs both.
    p.extended_key_usages =
        vec![rcgen::ExtendedKeyUsagePurpose::ServerAuth, rcgen::ExtendedKeyUsagePurpose::ClientAuth];
    let key = rcgen::KeyPair::generate().map_err(|e| Error::Run(format!("making {name}'s key: {e}")))?;
    let cert = p.signed_by(&key, issuer).map_err(|e| Error::Run(format!("signing {name}'s certificate: {e}")))?;
    write_private(&folder.join(format!("{name}.key")), &key.serialize_pem())?;
    write(&folder.join(format!("{name}.pem")), &cert.pem())
}

/// A revoked certificate, as `ca/revoked.txt` keeps it: `serial-hex name unix-seconds`.
struct Revoked {
    serial: Vec<u8>,
    name: String,
    at: time::OffsetDateTime,
}

/// What `certs` will replace: checked before anything is written.
struct Plan {
    /// Whether DIR is there already.
    out_exists: bool,
    /// The folders it writes, `ca` first, then every node's.
    folders: Vec<String>,
}

/// Checks every path `certs` will write or remove, and refuses in one line
/// before anything is changed: a symbolic link anywhere in DIR's folders
/// that certs writes (DIR itself, `ca/`, a node's folder, or any entry in
/// them), a file where a folder must be, a folder inside one (certs
/// replaces them whole), a folder it cannot read and write, or (for
/// --node and --revoke) no authority to use.
fn plan(dir: &Path, names: &[String], force: bool, changing: bool) -> Result<Plan, Error> {
    let out_exists = no_symlink(dir)?;
    if out_exists && !changing && !force && std::fs::read_dir(dir).map_or(false, |mut d| d.next().is_some()) {
        return Err(Error::Input(format!(
            "{} exists: --force replaces it (a new authority and new keys for every node), --node NAME reissues \
             one node, --revoke NAME revokes one",
            dir.display()
        )));
    }
    if out_exists {
        usable(dir)?;
    } else {
        let parent = match dir.parent() {
            Some(p) if !p.as_os_str().is_empty() => p,
            _ => Path::new("."),
        };
        if !parent.is_dir() {
            return Err(Error::Input(format!(
                "{}: the folder it would go in, {}, is not there",
                dir.display(),
                parent.display()
            )));
        }
        usable(parent)?;
    }
    let folders: Vec<String> = std::iter::once(CA_DIR.to_string()).chain(names.iter().cloned()).collect();
    for sub in &folders {
        let folder = dir.join(sub);
        if !no_symlink(&folder)? {
            continue;
        }
        usable(&folder)?;
        let entries =
            std::fs::read_dir(&folder).map_err(|e| Error::Input(format!("reading {}: {e}", folder.display())))?;
        for entry in entries {
            let path = entry.map_err(|e| Error::Input(format!("reading {}: {e}", folder.display())))?.path();
            let m = std::fs::symlink_metadata(&path)
                .map_err(|e| Error::Input(format!("reading {}: {e}", path.display())))?;
            if m.file_type().is_symlink() {
                return Err(link_refused(&path));
            }
            if !m.is_file() {
                return Err(Error::Input(format!(
                    "{} is {} inside {sub}/, which certs replaces whole: nothing was changed (move it out of {sub}/, \
                     then run again)",
                    path.display(),
                    if m.is_dir() { "a folder" } else { "not a plain file" }
                )));
            }
        }
    }
    if changing {
        let ca = dir.join(CA_DIR);
        let (cert, key) = (ca.join(CA_CERT), ca.join(CA_KEY));
        match (cert.is_file(), key.is_file()) {
            (true, true) => {}
            (false, false) => {
                return Err(Error::Input(format!(
                    "{}: no authority there ({}/{CA_KEY}): --node and --revoke change a folder `formation certs` made",
                    dir.display(),
                    CA_DIR
                )))
            }
            (true, false) => {
                return Err(Error::Input(format!(
                    "{} is there without its key {}: not replacing an authority (move the folder away to make a \
                     new one)",
                    cert.display(),
                    key.display()
                )))
            }
            (false, true) => {
                return Err(Error::Input(format!(
                    "{} is there without its certificate {}: not replacing an authority (move the folder away to \
                     make a new one)",
                    key.display(),
                    cert.display()
                )))
            }
        }
    }
    Ok(Plan { out_exists, folders })
}

/// Refuses a folder this user cannot read, enter and write.
fn usable(folder: &Path) -> Result<(), Error> {
    use std::os::unix::ffi::OsStrExt;
    let Ok(c) = std::ffi::CString::new(folder.as_os_str().as_bytes()) else {
        return Err(Error::Input(format!("{}: a path with a NUL byte", folder.display())));
    };
    // SAFETY: `c` is a NUL-terminated string that lives across the call.
    if unsafe { libc::access(c.as_ptr(), libc::R_OK | libc::W_OK | libc::X_OK) } != 0 {
        let e = std::io::Error::last_os_error();
        return Err(Error::Input(format!(
            "{}: this user cannot read and write it ({e}): nothing was changed",
            folder.display()
        )));
    }
    Ok(())
}

/// The one line for a symbolic link where certs would write or remove.
fn link_refused(path: &Path) -> Error {
    let to = std::fs::read_link(path).map(|t| format!(" (to {})", t.display())).unwrap_or_default();
    Error::Input(format!(
        "{}{to} is a symbolic link: certs never writes or removes anything through a link, and changed nothing \
         (move the link away, then run again)",
        path.display()
    ))
}

/// The folder inside DIR that the new authority and node folders are
/// written in before they replace the old ones. Removed on every path
/// (with DIR, if this run made it and nothing was put in it).
struct Staging {
    path: PathBuf,
    made_out: Option<PathBuf>,
}

impl Staging {
    fn new(dir: &Path, make_out: bool) -> Result<Staging, Error> {
        use std::os::unix::fs::DirBuilderExt;
        if make_out {
            make_dir(dir)?;
        }
        let path = dir.join(format!(".certs-new-{}", std::process::id()));
        if let Err(e) = std::fs::DirBuilder::new().mode(0o700).create(&path) {
            if make_out {
                let _ = std::fs::remove_dir(dir);
            }
            return Err(Error::Run(format!("creating {}: {e} (nothing was changed)", path.display())));
        }
        Ok(Staging { path, made_out: make_out.then(|| dir.to_path_buf()) })
    }

    /// The new folders are in DIR: keep it.
    fn keep_out(mut self) {
        self.made_out = None;
    }
}

impl Drop for Staging {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.path);
        if let Some(dir) = &self.made_out {
            let _ = std::fs::remove_dir(dir);
        }
    }
}

/// Copies into `new` every plain file of `old` that `new` does not have
/// (an untouched node's key and certificate, the authority's key with
/// --node or --revoke, anything else someone put there), and gives `new`
/// the permissions `old` had. Nothing if `old` is not there.
fn carry(old: &Path, new: &Path) -> Result<(), Error> {
    use std::io::Read;
    use std::os::unix::fs::{OpenOptionsExt, PermissionsExt};
    let entries = match std::fs::read_dir(old) {
        Ok(entries) => entries,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(e) => return Err(Error::Input(format!("reading {}: {e}", old.display()))),
    };
    for entry in entries {
        let from = entry.map_err(|e| Error::Input(format!("reading {}: {e}", old.display())))?.path();
        let Some(file) = from.file_name() else { continue };
        let to = new.join(file);
        if std::fs::symlink_metadata(&to).is_ok() {
            continue;
        }
        let m =
            std::fs::symlink_metadata(&from).map_err(|e| Error::Input(format!("reading {}: {e}", from.display())))?;
        if m.file_type().is_symlink() {
            return Err(link_refused(&from));
        }
        let mut bytes = Vec::new();
        std::fs::OpenOptions::new()
            .read(true)
            .custom_flags(libc::O_NOFOLLOW)
            .open(&from)
            .and_then(|mut f| f.read_to_end(&mut bytes))
            .map_err(|e| Error::Input(format!("reading {}: {e}", from.display())))?;
        write_mode(&to, &bytes, m.permissions().mode() & 0o777)?;
    }
    let m = std::fs::metadata(old).map_err(|e| Error::Input(format!("reading {}: {e}", old.display())))?;
    std::fs::set_permissions(new, std::fs::Permissions::from_mode(m.permissions().mode() & 0o777))
        .map_err(|e| Error::Run(format!("setting the permissions of {}: {e}", new.display())))
}

/// Puts the new `folders` (complete, in `stage`) in DIR: each old one is
/// moved aside first (into DIR/.certs-old-<pid>), and the old ones are
/// removed only once every new one is in place (if that fails, the warning
/// is returned). If a move fails, the moves done are undone.
fn swap(dir: &Path, stage: &Path, folders: &[String]) -> Result<Option<String>, Error> {
    use std::os::unix::fs::DirBuilderExt;
    let aside = dir.join(format!(".certs-old-{}", std::process::id()));
    std::fs::DirBuilder::new()
        .mode(0o700)
        .create(&aside)
        .map_err(|e| Error::Run(format!("creating {}: {e} (nothing was changed)", aside.display())))?;
    let mut moved: Vec<(PathBuf, PathBuf)> = Vec::new();
    let mut failed = None;
    'folders: for sub in folders {
        let current = dir.join(sub);
        let mut moves = Vec::new();
        if std::fs::symlink_metadata(&current).is_ok() {
            moves.push((current.clone(), aside.join(sub)));
        }
        moves.push((stage.join(sub), current));
        for (from, to) in moves {
            if let Err(e) = std::fs::rename(&from, &to) {
                failed = Some(format!("moving {} to {}: {e}", from.display(), to.display()));
                break 'folders;
            }
            moved.push((from, to));
        }
    }
    if let Some(why) = failed {
        let undone = moved.iter().rev().all(|(from, to)| std::fs::rename(to, from).is_ok());
        if undone {
            let _ = std::fs::remove_dir(&aside);
            return Err(Error::Run(format!("{why}: every folder was put back as it was")));
        }
        return Err(Error::Run(format!(
            "{why}, and putting the folders back failed: the old ones are in {}",
            aside.display()
        )));
    }
    Ok(std::fs::remove_dir_all(&aside).err().map(|e| {
        format!("warning: the new folders are in place, but removing the old ones in {} failed: {e}", aside.display())
    }))
}

/// The authority's signature of a policy: a certificate for [`POLICY_SUBJECT`]
/// that names the policy's SHA-256, PEM.
fn sign_policy(
    issuer: &rcgen::Issuer<'static, rcgen::KeyPair>,
    policy: &[u8],
    not_after: time::OffsetDateTime,
) -> Result<String, Error> {
    let mut p = rcgen::CertificateParams::default();
    p.distinguished_name.push(rcgen::DnType::CommonName, POLICY_SUBJECT);
    let digest = policy_digest_name(policy);
    p.subject_alt_names = vec![san(&digest)?];
    p.not_before = time::OffsetDateTime::now_utc() - time::Duration::minutes(5);
    p.not_after = not_after.max(p.not_before + time::Duration::days(1));
    p.use_authority_key_identifier_extension = true;
    let key = rcgen::KeyPair::generate().map_err(|e| Error::Run(format!("making the policy's key: {e}")))?;
    let cert = p.signed_by(&key, issuer).map_err(|e| Error::Run(format!("signing the policy: {e}")))?;
    Ok(cert.pem())
}

/// The serial of the certificate at `path`, if there is one.
fn serial_of(path: &Path) -> Result<Option<Vec<u8>>, Error> {
    use x509_parser::prelude::*;
    let Ok(bytes) = std::fs::read(path) else { return Ok(None) };
    let (_, pem) =
        parse_x509_pem(&bytes).map_err(|e| Error::Input(format!("{}: not a certificate: {e}", path.display())))?;
    let x509 = pem.parse_x509().map_err(|e| Error::Input(format!("{}: not a certificate: {e}", path.display())))?;
    Ok(Some(x509.raw_serial().to_vec()))
}

const REVOKED_LIST: &str = "revoked.txt";

fn read_revoked(ca_dir: &Path) -> Result<Vec<Revoked>, Error> {
    let path = ca_dir.join(REVOKED_LIST);
    let Ok(text) = std::fs::read_to_string(&path) else { return Ok(Vec::new()) };
    text.lines()
        .filter(|l| !l.trim().is_empty() && !l.starts_with('#'))
        .map(|l| {
            let bad = || Error::Input(format!("{}: cannot read the line {l:?}", path.display()));
            let mut f = l.split_whitespace();
            let (serial, name, at) = (f.next().ok_or_else(bad)?, f.next().ok_or_else(bad)?, f.next().ok_or_else(bad)?);
            let serial = (0..serial.len() / 2)
                .map(|i| u8::from_str_radix(serial.get(2 * i..2 * i + 2).unwrap_or("zz"), 16))
                .collect::<Result<Vec<u8>, _>>()
                .map_err(|_| bad())?;
            let at = at
                .parse::<i64>()
                .ok()
                .and_then(|t| time::OffsetDateTime::from_unix_timestamp(t).ok())
                .ok_or_else(bad)?;
            Ok(Revoked { serial, name: name.to_string(), at })
        })
        .collect()
}

fn write_revoked(ca_dir: &Path, revoked: &[Revoked]) -> Result<(), Error> {
    let mut text = String::from("# Certificates this authority revoked: serial (hex), node, when (unix seconds).\n");
    for r in revoked {
        let hex: String = r.serial.iter().map(|b| format!("{b:02x}")).collect();
        text.push_str(&format!("{hex} {} {}\n", r.name, r.at.unix_timestamp()));
    }
    write(&ca_dir.join(REVOKED_LIST), &text)
}

/// The authority's revocation list of `revoked`, PEM.
fn revocation_list(
    issuer: &rcgen::Issuer<'static, rcgen::KeyPair>,
    revoked: &[Revoked],
    now: time::OffsetDateTime,
) -> Result<String, Error> {
    let params = rcgen::CertificateRevocationListParams {
        this_update: now - time::Duration::minutes(5),
        next_update: now + time::Duration::days(MAX_DAYS.into()),
        crl_number: rcgen::SerialNumber::from(now.unix_timestamp().max(1) as u64),
        issuing_distribution_point: None,
        revoked_certs: revoked
            .iter()
            .map(|r| rcgen::RevokedCertParams {
                serial_number: rcgen::SerialNumber::from_slice(&r.serial),
                revocation_time: r.at,
                reason_code: None,
                invalidity_date: None,
            })
            .collect(),
        key_identifier_method: rcgen::KeyIdMethod::Sha256,
    };
    let crl = params.signed_by(issuer).map_err(|e| Error::Run(format!("signing the revocation list: {e}")))?;
    crl.pem().map_err(|e| Error::Run(format!("writing the revocation list: {e}")))
}

/// Whether `path` exists (as a real folder); a symbolic link there is refused.
fn no_symlink(path: &Path) -> Result<bool, Error> {
    match std::fs::symlink_metadata(path) {
        Err(_) => Ok(false),
        Ok(m) if m.file_type().is_symlink() => Err(link_refused(path)),
        Ok(m) if m.is_dir() => Ok(true),
        Ok(_) => Err(Error::Input(format!(
            "{} is a file, not a folder: nothing was changed (move it away, then run again)",
            path.display()
        ))),
    }
}

/// Creates a folder (0700) unless it is there; never through a symbolic link.
fn make_dir(path: &Path) -> Result<(), Error> {
    use std::os::unix::fs::DirBuilderExt;
    if no_symlink(path)? {
        return Ok(());
    }
    std::fs::DirBuilder::new()
        .mode(0o700)
        .create(path)
        .map_err(|e| Error::Run(format!("creating {}: {e}", path.display())))
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

/// The folder's authority (in `ca_dir`, both files there: [`plan`] checked),
/// and its certificate, PEM.
fn existing_authority(ca_dir: &Path) -> Result<(rcgen::Issuer<'static, rcgen::KeyPair>, String), Error> {
    let (cert_path, key_path) = (ca_dir.join(CA_CERT), ca_dir.join(CA_KEY));
    let key = read(&key_path)?;
    let key = rcgen::KeyPair::from_pem(&key)
        .map_err(|e| Error::Input(format!("{}: not a private key: {e}", key_path.display())))?;
    let pem = read(&cert_path)?;
    let issuer = rcgen::Issuer::from_ca_cert_pem(&pem, key)
        .map_err(|e| Error::Input(format!("{}: not a certificate: {e}", cert_path.display())))?;
    Ok((issuer, pem))
}

/// A new authority, written in `ca_dir`, and its certificate, PEM.
fn new_authority(
    ca_dir: &Path,
    not_before: time::OffsetDateTime,
) -> Result<(rcgen::Issuer<'static, rcgen::KeyPair>, String), Error> {
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
    write_private(&ca_dir.join(CA_KEY), &key.serialize_pem())?;
    let pem = cert.pem();
    write(&ca_dir.join(CA_CERT), &pem)?;
    Ok((rcgen::Issuer::new(p, key), pem))
}

fn read(path: &Path) -> Result<String, Error> {
    std::fs::read_to_string(path).map_err(|e| Error::Input(format!("reading {}: {e}", path.display())))
}

fn write(path: &Path, text: &str) -> Result<(), Error> {
    write_mode(path, text.as_bytes(), 0o644)
}

/// Writes a private key readable by its owner only (created 0600, not
/// chmod-ed after the fact).
fn write_private(path: &Path, text: &str) -> Result<(), Error> {
    write_mode(path, text.as_bytes(), 0o600)
}

/// Replaces the file at `path`: what was there (a file, or a symbolic link,
/// which is removed, never followed) goes first, and the new file is
/// created, never opened through a link (O_EXCL, O_NOFOLLOW).
fn write_mode(path: &Path, bytes: &[u8], mode: u32) -> Result<(), Error> {
    use std::io::Write;
    use std::os::unix::fs::OpenOptionsExt;
    if let Ok(m) = std::fs::symlink_metadata(path) {
        if m.is_dir() {
            return Err(Error::Input(format!("{} is a folder, not a file this command writes", path.display())));
        }
        std::fs::remove_file(path).map_err(|e| Error::Run(format!("replacing {}: {e}", path.display())))?;
    }
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .custom_flags(libc::O_NOFOLLOW)
        .mode(mode)
        .open(path)
        .map_err(|e| Error::Run(format!("writing {}: {e}", path.display())))?;
    f.write_all(bytes).map_err(|e| Error::Run(format!("writing {}: {e}", path.display())))
}
