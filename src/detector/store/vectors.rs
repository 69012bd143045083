//! The vector file beside a keyframe store (`<db>-vectors`): every stored descriptor once more, as raw
//! little-endian `f32` in insertion order after a one-page header, so that a load maps the rows
//! ([`DescriptorRows::map_file`]) instead of copying them out of SQLite into new memory (why that
//! matters: [`crate::detector::rows`]).
//!
//! It is derived data. The SQLite file stays the record (every durability promise is made by it);
//! this file is written after each commit without an fsync of its own, and a load trusts it only
//! after checking it, rebuilding it from the database otherwise. Deleting it loses nothing.
//!
//! Invariant: the file's `rows` rows are the database's rows with `seq <= last_seq`, in `seq` order.
//! Rows are never deleted and `seq` only grows, so that prefix never changes once written. Writers
//! keep it by appending only when the file ends exactly at the row before theirs (under an exclusive
//! `flock`); anything else (a crash between the commit and the append, a writer that does not know
//! this file, `db merge` copying rows inside SQLite) leaves the file behind, and the next load appends
//! the missing rows. A load checks, before mapping: the header's own checksum, descriptor length and
//! the store's unique id (a file left from another database at the same path); that the database row
//! at position `rows - 1` has `seq == last_seq` and the same descriptor as the file's last row; the
//! file's length; and the CRC-32 of all rows with every value finite. Any failure rewrites the file
//! from the database (a warning says why). The file is replaced only by rename and otherwise only
//! grows, so a map held by another process never loses its pages.
//!
//! Header (80 bytes, little-endian, at offset 0): magic `b"ecm-lcd vectors\n"`, format version `u32`,
//! values per row `u32`, the store's unique id (32 ASCII hex digits), `rows: u64`, `last_seq: i64`,
//! CRC-32 of all row bytes `u32`, CRC-32 of the preceding 76 header bytes `u32`. Rows start at 4096.

use std::fs::File;
use std::os::unix::fs::{FileExt, MetadataExt};
use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context, Result};
use rayon::prelude::*;

use crate::detector::rows::DescriptorRows;

const MAGIC: &[u8; 16] = b"ecm-lcd vectors\n";
/// 2 since keyframes stored with candidates, local features, a frame or a consistency state were
/// appended under another table's row id: a version-1 file may hold rows out of place where its last
/// row checks out, so it is rebuilt.
const VERSION: u32 = 2;
const HEADER_BYTES: usize = 80;
/// Byte offset of row 0: a whole page, so that the rows map from a page boundary.
pub(super) const ROWS_OFFSET: u64 = 4096;

/// The vector file of the store at `db`.
pub(super) fn path_for(db: &Path) -> PathBuf {
    let mut path = db.as_os_str().to_owned();
    path.push("-vectors");
    PathBuf::from(path)
}

/// The header's fields (module doc).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct Header {
    pub dim: u32,
    pub uid: [u8; 32],
    pub rows: u64,
    pub last_seq: i64,
    pub crc: u32,
}

impl Header {
    fn encode(&self) -> [u8; HEADER_BYTES] {
        let mut bytes = [0u8; HEADER_BYTES];
        bytes[..16].copy_from_slice(MAGIC);
        bytes[16..20].copy_from_slice(&VERSION.to_le_bytes());
        bytes[20..24].copy_from_slice(&self.dim.to_le_bytes());
        bytes[24..56].copy_from_slice(&self.uid);
        bytes[56..64].copy_from_slice(&self.rows.to_le_bytes());
        bytes[64..72].copy_from_slice(&self.last_seq.to_le_bytes());
        bytes[72..76].copy_from_slice(&self.crc.to_le_bytes());
        let own_crc = crc32fast::hash(&bytes[..76]);
        bytes[76..80].copy_from_slice(&own_crc.to_le_bytes());
        bytes
    }

