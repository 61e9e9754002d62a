//! A node's files in a certificate folder, checked at start: the
//! authority, the node's certificate (issued by the authority, for this
//! node, valid now, not revoked) and key (matching it), and the policy
//! (signed by the authority). Each problem is one line.
//!
//! The folder's layout: `DIR/ca/` holds the authority's certificate and
//! key; `DIR/<node>/` holds the authority's certificate, the node's
//! certificate and key, the policy, its signature and the revocation list.

use std::path::{Path, PathBuf};

use serde_json::Value;

/// A TLS identity or policy that cannot be used: the file and what is wrong with it.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct IdentityError(pub String);

/// The authority's certificate and key in a certificate folder.
pub const CA_CERT: &str = "ca.pem";
pub const CA_KEY: &str = "ca.key";
/// The authority's own folder in what `formation certs` writes: its key,
/// which no node needs, stays there.
pub const CA_DIR: &str = "ca";
/// The access-control policy in a certificate folder.
pub const POLICY: &str = "policy.json5";
/// The authority's signature of the policy: a certificate it issued to
/// [`POLICY_SUBJECT`] that names the policy's SHA-256 ([`policy_digest_name`]).
pub const POLICY_CERT: &str = "policy.pem";
pub const POLICY_SUBJECT: &str = "formation policy";
/// The authority's certificate revocation list.
pub const CRL: &str = "revoked.crl";
/// The folder that holds `name`'s files: `DIR/<name>/` (what `formation
/// certs` writes), or `DIR` itself (a node's folder copied to its host).
pub fn node_dir(dir: &Path, name: &str) -> PathBuf {
    let sub = dir.join(name);
    if sub.is_dir() {
        sub
    } else {
        dir.to_path_buf()
    }
}

/// The DNS name a policy certificate carries for a policy file: the file's
/// SHA-256 in hex, in two labels of 32 (a label holds at most 63).
pub fn policy_digest_name(policy: &[u8]) -> String {
    use sha2::Digest;
    let hex: String = sha2::Sha256::digest(policy).iter().map(|b| format!("{b:02x}")).collect();
    format!("{}.{}.sha256.formation-policy", &hex[..32], &hex[32..])
}

/// A node's files in a certificate folder, checked.
#[derive(Clone, Debug)]
pub struct Identity {
    pub ca: PathBuf,
    pub cert: PathBuf,
    pub key: PathBuf,
    pub policy: Value,
    pub crl: PathBuf,
}

