//! VariSpec-compatible filter controller firmware (placeholder; filled by the firmware issue).
#![cfg_attr(not(any(test, feature = "std")), no_std)]
#![forbid(unsafe_code)]
