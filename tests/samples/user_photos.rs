//! A new user's folder of photos through the real `mpiflow` binary and a real server on loopback:
//! a dataset that cannot make scenes is refused at start-up with one line naming the fix (exit
//! status 2) or, uploaded at run time, with FAILED_PRECONDITION and the same text; `pull` prints
//! no "wrote 0 samples" line before an error; a mixed folder (one photo above the working size,
//! one with an object) gives the same bytes from `generate` and from `serve` + `pull`, whatever
//! the thread or worker count.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

use mpiflow::service::client::client_for;
use mpiflow::service::pb;
use mpiflow::service::{start, ServiceConfig};
use tonic::transport::Endpoint;
use tonic::Code;

const BIN: &str = env!("CARGO_BIN_EXE_mpiflow");

/// The fix the refusal names, word for word where the tests look for it.
const FIX: &str = "photos carry no depth and no depth model is configured: pass --depth-model NAME|FILE (see \
                   docs/models.md), or ship depths/ beside images/";

fn tmp(name: &str) -> PathBuf {
    let d = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("user-photos-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A textured photo of `w` x `h` (a smooth pattern that differs with `seed`), PNG-encoded.
fn photo_png(w: u32, h: u32, seed: u32) -> Vec<u8> {
    let img = image::RgbImage::from_fn(w, h, |x, y| {
        let v = |k: u32| ((x * (3 + k) + y * (5 + seed) + k * 40 + seed * 17) % 256) as u8;
        image::Rgb([v(0), v(1), v(2)])
    });
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

/// `mpiflow serve` with `args`; stdout's first line and the process.
fn serve(args: &[&str]) -> (Child, String) {
    let mut child = Command::new(BIN)
        .args(["serve", "--addr", "127.0.0.1:0", "--log-level", "warn"])
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("mpiflow serve starts");
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    (child, line)
}

#[test]
fn serve_refuses_photos_without_depth_at_start_up_naming_the_fix() {
    let dir = tmp("nodepth");
    for (i, name) in ["a.png", "b.png"].iter().enumerate() {
        std::fs::write(dir.join(name), photo_png(40, 30, i as u32)).unwrap();
    }
    let (child, first_line) = serve(&["--source", &format!("mine={}", dir.display())]);
    let out = child.wait_with_output().unwrap();
    assert_eq!(first_line, "", "nothing is served");
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8(out.stderr).unwrap();
    assert_eq!(err.lines().count(), 1, "{err}");
    assert_eq!(err.trim_end(), format!("error: dataset \"mine\": {FIX}"));
    // a folder with one photo carrying depth is served (the others are skipped one by one)
    std::fs::create_dir_all(dir.join("images")).unwrap();
    std::fs::create_dir_all(dir.join("depths")).unwrap();
    for (i, name) in ["a", "b"].iter().enumerate() {
        std::fs::rename(dir.join(format!("{name}.png")), dir.join(format!("images/{name}.png"))).unwrap();
        if i == 0 {
            let depth: Vec<f32> = (0..40 * 30).map(|k| 2.0 + (k % 40) as f32 * 0.05).collect();
            mpiflow::io::npy::write_f32(&dir.join("depths/a.npy"), &[30, 40], &depth).unwrap();
        }
    }
    let (mut child, line) = serve(&["--source", &dir.display().to_string()]);
    assert!(line.starts_with("mpiflow serving on "), "{line:?}");
    child.kill().unwrap();
    child.wait().unwrap();
}

#[test]
fn serve_refuses_a_missing_depth_model_file_in_one_line() {
    let dir = tmp("nomodel");
    std::fs::write(dir.join("a.png"), photo_png(40, 30, 1)).unwrap();
    let missing = dir.join("no-such-model.onnx");
    let (child, first_line) =
        serve(&["--source", &dir.display().to_string(), "--depth-model", &missing.display().to_string()]);
    let out = child.wait_with_output().unwrap();
    assert_eq!(first_line, "");
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8(out.stderr).unwrap();
    assert_eq!(err.lines().count(), 1, "{err}");
    assert!(err.contains("no-such-model.onnx") && err.contains("depth model"), "{err}");
}

/// Photos alone uploaded to a server without a depth model: FAILED_PRECONDITION with the fix,
/// nothing kept; the same photos with their depth are accepted.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_upload_of_photos_without_depth_is_a_failed_precondition() {
    let config = ServiceConfig {
        addr: "127.0.0.1:0".into(),
        size: Some("64x48".into()),
        workers: 1,
        log_level: "warn".into(),
        ..ServiceConfig::default()
    };
    let s = start(config).await.unwrap();
    let channel = Endpoint::from_shared(format!("http://{}", s.addr)).unwrap().connect().await.unwrap();
    let mut c = client_for(channel);
    let chunk = |name: &str, kind: &str, data: Vec<u8>| pb::SourceChunk {
        dataset: "mine".into(),
        name: name.into(),
        kind: kind.into(),
        data,
    };
    let photos = vec![chunk("a", "image", photo_png(64, 48, 1)), chunk("b", "image", photo_png(64, 48, 2))];
    let e = c.upload_sources(tokio_stream::iter(photos)).await.unwrap_err();
    assert_eq!(e.code(), Code::FailedPrecondition, "{e:?}");
    assert_eq!(e.message(), format!("dataset \"mine\": {FIX}"));
    let info = c.get_info(pb::InfoRequest {}).await.unwrap().into_inner();
    assert!(info.datasets.iter().all(|d| d.name != "mine"), "nothing of the refused upload is kept");
    let mut depth = Vec::new();
    let values: Vec<f32> = (0..64 * 48).map(|k| 2.0 + (k % 64) as f32 * 0.02).collect();
    mpiflow::io::npy::write_f32_to(&mut depth, &[48, 64], &values).unwrap();
    let with_depth = vec![chunk("a", "image", photo_png(64, 48, 1)), chunk("a", "depth", depth)];
    let summary = c.upload_sources(tokio_stream::iter(with_depth)).await.unwrap().into_inner();
    assert_eq!((summary.sources, summary.rejected.len()), (1, 0), "{summary:?}");
    s.shutdown(std::time::Duration::from_secs(5)).await;
}

/// A stream that fails at its first sample (every photo's depth file is corrupt): `pull --out`
/// prints the error alone (no "wrote 0 samples ... previews" line), exit status 2.
#[test]
fn pull_prints_no_wrote_line_before_an_error() {
    let dir = tmp("pull");
    std::fs::create_dir_all(dir.join("src/images")).unwrap();
    std::fs::create_dir_all(dir.join("src/depths")).unwrap();
    std::fs::write(dir.join("src/images/a.png"), photo_png(64, 48, 1)).unwrap();
    // a depth whose header is whole (the folder opens) and whose data ends early (it fails when
    // the scene is made, so in the stream)
    let npy = dir.join("src/depths/a.npy");
    mpiflow::io::npy::write_f32(&npy, &[48, 64], &vec![2.0; 64 * 48]).unwrap();
    let bytes = std::fs::read(&npy).unwrap();
    std::fs::write(&npy, &bytes[..bytes.len() / 2]).unwrap();
    let (mut server, line) = serve(&["--size", "64x48", "--source", &dir.join("src").display().to_string()]);
    let addr = line.trim().strip_prefix("mpiflow serving on ").unwrap_or_else(|| panic!("{line:?}")).to_string();
    let out = Command::new(BIN).args(["pull", "--addr", &addr, "--count", "2", "--out"]).arg(dir.join("out")).output();
    server.kill().unwrap();
    server.wait().unwrap();
    let out = out.unwrap();
    let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert_eq!(out.status.code(), Some(2), "{stdout}{stderr}");
    assert!(!stdout.contains("wrote"), "{stdout}");
    assert!(stderr.contains("the stream ended with") && stderr.contains("a.npy"), "{stderr}");
}

/// A reference-layout folder of photos of four sizes (and aspects), each with its depth.
fn mixed_folder(name: &str) -> PathBuf {
    let dir = tmp(name);
    std::fs::create_dir_all(dir.join("images")).unwrap();
    std::fs::create_dir_all(dir.join("depths")).unwrap();
    for (i, (w, h)) in [(96u32, 64u32), (80, 80), (120, 72), (60, 45)].into_iter().enumerate() {
        std::fs::write(dir.join(format!("images/p{i}.png")), photo_png(w, h, i as u32)).unwrap();
        let depth: Vec<f32> = (0..w * h).map(|k| 1.5 + ((k % w) as f32 / w as f32) + (k / w) as f32 * 0.01).collect();
        mpiflow::io::npy::write_f32(&dir.join(format!("depths/p{i}.npy")), &[h as u64, w as u64], &depth).unwrap();
    }
    dir
}

async fn pull_all(addr: std::net::SocketAddr, r: pb::StreamRequest) -> Vec<pb::Sample> {
    let channel = Endpoint::from_shared(format!("http://{addr}")).unwrap().connect().await.unwrap();
    let mut c = client_for(channel);
    let mut stream = c.stream_samples(r).await.unwrap().into_inner();
    let mut out = Vec::new();
    while let Some(b) = stream.message().await.unwrap() {
        out.extend(b.samples.into_iter().map(|mut s| {
            s.timings = None;
            s
        }));
    }
    out
}

/// Photos of mixed sizes with no `--size`: every sample has the frame of the largest photo
/// (120x72 here, smaller than the working size), so a crop that fits it fits every photo's
/// samples; two servers give the same bytes; `--size` still sets the size.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn photos_of_mixed_sizes_serve_one_frame_and_any_crop_that_fits_it() {
    let dir = mixed_folder("mixed");
    let config = |size: Option<&str>| ServiceConfig {
        addr: "127.0.0.1:0".into(),
        size: size.map(str::to_string),
        workers: 2,
        log_level: "warn".into(),
        datasets: vec![mpiflow::service::config::DatasetConfig::parse(&dir.display().to_string()).unwrap()],
        ..ServiceConfig::default()
    };
    let spec = |crop: Option<pb::OutputCrop>| {
        let spec = pb::SampleSpec { seed: 3, motions_per_image: Some(1), crop, ..Default::default() };
        pb::StreamRequest { count: 8, ..spec.stream() }
    };
    let center = |width, height| Some(pb::OutputCrop { width, height, mode: pb::CropMode::Center as i32 });
    let request = spec(center(112, 64));
    let a = start(config(None)).await.unwrap();
    let b = start(config(None)).await.unwrap();
    let (sa, sb) = (pull_all(a.addr, request.clone()).await, pull_all(b.addr, request.clone()).await);
    assert_eq!(sa.len(), 8);
    let ids: std::collections::BTreeSet<&str> = sa.iter().map(|s| s.source_id.as_str()).collect();
    assert_eq!(ids.len(), 4, "every photo is served: {ids:?}");
    for s in &sa {
        assert_eq!((s.width, s.height), (112, 64), "{}", s.source_id);
        let image1 = s.tensors.iter().find(|t| t.name == "image1").unwrap();
        assert_eq!(image1.shape, [64, 112, 3]);
    }
    assert_eq!(sa, sb, "same address, same bytes");
    // the frame is the largest photo's: a crop wider than it is refused, naming 120x72
    let wide = spec(center(121, 64));
    let channel = Endpoint::from_shared(format!("http://{}", a.addr)).unwrap().connect().await.unwrap();
    let mut stream = client_for(channel).stream_samples(wide).await.unwrap().into_inner();
    let e = loop {
        match stream.message().await {
            Ok(Some(_)) => continue,
            Ok(None) => panic!("a crop wider than the frame was served"),
            Err(e) => break e,
        }
    };
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().contains("120x72"), "{}", e.message());
    // --size still sets the frame
    let c = start(config(Some("64x48"))).await.unwrap();
    let sc = pull_all(c.addr, spec(None)).await;
    assert!(sc.iter().all(|s| (s.width, s.height) == (64, 48)));
    for s in [a, b, c] {
        s.shutdown(std::time::Duration::from_secs(5)).await;
    }
}

