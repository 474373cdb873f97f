//! The `irid` binary: a thin shell over [`irid::cli`].

fn main() -> std::process::ExitCode {
    irid::cli::main()
}
