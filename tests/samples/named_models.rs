//! Named depth models end to end, offline: a loopback HTTP server in the Hugging Face hub's URL
//! layout (`/{repo}/resolve/{revision}/{file}`, with a redirect to a blob URL and the
//! `X-Repo-Commit` header, as the hub answers) serves a model the repo generates
//! (`tools/make_test_models.py`), and a test registry (`MPIFLOW_MODEL_REGISTRY`) points
//! `depth-anything-v2-small` at it with the file's SHA-256 and the built-in entry's contract.
//! Checked through the real binary and the real ONNX Runtime: first use downloads into the hub
//! cache layout and serves; `HF_HUB_OFFLINE=1` serves from the cache; a wrong checksum and an
//! interrupted download keep nothing; offline without the file names the
//! URL and the path; a local FILE runs with its manifest; the built-in contract (names, size,
//! normalisation) runs.
//!
//! Needs `MPIFLOW_PYTHON` (a Python with `onnx`) and `ORT_DYLIB_PATH`: run `bash tools/test.sh`,
//! or `eval "$(bash tools/setup_python.sh)"` first.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, OnceLock};

use mpiflow::io::image::RgbImage;
use mpiflow::scene::registry;

const BIN: &str = env!("CARGO_BIN_EXE_mpiflow");
const HOW: &str = "run the tests with `bash tools/test.sh` (or `eval \"$(bash tools/setup_python.sh)\"` first)";
/// The commit the loopback hub names for `main`.
const COMMIT: &str = "0123456789abcdef0123456789abcdef01234567";
const REPO: &str = "test-org/depth-hub";

fn models() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let python = std::env::var_os("MPIFLOW_PYTHON")
            .filter(|v| !v.is_empty())
            .unwrap_or_else(|| panic!("MPIFLOW_PYTHON is not set: {HOW}"));
        assert!(std::env::var_os("ORT_DYLIB_PATH").is_some_and(|v| !v.is_empty()), "ORT_DYLIB_PATH is not set: {HOW}");
        let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("named_models_{}", std::process::id()));
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/make_test_models.py");
        let out = Command::new(&python).arg(&script).arg(&dir).output().expect("the model script runs");
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        dir
    })
}

