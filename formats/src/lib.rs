//! File formats (being written).
