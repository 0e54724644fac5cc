//! `supervisor certs`: a certificate authority and one certificate per host for the bridge's
//! mutual TLS (docs/security.md).
//!
//! - `ca.pem` / `ca.key`: the CA. Made on the first call, reused by the next ones (so robots
//!   added later are signed by the CA the base station already trusts).
//! - `<name>.pem` / `<name>.key`: a host's certificate, common name `<name>` (the bridge's
//!   `robot`, or the base station's name), signed by the CA, usable to listen and to connect
//!   (extended key usage server and client auth). Its subject alternative names are `<name>`,
//!   `localhost`, `127.0.0.1`, `::1` and every `--san` (the addresses other hosts dial: TLS checks
//!   the address a peer connects to against them).
//!
//! - `revoked.txt`: the revocation list, one host name per line (`#` starts a comment), made
//!   by `--revoke`. A bridge reads the list next to its `ca_certificate` (or the file its
//!   `tls.revoked` names) and watches it: a revoked host's links are refused after the TLS
//!   handshake and the access control leaves it out, from the next second on (by name: the CA
//!   keeps no revocation list of its own).
//!
//! Private keys are ECDSA P-256 (PKCS#8 PEM), written with mode 0600.

use std::path::{Path, PathBuf};

use anyhow::{Context as _, bail};
use rcgen::{
    BasicConstraints, CertificateParams, DnType, ExtendedKeyUsagePurpose, IsCa, Issuer, KeyPair, KeyUsagePurpose,
};

/// What `certs` is asked to make.
#[derive(Debug, Clone)]
pub struct CertsRequest {
    /// Directory of the CA and the certificates.
    pub dir: PathBuf,
    /// One certificate per name (letters, digits, `_ - .`).
    pub names: Vec<String>,
    /// Hosts to add to the revocation list.
    pub revoke: Vec<String>,
    /// Make a new live-view token (`viewer.token`).
    pub viewer_token: bool,
    /// Extra subject alternative names (IP addresses or DNS names) of every certificate made.
    pub sans: Vec<String>,
    /// Validity of the certificates, days from now.
    pub days: f64,
    /// Validity of a new CA, days from now.
    pub ca_days: f64,
}

/// A file `certs` wrote, for the report.
#[derive(Debug, Clone)]
pub struct Written {
    /// The certificate file.
    pub path: PathBuf,
    /// Its common name.
    pub name: String,
    /// Whether it replaced a certificate of the same name.
    pub replaced: bool,
    /// When it stops being valid (UTC, RFC 3339).
    pub not_after: String,
}

/// The outcome of `certs`.
#[derive(Debug, Clone)]
pub struct CertsReport {
    /// The CA's certificate file, and whether it was made by this call.
    pub ca: PathBuf,
    /// Whether the CA is new.
    pub ca_created: bool,
    /// The host certificates.
    pub written: Vec<Written>,
    /// The revocation list, when it was changed or a name made is on it.
    pub revocations: Option<Revocations>,
    /// The live-view token's file, when one was made.
    pub viewer_token: Option<PathBuf>,
}

/// Writes a new random token (24 bytes from the kernel's generator, hex) to `<dir>/viewer.token`.
fn make_token(dir: &Path) -> anyhow::Result<PathBuf> {
    use std::io::Read as _;
    let mut bytes = [0u8; 24];
    std::fs::File::open("/dev/urandom")
        .and_then(|mut f| f.read_exact(&mut bytes))
        .context("reading /dev/urandom for the token")?;
    let token: String = bytes.iter().map(|b| format!("{b:02x}")).collect();
    let path = dir.join("viewer.token");
    write_private(&path, &format!("{token}\n"))?;
    Ok(path)
}

/// What `--revoke` did.
#[derive(Debug, Clone)]
pub struct Revocations {
    /// The list's file.
    pub path: PathBuf,
    /// Names added now.
    pub added: Vec<String>,
    /// Names asked for that were on it already.
    pub already: Vec<String>,
    /// Certificates made now for names on the list (they stay refused).
    pub made_but_revoked: Vec<String>,
}

/// The names on a revocation list's text (one per line, `#` comments).
pub fn revoked_names(text: &str) -> Vec<String> {
    text.lines()
        .filter_map(|l| l.split('#').next())
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .map(String::from)
        .collect()
}