fn tmp(name: &str) -> PathBuf {
    let d = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("named-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn sha256(path: &Path) -> String {
    mpiflow::scene::hub::sha256_file(path).unwrap()
}

/// How the loopback hub answers for the model file.
#[derive(Clone, Copy, PartialEq)]
enum Serve {
    /// The whole file.
    Whole,
    /// Other bytes than the pinned ones.
    Tampered,
    /// The declared length, then the connection closed halfway.
    Cut,
}

/// A loopback HTTP/1.1 server in the hub's layout: `/{REPO}/resolve/main/onnx/model.onnx`
/// answers 302 to `/blobs/model` with `X-Repo-Commit`, which answers the bytes as `mode` says.
/// Counts the requests it answered.
struct Hub {
    endpoint: String,
    requests: Arc<AtomicUsize>,
}

fn hub(model: &Path, mode: Serve) -> Hub {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let endpoint = format!("http://{}", listener.local_addr().unwrap());
    let mut body = std::fs::read(model).unwrap();
    if mode == Serve::Tampered {
        body.extend_from_slice(b"tampered");
    }
    let requests = Arc::new(AtomicUsize::new(0));
    let count = requests.clone();
    std::thread::spawn(move || {
        for conn in listener.incoming() {
            let Ok(mut conn) = conn else { continue };
            let mut reader = BufReader::new(conn.try_clone().unwrap());
            let mut request_line = String::new();
            if reader.read_line(&mut request_line).is_err() {
                continue;
            }
            // the headers, up to the empty line
            loop {
                let mut line = String::new();
                if reader.read_line(&mut line).map_or(true, |n| n == 0) || line == "\r\n" {
                    break;
                }
            }
            count.fetch_add(1, Ordering::SeqCst);
            let path = request_line.split_whitespace().nth(1).unwrap_or_default().to_string();
            let _ = if path == format!("/{REPO}/resolve/main/onnx/model.onnx") {
                conn.write_all(
                    format!(
                        "HTTP/1.1 302 Found\r\nLocation: /blobs/model\r\nX-Repo-Commit: {COMMIT}\r\n\
                         Content-Length: 0\r\nConnection: close\r\n\r\n"
                    )
                    .as_bytes(),
                )
            } else if path == "/blobs/model" {
                let head = format!("HTTP/1.1 200 OK\r\nContent-Length: {}\r\nConnection: close\r\n\r\n", body.len());
                let sent = if mode == Serve::Cut { &body[..body.len() / 2] } else { &body[..] };
                conn.write_all(head.as_bytes()).and_then(|()| conn.write_all(sent))
            } else {
                conn.write_all(b"HTTP/1.1 404 Not Found\r\nContent-Length: 0\r\nConnection: close\r\n\r\n")
            };
            let _ = conn.flush();
        }
    });
    Hub { endpoint, requests }
}

/// The built-in contract of `depth-anything-v2-small` (checked against the registry below).
const CONTRACT: &str = "input = \"pixel_values\"\noutput = \"predicted_depth\"\n\
                        output_kind = \"relative-inverse-depth\"\nsize = [518, 518]\nmultiple_of = 14\n\
                        mean = [0.485, 0.456, 0.406]\nstd = [0.229, 0.224, 0.225]\n";

/// A test registry: `depth-anything-v2-small` at the loopback hub's repository, pinned to the
/// SHA-256 of `depth_hub.onnx`, with the built-in entry's contract.
fn test_registry(dir: &Path) -> PathBuf {
    let builtin = registry::find("depth-anything-v2-small").unwrap().expect("the built-in entry");
    let contract: registry::Contract = toml::from_str(CONTRACT).unwrap();
    assert_eq!(contract, builtin.contract, "the test registry keeps the built-in contract");
    let text = format!(
        "[[model]]\nname = \"depth-anything-v2-small\"\nrole = \"depth\"\nrepo = \"{REPO}\"\nrevision = \"main\"\n\
         file = \"onnx/model.onnx\"\nsha256 = \"{}\"\nlicence = \"test\"\n\n[model.contract]\n{CONTRACT}",
        sha256(&models().join("depth_hub.onnx"))
    );
    let path = dir.join("registry.toml");
    std::fs::write(&path, text).unwrap();
    path
}

/// `mpiflow ARGS` with the hub environment: cache under `dir/hf`, the test registry, `endpoint`.
fn mpiflow(dir: &Path, endpoint: &str, offline: bool, args: &[&str]) -> Command {
    let mut c = Command::new(BIN);
    c.args(args)
        .env("HF_HOME", dir.join("hf"))
        .env_remove("HF_HUB_CACHE")
        .env("HF_ENDPOINT", endpoint)
        .env(registry::REGISTRY_ENV, test_registry(dir));
    if offline {
        c.env("HF_HUB_OFFLINE", "1");
    } else {
        c.env_remove("HF_HUB_OFFLINE");
    }
    c
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

/// Every file under `dir` (relative paths), links included.
fn files_under(dir: &Path) -> Vec<String> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let Ok(rd) = std::fs::read_dir(&d) else { continue };
        for e in rd.flatten() {
            let p = e.path();
            if e.file_type().unwrap().is_dir() {
                stack.push(p);
            } else {
                out.push(p.strip_prefix(dir).unwrap().display().to_string());
            }
        }
    }
    out.sort();
    out
}

fn repo_cache(dir: &Path) -> PathBuf {
    dir.join("hf/hub/models--test-org--depth-hub")
}

