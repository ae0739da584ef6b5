//! Synthetic MPIs for benchmarks and tests: dense colour with density concentrated near a
//! smooth depth surface, the way a trained MPI network's output looks.

use super::Mpi;
use crate::raster::Grid;

/// Disparity of the smooth benchmark surface at normalised coordinates (s, t) in [0, 1]^2:
/// a slanted ground with two bumps, within [0.08, 0.95].
pub fn surface_disparity(s: f64, t: f64) -> f64 {
    let slope = 0.15 + 0.6 * t;
    let bump1 = 0.25 * (-((s - 0.3).powi(2) + (t - 0.45).powi(2)) / 0.02).exp();
    let bump2 = 0.15 * (-((s - 0.72).powi(2) + (t - 0.6).powi(2)) / 0.01).exp();
    (slope + bump1 + bump2).clamp(0.08, 0.95)
}

/// A plausible MPI: `planes` planes at the reference disparities linspace(1, 0.001)[1:-1];
/// per pixel, sigma peaks (compactly, exactly 0 beyond about 1.5 plane gaps) at the planes
/// nearest the surface; colours vary smoothly with position and plane; the farthest plane is
/// opaque everywhere, as in a real MPI's background.
pub fn bench_mpi(width: usize, height: usize, planes: usize) -> Mpi {
    let disp = Mpi::reference_disparities(planes.max(1));
    let n = disp.len();
    let gap = if n > 1 { (disp[0] - disp[n - 1]) / (n - 1) as f64 } else { 1.0 };
    let mut mpi = Mpi::new(width, height, disp.clone(), 0);
    let grid = Grid::new(width, height);
    let plane_len = grid.len();
    for (i, &d) in disp.iter().enumerate() {
        let plane = &mut mpi.rgba[i * plane_len * 4..(i + 1) * plane_len * 4];
        for y in 0..height {
            let t = (y as f64 + 0.5) / height as f64;
            for x in 0..width {
                let s = (x as f64 + 0.5) / width as f64;
                let z = surface_disparity(s, t);
                let r = (d - z) / (1.5 * gap);
                let bump = (1.0 - r * r).max(0.0);
                let mut sigma = 40.0 * bump * bump;
                if i + 1 == n {
                    sigma = sigma.max(5.0);
                }
                let o = 4 * grid.index(x, y);
                plane[o] = (0.5 + 0.45 * (12.0 * s + 3.0 * i as f64 / n as f64).sin()) as f32;
                plane[o + 1] = (0.5 + 0.45 * (9.0 * t + 7.0 * s).cos()) as f32;
                plane[o + 2] = (0.5 + 0.4 * ((20.0 * s * t) + d * 4.0).sin()) as f32;
                plane[o + 3] = sigma as f32;
            }
        }
    }
    mpi
}

/// Gives a [`bench_mpi`] its surface ([`super::Surface`]): each pixel at
/// [`surface_disparity`], so its texels lie at the surface within their planes' slabs, as the
/// true-depth layering places them.
pub fn with_surface(mpi: &mut Mpi) {
    let grid = Grid::new(mpi.width, mpi.height);
    let (w, h) = (mpi.width as f64, mpi.height as f64);
    let disparity =
        grid.pixels().map(|(x, y)| surface_disparity((x as f64 + 0.5) / w, (y as f64 + 0.5) / h) as f32).collect();
    mpi.surface = Some(std::sync::Arc::new(super::Surface { disparity }));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bench_mpi_is_valid_and_sparse() {
        let m = bench_mpi(64, 48, 16);
        m.validate().unwrap();
        let zero = m.rgba.chunks_exact(4).filter(|p| p[3] == 0.0).count();
        assert!(zero > m.rgba.len() / 8, "most plane pixels should be exactly empty");
        assert!(m.plane_rgba(15).chunks_exact(4).all(|p| p[3] > 0.0));
    }
}
