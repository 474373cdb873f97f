//! Hardware behind small traits: cameras and the tunable-filter controller,
//! and recordings of both (MCAP) that replay as a camera and a filter.

pub mod camera;
pub mod filter;
pub mod record;
