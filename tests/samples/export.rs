//! The export formats read back by independent readers: NumPy for `.flo` (RAFT's `readFlow`)
//! and KITTI flow PNGs (RAFT's `readFlowKITTI`, with a zlib/NumPy PNG decoder because Pillow
//! truncates 16-bit RGB), Pillow for 8-bit PNGs, `json` for the records and the `webdataset`
//! library for the tar shards; plus preview sheets, atomic writing and the `generate` CLI.
//!
//! The Python side runs under `$MPIFLOW_PYTHON` (set by `eval "$(bash tools/setup_python.sh)"`,
//! which `bash tools/test.sh` does).

use std::path::{Path, PathBuf};
use std::process::Command;

use mpiflow::export::preview::{sheet_size, PreviewOptions};
use mpiflow::export::{sample_key, ExportError, ExportFormat, ExportOptions, Exporter};
use mpiflow::sample::motion::{Motion, RotationKind};
use mpiflow::sample::{ObjectRecord, Sample, SampleAddress, StageTimings};
use serde_json::Value;

const W: usize = 40;
const H: usize = 30;

fn python() -> PathBuf {
    match std::env::var_os("MPIFLOW_PYTHON") {
        Some(p) if !p.is_empty() => PathBuf::from(p),
        _ => panic!(
            "MPIFLOW_PYTHON is not set: these tests read the exports back with numpy, pillow and webdataset \
             from the project's Python environment; run `bash tools/test.sh` (or \
             `eval \"$(bash tools/setup_python.sh)\"` first)"
        ),
    }
}

