//! The detector's descriptor matrix: every keyframe's descriptor, one after another, in one contiguous
//! `f32` buffer that grows at the end and shrinks at the front (what [`KeyframeDb`](super::KeyframeDb)
//! and its index scan).
//!
//! The buffer is an ordinary vector, or, after a load from a keyframe store's vector file
//! ([`super::store`]), a private memory map of that file followed by anonymous room to grow in place.
//! Mapping makes a restart independent of how dear fresh memory is: the loaded rows are the page
//! cache's own pages (shared read-only until written, then copied), so a load takes no new memory.
//! Copying 100k 1280-value descriptors into new memory needs 512 MB of it, and on a virtual machine
//! whose host backs each new page on first touch that alone took 0.9-1.8 s (13 us a page, measured
//! on the CI's machine kind), more than the whole load is allowed.
//!
//! [`Rows`] is what the database holds: these `f32` rows, or six-level codes of them
//! ([`super::codes`], `detector.storage`), behind one interface for the scan and the index.

use std::borrow::Cow;
use std::ops::Deref;

use super::codes::{CodedQuery, CodedRows};

/// Contiguous descriptor values (module doc).
pub struct DescriptorRows {
    storage: Storage,
}

enum Storage {
    Owned(Vec<f32>),
    #[cfg(unix)]
    Mapped(mapped::MappedRows),
}

impl DescriptorRows {
    pub fn with_capacity(values: usize) -> Self {
        Vec::with_capacity(values).into()
    }

    /// `values` `f32`s stored at byte `offset` of `file` (little-endian), mapped privately, with room
    /// for `spare` more values after them before the rows move to ordinary memory. The caller
    /// guarantees the file holds those bytes and is never truncated below them while mapped (a
    /// shrunk file would fault on access); writes go to private copies, never to the file.
    #[cfg(unix)]
    pub(crate) fn map_file(file: &std::fs::File, offset: u64, values: usize, spare: usize) -> std::io::Result<Self> {
        Ok(DescriptorRows { storage: Storage::Mapped(mapped::MappedRows::map(file, offset, values, spare)?) })
    }

    /// Whether the rows are (still) a map of a vector file.
    pub fn is_mapped(&self) -> bool {
        match &self.storage {
            Storage::Owned(_) => false,
            #[cfg(unix)]
            Storage::Mapped(_) => true,
        }
    }

    pub fn extend_from_slice(&mut self, values: &[f32]) {
        match &mut self.storage {
            Storage::Owned(vec) => vec.extend_from_slice(values),
            #[cfg(unix)]
            Storage::Mapped(map) => {
                if !map.try_extend(values) {
                    // Out of room: continue in ordinary memory, with room to double as a Vec would.
                    let mut vec = Vec::with_capacity((map.len() + values.len()) * 2);
                    vec.extend_from_slice(map.as_slice());
                    vec.extend_from_slice(values);
                    self.storage = Storage::Owned(vec);
                }
            }
        }
    }

    /// Removes the first `values` values.
    pub fn drain_front(&mut self, values: usize) {
        match &mut self.storage {
            Storage::Owned(vec) => drop(vec.drain(..values)),
            #[cfg(unix)]
            Storage::Mapped(map) => map.drop_front(values),
        }
    }
}

impl From<Vec<f32>> for DescriptorRows {
    fn from(values: Vec<f32>) -> Self {
        DescriptorRows { storage: Storage::Owned(values) }
    }
}

impl Deref for DescriptorRows {
    type Target = [f32];

    fn deref(&self) -> &[f32] {
        match &self.storage {
            Storage::Owned(vec) => vec,
            #[cfg(unix)]
            Storage::Mapped(map) => map.as_slice(),
        }
    }
}

impl Clone for DescriptorRows {
    fn clone(&self) -> Self {
        self.to_vec().into()
    }
}

impl std::fmt::Debug for DescriptorRows {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "DescriptorRows({} values{})", self.len(), if self.is_mapped() { ", mapped" } else { "" })
    }
}

/// How the database keeps its rows.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum RowFormat {
    /// Every value as an `f32` (exact).
    #[default]
    F32,
    /// Six levels a value, three values a byte, three factors a row ([`super::codes`]).
    Levels6,
}

impl RowFormat {
    /// The name `detector.storage` gives this format.
    pub fn name(self) -> &'static str {
        match self {
            RowFormat::F32 => super::Storage::F32.name(),
            RowFormat::Levels6 => super::Storage::Levels6.name(),
        }
    }

    /// Bytes one `dim`-value row takes.
    pub fn row_bytes(self, dim: usize) -> usize {
        match self {
            RowFormat::F32 => 4 * dim,
            RowFormat::Levels6 => super::codes::row_bytes(dim),
        }
    }
}

