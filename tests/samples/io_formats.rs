//! File formats through the public API: the flow colour wheel against pictures drawn by PyPI
//! `flow-vis`, and `.flo` / KITTI / PNG round trips through files.

use mpiflow::io::colorwheel::{flow_to_color, flow_uv_to_colors, make_colorwheel};
use mpiflow::io::flo::{read_flo, read_kitti_flow_png, write_flo, write_kitti_flow_png};
use mpiflow::io::image::{load_rgb, rgb_to_u8, save_rgb_png, ImageLimits, RgbImage};
use mpiflow::io::npy::read_npy_file;
use std::path::{Path, PathBuf};

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/colorwheel").join(name)
}

/// The input of the shared vectors (`wheel_input_uv.npy`): a 257 x 257 grid with
/// u = linspace(-1, 1, 257) along x and v = linspace(-1, 1, 257) along y, float32
/// (`np.meshgrid`); every value is a multiple of 1/128 and exact in f32.
const N: usize = 257;

fn wheel_input() -> Vec<f32> {
    let mut flow = Vec::with_capacity(N * N * 2);
    for y in 0..N {
        for x in 0..N {
            flow.push(-1.0 + x as f32 / 128.0);
            flow.push(-1.0 + y as f32 / 128.0);
        }
    }
    flow
}

