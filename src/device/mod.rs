//! Hardware behind small traits: cameras and the tunable-filter controller.

pub mod camera;
pub mod filter;
