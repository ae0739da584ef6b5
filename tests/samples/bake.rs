//! `mpiflow bake` end to end, with the tiny ONNX models of `tools/make_test_models.py` in real
//! ONNX Runtime sessions and the real binary: N shards cover every item exactly once and give
//! the bytes of one unsharded bake; an interrupted bake (a `--limit`, an item cut in the middle,
//! leftover temporaries) restarted loses and repeats nothing; bad items are reported with their
//! reason and make the bake exit with status 2 naming them; a baked scene is the scene the models make (disparity, masks, image and MPI bit for
//! bit); the WebDataset layout holds the same files as tar members, sharded and resumed the
//! same way; and a server over the baked folder or shards runs no model (GetInfo says so, the model counters
//! stay 0) while the same server over the raw photos does.
//!
//! Needs `MPIFLOW_PYTHON` (a Python with `onnx`) and `ORT_DYLIB_PATH`: run `bash tools/test.sh`,
//! or `eval "$(bash tools/setup_python.sh)"` first.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::{Arc, OnceLock};

use mpiflow::export::bake::{shard_of, Shard};
use mpiflow::io::image::{load_rgb, save_rgb_png, ImageLimits};
use mpiflow::scene::models::ModelConfig;
use mpiflow::scene::stage::{SceneStage, SourceScenes};
use mpiflow::scene::SceneLoader;
use mpiflow::service::client::client_for;
use mpiflow::service::config::DatasetConfig;
use mpiflow::service::pb;
use mpiflow::service::{start, ServiceConfig};
use mpiflow::source::dir::resize_rgb;
use mpiflow::source::dir::{DirSource, SourceOptions};
use mpiflow::source::Source;
use proptest::prelude::*;
use tonic::transport::Endpoint;

const HOW: &str = "run the tests with `bash tools/test.sh` (or `eval \"$(bash tools/setup_python.sh)\"` first)";
const SIZE: &str = "64x48";

fn tmp(name: &str) -> PathBuf {
    let d = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("bake_{name}_{}", std::process::id()));
    std::fs::remove_dir_all(&d).ok();
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// The generated test models (once per test process).
fn models() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let python = std::env::var_os("MPIFLOW_PYTHON")
            .filter(|v| !v.is_empty())
            .unwrap_or_else(|| panic!("MPIFLOW_PYTHON is not set: {HOW}"));
        assert!(std::env::var_os("ORT_DYLIB_PATH").is_some_and(|v| !v.is_empty()), "ORT_DYLIB_PATH is not set: {HOW}");
        let dir = tmp("models");
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/make_test_models.py");
        let out = Command::new(&python).arg(&script).arg(&dir).output().expect("runs the model script");
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        dir
    })
}

fn model(name: &str) -> PathBuf {
    models().join(name)
}

/// A plain folder: the bundled photos as 64x48 8-bit PNGs, one twice under two names, one at
/// 80x60 (the bake's `--size` brings it to 64x48), and an image whose pixel data is corrupt.
fn photos(name: &str) -> PathBuf {
    let d = tmp(name);
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/photos");
    for (f, to, (w, h)) in [
        ("astronaut.png", "astronaut.png", (64, 48)),
        ("chelsea.png", "chelsea.png", (64, 48)),
        ("coffee.png", "coffee.png", (64, 48)),
        ("coffee.png", "mug.png", (64, 48)),
        ("rocket.jpg", "rocket.png", (80, 60)),
    ] {
        let img = load_rgb(&src.join(f), &ImageLimits::default()).unwrap();
        save_rgb_png(&d.join(to), &resize_rgb(img, w, h)).unwrap();
    }
    // a PNG whose header is whole (it passes the check when the folder is opened) and whose
    // pixel data is corrupt: it fails when decoded
    let mut broken = std::io::Cursor::new(Vec::new());
    image::RgbImage::from_fn(64, 48, |x, y| image::Rgb([(x * 3) as u8, (y * 5) as u8, (x ^ y) as u8]))
        .write_to(&mut broken, image::ImageFormat::Png)
        .unwrap();
    let mut broken = broken.into_inner();
    let n = broken.len();
    for v in &mut broken[n / 2..n - 20] {
        *v ^= 0x5a;
    }
    std::fs::write(d.join("broken.png"), broken).unwrap();
    d
}

const GOOD: [&str; 5] = ["astronaut", "chelsea", "coffee", "mug", "rocket"];