/// Adds `names` to the revocation list `<dir>/revoked.txt` (made if absent).
fn revoke(dir: &Path, names: &[String]) -> anyhow::Result<Revocations> {
    let path = dir.join("revoked.txt");
    let old = match std::fs::read_to_string(&path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            "# Hosts whose certificates are revoked: one name per line (supervisor certs --revoke NAME).\n\
             # Bridges watch this file and refuse a listed host from the moment it changes; delete a\n\
             # line to let the host in again.\n"
                .to_string()
        }
        Err(e) => return Err(e).with_context(|| format!("reading {}", path.display())),
    };
    let listed = revoked_names(&old);
    let now =
        time::OffsetDateTime::now_utc().format(&time::format_description::well_known::Rfc3339).unwrap_or_default();
    let (mut added, mut already, mut text) = (vec![], vec![], old.clone());
    for n in names {
        if listed.contains(n) || added.contains(n) {
            already.push(n.clone());
        } else {
            if !text.is_empty() && !text.ends_with('\n') {
                text.push('\n');
            }
            text += &format!("{n}  # revoked {now}\n");
            added.push(n.clone());
        }
    }
    if text != old {
        // Written whole and renamed into place: a bridge never reads half a list.
        let tmp = dir.join(".revoked.txt.tmp");
        std::fs::write(&tmp, &text).with_context(|| format!("writing {}", tmp.display()))?;
        std::fs::rename(&tmp, &path).with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(Revocations { path, added, already, made_but_revoked: vec![] })
}

fn name_ok(n: &str) -> bool {
    !n.is_empty() && n != "ca" && n.chars().all(|c| c.is_ascii_alphanumeric() || "_-.".contains(c))
}

fn when(days: f64) -> anyhow::Result<time::OffsetDateTime> {
    if !(days.is_finite() && days > 0.0 && days <= 36_500.0) {
        bail!("a validity of {days} days: give 0 < days <= 36500");
    }
    Ok(time::OffsetDateTime::now_utc() + time::Duration::seconds_f64(days * 86_400.0))
}

fn write_private(path: &Path, text: &str) -> anyhow::Result<()> {
    use std::io::Write as _;
    use std::os::unix::fs::OpenOptionsExt as _;
    // Removed first so that an existing file's wider mode does not survive.
    let _ = std::fs::remove_file(path);
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(0o600)
        .open(path)
        .with_context(|| format!("writing {}", path.display()))?;
    f.write_all(text.as_bytes()).with_context(|| format!("writing {}", path.display()))
}

/// Loads the CA of `dir`, or makes one.
fn ca(dir: &Path, ca_days: f64) -> anyhow::Result<(Issuer<'static, KeyPair>, bool)> {
    let (cert, key) = (dir.join("ca.pem"), dir.join("ca.key"));
    match (cert.exists(), key.exists()) {
        (true, true) => {
            let key_pem = std::fs::read_to_string(&key).with_context(|| format!("reading {}", key.display()))?;
            let cert_pem = std::fs::read_to_string(&cert).with_context(|| format!("reading {}", cert.display()))?;
            let key = KeyPair::from_pem(&key_pem).with_context(|| format!("{}: not a private key", key.display()))?;
            let issuer = Issuer::from_ca_cert_pem(&cert_pem, key)
                .with_context(|| format!("{}: not a CA certificate matching ca.key", cert.display()))?;
            Ok((issuer, false))
        }
        (false, false) => {
            let key = KeyPair::generate().context("generating the CA's key")?;
            let mut p = CertificateParams::new(Vec::<String>::new()).context("CA parameters")?;
            p.is_ca = IsCa::Ca(BasicConstraints::Constrained(0));
            p.key_usages =
                vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign, KeyUsagePurpose::DigitalSignature];
            p.distinguished_name.push(DnType::CommonName, "slam pipeline CA");
            p.not_before = time::OffsetDateTime::now_utc() - time::Duration::minutes(5);
            p.not_after = when(ca_days)?;
            let c = p.self_signed(&key).context("signing the CA")?;
            std::fs::write(&cert, c.pem()).with_context(|| format!("writing {}", cert.display()))?;
            write_private(&dir.join("ca.key"), &key.serialize_pem())?;
            Ok((Issuer::new(p, key), true))
        }
        (has_cert, _) => bail!(
            "{} has {} but not {}: restore the missing file, or remove both to make a new CA (every \
             certificate must then be made again)",
            dir.display(),
            if has_cert { "ca.pem" } else { "ca.key" },
            if has_cert { "ca.key" } else { "ca.pem" }
        ),
    }
}

