//! The named segmenter end to end, offline: a loopback HTTP server in the Hugging Face hub's URL
//! layout serves the repository's random-weight exports of the named architectures
//! (`tests/data/models/depth_anything_v2_tiny.onnx` for `depth-anything-v2-small`,
//! `tests/data/models/detr_panoptic_tiny.onnx` for `detr-resnet-50-panoptic`: `tools/export/`),
//! and a test registry (`MPIFLOW_MODEL_REGISTRY`) points both names at it with the files'
//! SHA-256 and the built-in entries' contracts. Checked through the real binary and the real
//! ONNX Runtime: `serve` fetches both and its samples move objects; `models list` names the
//! segmenter and its licence; `models check` writes a mask preview; a segmenter that finds no
//! object says so in the sample's provenance, and only the camera moves.
//!
//! The tiny DETR export's class head is biased towards COCO class 1 (person), so its random
//! weights find confident "things" (`tools/export/detr_panoptic.py --class-bias 1=12`).
//!
//! Needs `ORT_DYLIB_PATH`: run `bash tools/test.sh`, or `eval "$(bash tools/setup_python.sh)"`
//! first.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use mpiflow::scene::registry::{self, Role};
use mpiflow::service::pb;

const BIN: &str = env!("CARGO_BIN_EXE_mpiflow");
const HOW: &str = "run the tests with `bash tools/test.sh` (or `eval \"$(bash tools/setup_python.sh)\"` first)";
/// The commit the loopback hub names for `main`.
const COMMIT: &str = "89abcdef0123456789abcdef0123456789abcdef";
const DEPTH: &str = "depth-anything-v2-small";
const SEGMENTER: &str = "detr-resnet-50-panoptic";

fn model_file(name: &str) -> PathBuf {
    assert!(std::env::var_os("ORT_DYLIB_PATH").is_some_and(|v| !v.is_empty()), "ORT_DYLIB_PATH is not set: {HOW}");
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/models").join(name)
}

