//! The tunable-filter controller (to be written).
