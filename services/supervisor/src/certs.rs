//! `supervisor certs`: a certificate authority and one certificate per host for the bridge's
//! mutual TLS (README "Security").
//!
//! - `ca.pem` / `ca.key`: the CA. Made on the first call, reused by the next ones (so robots
//!   added later are signed by the CA the base station already trusts).
//! - `<name>.pem` / `<name>.key`: a host's certificate, common name `<name>` (the bridge's
//!   `robot`, or the base station's name), signed by the CA, usable to listen and to connect
//!   (extended key usage server and client auth). Its subject alternative names are `<name>`,
//!   `localhost`, `127.0.0.1`, `::1` and every `--san` (the addresses other hosts dial: TLS checks
//!   the address a peer connects to against them).
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
    if req.names.is_empty() {
        bail!("give at least one --name (the robots' `robot` names and the base station's)");
    }
    for n in &req.names {
        if !name_ok(n) {
            bail!("--name `{n}`: letters, digits, _ - . only (and not `ca`)");
        }
    }
    let not_after = when(req.days)?;
    std::fs::create_dir_all(&req.dir).with_context(|| format!("creating {}", req.dir.display()))?;
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
    Ok(CertsReport { ca: req.dir.join("ca.pem"), ca_created, written })
}

impl CertsReport {
    /// What was written, one line per file.
    pub fn render(&self) -> String {
        let mut s =
            format!("{} {}\n", if self.ca_created { "made the CA" } else { "signed with the CA" }, self.ca.display());
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
    fn bad_requests_say_what_is_wrong() {
        let dir = tempfile::tempdir().unwrap();
        let mut req =
            CertsRequest { dir: dir.path().to_path_buf(), names: vec![], sans: vec![], days: 1.0, ca_days: 1.0 };
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