/// The database's rows in their format, `dim` values a row (module doc).
#[derive(Clone, Debug)]
pub(crate) struct Rows {
    dim: usize,
    kind: RowsKind,
}

#[derive(Clone, Debug)]
enum RowsKind {
    Plain(DescriptorRows),
    Coded(CodedRows),
}

/// A query prepared for one scan of [`Rows`].
pub(crate) enum PreparedQuery<'q> {
    Plain(&'q [f32]),
    Coded(CodedQuery),
}

impl Rows {
    pub fn with_capacity(format: RowFormat, dim: usize, rows: usize) -> Self {
        let kind = match format {
            RowFormat::F32 => RowsKind::Plain(DescriptorRows::with_capacity(rows * dim)),
            RowFormat::Levels6 => RowsKind::Coded(CodedRows::with_capacity(dim, rows)),
        };
        Rows { dim, kind }
    }

    /// `f32` rows as they are.
    pub fn plain(dim: usize, rows: DescriptorRows) -> Self {
        Rows { dim, kind: RowsKind::Plain(rows) }
    }

    /// These rows in `format` (coding is lossy: `f32` rows from codes are their reconstructions).
    pub fn into_format(self, format: RowFormat) -> Self {
        if self.format() == format {
            return self;
        }
        use rayon::prelude::*;
        // In parallel pieces (a restart codes its whole loaded history), appended in order.
        const PIECE: usize = 4096;
        let slots = self.slots();
        let pieces: Vec<Rows> = (0..slots.div_ceil(PIECE))
            .into_par_iter()
            .map(|piece| {
                let (start, end) = (piece * PIECE, ((piece + 1) * PIECE).min(slots));
                let mut out = Rows::with_capacity(format, self.dim, end - start);
                out.extend(&self.values(start, end));
                out
            })
            .collect();
        let mut out = Rows::with_capacity(format, self.dim, slots);
        for piece in pieces {
            out.append(piece);
        }
        out
    }

    pub fn format(&self) -> RowFormat {
        match self.kind {
            RowsKind::Plain(_) => RowFormat::F32,
            RowsKind::Coded(_) => RowFormat::Levels6,
        }
    }

    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Rows held, from the buffer's start.
    pub fn slots(&self) -> usize {
        match &self.kind {
            RowsKind::Plain(rows) => rows.len() / self.dim.max(1),
            RowsKind::Coded(rows) => rows.rows(),
        }
    }

    /// Whether the rows are (still) a map of a vector file.
    pub fn is_mapped(&self) -> bool {
        matches!(&self.kind, RowsKind::Plain(rows) if rows.is_mapped())
    }

    /// Appends the rows of `values` (`dim` values each).
    pub fn extend(&mut self, values: &[f32]) {
        match &mut self.kind {
            RowsKind::Plain(rows) => rows.extend_from_slice(values),
            RowsKind::Coded(rows) => rows.extend_from_values(values),
        }
    }

    /// Moves `other`'s rows (the same format and length) to the end of these.
    fn append(&mut self, other: Rows) {
        match (&mut self.kind, other.kind) {
            (RowsKind::Plain(rows), RowsKind::Plain(more)) => rows.extend_from_slice(&more),
            (RowsKind::Coded(rows), RowsKind::Coded(more)) => rows.append(more),
            _ => unreachable!("rows of another format"),
        }
    }

    /// Removes the first `rows` rows.
    pub fn drain_front(&mut self, rows: usize) {
        match &mut self.kind {
            RowsKind::Plain(plain) => plain.drain_front(rows * self.dim),
            RowsKind::Coded(coded) => coded.drain_front(rows),
        }
    }