fn bake(source: &Path, out: &Path, extra: &[&str]) -> (serde_json::Value, String) {
    let bin = env!("CARGO_BIN_EXE_mpiflow");
    let mut cmd = Command::new(bin);
    cmd.args(["bake", "--source"]).arg(source).arg("--out").arg(out);
    cmd.arg("--depth-model").arg(model("depth.onnx")).arg("--segment-model").arg(model("seg.onnx"));
    cmd.args(["--size", SIZE]).args(extra);
    let o = cmd.output().expect("runs mpiflow bake");
    let stderr = String::from_utf8_lossy(&o.stderr).to_string();
    let shard = extra.iter().position(|a| *a == "--shard").map(|i| extra[i + 1].replace('/', "-of-"));
    let report = match shard {
        Some(tag) if tag != "0-of-1" => out.join(format!("bake-report.{tag}.json")),
        _ => out.join("bake-report.json"),
    };
    let r: serde_json::Value = serde_json::from_slice(&std::fs::read(report).expect("a report")).unwrap();
    // success exactly when no item failed; otherwise exit status 2 and a last line naming each
    let failed: Vec<&str> = r["failures"].as_array().unwrap().iter().map(|f| f["id"].as_str().unwrap()).collect();
    if failed.is_empty() {
        assert!(o.status.success(), "bake failed: {stderr}");
    } else {
        assert_eq!(o.status.code(), Some(2), "{failed:?} failed, yet: {stderr}");
        let last = stderr.lines().last().unwrap_or_default();
        assert!(last.starts_with(&format!("error: {} of ", failed.len())), "{stderr}");
        for id in &failed {
            assert!(last.contains(id), "{id} is not named: {stderr}");
        }
    }
    (r, stderr)
}

/// Every file under `dir` (relative path -> bytes), reports and hidden folders left out.
fn files(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    let mut out = BTreeMap::new();
    for sub in ["images", "disps", "masks", "mpis"] {
        let Ok(rd) = std::fs::read_dir(dir.join(sub)) else { continue };
        for e in rd {
            let p = e.unwrap().path();
            out.insert(format!("{sub}/{}", p.file_name().unwrap().to_string_lossy()), std::fs::read(&p).unwrap());
        }
    }
    out.insert("bake.json".into(), std::fs::read(dir.join("bake.json")).unwrap());
    out
}

fn ids_of(files: &BTreeMap<String, Vec<u8>>, sub: &str) -> BTreeSet<String> {
    files
        .keys()
        .filter_map(|k| k.strip_prefix(&format!("{sub}/")))
        .map(|n| n.rsplit_once('.').unwrap().0.to_string())
        .collect()
}

fn n(v: &serde_json::Value, key: &str) -> u64 {
    v[key].as_u64().unwrap_or_else(|| panic!("{key} in {v}"))
}

proptest! {
    /// N shards partition any set of ids: every id is in exactly one shard.
    #[test]
    fn shards_cover_every_item_exactly_once(ids in proptest::collection::btree_set("[a-z0-9_.-]{1,12}", 0..60), count in 1u64..9) {
        let shards: Vec<Shard> = (0..count).map(|index| Shard { index, count }).collect();
        for id in &ids {
            let owners = shards.iter().filter(|s| s.owns(id)).count();
            prop_assert_eq!(owners, 1, "{} is in {} shards of {}", id, owners, count);
            prop_assert!(shard_of(id, count) < count);
        }
    }
}

#[test]
fn shard_spec_parses_and_refuses() {
    assert_eq!("1/4".parse::<Shard>().unwrap(), Shard { index: 1, count: 4 });
    for bad in ["4/4", "0/0", "x/2", "1", "-1/2"] {
        assert!(bad.parse::<Shard>().is_err(), "{bad}");
    }
}

