//! The `ecm-lcd` command line: everything happens in the library.

fn main() -> std::process::ExitCode {
    ecm_lcd::cli::main()
}