    fn decode(bytes: &[u8; HEADER_BYTES]) -> Result<Header> {
        ensure!(&bytes[..16] == MAGIC, "not a vector file (no magic)");
        let u32_at = |at: usize| u32::from_le_bytes(bytes[at..at + 4].try_into().unwrap());
        let u64_at = |at: usize| u64::from_le_bytes(bytes[at..at + 8].try_into().unwrap());
        ensure!(u32_at(76) == crc32fast::hash(&bytes[..76]), "its header is damaged (checksum)");
        ensure!(u32_at(16) == VERSION, "format version {}, this program writes {VERSION}", u32_at(16));
        Ok(Header {
            dim: u32_at(20),
            uid: bytes[24..56].try_into().unwrap(),
            rows: u64_at(56),
            last_seq: u64_at(64) as i64,
            crc: u32_at(72),
        })
    }
}

/// An open vector file.
pub(super) struct VectorFile {
    file: File,
    path: PathBuf,
    /// Identifies the file that `path` named when opened (it may be replaced by a rebuild since).
    inode: u64,
}

/// An exclusive `flock` on a vector file, released when dropped.
struct Locked<'a>(&'a File);

impl<'a> Locked<'a> {
    fn exclusive(file: &'a File) -> std::io::Result<Self> {
        // SAFETY: flock on an fd we own.
        if unsafe { libc::flock(std::os::fd::AsRawFd::as_raw_fd(file), libc::LOCK_EX) } != 0 {
            return Err(std::io::Error::last_os_error());
        }
        Ok(Locked(file))
    }
}

impl Drop for Locked<'_> {
    fn drop(&mut self) {
        // SAFETY: as above.
        unsafe { libc::flock(std::os::fd::AsRawFd::as_raw_fd(self.0), libc::LOCK_UN) };
    }
}

