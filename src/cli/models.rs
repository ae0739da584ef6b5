//! `mpiflow models`: the named scene models (`list`), fetching one into the hub cache (`fetch`),
//! and checking a model on this machine (`check`: its contract, its time per photo, a depth
//! preview).

use std::path::PathBuf;
use std::time::Instant;

use clap::{Args, Subcommand};
use mpiflow::io::image::{load_rgb, ImageLimits, RgbImage};
use mpiflow::scene::hub::{sha256_file, Hub};
use mpiflow::scene::registry::{self, Role};

use super::CliError;

#[derive(Subcommand, Debug)]
pub enum ModelsCommand {
    /// The named models: name, role, licence, hub file, and whether it is in the cache.
    List,
    /// Download a named model into the hub cache (verified by its SHA-256) and print its path.
    Fetch {
        /// A name from `mpiflow models list`.
        name: String,
    },
    /// Load a depth model (NAME or FILE), print the contract it runs with, time it on a photo
    /// and write the photo's depth preview (PNG, white = near).
    Check(CheckArgs),
}

#[derive(Args, Debug)]
pub struct CheckArgs {
    /// A name from `mpiflow models list`, or an ONNX file (with its optional FILE.toml manifest).
    model: PathBuf,
    /// The photo (default: a 640x480 grey image).
    #[arg(long, value_name = "PHOTO")]
    image: Option<PathBuf>,
    /// Timed runs after the first (warm-up) run.
    #[arg(long, value_name = "N", default_value_t = 3, value_parser = clap::value_parser!(u64).range(1..=100))]
    runs: u64,
    /// The depth preview (default: depth-preview.png).
    #[arg(long, value_name = "FILE.png", default_value = "depth-preview.png")]
    out: PathBuf,
}

pub fn run(c: ModelsCommand) -> Result<(), CliError> {
    let hub = Hub::from_env();
    match c {
        ModelsCommand::List => {
            for e in registry::registry()? {
                let file = e.hub_file();
                let cached = hub.cached_path(&file);
                let state =
                    if cached.is_file() { format!("cached at {}", cached.display()) } else { "not cached".into() };
                println!("{}  ({}, {})  {}", e.name, e.role, e.licence, e.description);
                println!("    {} -> {state}", hub.url(&file));
                println!("    sha256 {}; {}", e.sha256, e.contract.describe(e.role));
            }
            println!(
                "hub cache: {}{}",
                hub.cache.display(),
                if hub.offline { " (HF_HUB_OFFLINE: cache only)" } else { "" }
            );
            Ok(())
        }
        ModelsCommand::Fetch { name } => {
            let r = registry::resolve(std::path::Path::new(&name), role_of(&name)?, &hub, true)?;
            println!("{}", r.path.display());
            Ok(())
        }
        ModelsCommand::Check(a) => check(&a, &hub),
    }
}

/// The role of a registry name (an unknown name is an error listing the names).
fn role_of(name: &str) -> Result<Role, CliError> {
    match registry::find(name)? {
        Some(e) => Ok(e.role),
        None => {
            let names: Vec<String> = registry::registry()?.into_iter().map(|e| e.name).collect();
            Err(CliError(format!("{name}: no model of that name (named models: {})", names.join(", "))))
        }
    }
}

fn check(a: &CheckArgs, hub: &Hub) -> Result<(), CliError> {
    let r = registry::resolve(&a.model, Role::Depth, hub, true)?;
    println!(
        "model: {} ({} bytes, sha256 {})",
        r.path.display(),
        std::fs::metadata(&r.path)?.len(),
        sha256_file(&r.path)?
    );
    match &r.entry {
        Some(e) => println!("registry: {} ({}), {}@{} {}", e.name, e.licence, e.repo, e.revision, e.file),
        None if registry::manifest_path(&r.path).is_file() => {
            println!("manifest: {}", registry::manifest_path(&r.path).display());
        }
        None => println!("manifest: none (the default contract)"),
    }
    println!("contract: {}", r.contract.describe(Role::Depth));
    let t = Instant::now();
    let model = registry::load_depth(&r)?;
    println!("loaded and warmed up in {:.0} ms", t.elapsed().as_secs_f64() * 1e3);
    let image = match &a.image {
        Some(p) => load_rgb(p, &ImageLimits::default()).map_err(|e| CliError(format!("--image: {e}")))?,
        None => RgbImage { width: 640, height: 480, data: vec![0.5; 640 * 480 * 3] },
    };
    // a first run (allocations, caches), then the timed ones
    let mut disparity = model.estimate(&image)?;
    let t = Instant::now();
    for _ in 0..a.runs {
        disparity = model.estimate(&image)?;
    }
    let ms = t.elapsed().as_secs_f64() * 1e3 / a.runs as f64;
    println!(
        "{ms:.0} ms per photo ({}x{} photo, mean of {} runs after one untimed run, {} threads available)",
        image.width,
        image.height,
        a.runs,
        std::thread::available_parallelism().map_or(1, usize::from)
    );
    let pixels: Vec<u8> = disparity.data.iter().map(|&d| (d.clamp(0.0, 1.0) * 255.0).round() as u8).collect();
    let preview = image::GrayImage::from_raw(disparity.width as u32, disparity.height as u32, pixels)
        .ok_or_else(|| CliError("the depth map has the wrong size".into()))?;
    preview.save(&a.out).map_err(|e| CliError(format!("{}: {e}", a.out.display())))?;
    println!("depth preview: {} (white = near)", a.out.display());
    Ok(())
}