    /// The values of slots `start..end`: borrowed `f32` rows, or the codes' reconstructions.
    pub fn values(&self, start: usize, end: usize) -> Cow<'_, [f32]> {
        match &self.kind {
            RowsKind::Plain(rows) => Cow::Borrowed(&rows[start * self.dim..end * self.dim]),
            RowsKind::Coded(rows) => {
                let mut out = vec![0f32; (end - start) * self.dim];
                for (slot, row) in (start..end).zip(out.chunks_exact_mut(self.dim.max(1))) {
                    rows.decode_into(slot, row);
                }
                Cow::Owned(out)
            }
        }
    }

    pub fn prepare<'q>(&self, query: &'q [f32]) -> PreparedQuery<'q> {
        match &self.kind {
            RowsKind::Plain(_) => PreparedQuery::Plain(query),
            RowsKind::Coded(_) => PreparedQuery::Coded(CodedQuery::new(query)),
        }
    }

    /// Calls `visit(position, squared distance)` for each `(position, slot)` of `items`; `query`
    /// comes from [`Rows::prepare`] on these rows.
    #[inline]
    pub fn scan(
        &self,
        query: &PreparedQuery<'_>,
        items: impl Iterator<Item = (usize, usize)>,
        mut visit: impl FnMut(usize, f32),
    ) {
        match (&self.kind, query) {
            (RowsKind::Plain(rows), PreparedQuery::Plain(query)) => {
                let dim = self.dim;
                super::index::scan(query, items.map(|(p, s)| (p, &rows[s * dim..(s + 1) * dim])), visit)
            }
            (RowsKind::Coded(rows), PreparedQuery::Coded(query)) => {
                for (position, slot) in items {
                    let (codes, factors) = rows.row(slot);
                    visit(position, query.squared_distance(codes, factors));
                }
            }
            _ => unreachable!("a query prepared for rows of another format"),
        }
    }

    /// Asks the CPU to start loading row `slot`: a whole coded row, the first 512 bytes of an `f32`
    /// one (the hardware prefetcher follows a longer row).
    #[inline(always)]
    pub fn prefetch(&self, slot: usize) {
        let bytes: &[u8] = match &self.kind {
            RowsKind::Plain(rows) => {
                let row = &rows[slot * self.dim..(slot + 1) * self.dim];
                bytemuck::cast_slice(&row[..row.len().min(128)])
            }
            RowsKind::Coded(rows) => rows.row_span(slot),
        };
        #[cfg(target_arch = "x86_64")]
        for offset in (0..bytes.len()).step_by(64) {
            // SAFETY: SSE is part of x86_64; prefetching a valid address has no side effect.
            #[allow(unused_unsafe)]
            unsafe {
                std::arch::x86_64::_mm_prefetch(bytes.as_ptr().add(offset) as *const i8, std::arch::x86_64::_MM_HINT_T0)
            };
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = bytes;
    }
}

#[cfg(unix)]
mod mapped {
    use std::os::fd::AsRawFd;
    use std::ptr::NonNull;

    /// One mapping: the file's pages holding the rows, then anonymous pages to grow into.
    pub(super) struct MappedRows {
        base: NonNull<u8>,
        /// Bytes mapped in all, from `base`.
        mapped_bytes: usize,
        /// Byte offset of the first value from `base` (grows as the front is dropped).
        head: usize,
        /// Values in use.
        len: usize,
    }

    // SAFETY: the mapping is owned by this value alone, like a Vec's buffer; shared access only reads.
    unsafe impl Send for MappedRows {}
    unsafe impl Sync for MappedRows {}

    fn page_size() -> usize {
        // SAFETY: sysconf has no preconditions.
        usize::try_from(unsafe { libc::sysconf(libc::_SC_PAGESIZE) }).ok().filter(|&p| p > 0).unwrap_or(4096)
    }

    impl MappedRows {
        pub(super) fn map(file: &std::fs::File, offset: u64, values: usize, spare: usize) -> std::io::Result<Self> {
            let page = page_size();
            let map_offset = offset / page as u64 * page as u64;
            let head = (offset - map_offset) as usize;
            let file_bytes = (head + values * 4).div_ceil(page) * page;
            let mapped_bytes = file_bytes + (spare * 4).div_ceil(page) * page;
            if mapped_bytes == 0 || !head.is_multiple_of(4) {
                return Err(std::io::Error::new(
                    std::io::ErrorKind::InvalidInput,
                    "nothing to map, or values not 4-byte aligned",
                ));
            }
            let error = std::io::Error::last_os_error;
            // SAFETY: a fresh anonymous reservation; nothing else refers to it.
            let base = unsafe {
                libc::mmap(
                    std::ptr::null_mut(),
                    mapped_bytes,
                    libc::PROT_READ | libc::PROT_WRITE,
                    libc::MAP_PRIVATE | libc::MAP_ANONYMOUS | libc::MAP_NORESERVE,
                    -1,
                    0,
                )
            };
            if base == libc::MAP_FAILED {
                return Err(error());
            }
            let rows = MappedRows {
                base: NonNull::new(base.cast()).expect("mmap returned null"),
                mapped_bytes,
                head,
                len: values,
            };
            if file_bytes > 0 {
                // The file's pages go over the start of the reservation. Mapped read-only with
                // MAP_POPULATE, so they are entered as the page cache's pages in one call (populating
                // a writable private map would copy every page); then made writable, which copies a
                // page only when it is written.
                // SAFETY: [base, base + file_bytes) lies in our own reservation, which MAP_FIXED replaces.
                let fixed = unsafe {
                    libc::mmap(
                        base,
                        file_bytes,
                        libc::PROT_READ,
                        libc::MAP_PRIVATE | libc::MAP_FIXED | libc::MAP_POPULATE,
                        file.as_raw_fd(),
                        map_offset as libc::off_t,
                    )
                };
                if fixed == libc::MAP_FAILED {
                    return Err(error()); // `rows` unmaps the reservation
                }
                // SAFETY: the same range, now our file mapping.
                if unsafe { libc::mprotect(base, file_bytes, libc::PROT_READ | libc::PROT_WRITE) } != 0 {
                    return Err(error());
                }
            }
            Ok(rows)
        }