#[test]
fn two_shards_make_the_whole_bake_and_bad_items_are_reported() {
    let src = photos("shards_src");
    let (whole, sharded) = (tmp("whole"), tmp("sharded"));
    let (r, _) = bake(&src, &whole, &[]);
    assert_eq!((n(&r, "baked"), n(&r, "failed"), n(&r, "remaining")), (5, 1, 0), "{r}");
    let f = &r["failures"][0];
    assert_eq!(f["id"], "broken");
    assert_eq!(f["kind"], "decode", "{f}");
    assert!(f["reason"].as_str().unwrap().contains("broken.png"), "{f}");
    assert_eq!(r["model_runs"]["depth"], 5);
    assert_eq!(r["model_runs"]["segment"], 5);
    let hash = r["models"][0]["content_hash"].as_str().unwrap().to_string();
    assert_eq!(hash.len(), 16);

    let (r0, _) = bake(&src, &sharded, &["--shard", "0/2"]);
    let (r1, _) = bake(&src, &sharded, &["--shard", "1/2"]);
    assert_eq!(n(&r0, "shard_items") + n(&r1, "shard_items"), 6);
    assert_eq!(n(&r0, "baked") + n(&r1, "baked"), 5, "{r0}\n{r1}");
    assert_eq!(n(&r0, "failed") + n(&r1, "failed"), 1);
    let (a, b) = (files(&whole), files(&sharded));
    let want: BTreeSet<String> = GOOD.iter().map(ToString::to_string).collect();
    for sub in ["images", "disps", "masks"] {
        assert_eq!(ids_of(&a, sub), want, "{sub}");
    }
    assert_eq!(a.keys().collect::<Vec<_>>(), b.keys().collect::<Vec<_>>());
    for (k, v) in &a {
        assert!(b[k] == *v, "{k} differs between the whole and the sharded bake");
    }
    // the manifest names the models by content hash
    assert!(String::from_utf8_lossy(&a["bake.json"]).contains(&hash));
    // a second run of a finished shard does nothing
    let (again, _) = bake(&src, &sharded, &["--shard", "1/2"]);
    assert_eq!((n(&again, "baked"), n(&again, "already_done")), (0, n(&r1, "baked")));
    assert_eq!(again["model_runs"]["depth"], 0);
}

#[test]
fn an_interrupted_bake_restarted_loses_and_repeats_nothing() {
    let src = photos("resume_src");
    let (whole, cut) = (tmp("resume_whole"), tmp("resume_cut"));
    bake(&src, &whole, &[]);
    let (r, _) = bake(&src, &cut, &["--limit", "2"]);
    assert_eq!(n(&r, "baked") + n(&r, "failed"), 2, "{r}");
    assert!(n(&r, "remaining") > 0);
    let first = ids_of(&files(&cut), "images");
    assert_eq!(first.len() as u64, n(&r, "baked"));
    // an item cut in the middle: its disparity renamed into place, its image not yet; and a
    // temporary file of the killed run
    let pending: Vec<&str> = GOOD.iter().copied().filter(|id| !first.contains(*id)).collect();
    let half = pending[0];
    std::fs::copy(whole.join(format!("disps/{half}.npy")), cut.join(format!("disps/{half}.npy"))).unwrap();
    std::fs::create_dir_all(cut.join(".partial/0-of-1")).unwrap();
    std::fs::write(cut.join(".partial/0-of-1/1234-x.png"), b"half written").unwrap();
    // the half item is not served: the listing goes by images/
    let listed = DirSource::open(&cut, &SourceOptions::default()).unwrap();
    assert_eq!(listed.len(), first.len());

    let (r2, _) = bake(&src, &cut, &[]);
    assert_eq!(n(&r2, "already_done"), n(&r, "baked"), "{r2}");
    assert_eq!(n(&r, "baked") + n(&r2, "baked"), 5, "every good item baked exactly once: {r}\n{r2}");
    assert_eq!(r2["model_runs"]["depth"], n(&r2, "baked"));
    assert!(!cut.join(".partial/0-of-1").exists(), "the leftover temporaries are cleared");
    let (a, b) = (files(&whole), files(&cut));
    assert_eq!(a.keys().collect::<Vec<_>>(), b.keys().collect::<Vec<_>>());
    for (k, v) in &a {
        assert!(b[k] == *v, "{k} differs from an uninterrupted bake");
    }
}

#[test]
fn a_folder_baked_with_other_models_is_refused() {
    let src = photos("refuse_src");
    let out = tmp("refuse");
    bake(&src, &out, &["--limit", "1"]);
    let o = Command::new(env!("CARGO_BIN_EXE_mpiflow"))
        .args(["bake", "--source"])
        .arg(&src)
        .arg("--out")
        .arg(&out)
        .arg("--depth-model")
        .arg(model("depth_fixed.onnx"))
        .args(["--size", SIZE])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("other models") && e.contains("bake.json"), "{e}");
}

fn stage(depth: bool, mpi: bool, seg: bool) -> Arc<SceneStage> {
    let m = ModelConfig {
        depth_model: depth.then(|| model("depth.onnx")),
        mpi_model: mpi.then(|| model("mpi.onnx")),
        segment_model: seg.then(|| model("seg.onnx")),
        ..ModelConfig::default()
    };
    Arc::new(m.build_stage().unwrap())
}