fn photos(dir: &Path) -> PathBuf {
    let p = dir.join("photos");
    std::fs::create_dir_all(&p).unwrap();
    for i in 0..2u32 {
        let img = image::RgbImage::from_fn(48, 32, |x, y| image::Rgb([(x * 5 + i * 40) as u8, (y * 7) as u8, 90]));
        img.save(p.join(format!("p{i}.png"))).unwrap();
    }
    p
}

/// `serve` until it prints its address, then GetSample 0 and stop it; the sample's image bytes.
fn serve_one_sample(cmd: &mut Command) -> Vec<u8> {
    let mut child = cmd.stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    let Some(addr) = line.trim().strip_prefix("mpiflow serving on ").map(str::to_string) else {
        let mut err = String::new();
        child.stderr.take().unwrap().read_to_string(&mut err).unwrap();
        panic!("the server did not start: {line:?} {err}");
    };
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    let sample = rt.block_on(async {
        let channel =
            tonic::transport::Endpoint::from_shared(format!("http://{addr}")).unwrap().connect().await.unwrap();
        let mut c = mpiflow::service::client::client_for(channel);
        c.get_sample(mpiflow::service::pb::SampleSpec { seed: 1, ..Default::default() }.sample(0)).await
    });
    child.kill().unwrap();
    child.wait().unwrap();
    let s = sample.expect("a sample through the named depth model").into_inner();
    s.tensors.iter().find(|t| t.name == "image2").expect("image2").data.to_vec()
}

#[test]
fn serve_fetches_a_named_model_from_a_mirror_then_serves_from_the_cache_offline() {
    let dir = tmp("serve");
    let model = models().join("depth_hub.onnx");
    let h = hub(&model, Serve::Whole);
    let src = photos(&dir).display().to_string();
    let args = ["serve", "--addr", "127.0.0.1:0", "--log-level", "warn", "--source", &src];
    let args = [&args[..], &["--depth-model", "depth-anything-v2-small"]].concat();
    let first = serve_one_sample(&mut mpiflow(&dir, &h.endpoint, false, &args));
    assert_eq!(h.requests.load(Ordering::SeqCst), 2, "the resolve URL and its redirect");
    // the hub cache layout: the blob by its SHA-256, the snapshot of the commit, the ref of main
    let sha = sha256(&model);
    assert_eq!(
        files_under(&repo_cache(&dir)),
        [format!("blobs/{sha}"), "refs/main".to_string(), format!("snapshots/{COMMIT}/onnx/model.onnx")]
    );
    assert_eq!(std::fs::read_to_string(repo_cache(&dir).join("refs/main")).unwrap(), COMMIT);
    let snapshot = repo_cache(&dir).join(format!("snapshots/{COMMIT}/onnx/model.onnx"));
    assert_eq!(std::fs::read_link(&snapshot).unwrap(), Path::new(&format!("../../../blobs/{sha}")));
    assert_eq!(sha256(&snapshot), sha);
    // offline, with nothing listening at the endpoint: the cache serves, the same bytes
    let closed = "http://127.0.0.1:1";
    let again = serve_one_sample(&mut mpiflow(&dir, closed, true, &args));
    assert_eq!(again, first, "same address, same bytes from the cached model");
    assert_eq!(h.requests.load(Ordering::SeqCst), 2, "nothing fetched twice");
    // `models list` says where it is
    let list = mpiflow(&dir, closed, true, &["models", "list"]).output().unwrap();
    assert!(text(&list.stdout).contains(&format!("cached at {}", snapshot.display())), "{}", text(&list.stdout));
}

fn fetch(dir: &Path, endpoint: &str, offline: bool) -> Output {
    mpiflow(dir, endpoint, offline, &["models", "fetch", "depth-anything-v2-small"]).output().unwrap()
}

#[test]
fn a_wrong_checksum_is_refused_and_nothing_is_kept() {
    let dir = tmp("tampered");
    let h = hub(&models().join("depth_hub.onnx"), Serve::Tampered);
    let out = fetch(&dir, &h.endpoint, false);
    let err = text(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("SHA-256") && err.contains("refused") && err.contains("nothing was kept"), "{err}");
    assert_eq!(files_under(&repo_cache(&dir)), Vec::<String>::new(), "no blob, no partial file, no snapshot");
}