/// Makes (or reuses) the CA of `req.dir` and a certificate for each name.
pub fn make(req: &CertsRequest) -> anyhow::Result<CertsReport> {
    if req.names.is_empty() && req.revoke.is_empty() && !req.viewer_token {
        bail!(
            "give at least one --name (the robots' `robot` names and the base station's), --revoke or --viewer-token"
        );
    }
    for (flag, list) in [("--name", &req.names), ("--revoke", &req.revoke)] {
        for n in list {
            if !name_ok(n) {
                bail!("{flag} `{n}`: letters, digits, _ - . only (and not `ca`)");
            }
        }
    }
    std::fs::create_dir_all(&req.dir).with_context(|| format!("creating {}", req.dir.display()))?;
    let mut revocations = if req.revoke.is_empty() { None } else { Some(revoke(&req.dir, &req.revoke)?) };
    let listed = match std::fs::read_to_string(req.dir.join("revoked.txt")) {
        Ok(t) => revoked_names(&t),
        Err(_) => vec![],
    };
    let made_but_revoked: Vec<String> = req.names.iter().filter(|n| listed.contains(n)).cloned().collect();
    if !made_but_revoked.is_empty() {
        let r = revocations.get_or_insert_with(|| Revocations {
            path: req.dir.join("revoked.txt"),
            added: vec![],
            already: vec![],
            made_but_revoked: vec![],
        });
        r.made_but_revoked = made_but_revoked;
    }
    let viewer_token = if req.viewer_token { Some(make_token(&req.dir)?) } else { None };
    if req.names.is_empty() {
        return Ok(CertsReport {
            ca: req.dir.join("ca.pem"),
            ca_created: false,
            written: vec![],
            revocations,
            viewer_token,
        });
    }
    let not_after = when(req.days)?;
    let (issuer, ca_created) = ca(&req.dir, req.ca_days)?;
    let mut written = vec![];
    for n in &req.names {
        let mut sans = vec![n.clone(), "localhost".into(), "127.0.0.1".into(), "::1".into()];
        for s in &req.sans {
            if !sans.contains(s) {
                sans.push(s.clone());
            }
        }
        let mut p =
            CertificateParams::new(sans).with_context(|| format!("--san of {n}: not an address or DNS name"))?;
        p.distinguished_name.push(DnType::CommonName, n.as_str());
        p.key_usages = vec![KeyUsagePurpose::DigitalSignature];
        p.extended_key_usages = vec![ExtendedKeyUsagePurpose::ServerAuth, ExtendedKeyUsagePurpose::ClientAuth];
        p.use_authority_key_identifier_extension = true;
        p.not_before = time::OffsetDateTime::now_utc() - time::Duration::minutes(5);
        p.not_after = not_after;
        let key = KeyPair::generate().context("generating a key")?;
        let cert = p.signed_by(&key, &issuer).with_context(|| format!("signing {n}'s certificate"))?;
        let path = req.dir.join(format!("{n}.pem"));
        let replaced = path.exists();
        std::fs::write(&path, cert.pem()).with_context(|| format!("writing {}", path.display()))?;
        write_private(&req.dir.join(format!("{n}.key")), &key.serialize_pem())?;
        written.push(Written {
            path,
            name: n.clone(),
            replaced,
            not_after: not_after.format(&time::format_description::well_known::Rfc3339).unwrap_or_default(),
        });
    }
    Ok(CertsReport { ca: req.dir.join("ca.pem"), ca_created, written, revocations, viewer_token })
}

