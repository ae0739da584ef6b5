//! The `mpiflow` command line: a thin layer that parses arguments, calls the library and maps
//! every failure to a one-line message and exit code 2.

mod cli;

fn main() {
    std::process::exit(cli::run());
}
