//! The floating-point type of the fields (f64 by default, f32 on request). Reductions are
//! always accumulated in f64.

/// A field scalar: f32 or f64.
pub trait Real: rustfft::FftNum + num_traits::Float + Default + Send + Sync + 'static {
    fn of(x: f64) -> Self;
    fn f64(self) -> f64;
}

impl Real for f64 {
    #[inline(always)]
    fn of(x: f64) -> Self {
        x
    }
    #[inline(always)]
    fn f64(self) -> f64 {
        self
    }
}

impl Real for f32 {
    #[inline(always)]
    fn of(x: f64) -> Self {
        x as f32
    }
    #[inline(always)]
    fn f64(self) -> f64 {
        self as f64
    }
}
