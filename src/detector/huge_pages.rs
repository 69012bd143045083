//! A growable byte buffer backed by huge pages where the system offers them: what the six-level
//! codes ([`super::codes`]) live in.
//!
//! An index query reads a few thousand rows of about a kilobyte scattered over the whole buffer
//! (a gigabyte at a million keyframes). With 4 KiB pages nearly every row is a TLB miss and a page
//! walk, which costs more than scanning the row; with 2 MiB pages the whole buffer needs a few
//! hundred TLB entries. So on Linux the buffer is one address range reserved up front (`PROT_NONE`,
//! which takes neither memory nor commit charge), advised `MADV_HUGEPAGE`, and made writable as it
//! grows, so it never moves. Growing a `Vec` instead would `mremap` it to a new address, which
//! splits the huge pages it had into small ones. Where the reservation is refused (an address-space
//! limit, another OS), or transparent huge pages are off, the buffer is an ordinary `Vec` or its
//! pages are small: the same contents, only slower scans.
//!
//! A small buffer (under [`RESERVE_FROM`]) stays an ordinary `Vec`: a few thousand rows fit the TLB
//! anyway, and small buffers are many (test databases, the pieces of a parallel conversion, an
//! index's centroids), each of which would otherwise take a reservation and a 2 MiB page. A buffer
//! growing past it moves into a reservation once.

use std::ops::{Deref, DerefMut};

/// Growable bytes (module doc).
pub struct HugePageBytes {
    storage: Storage,
    /// Set once the system refused a reservation or one overflowed: the bytes stay on the heap.
    heap_only: bool,
}

/// Bytes from which a buffer lives in a reservation (module doc).
pub const RESERVE_FROM: usize = 32 << 20;

enum Storage {
    Heap(Vec<u8>),
    #[cfg(target_os = "linux")]
    Reserved(reserved::Reserved),
}

impl HugePageBytes {
    /// An empty buffer expected to grow to about `capacity` bytes (it may grow past them).
    pub fn with_capacity(capacity: usize) -> Self {
        let mut bytes = HugePageBytes { storage: Storage::Heap(Vec::new()), heap_only: false };
        if !bytes.try_reserve(capacity) {
            bytes.storage = Storage::Heap(Vec::with_capacity(capacity));
        }
        bytes
    }

    /// Moves the bytes into a reservation for at least `capacity` bytes where that is due and the
    /// system gives one; whether the bytes are reserved afterwards.
    fn try_reserve(&mut self, capacity: usize) -> bool {
        #[cfg(target_os = "linux")]
        if capacity >= RESERVE_FROM && !self.heap_only && !self.is_reserved() {
            match reserved::Reserved::new(capacity) {
                Some(mut reserved) => {
                    let len = self.len();
                    if reserved.try_grow(len) {
                        reserved.as_mut_slice().copy_from_slice(self);
                        self.storage = Storage::Reserved(reserved);
                    } else {
                        self.heap_only = true;
                    }
                }
                None => self.heap_only = true,
            }
        }
        self.is_reserved()
    }

    /// Appends `count` zero bytes; the appended bytes, to fill in.
    pub fn extend_zeroed(&mut self, count: usize) -> &mut [u8] {
        let at = self.len();
        if at + count >= RESERVE_FROM && !self.is_reserved() {
            self.try_reserve(2 * (at + count));
        }
        match &mut self.storage {
            Storage::Heap(vec) => vec.resize(at + count, 0),
            #[cfg(target_os = "linux")]
            Storage::Reserved(reserved) => {
                if !reserved.try_grow(at + count) {
                    // Past the reservation (or refused room): continue on the heap, as a Vec would.
                    let mut vec = Vec::with_capacity(2 * (at + count));
                    vec.extend_from_slice(reserved.as_slice());
                    vec.resize(at + count, 0);
                    self.storage = Storage::Heap(vec);
                    self.heap_only = true;
                }
            }
        }
        &mut self[at..]
    }

    pub fn extend_from_slice(&mut self, bytes: &[u8]) {
        self.extend_zeroed(bytes.len()).copy_from_slice(bytes);
    }

    /// Removes the first `count` bytes (moving the rest to the front, as `Vec::drain` does).
    pub fn drain_front(&mut self, count: usize) {
        match &mut self.storage {
            Storage::Heap(vec) => drop(vec.drain(..count)),
            #[cfg(target_os = "linux")]
            Storage::Reserved(reserved) => reserved.drain_front(count),
        }
    }