/// The scenes of the raw photos through the models equal the scenes of the baked folder
/// through no model, bit for bit (image, disparity, masks, MPI), with and without an MPI network.
#[test]
fn a_baked_scene_is_the_scene_the_models_make() {
    let src = photos("scene_src");
    for mpi_net in [false, true] {
        let out = tmp(&format!("scene_{mpi_net}"));
        let extra: &[&str] = if mpi_net { &["--mpi-model", "MPI"] } else { &[] };
        let mpi_path = model("mpi.onnx").display().to_string();
        let extra: Vec<&str> = extra.iter().map(|a| if *a == "MPI" { mpi_path.as_str() } else { a }).collect();
        bake(&src, &out, &extra);
        let opts = SourceOptions { resize: Some((64, 48)), ..SourceOptions::default() };
        let raw = SourceScenes::new(Arc::new(DirSource::open(&src, &opts).unwrap()), stage(true, mpi_net, true));
        let baked_src = Arc::new(DirSource::open(&out, &SourceOptions::default()).unwrap());
        assert!(baked_src.baked_with().unwrap().contains("onnx:depth.onnx"));
        // the baked folder through a stage with every model configured still runs none
        let baked = SourceScenes::new(baked_src, stage(true, mpi_net, true));
        assert!(raw.needs_models() && !baked.needs_models());
        let before = baked.stage.model_runs();
        let mut compared = 0;
        for i in 0..raw.len() {
            // rocket is resized by --size: the bake ran the models on its image quantised to
            // the 8 bits it stores, the raw path on the unquantised one
            if raw.id(i) == "rocket" {
                continue;
            }
            let Ok(a) = raw.load_scene(i) else { continue };
            let j = (0..baked.len()).find(|&j| baked.id(j) == a.id).expect("baked");
            let b = baked.load_scene(j).unwrap();
            assert!(a.image == b.image, "{}: image", a.id);
            assert_eq!(a.masks.masks.len(), b.masks.masks.len(), "{}: instances", a.id);
            for (ma, mb) in a.masks.masks.iter().zip(&b.masks.masks) {
                assert_eq!(ma.mask, mb.mask, "{}: mask {}", a.id, ma.id);
            }
            assert_eq!(a.mpi.disparity, b.mpi.disparity, "{}: planes", a.id);
            assert!(a.mpi.rgba == b.mpi.rgba, "{}: MPI values", a.id);
            if !mpi_net {
                assert!(a.disparity == b.disparity, "{}: disparity", a.id);
            }
            compared += 1;
        }
        assert_eq!(compared, 4);
        assert_eq!(baked.stage.model_runs(), before, "loading baked scenes ran a model");
    }
}

/// `--mpi-dtype f16`: the stored MPI is the f32 bake's rounded to f16 in a smaller file, the
/// other files are the same bytes, the manifest and the served description say so, the served
/// fingerprint differs, and a folder baked in f32 is not continued in f16.
#[test]
fn an_f16_bake_stores_the_f32_mpi_rounded() {
    let src = photos("f16_src");
    let mpi_path = model("mpi.onnx").display().to_string();
    let (a, b) = (tmp("f16_a"), tmp("f16_b"));
    bake(&src, &a, &["--mpi-model", &mpi_path]);
    bake(&src, &b, &["--mpi-model", &mpi_path, "--mpi-dtype", "f16"]);
    let (fa, fb) = (files(&a), files(&b));
    let manifest: serde_json::Value = serde_json::from_slice(&fb["bake.json"]).unwrap();
    assert_eq!(manifest["mpi_dtype"], "f16");
    let (sa, sb) = (
        DirSource::open(&a, &SourceOptions::default()).unwrap(),
        DirSource::open(&b, &SourceOptions::default()).unwrap(),
    );
    assert_ne!(sa.fingerprint(), sb.fingerprint());
    assert!(sb.baked_with().unwrap().contains("MPIs stored as f16"), "{:?}", sb.baked_with());
    assert!(!sa.baked_with().unwrap().contains("MPIs stored as"));
    for key in GOOD {
        let name = format!("mpis/{key}.npz");
        assert!(fb[&name].len() < fa[&name].len(), "{key}: {} >= {} bytes", fb[&name].len(), fa[&name].len());
        let ma = mpiflow::mpi::npz::load_npz(&a.join(&name)).unwrap();
        let mb = mpiflow::mpi::npz::load_npz(&b.join(&name)).unwrap();
        assert_eq!(ma.disparity, mb.disparity, "{key}");
        let want: Vec<f32> = ma.rgba.iter().map(|&v| half::f16::from_f32(v.min(65504.0)).to_f32()).collect();
        assert!(mb.rgba == want, "{key}: not the f32 values rounded to f16");
        assert!(ma.rgba != mb.rgba, "{key}: rounding changed nothing (the test would not see f32 stored)");
    }
    for (k, v) in fa.iter().filter(|(k, _)| !k.starts_with("mpis/") && *k != "bake.json") {
        assert!(fb[k] == *v, "{k} differs");
    }
    let o = Command::new(env!("CARGO_BIN_EXE_mpiflow"))
        .args(["bake", "--source"])
        .arg(&src)
        .arg("--out")
        .arg(&a)
        .arg("--depth-model")
        .arg(model("depth.onnx"))
        .arg("--segment-model")
        .arg(model("seg.onnx"))
        .arg("--mpi-model")
        .arg(model("mpi.onnx"))
        .args(["--size", SIZE, "--mpi-dtype", "f16"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("stores MPIs as f32"), "{e}");
}

/// A sample's members: field -> bytes.
type Fields = BTreeMap<String, Vec<u8>>;

/// Every sample of every `*.tar` in `dir`: key -> field -> bytes, and how often each key occurs.
fn tar_samples(dir: &Path) -> (BTreeMap<String, Fields>, BTreeMap<String, usize>) {
    use std::io::Read;
    let (mut out, mut seen) = (BTreeMap::new(), BTreeMap::new());
    let mut tars: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "tar"))
        .collect();
    tars.sort();
    for t in tars {
        let mut keys = BTreeSet::new();
        let mut a = tar::Archive::new(std::fs::File::open(&t).unwrap());
        for e in a.entries().unwrap() {
            let mut e = e.unwrap();
            let name = e.path().unwrap().to_string_lossy().to_string();
            let (key, field) = name.split_once('.').unwrap();
            let (key, field) = (key.to_string(), field.to_string());
            let mut bytes = Vec::new();
            e.read_to_end(&mut bytes).unwrap();
            keys.insert(key.clone());
            let fields: &mut Fields = out.entry(key).or_default();
            assert!(fields.insert(field, bytes).is_none(), "{name} twice in {}", t.display());
        }
        for k in keys {
            *seen.entry(k).or_insert(0) += 1;
        }
    }
    (out, seen)
}

