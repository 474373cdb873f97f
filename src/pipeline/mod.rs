//! The streaming pipeline (to be written).