    /// Whether the bytes are in a reservation advised to huge pages (not whether the kernel gave
    /// them: that is its choice, page by page).
    pub fn is_reserved(&self) -> bool {
        !matches!(self.storage, Storage::Heap(_))
    }
}

impl Default for HugePageBytes {
    fn default() -> Self {
        HugePageBytes { storage: Storage::Heap(Vec::new()), heap_only: false }
    }
}

impl Deref for HugePageBytes {
    type Target = [u8];

    fn deref(&self) -> &[u8] {
        match &self.storage {
            Storage::Heap(vec) => vec,
            #[cfg(target_os = "linux")]
            Storage::Reserved(reserved) => reserved.as_slice(),
        }
    }
}

impl DerefMut for HugePageBytes {
    fn deref_mut(&mut self) -> &mut [u8] {
        match &mut self.storage {
            Storage::Heap(vec) => vec,
            #[cfg(target_os = "linux")]
            Storage::Reserved(reserved) => reserved.as_mut_slice(),
        }
    }
}

impl Clone for HugePageBytes {
    fn clone(&self) -> Self {
        let mut copy = HugePageBytes::with_capacity(self.len());
        copy.extend_from_slice(self);
        copy
    }
}

impl std::fmt::Debug for HugePageBytes {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "HugePageBytes({} bytes{})", self.len(), if self.is_reserved() { ", reserved" } else { "" })
    }
}

#[cfg(target_os = "linux")]
mod reserved {
    use std::ptr::NonNull;

    /// A huge page's size on x86-64 and most aarch64 kernels; writable room grows in these steps.
    const HUGE_PAGE: usize = 2 << 20;
    /// Address space reserved at least: no memory until written, and a million default rows fit.
    const MIN_RESERVE: usize = 64 << 30;

    /// One reserved range: `[base, base + writable)` readable and writable, the rest `PROT_NONE`.
    pub(super) struct Reserved {
        base: NonNull<u8>,
        reserved: usize,
        writable: usize,
        len: usize,
    }

    // SAFETY: the mapping is owned by this value alone, like a Vec's buffer; shared access only reads.
    unsafe impl Send for Reserved {}
    unsafe impl Sync for Reserved {}

    impl Reserved {
        /// A reservation for at least `capacity` bytes, or `None` where the system refuses one.
        pub(super) fn new(capacity: usize) -> Option<Self> {
            let wanted = capacity.checked_mul(2)?.max(MIN_RESERVE).next_multiple_of(HUGE_PAGE);
            // A smaller reservation where the large one is refused (e.g. `ulimit -v`).
            let smaller = capacity.checked_mul(2)?.max(64 << 20).next_multiple_of(HUGE_PAGE);
            [wanted, smaller].into_iter().find_map(Self::reserve)
        }

        pub(super) fn reserve(bytes: usize) -> Option<Self> {
            // One huge page more than asked, so that the range can start on a huge-page boundary.
            let mapped = bytes.checked_add(HUGE_PAGE)?;
            // SAFETY: a fresh anonymous mapping; nothing else refers to it.
            let raw = unsafe {
                libc::mmap(
                    std::ptr::null_mut(),
                    mapped,
                    libc::PROT_NONE,
                    libc::MAP_PRIVATE | libc::MAP_ANONYMOUS | libc::MAP_NORESERVE,
                    -1,
                    0,
                )
            };
            if raw == libc::MAP_FAILED {
                return None;
            }
            let start = raw as usize;
            let aligned = start.next_multiple_of(HUGE_PAGE);
            // SAFETY: both pieces lie in the mapping just made and are page-aligned; the aligned
            // range of `bytes` stays mapped.
            unsafe {
                if aligned > start {
                    libc::munmap(raw, aligned - start);
                }
                let tail = mapped - (aligned - start) - bytes;
                if tail > 0 {
                    libc::munmap((aligned + bytes) as *mut libc::c_void, tail);
                }
                // Advice only: where transparent huge pages are off it changes nothing.
                libc::madvise(aligned as *mut libc::c_void, bytes, libc::MADV_HUGEPAGE);
            }
            Some(Reserved { base: NonNull::new(aligned as *mut u8)?, reserved: bytes, writable: 0, len: 0 })
        }

