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

/// Keeps freed memory in the process instead of handing it back to the kernel (glibc only; a
/// no-op elsewhere). Training and the forward pass allocate and free tensors of 0.1 to 30 MB
/// many times a second. By default glibc maps each one afresh and unmaps it when freed, and it
/// trims the heap top once 2x the (dynamic) mmap threshold is free, so the same memory is faulted
/// in again and again: about a quarter of a training run's CPU time was the kernel's (page faults,
/// unmaps and their TLB shootdowns), and on this project's VMs, whose balloon takes freed pages
/// back, a page faulted in afresh costs about 13 us. With allocations below 32 MB (glibc's
/// largest allowed threshold) served from the heap and up to 1 GB of free heap kept, a 64 px
/// training run spent 1.9 s instead of 6.1 s in the kernel (22.5 -> 21.5 s wall). Larger
/// allocations (the descriptor matrix) are still mapped, so growing them stays a remap.
pub fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        static ONCE: std::sync::Once = std::sync::Once::new();
        ONCE.call_once(|| {
            // SAFETY: mallopt only changes allocator parameters and is thread-safe.
            unsafe {
                libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
                libc::mallopt(libc::M_TRIM_THRESHOLD, 1 << 30);
            }
        });
    }
}

/// Runs `f` on a worker of rayon's global pool and waits for it. The fast kernels open dozens of
/// parallel regions per forward pass; opened from a thread outside the pool, each one is handed
/// across threads and waited for (the caller sleeps, the workers wake up), which made a 224² forward
/// pass take 16 ms from the pipeline where it takes 9.8 ms from a worker.
pub fn on_worker<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    rayon::scope(|_| f())
}

/// How long a worker kept hot by [`with_hot_workers`] polls without finding work before it stops
/// (longer than the sequential stretches of a forward pass, which are tens of microseconds).
pub const HOT_WORKER_PATIENCE: std::time::Duration = std::time::Duration::from_millis(2);

thread_local! {
    /// Set while this thread runs the `f` of a [`with_hot_workers`]: a nested call (the forward
    /// pass inside a keyframe's processing) finds the workers hot already and just runs.
    static KEEPING_HOT: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Sets [`KEEPING_HOT`] for its lifetime (cleared on unwinding too).
struct KeepingHot;

impl KeepingHot {
    fn enter() -> Self {
        KEEPING_HOT.set(true);
        KeepingHot
    }
}

impl Drop for KeepingHot {
    fn drop(&mut self) {
        KEEPING_HOT.set(false);
    }
}

/// Runs `f` on the current rayon worker while every other worker of its pool busy-waits for work
/// (polling with `rayon::yield_now`, which runs whatever they can steal) until `f` returns.
///
/// A forward pass opens about a hundred short parallel regions with short sequential stretches
/// between them. Idle rayon workers go to sleep after a few microseconds, and on a virtual machine
/// waking one means waking a halted virtual CPU, which cost more than the region saved: 2 threads
/// were no faster than 1. Kept polling, they pick up each region's work at once (ONNX Runtime's
/// thread pool spins between operators for the same reason). Outside a pool, or with one thread,
/// `f` simply runs. A poller that has found nothing for [`HOT_WORKER_PATIENCE`] stops: it may have
/// been started inside a wait of its own (a worker waiting on a stolen job runs other jobs), where
/// polling until `f` returned could wait on itself. A nested call from `f`'s thread just runs: the
/// pipeline keeps the workers hot for a whole keyframe (forward pass, then the search's parallel
/// scan), and the forward pass inside it makes the nested call.
pub fn with_hot_workers<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    use std::sync::atomic::{AtomicBool, Ordering};
    let Some(caller) = rayon::current_thread_index() else { return f() };
    let others = rayon::current_num_threads().saturating_sub(1);
    if others == 0 || KEEPING_HOT.get() {
        return f();
    }
    let done = AtomicBool::new(false);
    rayon::scope(|scope| {
        for _ in 0..others {
            scope.spawn(|_| {
                // The caller may run this job itself while it waits inside `f`; spinning there would
                // never return to `f`, so only other workers poll.
                if rayon::current_thread_index() == Some(caller) {
                    return;
                }
                let mut last_work = std::time::Instant::now();
                while !done.load(Ordering::Acquire) {
                    if rayon::yield_now() == Some(rayon::Yield::Executed) {
                        last_work = std::time::Instant::now();
                    } else if last_work.elapsed() > HOT_WORKER_PATIENCE {
                        return;
                    } else {
                        std::hint::spin_loop();
                    }
                }
            });
        }
        let out = {
            let _hot = KeepingHot::enter();
            f()
        };
        done.store(true, Ordering::Release);
        out
    })
}

