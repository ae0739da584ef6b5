//! The vector instruction set the hot loops run with, chosen once per process (the widest the
//! CPU has, or the one `MPIFLOW_SIMD` names), and the dispatch that runs a loop compiled for it.
//!
//! [`dispatch`] hands a [`Wide`] job to `pulp`, which calls it inside a function compiled with
//! the set's target features (x86-64: AVX-512 F/BW/CD/DQ/VL, AVX2 + FMA, or the SSE2 baseline),
//! checked at run time: no `unsafe` here. Everything the job calls with `#[inline(always)]` is
//! compiled again for each set, so one source gives three machine-code loops.
//!
//! **The same bytes on every path.** The loops are written once, in IEEE operations that each
//! set performs exactly (add, multiply, divide, square root, compares, conversions), in one
//! order; nothing here or in the loops asks for fused multiply-add, and LLVM does not contract a
//! multiply and an add into one without fast-math flags, which Rust never sets. So a sample's
//! bytes do not depend on the path (`tests/process/simd_paths.rs` renders and makes samples on every
//! path this CPU has and compares them byte for byte).

use std::sync::atomic::{AtomicU8, Ordering};

/// The environment variable that forces a path: `sse2`, `avx2`, `avx512` or `auto` (the widest).
pub const SIMD_ENV: &str = "MPIFLOW_SIMD";

/// A vector instruction set the hot loops are compiled for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Isa {
    /// The build's baseline: SSE2 on x86-64 (4 f32 lanes), NEON on aarch64, scalar elsewhere.
    Sse2,
    /// AVX2 with FMA, BMI and F16C (x86-64-v3; 8 f32 lanes). FMA is present, not used.
    Avx2,
    /// AVX-512 F/BW/CD/DQ/VL (x86-64-v4; 16 f32 lanes).
    Avx512,
}

/// A path named in `MPIFLOW_SIMD` or given to [`force`] that is not known or not on this CPU.
#[derive(Debug, thiserror::Error)]
pub enum IsaError {
    #[error("{SIMD_ENV}={0:?}: expected sse2, avx2, avx512 or auto")]
    Unknown(String),
    #[error("{SIMD_ENV}: {0} is not available on this CPU (available: {1})")]
    Unavailable(&'static str, String),
}

impl Isa {
    /// Every set, narrowest first.
    pub const ALL: [Isa; 3] = [Isa::Sse2, Isa::Avx2, Isa::Avx512];

    /// The name operators see (logs, `GetInfo`) and `MPIFLOW_SIMD` takes.
    pub fn name(self) -> &'static str {
        match self {
            Isa::Sse2 => "sse2",
            Isa::Avx2 => "avx2",
            Isa::Avx512 => "avx512",
        }
    }

    /// The f32 lanes of the set's widest vector register.
    pub fn lanes(self) -> usize {
        match self {
            Isa::Sse2 => 4,
            Isa::Avx2 => 8,
            Isa::Avx512 => 16,
        }
    }

    /// Whether this CPU runs the set (the baseline always).
    pub fn available(self) -> bool {
        match self {
            Isa::Sse2 => true,
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => pulp::x86::V3::try_new().is_some(),
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => pulp::x86::V4::try_new().is_some(),
            #[cfg(not(target_arch = "x86_64"))]
            _ => false,
        }
    }

    /// The sets this CPU runs, narrowest first.
    pub fn available_all() -> Vec<Isa> {
        Isa::ALL.into_iter().filter(|i| i.available()).collect()
    }

    /// The widest set this CPU runs.
    pub fn widest() -> Isa {
        *Isa::available_all().last().expect("the baseline is always available")
    }

    /// `sse2`, `avx2`, `avx512`, or `auto` (the widest available); an unavailable set is an error.
    pub fn parse(name: &str) -> Result<Isa, IsaError> {
        let isa = match name.trim().to_ascii_lowercase().as_str() {
            "auto" | "" => return Ok(Isa::widest()),
            "sse2" => Isa::Sse2,
            "avx2" => Isa::Avx2,
            "avx512" => Isa::Avx512,
            _ => return Err(IsaError::Unknown(name.to_string())),
        };
        if !isa.available() {
            let have: Vec<&str> = Isa::available_all().into_iter().map(Isa::name).collect();
            return Err(IsaError::Unavailable(isa.name(), have.join(", ")));
        }
        Ok(isa)
    }

    fn code(self) -> u8 {
        self as u8 + 1
    }

    fn of_code(c: u8) -> Option<Isa> {
        Isa::ALL.get(usize::from(c).checked_sub(1)?).copied()
    }
}

