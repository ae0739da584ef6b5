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

/// Which of Telea's methods a call runs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum TeleaVariant {
    /// The paper's first-order method, with [`TeleaOptions::gradient`] and
    /// [`TeleaOptions::excluded`].
    #[default]
    Paper,
    /// What `cv2.inpaint(..., cv2.INPAINT_TELEA)` computes, its quirks and rounding included (see
    /// the documentation of `sample::inpaint`); its gradient correction is its own
    /// ([`TeleaOptions::gradient`] is not used) and it reads every known pixel.
    OpenCv,
}

/// Options of an inpainting call (`sample::inpaint::inpaint`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TeleaOptions<'a> {
    /// Neighbourhood radius in pixels (below 1 or NaN means 1; at most [`MAX_RADIUS`]; the OpenCV
    /// variant rounds it to an integer, as OpenCV does).
    pub radius: f32,
    /// The first-order term of the paper's method.
    pub gradient: GradientTerm,
    /// The paper's method or OpenCV's.
    pub variant: TeleaVariant,
    /// Pixels that are no context (H x W, true = not context; paper's method only): they are never
    /// read, the front does not start from them, and `grad T` leaves them out; hole pixels the
    /// front reaches only through them (enclosed by them and the image border) are filled
    /// afterwards from everything around them. Those outside the hole are not changed.
    pub excluded: Option<&'a [bool]>,
}

impl Default for TeleaOptions<'_> {
    /// Radius 5, [`GradientTerm::Propagated`], [`TeleaVariant::Paper`], no excluded pixel.
    fn default() -> Self {
        TeleaOptions { radius: 5.0, gradient: GradientTerm::Propagated, variant: TeleaVariant::Paper, excluded: None }
    }
}