/// A folder with photos larger than the working size is rendered at the working size (the
/// largest photo's 4:3 aspect at 640x480), every photo covering it, whatever its own size.
#[test]
fn large_photos_are_rendered_at_the_working_size() {
    let dir = tmp("working-size");
    std::fs::create_dir_all(dir.join("images")).unwrap();
    std::fs::create_dir_all(dir.join("depths")).unwrap();
    for (i, (w, h)) in [(1600u32, 1200u32), (800, 450)].into_iter().enumerate() {
        std::fs::write(dir.join(format!("images/p{i}.png")), photo_png(w, h, i as u32)).unwrap();
        let depth: Vec<f32> = (0..w * h).map(|k| 1.5 + ((k % w) as f32 / w as f32)).collect();
        mpiflow::io::npy::write_f32(&dir.join(format!("depths/p{i}.npy")), &[h as u64, w as u64], &depth).unwrap();
    }
    let out = dir.join("out");
    let r = Command::new(BIN)
        .args(["generate", "--source", &dir.display().to_string(), "--count", "2", "--objects", "0"])
        .args(["--preview-every", "0", "--out", &out.display().to_string()])
        .output()
        .unwrap();
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    let mut ids = Vec::new();
    for i in 0..2 {
        assert_eq!(image::image_dimensions(out.join(format!("{i:08}_img1.png"))).unwrap(), (640, 480), "sample {i}");
        let record: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join(format!("{i:08}.json"))).unwrap()).unwrap();
        ids.push(record["source_id"].as_str().unwrap().to_owned());
    }
    assert_eq!(ids, ["p0", "p1"], "consecutive samples come from different photos");
}