impl std::fmt::Display for Isa {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// The chosen set ([`Isa::code`]; 0: not chosen yet).
static CHOSEN: AtomicU8 = AtomicU8::new(0);

/// Chooses the path from `MPIFLOW_SIMD` (unset: the widest available) unless one was chosen
/// already, and returns it. Entry points call it at start-up so that a wrong value is an error
/// there; [`current`] calls it on first use.
pub fn init() -> Result<Isa, IsaError> {
    if let Some(isa) = Isa::of_code(CHOSEN.load(Ordering::Relaxed)) {
        return Ok(isa);
    }
    let isa = match std::env::var(SIMD_ENV) {
        Ok(v) => Isa::parse(&v)?,
        Err(_) => Isa::widest(),
    };
    let _ = CHOSEN.compare_exchange(0, isa.code(), Ordering::Relaxed, Ordering::Relaxed);
    Ok(Isa::of_code(CHOSEN.load(Ordering::Relaxed)).unwrap_or(isa))
}

/// The path the hot loops take. A wrong `MPIFLOW_SIMD` that no entry point reported ([`init`])
/// gives the baseline, which makes the same bytes.
pub fn current() -> Isa {
    match Isa::of_code(CHOSEN.load(Ordering::Relaxed)) {
        Some(isa) => isa,
        None => init().unwrap_or_else(|_| {
            let _ = CHOSEN.compare_exchange(0, Isa::Sse2.code(), Ordering::Relaxed, Ordering::Relaxed);
            current()
        }),
    }
}

/// Makes every later dispatch in this process take `isa` (tests and benchmarks compare the
/// paths; the bytes are the same on each, so a concurrent render only changes its speed).
pub fn force(isa: Isa) -> Result<(), IsaError> {
    if !isa.available() {
        let have: Vec<&str> = Isa::available_all().into_iter().map(Isa::name).collect();
        return Err(IsaError::Unavailable(isa.name(), have.join(", ")));
    }
    CHOSEN.store(isa.code(), Ordering::Relaxed);
    Ok(())
}

/// A hot loop to run on the chosen path. `run` must be `#[inline(always)]`, and so must
/// everything hot that it calls: only inlined code is compiled for the path's features.
/// `LANES` is the path's f32 lanes per register ([`Isa::lanes`]: 4, 8 or 16), for loops that
/// take that many values at once.
pub trait Wide {
    type Output;
    fn run<const LANES: usize>(self) -> Self::Output;

    /// [`Self::run`] on the AVX-512 path with its token, for loops that use its instructions
    /// directly (`pulp`'s safe wrappers); by default `run::<16>`.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    fn run_v4(self, v4: pulp::x86::V4) -> Self::Output
    where
        Self: Sized,
    {
        let _ = v4;
        self.run::<16>()
    }
}

/// Runs `job` compiled for the chosen path ([`current`]).
#[inline(always)]
pub fn dispatch<W: Wide>(job: W) -> W::Output {
    struct Op<W, const LANES: usize>(W);
    #[cfg(target_arch = "x86_64")]
    struct OpV4<W>(W, pulp::x86::V4);
    #[cfg(target_arch = "x86_64")]
    impl<W: Wide> pulp::WithSimd for OpV4<W> {
        type Output = W::Output;
        #[inline(always)]
        fn with_simd<S: pulp::Simd>(self, _: S) -> W::Output {
            self.0.run_v4(self.1)
        }
    }
    impl<W: Wide, const LANES: usize> pulp::WithSimd for Op<W, LANES> {
        type Output = W::Output;
        #[inline(always)]
        fn with_simd<S: pulp::Simd>(self, _: S) -> W::Output {
            self.0.run::<LANES>()
        }
    }
    match current() {
        #[cfg(target_arch = "x86_64")]
        Isa::Avx512 => match pulp::x86::V4::try_new() {
            Some(v4) => pulp::Simd::vectorize(v4, OpV4(job, v4)),
            None => job.run::<4>(),
        },
        #[cfg(target_arch = "x86_64")]
        Isa::Avx2 => match pulp::x86::V3::try_new() {
            Some(v3) => pulp::Simd::vectorize(v3, Op::<W, 8>(job)),
            None => job.run::<4>(),
        },
        _ => pulp::Simd::vectorize(pulp::Scalar::new(), Op::<W, 4>(job)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_parse_back_and_the_baseline_is_always_there() {
        assert!(Isa::Sse2.available());
        for isa in Isa::available_all() {
            assert_eq!(Isa::parse(isa.name()).unwrap(), isa);
            assert_eq!(Isa::of_code(isa.code()), Some(isa));
        }
        assert_eq!(Isa::parse("auto").unwrap(), Isa::widest());
        assert!(matches!(Isa::parse("avx1024"), Err(IsaError::Unknown(_))));
        assert_eq!(Isa::of_code(0), None);
    }

    #[test]
    fn dispatch_runs_the_job() {
        struct Sum<'a>(&'a [f32]);
        impl Wide for Sum<'_> {
            type Output = f32;
            #[inline(always)]
            fn run<const LANES: usize>(self) -> f32 {
                assert_eq!(LANES, current().lanes());
                self.0.iter().sum()
            }
        }
        assert_eq!(dispatch(Sum(&[1.0, 2.0, 3.5])), 6.5);
    }
}
