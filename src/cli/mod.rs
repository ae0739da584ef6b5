//! Argument definitions and dispatch of the `mpiflow` subcommands.

mod bake;
mod bench;
mod bench_serve;
mod bench_soak;
mod connect;
mod generate;
mod health;
mod kernels;
mod models;
mod pull;
mod render;
mod scene_flags;
mod serve;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "mpiflow",
    version,
    about = "Optical-flow training data from still photos via multiplane images (MPI-Flow)"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run the scene models once per source item and write a folder that serves with no model.
    Bake(bake::BakeArgs),
    /// Render one novel view with its flow, depth and masks from an MPI (.npz) or an RGB-D pair.
    Render(render::RenderArgs),
    /// Benchmarks: render speed, and error against run time.
    #[command(subcommand)]
    Bench(bench::BenchCommand),
    /// Write a training set to disk (flo, kitti, webdataset or stereo layout) with preview sheets.
    Generate(generate::GenerateArgs),
    /// Serve endless reproducible sample streams over gRPC (mpiflow.v1.MpiFlow).
    Serve(serve::ServeArgs),
    /// Pull samples from a server (optionally saving them in the flo layout) and report the rate.
    Pull(pull::PullArgs),
    /// gRPC health check of a server: exit code 0 only when it is SERVING.
    Health(health::HealthArgs),
    /// Named scene models: list them, fetch one into the hub cache, check one on a photo.
    #[command(subcommand)]
    Models(models::ModelsCommand),
}

/// A failure the user can act on: printed as one line, exit code 2.
#[derive(Debug)]
pub struct CliError(pub String);

impl<E: std::fmt::Display> From<E> for CliError {
    fn from(e: E) -> Self {
        CliError(e.to_string())
    }
}

pub fn run() -> i32 {
    let cli = match Cli::try_parse() {
        Ok(c) => c,
        Err(e) if e.use_stderr() => {
            // clap's whole message: the problem, the usage line, a suggestion for a near miss
            // and the pointer to --help; exit code 2
            let _ = e.print();
            return 2;
        }
        Err(e) => {
            let _ = e.print();
            return 0;
        }
    };
    // the hot loops' instruction set, chosen once: a wrong MPIFLOW_SIMD is an error up front
    if let Err(e) = mpiflow::isa::init() {
        eprintln!("error: {e}");
        return 2;
    }
    let result = match cli.command {
        Command::Bake(a) => bake::run(a),
        Command::Render(a) => render::run(a),
        Command::Bench(b) => bench::run(b),
        Command::Generate(a) => generate::run(a),
        Command::Serve(a) => serve::run(a),
        Command::Pull(a) => pull::run(a),
        Command::Health(a) => health::run(a),
        Command::Models(c) => models::run(c),
    };
    match result {
        Ok(()) => 0,
        Err(CliError(msg)) => {
            // one printable line: never raw bytes from a file or a request
            eprintln!("error: {}", mpiflow::failure::printable(&msg, 4096));
            2
        }
    }
}

/// Parses exactly `N` comma-separated finite numbers.
pub fn parse_floats<const N: usize>(s: &str) -> Result<[f64; N], String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    if parts.len() != N {
        return Err(format!("expected {N} comma-separated numbers, got {} in `{s}`", parts.len()));
    }
    let mut out = [0.0; N];
    for (o, p) in out.iter_mut().zip(&parts) {
        let v: f64 = p.parse().map_err(|_| format!("`{p}` is not a number"))?;
        if !v.is_finite() {
            return Err(format!("`{p}` is not finite"));
        }
        *o = v;
    }
    Ok(out)
}