        pub(super) fn as_slice(&self) -> &[u8] {
            // SAFETY: [base, base + len) is writable (so mapped) and initialised (zero-filled pages
            // or written bytes).
            unsafe { std::slice::from_raw_parts(self.base.as_ptr(), self.len) }
        }

        pub(super) fn as_mut_slice(&mut self) -> &mut [u8] {
            // SAFETY: as in `as_slice`, and `&mut self` makes the access exclusive.
            unsafe { std::slice::from_raw_parts_mut(self.base.as_ptr(), self.len) }
        }

        /// Grows to `len` bytes (new bytes are zero); false, with nothing changed, when that is
        /// past the reservation or the system refuses to make the room writable.
        pub(super) fn try_grow(&mut self, len: usize) -> bool {
            if len > self.reserved || len < self.len {
                return false;
            }
            if len > self.writable {
                let writable = len.max(2 * self.writable).next_multiple_of(HUGE_PAGE).min(self.reserved);
                // SAFETY: [base + writable, base + new writable) lies in our reservation.
                let made = unsafe {
                    libc::mprotect(
                        self.base.as_ptr().add(self.writable).cast(),
                        writable - self.writable,
                        libc::PROT_READ | libc::PROT_WRITE,
                    )
                };
                if made != 0 {
                    return false;
                }
                self.writable = writable;
            }
            // Bytes past `len` were never written since they were last cleared (see drain_front),
            // and fresh anonymous pages are zero.
            self.len = len;
            true
        }

        pub(super) fn drain_front(&mut self, count: usize) {
            let count = count.min(self.len);
            let rest = self.len - count;
            // SAFETY: both ranges lie in [base, base + len); `copy` allows overlap.
            unsafe {
                std::ptr::copy(self.base.as_ptr().add(count), self.base.as_ptr(), rest);
                // Bytes past the new end are zero again, as `try_grow` promises.
                std::ptr::write_bytes(self.base.as_ptr().add(rest), 0, count);
            }
            self.len = rest;
        }
    }

    impl Drop for Reserved {
        fn drop(&mut self) {
            // SAFETY: unmaps exactly the range `reserve` kept; no reference into it outlives `self`.
            unsafe { libc::munmap(self.base.as_ptr().cast(), self.reserved) };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bytes_grow_past_their_capacity_hint_and_drain_from_the_front() {
        let mut bytes = HugePageBytes::with_capacity(10);
        assert!(!bytes.is_reserved(), "a small buffer stays on the heap");
        let pattern: Vec<u8> = (0..=255).cycle().take(RESERVE_FROM + (5 << 20)).collect();
        bytes.extend_from_slice(&pattern[..100]);
        bytes.extend_from_slice(&pattern[100..]);
        #[cfg(target_os = "linux")]
        assert!(bytes.is_reserved(), "a large one moves into a reservation");
        assert_eq!(&bytes[..], &pattern[..]);
        bytes.drain_front(3 << 20);
        assert_eq!(&bytes[..], &pattern[3 << 20..]);
        // Room freed at the end reads as zero when grown into again.
        let fresh = bytes.extend_zeroed(3 << 20);
        assert!(fresh.iter().all(|&b| b == 0));
        fresh[0] = 7;
        assert_eq!(bytes.len(), pattern.len());
        assert_eq!(bytes[pattern.len() - (3 << 20)], 7);
        let copy = bytes.clone();
        assert_eq!(&copy[..], &bytes[..]);
        #[cfg(target_os = "linux")]
        assert!(HugePageBytes::with_capacity(RESERVE_FROM).is_reserved());
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn a_full_reservation_moves_to_the_heap_with_its_bytes() {
        let reserved = reserved::Reserved::reserve(2 << 20).expect("a reservation");
        let mut bytes = HugePageBytes { storage: Storage::Reserved(reserved), heap_only: false };
        bytes.extend_from_slice(&vec![3u8; 2 << 20]);
        assert!(bytes.is_reserved(), "it fits exactly");
        bytes.extend_from_slice(&[4u8; 10]);
        assert!(!bytes.is_reserved());
        assert_eq!(bytes.len(), (2 << 20) + 10);
        assert!(bytes[..2 << 20].iter().all(|&b| b == 3));
        assert_eq!(&bytes[2 << 20..], &[4u8; 10][..]);
    }
}
