//! grainpipe-charts: one plotting stack and one look for every grainpipe chart.
//!
//! Charts are plotters charts with the style of [`style`] (colours, the viridis colour map,
//! tick and axis text with units, log axes): inline SVG for the self-contained HTML reports
//! ([`Figure::svg`], [`slice::frame`]), PNG and SVG files for sweeps and stages
//! ([`Figure::save`]). Inline SVG text is laid out by the browser and needs no font; PNG text
//! uses a system TrueType font when there is one (DejaVu Sans, fonts-dejavu-core) and is left
//! out otherwise.

pub mod figure;
pub mod slice;
pub mod style;
pub mod violin;

pub use figure::{Figure, HLine, PlotArea, Secondary, Series};
pub use violin::{violin, violin_figure, violins, Group};
