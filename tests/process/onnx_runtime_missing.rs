//! ONNX Runtime library errors: a missing file, a file that is not a library, a library older
//! than the bindings need, each a `SceneError::Runtime` naming the path (never a panic), and a
//! failed attempt does not stop a later good one. A test binary of its own because the library is
//! loaded once per process: the steps run in order in one test.
//!
//! The last step needs `ORT_DYLIB_PATH` (run `bash tools/test.sh`); the "too old" step builds a
//! fake library with the system C compiler `cc` (which Rust needs for linking anyway).

use std::path::{Path, PathBuf};
use std::process::Command;

use mpiflow::scene::onnx::{init_runtime, runtime_info, OnnxDepth, OnnxDepthConfig};
use mpiflow::scene::SceneError;

const HOW: &str = "run the tests with `bash tools/test.sh` (or `eval \"$(bash tools/setup_python.sh)\"` first)";

#[track_caller]
fn runtime_error<T: std::fmt::Debug>(result: Result<T, SceneError>, needles: &[&str]) -> String {
    let err = result.expect_err("expected an error");
    assert!(matches!(err, SceneError::Runtime(_)), "not a Runtime error: {err:?}");
    let msg = err.to_string();
    for n in needles {
        assert!(msg.contains(n), "the message lacks {n:?}: {msg}");
    }
    msg
}

/// A shared library exporting `OrtGetApiBase` that reports ONNX Runtime 1.10.0.
fn fake_old_library(dir: &Path) -> PathBuf {
    let src = dir.join("fake_ort.c");
    let lib = dir.join("libfake_onnxruntime.so");
    std::fs::write(
        &src,
        r#"
typedef struct { const void *(*GetApi)(unsigned); const char *(*GetVersionString)(void); } OrtApiBase;
static const void *get_api(unsigned version) { (void)version; return 0; }
static const char *version_string(void) { return "1.10.0"; }
static const OrtApiBase base = { get_api, version_string };
const OrtApiBase *OrtGetApiBase(void) { return &base; }
"#,
    )
    .unwrap();
    let out = Command::new("cc")
        .args(["-shared", "-fPIC", "-o"])
        .arg(&lib)
        .arg(&src)
        .output()
        .expect("cannot run the C compiler `cc` to build the fake library");
    assert!(out.status.success(), "cc failed: {}", String::from_utf8_lossy(&out.stderr));
    lib
}

#[test]
fn bad_libraries_are_errors_and_a_good_one_still_loads() {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("onnx_runtime_missing_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    assert_eq!(runtime_info(), None);

    // No such file.
    let missing = dir.join("libonnxruntime.so.0.0.0");
    runtime_error(init_runtime(Some(&missing)), &[missing.to_str().unwrap(), "does not exist", "ORT_DYLIB_PATH"]);

    // A file that is not a shared library.
    let text = dir.join("not_a_library.so");
    std::fs::write(&text, "hello").unwrap();
    runtime_error(init_runtime(Some(&text)), &["cannot load", "not_a_library.so"]);

    // A library too old for the bindings.
    let old = fake_old_library(&dir);
    runtime_error(init_runtime(Some(&old)), &["libfake_onnxruntime.so", "1.10.0", "1.31"]);

    // The models report the same errors (not a panic, not a model error).
    let mut cfg = OnnxDepthConfig::new(dir.join("depth.onnx"));
    cfg.runtime_library = Some(missing.clone());
    runtime_error(OnnxDepth::new(cfg), &["does not exist"]);
    assert_eq!(runtime_info(), None, "nothing was loaded");

    // After all that, the real library loads.
    let real = std::env::var_os("ORT_DYLIB_PATH")
        .filter(|v| !v.is_empty())
        .unwrap_or_else(|| panic!("ORT_DYLIB_PATH is not set: {HOW}"));
    let info = init_runtime(Some(Path::new(&real))).unwrap();
    assert_eq!(info.library, std::fs::canonicalize(&real).unwrap());
    assert_eq!(runtime_info(), Some(info));
    // Once loaded, another library cannot replace it.
    runtime_error(init_runtime(Some(&old)), &["already loaded", "libfake_onnxruntime.so"]);
    // With the runtime loaded, a missing model file is a model error naming it.
    let err = OnnxDepth::new(OnnxDepthConfig::new(dir.join("depth.onnx"))).unwrap_err();
    assert!(matches!(err, SceneError::Model { .. }) && err.to_string().contains("depth.onnx"), "{err}");
}