/// Runs a Python script with arguments and parses its stdout as JSON.
fn run_python(script: &str, args: &[&str]) -> Value {
    let dir = tmpdir("py");
    let path = dir.join("reader.py");
    std::fs::write(&path, script).unwrap();
    let out = Command::new(python()).arg(&path).args(args).output().expect("cannot start $MPIFLOW_PYTHON");
    let _ = std::fs::remove_dir_all(&dir);
    assert!(
        out.status.success(),
        "python reader failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("reader output is not JSON ({e})"))
}

fn tmpdir(name: &str) -> PathBuf {
    use std::sync::atomic::{AtomicUsize, Ordering};
    static N: AtomicUsize = AtomicUsize::new(0);
    let d = std::env::temp_dir().join(format!(
        "mpiflow-export-{}-{name}-{}",
        std::process::id(),
        N.fetch_add(1, Ordering::Relaxed)
    ));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A small sample with known, distinct values; `objects` adds two moved objects.
fn make_sample(index: u64, objects: bool) -> Sample {
    let n = W * H;
    let k = index as f32;
    let mut image1 = Vec::with_capacity(n * 3);
    let mut image2 = Vec::with_capacity(n * 3);
    let mut flow = Vec::with_capacity(n * 2);
    let mut valid = vec![1u8; n];
    let mut occlusion = vec![0u8; n];
    let mut mask1 = vec![0u8; n];
    let mut mask2 = vec![0u8; n];
    for y in 0..H {
        for x in 0..W {
            let i = y * W + x;
            image1.extend_from_slice(&[(x * 6) as u8, (y * 8) as u8, ((x + y) * 3 + index as usize) as u8]);
            image2.extend_from_slice(&[(255 - x * 6) as u8, (y * 5 + 7) as u8, ((x * y) % 251) as u8]);
            // not multiples of 1/64, some negative, up to ~+-90 px
            flow.push((x as f32 - 20.0) * 1.37 + 0.1 + k * 0.01);
            flow.push((y as f32 - 15.0) * -2.11 + 0.3 - ((x * y) as f32) * 0.173);
            if x == 0 || y == H - 1 || (x + y) % 17 == 0 {
                valid[i] = 0;
            }
            if (10..15).contains(&x) && y > 3 {
                occlusion[i] = 1;
            }
            if objects {
                if (5..15).contains(&x) && (5..12).contains(&y) {
                    mask1[i] = 1;
                }
                if (20..30).contains(&x) && (10..20).contains(&y) {
                    mask1[i] = 2;
                }
                if (7..17).contains(&x) && (5..12).contains(&y) {
                    mask2[i] = 1;
                }
            }
        }
    }
    // a few exactly representable extremes
    flow[0] = -511.5;
    flow[1] = 300.0 + 1.0 / 64.0;
    let camera = Motion::new("paper-kitti", [0.1, -0.05, -0.2], RotationKind::EulerZyx, [0.01, -0.02, 0.005]);
    let objects = if objects {
        vec![
            ObjectRecord {
                label: 1,
                instance: 7,
                score: 0.9,
                area: 70.0,
                motion: Motion::new("paper-kitti", [0.05, 0.0, 0.0], RotationKind::AxisAngle, [0.0, 0.01, 0.0]),
            },
            ObjectRecord { label: 2, instance: 3, score: 0.75, area: 100.0, motion: Motion::identity("paper-kitti") },
        ]
    } else {
        Vec::new()
    };
    Sample {
        address: SampleAddress { dataset: 0xfedc_ba98_7654_3210, seed: 42, index },
        source_id: format!("photo-{}", index % 3),
        width: W,
        height: H,
        image1,
        image2,
        flow,
        valid,
        occlusion,
        mask1,
        mask2,
        camera,
        objects,
        depth1: (0..n).map(|i| 1.0 + i as f32 * 0.01).collect(),
        depth2: (0..n).map(|i| if i % 7 == 0 { 0.0 } else { 2.0 + i as f32 * 0.01 }).collect(),
        holes: (0..n).map(|i| u8::from(i % 7 == 0)).collect(),
        inpainted_pixels: 17,
        backward: Default::default(),
        clip: Vec::new(),
        skipped_sources: 0,
        provenance: vec!["depth: test".into(), "mpi: test".into()],
        intrinsics: mpiflow::geometry::Intrinsics::reference_default(W, H),
        timings: StageTimings {
            scene_ms: 1.0,
            render_ms: 2.0,
            objects_ms: 3.0,
            merge_ms: 0.5,
            inpaint_ms: 0.25,
            total_ms: 6.75,
        },
    }
}

fn as_u8(v: &Value) -> Vec<u8> {
    v.as_array().unwrap().iter().map(|x| x.as_u64().unwrap() as u8).collect()
}

fn as_f32(v: &Value) -> Vec<f32> {
    v.as_array().unwrap().iter().map(|x| x.as_f64().unwrap() as f32).collect()
}

fn to255(m: &[u8]) -> Vec<u8> {
    m.iter().map(|&v| if v != 0 { 255 } else { 0 }).collect()
}

fn list_files(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> =
        std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    v.sort();
    v
}

/// Readers for the flat layouts: RAFT's `readFlow` (numpy), RAFT's `readFlowKITTI` on a PNG
/// decoded with zlib + numpy, Pillow for 8-bit PNGs.
const FLAT_READER: &str = r#"
import json, os, struct, sys, zlib
import numpy as np
from PIL import Image

out, key, fmt = sys.argv[1], sys.argv[2], sys.argv[3]

def read_flo(path):
    # RAFT core/utils/frame_utils.py readFlow
    with open(path, 'rb') as f:
        magic = np.fromfile(f, np.float32, count=1)
        assert magic.size == 1 and magic[0] == 202021.25, magic
        w = np.fromfile(f, np.int32, count=1)[0]
        h = np.fromfile(f, np.int32, count=1)[0]
        data = np.fromfile(f, np.float32, count=2 * int(w) * int(h))
        assert data.size == 2 * w * h
        assert f.read() == b'', 'trailing bytes'
    return np.resize(data, (int(h), int(w), 2)), int(w), int(h)

def read_png16_rgb(path):
    # a minimal PNG decoder (Pillow reads 16-bit RGB as 8-bit)
    b = open(path, 'rb').read()
    assert b[:8] == b'\x89PNG\r\n\x1a\n'
    pos, idat, ihdr = 8, b'', None
    while pos < len(b):
        n, = struct.unpack('>I', b[pos:pos + 4])
        t, d = b[pos + 4:pos + 8], b[pos + 8:pos + 8 + n]
        assert zlib.crc32(t + d) == struct.unpack('>I', b[pos + 8 + n:pos + 12 + n])[0], 'bad CRC'
        pos += 12 + n
        if t == b'IHDR':
            ihdr = struct.unpack('>IIBBBBB', d)
        elif t == b'IDAT':
            idat += d
        elif t == b'IEND':
            break
    w, h, depth, ctype, _, _, interlace = ihdr
    assert (depth, ctype, interlace) == (16, 2, 0), ihdr
    raw = zlib.decompress(idat)
    bpp, stride = 6, w * 6
    assert len(raw) == h * (stride + 1)
    out = np.zeros((h, stride), np.uint8)
    prev = [0] * stride
    for y in range(h):
        ft = raw[y * (stride + 1)]
        line = raw[y * (stride + 1) + 1:(y + 1) * (stride + 1)]
        cur = [0] * stride
        for i in range(stride):
            a = cur[i - bpp] if i >= bpp else 0
            c = prev[i - bpp] if i >= bpp else 0
            up = prev[i]
            if ft == 0: p = 0
            elif ft == 1: p = a
            elif ft == 2: p = up
            elif ft == 3: p = (a + up) // 2
            elif ft == 4:
                pa, pb, pc = abs(up - c), abs(a - c), abs(a + up - 2 * c)
                p = a if pa <= pb and pa <= pc else (up if pb <= pc else c)
            else: raise ValueError('filter %d' % ft)
            cur[i] = (line[i] + p) & 255
        out[y] = cur
        prev = cur
    return out.view('>u2').reshape(h, w, 3).astype(np.float32)

def read_flow_kitti(path):
    # RAFT readFlowKITTI: flow = (png[..., :2] - 2**15) / 64, valid = png[..., 2]
    png = read_png16_rgb(path)
    flow, valid = png[:, :, :2], png[:, :, 2]
    flow = (flow - 2 ** 15) / 64.0
    return flow, valid

def png8(name, mode):
    im = Image.open(os.path.join(out, '%s_%s.png' % (key, name)))
    assert im.mode == mode, (name, im.mode)
    return np.asarray(im)

res = {'files': sorted(os.listdir(out))}
res['img1'] = png8('img1', 'RGB').reshape(-1).tolist()
res['img2'] = png8('img2', 'RGB').reshape(-1).tolist()
res['valid'] = png8('valid', 'L').reshape(-1).tolist()
res['occ'] = png8('occ', 'L').reshape(-1).tolist()
res['holes'] = png8('holes', 'L').reshape(-1).tolist()
mask_path = os.path.join(out, key + '_mask.png')
res['mask'] = png8('mask', 'L').reshape(-1).tolist() if os.path.exists(mask_path) else None
if fmt == 'flo':
    flow, w, h = read_flo(os.path.join(out, key + '_flow.flo'))
    res['size'] = [w, h]
    res['flow'] = [float(x) for x in flow.reshape(-1)]
else:
    p = os.path.join(out, key + '_flow.png')
    im = Image.open(p)
    res['size'] = list(im.size)
    flow, valid = read_flow_kitti(p)
    res['flow'] = [float(x) for x in flow.reshape(-1)]
    res['kitti_valid'] = [int(x) for x in valid.reshape(-1)]
with open(os.path.join(out, key + '.json')) as f:
    res['json'] = json.load(f)
print(json.dumps(res))
"#;

/// A value as it reads back from its JSON text (f32 fields are written in their shortest form).
fn as_written<T: serde::Serialize>(v: &T) -> Value {
    serde_json::from_str(&serde_json::to_string(v).unwrap()).unwrap()
}

/// Structural equality of JSON values, numbers within 1e-14 relative.
fn json_close(a: &Value, b: &Value, at: &str) {
    match (a, b) {
        (Value::Number(x), Value::Number(y)) => {
            let (x, y) = (x.as_f64().unwrap(), y.as_f64().unwrap());
            assert!((x - y).abs() <= 1e-14 * x.abs().max(y.abs()).max(1e-300), "{at}: {x} != {y}");
        }
        (Value::Array(x), Value::Array(y)) => {
            assert_eq!(x.len(), y.len(), "{at}: lengths");
            for (i, (p, q)) in x.iter().zip(y).enumerate() {
                json_close(p, q, &format!("{at}[{i}]"));
            }
        }
        (Value::Object(x), Value::Object(y)) => {
            assert_eq!(x.keys().collect::<Vec<_>>(), y.keys().collect::<Vec<_>>(), "{at}: keys");
            for (k, p) in x {
                json_close(p, &y[k], &format!("{at}.{k}"));
            }
        }
        _ => assert_eq!(a, b, "{at}"),
    }
}

fn check_json(j: &Value, index: u64, s: &Sample, flow_field: &str) {
    assert_eq!(j["mpiflow_export"], 1);
    assert_eq!(j["key"], sample_key(index));
    assert_eq!(j["index"], index);
    assert_eq!(j["source_id"], s.source_id.as_str());
    assert_eq!(j["address"]["dataset"].as_u64(), Some(s.address.dataset));
    assert_eq!(j["address"]["dataset_hex"], "fedcba9876543210");
    assert_eq!(j["address"]["seed"], 42);
    assert_eq!(j["address"]["index"], index);
    assert_eq!((j["width"].as_u64(), j["height"].as_u64()), (Some(W as u64), Some(H as u64)));
    // numbers went through Python's json (exact) and back through serde_json's parser (within
    // an ulp without its float_roundtrip feature)
    json_close(&j["camera"], &as_written(&s.camera), "camera");
    json_close(&j["objects"], &as_written(&s.objects), "objects");
    json_close(&j["timings"], &as_written(&s.timings), "timings");
    let camera: Motion = serde_json::from_value(j["camera"].clone()).unwrap();
    assert_eq!(camera.translation, s.camera.translation);
    let objects: Vec<ObjectRecord> = serde_json::from_value(j["objects"].clone()).unwrap();
    assert_eq!(objects.len(), s.objects.len());
    assert_eq!(j["provenance"], serde_json::json!(["depth: test", "mpi: test"]));
    assert_eq!(j["inpainted_pixels"], 17);
    let fields: Vec<String> = serde_json::from_value(j["fields"].clone()).unwrap();
    let mut want = vec![
        "img1.png".to_string(),
        "img2.png".into(),
        flow_field.into(),
        "valid.png".into(),
        "occ.png".into(),
        "holes.png".into(),
    ];
    if !s.objects.is_empty() {
        want.push("mask.png".into());
    }
    want.push("json".into());
    assert_eq!(fields, want);
    let vf = j["stats"]["valid_fraction"].as_f64().unwrap();
    let expect = s.valid.iter().filter(|&&v| v != 0).count() as f64 / s.valid.len() as f64;
    assert!((vf - expect).abs() < 1e-12);
}

fn options(format: ExportFormat, dir: &Path) -> ExportOptions {
    let mut o = ExportOptions::new(format, dir);
    o.preview = PreviewOptions { every: 0, ..PreviewOptions::default() };
    o
}

#[test]
fn flo_layout_reads_back_exactly_with_numpy_and_pillow() {
    let dir = tmpdir("flo");
    let samples = [(0u64, make_sample(0, true)), (42, make_sample(42, false))];
    let mut ex = Exporter::create(options(ExportFormat::Flo, &dir)).unwrap();
    for (i, s) in &samples {
        ex.write(*i, s).unwrap();
    }
    let summary = ex.finish().unwrap();
    assert_eq!(summary.samples, 2);
    assert!(summary.shards.is_empty() && summary.previews.is_empty());

    let mut expect_files = vec![];
    for (key, objects) in [("00000000", true), ("00000042", false)] {
        for f in ["img1.png", "img2.png", "flow.flo", "valid.png", "occ.png", "holes.png"] {
            expect_files.push(format!("{key}_{f}"));
        }
        if objects {
            expect_files.push(format!("{key}_mask.png"));
        }
        expect_files.push(format!("{key}.json"));
    }
    expect_files.sort();
    assert_eq!(list_files(&dir), expect_files, "exact layout, no temporary files left");

    for (i, s) in &samples {
        let r = run_python(FLAT_READER, &[dir.to_str().unwrap(), &sample_key(*i), "flo"]);
        assert_eq!(r["size"], serde_json::json!([W, H]));
        assert_eq!(as_f32(&r["flow"]), s.flow, "flow must round-trip exactly");
        assert_eq!(as_u8(&r["img1"]), s.image1);
        assert_eq!(as_u8(&r["img2"]), s.image2);
        assert_eq!(as_u8(&r["valid"]), to255(&s.valid));
        assert_eq!(as_u8(&r["occ"]), to255(&s.occlusion));
        assert_eq!(as_u8(&r["holes"]), to255(&s.holes));
        if s.objects.is_empty() {
            assert!(r["mask"].is_null());
        } else {
            assert_eq!(as_u8(&r["mask"]), s.mask1, "mask holds the raw object labels");
        }
        check_json(&r["json"], *i, s, "flow.flo");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn kitti_layout_reads_back_within_quantisation() {
    let dir = tmpdir("kitti");
    let s = make_sample(7, true);
    let mut ex = Exporter::create(options(ExportFormat::Kitti, &dir)).unwrap();
    ex.write(7, &s).unwrap();
    ex.finish().unwrap();
    let files = list_files(&dir);
    assert!(files.contains(&"00000007_flow.png".to_string()), "{files:?}");
    assert!(!files.iter().any(|f| f.ends_with(".flo")), "{files:?}");

    let r = run_python(FLAT_READER, &[dir.to_str().unwrap(), "00000007", "kitti"]);
    assert_eq!(r["size"], serde_json::json!([W, H]));
    let flow = as_f32(&r["flow"]);
    assert_eq!(flow.len(), s.flow.len());
    let mut max_err = 0.0f32;
    for (a, b) in flow.iter().zip(&s.flow) {
        max_err = max_err.max((a - b).abs());
        // the stored value is the nearest multiple of 1/64
        assert_eq!(*a, (b * 64.0).round() / 64.0);
    }
    assert!(max_err <= 1.0 / 128.0 + 1e-5, "max error {max_err}");
    assert_eq!(flow[0], -511.5);
    assert_eq!(flow[1], 300.0 + 1.0 / 64.0);
    let kv: Vec<u8> = r["kitti_valid"].as_array().unwrap().iter().map(|v| v.as_u64().unwrap() as u8).collect();
    assert_eq!(kv, s.valid, "the KITTI B channel is the valid mask");
    assert_eq!(as_u8(&r["img1"]), s.image1);
    assert_eq!(as_u8(&r["mask"]), s.mask1);
    assert_eq!(as_u8(&r["occ"]), to255(&s.occlusion));
    check_json(&r["json"], 7, &s, "flow.png");

    // the crate's own KITTI reader agrees
    let k = mpiflow::io::flo::read_kitti_flow_png(&dir.join("00000007_flow.png")).unwrap();
    assert_eq!(k.flow, flow);
    assert_eq!(k.valid, s.valid);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Reads every shard with the `webdataset` library (PIL decoding for images, its default
/// handlers for .npy and .json) and with `tarfile` for the member names.
const WDS_READER: &str = r#"
import glob, io, json, os, sys, tarfile
import numpy as np
import webdataset as wds
from PIL import Image

def gray(data):
    im = Image.open(io.BytesIO(data))
    assert im.mode == 'L', im.mode
    return np.asarray(im)

out = sys.argv[1]
urls = sorted(glob.glob(os.path.join(out, 'shard-*.tar')))
res = {'shards': [os.path.basename(u) for u in urls], 'members': {}, 'samples': []}
for u in urls:
    with tarfile.open(u) as t:
        res['members'][os.path.basename(u)] = [(m.name, m.size, m.mode) for m in t.getmembers()]
# masks as 8-bit gray arrays, images through webdataset's own 'rgb8' handler (uint8 HxWx3)
masks = wds.handle_extension('valid.png occ.png holes.png mask.png', gray)
ds = wds.WebDataset(urls, shardshuffle=False).decode(masks, 'rgb8')
for s in ds:
    flow = s['flow.npy']
    assert isinstance(flow, np.ndarray) and flow.dtype == np.float32, type(flow)
    img1, img2 = s['img1.png'], s['img2.png']
    assert isinstance(img1, np.ndarray) and img1.dtype == np.uint8, type(img1)
    assert isinstance(s['json'], dict)
    r = {
        'key': s['__key__'],
        'fields': sorted(k for k in s if not k.startswith('__')),
        'flow_shape': list(flow.shape),
        'flow': [float(x) for x in flow.reshape(-1)],
        'img1': img1.reshape(-1).tolist(),
        'img1_shape': list(img1.shape),
        'img2': img2.reshape(-1).tolist(),
        'valid': s['valid.png'].reshape(-1).tolist(),
        'occ': s['occ.png'].reshape(-1).tolist(),
        'holes': s['holes.png'].reshape(-1).tolist(),
        'mask': s['mask.png'].reshape(-1).tolist() if 'mask.png' in s else None,
        'json': s['json'],
    }
    res['samples'].append(r)
# the default decoder (no image handler) decodes .npy and .json and leaves PNG bytes
plain = next(iter(wds.WebDataset(urls[:1], shardshuffle=False).decode()))
assert isinstance(plain['flow.npy'], np.ndarray) and isinstance(plain['json'], dict)
assert isinstance(plain['img1.png'], bytes)
print(json.dumps(res))
"#;

#[test]
fn webdataset_shards_round_trip_through_the_webdataset_library() {
    let dir = tmpdir("wds");
    let mut o = options(ExportFormat::WebDataset, &dir);
    o.shard_size = 2;
    let mut ex = Exporter::create(o).unwrap();
    // index 3 is "skipped" (a failed source): shards follow the index, not the count
    let indices = [0u64, 1, 2, 4, 5];
    let samples: Vec<(u64, Sample)> = indices.iter().map(|&i| (i, make_sample(i, i % 2 == 0))).collect();
    for (i, s) in &samples {
        ex.write(*i, s).unwrap();
    }
    let summary = ex.finish().unwrap();
    let names: Vec<String> =
        summary.shards.iter().map(|p| p.file_name().unwrap().to_string_lossy().into_owned()).collect();
    assert_eq!(names, ["shard-000000.tar", "shard-000001.tar", "shard-000002.tar"]);
    assert_eq!(list_files(&dir), names, "only finished shards, no temporary files");

    let r = run_python(WDS_READER, &[dir.to_str().unwrap()]);
    assert_eq!(r["shards"], serde_json::json!(names));
    let members = r["members"]["shard-000000.tar"].as_array().unwrap();
    let member_names: Vec<&str> = members.iter().map(|m| m[0].as_str().unwrap()).collect();
    assert_eq!(
        member_names,
        [
            "00000000.img1.png",
            "00000000.img2.png",
            "00000000.flow.npy",
            "00000000.valid.png",
            "00000000.occ.png",
            "00000000.holes.png",
            "00000000.mask.png",
            "00000000.json",
            "00000001.img1.png",
            "00000001.img2.png",
            "00000001.flow.npy",
            "00000001.valid.png",
            "00000001.occ.png",
            "00000001.holes.png",
            "00000001.json",
        ]
    );
    assert!(members.iter().all(|m| m[2] == 0o444));
    let got = r["samples"].as_array().unwrap();
    assert_eq!(got.len(), samples.len());
    for (g, (i, s)) in got.iter().zip(&samples) {
        assert_eq!(g["key"], sample_key(*i));
        let mut fields = vec!["flow.npy", "holes.png", "img1.png", "img2.png", "json", "occ.png", "valid.png"];
        if !s.objects.is_empty() {
            fields.push("mask.png");
            fields.sort();
        }
        assert_eq!(g["fields"], serde_json::json!(fields));
        assert_eq!(g["flow_shape"], serde_json::json!([H, W, 2]));
        assert_eq!(as_f32(&g["flow"]), s.flow, "flow.npy must round-trip exactly");
        assert_eq!(g["img1_shape"], serde_json::json!([H, W, 3]));
        assert_eq!(as_u8(&g["img1"]), s.image1);
        assert_eq!(as_u8(&g["img2"]), s.image2);
        assert_eq!(as_u8(&g["valid"]), to255(&s.valid));
        assert_eq!(as_u8(&g["occ"]), to255(&s.occlusion));
        assert_eq!(as_u8(&g["holes"]), to255(&s.holes));
        if s.objects.is_empty() {
            assert!(g["mask"].is_null());
        } else {
            assert_eq!(as_u8(&g["mask"]), s.mask1);
        }
        check_json(&g["json"], *i, s, "flow.npy");
    }

    // same samples, same shard bytes
    let dir2 = tmpdir("wds2");
    let mut o = options(ExportFormat::WebDataset, &dir2);
    o.shard_size = 2;
    let mut ex = Exporter::create(o).unwrap();
    for (i, s) in &samples {
        ex.write(*i, s).unwrap();
    }
    ex.finish().unwrap();
    for n in &names {
        assert_eq!(std::fs::read(dir.join(n)).unwrap(), std::fs::read(dir2.join(n)).unwrap(), "{n}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
    std::fs::remove_dir_all(&dir2).unwrap();
}

#[test]
fn an_unfinished_shard_never_appears_under_its_final_name() {
    let dir = tmpdir("wds-atomic");
    let mut o = options(ExportFormat::WebDataset, &dir);
    o.shard_size = 10;
    let mut ex = Exporter::create(o).unwrap();
    ex.write(0, &make_sample(0, false)).unwrap();
    ex.write(1, &make_sample(1, true)).unwrap();
    // in progress: only the hidden temporary file exists
    assert_eq!(list_files(&dir), [".shard-000000.tar.tmp"]);
    // indices must increase
    let e = ex.write(1, &make_sample(1, true)).unwrap_err();
    assert!(e.to_string().contains("increasing index order"), "{e}");
    // dropped without finishing (an error path): the partial shard is removed
    drop(ex);
    assert!(list_files(&dir).is_empty(), "{:?}", list_files(&dir));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn preview_sheets_have_the_expected_size() {
    let dir = tmpdir("preview");
    let mut o = ExportOptions::new(ExportFormat::Flo, &dir);
    o.preview = PreviewOptions { every: 4, rows: 2, panel_width: 64 };
    let mut ex = Exporter::create(o).unwrap();
    // the first written sample (1) always starts a sheet; then 4 and 8 (index multiples of 4)
    for i in 1..10u64 {
        ex.write(i, &make_sample(i, i % 2 == 1)).unwrap();
    }
    let summary = ex.finish().unwrap();
    let pdir = dir.join("previews");
    assert_eq!(list_files(&pdir), ["preview-00000001.png", "preview-00000004.png", "preview-00000008.png"]);
    assert_eq!(summary.previews.len(), 3);
    let (sw, sh) = sheet_size(&[(W, H), (W, H)], 64);
    // 5 panels of 64 px + 6 gaps of 2 px; rows of 48 px (30 * 64 / 40) + gaps
    assert_eq!((sw, sh), (5 * 64 + 6 * 2, 2 + 2 * (48 + 2)));
    for name in ["preview-00000001.png", "preview-00000004.png", "preview-00000008.png"] {
        let img = image::open(pdir.join(name)).unwrap();
        assert_eq!((img.width() as usize, img.height() as usize), (sw, sh), "{name}");
    }
    // the first panel of the first row is image1 enlarged (nearest): its top-left pixel
    let img = image::open(pdir.join("preview-00000001.png")).unwrap().to_rgb8();
    let s = make_sample(1, true);
    assert_eq!(img.get_pixel(2, 2).0, [s.image1[0], s.image1[1], s.image1[2]]);
    // the validity panel: pixel (0, 0) is invalid (black), pixel (1, 1) valid (light grey)
    let x5 = 2 + 4 * 66;
    assert_eq!(img.get_pixel(x5 as u32, 2).0, [0, 0, 0]);
    let pil = run_python(
        "import sys, json\nfrom PIL import Image\nim = Image.open(sys.argv[1])\nprint(json.dumps([im.size[0], im.size[1], im.mode]))\n",
        &[pdir.join("preview-00000008.png").to_str().unwrap()],
    );
    assert_eq!(pil, serde_json::json!([sw, sh, "RGB"]), "sheet 8 holds samples 8 and 9");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn bad_samples_and_formats_are_refused_with_a_clear_message() {
    let dir = tmpdir("bad");
    let mut ex = Exporter::create(options(ExportFormat::Flo, &dir)).unwrap();
    let mut s = make_sample(3, false);
    s.flow.pop();
    let e = ex.write(3, &s).unwrap_err();
    assert!(matches!(e, ExportError::InvalidSample { index: 3, .. }), "{e}");
    assert!(e.to_string().contains("flow holds 2399 values"), "{e}");
    let mut s = make_sample(3, false);
    s.flow[10] = f32::NAN;
    assert!(ex.write(3, &s).unwrap_err().to_string().contains("not finite"));
    assert!(list_files(&dir).is_empty());
    assert_eq!("kitti".parse::<ExportFormat>().unwrap(), ExportFormat::Kitti);
    assert_eq!("webdataset".parse::<ExportFormat>().unwrap(), ExportFormat::WebDataset);
    assert!("tfrecord"
        .parse::<ExportFormat>()
        .unwrap_err()
        .contains("expected flo, kitti, webdataset, sintel or stereo"));
    assert_eq!("sintel".parse::<ExportFormat>().unwrap(), ExportFormat::Sintel);
    std::fs::remove_dir_all(&dir).unwrap();
}

// ---------------------------------------------------------------------------------------------
// `mpiflow generate`, end to end through the built binary

fn mpiflow(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_mpiflow")).args(args).output().expect("cannot run the mpiflow binary")
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

/// Reads `.flo` files with numpy (RAFT's readFlow) and returns their shapes.
const FLO_SHAPES: &str = r#"
import json, sys
import numpy as np
out = []
for p in sys.argv[1:]:
    with open(p, 'rb') as f:
        assert np.fromfile(f, np.float32, count=1)[0] == 202021.25
        w, h = [int(v) for v in np.fromfile(f, np.int32, count=2)]
        data = np.fromfile(f, np.float32, count=2 * w * h)
        assert data.size == 2 * w * h and f.read() == b''
        assert np.isfinite(data).all()
    out.append([h, w, 2])
print(json.dumps(out))
"#;

/// `--label-rule depth-only` is the earlier occlusion rule, which marks fewer pixels occluded
/// where objects moved (it does not occlude next to holes): another dataset (the fingerprint
/// names the rule, so its samples draw other motions), with fewer occluded pixels over the same
/// indices.
#[test]
fn generate_label_rule_selects_the_occlusion_rule() {
    let dir = tmpdir("gen-labels");
    let run = |rule: &str| {
        let out = dir.join(rule);
        let o = out.to_str().unwrap().to_string();
        let args = ["generate", "--count", "4", "--size", "96x64", "--quiet", "--label-rule", rule, "--out", &o];
        let r = mpiflow(&args);
        assert!(r.status.success(), "{rule}: {}", text(&r.stderr));
        out
    };
    let (honest, depth) = (run("honest"), run("depth-only"));
    let (mut occ_h, mut occ_d) = (0usize, 0usize);
    for i in 0..4u64 {
        let key = sample_key(i);
        let gray = |d: &Path| image::open(d.join(format!("{key}_occ.png"))).unwrap().to_luma8().into_raw();
        let count = |v: Vec<u8>| v.iter().filter(|&&p| p != 0).count();
        occ_h += count(gray(&honest));
        occ_d += count(gray(&depth));
        let fp = |d: &Path| -> Value {
            serde_json::from_slice(&std::fs::read(d.join(format!("{key}.json"))).unwrap()).unwrap()
        };
        assert_ne!(fp(&honest)["address"]["dataset"], fp(&depth)["address"]["dataset"]);
    }
    assert!(occ_h > occ_d, "honest occludes more: {occ_h} vs {occ_d}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn generate_makes_the_smallest_frames_of_the_bundled_scenes() {
    let dir = tmpdir("gen-small");
    let out = dir.join("out");
    let r = mpiflow(&["generate", "--count", "4", "--size", "16x16", "--out", out.to_str().unwrap()]);
    assert!(r.status.success(), "stdout: {}\nstderr: {}", text(&r.stdout), text(&r.stderr));
    assert!(text(&r.stdout).contains("wrote 4 samples (0 skipped)"), "{}", text(&r.stdout));
}

#[test]
fn generate_flo_on_the_bundled_scenes() {
    let dir = tmpdir("gen-flo");
    let out = dir.join("out");
    let o = out.to_str().unwrap();
    let common = [
        "generate",
        "--count",
        "3",
        "--format",
        "flo",
        "--size",
        "96x64",
        "--motions-per-image",
        "2",
        "--scene-window",
        "1",
    ];
    let r = mpiflow(&[&common[..], &["--out", o, "--preview-every", "2", "--threads", "2"]].concat());
    assert!(r.status.success(), "stdout: {}\nstderr: {}", text(&r.stdout), text(&r.stderr));
    let stdout = text(&r.stdout);
    assert!(stdout.contains("wrote 3 samples (0 skipped)"), "{stdout}");
    assert!(stdout.contains(" s ("), "{stdout}");

    let files = list_files(&out);
    let mut flos = Vec::new();
    for i in 0..3u64 {
        let key = sample_key(i);
        for f in ["img1.png", "img2.png", "flow.flo", "valid.png", "occ.png", "holes.png"] {
            assert!(files.contains(&format!("{key}_{f}")), "{key}_{f} missing in {files:?}");
        }
        let j: Value = serde_json::from_slice(&std::fs::read(out.join(format!("{key}.json"))).unwrap()).unwrap();
        assert_eq!(j["index"], i);
        assert_eq!(j["address"]["index"], i);
        assert_eq!((j["width"].as_u64(), j["height"].as_u64()), (Some(96), Some(64)));
        assert!(j["source_id"].as_str().is_some_and(|s| !s.is_empty()));
        let moved = !j["objects"].as_array().unwrap().is_empty();
        assert_eq!(files.contains(&format!("{key}_mask.png")), moved, "mask.png iff objects moved ({key})");
        let img = image::open(out.join(format!("{key}_img1.png"))).unwrap();
        assert_eq!((img.width(), img.height()), (96, 64));
        flos.push(out.join(format!("{key}_flow.flo")).to_string_lossy().into_owned());
    }
    // consecutive indices share a source with --motions-per-image 2 and --scene-window 1
    let id = |i: u64| -> Value {
        serde_json::from_slice::<Value>(&std::fs::read(out.join(format!("{}.json", sample_key(i)))).unwrap()).unwrap()
            ["source_id"]
            .clone()
    };
    assert_eq!(id(0), id(1));
    let args: Vec<&str> = flos.iter().map(String::as_str).collect();
    assert_eq!(run_python(FLO_SHAPES, &args), serde_json::json!([[64, 96, 2], [64, 96, 2], [64, 96, 2]]));
    // previews: the first sheet (samples 0 and 1, rows of 160 x 107) and one at index 2
    assert_eq!(list_files(&out.join("previews")), ["preview-00000000.png", "preview-00000002.png"]);
    let (sw, sh) = sheet_size(&[(96, 64), (96, 64)], 160);
    let p = image::open(out.join("previews/preview-00000000.png")).unwrap();
    assert_eq!((p.width() as usize, p.height() as usize), (sw, sh));

    // the same samples with one thread: identical bytes (the JSON differs only in timings)
    let out1 = dir.join("out1");
    let r =
        mpiflow(&[&common[..], &["--out", out1.to_str().unwrap(), "--threads", "1", "--preview-every", "0"]].concat());
    assert!(r.status.success(), "{}", text(&r.stderr));
    for f in files.iter().filter(|f| !f.ends_with(".json") && f.as_str() != "previews") {
        assert_eq!(std::fs::read(out.join(f)).unwrap(), std::fs::read(out1.join(f)).unwrap(), "{f}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn generate_webdataset_shards_on_the_bundled_scenes() {
    let dir = tmpdir("gen-wds");
    let o = dir.join("out");
    let r = mpiflow(&[
        "generate",
        "--count",
        "5",
        "--out",
        o.to_str().unwrap(),
        "--format",
        "webdataset",
        "--shard-size",
        "2",
        "--size",
        "64x48",
        "--seed",
        "3",
        "--objects",
        "2",
        "--preset",
        "paper-kitti",
        "--quiet",
    ]);
    assert!(r.status.success(), "{}", text(&r.stderr));
    assert!(text(&r.stdout).contains("wrote 5 samples (0 skipped)"), "{}", text(&r.stdout));
    assert!(text(&r.stdout).contains("3 shard(s)"), "{}", text(&r.stdout));
    assert_eq!(list_files(&o), ["previews", "shard-000000.tar", "shard-000001.tar", "shard-000002.tar"]);
    let res = run_python(WDS_READER, &[o.to_str().unwrap()]);
    let samples = res["samples"].as_array().unwrap();
    assert_eq!(samples.len(), 5);
    for (i, s) in samples.iter().enumerate() {
        assert_eq!(s["key"], sample_key(i as u64));
        assert_eq!(s["flow_shape"], serde_json::json!([48, 64, 2]));
        assert_eq!(s["img1_shape"], serde_json::json!([48, 64, 3]));
        assert_eq!(s["json"]["address"]["seed"], 3);
        assert_eq!(s["json"]["camera"]["law"], "paper-kitti");
        assert_eq!(s["mask"].is_null(), s["json"]["objects"].as_array().unwrap().is_empty());
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

fn write_png_rgb(path: &Path, w: u32, h: u32, seed: u32) {
    let img = image::RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 7 + seed) as u8, (y * 5) as u8, (x ^ y) as u8]));
    img.save(path).unwrap();
}

#[test]
fn generate_passes_over_a_failing_source_with_a_warning_and_counts_it() {
    let dir = tmpdir("gen-skip");
    let src = dir.join("src");
    std::fs::create_dir_all(src.join("images")).unwrap();
    std::fs::create_dir_all(src.join("depths")).unwrap();
    write_png_rgb(&src.join("images/good.png"), 48, 32, 0);
    write_png_rgb(&src.join("images/nodepth.png"), 48, 32, 9);
    let depth: Vec<f32> = (0..48 * 32).map(|i| 2.0 + (i % 48) as f32 * 0.01).collect();
    mpiflow::io::npy::write_f32(&src.join("depths/good.npy"), &[32, 48], &depth).unwrap();
    let out = dir.join("out");
    let r = mpiflow(&[
        "generate",
        "--source",
        src.to_str().unwrap(),
        "--count",
        "4",
        "--out",
        out.to_str().unwrap(),
        "--format",
        "kitti",
        "--intrinsics",
        "30,30,24,16",
    ]);
    let (stdout, stderr) = (text(&r.stdout), text(&r.stderr));
    assert!(r.status.success(), "{stdout}\n{stderr}");
    // the bad source is passed over: its indices are served by the next good source
    assert!(
        stdout.contains("wrote 4 samples (0 skipped)") && stdout.contains("1 bad source(s) passed over"),
        "{stdout}"
    );
    let warnings: Vec<&str> = stderr.lines().filter(|l| l.starts_with("warning:")).collect();
    assert_eq!(warnings.len(), 1, "{stderr}");
    assert!(warnings[0].contains("source item 1 (nodepth) skipped") && warnings[0].contains("no depth"), "{stderr}");
    let files = list_files(&out);
    for key in ["00000000", "00000001", "00000002", "00000003"] {
        assert!(files.contains(&format!("{key}_flow.png")), "{files:?}");
        let j: Value = serde_json::from_slice(&std::fs::read(out.join(format!("{key}.json"))).unwrap()).unwrap();
        assert_eq!(j["source_id"], "good");
    }

    // the one depth file corrupt: its photo is left out when the folder is opened (named), and
    // the photos left carry no depth: refused before anything is made, exit code 2
    std::fs::write(src.join("depths/good.npy"), b"not an array").unwrap();
    let r = mpiflow(&["generate", "--source", src.to_str().unwrap(), "--count", "2", "--out", out.to_str().unwrap()]);
    assert_eq!(r.status.code(), Some(2));
    let stderr = text(&r.stderr);
    assert!(stderr.contains("depths/good.npy") && stderr.contains("not a valid .npy depth"), "{stderr}");
    let last = stderr.lines().last().unwrap();
    assert!(last.starts_with("error: ") && last.contains("pass --depth-model NAME|FILE"), "{stderr}");

    // with no photo carrying depth: refused before anything is made, naming the fix
    std::fs::remove_file(src.join("depths/good.npy")).unwrap();
    let r = mpiflow(&["generate", "--source", src.to_str().unwrap(), "--count", "2", "--out", out.to_str().unwrap()]);
    assert_eq!(r.status.code(), Some(2));
    let stderr = text(&r.stderr);
    let last = stderr.lines().last().unwrap();
    assert!(last.starts_with("error: ") && last.contains("pass --depth-model NAME|FILE"), "{stderr}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn generate_refuses_bad_arguments_naming_them_with_exit_code_2() {
    let dir = tmpdir("gen-bad");
    let o = dir.join("out");
    let o = o.to_str().unwrap();
    for (args, needle) in [
        (vec!["--count", "1", "--out", o, "--format", "tfrecord"], "expected flo, kitti, webdataset, sintel or stereo"),
        (vec!["--count", "1", "--out", o, "--frames", "9"], "--frames"),
        (vec!["--count", "0", "--out", o], "--count"),
        (vec!["--count", "1", "--out", o, "--intrinsics", "1,2,3"], "expected 4"),
        (vec!["--count", "1", "--out", o, "--intrinsics", "30,30,24,16"], "--intrinsics needs --source"),
        (vec!["--count", "1", "--out", o, "--source", "/nonexistent/mpiflow-photos"], "--source"),
        (vec!["--count", "1", "--out", o, "--preset", "fast"], "unknown motion preset"),
        (vec!["--count", "1", "--out", o, "--merge", "painter"], "unknown merge rule"),
        (vec!["--count", "1", "--out", o, "--label-rule", "lenient"], "unknown label rule"),
        (vec!["--count", "1", "--out", o, "--planes", "0"], "--planes"),
        (vec!["--count", "1", "--out", o, "--shard-size", "0"], "--shard-size"),
        (vec!["--count", "1", "--out", o, "--size", "8x8"], "--size"),
    ] {
        let r = mpiflow(&[&["generate"], &args[..]].concat());
        let stderr = text(&r.stderr);
        assert_eq!(r.status.code(), Some(2), "{args:?}: {stderr}");
        // the problem on the first line; a command-line error goes on with clap's pointer to
        // --help, a check of the command's own with nothing more
        let first = stderr.lines().next().unwrap_or_default();
        assert!(first.starts_with("error: ") && first.contains(needle), "{args:?}: {stderr}");
        let lines = stderr.lines().count();
        assert!(lines == 1 || stderr.ends_with("For more information, try '--help'.\n"), "{args:?}: {stderr}");
    }
    assert!(!Path::new(o).exists(), "nothing is written for bad arguments");
    std::fs::remove_dir_all(&dir).unwrap();
}
