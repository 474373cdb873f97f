//! Command-line front ends (to be written).

/// Entry point of the `irid` binary.
pub fn main() -> std::process::ExitCode {
    std::process::ExitCode::SUCCESS
}
