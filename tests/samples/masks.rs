//! Instance masks: COCO RLE and polygons against pycocotools' vectors, instance-index PNGs,
//! COCO annotation JSON, object selection, resizing, and malformed input.

use mpiflow::raster::{
    mask_bbox, polygon_to_mask, polygon_to_rle, resize_bilinear, resize_nearest, rle_area, rle_bbox, rle_decode,
    rle_decode_counts, rle_encode, rle_from_string, rle_to_string, Instance, InstanceMasks, MaskError, RleCounts,
};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};

fn data(name: &str) -> Value {
    let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/masks").join(name);
    let text = std::fs::read_to_string(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
    serde_json::from_str(&text).unwrap()
}

fn rows_to_mask(rows: &Value) -> (usize, usize, Vec<u8>) {
    let rows = rows.as_array().unwrap();
    let h = rows.len();
    let w = rows[0].as_array().unwrap().len();
    let mask = rows.iter().flat_map(|r| r.as_array().unwrap().iter().map(|v| v.as_u64().unwrap() as u8)).collect();
    (h, w, mask)
}

fn u32s(v: &Value) -> Vec<u32> {
    v.as_array().unwrap().iter().map(|x| x.as_u64().unwrap() as u32).collect()
}

fn f64s(v: &Value) -> Vec<f64> {
    v.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect()
}

/// Every vector of `tests/data/masks/coco_rle_vectors.json` (pycocotools 2.0.11).
#[test]
fn coco_rle_vectors() {
    let v = data("coco_rle_vectors.json");
    let mut checked = 0;
    for case in v["vectors"].as_array().unwrap() {
        let name = case["name"].as_str().unwrap();
        let compressed = case["compressed_counts"].as_str().unwrap();
        if name == "uncompressed_to_compressed" {
            let counts = u32s(&case["input"]["counts"]);
            let size = u32s(&case["input"]["size"]);
            assert_eq!(rle_to_string(&counts), compressed);
            let m = rle_decode(&RleCounts::Uncompressed(counts.clone()), size[0] as usize, size[1] as usize).unwrap();
            assert_eq!(rle_encode(&m, size[0] as usize, size[1] as usize), counts);
            checked += 1;
            continue;
        }
        let (h, w) = (case["h"].as_u64().unwrap() as usize, case["w"].as_u64().unwrap() as usize);
        let expected: Vec<u8> = if let Some(rows) = case.get("mask_rows") {
            rows_to_mask(rows).2
        } else if let Some(rows) = case.get("decoded_rows") {
            rows_to_mask(rows).2
        } else {
            // rects [y0, y1, x0, x1), half open
            let mut m = vec![0u8; h * w];
            for r in case["rects_yx_half_open"].as_array().unwrap() {
                let r = u32s(r);
                for y in r[0]..r[1] {
                    for x in r[2]..r[3] {
                        m[y as usize * w + x as usize] = 1;
                    }
                }
            }
            m
        };
        // decode the compressed string
        let counts = rle_from_string(compressed).unwrap();
        assert_eq!(rle_decode(&RleCounts::Compressed(compressed.into()), h, w).unwrap(), expected, "{name}");
        // encode back to the same counts and string
        assert_eq!(rle_encode(&expected, h, w), counts, "{name}");
        assert_eq!(rle_to_string(&counts), compressed, "{name}");
        // uncompressed form, where given
        if let Some(u) = case.get("uncompressed_counts").filter(|u| !u.is_null()) {
            let u = u32s(u);
            assert_eq!(u, counts, "{name}");
            assert_eq!(rle_decode(&RleCounts::Uncompressed(u), h, w).unwrap(), expected, "{name}");
        }
        assert_eq!(rle_area(&counts), case["area"].as_u64().unwrap(), "{name}");
        if let Some(b) = case.get("bbox_xywh") {
            assert_eq!(rle_bbox(&counts, h, w).to_vec(), f64s(b), "{name}");
            assert_eq!(mask_bbox(&expected, h, w).to_vec(), f64s(b), "{name}");
        }
        // polygons rasterise to the same RLE as pycocotools' frPyObjects
        if let Some(polys) = case.get("polygon") {
            let polys: Vec<Vec<f64>> = polys.as_array().unwrap().iter().map(f64s).collect();
            assert_eq!(rle_to_string(&polygon_to_rle(&polys[0], h, w).unwrap()), compressed, "{name}");
            assert_eq!(polygon_to_mask(&polys, h, w).unwrap(), expected, "{name}");
        }
        checked += 1;
    }
    assert_eq!(checked, 6);
}

/// Random masks and polygons with pycocotools' results (`make_pycocotools_random.py`).
#[test]
fn pycocotools_random_cases() {
    let v = data("pycocotools_random.json");
    let masks = v["masks"].as_array().unwrap();
    for (i, c) in masks.iter().enumerate() {
        let (h, w) = (c["h"].as_u64().unwrap() as usize, c["w"].as_u64().unwrap() as usize);
        let mask: Vec<u8> = c["mask"].as_str().unwrap().bytes().map(|b| b - b'0').collect();
        let counts = rle_encode(&mask, h, w);
        assert_eq!(rle_to_string(&counts), c["counts"].as_str().unwrap(), "mask {i}");
        assert_eq!(rle_area(&counts), c["area"].as_u64().unwrap(), "mask {i}");
        assert_eq!(rle_bbox(&counts, h, w).to_vec(), f64s(&c["bbox"]), "mask {i}");
        assert_eq!(rle_decode_counts(&rle_from_string(c["counts"].as_str().unwrap()).unwrap(), h, w).unwrap(), mask);
    }
    let polys = v["polygons"].as_array().unwrap();
    for (i, c) in polys.iter().enumerate() {
        let (h, w) = (c["h"].as_u64().unwrap() as usize, c["w"].as_u64().unwrap() as usize);
        let ps: Vec<Vec<f64>> = c["polygons"].as_array().unwrap().iter().map(f64s).collect();
        for (j, (p, e)) in ps.iter().zip(c["each"].as_array().unwrap()).enumerate() {
            assert_eq!(rle_to_string(&polygon_to_rle(p, h, w).unwrap()), e.as_str().unwrap(), "case {i} polygon {j}");
        }
        let m = polygon_to_mask(&ps, h, w).unwrap();
        assert_eq!(rle_to_string(&rle_encode(&m, h, w)), c["merged"].as_str().unwrap(), "case {i} merged");
    }
    println!("{} masks and {} polygon cases agree with pycocotools", masks.len(), polys.len());
    assert!(masks.len() >= 50 && polys.len() >= 100);
}

struct TempDir(PathBuf);

impl TempDir {
    fn new(name: &str) -> Self {
        let d = std::env::temp_dir().join(format!("mpiflow-masks-{}-{name}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        TempDir(d)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn check_instances(m: &InstanceMasks, ids: &[u32], w: usize, h: usize) {
    assert_eq!((m.width, m.height), (w, h));
    let mut distinct: Vec<u32> = ids.iter().copied().filter(|&v| v != 0).collect();
    distinct.sort_unstable();
    distinct.dedup();
    assert_eq!(m.masks.iter().map(|i| i.id).collect::<Vec<_>>(), distinct);
    for inst in &m.masks {
        assert_eq!(inst.score, 1.0);
        let expected: Vec<f32> = ids.iter().map(|&v| f32::from(u8::from(v == inst.id))).collect();
        assert_eq!(inst.mask, expected, "instance {}", inst.id);
        assert_eq!(inst.area, ids.iter().filter(|&&v| v == inst.id).count() as f64);
    }
}

#[test]
fn index_png_round_trip_8_and_16_bit() {
    let dir = TempDir::new("index");
    let (w, h) = (7, 5);
    // 8 bit
    let ids8: Vec<u8> = (0..w * h).map(|i| [0u8, 1, 2, 7, 255, 0, 2][i % 7]).collect();
    let p8 = dir.0.join("ids8.png");
    image::GrayImage::from_raw(w as u32, h as u32, ids8.clone()).unwrap().save(&p8).unwrap();
    let m8 = InstanceMasks::from_index_png(&p8).unwrap();
    let ids8: Vec<u32> = ids8.into_iter().map(u32::from).collect();
    check_instances(&m8, &ids8, w, h);
    assert_eq!(m8.to_index_map(0.5), ids8);
    // 16 bit
    let ids16: Vec<u16> = (0..w * h).map(|i| [0u16, 300, 1000, 65535, 1][i % 5]).collect();
    let p16 = dir.0.join("ids16.png");
    image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_raw(w as u32, h as u32, ids16.clone())
        .unwrap()
        .save(&p16)
        .unwrap();
    let m16 = InstanceMasks::from_index_png(&p16).unwrap();
    let ids16: Vec<u32> = ids16.into_iter().map(u32::from).collect();
    check_instances(&m16, &ids16, w, h);
    // writing: 8-bit when the ids fit, else 16-bit, and back
    for (m, ids, depth) in [(&m8, &ids8, image::ColorType::L8), (&m16, &ids16, image::ColorType::L16)] {
        let p = dir.0.join("written.png");
        m.save_index_png(&p).unwrap();
        assert_eq!(image::open(&p).unwrap().color(), depth);
        check_instances(&InstanceMasks::from_index_png(&p).unwrap(), ids, w, h);
    }
    // empty map: no instances
    let p0 = dir.0.join("empty.png");
    image::GrayImage::new(3, 2).save(&p0).unwrap();
    assert!(InstanceMasks::from_index_png(&p0).unwrap().masks.is_empty());
}

#[test]
fn index_png_colour_and_refusals() {
    let dir = TempDir::new("colour");
    let (w, h) = (4, 3);
    // grey saved as RGB: the grey level is the id
    let grey: Vec<u8> = (0..w * h).flat_map(|i| [[0u8; 3], [5; 3], [9; 3]][i % 3]).collect();
    let p = dir.0.join("grey_rgb.png");
    image::RgbImage::from_raw(w as u32, h as u32, grey).unwrap().save(&p).unwrap();
    let m = InstanceMasks::from_index_png(&p).unwrap();
    assert_eq!(m.masks.iter().map(|i| i.id).collect::<Vec<_>>(), vec![5, 9]);
    // colours: one instance per colour, id = R << 16 | G << 8 | B; black is background
    let colours = [[0u8, 0, 0], [255, 0, 0], [0, 128, 1], [255, 0, 0]];
    let rgb: Vec<u8> = (0..w * h).flat_map(|i| colours[i % 4]).collect();
    let p = dir.0.join("colour.png");
    image::RgbImage::from_raw(w as u32, h as u32, rgb).unwrap().save(&p).unwrap();
    let m = InstanceMasks::from_index_png(&p).unwrap();
    assert_eq!(m.masks.iter().map(|i| i.id).collect::<Vec<_>>(), vec![0x00_80_01, 0xff_00_00]);
    assert_eq!(m.masks[1].area, 6.0);
    // RGBA: transparent pixels are background
    let rgba: Vec<u8> = (0..w * h).flat_map(|i| if i < 6 { [10, 20, 30, 255] } else { [10, 20, 30, 0] }).collect();
    let p = dir.0.join("rgba.png");
    image::RgbaImage::from_raw(w as u32, h as u32, rgba).unwrap().save(&p).unwrap();
    let m = InstanceMasks::from_index_png(&p).unwrap();
    assert_eq!((m.masks.len(), m.masks[0].area), (1, 6.0));
    // 16-bit colour: refused, naming the file
    let rgb16: Vec<u16> = (0..w * h * 3).map(|i| (i * 1000) as u16).collect();
    let p = dir.0.join("rgb16.png");
    image::ImageBuffer::<image::Rgb<u16>, Vec<u16>>::from_raw(w as u32, h as u32, rgb16).unwrap().save(&p).unwrap();
    let e = InstanceMasks::from_index_png(&p).unwrap_err();
    assert!(matches!(e, MaskError::IndexPng { .. }) && e.to_string().contains("rgb16.png"), "{e}");
    // not a PNG
    let p = dir.0.join("mask.jpg");
    image::GrayImage::new(8, 8).save(&p).unwrap();
    let e = InstanceMasks::from_index_png(&p).unwrap_err();
    assert!(e.to_string().contains("not a PNG"), "{e}");
    // missing and truncated files
    let e = InstanceMasks::from_index_png(&dir.0.join("missing.png")).unwrap_err();
    assert!(e.to_string().contains("missing.png"), "{e}");
    let p = dir.0.join("short.png");
    std::fs::write(&p, [0x89, b'P', b'N', b'G', 0x0d, 0x0a, 0x1a, 0x0a, 0, 0]).unwrap();
    assert!(InstanceMasks::from_index_png(&p).is_err());
    // id 0 cannot be written
    let m = InstanceMasks { width: 1, height: 1, masks: vec![Instance::new(0, 1.0, vec![1.0])] };
    assert!(m.save_index_png(&dir.0.join("zero.png")).is_err());
}

#[test]
fn coco_json_annotations() {
    let (h, w) = (6, 5);
    let anns = json!([
        {"id": 11, "category_id": 3, "score": 0.9, "segmentation": {"counts": "7330:N", "size": [6, 5]}},
        {"segmentation": {"counts": [7, 3, 3, 3, 13, 1], "size": [6, 5]}},
        {"id": 4, "score": 0.5, "segmentation": [[1.0, 1.0, 3.0, 1.0, 3.0, 4.0, 1.0, 4.0]]},
        {"id": 5, "segmentation": [0.0, 0.0, 2.0, 0.0, 0.0, 2.0]},
        {"id": 6, "segmentation": [[1.0, 1.0, 2.0, 2.0], [0.0, 0.0, 4.0, 0.0, 4.0, 5.0]]}
    ]);
    let m = InstanceMasks::from_coco_json(&anns, h, w).unwrap();
    assert_eq!(m.masks.len(), 5);
    let (_, _, small) = rows_to_mask(&data("coco_rle_vectors.json")["vectors"][0]["mask_rows"]);
    let small: Vec<f32> = small.iter().map(|&v| f32::from(v)).collect();
    assert_eq!((m.masks[0].id, m.masks[0].category, m.masks[0].score), (11, Some(3), 0.9));
    assert_eq!(m.masks[0].mask, small);
    assert_eq!(m.masks[0].area, 7.0);
    assert_eq!((m.masks[1].id, m.masks[1].score, m.masks[1].category), (2, 1.0, None));
    assert_eq!(m.masks[1].mask, small);
    let poly = polygon_to_mask(&[vec![1.0, 1.0, 3.0, 1.0, 3.0, 4.0, 1.0, 4.0]], h, w).unwrap();
    assert_eq!(m.masks[2].mask, poly.iter().map(|&v| f32::from(v)).collect::<Vec<_>>());
    assert!(m.masks[3].area > 0.0);
    // the 2-point polygon is skipped; the other one counts
    let big = polygon_to_mask(&[vec![0.0, 0.0, 4.0, 0.0, 4.0, 5.0]], h, w).unwrap();
    assert_eq!(m.masks[4].area, big.iter().filter(|&&v| v != 0).count() as f64);
    // the COCO file layout
    let file = json!({"images": [], "annotations": anns});
    assert_eq!(InstanceMasks::from_coco_json(&file, h, w).unwrap(), m);
}

#[test]
fn coco_json_errors_name_the_field() {
    let (h, w) = (6, 5);
    let cases = [
        (
            json!([{"segmentation": {"counts": "7330:N", "size": [6, 5]}}, {"segmentation": {"counts": "7 3", "size": [6, 5]}}]),
            "annotations[1].segmentation.counts",
        ),
        (json!([{"segmentation": {"counts": "7330:", "size": [6, 5]}}]), "annotations[0].segmentation.counts"),
        (json!([{"segmentation": {"counts": "7330:N", "size": [5, 6]}}]), "annotations[0].segmentation.size"),
        (json!([{"segmentation": {"counts": [1, -2], "size": [6, 5]}}]), "annotations[0].segmentation.counts[1]"),
        (json!([{"segmentation": [[1.0, 2.0, "x", 3.0, 4.0, 5.0]]}]), "annotations[0].segmentation[0][2]"),
        (json!([{"segmentation": [[1.0, 2.0, 3.0, 3.0, 4.0, 5.0, 6.0]]}]), "annotations[0].segmentation[0]"),
        (json!([{"segmentation": [[1.0, 2.0, 3.0, 3.0, 4.0, 5.0e12]]}]), "annotations[0].segmentation[0]"),
        (json!([{"score": "high", "segmentation": []}]), "annotations[0].score"),
        (json!([{"id": -1, "segmentation": []}]), "annotations[0].id"),
        (json!([{"bbox": [1, 2, 3, 4]}]), "annotations[0]"),
        (json!([{"segmentation": 3}]), "annotations[0].segmentation"),
        (json!({"images": []}), "annotations"),
        (json!("annotations"), "annotations"),
    ];
    for (value, field) in cases {
        let e = InstanceMasks::from_coco_json(&value, h, w).unwrap_err();
        let msg = e.to_string();
        assert!(msg.starts_with(&format!("{field}:")), "expected the field {field}: {msg}");
    }
    // a file: errors name it
    let dir = TempDir::new("json");
    let p = dir.0.join("anns.json");
    std::fs::write(&p, r#"[{"segmentation": {"counts": "!", "size": [6, 5]}}]"#).unwrap();
    let e = InstanceMasks::from_coco_json_file(&p, h, w).unwrap_err();
    assert!(e.to_string().contains("anns.json: annotations[0].segmentation.counts"), "{e}");
    std::fs::write(&p, "[{").unwrap();
    assert!(InstanceMasks::from_coco_json_file(&p, h, w).unwrap_err().to_string().contains("invalid JSON"));
}

fn inst(id: u32, score: f32, area: usize, n: usize) -> Instance {
    let mask: Vec<f32> = (0..n).map(|i| f32::from(u8::from(i < area))).collect();
    Instance::new(id, score, mask)
}

#[test]
fn selection_order() {
    let n = 100; // a 10 x 10 image
    let m = InstanceMasks {
        width: 10,
        height: 10,
        masks: vec![
            inst(1, 0.5, 30, n),      // 0
            inst(2, 0.9, 5, n),       // 1
            inst(3, 0.9, 20, n),      // 2
            inst(4, 0.5, 30, n),      // 3: ties with 0 on score and area: id decides
            inst(5, f32::NAN, 50, n), // 4: NaN score sorts last
            inst(6, 0.99, 0, n),      // 5: empty, never chosen
            inst(7, 0.7, 1, n),       // 6: small
        ],
    };
    assert_eq!(m.select_objects(10, 0.0), vec![2, 1, 6, 0, 3, 4]);
    assert_eq!(m.select_objects(3, 0.0), vec![2, 1, 6]);
    assert_eq!(m.select_objects(10, 0.05), vec![2, 1, 0, 3, 4]);
    assert_eq!(m.select_objects(10, 0.25), vec![0, 3, 4]);
    assert_eq!(m.select_objects(0, 0.0), Vec::<usize>::new());
    assert_eq!(m.select_objects(10, 0.9), Vec::<usize>::new());
    // the same instances in another order give the same choice of ids
    let mut rev = m.clone();
    rev.masks.reverse();
    let ids = |mm: &InstanceMasks, sel: Vec<usize>| sel.into_iter().map(|i| mm.masks[i].id).collect::<Vec<_>>();
    assert_eq!(ids(&rev, rev.select_objects(10, 0.0)), ids(&m, m.select_objects(10, 0.0)));
}

#[test]
fn resizing() {
    // nearest: integer upsampling then downsampling gives the mask back
    let (w, h) = (5, 4);
    let mask: Vec<f32> = (0..w * h).map(|i| ((i * 7) % 3) as f32 / 2.0).collect();
    let up = resize_nearest(&mask, w, h, w * 3, h * 2);
    assert_eq!(resize_nearest(&up, w * 3, h * 2, w, h), mask);
    // bilinear keeps constants and stays within the input range
    let c = resize_bilinear(&[0.25; 12], 4, 3, 9, 7);
    assert!(c.iter().all(|&v| (v - 0.25).abs() < 1e-7));
    let b = resize_bilinear(&mask, w, h, 13, 3);
    assert_eq!(b.len(), 39);
    assert!(b.iter().all(|&v| (0.0..=1.0).contains(&v)));
    // instance masks: areas follow
    let m = InstanceMasks { width: w, height: h, masks: vec![inst(1, 1.0, 6, w * h)] };
    let r = m.resize_nearest(w * 2, h * 2);
    assert_eq!((r.width, r.height, r.masks[0].area), (10, 8, 24.0));
    let r = m.resize_bilinear(w * 2, h * 2);
    assert_eq!(r.masks[0].mask.len(), 80);
    assert!(r.masks[0].area > 0.0);
}

/// A 64-bit LCG.
struct Lcg(u64);

impl Lcg {
    fn next(&mut self) -> u32 {
        self.0 = self.0.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (self.0 >> 33) as u32
    }
}

#[test]
fn malformed_input_gives_errors_not_panics() {
    let mut rng = Lcg(2024);
    let (mut ok, mut err) = (0, 0);
    for i in 0..600 {
        let s: String = if i % 2 == 0 {
            // a valid encoding, then maybe one character replaced or the end cut off
            let counts: Vec<u32> = (0..rng.next() % 12).map(|_| rng.next() % [5, 300, 1 << 31][i % 3]).collect();
            let mut chars: Vec<char> = rle_to_string(&counts).chars().collect();
            if !chars.is_empty() {
                let at = rng.next() as usize % chars.len();
                match rng.next() % 4 {
                    0 => chars[at] = char::from(32 + (rng.next() % 96) as u8),
                    1 => chars.truncate(at),
                    _ => {}
                }
            }
            chars.into_iter().collect()
        } else {
            let len = (rng.next() % 24) as usize;
            (0..len)
                .map(|_| {
                    let r = rng.next();
                    // mostly valid characters, some printable ASCII, some other Unicode
                    match r % 10 {
                        0 => char::from_u32(0x20 + (r >> 8) % 0x5f).unwrap(),
                        1 => ['\u{e9}', '\u{3b1}', '\u{1f600}', '\0'][(r >> 8) as usize % 4],
                        _ => char::from(48 + ((r >> 8) % 64) as u8),
                    }
                })
                .collect()
        };
        match rle_from_string(&s) {
            Ok(counts) => {
                ok += 1;
                assert_eq!(rle_from_string(&rle_to_string(&counts)).unwrap(), counts, "{s:?}");
                let (h, w) = (1 + (rng.next() % 9) as usize, 1 + (rng.next() % 9) as usize);
                let _ = rle_decode_counts(&counts, h, w);
                let _ = rle_bbox(&counts, h, w);
                let _ = rle_area(&counts);
                // a count vector that does sum to the size decodes
                if i % 3 == 0 {
                    let total: u64 = counts.iter().map(|&c| u64::from(c)).sum();
                    if total > 0 && total < 10_000 {
                        assert!(rle_decode_counts(&counts, total as usize, 1).is_ok());
                    }
                }
            }
            Err(e) => {
                err += 1;
                assert!(matches!(e, MaskError::Rle { .. }), "{s:?}: {e}");
            }
        }
    }
    println!("random RLE strings: {ok} decoded, {err} refused");
    assert!(ok > 150 && err > 150);
    // polygons with odd, huge or non-finite coordinates
    for _ in 0..300 {
        let n = (rng.next() % 12) as usize;
        let p: Vec<f64> = (0..n)
            .map(|_| match rng.next() % 12 {
                0 => f64::NAN,
                1 => f64::INFINITY,
                2 => -1.0e12,
                3 => 3.0e8,
                _ => (rng.next() % 400) as f64 / 10.0 - 5.0,
            })
            .collect();
        let (h, w) = ((rng.next() % 20) as usize, (rng.next() % 20) as usize);
        if let Ok(rle) = polygon_to_rle(&p, h, w) {
            assert_eq!(rle.iter().map(|&c| u64::from(c)).sum::<u64>(), (h * w) as u64, "{p:?}");
            assert!(rle_decode_counts(&rle, h, w).is_ok());
        }
    }
    // sizes beyond 32-bit counts
    assert!(rle_decode_counts(&[0], 1 << 20, 1 << 20).is_err());
    assert!(polygon_to_rle(&[0.0, 0.0, 1.0, 1.0, 0.0, 1.0], 1 << 20, 1 << 20).is_err());
}
