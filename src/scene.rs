//! The scene description (to be written).