/// An interrupted download keeps nothing (no partial file left to fill a disk); a later
/// download from a mirror that sends the whole file again works.
#[test]
fn an_interrupted_download_keeps_nothing_and_a_later_one_works() {
    let dir = tmp("cut");
    let model = models().join("depth_hub.onnx");
    let cut = hub(&model, Serve::Cut);
    let out = fetch(&dir, &cut.endpoint, false);
    let err = text(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("the download ended after") && err.contains("nothing was kept"), "{err}");
    assert_eq!(files_under(&repo_cache(&dir)), Vec::<String>::new(), "no partial file");
    let whole = hub(&model, Serve::Whole);
    let out = fetch(&dir, &whole.endpoint, false);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let path = PathBuf::from(text(&out.stdout).trim());
    assert_eq!(sha256(&path), sha256(&model));
}

#[test]
fn offline_without_the_file_names_the_url_and_where_to_put_it() {
    let dir = tmp("offline");
    let out = fetch(&dir, "http://127.0.0.1:1", true);
    let err = text(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    let url = format!("http://127.0.0.1:1/{REPO}/resolve/main/onnx/model.onnx");
    let path = repo_cache(&dir).join("snapshots/main/onnx/model.onnx");
    assert!(err.contains(&url) && err.contains(&path.display().to_string()), "{err}");
    // a file put there as the message says is used (and checked)
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::copy(models().join("depth_hub.onnx"), &path).unwrap();
    let out = fetch(&dir, "http://127.0.0.1:1", true);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert_eq!(text(&out.stdout).trim(), path.display().to_string());
}

/// Online, with nothing listening at the endpoint: the error names the URL, a mirror and the
/// path where a file downloaded elsewhere goes; nothing is kept.
#[test]
fn an_unreachable_hub_names_the_url_and_the_path() {
    let dir = tmp("unreachable");
    let out = fetch(&dir, "http://127.0.0.1:1", false);
    let err = text(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    let path = repo_cache(&dir).join("snapshots/main/onnx/model.onnx");
    assert!(err.contains(&format!("http://127.0.0.1:1/{REPO}/resolve/main/onnx/model.onnx")), "{err}");
    assert!(err.contains("HF_ENDPOINT") && err.contains(&path.display().to_string()), "{err}");
    assert_eq!(files_under(&repo_cache(&dir)), Vec::<String>::new());
}

/// `models check FILE --image PHOTO`: a file with the hub's tensor names runs with the manifest
/// beside it (and not without it); the preview is the photo's depth (the model's output grows
/// with red, so the preview brightens left to right on a red ramp).
#[test]
fn check_runs_a_local_file_with_its_manifest_and_writes_the_preview() {
    let dir = tmp("check");
    let model = dir.join("da.onnx");
    std::fs::copy(models().join("depth_hub.onnx"), &model).unwrap();
    let photo = dir.join("ramp.png");
    image::RgbImage::from_fn(40, 20, |x, _| image::Rgb([(x * 6) as u8, 100, 100])).save(&photo).unwrap();
    let preview = dir.join("preview.png");
    let args = |m: &Path| {
        vec![
            "models".to_string(),
            "check".into(),
            m.display().to_string(),
            "--image".into(),
            photo.display().to_string(),
            "--out".into(),
            preview.display().to_string(),
        ]
    };
    let without = Command::new(BIN).args(args(&model)).output().unwrap();
    assert_eq!(without.status.code(), Some(2));
    assert!(text(&without.stderr).contains("has no input tensor `image`"), "{}", text(&without.stderr));
    std::fs::write(registry::manifest_path(&model), "input = \"pixel_values\"\noutput = \"predicted_depth\"\n")
        .unwrap();
    let with = Command::new(BIN).args(args(&model)).output().unwrap();
    let stdout = text(&with.stdout);
    assert!(with.status.success(), "{stdout}{}", text(&with.stderr));
    assert!(stdout.contains("input `pixel_values`") && stdout.contains("ms per photo"), "{stdout}");
    let p = image::open(&preview).unwrap().to_luma8();
    assert_eq!(p.dimensions(), (40, 20));
    let row: Vec<u8> = (0..40).map(|x| p.get_pixel(x, 10)[0]).collect();
    assert!(row.windows(2).all(|w| w[0] <= w[1]) && row[0] < row[39], "{row:?}");
}

/// The built-in contract of `depth-anything-v2-small` through the real ONNX Runtime path: on a
/// flat colour the network (`2 R + G - 0.5 B + 3` on its input) must see the colour normalised
/// with the entry's ImageNet mean and std, at the entry's 518x518.
#[test]
fn the_registry_contract_feeds_the_named_tensors_normalised() {
    let entry = registry::find("depth-anything-v2-small").unwrap().unwrap();
    let resolved = registry::Resolved {
        path: models().join("depth_hub.onnx"),
        contract: entry.contract.clone(),
        entry: Some(entry),
    };
    let config = resolved.contract.depth_config(&resolved.path);
    let depth = mpiflow::scene::onnx::OnnxDepth::new(config).unwrap();
    let (r, g, b) = (0.8f32, 0.3, 0.6);
    let image = RgbImage { width: 30, height: 20, data: [r, g, b].repeat(600) };
    let raw = depth.estimate_raw(&image).unwrap();
    let norm = |v: f32, m: f32, s: f32| (v - m) / s;
    let want = 2.0 * norm(r, 0.485, 0.229) + norm(g, 0.456, 0.224) - 0.5 * norm(b, 0.406, 0.225) + 3.0;
    assert_eq!((raw.width, raw.height), (30, 20));
    assert!(raw.data.iter().all(|v| (v - want).abs() < 1e-4), "{} vs {want}", raw.data[0]);
    assert_eq!(depth.config().size, mpiflow::scene::onnx::SizePolicy::Fixed { width: 518, height: 518 });
    // and through the stage, as serve loads it
    let m = registry::load_depth(&resolved).unwrap();
    assert_eq!(m.inference_runs(), Some(0));
}

/// Each named architecture itself (reduced-width random-weight exports in tests/data/models:
/// `tools/export/depth_anything.py --random-init tiny`, `tools/export/midas_depth.py
/// --random-init dpt-hybrid-tiny --hub-contract`) through the real ONNX Runtime path with its
/// registry entry's contract: a photo gives a depth map of its size in the scene scale, not a
/// constant.
#[test]
fn each_named_architecture_runs_with_its_registry_contract() {
    for (name, file) in
        [("depth-anything-v2-small", "depth_anything_v2_tiny.onnx"), ("dpt-hybrid-midas", "dpt_hybrid_tiny.onnx")]
    {
        let entry = registry::find(name).unwrap().unwrap();
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/models").join(file);
        let resolved = registry::Resolved { path, contract: entry.contract.clone(), entry: Some(entry) };
        let model = registry::load_depth(&resolved).unwrap();
        let photo = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/photos/chelsea.png");
        let image = mpiflow::io::image::load_rgb(&photo, &Default::default()).unwrap();
        let d = model.estimate(&image).unwrap();
        assert_eq!((d.width, d.height), (image.width, image.height), "{name}");
        assert!(d.data.iter().all(|v| v.is_finite() && (0.001..=1.0).contains(v)), "{name}");
        let (lo, hi) = d.data.iter().fold((f32::MAX, f32::MIN), |(lo, hi), &v| (lo.min(v), hi.max(v)));
        assert!(lo < 0.5 && hi == 1.0, "{name}: a depth map, not a constant: {lo}..{hi}");
        assert_eq!(model.inference_runs(), Some(1), "{name}");
        assert_eq!(model.name(), format!("{name} (onnx:{file})"));
    }
}

/// A manifest's `output_kind = "metric-depth"`: the output is depth (larger = farther), inverted
/// before the normalisation, so the depth map runs the other way than as inverse depth.
#[test]
fn a_metric_depth_manifest_inverts_the_output() {
    let dir = tmp("metric");
    let image =
        RgbImage { width: 16, height: 4, data: (0..64).flat_map(|i| [(i % 16) as f32 / 15.0, 0.2, 0.2]).collect() };
    let run = |kind: &str| {
        let model = dir.join(format!("{kind}.onnx"));
        std::fs::copy(models().join("depth_hub.onnx"), &model).unwrap();
        let manifest = format!("input = \"pixel_values\"\noutput = \"predicted_depth\"\noutput_kind = \"{kind}\"\n");
        std::fs::write(registry::manifest_path(&model), manifest).unwrap();
        let hub = mpiflow::scene::hub::Hub {
            endpoint: String::new(),
            cache: dir.join("hub"),
            offline: true,
            timeout: std::time::Duration::from_secs(10),
            deadline: std::time::Duration::from_secs(3600),
            min_rate: 0,
        };
        let r = registry::resolve(&model, registry::Role::Depth, &hub, false).unwrap();
        registry::load_depth(&r).unwrap().estimate(&image).unwrap().data
    };
    let inverse = run("relative-inverse-depth");
    let metric = run("metric-depth");
    // red grows to the right: the output (2 R + G - 0.5 B + 3) grows, so as inverse depth the
    // right is nearest (1), as metric depth the left is
    assert_eq!((inverse[15], metric[0]), (1.0, 1.0));
    assert!(inverse[0] < inverse[15] && metric[15] < metric[0]);
    // metric: disparity ~ 1 / depth, min-max normalised
    let d = |x: usize| 2.0 * (x as f32 / 15.0) + 0.2 - 0.1 + 3.0;
    let inv: Vec<f32> = (0..16).map(|x| 1.0 / d(x)).collect();
    let want = |x: usize| (inv[x] - inv[15]) / (inv[0] - inv[15]);
    assert!((0..16).all(|x| (metric[x] - want(x).max(0.001)).abs() < 1e-4), "{metric:?}");
}

/// A segmentation file whose outputs have other names runs with a manifest naming them.
#[test]
fn a_segmentation_manifest_names_the_outputs() {
    let dir = tmp("seg");
    let model = dir.join("seg.onnx");
    std::fs::copy(models().join("seg_wrong_names.onnx"), &model).unwrap();
    let hub = mpiflow::scene::hub::Hub {
        endpoint: String::new(),
        cache: dir.join("hub"),
        offline: true,
        timeout: std::time::Duration::from_secs(10),
        deadline: std::time::Duration::from_secs(3600),
        min_rate: 0,
    };
    let load = || {
        let r = registry::resolve(&model, registry::Role::Segment, &hub, false).unwrap();
        mpiflow::scene::onnx::OnnxSegmenter::new(r.contract.segment_config(&r.path))
    };
    let e = load().unwrap_err();
    assert!(e.to_string().contains("has no output tensor `masks`"), "{e}");
    std::fs::write(
        registry::manifest_path(&model),
        "masks_output = \"out_masks\"\nscores_output = \"out_scores\"\nlabels_output = \"out_labels\"\n",
    )
    .unwrap();
    let seg = load().unwrap();
    // channel 0 bright on the left half: one instance there (seg.onnx's known function)
    let image = RgbImage {
        width: 8,
        height: 4,
        data: (0..32).flat_map(|i| [if i % 8 < 4 { 1.0 } else { 0.0 }, 0.0, 0.0]).collect(),
    };
    let masks = mpiflow::scene::Segmenter::segment(&seg, &image).unwrap();
    assert_eq!(masks.masks.len(), 1);
}