/// A WebDataset bake (two shards, 2 items per tar) holds exactly the reference bake's files as
/// members, every item once; its scenes are the reference bake's scenes through no model.
#[test]
fn a_webdataset_bake_holds_the_reference_bake_member_for_member() {
    let src = photos("wds_src");
    for mpi_net in [false, true] {
        webdataset_against_reference(&src, mpi_net);
    }
}

fn webdataset_against_reference(src: &Path, mpi_net: bool) {
    let src = src.to_path_buf();
    let (whole, wds) = (tmp(&format!("wds_whole_{mpi_net}")), tmp(&format!("wds_{mpi_net}")));
    let mpi_path = model("mpi.onnx").display().to_string();
    let net: Vec<&str> = if mpi_net { vec!["--mpi-model", &mpi_path] } else { vec![] };
    bake(&src, &whole, &net);
    let wd = [&net[..], &["--format", "webdataset", "--items-per-shard", "2"]].concat();
    let (r0, _) = bake(&src, &wds, &[&wd[..], &["--shard", "0/2"]].concat());
    let (r1, _) = bake(&src, &wds, &[&wd[..], &["--shard", "1/2"]].concat());
    assert_eq!(n(&r0, "baked") + n(&r1, "baked"), 5, "{r0}\n{r1}");
    assert_eq!(n(&r0, "failed") + n(&r1, "failed"), 1);
    let (samples, seen) = tar_samples(&wds);
    assert!(seen.values().all(|&c| c == 1), "a key in two shards: {seen:?}");
    let want: BTreeSet<String> = GOOD.iter().map(ToString::to_string).collect();
    assert_eq!(samples.keys().cloned().collect::<BTreeSet<_>>(), want);
    let reference = files(&whole);
    for (key, fields) in &samples {
        let names: Vec<&str> = fields.keys().map(String::as_str).collect();
        let want: &[&str] =
            if mpi_net { &["disp.npy", "mask.png", "mpi.npz", "png"] } else { &["disp.npy", "mask.png", "png"] };
        assert_eq!(names, want, "{key}");
        for (field, sub) in [
            ("disp.npy", "disps/KEY.npy"),
            ("mask.png", "masks/KEY.png"),
            ("mpi.npz", "mpis/KEY.npz"),
            ("png", "images/KEY.png"),
        ] {
            if let Some(bytes) = fields.get(field) {
                assert!(*bytes == reference[&sub.replace("KEY", key)], "{key}.{field} differs from {sub}");
            }
        }
    }
    // at most 2 items per tar, one series of tars per shard
    let tars: Vec<String> = std::fs::read_dir(&wds)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
        .filter(|n| n.ends_with(".tar"))
        .collect();
    assert!(tars.iter().all(|t| t.starts_with("bake-0-of-2-") || t.starts_with("bake-1-of-2-")), "{tars:?}");
    assert_eq!(tars.len() as u64, n(&r0, "baked").div_ceil(2) + n(&r1, "baked").div_ceil(2), "{tars:?}");
    let manifest: serde_json::Value = serde_json::from_slice(&std::fs::read(wds.join("bake.json")).unwrap()).unwrap();
    assert_eq!(manifest["layout"], "webdataset");

    // served: the shards are a baked collection whose scenes are the reference bake's
    let shards = Arc::new(mpiflow::source::shard::ShardSource::open(&wds, &SourceOptions::default()).unwrap());
    assert!(shards.baked_with().unwrap().contains("onnx:depth.onnx"));
    let a = SourceScenes::new(
        Arc::new(DirSource::open(&whole, &SourceOptions::default()).unwrap()),
        stage(true, mpi_net, true),
    );
    let b = SourceScenes::new(shards, stage(true, mpi_net, true));
    assert!(!a.needs_models() && !b.needs_models());
    let before = b.stage.model_runs();
    assert_eq!(b.len(), 5);
    for j in 0..b.len() {
        let sb = b.load_scene(j).unwrap();
        let key = sb.id.rsplit('/').next().unwrap().to_string();
        let i = (0..a.len()).find(|&i| a.id(i) == key).expect("in the reference bake");
        let sa = a.load_scene(i).unwrap();
        assert!(sa.image == sb.image && sa.disparity == sb.disparity, "{key}");
        assert_eq!(sa.mpi.width, sb.mpi.width);
        assert!(sa.mpi.rgba == sb.mpi.rgba && sa.mpi.disparity == sb.mpi.disparity, "{key}: MPI");
        assert_eq!(sa.masks.masks.len(), sb.masks.masks.len(), "{key}: instances");
    }
    assert_eq!(b.stage.model_runs(), before, "loading baked shards ran a model");

    if mpi_net {
        return;
    }
    // a folder of one layout is not continued in the other
    let o = Command::new(env!("CARGO_BIN_EXE_mpiflow"))
        .args(["bake", "--source"])
        .arg(&src)
        .arg("--out")
        .arg(&wds)
        .arg("--depth-model")
        .arg(model("depth.onnx"))
        .arg("--segment-model")
        .arg(model("seg.onnx"))
        .args(["--size", SIZE])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("webdataset bake"), "{e}");
    assert!(!wds.join("images").exists(), "the refused bake left an images/ folder");

    // the shards re-baked into the reference layout: ids `SHARD/KEY` name files `SHARD-KEY`,
    // the bytes are the reference bake's, and the baked parts are carried, not recomputed
    let again = tmp("wds_rebaked");
    let (r, _) = bake(&wds, &again, &[]);
    assert_eq!((n(&r, "baked"), n(&r, "failed")), (5, 0), "{r}");
    let rebaked = files(&again);
    let keys = ids_of(&rebaked, "images");
    assert_eq!(keys.len(), 5, "{keys:?}");
    for name in &keys {
        let (shard, key) = name.rsplit_once('-').unwrap();
        assert!(shard.starts_with("bake-") && seen.contains_key(key), "{name}");
        for sub in ["images/KEY.png", "disps/KEY.npy", "masks/KEY.png"] {
            let (x, y) = (sub.replace("KEY", name), sub.replace("KEY", key));
            assert!(rebaked[&x] == reference[&y], "{x} differs from {y}");
        }
    }
}

