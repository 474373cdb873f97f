//! Command-line front ends (to be written).
pub mod lctf;

/// Entry point of the `irid` binary.
pub fn main() -> std::process::ExitCode {
    std::process::ExitCode::SUCCESS
}