impl CertsReport {
    /// What was written, one line per file.
    pub fn render(&self) -> String {
        let mut s = if self.written.is_empty() {
            String::new()
        } else {
            format!("{} {}\n", if self.ca_created { "made the CA" } else { "signed with the CA" }, self.ca.display())
        };
        for w in &self.written {
            s += &format!(
                "{} {} (CN {}, valid until {}; key {})\n",
                if w.replaced { "replaced" } else { "wrote" },
                w.path.display(),
                w.name,
                w.not_after,
                w.path.with_extension("key").display()
            );
        }
        if let Some(t) = &self.viewer_token {
            s += &format!(
                "wrote {} (the live view's token: a viewer's token_file; clients connect with \
                 wss://<host>:<port>/?token=<its content>)\n",
                t.display()
            );
        }
        if let Some(r) = &self.revocations {
            for n in &r.added {
                s += &format!("revoked {n} in {} (running bridges apply it within a second)\n", r.path.display());
            }
            for n in &r.already {
                s += &format!("{n} was revoked already ({})\n", r.path.display());
            }
            for n in &r.made_but_revoked {
                s += &format!(
                    "warning: {n} is on the revocation list {}: its new certificate is refused too until its line \
                     is deleted\n",
                    r.path.display()
                );
            }
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_ca_is_made_once_and_signs_every_later_certificate() {
        let dir = tempfile::tempdir().unwrap();
        let req = |names: &[&str]| CertsRequest {
            dir: dir.path().to_path_buf(),
            names: names.iter().map(|s| s.to_string()).collect(),
            revoke: vec![],
            viewer_token: false,
            sans: vec!["10.0.0.2".into()],
            days: 2.0,
            ca_days: 10.0,
        };
        let a = make(&req(&["base", "auv1"])).unwrap();
        assert!(a.ca_created);
        let ca1 = std::fs::read_to_string(dir.path().join("ca.pem")).unwrap();
        let b = make(&req(&["auv2", "auv1"])).unwrap();
        assert!(!b.ca_created, "the CA is reused");
        assert_eq!(std::fs::read_to_string(dir.path().join("ca.pem")).unwrap(), ca1);
        assert!(b.written[1].replaced && !b.written[0].replaced);
        // Every certificate is signed by the CA's key and carries its name and the SANs.
        let ca = x509_parser::pem::parse_x509_pem(ca1.as_bytes()).unwrap().1;
        let ca = ca.parse_x509().unwrap();
        for n in ["base", "auv1", "auv2"] {
            let pem = std::fs::read(dir.path().join(format!("{n}.pem"))).unwrap();
            let pem = x509_parser::pem::parse_x509_pem(&pem).unwrap().1;
            let c = pem.parse_x509().unwrap();
            c.verify_signature(Some(ca.public_key())).unwrap();
            let cn = c.subject().iter_common_name().next().unwrap().as_str().unwrap().to_string();
            assert_eq!(cn, n);
            let sans = format!("{:?}", c.subject_alternative_name().unwrap().unwrap().value.general_names);
            assert!(sans.contains("10.0.0.2") || sans.contains("[10, 0, 0, 2]"), "{sans}");
            let mode = std::os::unix::fs::PermissionsExt::mode(
                &std::fs::metadata(dir.path().join(format!("{n}.key"))).unwrap().permissions(),
            );
            assert_eq!(mode & 0o777, 0o600, "{n}.key is private");
        }
    }

    #[test]
    fn revoking_appends_to_the_list_once_and_warns_about_new_certificates_of_revoked_names() {
        let dir = tempfile::tempdir().unwrap();
        let req = |names: &[&str], revoke: &[&str]| CertsRequest {
            dir: dir.path().to_path_buf(),
            names: names.iter().map(|s| s.to_string()).collect(),
            revoke: revoke.iter().map(|s| s.to_string()).collect(),
            viewer_token: false,
            sans: vec![],
            days: 1.0,
            ca_days: 2.0,
        };
        make(&req(&["base", "auv1", "auv2"], &[])).unwrap();
        assert!(!dir.path().join("revoked.txt").exists());
        let r = make(&req(&[], &["auv2"])).unwrap();
        assert!(r.written.is_empty());
        assert!(r.render().contains("revoked auv2"), "{}", r.render());
        let list = std::fs::read_to_string(dir.path().join("revoked.txt")).unwrap();
        assert_eq!(revoked_names(&list), vec!["auv2"]);
        let again = make(&req(&[], &["auv2", "auv1"])).unwrap().revocations.unwrap();
        assert_eq!((again.added, again.already), (vec!["auv1".to_string()], vec!["auv2".to_string()]));
        let list = std::fs::read_to_string(dir.path().join("revoked.txt")).unwrap();
        assert_eq!(revoked_names(&list), vec!["auv2", "auv1"]);
        let t = make(&CertsRequest { viewer_token: true, ..req(&[], &[]) }).unwrap().viewer_token.unwrap();
        let token = std::fs::read_to_string(&t).unwrap();
        assert_eq!(token.trim().len(), 48, "{token}");
        let mode = std::os::unix::fs::PermissionsExt::mode(&std::fs::metadata(&t).unwrap().permissions());
        assert_eq!(mode & 0o777, 0o600);
        let remade = make(&req(&["auv2"], &[])).unwrap();
        assert!(remade.render().contains("warning: auv2 is on the revocation list"), "{}", remade.render());
    }

    #[test]
    fn bad_requests_say_what_is_wrong() {
        let dir = tempfile::tempdir().unwrap();
        let mut req = CertsRequest {
            dir: dir.path().to_path_buf(),
            names: vec![],
            revoke: vec![],
            viewer_token: false,
            sans: vec![],
            days: 1.0,
            ca_days: 1.0,
        };
        assert!(make(&req).unwrap_err().to_string().contains("--name"));
        req.names = vec!["a/b".into()];
        assert!(make(&req).unwrap_err().to_string().contains("`a/b`"));
        req.names = vec!["a".into()];
        req.days = 0.0;
        assert!(make(&req).unwrap_err().to_string().contains("0 days"));
        req.days = 1.0;
        std::fs::write(dir.path().join("ca.pem"), "x").unwrap();
        let e = make(&req).unwrap_err().to_string();
        assert!(e.contains("not ca.key"), "{e}");
    }
}
