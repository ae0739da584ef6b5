//! mpiflow: realistic optical-flow training samples from still photos via multiplane images
//! (MPI-Flow, ICCV 2023). The library holds the geometry, the MPI type and its construction,
//! the renderer, file formats and benchmarks; the `mpiflow` binary is a thin CLI over it.

pub mod bench;
pub mod buf;
pub mod export;
pub mod failure;
pub mod geometry;
pub mod hash;
pub mod io;
pub mod isa;
pub mod mpi;
pub mod raster;
pub mod render;
pub mod rng;
pub mod sample;
pub mod scene;
pub mod service;
pub mod source;
