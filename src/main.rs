//! The `mpiflow` command line: a thin layer that parses arguments, calls the library and maps
//! every failure to a one-line message and exit code 2.

mod cli;

/// jemalloc with a background thread that returns freed pages to the OS within about a second
/// (`.cargo/config.toml` sets its options), so RSS falls back when the clients that filled the
/// sample buffers leave; glibc's malloc kept them.
#[global_allocator]
static ALLOCATOR: tikv_jemallocator::Jemalloc = tikv_jemallocator::Jemalloc;

fn main() {
    std::process::exit(cli::run());
}
