//! Loading the ONNX Runtime library (once per process) and the one `ort` environment every
//! session shares.
//!
//! `ort` is built with `load-dynamic`: nothing is linked at build time, the shared library is
//! opened at run time from an explicit path (a configuration value) or `ORT_DYLIB_PATH`. Every
//! way this can go wrong (no path, no file, not a library, a library older than the 1.31 API the
//! bindings need) is a [`SceneError::Runtime`] naming the path, never a panic; a failed attempt
//! leaves nothing behind, so a later call with a good path still works. Once a library is loaded
//! it stays for the life of the process (a shared library cannot be swapped), and a request for a
//! *different* explicit path is an error rather than being silently ignored.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock};

use ort::environment::Environment;

use crate::scene::SceneError;

/// The environment variable naming the ONNX Runtime shared library.
pub const ORT_DYLIB_ENV: &str = "ORT_DYLIB_PATH";

/// The oldest ONNX Runtime the bindings accept (its C API version 31, i.e. 1.31.x).
pub const MIN_ORT_VERSION: &str = "1.31";

/// Where the library came from, once loaded.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RuntimeInfo {
    /// The library file (absolute, symlinks resolved).
    pub library: PathBuf,
    /// ONNX Runtime's build description (`ORT Build Info: git-branch=rel-1.31.1, ...`).
    pub build_info: String,
}

struct Runtime {
    env: Environment,
    info: RuntimeInfo,
}

static RUNTIME: OnceLock<Runtime> = OnceLock::new();
static INIT: Mutex<()> = Mutex::new(());

const HINT: &str = "mpiflow needs ONNX Runtime >= 1.31 as a shared library, e.g. from the PyPI wheel \
                    onnxruntime==1.31.1: run `eval \"$(bash tools/setup_python.sh)\"` to set ORT_DYLIB_PATH";

/// The library path to load: `configured` if given, else the value of `ORT_DYLIB_PATH` (`env`).
/// An empty value counts as unset.
pub(crate) fn resolve_library_path(
    configured: Option<&Path>,
    env: Option<std::ffi::OsString>,
) -> Result<PathBuf, SceneError> {
    if let Some(p) = configured.filter(|p| !p.as_os_str().is_empty()) {
        return Ok(p.to_path_buf());
    }
    match env.filter(|v| !v.is_empty()) {
        Some(v) => Ok(PathBuf::from(v)),
        None => Err(SceneError::Runtime(format!(
            "no ONNX Runtime library configured: set {ORT_DYLIB_ENV} or the model's runtime library path ({HINT})"
        ))),
    }
}

/// Loads ONNX Runtime from `library` (or `ORT_DYLIB_PATH` when `None`) unless it is already
/// loaded, and returns where it came from. Safe to call from several threads and many times.
pub fn init_runtime(library: Option<&Path>) -> Result<RuntimeInfo, SceneError> {
    runtime(library).map(|rt| rt.info.clone())
}

/// The loaded runtime, if any (without trying to load one).
pub fn runtime_info() -> Option<RuntimeInfo> {
    RUNTIME.get().map(|rt| rt.info.clone())
}

/// The shared environment, loading the library first if needed.
pub(crate) fn environment(library: Option<&Path>) -> Result<&'static Environment, SceneError> {
    runtime(library).map(|rt| &rt.env)
}

fn runtime(library: Option<&Path>) -> Result<&'static Runtime, SceneError> {
    let _guard = INIT.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
    if let Some(rt) = RUNTIME.get() {
        // Already loaded: any request without an explicit path, or for the same file, is fine.
        let Some(requested) = library.filter(|p| !p.as_os_str().is_empty()) else {
            return Ok(rt);
        };
        let same = std::fs::canonicalize(requested).map(|p| p == rt.info.library).unwrap_or(false);
        if same {
            return Ok(rt);
        }
        return Err(SceneError::Runtime(format!(
            "already loaded from {} in this process; cannot also load {}",
            rt.info.library.display(),
            requested.display()
        )));
    }
    let requested = resolve_library_path(library, std::env::var_os(ORT_DYLIB_ENV))?;
    if !requested.is_file() {
        return Err(SceneError::Runtime(format!(
            "library {} does not exist or is not a file ({HINT})",
            requested.display()
        )));
    }
    let path = std::fs::canonicalize(&requested)
        .map_err(|e| SceneError::Runtime(format!("cannot resolve {}: {e}", requested.display())))?;
    let loaded = catch_unwind(AssertUnwindSafe(|| -> Result<(Environment, String), String> {
        let builder = ort::init_from(&path).map_err(|e| e.to_string())?;
        let env = builder
            .with_name("mpiflow")
            .with_telemetry(false)
            .build()
            .map_err(|e| format!("cannot create the ONNX Runtime environment: {e}"))?;
        Ok((env, ort::info().trim().to_string()))
    }));
    let (env, build_info) = match loaded {
        Ok(Ok(v)) => v,
        Ok(Err(msg)) => {
            return Err(SceneError::Runtime(format!("cannot load {}: {msg} ({HINT})", path.display())));
        }
        Err(panic) => {
            let msg = panic
                .downcast_ref::<String>()
                .map(String::as_str)
                .or_else(|| panic.downcast_ref::<&str>().copied())
                .unwrap_or("unknown panic");
            return Err(SceneError::Runtime(format!(
                "loading {} failed inside the ort bindings: {msg} ({HINT})",
                path.display()
            )));
        }
    };
    let info = RuntimeInfo { library: path, build_info };
    Ok(RUNTIME.get_or_init(|| Runtime { env, info }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn configured_path_wins_then_env_then_error() {
        let p = resolve_library_path(Some(Path::new("/a/lib.so")), Some("/b/lib.so".into())).unwrap();
        assert_eq!(p, PathBuf::from("/a/lib.so"));
        let p = resolve_library_path(None, Some("/b/lib.so".into())).unwrap();
        assert_eq!(p, PathBuf::from("/b/lib.so"));
        let p = resolve_library_path(Some(Path::new("")), Some("/b/lib.so".into())).unwrap();
        assert_eq!(p, PathBuf::from("/b/lib.so"));
        for env in [None, Some("".into())] {
            let e = resolve_library_path(None, env).unwrap_err().to_string();
            assert!(e.contains("ORT_DYLIB_PATH") && e.contains("setup_python.sh"), "{e}");
        }
    }
}
