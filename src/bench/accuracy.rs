//! Error against run time (being written).