impl VectorFile {
    /// Opens the vector file at `path`; `None` when there is none.
    pub fn open(path: &Path) -> Result<Option<VectorFile>> {
        match File::options().read(true).write(true).open(path) {
            Ok(file) => {
                let inode = file.metadata().with_context(|| format!("reading {}", path.display()))?.ino();
                Ok(Some(VectorFile { file, path: path.to_path_buf(), inode }))
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(e).with_context(|| format!("opening {}", path.display())),
        }
    }

    /// Writes an empty vector file at `path` (under a temporary name, then renamed over whatever is
    /// there: a process still mapping the old file keeps its pages).
    pub fn create_empty(path: &Path, dim: usize, uid: [u8; 32]) -> Result<VectorFile> {
        let context = || format!("writing {}", path.display());
        let mut temporary = path.as_os_str().to_owned();
        temporary.push(format!(".{}.tmp", std::process::id()));
        let temporary = PathBuf::from(temporary);
        let header =
            Header { dim: u32::try_from(dim).context("descriptor too long")?, uid, rows: 0, last_seq: 0, crc: 0 };
        let mut page = vec![0u8; ROWS_OFFSET as usize];
        page[..HEADER_BYTES].copy_from_slice(&header.encode());
        std::fs::write(&temporary, &page).with_context(context)?;
        std::fs::rename(&temporary, path).with_context(context)?;
        VectorFile::open(path)?.with_context(|| format!("{} vanished after writing it", path.display()))
    }

    /// Whether `path` still names the file this was opened as.
    pub fn is_current(&self) -> bool {
        std::fs::metadata(&self.path).is_ok_and(|m| m.ino() == self.inode)
    }

    pub fn header(&self) -> Result<Header> {
        let mut bytes = [0u8; HEADER_BYTES];
        self.file.read_exact_at(&mut bytes, 0).context("its header is incomplete")?;
        Header::decode(&bytes)
    }

    /// Appends `values` (whole rows, the last with `seq == last_seq`) when the file ends at the row
    /// before them: its last row has `seq == prev_seq`, or it is empty and `prev_seq` is `None` (the
    /// rows are the store's first). Returns whether it appended (module doc: otherwise the next load
    /// catches up).
    pub fn append_after(
        &self,
        dim: usize,
        uid: &[u8; 32],
        prev_seq: Option<i64>,
        last_seq: i64,
        values: &[f32],
    ) -> Result<bool> {
        let context = || format!("appending to {}", self.path.display());
        let _lock = Locked::exclusive(&self.file).with_context(context)?;
        let Ok(header) = self.header() else { return Ok(false) };
        let ends_before = if header.rows == 0 { prev_seq.is_none() } else { prev_seq == Some(header.last_seq) };
        if !ends_before || header.dim as usize != dim || &header.uid != uid || dim == 0 {
            return Ok(false);
        }
        let bytes: &[u8] = bytemuck::cast_slice(values);
        ensure!(cfg!(target_endian = "little"), "vector files are little-endian");
        self.file.write_all_at(bytes, ROWS_OFFSET + header.rows * dim as u64 * 4).with_context(context)?;
        let mut crc = crc32fast::Hasher::new_with_initial_len(header.crc, header.rows * dim as u64 * 4);
        crc.update(bytes);
        let header =
            Header { rows: header.rows + (values.len() / dim) as u64, last_seq, crc: crc.finalize(), ..header };
        self.file.write_all_at(&header.encode(), 0).with_context(context)?;
        Ok(true)
    }

    /// Maps the file's first `header.rows` rows after checking their checksum and that every value is
    /// finite, with room for `spare` more values; an error says what is wrong.
    pub fn map_checked(&self, header: &Header, spare: usize) -> Result<DescriptorRows> {
        let dim = header.dim as usize;
        if header.rows == 0 {
            return Ok(DescriptorRows::with_capacity(0));
        }
        let bytes = header.rows.checked_mul(dim as u64 * 4).context("its row count is impossible")?;
        let length = self.file.metadata().with_context(|| format!("reading {}", self.path.display()))?.len();
        ensure!(length >= ROWS_OFFSET + bytes, "it is {length} bytes, too short for its {} rows", header.rows);
        let rows = DescriptorRows::map_file(&self.file, ROWS_OFFSET, bytes as usize / 4, spare)
            .with_context(|| format!("mapping {}", self.path.display()))?;
        // Checked in parallel pieces, whose CRCs combine in order.
        let pieces: Vec<(crc32fast::Hasher, bool)> = rows
            .par_chunks(1 << 20)
            .map(|piece| {
                let mut crc = crc32fast::Hasher::new();
                crc.update(bytemuck::cast_slice(piece));
                (crc, piece.iter().fold(true, |ok, x| ok & x.is_finite()))
            })
            .collect();
        let mut crc = crc32fast::Hasher::new();
        for (piece, finite) in &pieces {
            if !finite {
                bail!("it holds a value that is not finite");
            }
            crc.combine(piece);
        }
        ensure!(crc.finalize() == header.crc, "its rows do not match their checksum (damaged or torn)");
        Ok(rows)
    }

    /// The row at `position` (for comparing with the database).
    pub fn row(&self, position: u64, dim: usize) -> Result<Vec<u8>> {
        let mut bytes = vec![0u8; dim * 4];
        self.file
            .read_exact_at(&mut bytes, ROWS_OFFSET + position * dim as u64 * 4)
            .context("it ends inside its rows")?;
        Ok(bytes)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_header_round_trips_and_any_changed_byte_is_caught() {
        let header = Header {
            dim: 1280,
            uid: *b"0123456789abcdef0123456789abcdef",
            rows: 123_456,
            last_seq: -7,
            crc: 0xdead_beef,
        };
        let bytes = header.encode();
        assert_eq!(Header::decode(&bytes).unwrap(), header);
        for at in 0..HEADER_BYTES {
            let mut changed = bytes;
            changed[at] ^= 0x10;
            assert!(Header::decode(&changed).is_err(), "a change at byte {at} went unnoticed");
        }
    }
}