/// `mpiflow generate` on the same mixed folder writes every sample at the frame's size.
#[test]
fn generate_exports_photos_of_mixed_sizes_at_one_size() {
    let dir = mixed_folder("mixed-generate");
    let out = dir.join("out");
    let r = Command::new(BIN)
        .args(["generate", "--source", &dir.display().to_string(), "--count", "4", "--motions-per-image", "1"])
        .args(["--format", "flo", "--out", &out.display().to_string()])
        .output()
        .unwrap();
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    for i in 0..4 {
        let (w, h) = image::image_dimensions(out.join(format!("{i:08}_img1.png"))).unwrap();
        assert_eq!((w, h), (120, 72), "sample {i}");
    }
}

/// A mixed folder with a photo larger than the working size, at the defaults (working size,
/// scene windows, one moving object): `generate` on one thread and on two, and a server with
/// one worker and with two pulled into the same layout, write the same bytes for every sample;
/// so do `generate --crop 496x368 --random-crop` and `pull` with the same crop.
#[test]
fn a_mixed_folder_gives_the_same_bytes_from_generate_and_pull_on_any_worker_count() {
    let dir = mixed_folder("mixed-bytes");
    std::fs::write(dir.join("images/large.png"), photo_png(1600, 1200, 9)).unwrap();
    let depth: Vec<f32> =
        (0..1600 * 1200).map(|k| 2.0 - ((k % 1600) as f32 / 1600.0) + (k / 1600) as f32 * 1e-4).collect();
    mpiflow::io::npy::write_f32(&dir.join("depths/large.npy"), &[1200, 1600], &depth).unwrap();
    // an object (instance 1) in the large photo
    std::fs::create_dir_all(dir.join("masks")).unwrap();
    let mask = image::GrayImage::from_fn(1600, 1200, |x, y| {
        image::Luma([u8::from((500..1100).contains(&x) && (300..900).contains(&y))])
    });
    mask.save(dir.join("masks/large.png")).unwrap();
    let source = dir.display().to_string();
    let n = "6";
    let files = ["img1.png", "img2.png", "flow.flo", "valid.png", "occ.png", "holes.png", "mask.png"];
    let mut outs = Vec::new();
    let crop = ["--crop", "496x368", "--random-crop"];
    let mut cropped = Vec::new();
    for threads in ["1", "2"] {
        let out = dir.join(format!("generate-{threads}"));
        let r = Command::new(BIN)
            .args(["generate", "--source", &source, "--count", n, "--threads", threads, "--quiet"])
            .args(["--preview-every", "0", "--out", &out.display().to_string()])
            .output()
            .unwrap();
        assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
        outs.push(out);
    }
    let out = dir.join("generate-crop");
    let r = Command::new(BIN)
        .args(["generate", "--source", &source, "--count", n, "--quiet", "--preview-every", "0"])
        .args(crop)
        .args(["--out", &out.display().to_string()])
        .output()
        .unwrap();
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    cropped.push(out);
    for workers in ["1", "2"] {
        let (mut child, line) = serve(&["--source", &source, "--workers", workers]);
        let addr = line.trim().strip_prefix("mpiflow serving on ").unwrap_or_else(|| panic!("printed {line:?}"));
        let addr = addr.split_whitespace().next().unwrap().to_string();
        let pull = |out: &PathBuf, extra: &[&str]| {
            let r = Command::new(BIN)
                .args([
                    "pull",
                    "--addr",
                    &addr,
                    "--count",
                    n,
                    "--preview-every",
                    "0",
                    "--out",
                    &out.display().to_string(),
                ])
                .args(extra)
                .output()
                .unwrap();
            assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
        };
        let out = dir.join(format!("pull-{workers}"));
        pull(&out, &[]);
        outs.push(out);
        let out = dir.join(format!("pull-crop-{workers}"));
        pull(&out, &crop);
        cropped.push(out);
        child.kill().unwrap();
        child.wait().unwrap();
    }
    let mut sizes = std::collections::BTreeSet::new();
    let mut with_masks = 0;
    for (i, outs) in (0..6).flat_map(|i| [(i, &outs), (i, &cropped)]) {
        sizes.insert(image::image_dimensions(outs[0].join(format!("{i:08}_img1.png"))).unwrap());
        for f in files {
            let path = |o: &PathBuf| o.join(format!("{i:08}_{f}"));
            let first = std::fs::read(path(&outs[0])).ok();
            with_masks += usize::from(f == "mask.png" && first.is_some());
            for o in &outs[1..] {
                assert!(
                    std::fs::read(path(o)).ok() == first,
                    "{} differs from {}",
                    path(o).display(),
                    path(&outs[0]).display()
                );
            }
        }
    }
    assert_eq!(
        sizes.into_iter().collect::<Vec<_>>(),
        [(496, 368), (640, 480)],
        "the working size of a 1600x1200 photo, and the crop"
    );
    assert!(with_masks > 0, "objects moved in some samples");
}