        pub(super) fn len(&self) -> usize {
            self.len
        }

        fn capacity(&self) -> usize {
            (self.mapped_bytes - self.head) / 4
        }

        pub(super) fn as_slice(&self) -> &[f32] {
            // SAFETY: [head, head + 4 len) is mapped, initialised (file bytes or written values) and 4-byte aligned.
            unsafe { std::slice::from_raw_parts(self.base.as_ptr().add(self.head).cast::<f32>(), self.len) }
        }

        /// Appends `values` when they fit in the mapping; false (nothing changed) otherwise.
        pub(super) fn try_extend(&mut self, values: &[f32]) -> bool {
            if self.len + values.len() > self.capacity() {
                return false;
            }
            // SAFETY: the destination is inside the mapping (checked above) and cannot overlap `values`,
            // which the caller borrows from elsewhere (we hold `&mut self`).
            unsafe {
                let end = self.base.as_ptr().add(self.head).cast::<f32>().add(self.len);
                std::ptr::copy_nonoverlapping(values.as_ptr(), end, values.len());
            }
            self.len += values.len();
            true
        }

        pub(super) fn drop_front(&mut self, values: usize) {
            let values = values.min(self.len);
            self.head += values * 4;
            self.len -= values;
        }
    }

    impl Drop for MappedRows {
        fn drop(&mut self) {
            // SAFETY: unmaps exactly what `map` mapped; no reference into it outlives `self`.
            unsafe { libc::munmap(self.base.as_ptr().cast(), self.mapped_bytes) };
        }
    }
}

#[cfg(all(test, target_os = "linux"))]
mod tests {
    use super::*;
    use std::io::Write;

    #[test]
    fn mapped_rows_read_the_file_grow_in_place_then_move_and_never_write_the_file() {
        let mut file = tempfile::tempfile().unwrap();
        let header = [7u8; 4096 + 12];
        let values: Vec<f32> = (0..3000).map(|i| i as f32 * 0.5).collect();
        file.write_all(&header).unwrap();
        file.write_all(bytemuck::cast_slice(&values)).unwrap();
        let before = std::fs::read(format!("/proc/self/fd/{}", std::os::fd::AsRawFd::as_raw_fd(&file))).unwrap();
        // From value 3 on (offset not page-aligned), room for 1100 more (rounded up to whole pages).
        let mut rows = DescriptorRows::map_file(&file, 4096 + 12 + 12, 2997, 1100).unwrap();
        assert!(rows.is_mapped());
        assert_eq!(&rows[..], &values[3..]);
        rows.drain_front(10);
        assert_eq!(&rows[..], &values[13..]);
        let extra: Vec<f32> = (0..1000).map(|i| -(i as f32)).collect();
        rows.extend_from_slice(&extra);
        assert!(rows.is_mapped(), "1000 values fit in the spare room");
        assert_eq!(&rows[..2987], &values[13..]);
        assert_eq!(&rows[2987..], &extra[..]);
        let more = vec![9.0f32; 5000];
        rows.extend_from_slice(&more);
        assert!(!rows.is_mapped(), "past the spare room the rows move to ordinary memory");
        assert_eq!(rows.len(), 2987 + 1000 + 5000);
        assert_eq!((&rows[..2987], &rows[2987..3987], &rows[3987..]), (&values[13..], &extra[..], &more[..]));
        let after = std::fs::read(format!("/proc/self/fd/{}", std::os::fd::AsRawFd::as_raw_fd(&file))).unwrap();
        assert!(before == after, "the file was written through the map");
    }
}
