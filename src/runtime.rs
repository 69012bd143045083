//! Process-wide compute settings. candle re-reads the CPU count on every matmul unless the
//! rayon pool size is fixed, so every entry point calls [`init_threads`] first.

use std::sync::OnceLock;

static THREADS: OnceLock<usize> = OnceLock::new();

/// Fixes the number of compute threads (rayon's global pool, used by candle and our kernels).
/// `None` means the number of CPUs. Only the first call has an effect; returns the count in force.
pub fn init_threads(threads: Option<usize>) -> usize {
    *THREADS.get_or_init(|| {
        let n = threads
            .filter(|&n| n > 0)
            .unwrap_or_else(|| std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1));
        // candle's CPU backend asks this variable for its thread count.
        std::env::set_var("RAYON_NUM_THREADS", n.to_string());
        let _ = rayon::ThreadPoolBuilder::new().num_threads(n).build_global();
        n
    })
}