/// A WebDataset bake stopped by `--limit`, then killed inside a shard (one complete sample and
/// one cut in its image), restarted: the complete sample is kept, the cut one redone, and every
/// item ends up in exactly one shard with the bytes of an uninterrupted bake.
#[test]
fn an_interrupted_webdataset_bake_restarted_loses_and_repeats_nothing() {
    let src = photos("wds_resume_src");
    let (whole, cut) = (tmp("wds_resume_whole"), tmp("wds_resume_cut"));
    bake(&src, &whole, &[]);
    let wd = ["--format", "webdataset", "--items-per-shard", "10"];
    let (r, _) = bake(&src, &cut, &[&wd[..], &["--limit", "2"]].concat());
    let (first, _) = tar_samples(&cut);
    assert_eq!(first.len() as u64, n(&r, "baked"));
    // the shard a killed run was writing: one complete sample, then one cut inside its image
    let reference = files(&whole);
    let pending: Vec<&str> = GOOD.iter().copied().filter(|id| !first.contains_key(*id)).collect();
    assert!(pending.len() >= 2, "{pending:?}");
    let member = |id: &str, sub: &str, ext: &str| reference[&format!("{sub}/{id}.{ext}")].clone();
    let partial = cut.join(".partial/0-of-1");
    std::fs::create_dir_all(&partial).unwrap();
    let killed = partial.join("bake-0-of-1-000001.tar");
    {
        let mut b = tar::Builder::new(std::fs::File::create(&killed).unwrap());
        for id in &pending[..2] {
            for (sub, ext, field) in
                [("disps", "npy", "disp.npy"), ("masks", "png", "mask.png"), ("images", "png", "png")]
            {
                let bytes = member(id, sub, ext);
                let mut h = tar::Header::new_gnu();
                h.set_size(bytes.len() as u64);
                h.set_mode(0o444);
                h.set_cksum();
                b.append_data(&mut h, format!("{id}.{field}"), bytes.as_slice()).unwrap();
            }
        }
        b.into_inner().unwrap();
    }
    // cut inside the second sample's image (and no end-of-archive block)
    let len = std::fs::metadata(&killed).unwrap().len();
    let image = member(pending[1], "images", "png").len() as u64;
    let f = std::fs::OpenOptions::new().write(true).open(&killed).unwrap();
    f.set_len(len - 1024 - image.div_ceil(512) * 512 + 100).unwrap();
    drop(f);

    let (r2, _) = bake(&src, &cut, &wd);
    assert_eq!(n(&r2, "already_done"), n(&r, "baked") + 1, "the complete sample is kept: {r2}");
    assert_eq!(n(&r, "baked") + 1 + n(&r2, "baked"), 5, "every good item baked once: {r}\n{r2}");
    assert_eq!(r2["model_runs"]["depth"], n(&r2, "baked"));
    assert!(!partial.exists(), "the killed run's shard is cleared");
    let (samples, seen) = tar_samples(&cut);
    assert!(seen.values().all(|&c| c == 1), "a key in two shards: {seen:?}");
    let want: BTreeSet<String> = GOOD.iter().map(ToString::to_string).collect();
    assert_eq!(samples.keys().cloned().collect::<BTreeSet<_>>(), want);
    for (key, fields) in &samples {
        assert!(fields["png"] == member(key, "images", "png"), "{key}: image");
        assert!(fields["disp.npy"] == member(key, "disps", "npy"), "{key}: disparity");
        assert!(fields["mask.png"] == member(key, "masks", "png"), "{key}: masks");
    }
    // the restarted shard is indexable in full: the source serves all five
    let shards = mpiflow::source::shard::ShardSource::open(&cut, &SourceOptions::default()).unwrap();
    assert_eq!((shards.len(), shards.skipped().len()), (5, 0), "{:?}", shards.skipped());
}

