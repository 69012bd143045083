//! The `ecm-lcd` command line ([`cli`]): a thin shell over the library.

mod cli;

fn main() -> std::process::ExitCode {
    cli::main()
}
