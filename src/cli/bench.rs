//! `mpiflow bench render` (speed) and `mpiflow bench accuracy` (error against run time).

use super::CliError;
use clap::{Args, Subcommand};
use mpiflow::bench::{bench_render, peak_rss_mib, RenderBenchConfig};
use mpiflow::render::{Mode, Skip};

#[derive(Subcommand, Debug)]
pub enum BenchCommand {
    /// Median time of image + flow + depth renders of a synthetic MPI.
    Render(RenderBench),
}

#[derive(Args, Debug)]
pub struct RenderBench {
    #[arg(long, default_value_t = 640)]
    width: usize,
    #[arg(long, default_value_t = 480)]
    height: usize,
    #[arg(long, default_value_t = 32)]
    planes: usize,
    #[arg(long, default_value_t = 10)]
    runs: usize,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    #[arg(long, default_value = "exact")]
    mode: Mode,
    /// Also time each work-skipping variant separately.
    #[arg(long)]
    variants: bool,
}

pub fn run(cmd: BenchCommand) -> Result<(), CliError> {
    match cmd {
        BenchCommand::Render(b) => render(b),
    }
}

fn render(b: RenderBench) -> Result<(), CliError> {
    if b.width == 0 || b.height == 0 || b.planes == 0 || b.width * b.height > 64 << 20 || b.planes > 256 {
        return Err(CliError("bench sizes must be positive, at most 64 Mpx and 256 planes".into()));
    }
    let threads = b.threads.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build()?;
    let skip = if b.mode == Mode::Exact { Skip::DEFAULT } else { Skip::NONE };
    let mut variants = vec![("default", skip)];
    if b.variants && b.mode == Mode::Exact {
        variants = vec![
            ("no skipping", Skip::NONE),
            ("tile skipping", Skip { tiles: true, ..Skip::NONE }),
            ("early stop T<1e-4", Skip { transmittance_eps: 1e-4, ..Skip::NONE }),
            ("both (default)", Skip::DEFAULT),
        ];
    }
    for (name, skip) in variants {
        let cfg =
            RenderBenchConfig { width: b.width, height: b.height, planes: b.planes, runs: b.runs, mode: b.mode, skip };
        let t = pool.install(|| bench_render(&cfg));
        if b.variants {
            print!("{name:>20}: ");
        }
        println!(
            "median {:.1} ms (min {:.1}, max {:.1}) over {} runs, {threads} threads",
            t.median, t.min, t.max, t.runs
        );
    }
    if let Some(m) = peak_rss_mib() {
        println!("peak memory {m:.0} MiB ({}x{}, {} planes, mode {:?})", b.width, b.height, b.planes, b.mode);
    }
    Ok(())
}
