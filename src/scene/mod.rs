//! The per-source scene: depth, MPI and instance masks, from models or given with the source.

pub mod masks;