fn load_expected(name: &str) -> Vec<u8> {
    let img = image::open(data(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
    assert_eq!((img.width() as usize, img.height() as usize), (N, N));
    img.to_rgb8().into_raw()
}

/// How two u8 pictures differ.
#[derive(Debug)]
struct Diff {
    /// Largest difference in u8 levels.
    max: u8,
    /// Number of differing channel values.
    count: usize,
    /// The first difference: (row, column, ours, expected).
    first: Option<(usize, usize, u8, u8)>,
}

fn compare(got: &[u8], want: &[u8]) -> Diff {
    assert_eq!(got.len(), want.len());
    let mut d = Diff { max: 0, count: 0, first: None };
    for (i, (&g, &w)) in got.iter().zip(want).enumerate() {
        let diff = g.abs_diff(w);
        if diff > 0 {
            d.count += 1;
            d.first.get_or_insert((i / 3 / N, i / 3 % N, g, w));
        }
        d.max = d.max.max(diff);
    }
    d
}

#[test]
fn palette_matches_flow_vis() {
    let a = read_npy_file(&data("colorwheel_55x3.npy")).unwrap();
    assert_eq!(a.shape, vec![55, 3]);
    let ours: Vec<f64> = make_colorwheel().iter().flatten().map(|&v| f64::from(v)).collect();
    assert_eq!(ours, a.data);
}

#[test]
fn grid_matches_the_vectors_input() {
    let a = read_npy_file(&data("wheel_input_uv.npy")).unwrap();
    assert_eq!(a.shape, vec![N as u64, N as u64, 2]);
    let ours: Vec<f64> = wheel_input().iter().map(|&v| f64::from(v)).collect();
    assert_eq!(ours, a.data);
}

#[test]
fn flow_to_color_normalized_matches_flow_vis() {
    let got = flow_to_color(&wheel_input(), N, N, None);
    let want = load_expected("wheel_flow_to_color_normalized.png");
    let Diff { max, count, first } = compare(&got, &want);
    eprintln!(
        "flow_to_color (normalised): max difference {max} level(s), {count} of {} values differ, first {first:?}",
        want.len()
    );
    // measured: identical (max difference 0)
    assert!(max <= 1, "max difference {max}, first (row, col, ours, flow-vis) {first:?}");
    assert!(count <= 4, "{count} values differ");
}

#[test]
fn flow_uv_to_colors_unnormalized_matches_flow_vis() {
    let flow = wheel_input();
    let u: Vec<f32> = flow.iter().step_by(2).copied().collect();
    let v: Vec<f32> = flow.iter().skip(1).step_by(2).copied().collect();
    let got = flow_uv_to_colors(&u, &v);
    let want = load_expected("wheel_flow_uv_to_colors_unnormalized.png");
    let Diff { max, count, first } = compare(&got, &want);
    eprintln!(
        "flow_uv_to_colors (raw uv): max difference {max} level(s), {count} of {} values differ, first {first:?}",
        want.len()
    );
    assert!(max <= 1, "max difference {max}, first (row, col, ours, flow-vis) {first:?}");
    assert!(count <= 4, "{count} values differ");
}

#[test]
fn flo_kitti_and_png_files_round_trip() {
    let dir = std::env::temp_dir().join(format!("mpiflow-io-formats-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (w, h) = (7, 5);
    let flow: Vec<f32> = (0..w * h * 2).map(|i| (i as f32 - 30.0) * 0.75).collect();

    write_flo(&dir.join("f.flo"), w, h, &flow).unwrap();
    assert_eq!(read_flo(&dir.join("f.flo")).unwrap(), (w, h, flow.clone()));

    // multiples of 1/64 survive the KITTI encoding exactly
    write_kitti_flow_png(&dir.join("k.png"), w, h, &flow, None).unwrap();
    let k = read_kitti_flow_png(&dir.join("k.png")).unwrap();
    assert_eq!((k.width, k.height, &k.flow), (w, h, &flow));
    assert!(k.valid.iter().all(|&v| v == 1));

    let colours = flow_to_color(&flow, w, h, None);
    let img = RgbImage { width: w, height: h, data: colours.iter().map(|&c| f32::from(c) / 255.0).collect() };
    save_rgb_png(&dir.join("c.png"), &img).unwrap();
    let back = load_rgb(&dir.join("c.png"), &ImageLimits::default()).unwrap();
    assert_eq!(rgb_to_u8(&back), colours);
    std::fs::remove_dir_all(&dir).unwrap();
}

proptest::proptest! {
    /// An MPI written as `.npz` reads back bit for bit in f32 and as the f16 rounding of every
    /// colour and density in f16 (densities above the largest f16 capped at it); either way the
    /// zip members are dated 1980-01-01, so the bytes do not depend on when they were written.
    #[test]
    fn mpi_npz_round_trips_exactly_in_f32_and_as_the_f16_rounding(
        values in proptest::collection::vec(
            proptest::prop_oneof![0.0f32..1.0, 0.0f32..1e3, 6.0e4f32..1e9, proptest::num::f32::POSITIVE | proptest::num::f32::ZERO],
            2 * 3 * 2 * 4,
        ),
        extra in proptest::bool::ANY,
    ) {
        use mpiflow::mpi::npz::{load_npz_bytes_limited, save_npz_as, MpiDtype};
        let mut mpi = mpiflow::mpi::Mpi::new(3, 2, vec![0.9, 0.1], usize::from(extra));
        mpi.rgba.copy_from_slice(&values);
        for (i, e) in mpi.extras.iter_mut().enumerate() {
            *e = i as f32 / 7.0;
        }
        for dtype in [MpiDtype::F32, MpiDtype::F16] {
            let bytes = save_npz_as(&mpi, std::io::Cursor::new(Vec::new()), dtype).unwrap().into_inner();
            // the first local file header: its DOS time and date (1980-01-01 00:00:00)
            proptest::prop_assert_eq!(&bytes[..4], b"PK\x03\x04");
            proptest::prop_assert_eq!(&bytes[10..14], &[0u8, 0, 0x21, 0]);
            let back = load_npz_bytes_limited(&bytes, "test", u64::MAX).unwrap();
            proptest::prop_assert_eq!(&back.disparity, &mpi.disparity);
            proptest::prop_assert!(back.extras == mpi.extras);
            let want: Vec<f32> = match dtype {
                MpiDtype::F32 => mpi.rgba.clone(),
                MpiDtype::F16 => mpi.rgba.iter().map(|&v| half::f16::from_f32(v.min(65504.0)).to_f32()).collect(),
            };
            proptest::prop_assert!(back.rgba == want, "{:?}: {:?} != {:?}", dtype, back.rgba, want);
            proptest::prop_assert!(back.rgba.iter().all(|v| v.is_finite()));
        }
    }
}