/// Checks `dir` for node `name`: the authority, the node's certificate
/// (issued by the authority, for this node, valid now, not revoked) and key
/// (matching it), and the policy (signed by the authority). Each problem is
/// one line.
pub fn identity(dir: &Path, name: &str) -> Result<Identity, IdentityError> {
    use x509_parser::prelude::*;
    let top = dir;
    let dir = &node_dir(top, name);
    let (ca, cert, key) = (dir.join(CA_CERT), dir.join(format!("{name}.pem")), dir.join(format!("{name}.key")));
    if top.join(CA_KEY).exists() && !dir.join(POLICY_CERT).exists() {
        return Err(IdentityError(format!(
            "--tls {}: made by an older `formation certs` (the authority's key beside the nodes' files, no signed \
             policy): make it again with `formation certs SCENARIO --out {} --force`",
            top.display(),
            top.display()
        )));
    }
    if !ca.exists() && top.join(CA_DIR).join(CA_CERT).exists() && !dir.join(format!("{name}.pem")).exists() {
        return Err(IdentityError(format!(
            "--tls {}: no folder {name}/ for node {name} (run `formation certs` with the scenario of this run)",
            top.display()
        )));
    }
    let read = |p: &Path| -> Result<Vec<u8>, IdentityError> {
        std::fs::read(p)
            .map_err(|e| IdentityError(format!("--tls {}: cannot read {}: {e}", dir.display(), p.display())))
    };
    let pem_of = |p: &Path, bytes: &[u8]| -> Result<Pem, IdentityError> {
        let (_, pem) =
            parse_x509_pem(bytes).map_err(|e| IdentityError(format!("{}: not a PEM certificate: {e}", p.display())))?;
        Ok(pem)
    };
    let ca_bytes = read(&ca)?;
    let ca_pem = pem_of(&ca, &ca_bytes)?;
    let ca_x509 =
        ca_pem.parse_x509().map_err(|e| IdentityError(format!("{}: not a certificate: {e}", ca.display())))?;
    let cert_bytes = read(&cert)?;
    let cert_pem = pem_of(&cert, &cert_bytes)?;
    let x509 =
        cert_pem.parse_x509().map_err(|e| IdentityError(format!("{}: not a certificate: {e}", cert.display())))?;
    let cn = x509.subject().iter_common_name().next().and_then(|c| c.as_str().ok()).unwrap_or("").to_string();
    if cn != name {
        return Err(IdentityError(format!("{} is the certificate of {cn:?}, not of {name}", cert.display())));
    }
    if x509.verify_signature(Some(ca_x509.public_key())).is_err() {
        return Err(IdentityError(format!("{} was not issued by the authority {}", cert.display(), ca.display())));
    }
    let now = ASN1Time::now();
    let validity = x509.validity();
    if now < validity.not_before {
        return Err(IdentityError(format!(
            "{} is not valid yet: valid from {} (now {})",
            cert.display(),
            validity.not_before,
            now
        )));
    }
    if now > validity.not_after {
        return Err(IdentityError(format!("{} expired on {} (now {})", cert.display(), validity.not_after, now)));
    }
    let key_text = String::from_utf8(read(&key)?)
        .map_err(|_| IdentityError(format!("{}: not a PEM private key", key.display())))?;
    let public =
        public_key_of(&key_text).map_err(|e| IdentityError(format!("{}: not a private key: {e}", key.display())))?;
    if public != x509.public_key().subject_public_key.data[..] {
        return Err(IdentityError(format!("{} is not the key of {}", key.display(), cert.display())));
    }
    let policy_path = dir.join(POLICY);
    let policy_bytes = read(&policy_path)?;
    signed_policy(dir, &policy_path, &policy_bytes, &ca_x509, &read)?;
    let text =
        String::from_utf8(policy_bytes).map_err(|_| IdentityError(format!("{}: not UTF-8", policy_path.display())))?;
    let policy: Value = json5::from_str(&text).map_err(|e| IdentityError(format!("{}: {e}", policy_path.display())))?;
    let crl = dir.join(CRL);
    not_revoked(&crl, &read(&crl)?, &ca_x509, &x509, name)?;
    Ok(Identity { ca, cert, key, policy, crl })
}

/// The policy file is the one the authority signed: `policy.pem` was issued
/// by it to [`POLICY_SUBJECT`] and names the file's SHA-256.
fn signed_policy(
    dir: &Path,
    policy_path: &Path,
    policy: &[u8],
    ca: &x509_parser::certificate::X509Certificate<'_>,
    read: &dyn Fn(&Path) -> Result<Vec<u8>, IdentityError>,
) -> Result<(), IdentityError> {
    use x509_parser::prelude::*;
    let sig_path = dir.join(POLICY_CERT);
    let bytes = read(&sig_path)?;
    let refused = |why: &str| {
        IdentityError(format!(
            "{} is refused: {why} (a policy that is not the authority's is never loaded; run `formation certs` again)",
            policy_path.display()
        ))
    };
    let (_, pem) =
        parse_x509_pem(&bytes).map_err(|_| refused(&format!("{} is not a certificate", sig_path.display())))?;
    let x509 = pem.parse_x509().map_err(|_| refused(&format!("{} is not a certificate", sig_path.display())))?;
    let cn = x509.subject().iter_common_name().next().and_then(|c| c.as_str().ok()).unwrap_or("");
    if cn != POLICY_SUBJECT || x509.verify_signature(Some(ca.public_key())).is_err() {
        return Err(refused(&format!("{} is not the authority's signature of a policy", sig_path.display())));
    }
    let want = policy_digest_name(policy);
    let names: Vec<String> = x509
        .subject_alternative_name()
        .ok()
        .flatten()
        .map(|san| {
            san.value
                .general_names
                .iter()
                .filter_map(|g| match g {
                    GeneralName::DNSName(n) => Some(n.to_string()),
                    _ => None,
                })
                .collect()
        })
        .unwrap_or_default();
    if !names.contains(&want) {
        return Err(refused(&format!(
            "it is not the file the authority signed ({} names another SHA-256)",
            sig_path.display()
        )));
    }
    Ok(())
}

