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

/// Runs `f` on a worker of rayon's global pool and waits for it. The fast kernels open dozens of
/// parallel regions per forward pass; opened from a thread outside the pool, each one is handed
/// across threads and waited for (the caller sleeps, the workers wake up), which made a 224² forward
/// pass take 16 ms from the pipeline where it takes 9.8 ms from a worker.
pub fn on_worker<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    rayon::scope(|_| f())
}

/// Candidate locations of the shared data folder (models, ImageNet samples, TUM frames):
/// `$ECM_LCD_SHARED` alone when set, else `./../shared`, `./shared`, and the `shared` folder
/// beside the source tree this binary was built from. Only existing folders are returned.
pub fn shared_dirs() -> Vec<std::path::PathBuf> {
    if let Some(d) = std::env::var_os("ECM_LCD_SHARED") {
        let d = std::path::PathBuf::from(d);
        return if d.is_dir() { vec![d] } else { vec![] };
    }
    let mut dirs: Vec<std::path::PathBuf> = Vec::new();
    dirs.push("../shared".into());
    dirs.push("shared".into());
    dirs.push(std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared"));
    let mut seen = Vec::new();
    dirs.into_iter()
        .filter(|d| d.is_dir())
        .filter(|d| {
            let canon = d.canonicalize().unwrap_or_else(|_| d.clone());
            let new = !seen.contains(&canon);
            seen.push(canon);
            new
        })
        .collect()
}
