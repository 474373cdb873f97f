//! Hardware behind small traits: cameras and the tunable-filter controller,
//! recordings of both (MCAP) that replay as a camera and a filter, and the
//! line's configured rig (`line.toml`, the emulated controller).

pub mod camera;
pub mod filter;
pub mod record;
pub mod rig;