/// The node's certificate is not on the authority's revocation list (which
/// must be the authority's).
fn not_revoked(
    crl_path: &Path,
    bytes: &[u8],
    ca: &x509_parser::certificate::X509Certificate<'_>,
    cert: &x509_parser::certificate::X509Certificate<'_>,
    name: &str,
) -> Result<(), IdentityError> {
    use x509_parser::prelude::*;
    let bad = |why: String| IdentityError(format!("{}: {why}", crl_path.display()));
    let (_, pem) = parse_x509_pem(bytes).map_err(|e| bad(format!("not a PEM revocation list: {e}")))?;
    let (_, crl) = parse_x509_crl(&pem.contents).map_err(|e| bad(format!("not a revocation list: {e}")))?;
    if crl.verify_signature(ca.public_key()).is_err() {
        return Err(bad("not signed by the authority".into()));
    }
    if let Some(r) = crl.iter_revoked_certificates().find(|r| r.raw_serial() == cert.raw_serial()) {
        return Err(IdentityError(format!(
            "{name}'s certificate (serial {}) was revoked on {}: this node may not join (issue it a new one with \
             `formation certs SCENARIO --out DIR --node {name}`)",
            cert.raw_serial_as_string(),
            r.revocation_date
        )));
    }
    Ok(())
}

/// The public key of a PKCS#8 private key in PEM, as a certificate's
/// subject public key carries it: Ed25519, ECDSA P-256 or P-384, or RSA,
/// the kinds `formation certs` and rcgen make. An error reads as rcgen's
/// did when it read the key.
fn public_key_of(pem_text: &str) -> Result<Vec<u8>, String> {
    use ring::signature::{self, EcdsaKeyPair, Ed25519KeyPair, KeyPair as _, RsaKeyPair};
    use rustls_pki_types::PrivateKeyDer;
    let pem = pem::parse(pem_text).map_err(|e| format!("PEM error: {e}"))?;
    let could_not = || "Could not parse key pair".to_string();
    let Ok(PrivateKeyDer::Pkcs8(pkcs8)) = PrivateKeyDer::try_from(pem.contents()) else {
        return Err(could_not());
    };
    let der = pkcs8.secret_pkcs8_der();
    let rng = ring::rand::SystemRandom::new();
    let ecdsa = |alg| EcdsaKeyPair::from_pkcs8(alg, der, &rng).map(|k| k.public_key().as_ref().to_vec());
    if let Ok(k) = Ed25519KeyPair::from_pkcs8_maybe_unchecked(der) {
        Ok(k.public_key().as_ref().to_vec())
    } else if let Ok(k) = ecdsa(&signature::ECDSA_P256_SHA256_ASN1_SIGNING) {
        Ok(k)
    } else if let Ok(k) = ecdsa(&signature::ECDSA_P384_SHA384_ASN1_SIGNING) {
        Ok(k)
    } else if let Ok(k) = RsaKeyPair::from_pkcs8(der) {
        Ok(k.public_key().as_ref().to_vec())
    } else {
        Err(could_not())
    }
}

#[cfg(test)]
mod tests {
    use super::public_key_of;

    /// The key check reads a key as rcgen did when it was the check: the
    /// same public key for every kind `formation certs` can make, and the
    /// same words for what is not a key.
    #[test]
    fn public_key_of_agrees_with_rcgen() {
        for alg in [&rcgen::PKCS_ECDSA_P256_SHA256, &rcgen::PKCS_ECDSA_P384_SHA384, &rcgen::PKCS_ED25519] {
            let key = rcgen::KeyPair::generate_for(alg).expect("a key");
            let public = public_key_of(&key.serialize_pem()).expect("a key read back");
            assert_eq!(public, rcgen::PublicKeyData::der_bytes(&key), "{alg:?}");
        }
        let not_a_key = "-----BEGIN PRIVATE KEY-----\nAAEC\n-----END PRIVATE KEY-----\n";
        for text in ["", "not PEM at all", not_a_key] {
            let rcgen_says = rcgen::KeyPair::from_pem(text).expect_err("not a key").to_string();
            assert_eq!(public_key_of(text).expect_err("not a key"), rcgen_says, "{text:?}");
        }
    }
}
