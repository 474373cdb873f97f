//! Cameras (to be written).