/// Candidate locations of the shared data folder (models, ImageNet samples, TUM frames):
/// `$ECM_LCD_SHARED` alone when set, else `./../shared`, `./shared`, and the `shared` folder
/// beside the source tree this binary was built from. Only existing folders are returned.
pub fn shared_dirs() -> Vec<std::path::PathBuf> {
    if let Some(d) = std::env::var_os("ECM_LCD_SHARED") {
        let d = std::path::PathBuf::from(d);
        return if d.is_dir() { vec![d] } else { vec![] };
    }
    let dirs: Vec<std::path::PathBuf> =
        vec!["../shared".into(), "shared".into(), std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared")];
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

/// `--threads`: 1 to 1024. (A `usize`, as the subcommands that take their own `--threads` lists
/// read the same argument id.)
pub fn parse_threads(text: &str) -> Result<usize, String> {
    match text.parse::<usize>() {
        Ok(n) if (1..=1024).contains(&n) => Ok(n),
        _ => Err(format!("{text:?} is not a thread count from 1 to 1024")),
    }
}

/// What every program of the crate sets up first: the log (see [`default_log_filter`]), the compute
/// threads and the allocator's handling of freed memory.
pub fn init_process(threads: Option<usize>) {
    env_logger::Builder::from_env(env_logger::Env::default().default_filter_or(default_log_filter(std::env::args())))
        .format_timestamp_millis()
        .init();
    init_threads(threads);
    keep_freed_memory();
}

/// The log filter when `RUST_LOG` is unset: ecm-lcd's own lines at `info` (or at the level of a ROS
/// `--log-level LEVEL` among the arguments), dependencies at `warn`, RustDDS at `error` (it logs
/// protocol details as `info` and `warn`, hundreds of lines a second with some peers), and
/// ros2-client's ROS_DISTRO check at `error` (ecm-lcd needs no ROS install).
pub(crate) fn default_log_filter(args: impl Iterator<Item = String>) -> String {
    let args: Vec<String> = args.collect();
    let level = args
        .windows(2)
        .filter(|pair| pair[0] == "--log-level")
        .filter_map(|pair| {
            // `[logger:=]LEVEL`; rcl's `fatal` is `error` here.
            let level = pair[1].rsplit(":=").next()?.to_ascii_lowercase();
            match level.as_str() {
                "debug" | "info" | "warn" | "error" => Some(level),
                "fatal" => Some("error".to_string()),
                _ => None,
            }
        })
        .next_back()
        .unwrap_or_else(|| "info".to_string());
    format!("ecm_lcd={level},rustdds=error,ros2_client::distributions=error,warn")
}

#[cfg(test)]
mod tests {
    use super::default_log_filter;
    use rayon::prelude::*;

    /// Nested parallel work inside `f` completes with hot workers on pools of 2 to 4 threads (a
    /// poller started inside a nested wait must not wait on itself).
    #[test]
    fn hot_workers_finish_nested_parallel_work() {
        for threads in 2..=4 {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            let started = std::time::Instant::now();
            for round in 0..200u64 {
                let sum = pool.install(|| {
                    super::with_hot_workers(|| {
                        (0..64u64)
                            .into_par_iter()
                            .map(|i| (0..100u64).into_par_iter().map(|j| i * j + round).sum::<u64>())
                            .sum::<u64>()
                    })
                });
                let expected: u64 = (0..64u64).map(|i| (0..100u64).map(|j| i * j + round).sum::<u64>()).sum();
                assert_eq!(sum, expected, "{threads} threads, round {round}");
                // Nested: the inner call runs inside the outer one's hot period.
                let (inner, flag_inside, flag_after) = pool.install(|| {
                    let (inner, flag_inside) = super::with_hot_workers(|| {
                        let inner =
                            super::with_hot_workers(|| (0..1000u64).into_par_iter().map(|i| i + round).sum::<u64>());
                        (inner, super::KEEPING_HOT.get())
                    });
                    (inner, flag_inside, super::KEEPING_HOT.get())
                });
                assert_eq!(inner, (0..1000u64).map(|i| i + round).sum::<u64>());
                assert!(flag_inside, "the outer call marks its thread as keeping the workers hot");
                assert!(!flag_after, "cleared when the call returns");
            }
            assert!(
                started.elapsed() < std::time::Duration::from_secs(20),
                "{threads} threads: {:?}",
                started.elapsed()
            );
        }
    }

    #[test]
    fn logs_are_ours_at_info_and_dependencies_at_warn_unless_a_level_is_asked_for() {
        let args = |list: &[&str]| list.iter().map(|s| s.to_string()).collect::<Vec<_>>().into_iter();
        let ours = |filter: String| filter.split(',').next().unwrap().to_string();
        let filter = default_log_filter(args(&["ecm-lcd", "node"]));
        assert_eq!(filter, "ecm_lcd=info,rustdds=error,ros2_client::distributions=error,warn");
        assert_eq!(
            ours(default_log_filter(args(&["ecm-lcd", "node", "--ros-args", "--log-level", "debug"]))),
            "ecm_lcd=debug"
        );
        assert_eq!(
            ours(default_log_filter(args(&["ecm-lcd", "node", "--ros-args", "--log-level", "ecm_lcd:=WARN"]))),
            "ecm_lcd=warn"
        );
        assert_eq!(
            ours(default_log_filter(args(&["ecm-lcd", "node", "--ros-args", "--log-level", "fatal"]))),
            "ecm_lcd=error"
        );
        assert_eq!(
            ours(default_log_filter(args(&["ecm-lcd", "node", "--ros-args", "--log-level", "loud"]))),
            "ecm_lcd=info"
        );
    }
}
