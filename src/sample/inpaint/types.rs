//! The options and the report of an inpainting call, and its limits.

/// Largest radius used; larger requests are clamped (OpenCV clamps to 100 as well).
pub const MAX_RADIUS: f32 = 100.0;

/// Smallest directional weight `|cos|` in the paper variant, so that pixels along the front
/// still count a little and the weight sum is never zero.
pub const DIR_FLOOR: f32 = 1.0e-3;

/// What an inpainting call did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct InpaintStats {
    /// Pixels filled: the hole pixels plus known pixels with a non-finite value.
    pub filled: usize,
    /// Of [`filled`](Self::filled), pixels outside the hole mask that were filled because a
    /// channel was NaN or infinite (f32 only).
    pub nonfinite: usize,
    /// Every pixel was to be filled; all values were set to 0.
    pub all_hole: bool,
    /// Largest arrival time `T` inside the hole: roughly the distance in pixels from the
    /// boundary to the deepest hole pixel (0 when nothing was filled).
    pub max_distance: f32,
}

/// Where the image gradient in the first-order term `I(q) + grad I(q) . (p - q)` comes from.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum GradientTerm {
    /// Known pixels: finite differences of the known image (minmod-limited). Filled pixels: the
    /// weighted mean of the gradients their own value was extrapolated with. Exact on linear
    /// images at any depth; the paper's first-order method, kept stable (finite differences of
    /// filled values, the literal reading, amplify errors and diverge on large holes).
    #[default]
    Propagated,
    /// Known pixels as above; filled pixels contribute their value only (zero order). Not exact
    /// on linear images deeper than `radius` into the hole, but less overshoot on textured
    /// photographs with large holes (see the documentation of `sample::inpaint`).
    KnownOnly,
    /// No gradient term: a weighted mean of the available values (zero order).
    Off,
}

/// Options of `inpaint_telea_with`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TeleaOptions {
    /// Neighbourhood radius in pixels (below 1 or NaN means 1; at most [`MAX_RADIUS`]).
    pub radius: f32,
    /// The first-order term.
    pub gradient: GradientTerm,
}

impl Default for TeleaOptions {
    /// Radius 5, [`GradientTerm::Propagated`].
    fn default() -> Self {
        TeleaOptions { radius: 5.0, gradient: GradientTerm::Propagated }
    }
}