fn tmp(name: &str) -> PathBuf {
    let d = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("segmenter-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// The built-in contract of `depth-anything-v2-small` (checked against the registry below).
const DEPTH_CONTRACT: &str = "input = \"pixel_values\"\noutput = \"predicted_depth\"\n\
                              output_kind = \"relative-inverse-depth\"\nsize = [518, 518]\nmultiple_of = 14\n\
                              mean = [0.485, 0.456, 0.406]\nstd = [0.229, 0.224, 0.225]\n";

/// The built-in contract of `detr-resnet-50-panoptic`, with `thing_labels` replaced by `things`.
fn detr_contract(things: [u32; 2]) -> String {
    format!(
        "input = \"pixel_values\"\noutput_kind = \"detr-panoptic\"\nlogits_output = \"logits\"\n\
         masks_output = \"pred_masks\"\nthing_labels = [{}, {}]\nlong_side = 640\nmultiple_of = 32\n\
         mean = [0.485, 0.456, 0.406]\nstd = [0.229, 0.224, 0.225]\n",
        things[0], things[1]
    )
}

/// The contract text of a built-in entry, checked to parse to the entry's contract.
fn contract_of(name: &str) -> String {
    let text = if name == DEPTH { DEPTH_CONTRACT.to_string() } else { detr_contract([1, 90]) };
    let parsed: registry::Contract = toml::from_str(&text).unwrap();
    assert_eq!(
        parsed,
        registry::find(name).unwrap().unwrap().contract,
        "the test registry keeps the built-in contract"
    );
    text
}

/// Each served model: its registry name, its repository on the loopback hub and its file.
fn served() -> [(&'static str, &'static str, PathBuf); 2] {
    [
        (DEPTH, "test-org/depth-hub", model_file("depth_anything_v2_tiny.onnx")),
        (SEGMENTER, "test-org/detr-hub", model_file("detr_panoptic_tiny.onnx")),
    ]
}

/// A loopback HTTP/1.1 server in the hub's layout: `/{repo}/resolve/main/{file}` answers 302 to
/// `/blobs/{n}` with `X-Repo-Commit`, which answers the bytes of model `n` of [`served`].
fn hub() -> String {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let endpoint = format!("http://{}", listener.local_addr().unwrap());
    let files: Vec<(String, Vec<u8>)> = served()
        .iter()
        .map(|(name, repo, path)| {
            let entry = registry::find(name).unwrap().expect("a built-in entry");
            (format!("/{repo}/resolve/main/{}", entry.file), std::fs::read(path).unwrap())
        })
        .collect();
    std::thread::spawn(move || {
        for conn in listener.incoming() {
            let Ok(mut conn) = conn else { continue };
            let mut reader = BufReader::new(conn.try_clone().unwrap());
            let mut request_line = String::new();
            if reader.read_line(&mut request_line).is_err() {
                continue;
            }
            loop {
                let mut line = String::new();
                if reader.read_line(&mut line).map_or(true, |n| n == 0) || line == "\r\n" {
                    break;
                }
            }
            let path = request_line.split_whitespace().nth(1).unwrap_or_default().to_string();
            let blob = path.strip_prefix("/blobs/").and_then(|n| n.parse::<usize>().ok());
            let _ = if let Some(n) = files.iter().position(|(url, _)| *url == path) {
                conn.write_all(
                    format!(
                        "HTTP/1.1 302 Found\r\nLocation: /blobs/{n}\r\nX-Repo-Commit: {COMMIT}\r\n\
                         Content-Length: 0\r\nConnection: close\r\n\r\n"
                    )
                    .as_bytes(),
                )
            } else if let Some((_, body)) = blob.and_then(|n| files.get(n)) {
                let head = format!("HTTP/1.1 200 OK\r\nContent-Length: {}\r\nConnection: close\r\n\r\n", body.len());
                conn.write_all(head.as_bytes()).and_then(|()| conn.write_all(body))
            } else {
                conn.write_all(b"HTTP/1.1 404 Not Found\r\nContent-Length: 0\r\nConnection: close\r\n\r\n")
            };
            let _ = conn.flush();
        }
    });
    endpoint
}

/// A test registry: both names at the loopback hub's repositories, pinned to the files' SHA-256,
/// with the built-in entries' contracts (and files).
fn test_registry(dir: &Path) -> PathBuf {
    let mut text = String::new();
    for (name, repo, path) in served() {
        let e = registry::find(name).unwrap().unwrap();
        let contract = contract_of(name);
        text += &format!(
            "[[model]]\nname = \"{name}\"\nrole = \"{}\"\nrepo = \"{repo}\"\nrevision = \"main\"\nfile = \"{}\"\n\
             sha256 = \"{}\"\nlicence = \"{}\"\n\n[model.contract]\n{contract}\n",
            e.role,
            e.file,
            mpiflow::scene::hub::sha256_file(&path).unwrap(),
            e.licence
        );
    }
    let path = dir.join("registry.toml");
    std::fs::write(&path, text).unwrap();
    path
}

/// `mpiflow ARGS` with the hub environment: cache under `dir/hf`, the test registry, `endpoint`.
fn mpiflow(dir: &Path, endpoint: &str, args: &[&str]) -> Command {
    let mut c = Command::new(BIN);
    c.args(args)
        .env("HF_HOME", dir.join("hf"))
        .env_remove("HF_HUB_CACHE")
        .env_remove("HF_HUB_OFFLINE")
        .env("HF_ENDPOINT", endpoint)
        .env(registry::REGISTRY_ENV, test_registry(dir));
    c
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

fn photos(dir: &Path) -> PathBuf {
    let p = dir.join("photos");
    std::fs::create_dir_all(&p).unwrap();
    for i in 0..2u32 {
        let img = image::RgbImage::from_fn(64, 48, |x, y| image::Rgb([(x * 4 + i * 40) as u8, (y * 5) as u8, 90]));
        img.save(p.join(format!("p{i}.png"))).unwrap();
    }
    p
}

/// `serve` until it prints its address, then GetSample 0 of seed 1 and stop it.
fn serve_one_sample(cmd: &mut Command) -> pb::Sample {
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
        let fields = vec![pb::Field::Image1 as i32, pb::Field::Mask1 as i32];
        c.get_sample(pb::SampleSpec { seed: 1, fields, ..Default::default() }.sample(0)).await
    });
    child.kill().unwrap();
    child.wait().unwrap();
    sample.expect("a sample through the named models").into_inner()
}

fn serve_args(src: &Path, segment_model: &str) -> Vec<String> {
    let src = src.display().to_string();
    ["serve", "--addr", "127.0.0.1:0", "--log-level", "warn", "--source", &src, "--depth-model", DEPTH]
        .iter()
        .map(ToString::to_string)
        .chain(["--segment-model".to_string(), segment_model.to_string()])
        .collect()
}

#[test]
fn serve_with_the_named_segmenter_from_a_mirror_moves_objects() {
    let dir = tmp("serve");
    let endpoint = hub();
    let args = serve_args(&photos(&dir), SEGMENTER);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let s = serve_one_sample(&mut mpiflow(&dir, &endpoint, &args));
    let masks = s.provenance.iter().find(|p| p.starts_with("masks: ")).expect("a masks provenance");
    assert!(masks.starts_with(&format!("masks: {SEGMENTER} (onnx:")) && masks.ends_with(" instances)"), "{masks}");
    assert!(!s.objects.is_empty(), "objects move: {:?}", s.provenance);
    let o = &s.objects[0];
    assert!(o.score >= 0.85 && o.area > 0.0 && o.motion.is_some(), "{o:?}");
    let mask1 = s.tensors.iter().find(|t| t.name == "mask1").expect("mask1");
    assert!(mask1.data.iter().any(|&v| u32::from(v) == o.label), "the moved object's label lies in mask1");
    // both models came from the mirror into the hub cache
    for repo in ["models--test-org--depth-hub", "models--test-org--detr-hub"] {
        assert!(dir.join("hf/hub").join(repo).join("refs/main").is_file(), "{repo}");
    }
}

#[test]
fn models_list_names_the_segmenter_and_its_licence() {
    let dir = tmp("list");
    let out = mpiflow(&dir, "http://127.0.0.1:1", &["models", "list"]).output().unwrap();
    let stdout = text(&out.stdout);
    assert!(out.status.success(), "{stdout}{}", text(&out.stderr));
    let line = stdout.lines().find(|l| l.starts_with(SEGMENTER)).unwrap_or_else(|| panic!("{stdout}"));
    assert!(line.contains("(segment, Apache-2.0)"), "{line}");
    assert!(stdout.contains("DETR panoptic queries, classes 1 to 90"), "{stdout}");
    // the built-in entry, not only the test registry's copy
    let builtin = registry::find(SEGMENTER).unwrap().unwrap();
    assert_eq!((builtin.role, builtin.licence.as_str()), (Role::Segment, "Apache-2.0"));
    assert_eq!(builtin.repo, "Xenova/detr-resnet-50-panoptic");
}

/// `models check NAME --image PHOTO`: fetched, timed, the objects listed and the mask preview
/// written at the photo's size (the photo dimmed, the objects tinted).
#[test]
fn models_check_writes_a_mask_preview() {
    let dir = tmp("check");
    let endpoint = hub();
    let photo = photos(&dir).join("p0.png");
    let preview = dir.join("masks.png");
    let (photo_s, preview_s) = (photo.display().to_string(), preview.display().to_string());
    let args = ["models", "check", SEGMENTER, "--image", &photo_s, "--runs", "1", "--out", &preview_s];
    let out = mpiflow(&dir, &endpoint, &args).output().unwrap();
    let stdout = text(&out.stdout);
    assert!(out.status.success(), "{stdout}{}", text(&out.stderr));
    assert!(stdout.contains("ms per photo") && stdout.contains("object 1: class 1, score"), "{stdout}");
    assert!(stdout.contains("longer side 640 (multiples of 32)"), "{stdout}");
    let p = image::open(&preview).unwrap().to_rgb8();
    assert_eq!(p.dimensions(), (64, 48));
    let original = image::open(&photo).unwrap().to_rgb8();
    let tinted = p.pixels().zip(original.pixels()).filter(|(a, b)| a[0] > b[0] / 2 + 2).count();
    assert!(tinted > 0 && tinted < 64 * 48, "some pixels tinted, not all: {tinted}");
}

/// The same network as a FILE with a manifest that counts only classes 2 to 90 as objects: its
/// "person" queries do not move, the sample's provenance says no object was found, and only the
/// camera moves.
#[test]
fn a_segmenter_that_finds_nothing_says_so_and_only_the_camera_moves() {
    let dir = tmp("none");
    let endpoint = hub();
    let model = dir.join("detr.onnx");
    std::fs::copy(model_file("detr_panoptic_tiny.onnx"), &model).unwrap();
    std::fs::write(registry::manifest_path(&model), detr_contract([2, 90])).unwrap();
    let args = serve_args(&photos(&dir), &model.display().to_string());
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let s = serve_one_sample(&mut mpiflow(&dir, &endpoint, &args));
    assert!(s.objects.is_empty(), "{:?}", s.objects);
    assert!(
        s.provenance.iter().any(|p| p == "masks: onnx:detr.onnx (no object found: only the camera moves)"),
        "{:?}",
        s.provenance
    );
    let mask1 = s.tensors.iter().find(|t| t.name == "mask1").expect("mask1");
    assert!(mask1.data.iter().all(|&v| v == 0));
}

/// The built-in contract through the library, as `serve` loads it: the photo's instances are
/// of its size, "things" of class 1, disjoint, in score order; a depth contract refuses the file.
#[test]
fn the_registry_contract_runs_the_detr_architecture() {
    let entry = registry::find(SEGMENTER).unwrap().unwrap();
    let path = model_file("detr_panoptic_tiny.onnx");
    let resolved = registry::Resolved { path, contract: entry.contract.clone(), entry: Some(entry) };
    let seg = registry::load_segmenter(&resolved).unwrap();
    assert_eq!(seg.name(), format!("{SEGMENTER} (onnx:detr_panoptic_tiny.onnx)"));
    let photo = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/photos/chelsea.png");
    let image = mpiflow::io::image::load_rgb(&photo, &Default::default()).unwrap();
    let m = seg.segment(&image).unwrap();
    assert_eq!((m.width, m.height), (image.width, image.height));
    assert!(!m.masks.is_empty());
    for (k, i) in m.masks.iter().enumerate() {
        assert_eq!((i.id, i.category), (k as u32 + 1, Some(1)));
        assert!(i.mask.len() == image.width * image.height && i.mask.iter().all(|v| (0.0..=1.0).contains(v)));
        assert!(i.area >= 0.002 * (image.width * image.height) as f64);
    }
    assert!(m.masks.windows(2).all(|w| w[0].score >= w[1].score));
    assert_eq!(seg.inference_runs(), Some(1));
    let e = registry::load_depth(&resolved).map(|_| ()).unwrap_err().to_string();
    assert!(e.contains("output_kind `detr-panoptic` is a segment output: use the model as --segment-model"), "{e}");
}

/// A file that is not a DETR network, run with the DETR contract, is refused at load naming the
/// missing tensor and listing the file's real ones.
#[test]
fn the_detr_contract_refuses_another_network_naming_the_tensor() {
    let entry = registry::find(SEGMENTER).unwrap().unwrap();
    let path = model_file("depth_anything_v2_tiny.onnx");
    let resolved = registry::Resolved { path, contract: entry.contract, entry: None };
    let e = registry::load_segmenter(&resolved).map(|_| ()).unwrap_err().to_string();
    assert!(
        e.contains("depth_anything_v2_tiny.onnx: has no output tensor `logits`; its outputs are: `predicted_depth`"),
        "{e}"
    );
}