async fn http_get(addr: &str, path: &str) -> String {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut sock = tokio::net::TcpStream::connect(addr).await.unwrap();
    sock.write_all(format!("GET {path} HTTP/1.1\r\nHost: x\r\n\r\n").as_bytes()).await.unwrap();
    let mut out = String::new();
    sock.read_to_string(&mut out).await.unwrap();
    out
}

/// The value of a metric line `NAME{LABELS} VALUE` in an OpenMetrics text.
fn metric(text: &str, name_and_labels: &str) -> Option<f64> {
    text.lines().find_map(|l| l.strip_prefix(name_and_labels)?.trim().parse().ok())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serving_a_baked_folder_runs_no_model() {
    let src = photos("serve_src");
    let out = tmp("serve_baked");
    bake(&src, &out, &[]);
    let wds = tmp("serve_baked_wds");
    bake(&src, &wds, &["--format", "webdataset"]);
    let models = ModelConfig {
        depth_model: Some(model("depth.onnx")),
        segment_model: Some(model("seg.onnx")),
        ..ModelConfig::default()
    };
    let dataset =
        |name: &str, p: &Path| DatasetConfig { name: Some(name.into()), path: p.display().to_string(), sample: None };
    let config = ServiceConfig {
        addr: "127.0.0.1:0".into(),
        metrics_addr: Some("127.0.0.1:0".into()),
        workers: 2,
        log_level: "warn".into(),
        models,
        datasets: vec![dataset("baked", &out), dataset("raw", &src), dataset("shards", &wds)],
        ..ServiceConfig::default()
    };
    // the raw photos are served at the baked size
    let config = ServiceConfig { size: Some(SIZE.into()), ..config };
    let s = start(config).await.expect("server starts");
    let ch = Endpoint::from_shared(format!("http://{}", s.addr)).unwrap().connect().await.unwrap();
    let mut c = client_for(ch);
    let info = c.get_info(pb::InfoRequest {}).await.unwrap().into_inner();
    let baked = info.datasets.iter().find(|d| d.name == "baked").unwrap();
    let raw = info.datasets.iter().find(|d| d.name == "raw").unwrap();
    assert!(!baked.needs_models && raw.needs_models, "{baked:?}\n{raw:?}");
    assert!(baked.baked_with.contains("mpiflow bake v1") && baked.baked_with.contains("onnx:seg.onnx"), "{baked:?}");
    assert!(baked.description.contains("baked: "), "{}", baked.description);
    assert!(raw.baked_with.is_empty());
    assert_eq!(baked.sources, 5);
    let shards = info.datasets.iter().find(|d| d.name == "shards").unwrap();
    assert!(!shards.needs_models && shards.baked_with.contains("onnx:seg.onnx"), "{shards:?}");
    assert_eq!(shards.sources, 5);

    let metrics = s.metrics_addr.unwrap().to_string();
    let pull = |dataset: &str| pb::StreamRequest {
        count: 6,
        ..pb::SampleSpec { dataset: dataset.into(), seed: 3, ..Default::default() }.stream()
    };
    let mut got = 0;
    let mut st = c.stream_samples(pull("baked")).await.unwrap().into_inner();
    while let Some(b) = st.message().await.unwrap() {
        got += b.samples.len();
    }
    assert_eq!(got, 6);
    let mut st = c.stream_samples(pull("shards")).await.unwrap().into_inner();
    let mut got = 0;
    while let Some(b) = st.message().await.unwrap() {
        got += b.samples.len();
    }
    assert_eq!(got, 6);
    let m = http_get(&metrics, "/metrics").await;
    assert_eq!(metric(&m, "mpiflow_model_runs_total{role=\"depth\"}"), Some(0.0), "{m}");
    assert_eq!(metric(&m, "mpiflow_model_runs_total{role=\"segment\"}"), Some(0.0), "{m}");
    assert!(metric(&m, "mpiflow_scene_builds_total{dataset=\"baked\"}").unwrap() >= 5.0);

    // the raw photos through the same server do run the models (the counter counts)
    let mut st = c.stream_samples(pull("raw")).await.unwrap().into_inner();
    while st.message().await.unwrap().is_some() {}
    let m = http_get(&metrics, "/metrics").await;
    assert!(metric(&m, "mpiflow_model_runs_total{role=\"depth\"}").unwrap() > 0.0, "{m}");
    s.shutdown(std::time::Duration::from_secs(5)).await;
}

/// A folder that carries its depth needs no model to bake; one item whose photo is cut short
/// fails: the bake goes on with the others, then exits with status 2 naming it.
#[test]
fn a_bake_with_a_failing_item_exits_non_zero_naming_it() {
    let src = tmp("failing_src");
    std::fs::create_dir_all(src.join("images")).unwrap();
    std::fs::create_dir_all(src.join("depths")).unwrap();
    let photos = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/photos");
    for (f, id) in [("chelsea.png", "cat"), ("coffee.png", "mug"), ("rocket.jpg", "rocket")] {
        let img = resize_rgb(load_rgb(&photos.join(f), &ImageLimits::default()).unwrap(), 64, 48);
        save_rgb_png(&src.join(format!("images/{id}.png")), &img).unwrap();
        let depth: Vec<f32> = (0..64 * 48).map(|i| 1.0 + (i % 64) as f32 / 32.0).collect();
        mpiflow::io::npy::write_f32(&src.join(format!("depths/{id}.npy")), &[48, 64], &depth).unwrap();
    }
    // the rocket's PNG cut in half: it lists, then fails to decode
    let p = src.join("images/rocket.png");
    let bytes = std::fs::read(&p).unwrap();
    std::fs::write(&p, &bytes[..bytes.len() / 2]).unwrap();
    let run = |out: &Path| {
        Command::new(env!("CARGO_BIN_EXE_mpiflow"))
            .args(["bake", "--quiet", "--source"])
            .arg(&src)
            .arg("--out")
            .arg(out)
            .output()
            .unwrap()
    };
    let out = tmp("failing_out");
    let o = run(&out);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{stderr}");
    let last = stderr.lines().last().unwrap();
    assert!(last.starts_with("error: 1 of 3 items failed (rocket;"), "{stderr}");
    assert!(last.contains("bake-report.json"), "{stderr}");
    let r: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("bake-report.json")).unwrap()).unwrap();
    assert_eq!((n(&r, "baked"), n(&r, "failed")), (2, 1), "{r}");
    assert_eq!(r["failures"][0]["id"], "rocket");
    // the same folder without the broken photo: exit status 0
    std::fs::remove_file(&p).unwrap();
    let o = run(&tmp("failing_out_fixed"));
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}
