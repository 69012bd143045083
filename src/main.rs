//! The `ecm-lcd` command line: everything happens in the library.

/// candle allocates a fresh buffer for every op's output; mimalloc hands freed ones back
/// without returning them to the OS, so a frame does not page-fault its activations in again.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> std::process::ExitCode {
    ecm_lcd::cli::main()
}
